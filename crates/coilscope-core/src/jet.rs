//! [`Jet`]: a forward-mode dual number with `N` derivative lanes that are always there, for
//! the Jacobians' runs (one pass of the model over a record gives `N` columns).
//!
//! Why not num-dual's `DualSVec64<N>`: its derivative part is an `Option` of a nalgebra
//! vector (`None` for a constant), so every operation branches on it, and the 96-byte value
//! with its tag stays in memory between operations instead of in registers. On a model-like
//! kernel (three cubic power series, products, a reciprocal; ten lanes) a `Jet` step took
//! 170-184 ns against num-dual's 395-477 ns (2.2-2.8x), and a jet on a nalgebra vector
//! without the `Option` 266 ns: the lanes are a plain array.
//!
//! Every operation computes what num-dual's computes, in the same order, so that a Jacobian
//! comes out the same to the last bit (a lane num-dual holds as `None` is a lane of zeros
//! here: `x * 0 + y = y` and `0 - y = -y` exactly). The one difference is where a derivative
//! factor is not finite (the square root or the reciprocal of zero): num-dual's constant
//! stays a constant, and so does a `Jet` whose lanes are zero (`Jet::chain`).
//!
//! It implements num-dual's [`DualNum`] (`Primitive = f64`), so the model, the integrators
//! and everything generic over the scalar type take it unchanged.

use num_dual::{DualNum, DualStruct, Mappable};
use num_traits::{FromPrimitive, Inv, Num, One, Signed, Zero};
use std::fmt;
use std::iter::{Product, Sum};
use std::ops::{Add, AddAssign, Div, DivAssign, Mul, MulAssign, Neg, Rem, RemAssign, Sub, SubAssign};

/// A dual number `re + sum_k eps_k e_k` with `N` lanes (`e_k e_j = 0`): `eps_k` is the
/// derivative of `re` with respect to the `k`-th seeded unknown.
#[derive(Clone, Copy, Debug)]
pub struct Jet<const N: usize> {
    /// The value.
    pub re: f64,
    /// The derivatives, one per seeded unknown.
    pub eps: [f64; N],
}

impl<const N: usize> Jet<N> {
    /// A value with the derivative parts `eps`.
    #[inline(always)]
    pub fn new(re: f64, eps: [f64; N]) -> Self {
        Jet { re, eps }
    }

    /// A constant (every lane zero).
    #[inline(always)]
    pub fn constant(re: f64) -> Self {
        Jet { re, eps: [0.0; N] }
    }

    /// `self` with lane `k` seeded: the unknown `k` itself.
    #[inline]
    pub fn derivative(mut self, k: usize) -> Self {
        self.eps = [0.0; N];
        self.eps[k] = 1.0;
        self
    }

    /// `f(self)` from `f0 = f(re)` and `f1 = f'(re)`: lanes times `f1`. A constant stays a
    /// constant where `f1` is not finite (num-dual's `None`).
    #[inline(always)]
    fn chain(&self, f0: f64, f1: f64) -> Self {
        if !f1.is_finite() && self.eps.iter().all(|&e| e == 0.0) {
            return Jet::constant(f0);
        }
        Jet { re: f0, eps: lanes(|k| self.eps[k] * f1) }
    }
}

/// The lanes `f(0) .. f(N - 1)`: a plain loop, which LLVM vectorises (`std::array::from_fn`
/// compiled to a scalar loop, one lane per iteration, inside the model's derivative).
#[inline(always)]
fn lanes<const N: usize>(f: impl Fn(usize) -> f64) -> [f64; N] {
    let mut e = [0.0; N];
    for (k, v) in e.iter_mut().enumerate() {
        *v = f(k);
    }
    e
}

impl<const N: usize> Add for Jet<N> {
    type Output = Self;
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        Jet { re: self.re + o.re, eps: lanes(|k| self.eps[k] + o.eps[k]) }
    }
}

impl<const N: usize> Sub for Jet<N> {
    type Output = Self;
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        Jet { re: self.re - o.re, eps: lanes(|k| self.eps[k] - o.eps[k]) }
    }
}

impl<const N: usize> Mul for Jet<N> {
    type Output = Self;
    /// num-dual's product rule: `eps * o.re + o.eps * re`.
    #[inline(always)]
    #[allow(clippy::suspicious_arithmetic_impl)]
    fn mul(self, o: Self) -> Self {
        Jet { re: self.re * o.re, eps: lanes(|k| self.eps[k] * o.re + o.eps[k] * self.re) }
    }
}

impl<const N: usize> Div for Jet<N> {
    type Output = Self;
    /// num-dual's quotient rule: `inv = 1 / o.re`, `(eps * o.re - o.eps * re) * inv * inv`.
    #[inline(always)]
    #[allow(clippy::suspicious_arithmetic_impl)]
    fn div(self, o: Self) -> Self {
        let inv = o.re.recip();
        Jet { re: self.re * inv, eps: lanes(|k| (self.eps[k] * o.re - o.eps[k] * self.re) * inv * inv) }
    }
}

impl<const N: usize> Rem for Jet<N> {
    type Output = Self;
    fn rem(self, _: Self) -> Self {
        unimplemented!("the remainder of dual numbers (num-dual has none either)")
    }
}

impl<const N: usize> Neg for Jet<N> {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        Jet { re: -self.re, eps: lanes(|k| -self.eps[k]) }
    }
}

impl<const N: usize> Neg for &Jet<N> {
    type Output = Jet<N>;
    #[inline(always)]
    fn neg(self) -> Jet<N> {
        -*self
    }
}

/// The binary operations on references and the assigning ones, from the ones on values.
macro_rules! forward {
    ($($trt:ident $mth:ident $atrt:ident $amth:ident),*) => {$(
        impl<'a, const N: usize> $trt<&'a Jet<N>> for Jet<N> {
            type Output = Jet<N>;
            #[inline(always)]
            fn $mth(self, o: &'a Jet<N>) -> Jet<N> {
                $trt::$mth(self, *o)
            }
        }
        impl<'a, const N: usize> $trt<&'a Jet<N>> for &Jet<N> {
            type Output = Jet<N>;
            #[inline(always)]
            fn $mth(self, o: &'a Jet<N>) -> Jet<N> {
                $trt::$mth(*self, *o)
            }
        }
        impl<const N: usize> $trt<Jet<N>> for &Jet<N> {
            type Output = Jet<N>;
            #[inline(always)]
            fn $mth(self, o: Jet<N>) -> Jet<N> {
                $trt::$mth(*self, o)
            }
        }
        impl<const N: usize> $atrt for Jet<N> {
            #[inline(always)]
            fn $amth(&mut self, o: Jet<N>) {
                *self = $trt::$mth(*self, o);
            }
        }
    )*};
}
forward!(Add add AddAssign add_assign, Sub sub SubAssign sub_assign, Mul mul MulAssign mul_assign, Div div DivAssign div_assign, Rem rem RemAssign rem_assign);

// Operations with a plain number, as num-dual's (`eps * s`, `eps / s`; `+ s`, `- s` on the
// value alone).
impl<const N: usize> Mul<f64> for Jet<N> {
    type Output = Self;
    #[inline(always)]
    fn mul(self, s: f64) -> Self {
        Jet { re: self.re * s, eps: lanes(|k| self.eps[k] * s) }
    }
}

impl<const N: usize> Div<f64> for Jet<N> {
    type Output = Self;
    #[inline(always)]
    fn div(self, s: f64) -> Self {
        Jet { re: self.re / s, eps: lanes(|k| self.eps[k] / s) }
    }
}

impl<const N: usize> Add<f64> for Jet<N> {
    type Output = Self;
    #[inline(always)]
    fn add(mut self, s: f64) -> Self {
        self.re += s;
        self
    }
}

impl<const N: usize> Sub<f64> for Jet<N> {
    type Output = Self;
    #[inline(always)]
    fn sub(mut self, s: f64) -> Self {
        self.re -= s;
        self
    }
}

impl<const N: usize> Rem<f64> for Jet<N> {
    type Output = Self;
    fn rem(self, _: f64) -> Self {
        unimplemented!("the remainder of dual numbers (num-dual has none either)")
    }
}

macro_rules! assign_scalar {
    ($($trt:ident $mth:ident $atrt:ident $amth:ident),*) => {$(
        impl<const N: usize> $atrt<f64> for Jet<N> {
            #[inline(always)]
            fn $amth(&mut self, s: f64) {
                *self = $trt::$mth(*self, s);
            }
        }
    )*};
}
assign_scalar!(Add add AddAssign add_assign, Sub sub SubAssign sub_assign, Mul mul MulAssign mul_assign, Div div DivAssign div_assign, Rem rem RemAssign rem_assign);

impl<const N: usize> Zero for Jet<N> {
    #[inline(always)]
    fn zero() -> Self {
        Jet::constant(0.0)
    }
    #[inline]
    fn is_zero(&self) -> bool {
        self.re == 0.0
    }
}

impl<const N: usize> One for Jet<N> {
    #[inline(always)]
    fn one() -> Self {
        Jet::constant(1.0)
    }
}

/// Comparisons look at the value only (as num-dual's): the code takes the branches a plain
/// number would.
impl<const N: usize> PartialEq for Jet<N> {
    #[inline]
    fn eq(&self, o: &Self) -> bool {
        self.re == o.re
    }
}

impl<const N: usize> PartialEq<f64> for Jet<N> {
    #[inline]
    fn eq(&self, o: &f64) -> bool {
        self.re == *o
    }
}

impl<const N: usize> PartialOrd for Jet<N> {
    #[inline]
    fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
        self.re.partial_cmp(&o.re)
    }
}

impl<const N: usize> PartialOrd<f64> for Jet<N> {
    #[inline]
    fn partial_cmp(&self, o: &f64) -> Option<std::cmp::Ordering> {
        self.re.partial_cmp(o)
    }
}

impl<const N: usize> Num for Jet<N> {
    type FromStrRadixErr = &'static str;
    fn from_str_radix(_: &str, _: u32) -> Result<Self, Self::FromStrRadixErr> {
        Err("a dual number is not parsed from text")
    }
}

impl<const N: usize> Signed for Jet<N> {
    #[inline]
    fn abs(&self) -> Self {
        if self.is_positive() {
            *self
        } else {
            -*self
        }
    }
    fn abs_sub(&self, o: &Self) -> Self {
        if self.re > o.re {
            *self - *o
        } else {
            Self::zero()
        }
    }
    fn signum(&self) -> Self {
        if self.is_positive() {
            Self::one()
        } else if self.is_zero() {
            Self::zero()
        } else {
            -Self::one()
        }
    }
    #[inline]
    fn is_positive(&self) -> bool {
        Signed::is_positive(&self.re)
    }
    #[inline]
    fn is_negative(&self) -> bool {
        Signed::is_negative(&self.re)
    }
}

impl<const N: usize> Inv for Jet<N> {
    type Output = Self;
    fn inv(self) -> Self {
        DualNum::recip(&self)
    }
}

impl<const N: usize> Sum for Jet<N> {
    fn sum<I: Iterator<Item = Self>>(iter: I) -> Self {
        iter.fold(Self::zero(), |a, c| a + c)
    }
}

impl<'a, const N: usize> Sum<&'a Jet<N>> for Jet<N> {
    fn sum<I: Iterator<Item = &'a Jet<N>>>(iter: I) -> Self {
        iter.fold(Self::zero(), |a, c| a + *c)
    }
}

impl<const N: usize> Product for Jet<N> {
    fn product<I: Iterator<Item = Self>>(iter: I) -> Self {
        iter.fold(Self::one(), |a, c| a * c)
    }
}

impl<'a, const N: usize> Product<&'a Jet<N>> for Jet<N> {
    fn product<I: Iterator<Item = &'a Jet<N>>>(iter: I) -> Self {
        iter.fold(Self::one(), |a, c| a * *c)
    }
}

impl<const N: usize> FromPrimitive for Jet<N> {
    fn from_i64(n: i64) -> Option<Self> {
        f64::from_i64(n).map(Jet::constant)
    }
    fn from_u64(n: u64) -> Option<Self> {
        f64::from_u64(n).map(Jet::constant)
    }
    fn from_f64(n: f64) -> Option<Self> {
        Some(Jet::constant(n))
    }
}

impl<const N: usize> From<f64> for Jet<N> {
    #[inline(always)]
    fn from(v: f64) -> Self {
        Jet::constant(v)
    }
}

impl<const N: usize> DualStruct for Jet<N> {
    type Real = f64;
    type Inner = f64;
    #[inline(always)]
    fn re(&self) -> f64 {
        self.re
    }
    fn from_inner(inner: &f64) -> Self {
        Jet::constant(*inner)
    }
}

impl<const N: usize> Mappable<Self> for Jet<N> {
    type Output<O> = O;
    fn map_dual<G: Fn(Self) -> O, O>(self, g: G) -> O {
        g(self)
    }
}

impl<const N: usize> fmt::Display for Jet<N> {
    fn fmt(&self, f: &mut fmt::Formatter) -> fmt::Result {
        write!(f, "{}", self.re)?;
        for (k, e) in self.eps.iter().enumerate() {
            write!(f, " + {e}ε{k}")?;
        }
        Ok(())
    }
}

/// num-dual's first derivatives, term for term (`impl_derivatives!` at first order).
impl<const N: usize> DualNum for Jet<N> {
    type Primitive = f64;
    const NDERIV: usize = 1;
    type InnerDual = f64;

    fn from_re(re: f64) -> Self {
        Jet::constant(re)
    }

    #[inline]
    fn scale(self, factor: &f64) -> Self {
        self * *factor
    }

    #[inline]
    fn recip(&self) -> Self {
        let rec = self.re.recip();
        self.chain(rec, -rec * rec)
    }

    #[inline]
    fn powi(&self, n: i32) -> Self {
        match n {
            0 => Self::one(),
            1 => *self,
            2 => *self * *self,
            _ => {
                let pow3 = self.re.powi(n - 3);
                let f0 = pow3 * self.re * self.re * self.re;
                self.chain(f0, pow3 * self.re * self.re * n as f64)
            }
        }
    }

    #[inline]
    fn powf(&self, n: f64) -> Self {
        if n == 0.0 {
            Self::one()
        } else if n == 1.0 {
            *self
        } else if (n - 1.0 - 1.0).abs() < f64::EPSILON {
            *self * *self
        } else {
            let pow3 = self.re.powf(n - 1.0 - 1.0 - 1.0);
            let f0 = pow3 * self.re * self.re * self.re;
            self.chain(f0, pow3 * self.re * self.re * n)
        }
    }

    #[inline]
    fn sqrt(&self) -> Self {
        let rec = self.re.recip();
        let f0 = self.re.sqrt();
        self.chain(f0, f0 * rec * 0.5)
    }

    fn cbrt(&self) -> Self {
        let rec = self.re.recip();
        let f0 = self.re.cbrt();
        self.chain(f0, f0 * rec * (1.0 / 3.0))
    }

    #[inline]
    fn exp(&self) -> Self {
        let f = self.re.exp();
        self.chain(f, f)
    }

    fn exp2(&self) -> Self {
        let f0 = self.re.exp2();
        self.chain(f0, f0 * 2f64.ln())
    }

    fn exp_m1(&self) -> Self {
        self.chain(self.re.exp_m1(), self.re.exp())
    }

    #[inline]
    fn ln(&self) -> Self {
        self.chain(self.re.ln(), self.re.recip())
    }

    fn log(&self, base: f64) -> Self {
        self.chain(self.re.log(base), self.re.recip() / base.ln())
    }

    fn log2(&self) -> Self {
        self.chain(self.re.log2(), self.re.recip() / (1f64 + 1.0).ln())
    }

    fn log10(&self) -> Self {
        self.chain(self.re.log10(), self.re.recip() / std::f64::consts::LN_10)
    }

    fn ln_1p(&self) -> Self {
        self.chain(self.re.ln_1p(), (self.re + 1.0).recip())
    }

    fn sin(&self) -> Self {
        let (s, c) = self.re.sin_cos();
        self.chain(s, c)
    }

    fn cos(&self) -> Self {
        let (s, c) = self.re.sin_cos();
        self.chain(c, -s)
    }

    fn sin_cos(&self) -> (Self, Self) {
        let (s, c) = self.re.sin_cos();
        (self.chain(s, c), self.chain(c, -s))
    }

    fn tan(&self) -> Self {
        let (s, c) = self.sin_cos();
        s / c
    }

    fn asin(&self) -> Self {
        let rec = (1.0 - self.re * self.re).recip();
        self.chain(self.re.asin(), rec.sqrt())
    }

    fn acos(&self) -> Self {
        let rec = (1.0 - self.re * self.re).recip();
        self.chain(self.re.acos(), -rec.sqrt())
    }

    fn atan(&self) -> Self {
        let rec = (1.0 + self.re * self.re).recip();
        self.chain(self.re.atan(), rec)
    }

    fn atan2(&self, other: Self) -> Self {
        let mut r = (*self / other).atan();
        r.re = self.re.atan2(other.re);
        r
    }

    fn sinh(&self) -> Self {
        self.chain(self.re.sinh(), self.re.cosh())
    }

    fn cosh(&self) -> Self {
        self.chain(self.re.cosh(), self.re.sinh())
    }

    fn tanh(&self) -> Self {
        self.sinh() / self.cosh()
    }

    fn asinh(&self) -> Self {
        let rec = (1.0 + self.re * self.re).recip();
        self.chain(self.re.asinh(), rec.sqrt())
    }

    fn acosh(&self) -> Self {
        let rec = (self.re * self.re - 1.0).recip();
        self.chain(self.re.acosh(), rec.sqrt())
    }

    fn atanh(&self) -> Self {
        let rec = (1.0 - self.re * self.re).recip();
        self.chain(self.re.atanh(), rec)
    }

    fn sph_j0(&self) -> Self {
        if self.re.abs() < f64::EPSILON {
            Self::one() - *self * *self / 6.0
        } else {
            self.sin() / *self
        }
    }

    fn sph_j1(&self) -> Self {
        if self.re.abs() < f64::EPSILON {
            *self / 3.0
        } else {
            let (s, c) = self.sin_cos();
            (s - *self * c) / (*self * *self)
        }
    }

    fn sph_j2(&self) -> Self {
        if self.re.abs() < f64::EPSILON {
            *self * *self / 15.0
        } else {
            let (s, c) = self.sin_cos();
            let s2 = *self * *self;
            ((s - *self * c) * 3.0 - s2 * s) / (s2 * *self)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use num_dual::DualSVec64;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// The same expression in a [`Jet`] and in num-dual's `DualSVec64`, some inputs
    /// constants (num-dual's `None`): the same value and derivatives, to the last bit.
    fn expression<D: DualNum<Primitive = f64> + Copy>(a: D, b: D, c: D, k: f64) -> D {
        let p = (a * a * k + b) * c - b / a + (c * 2.0 - 1.5);
        let q = p.recip() + a.exp() * b.sqrt() - (c * c).powi(3) / 7.0 + (a + 0.3).ln() * b.tanh();
        let mut r = q * q - p;
        r += a.powf(2.5) * c;
        r -= b.sin() * a.cos() + (a * 0.1).atan();
        r *= c + 1.0;
        r /= b + 2.0;
        -r.abs() + (a / c).powi(2) + b.cbrt()
    }

    #[test]
    fn a_jet_computes_num_duals_derivatives_to_the_last_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(0x6a6574);
        for _ in 0..200 {
            let (a, b, c, k): (f64, f64, f64, f64) = (
                rng.random_range(0.2..2.0),
                rng.random_range(0.1..3.0),
                rng.random_range(-2.0..2.0),
                rng.random_range(-3.0..3.0),
            );
            // a and c seeded (lanes 0 and 2), b a constant.
            let jd = expression(
                Jet::<3>::constant(a).derivative(0),
                Jet::constant(b),
                Jet::<3>::constant(c).derivative(2),
                k,
            );
            let nd = expression(
                DualSVec64::<3>::from_re(a).derivative(0),
                DualSVec64::from_re(b),
                DualSVec64::<3>::from_re(c).derivative(2),
                k,
            );
            assert_eq!(jd.re.to_bits(), nd.re.to_bits(), "value at {a} {b} {c} {k}");
            let e = nd.eps.0.expect("seeded");
            for lane in 0..3 {
                // Equal as numbers: a lane num-dual never touched is a zero of either sign here.
                assert_eq!(jd.eps[lane], e[lane], "lane {lane} at {a} {b} {c} {k}");
            }
        }
    }

    #[test]
    fn a_jet_matches_finite_differences() {
        let f = |a: f64, c: f64| expression(a, 1.3, c, 0.7);
        let (a, c) = (0.9, 0.4);
        let j = expression(
            Jet::<2>::constant(a).derivative(0),
            Jet::constant(1.3),
            Jet::<2>::constant(c).derivative(1),
            0.7,
        );
        let h = 1e-6;
        let da = (f(a + h, c) - f(a - h, c)) / (2.0 * h);
        let dc = (f(a, c + h) - f(a, c - h)) / (2.0 * h);
        assert!((j.eps[0] - da).abs() < 1e-7 * da.abs().max(1.0), "{} vs {da}", j.eps[0]);
        assert!((j.eps[1] - dc).abs() < 1e-7 * dc.abs().max(1.0), "{} vs {dc}", j.eps[1]);
    }

    #[test]
    fn a_constant_stays_a_constant_where_the_derivative_is_infinite() {
        let z = Jet::<2>::constant(0.0);
        let s = z.sqrt();
        assert_eq!((s.re, s.eps), (0.0, [0.0, 0.0]));
        let r = Jet::<2>::constant(0.0).recip();
        assert!(r.re.is_infinite() && r.eps == [0.0, 0.0]);
    }
}

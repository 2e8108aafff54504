//! The Volterra approximation (seed section 3.2.2.1): the model's response to a sine expanded
//! in powers of the amplitude and truncated after the third order.
//!
//! Harmonic probing: with the input `u = a e^{jwt} + a e^{-jwt}` every state is a series
//! `y = sum_{n=1..3} a^n sum_{|k|<=n} c[n][k] e^{jkwt}`. Inserting the power series of Bl, Kms,
//! Le, L2, R2 into the model's equations (the same equations as `coilscope_core::model`,
//! thermal off) and collecting equal powers of `a` gives, order by order, the *linear* model at
//! rest driven by products of lower orders:
//!
//! ```text
//! J(jkw) c[n][k] = -R[n][k](c[1], ..., c[n-1])
//! ```
//!
//! `J` is the Jacobian of the equations at rest, with the linear elements that have states of
//! their own (creep's dynamic stiffness, the LR-3 branch) at each line's frequency. Le(i) and
//! Rms(|v|) are not in the expansion (|v| has no power series): `distortion` integrates them.
//! With `a = 1` the coefficients are the diagonal kernels: `H1(f) = c[1][1]`, `H2(f,f) = c[2][2]`,
//! `H3(f,f,f) = c[3][3]` (displacement,
//! m/V^n for the complex amplitude `a` of `e^{jwt}`).
//!
//! A sine of peak `A` has `a = A / 2`, so the Volterra harmonic ratios are
//! `HD2 = |H2| a / |H1|` and `HD3 = |H3| a^2 / |H1|` (in displacement; in pressure each
//! harmonic k is multiplied by `(jkw)^2`). They grow as `A` and `A^2` for ever; the full model
//! does not, since its distortion feeds back into its own generation.

use coilscope_core::{Parameters, Poly};
use realfft::num_complex::Complex64 as C;
use serde_json::{json, Value};
use std::f64::consts::PI;

use crate::distortion::Output;

const KMAX: usize = 3;
const NK: usize = 2 * KMAX + 1;
const NO: usize = 4;

/// A truncated series in the amplitude `a` (orders 0..=3) of Fourier lines `k = -3..=3`.
#[derive(Clone, Copy, Debug)]
struct Pert {
    c: [[C; NK]; NO],
    w: f64,
}

impl Pert {
    fn zero(w: f64) -> Self {
        Pert { c: [[C::new(0.0, 0.0); NK]; NO], w }
    }
    fn constant(v: f64, w: f64) -> Self {
        let mut p = Pert::zero(w);
        p.c[0][KMAX] = C::new(v, 0.0);
        p
    }
    fn add(&self, o: &Pert) -> Pert {
        let mut r = *self;
        for n in 0..NO {
            for k in 0..NK {
                r.c[n][k] += o.c[n][k];
            }
        }
        r
    }
    fn sub(&self, o: &Pert) -> Pert {
        self.add(&o.scale(-1.0))
    }
    fn scale(&self, s: f64) -> Pert {
        let mut r = *self;
        r.c.iter_mut().flatten().for_each(|c| *c *= s);
        r
    }
    fn mul(&self, o: &Pert) -> Pert {
        let mut r = Pert::zero(self.w);
        for n1 in 0..NO {
            for n2 in 0..NO - n1 {
                for k1 in 0..NK {
                    let a = self.c[n1][k1];
                    if a == C::new(0.0, 0.0) {
                        continue;
                    }
                    for k2 in 0..NK {
                        let k = k1 as isize + k2 as isize - KMAX as isize;
                        if (0..NK as isize).contains(&k) {
                            r.c[n1 + n2][k as usize] += a * o.c[n2][k2];
                        }
                    }
                }
            }
        }
        r
    }
    /// Time derivative: line k times `j k w`.
    fn dt(&self) -> Pert {
        let mut r = *self;
        for n in 0..NO {
            for k in 0..NK {
                r.c[n][k] *= C::new(0.0, (k as f64 - KMAX as f64) * self.w);
            }
        }
        r
    }
    fn at(&self, n: usize, k: isize) -> C {
        self.c[n][(k + KMAX as isize) as usize]
    }
}

fn poly(f: &Poly, x: &Pert) -> Pert {
    let mut acc = Pert::constant(f.c[f.c.len() - 1], x.w);
    for &cj in f.c[..f.c.len() - 1].iter().rev() {
        acc = acc.mul(x).add(&Pert::constant(cj, x.w));
    }
    acc
}

/// Solve a complex 3x3 system by Gaussian elimination with partial pivoting.
fn solve3(mut a: [[C; 3]; 3], mut b: [C; 3]) -> [C; 3] {
    for col in 0..3 {
        let piv = (col..3).max_by(|&i, &j| a[i][col].norm().total_cmp(&a[j][col].norm())).unwrap_or(col);
        a.swap(col, piv);
        b.swap(col, piv);
        for row in col + 1..3 {
            let f = a[row][col] / a[col][col];
            for c in col..3 {
                let v = a[col][c];
                a[row][c] -= f * v;
            }
            let v = b[col];
            b[row] -= f * v;
        }
    }
    let mut x = [C::new(0.0, 0.0); 3];
    for row in (0..3).rev() {
        let mut s = b[row];
        for c in row + 1..3 {
            s -= a[row][c] * x[c];
        }
        x[row] = s / a[row][row];
    }
    x
}

/// The probed series of x and i for a sine of complex amplitude `a = 1` at `freq`.
#[derive(Clone, Debug)]
pub struct Probe {
    pub freq: f64,
    x: Pert,
    i: Pert,
}

/// Harmonic probing of the model of `p` (thermal off, Re at rest temperature) at `freq`.
pub fn probe(p: &Parameters, freq: f64) -> Probe {
    let w = 2.0 * PI * freq;
    let (l2, r2) = match &p.l2r2 {
        Some((l2, r2)) => (Some(l2.clone()), r2.clone()),
        None => (None, Poly::constant(0.0)),
    };
    let (dle, dl2) = (p.le.derivative(), l2.as_ref().map(|f| f.derivative()));
    let mut u = Pert::zero(w);
    u.c[1][KMAX + 1] = C::new(1.0, 0.0);
    u.c[1][KMAX - 1] = C::new(1.0, 0.0);
    let (mut x, mut i, mut i2) = (Pert::zero(w), Pert::zero(w), Pert::zero(w));
    let residuals = |x: &Pert, i: &Pert, i2: &Pert| {
        let v = x.dt();
        let ir = i.sub(i2);
        let r2x = poly(&r2, x);
        let e1 = u.sub(&i.scale(p.re)).sub(&poly(&p.le, x).mul(i).dt()).sub(&poly(&p.bl, x).mul(&v)).sub(&r2x.mul(&ir));
        let mut e3 = poly(&p.bl, x)
            .mul(i)
            .sub(&v.dt().scale(p.mms))
            .sub(&v.scale(p.rms))
            .sub(&poly(&p.kms, x).mul(x))
            .add(&poly(&dle, x).mul(&i.mul(i)).scale(0.5));
        let e2 = match (&l2, &dl2) {
            (Some(l2), Some(dl2)) => {
                e3 = e3.add(&poly(dl2, x).mul(&i2.mul(i2)).scale(0.5));
                poly(l2, x).mul(i2).dt().sub(&r2x.mul(&ir))
            }
            _ => i2.scale(-1.0),
        };
        (e1, e2, e3)
    };
    let (b0, l0, m, rm, re) = (p.bl.c[0], p.le.c[0], p.mms, p.rms, p.re);
    let r0 = r2.c[0];
    for n in 1..NO {
        let (e1, e2, e3) = residuals(&x, &i, &i2);
        for k in -(n as isize)..=n as isize {
            let s = C::new(0.0, k as f64 * w);
            // Unknowns [dx, di, di2]; rows: electrical, LR-2 branch, mechanical.
            let row_l2 = match &l2 {
                Some(l2) => [C::new(0.0, 0.0), C::new(-r0, 0.0), s * l2.c[0] + r0],
                None => [C::new(0.0, 0.0), C::new(0.0, 0.0), C::new(-1.0, 0.0)],
            };
            // Creep and LR-3 are linear with constant coefficients: they enter the Jacobian
            // only, as creep's dynamic stiffness and LR-3's series impedance at this line
            // (the residuals of order n hold products of lower orders, which they do not make).
            let k_dyn = coilscope_core::small_signal::dynamic_stiffness(p, k as f64 * w);
            let z3 = p.l3r3.map_or(C::new(0.0, 0.0), |(l3, r3)| s * l3 * r3 / (s * l3 + r3));
            let j = [
                [-s * b0, -(s * l0) - re - r0 - z3, C::new(r0, 0.0)],
                row_l2,
                [-(s * s * m) - s * rm - k_dyn, C::new(b0, 0.0), C::new(0.0, 0.0)],
            ];
            let d = solve3(j, [-e1.at(n, k), -e2.at(n, k), -e3.at(n, k)]);
            let ki = (k + KMAX as isize) as usize;
            x.c[n][ki] = d[0];
            i.c[n][ki] = d[1];
            i2.c[n][ki] = d[2];
        }
    }
    Probe { freq, x, i }
}

impl Probe {
    /// The diagonal kernels of the displacement: `[H1(f), H2(f,f), H3(f,f,f)]` (m/V^n).
    pub fn kernels(&self) -> [C; 3] {
        [self.x.at(1, 1), self.x.at(2, 2), self.x.at(3, 3)]
    }
    /// Series coefficient of `out` at order `n`, harmonic `k`.
    fn line(&self, out: Output, n: usize, k: isize) -> C {
        match out {
            Output::Displacement => self.x.at(n, k),
            Output::Current => self.i.at(n, k),
            Output::Pressure => self.x.at(n, k) * C::new(0.0, k as f64 * 2.0 * PI * self.freq).powi(2),
        }
    }
    /// The Volterra prediction of the complex ratios `(line 2 / line 1, line 3 / line 1)` of
    /// `out` for a cosine of `volts` RMS (what [`crate::distortion::harmonics`] measures on
    /// the full model, whose tone is a cosine): `H2 a / H1` and `H3 a^2 / H1`, `a` = peak / 2.
    pub fn ratios(&self, out: Output, volts: f64) -> (C, C) {
        let a = volts * std::f64::consts::SQRT_2 / 2.0;
        let h1 = self.line(out, 1, 1);
        (self.line(out, 2, 2) * a / h1, self.line(out, 3, 3) * a * a / h1)
    }
    /// Volterra prediction of `(HD2, HD3)` of `out` for a sine of `volts` RMS.
    pub fn hd(&self, out: Output, volts: f64) -> (f64, f64) {
        let a = volts * std::f64::consts::SQRT_2 / 2.0;
        let h1 = self.line(out, 1, 1).norm();
        (self.line(out, 2, 2).norm() * a / h1, self.line(out, 3, 3).norm() * a * a / h1)
    }
    /// Volterra prediction of the DC displacement (m) for a sine of `volts` RMS.
    pub fn x_dc(&self, volts: f64) -> f64 {
        let a = volts * std::f64::consts::SQRT_2 / 2.0;
        self.x.at(2, 0).re * a * a
    }
    pub fn to_json(&self) -> Value {
        let [h1, h2, h3] = self.kernels();
        json!({
            "freq": self.freq,
            "H1": {"abs": h1.norm(), "phase": h1.arg(), "unit": "m/V"},
            "H2": {"abs": h2.norm(), "phase": h2.arg(), "unit": "m/V^2"},
            "H3": {"abs": h3.norm(), "phase": h3.arg(), "unit": "m/V^3"},
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use coilscope_core::embedded_driver;
    use coilscope_core::small_signal::{displacement_per_current, impedance};

    #[test]
    fn first_kernel_is_the_linear_transfer_function() {
        for name in coilscope_core::embedded_driver_names() {
            let p = embedded_driver(name).unwrap();
            for f in [20.0, 80.0, 700.0] {
                let h1 = probe(&p, f).kernels()[0];
                let lin = displacement_per_current(&p, f) / impedance(&p, f);
                assert!((h1 - lin).norm() < 1e-9 * lin.norm(), "{name} {f} Hz: {h1} vs {lin}");
            }
        }
    }

    #[test]
    fn first_kernel_keeps_creep_and_lr3() {
        let mut p = embedded_driver("sb17cac35-4").unwrap();
        p.creep = Some(coilscope_core::params::Creep { lambda: 0.1, f_ref: None });
        let (l2, r2) = p.l2r2.as_ref().map(|(l, r)| (l.c[0], r.c[0])).unwrap();
        p.l3r3 = Some((0.5 * l2, 3.0 * r2));
        for f in [5.0, 40.0, 700.0, 5000.0] {
            let h1 = probe(&p, f).kernels()[0];
            let lin = displacement_per_current(&p, f) / impedance(&p, f);
            assert!((h1 - lin).norm() < 1e-9 * lin.norm(), "{f} Hz: {h1} vs {lin}");
        }
    }

    #[test]
    fn a_linear_set_has_no_higher_kernels() {
        let p = crate::distortion::with_only(&embedded_driver("sb17cac35-4").unwrap(), &[], 0.0);
        let [h1, h2, h3] = probe(&p, 50.0).kernels();
        assert!(h2.norm() < 1e-15 * h1.norm() && h3.norm() < 1e-15 * h1.norm());
    }

    #[test]
    fn quadratic_stiffness_alone_gives_the_closed_form_dc_offset() {
        // With only Kms(x) = k0 + k1 x nonlinear, the order-2 DC balance is
        // k0 x_dc + k1 <x1^2> = 0, with <x1^2> = 2 |H1|^2 a^2 for the two lines of x1.
        let mut p = crate::distortion::with_only(&embedded_driver("sb17cac35-4").unwrap(), &[], 0.0);
        p.kms = Poly { c: vec![p.kms.c[0], 2.0e5] };
        let pr = probe(&p, 40.0);
        let h1 = pr.kernels()[0].norm();
        let expect = -2.0e5 * 2.0 * h1 * h1 / p.kms.c[0];
        assert!((pr.x.at(2, 0).re - expect).abs() < 1e-9 * expect.abs(), "{} vs {expect}", pr.x.at(2, 0));
    }
}

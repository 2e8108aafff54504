//! Ascending power series in the displacement x (metres): `f(x) = sum_j c_j x^j`.
//!
//! This is how the file contract stores every x-dependent parameter (Bl, Kms, Le, L2, R2).
//! The coefficients are generic over the scalar type so that dual numbers propagate
//! derivatives with respect to the coefficients (identification) and to x.

use num_dual::DualNum;

/// A power series `f(x) = c[0] + c[1] x + c[2] x^2 + ...` with x in metres (SI).
#[derive(Clone, Debug, PartialEq)]
pub struct Poly<D = f64> {
    /// Ascending coefficients; never empty (a constant has one coefficient).
    pub c: Vec<D>,
}

impl<D: DualNum<Primitive = f64> + Copy> Poly<D> {
    /// A constant function.
    pub fn constant(v: D) -> Self {
        Poly { c: vec![v] }
    }

    /// Value at x (Horner).
    #[inline]
    pub fn eval(&self, x: D) -> D {
        let mut acc = self.c[self.c.len() - 1];
        for &cj in self.c[..self.c.len() - 1].iter().rev() {
            acc = acc * x + cj;
        }
        acc
    }

    /// Value and first derivative d f / d x at x.
    #[inline]
    pub fn eval_d(&self, x: D) -> (D, D) {
        let n = self.c.len();
        let mut f = self.c[n - 1];
        let mut df = D::zero();
        for &cj in self.c[..n - 1].iter().rev() {
            df = df * x + f;
            f = f * x + cj;
        }
        (f, df)
    }

    /// Value, first and second derivative at x.
    pub fn eval_d2(&self, x: D) -> (D, D, D) {
        let n = self.c.len();
        let mut f = self.c[n - 1];
        let mut df = D::zero();
        let mut ddf = D::zero();
        for &cj in self.c[..n - 1].iter().rev() {
            ddf = ddf * x + df;
            df = df * x + f;
            f = f * x + cj;
        }
        (f, df, ddf * 2.0)
    }

    /// `int_0^x f(s) s ds`: the potential energy stored in a suspension whose restoring force
    /// is `f(s) s` (f = Kms, the secant stiffness of the file contract).
    pub fn moment_integral(&self, x: D) -> D {
        // sum_j c_j x^(j+2) / (j+2)
        let mut acc = D::zero();
        for (j, &cj) in self.c.iter().enumerate().rev() {
            acc = acc * x + cj * (1.0 / (j as f64 + 2.0));
        }
        acc * x * x
    }

    /// True when the series has no x-dependent term.
    pub fn is_constant(&self) -> bool {
        self.c.iter().skip(1).all(|c| c.re() == 0.0)
    }
}

impl Poly<f64> {
    /// The series times `k`.
    pub fn scaled(&self, k: f64) -> Poly {
        Poly { c: self.c.iter().map(|c| c * k).collect() }
    }

    /// The series of `g(x) = f(x + d)`: the same function seen from an origin moved by `d`
    /// (`g_k = sum_{j >= k} c_j C(j, k) d^(j-k)`).
    pub fn shifted(&self, d: f64) -> Poly {
        let n = self.c.len();
        let mut g = vec![0.0; n];
        for (j, &c) in self.c.iter().enumerate() {
            // C(j, k) d^(j-k) for k = j, j-1, ..., 0.
            let mut binom_pow = 1.0;
            for k in (0..=j).rev() {
                g[k] += c * binom_pow;
                binom_pow *= d * k as f64 / (j - k + 1) as f64;
            }
        }
        Poly { c: g }
    }

    /// The coefficients as a plain series (for files).
    pub fn coefficients(&self) -> &[f64] {
        &self.c
    }

    /// The derivative d f / d x as a series (a constant's is 0).
    pub fn derivative(&self) -> Poly {
        if self.c.len() < 2 {
            return Poly::constant(0.0);
        }
        Poly { c: self.c.iter().enumerate().skip(1).map(|(j, c)| j as f64 * c).collect() }
    }

    /// Lift to another scalar type (e.g. dual numbers with zero derivative parts).
    pub fn lift<D: DualNum<Primitive = f64> + Copy>(&self) -> Poly<D> {
        Poly { c: self.c.iter().map(|&c| D::from(c)).collect() }
    }

    /// Minimum and maximum of f on `[lo, hi]`, sampled on a dense grid (plus end points).
    pub fn min_max_on(&self, lo: f64, hi: f64) -> (f64, f64) {
        let n = 2000;
        let mut mn = f64::INFINITY;
        let mut mx = f64::NEG_INFINITY;
        for k in 0..=n {
            let x = lo + (hi - lo) * k as f64 / n as f64;
            let v = self.eval(x);
            mn = mn.min(v);
            mx = mx.max(v);
        }
        (mn, mx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use num_dual::Dual64;

    #[test]
    fn a_shifted_series_is_the_function_seen_from_a_moved_origin() {
        let f = Poly { c: vec![5.06, -44.4, -17036.0, 149409.0, -3.87e8] };
        for d in [-5e-4, 0.0, 3e-4] {
            let g = f.shifted(d);
            for x in [-6e-3, -1e-3, 0.0, 2e-3, 5e-3] {
                let (a, b) = (g.eval(x), f.eval(x + d));
                assert!((a - b).abs() <= 1e-12 * b.abs().max(1.0), "d {d} x {x}: {a} against {b}");
            }
        }
    }

    #[test]
    fn horner_matches_direct_sum() {
        let p = Poly { c: vec![5.0, -44.0, -17036.0, 149409.0, -3.87e8] };
        for &x in &[-0.006, -0.001, 0.0, 0.002, 0.0055] {
            let direct: f64 = p.c.iter().enumerate().map(|(j, c)| c * x.powi(j as i32)).sum();
            assert!((p.eval(x) - direct).abs() < 1e-12 * direct.abs().max(1.0));
        }
    }

    #[test]
    fn derivatives_match_dual_numbers_and_finite_differences() {
        let p = Poly { c: vec![1.1e-4, -5.5e-3, 0.25, 34.0, 1.0e4] };
        for &x in &[-0.005, 0.0, 0.003] {
            let (f, df, ddf) = p.eval_d2(x);
            let pd: Poly<Dual64> = p.lift();
            let d = pd.eval(Dual64::from(x).derivative());
            assert!((d.re - f).abs() < 1e-18);
            assert!((d.eps - df).abs() < 1e-12 * df.abs().max(1e-12));
            let h = 1e-6;
            let fd2 = (p.eval(x + h) - 2.0 * p.eval(x) + p.eval(x - h)) / (h * h);
            assert!((fd2 - ddf).abs() < 1e-4 * ddf.abs().max(1.0), "{fd2} vs {ddf}");
            let (f1, df1) = p.eval_d(x);
            assert_eq!((f1, df1), (f, df));
            // The derivative series gives the same slope.
            assert!((p.derivative().eval(x) - df).abs() < 1e-12 * df.abs().max(1e-12));
        }
    }

    #[test]
    fn moment_integral_is_the_antiderivative_of_f_times_x() {
        let p = Poly { c: vec![636.0, -15728.0, 2.0e7, -9.2e7, 7.5e10] };
        let x = 0.004;
        // Simpson with many panels: slow, obviously correct.
        let n = 2000;
        let h = x / n as f64;
        let g = |s: f64| p.eval(s) * s;
        let mut s = g(0.0) + g(x);
        for k in 1..n {
            s += g(k as f64 * h) * if k % 2 == 1 { 4.0 } else { 2.0 };
        }
        let simpson = s * h / 3.0;
        assert!((p.moment_integral(x) - simpson).abs() < 1e-10 * simpson.abs());
    }
}

//! Comparisons a NaN cannot pass, and the two-sided check of reported uncertainty.
//!
//! `fold(0.0, f64::max)` drops a NaN (`f64::max` returns the other operand), so a fit without
//! a covariance (NaN bands) passed every coverage test as "0.00 sd". Every worst case here
//! is NaN when any of its values is, and every bound check fails on NaN.

/// The larger of two values, or NaN when either is NaN: `fold(0.0, nan_max)` is the worst
/// case that a NaN cannot hide in (`fold(0.0, f64::max)` drops it).
pub fn nan_max(a: f64, b: f64) -> f64 {
    if a.is_nan() || b.is_nan() {
        f64::NAN
    } else {
        a.max(b)
    }
}

/// The largest of the values, or NaN when any is NaN (0 for none).
pub fn max_nan(values: impl IntoIterator<Item = f64>) -> f64 {
    let mut m: f64 = 0.0;
    for v in values {
        if v.is_nan() {
            return f64::NAN;
        }
        m = m.max(v);
    }
    m
}

/// The largest |value|, or NaN when any is NaN.
pub fn max_abs(values: impl IntoIterator<Item = f64>) -> f64 {
    max_nan(values.into_iter().map(f64::abs))
}

/// Whether `v` is a number within `bound` (false for NaN).
pub fn within(v: f64, bound: f64) -> bool {
    v.is_finite() && v.abs() <= bound
}

/// Standardised errors (estimate - truth) / sd, pooled over the cases of a sweep, to judge a
/// reported uncertainty from both sides: the truth inside the bands often enough, and the
/// bands not inflated.
#[derive(Clone, Debug, Default)]
pub struct Coverage {
    z: Vec<f64>,
}

impl Coverage {
    pub fn new() -> Self {
        Self::default()
    }

    /// One standardised error; NaN (an sd that was not given, an estimate that is not a number)
    /// is kept and fails [`Coverage::problems`].
    pub fn push(&mut self, z: f64) {
        self.z.push(z);
    }

    pub fn extend(&mut self, z: impl IntoIterator<Item = f64>) {
        self.z.extend(z);
    }

    pub fn len(&self) -> usize {
        self.z.len()
    }

    pub fn is_empty(&self) -> bool {
        self.z.is_empty()
    }

    /// The share of |z| within `k`.
    pub fn share_within(&self, k: f64) -> f64 {
        self.z.iter().filter(|z| z.abs() <= k).count() as f64 / self.z.len().max(1) as f64
    }

    /// The median |z|.
    pub fn median_abs(&self) -> f64 {
        let mut a: Vec<f64> = self.z.iter().map(|z| z.abs()).collect();
        a.sort_by(f64::total_cmp);
        if a.is_empty() {
            f64::NAN
        } else {
            a[a.len() / 2]
        }
    }

    /// One line for the log.
    pub fn summary(&self, what: &str) -> String {
        format!("{what}: {} standardised errors, {:.1} % within 2 sd (a Gaussian band: 95 %), median |error|/sd {:.2} (Gaussian: 0.67), largest {:.1}", self.z.len(), 100.0 * self.share_within(2.0), self.median_abs(), max_abs(self.z.iter().copied()))
    }

    /// What is wrong with the bands: a NaN, the truth within 2 sd in fewer than `min_within_2sd`
    /// of the cases, or a median |error|/sd below `min_median` (inflated bands).
    pub fn problems(&self, what: &str, min_within_2sd: f64, min_median: f64) -> Vec<String> {
        let mut bad = Vec::new();
        if self.z.is_empty() {
            bad.push(format!("{what}: no standardised error to judge the bands by"));
            return bad;
        }
        let nans = self.z.iter().filter(|z| z.is_nan()).count();
        if nans > 0 {
            bad.push(format!(
                "{what}: {nans} of {} standardised errors are NaN (an sd or an estimate missing)",
                self.z.len()
            ));
        }
        let share = self.share_within(2.0);
        if share < min_within_2sd {
            bad.push(format!(
                "{what}: the truth lies within 2 sd in only {:.1} % of {} (at least {:.0} % asked)",
                100.0 * share,
                self.z.len(),
                100.0 * min_within_2sd
            ));
        }
        let med = self.median_abs();
        if !(med >= min_median) {
            bad.push(format!("{what}: the median |error|/sd is {med:.3}, below {min_median}: the bands are inflated"));
        }
        bad
    }
}

/// The normal distribution's upper tail `1 - Phi(k)` (k >= 0), by its continued fraction
/// (Abramowitz-Stegun 7.1.26 is too coarse for the rates of 3-sd limits).
pub fn normal_upper_tail(k: f64) -> f64 {
    let x = k / std::f64::consts::SQRT_2;
    let mut f = 0.0;
    for n in (1..200).rev() {
        f = (n as f64 / 2.0) / (x + f);
    }
    0.5 * (-x * x).exp() / (std::f64::consts::PI.sqrt() * (x + f))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_nan_is_never_the_harmless_worst_case() {
        assert!(max_nan([1.0, f64::NAN, 3.0]).is_nan());
        assert!([1.0, f64::NAN, 3.0].into_iter().fold(0.0, nan_max).is_nan());
        assert_eq!([1.0, 2.0].into_iter().fold(0.0, nan_max), 2.0);
        assert!(max_abs([-4.0, 2.0]) == 4.0);
        assert!(!within(f64::NAN, 1.0));
        assert!(within(-0.5, 1.0));
    }

    #[test]
    fn coverage_fails_missing_too_narrow_and_inflated_bands() {
        let mut c = Coverage::new();
        c.extend((0..100).map(|k| (k as f64 / 100.0 - 0.5) * 3.0));
        assert!(c.problems("good", 0.9, 0.3).is_empty(), "{:?}", c.problems("good", 0.9, 0.3));
        let mut wide = Coverage::new();
        wide.extend((0..100).map(|k| (k as f64 / 100.0 - 0.5) * 0.03));
        assert!(wide.problems("wide", 0.9, 0.3).iter().any(|p| p.contains("inflated")));
        let mut narrow = Coverage::new();
        narrow.extend((0..100).map(|k| (k as f64 / 100.0 - 0.5) * 30.0));
        assert!(narrow.problems("narrow", 0.9, 0.3).iter().any(|p| p.contains("within 2 sd")));
        let mut nan = c.clone();
        nan.push(f64::NAN);
        assert!(nan.problems("nan", 0.9, 0.3).iter().any(|p| p.contains("NaN")));
    }

    #[test]
    fn the_normal_tail_matches_the_tables() {
        for (k, p) in [(1.0, 0.158_655_253_931_457), (2.0, 0.022_750_131_948_179), (3.0, 0.001_349_898_031_630)] {
            let got = super::normal_upper_tail(k);
            assert!((got / p - 1.0).abs() < 1e-8, "1 - Phi({k}) = {got}, the tables' {p}");
        }
    }
}

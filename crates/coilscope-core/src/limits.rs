//! Displacement limits of a parameter set (IEC 62458 / Klippel LSI reporting), evaluated only
//! inside the range the measurement reached (never extrapolated).
//!
//! With `a` the symmetric reach `min(-x_min, x_max)`:
//!
//! * **XBl**: the smallest `x` where `min(Bl(x), Bl(-x))` falls to 82 % of `Bl(0)`
//!   (10 % harmonic distortion from Bl alone, in Klippel's derivation).
//! * **XC**: the smallest `x` where `min(Cms(x), Cms(-x))` falls to 75 % of `Cms(0)`, i.e.
//!   `max(Kms(x), Kms(-x))` rises to `Kms(0) / 0.75`.
//! * **XL**: the smallest `x` where `Le(x)` or `Le(-x)` differs from `Le(0)` by 10 %.
//! * **Xsym**: the symmetry point of Bl at amplitude `x_ac`: the offset `s` with
//!   `Bl(s + x_ac) = Bl(s - x_ac)`, at the largest `x_ac` from `0.8 a` down to `0.2 a` (in
//!   steps of `0.1 a`) for which `s +- x_ac` stays inside the reached range. Positive: Bl's
//!   centre lies coil-out of the rest position.
//! * **Ak**: stiffness asymmetry at the reach, `(Kms(a) - Kms(-a)) / max(Kms(a), Kms(-a))`,
//!   in percent.
//!
//! The percentages above are the defaults of [`Thresholds`]; [`limits_with`] takes others.
//!
//! A limit that the record did not reach is `None`: it lies beyond `a`.

use crate::params::Parameters;
use crate::poly::Poly;

/// The thresholds that define XBl, XC and XL (fractions, not percent).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Thresholds {
    /// XBl: `min(Bl(x), Bl(-x)) / Bl(0)` falls to this (default 0.82).
    pub bl: f64,
    /// XC: `min(Cms(x), Cms(-x)) / Cms(0)` falls to this (default 0.75).
    pub cms: f64,
    /// XL: `|Le(+-x) / Le(0) - 1|` rises to this (default 0.10).
    pub le: f64,
}

impl Default for Thresholds {
    fn default() -> Self {
        Thresholds { bl: 0.82, cms: 0.75, le: 0.10 }
    }
}

impl Thresholds {
    /// Check that each threshold is a fraction strictly inside (0, 1).
    pub fn validate(&self) -> Result<(), String> {
        for (name, v) in [("Bl", self.bl), ("Cms", self.cms), ("Le", self.le)] {
            if !(v > 0.0 && v < 1.0) {
                return Err(format!(
                    "the {name} threshold {v} is not valid: give a fraction in (0, 1), e.g. 0.82 / 0.75 / 0.10"
                ));
            }
        }
        Ok(())
    }
}

/// The limits of one parameter set over a reached range.
#[derive(Clone, Debug, PartialEq)]
pub struct Limits {
    /// The thresholds the limits were computed with.
    pub thresholds: Thresholds,
    /// `[x_min, x_max]` the limits were searched in (m).
    pub range: [f64; 2],
    /// Symmetric reach `min(-x_min, x_max)` (m).
    pub reach: f64,
    pub xbl: Option<f64>,
    pub xc: Option<f64>,
    pub xl: Option<f64>,
    /// Bl symmetry point at amplitude `xsym_amplitude` (m).
    pub xsym: Option<f64>,
    pub xsym_amplitude: f64,
    /// Stiffness asymmetry at the reach (%).
    pub ak: f64,
}

/// Smallest x in (0, a] where `crossed(x)` turns true (grid, then bisection).
fn first_crossing(a: f64, crossed: impl Fn(f64) -> bool) -> Option<f64> {
    let n = 400;
    let mut prev = 0.0;
    for k in 1..=n {
        let x = a * k as f64 / n as f64;
        if crossed(x) {
            let (mut lo, mut hi) = (prev, x);
            for _ in 0..60 {
                let mid = 0.5 * (lo + hi);
                if crossed(mid) {
                    hi = mid
                } else {
                    lo = mid
                }
            }
            return Some(hi);
        }
        prev = x;
    }
    None
}

/// Offset `s` in `[lo + amp, hi - amp]` with `f(s + amp) = f(s - amp)`, the root nearest 0.
pub fn symmetry_point(f: &Poly, amp: f64, range: [f64; 2]) -> Option<f64> {
    let (lo, hi) = (range[0] + amp, range[1] - amp);
    if lo > hi {
        return None;
    }
    let g = |s: f64| f.eval(s + amp) - f.eval(s - amp);
    let n = 400;
    let pts: Vec<f64> = (0..=n).map(|k| lo + (hi - lo) * k as f64 / n as f64).collect();
    let mut best: Option<f64> = None;
    for w in pts.windows(2) {
        let (a, b) = (w[0], w[1]);
        if g(a) == 0.0 || g(a) * g(b) < 0.0 {
            let (mut l, mut h) = (a, b);
            for _ in 0..60 {
                let m = 0.5 * (l + h);
                if g(l) * g(m) <= 0.0 {
                    h = m
                } else {
                    l = m
                }
            }
            let s = 0.5 * (l + h);
            if best.is_none_or(|b: f64| s.abs() < b.abs()) {
                best = Some(s);
            }
        }
    }
    best
}

/// The limits of `p` over the reached range `[x_min, x_max]` (m), default thresholds.
pub fn limits(p: &Parameters, range: [f64; 2]) -> Limits {
    limits_with(p, range, Thresholds::default())
}

/// The limits of `p` over the reached range `[x_min, x_max]` (m) with thresholds `th`.
pub fn limits_with(p: &Parameters, range: [f64; 2], th: Thresholds) -> Limits {
    let a = (-range[0]).min(range[1]).max(0.0);
    let bl0 = p.bl.eval(0.0);
    let k0 = p.kms.eval(0.0);
    let le0 = p.le.eval(0.0);
    let xbl = first_crossing(a, |x| p.bl.eval(x).min(p.bl.eval(-x)) <= th.bl * bl0);
    let xc = first_crossing(a, |x| p.kms.eval(x).max(p.kms.eval(-x)) >= k0 / th.cms);
    let xl = first_crossing(a, |x| ((p.le.eval(x) / le0 - 1.0).abs()).max((p.le.eval(-x) / le0 - 1.0).abs()) >= th.le);
    // The largest amplitude (0.8 a down to 0.2 a) whose symmetry point lies inside the range.
    let (xsym, amp) = (2..=8)
        .rev()
        .map(|k| 0.1 * k as f64 * a)
        .find_map(|amp| symmetry_point(&p.bl, amp, range).map(|s| (Some(s), amp)))
        .unwrap_or((None, 0.8 * a));
    let (kp, km) = (p.kms.eval(a), p.kms.eval(-a));
    Limits {
        thresholds: th,
        range,
        reach: a,
        xbl,
        xc,
        xl,
        xsym,
        xsym_amplitude: amp,
        ak: 100.0 * (kp - km) / kp.max(km),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn set(bl: Vec<f64>, kms: Vec<f64>, le: Vec<f64>) -> Parameters {
        let mut p = crate::params::embedded_driver("sb17cac35-4").unwrap();
        p.bl = Poly { c: bl };
        p.kms = Poly { c: kms };
        p.le = Poly { c: le };
        p
    }

    #[test]
    fn limits_of_quadratic_curves_match_closed_forms() {
        // Bl = 5 (1 - (x/0.01)^2): 82 % at x = 0.01 sqrt(0.18).
        // Kms = 1000 (1 + (x/0.005)^2): 1/0.75 at x = 0.005 sqrt(1/3).
        // Le = 1e-3 (1 + 20 x): 10 % at x = 0.005.
        let p = set(vec![5.0, 0.0, -5.0e4], vec![1000.0, 0.0, 4.0e7], vec![1e-3, 2e-2]);
        let l = limits(&p, [-0.008, 0.009]);
        assert!((l.xbl.unwrap() - 0.01 * 0.18f64.sqrt()).abs() < 1e-9, "{:?}", l.xbl);
        assert!((l.xc.unwrap() - 0.005 * (1.0f64 / 3.0).sqrt()).abs() < 1e-9, "{:?}", l.xc);
        assert!((l.xl.unwrap() - 0.005).abs() < 1e-9, "{:?}", l.xl);
        // Symmetric Bl: symmetry point at 0; symmetric Kms: Ak = 0.
        assert!(l.xsym.unwrap().abs() < 1e-9);
        assert!(l.ak.abs() < 1e-9);
        assert_eq!(l.reach, 0.008);
    }

    #[test]
    fn shifted_bl_has_its_symmetry_point_at_the_shift() {
        // Bl(x) = 5 - 5e4 (x - 0.001)^2: symmetric about +1 mm.
        let p = set(vec![5.0 - 5e4 * 1e-6, 2.0 * 5e4 * 1e-3, -5e4], vec![1000.0, -1e4], vec![1e-3]);
        let l = limits(&p, [-0.006, 0.006]);
        assert!((l.xsym.unwrap() - 0.001).abs() < 1e-9, "{:?}", l.xsym);
        // Kms = 1000 - 1e4 x: softer coil-out, Ak = (940 - 1060)/1060.
        assert!((l.ak - 100.0 * (940.0 - 1060.0) / 1060.0).abs() < 1e-9, "{}", l.ak);
    }

    #[test]
    fn changed_thresholds_move_the_limits_to_their_closed_forms() {
        // Bl = 5 (1 - (x/0.01)^2) reaches 70 % at x = 0.01 sqrt(0.3); Le = 1e-3 (1 + 20 x)
        // changes by 5 % at 2.5 mm; Kms = 1000 (1 + (x/0.005)^2) reaches 1/0.5 at 5 mm.
        let p = set(vec![5.0, 0.0, -5.0e4], vec![1000.0, 0.0, 4.0e7], vec![1e-3, 2e-2]);
        let th = Thresholds { bl: 0.70, cms: 0.5, le: 0.05 };
        let l = limits_with(&p, [-0.008, 0.009], th);
        assert!((l.xbl.unwrap() - 0.01 * 0.3f64.sqrt()).abs() < 1e-9, "{:?}", l.xbl);
        assert!((l.xc.unwrap() - 0.005).abs() < 1e-9, "{:?}", l.xc);
        assert!((l.xl.unwrap() - 0.0025).abs() < 1e-9, "{:?}", l.xl);
        assert!(crate::result::LimitsRecord::from(&l).definitions.contains("70 % Bl(0)"));
        assert!(Thresholds { bl: 1.2, ..th }.validate().unwrap_err().contains("Bl threshold 1.2"));
    }

    #[test]
    fn limits_beyond_the_reach_are_none() {
        let p = set(vec![5.0, 0.0, -5.0e4], vec![1000.0], vec![1e-3]);
        let l = limits(&p, [-0.002, 0.003]);
        assert_eq!((l.xbl, l.xc, l.xl), (None, None, None));
        let j = serde_json::to_value(crate::result::LimitsRecord::from(&l)).unwrap();
        assert_eq!(j["XBl_beyond"], 0.002);
        assert!(j["XBl"].is_null());
    }
}

//! LOG creep of the suspension (formats.md "Extensions": `creep`), realised as a bank of
//! Maxwell elements: the one definition shared by the small-signal impedance, the linear fit
//! and (when it comes) the time-domain model.
//!
//! Klippel's LOG model describes the compliance as `Cms(f) = Cms(f_ref) (1 - lambda
//! log10(f / f_ref))`. A real suspension is causal, so a stiffness that rises with frequency
//! also loses energy. coilscope realises it as `N` Maxwell elements (a spring `dK` in series
//! with a damper, relaxation time `tau_k`), [`PER_DECADE`] per decade from [`F_MIN`] to
//! [`F_MAX`], each with `dK = lambda Kms(0) / PER_DECADE`. At `x = 0` the dynamic stiffness
//! is
//!
//! ```text
//! K(jw) = Kms(0) [1 + lambda (b(w) - Re b(w_ref))],   b(w) = (1/PER_DECADE) sum_k jw tau_k / (1 + jw tau_k)
//! ```
//!
//! The static spring is `Kms(x) - lambda Kms(0) Re b(w_ref)`, so the real part of the
//! dynamic stiffness at `f_ref` is the file's `Kms(x)`, as Klippel LSI reports it. Over the
//! bank's span the real part rises by `lambda Kms(0)` per decade, and the imaginary part,
//! the creep's loss, is about `lambda Kms(0) pi / (2 ln 10)` (0.68 lambda Kms(0)): the
//! Kramers-Kronig partner of the LOG law. This is the realisation the reference recordings
//! in `shared/recordings` use (two per decade, 0.05 Hz to 2 kHz).

use realfft::num_complex::Complex64;
use std::f64::consts::PI;

/// Maxwell elements per decade.
pub const PER_DECADE: usize = 2;
/// Corner frequency of the slowest element (Hz).
pub const F_MIN: f64 = 0.05;
/// Upper limit of the fastest element's corner (Hz).
pub const F_MAX: f64 = 2000.0;

/// Relaxation times `tau_k = 1 / (2 pi f_k)` of the bank (s), slowest first (computed once:
/// the linear fit evaluates the bank at every bin).
pub fn taus() -> &'static [f64] {
    static TAUS: std::sync::LazyLock<Vec<f64>> = std::sync::LazyLock::new(|| {
        (0..)
            .map(|k| F_MIN * 10f64.powf(k as f64 / PER_DECADE as f64))
            .take_while(|&f| f <= F_MAX * (1.0 + 1e-9))
            .map(|f| 1.0 / (2.0 * PI * f))
            .collect()
    });
    &TAUS
}

/// `b(w)`: the bank's dynamic stiffness per `lambda Kms(0)` at angular frequency `w` (rad/s).
pub fn bank(w: f64) -> Complex64 {
    let per = 1.0 / PER_DECADE as f64;
    // j u / (1 + j u) = (u^2 + j u) / (1 + u^2), u = w tau: one real division per element.
    taus()
        .iter()
        .map(|&tau| {
            let u = w * tau;
            let d = per / (1.0 + u * u);
            Complex64::new(u * u * d, u * d)
        })
        .sum()
}

/// `d Re b / d ln w` at `w`: how the static spring's correction moves with the reference.
pub fn bank_re_slope(w: f64) -> f64 {
    let per = 1.0 / PER_DECADE as f64;
    taus()
        .iter()
        .map(|&tau| {
            let u = (w * tau).powi(2);
            per * 2.0 * u / ((1.0 + u) * (1.0 + u))
        })
        .sum()
}

/// `Re b(w)` for a scalar of any type (dual numbers carry its derivative): where the static
/// spring's correction comes from when the reference `w` is itself an unknown.
pub fn bank_re<D: num_dual::DualNum<Primitive = f64> + Copy>(w: D) -> D {
    let per = 1.0 / PER_DECADE as f64;
    taus().iter().fold(D::zero(), |acc, &tau| {
        let u = w * w * (tau * tau);
        acc + u / (u + 1.0) * per
    })
}

/// The stiffness factor `K(jw) / Kms(0)` at `x = 0`: `1 + lambda (b(w) - Re b(w_ref))`.
pub fn stiffness_factor(lambda: f64, w: f64, w_ref: f64) -> Complex64 {
    1.0 + lambda * (bank(w) - bank(w_ref).re)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_bank_has_two_elements_per_decade_from_0_05_hz_to_2_khz() {
        let f: Vec<f64> = taus().iter().map(|t| 1.0 / (2.0 * PI * t)).collect();
        assert_eq!(f.len(), 10, "{f:?}");
        assert!((f[0] - 0.05).abs() < 1e-12 && (f[9] - 1581.1388).abs() < 1e-3, "{f:?}");
    }

    /// The LOG law to first order inside the bank's span: the real part rises by lambda per
    /// decade (within the ripple of two elements per decade), and the loss is the
    /// Kramers-Kronig partner pi / (2 ln 10) lambda.
    #[test]
    fn the_bank_follows_the_log_law_inside_its_span() {
        let lambda = 0.07;
        let wr = 2.0 * PI * 40.0;
        for f in [1.0, 4.0, 10.0, 40.0, 100.0, 200.0] {
            let k = stiffness_factor(lambda, 2.0 * PI * f, wr);
            let log_law = 1.0 + lambda * (f / 40.0f64).log10();
            assert!((k.re - log_law).abs() < 0.03 * lambda, "{f} Hz: {} vs {log_law}", k.re);
            let loss = lambda * PI / (2.0 * std::f64::consts::LN_10);
            assert!((k.im - loss).abs() < 0.06 * loss, "{f} Hz: {} vs {loss}", k.im);
        }
        // At the reference the real part is exactly 1: Kms is the dynamic stiffness there.
        assert!((stiffness_factor(lambda, wr, wr).re - 1.0).abs() < 1e-15);
    }

    #[test]
    fn the_generic_real_part_is_the_real_part() {
        for f in [0.3, 20.0, 700.0] {
            let w = 2.0 * PI * f;
            assert!((bank_re(w) - bank(w).re).abs() < 1e-14);
        }
    }

    #[test]
    fn the_slope_is_the_derivative_of_the_real_part() {
        for f in [0.3, 20.0, 700.0] {
            let w = 2.0 * PI * f;
            let h = 1e-6;
            let fd = (bank(w * (1.0 + h)).re - bank(w * (1.0 - h)).re) / ((1.0 + h).ln() - (1.0 - h).ln());
            assert!((fd - bank_re_slope(w)).abs() < 1e-8, "{f}: {fd} vs {}", bank_re_slope(w));
        }
    }
}

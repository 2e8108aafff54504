//! The linearised model at the rest position (x = 0, cold): electrical impedance and the
//! Thiele/Small figures. One function per number, shared by fitting, reports and tests.

use crate::params::Parameters;
use realfft::num_complex::Complex64;
use std::f64::consts::PI;

/// Density of air (kg/m^3) and speed of sound (m/s) at 20 degC, for Vas.
pub const RHO_AIR: f64 = 1.204;
pub const C_AIR: f64 = 343.2;

/// Electrical input impedance (ohm) of the linearised model at x = 0 and ambient temperature:
/// `Re + jw Le + (jw L2 || R2) + (jw L3 || R3) + Bl^2 / (Rms + jw Mms + K(jw) / jw + Zbox)`,
/// with `K(jw) = Kms(0)` without creep and the [`crate::creep`] bank's dynamic stiffness with
/// it, and `Zbox` the box's mechanical load ([`box_load`]; zero in free air).
pub fn impedance(p: &Parameters, f: f64) -> Complex64 {
    let jw = Complex64::new(0.0, 2.0 * PI * f);
    let mut z = p.re + jw * p.le.c[0];
    if let Some((l2, r2)) = &p.l2r2 {
        let zl2 = jw * l2.c[0];
        z += zl2 * r2.c[0] / (zl2 + r2.c[0]);
    }
    if let Some((l3, r3)) = p.l3r3 {
        z += jw * l3 * r3 / (jw * l3 + r3);
    }
    let k = dynamic_stiffness(p, 2.0 * PI * f);
    let zm = p.rms + jw * p.mms + k / jw + box_load(p, 2.0 * PI * f);
    z + p.bl.c[0] * p.bl.c[0] / zm
}

/// The box's mechanical load on the cone at x = 0 (N s/m, [`crate::enclosure::Enclosure::
/// mechanical_load`]): `Sd^2` times the acoustic impedance of the box air, its leak and its
/// port or radiator in parallel; zero in free air.
pub fn box_load(p: &Parameters, w: f64) -> Complex64 {
    match (&p.enclosure, p.sd) {
        (Some(e), Some(sd)) => e.mechanical_load(&e.elements(p.kms.c[0], p.mms, sd), w),
        _ => Complex64::new(0.0, 0.0),
    }
}

/// Displacement per current `X / I` (m/A) at x = 0: `Bl / (K(jw) - w^2 Mms + jw Rms + jw
/// Zbox)`, with the box's load [`box_load`].
pub fn displacement_per_current(p: &Parameters, f: f64) -> Complex64 {
    let w = 2.0 * PI * f;
    let k = dynamic_stiffness(p, w);
    p.bl.c[0] / (k + Complex64::new(-w * w * p.mms, w * p.rms) + Complex64::new(0.0, w) * box_load(p, w))
}

/// Thiele/Small figures at x = 0, as KLIPPEL LPM and Speakerbench report them: at the
/// resonance `fs`, with the suspension's creep in its stiffness and its loss.
///
/// With creep ([`crate::creep`]) the suspension's stiffness is complex, `K(jw)`: its real
/// part sets the resonance, where `Re K(jw_s) = w_s^2 Mms`, and its imaginary part is a loss
/// that acts at `fs` as a mechanical resistance `Im K(jw_s) / w_s` (about `0.68 lambda
/// Kms(0) / w_s`) beside the viscous `Rms`. `rms_fs` is their sum, and `Qms = w_s Mms /
/// rms_fs`, so `Qms`, `Qts` and `Res = Bl^2 / rms_fs` are the figures read off the
/// impedance peak. Without creep, `rms_fs = Rms` and `fs = sqrt(Kms(0) / Mms) / 2 pi`.
#[derive(Clone, Debug, PartialEq)]
pub struct ThieleSmall {
    /// Resonance frequency (Hz).
    pub fs: f64,
    pub qms: f64,
    pub qes: f64,
    pub qts: f64,
    /// Compliance 1/Kms(0) (m/N): with creep, the compliance at its reference frequency
    /// (the resonance, unless the set names another `f_ref`).
    pub cms: f64,
    /// Equivalent air volume (m^3), when Sd is known.
    pub vas: Option<f64>,
    /// Mechanical resistance at `fs` (kg/s): the viscous `Rms` plus creep's loss there.
    pub rms_fs: f64,
}

/// The suspension's dynamic stiffness `K(jw)` (N/m) at x = 0: `Kms(0)` without creep, the
/// [`crate::creep`] bank's with it.
pub fn dynamic_stiffness(p: &Parameters, w: f64) -> Complex64 {
    match (&p.creep, p.creep_f_ref()) {
        (Some(c), Some(f_ref)) => p.kms.c[0] * crate::creep::stiffness_factor(c.lambda, w, 2.0 * PI * f_ref),
        _ => Complex64::new(p.kms.c[0], 0.0),
    }
}

/// Thiele/Small figures of a parameter set at x = 0 (see [`ThieleSmall`]).
pub fn thiele_small(p: &Parameters) -> ThieleSmall {
    let kms = p.kms.c[0];
    let bl = p.bl.c[0];
    // The resonance: `Re K(jw) = w^2 Mms`. `Re K` moves by lambda Kms(0) per decade, so the
    // fixed point contracts by about lambda / (2 ln 10) per step; without creep it is exact
    // at once.
    let mut ws = (kms / p.mms).sqrt();
    for _ in 0..50 {
        let next = (dynamic_stiffness(p, ws).re / p.mms).sqrt();
        let done = (next - ws).abs() <= 1e-13 * ws;
        ws = next;
        if done || !ws.is_finite() {
            break;
        }
    }
    let rms_fs = p.rms + dynamic_stiffness(p, ws).im / ws;
    let qms = ws * p.mms / rms_fs;
    let qes = ws * p.mms * p.re / (bl * bl);
    let cms = 1.0 / kms;
    ThieleSmall {
        fs: ws / (2.0 * PI),
        qms,
        qes,
        qts: qms * qes / (qms + qes),
        cms,
        vas: p.sd.map(|sd| RHO_AIR * C_AIR * C_AIR * sd * sd * cms),
        rms_fs,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::embedded_driver;

    #[test]
    fn impedance_peaks_at_fs_with_the_motional_resistance() {
        let p = embedded_driver("sb17cac35-4").unwrap();
        let ts = thiele_small(&p);
        let z = impedance(&p, ts.fs);
        // At resonance the motional branch is purely resistive: Bl^2 / Rms.
        let zm = z - (impedance(&Parameters { bl: crate::Poly::constant(1e-12), ..p.clone() }, ts.fs));
        assert!((zm.re - p.bl.c[0].powi(2) / p.rms).abs() < 1e-6 * zm.re);
        assert!(zm.im.abs() < 1e-6 * zm.re);
        // Qes = Re / (Bl^2/Rms) * Qms.
        assert!((ts.qes - ts.qms * p.re / (p.bl.c[0].powi(2) / p.rms)).abs() < 1e-12);
        assert!((ts.fs - 32.38).abs() < 0.01, "{}", ts.fs);
        assert!(ts.vas.unwrap() > 0.02 && ts.vas.unwrap() < 0.04);
    }

    /// With creep, fs is where the motional impedance is real, and there it is `Bl^2 /
    /// rms_fs`: the peak an impedance curve shows, whatever the creep's reference.
    #[test]
    fn qms_at_fs_takes_creeps_loss_from_the_impedance_peak() {
        let plain = embedded_driver("sb17cac35-4").unwrap();
        for (lambda, f_ref) in [(0.02, None), (0.1, None), (0.15, None), (0.1, Some(10.0)), (0.1, Some(300.0))] {
            let p = Parameters { creep: Some(crate::params::Creep { lambda, f_ref }), ..plain.clone() };
            let ts = thiele_small(&p);
            let zmot =
                impedance(&p, ts.fs) - impedance(&Parameters { bl: crate::Poly::constant(1e-12), ..p.clone() }, ts.fs);
            let peak = p.bl.c[0].powi(2) / ts.rms_fs;
            assert!(zmot.im.abs() < 1e-9 * zmot.re, "lambda {lambda} f_ref {f_ref:?}: Zmot {zmot} at fs {}", ts.fs);
            assert!(
                (zmot.re - peak).abs() < 1e-9 * peak,
                "lambda {lambda} f_ref {f_ref:?}: Zmot {zmot}, Bl^2/rms_fs {peak}"
            );
            // The loss is the Kramers-Kronig partner of the LOG law, about 0.68 lambda K / w.
            let ws = 2.0 * PI * ts.fs;
            let loss = ts.rms_fs - p.rms;
            let kk = lambda * p.kms.c[0] * PI / (2.0 * std::f64::consts::LN_10) / ws;
            assert!(
                loss > 0.0 && (loss / kk - 1.0).abs() < 0.1,
                "lambda {lambda} f_ref {f_ref:?}: loss {loss}, 0.68 lambda Kms / ws {kk}"
            );
            assert!((ts.qms - ws * p.mms / ts.rms_fs).abs() < 1e-12 * ts.qms);
            assert!(ts.qms < thiele_small(&plain).qms);
        }
        // Without creep nothing moves.
        let ts = thiele_small(&plain);
        assert_eq!(ts.rms_fs, plain.rms);
        assert_eq!(ts.fs, plain.resonance_hz());
    }

    #[test]
    fn displacement_per_current_is_bl_over_kms_at_dc() {
        let p = embedded_driver("ptt4.0w04-01a").unwrap();
        let h = displacement_per_current(&p, 1e-6);
        assert!((h.re - p.bl.c[0] / p.kms.c[0]).abs() < 1e-9);
    }
}

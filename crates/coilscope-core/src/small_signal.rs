//! The linearised model at the rest position (x = 0, cold): electrical impedance and the
//! Thiele/Small figures. One function per number, shared by fitting, reports and tests.

use crate::params::Parameters;
use realfft::num_complex::Complex64;
use std::f64::consts::PI;

/// Density of air (kg/m^3) and speed of sound (m/s) at 20 degC, for Vas.
pub const RHO_AIR: f64 = 1.204;
pub const C_AIR: f64 = 343.2;

/// Electrical input impedance (ohm) of the linearised model at x = 0 and ambient temperature:
/// `Re + jw Le + (jw L2 || R2) + (jw L3 || R3) + Bl^2 / (Rms + jw Mms + K(jw) / jw)`, with
/// `K(jw) = Kms(0)` without creep and the [`crate::creep`] bank's dynamic stiffness with it.
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
    let k = match (&p.creep, p.creep_f_ref()) {
        (Some(c), Some(f_ref)) => p.kms.c[0] * crate::creep::stiffness_factor(c.lambda, 2.0 * PI * f, 2.0 * PI * f_ref),
        _ => Complex64::new(p.kms.c[0], 0.0),
    };
    let zm = p.rms + jw * p.mms + k / jw;
    z + p.bl.c[0] * p.bl.c[0] / zm
}

/// Displacement per current `X / I` (m/A) at x = 0: `Bl / (K(jw) - w^2 Mms + jw Rms)`.
pub fn displacement_per_current(p: &Parameters, f: f64) -> Complex64 {
    let w = 2.0 * PI * f;
    let k = match (&p.creep, p.creep_f_ref()) {
        (Some(c), Some(f_ref)) => p.kms.c[0] * crate::creep::stiffness_factor(c.lambda, w, 2.0 * PI * f_ref),
        _ => Complex64::new(p.kms.c[0], 0.0),
    };
    p.bl.c[0] / (k + Complex64::new(-w * w * p.mms, w * p.rms))
}

/// Thiele/Small figures at x = 0.
#[derive(Clone, Debug, PartialEq)]
pub struct ThieleSmall {
    /// Resonance frequency (Hz).
    pub fs: f64,
    pub qms: f64,
    pub qes: f64,
    pub qts: f64,
    /// Compliance 1/Kms(0) (m/N).
    pub cms: f64,
    /// Equivalent air volume (m^3), when Sd is known.
    pub vas: Option<f64>,
}

/// Thiele/Small figures of a parameter set at x = 0.
pub fn thiele_small(p: &Parameters) -> ThieleSmall {
    let kms = p.kms.c[0];
    let bl = p.bl.c[0];
    let ws = (kms / p.mms).sqrt();
    let qms = ws * p.mms / p.rms;
    let qes = ws * p.mms * p.re / (bl * bl);
    let cms = 1.0 / kms;
    ThieleSmall { fs: ws / (2.0 * PI), qms, qes, qts: qms * qes / (qms + qes), cms, vas: p.sd.map(|sd| RHO_AIR * C_AIR * C_AIR * sd * sd * cms) }
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

    #[test]
    fn displacement_per_current_is_bl_over_kms_at_dc() {
        let p = embedded_driver("ptt4.0w04-01a").unwrap();
        let h = displacement_per_current(&p, 1e-6);
        assert!((h.re - p.bl.c[0] / p.kms.c[0]).abs() < 1e-9);
    }
}

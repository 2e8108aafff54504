//! Loudspeaker diagnosis from a parameter set (seed section 5): displacement limits with
//! changeable thresholds, the voice-coil rest-position shift that symmetrises Bl(x), the
//! polarity check from the Le(x) asymmetry, and the thermal power handling.
//!
//! * **Bl shift**: `Xsym` is the offset `s` about which Bl is symmetric at the largest usable
//!   amplitude; moving the coil's rest position by `+s` (coil out for `s > 0`) centres it in
//!   the Bl plateau.
//! * **Polarity**: the inductance rises when the coil moves toward the back plate (x < 0,
//!   "coil in"), where the flux path through air is shorter. If Le rises toward x > 0 instead,
//!   the x axis (or the polarity of the connection) is most likely reversed. An asymmetry below
//!   2 % of Le(0) is inconclusive.
//! * **Thermal power handling**: in the steady state of the two-node thermal model
//!   (`core::model`), `Tv = (Rtv + Rtm) P_Re + Rtm P_R2`. The continuous electrical power in Re
//!   at the rise limit is `dT / (Rtv + Rtm)` (eddy losses aside); the voltages that reach the
//!   limit follow from the linear model with Re at the hot temperature: for the worst sine
//!   (the frequency that heats most per volt, near the impedance minimum) and for IEC 60268-1
//!   noise.

use coilscope_core::excitation::{generate, Excitation, SignalSpec};
use coilscope_core::fft::rfft;
use coilscope_core::limits::{limits_with, Limits, Thresholds};
use coilscope_core::params::Thermal;
use coilscope_core::small_signal::impedance;
use coilscope_core::Parameters;
use realfft::num_complex::Complex64 as C;
use serde_json::{json, Value};
use std::f64::consts::PI;

/// The polarity check.
#[derive(Clone, Debug, PartialEq)]
pub struct Polarity {
    /// The amplitude the check looked at (m).
    pub at: f64,
    pub le_minus: f64,
    pub le_plus: f64,
    /// `(Le(-at) - Le(at)) / Le(0)`: positive when Le rises toward the back plate.
    pub asymmetry: f64,
    /// "consistent", "reversed?" or "inconclusive".
    pub verdict: &'static str,
}

pub fn polarity(p: &Parameters, reach: f64) -> Polarity {
    let at = reach;
    let (lm, lp, l0) = (p.le.eval(-at), p.le.eval(at), p.le.eval(0.0));
    let asym = (lm - lp) / l0;
    let verdict = if asym.abs() < 0.02 {
        "inconclusive"
    } else if asym > 0.0 {
        "consistent"
    } else {
        "reversed?"
    };
    Polarity { at, le_minus: lm, le_plus: lp, asymmetry: asym, verdict }
}

/// Thermal power handling at a voice-coil rise limit.
#[derive(Clone, Debug, PartialEq)]
pub struct ThermalHandling {
    /// The rise limit (K).
    pub dt_max: f64,
    /// Voice-coil and magnet time constants `Rtv Ctv`, `Rtm Ctm` (s).
    pub tau_v: f64,
    pub tau_m: f64,
    /// Continuous power in Re at the limit (W).
    pub p_max: f64,
    /// RMS voltage of the worst-case sine and its frequency.
    pub volts_sine: f64,
    pub f_sine: f64,
    /// RMS voltage of IEC 60268-1 noise at the limit, and its nominal power `U^2 / Re` (W).
    pub volts_iec: f64,
    pub p_nominal_iec: f64,
}

/// Steady voice-coil rise per squared RMS volt of a sine at `f`, for `hot` (the set with Re
/// at the hot temperature) and its thermal resistances `t`.
fn heating_per_v2(hot: &Parameters, t: &Thermal, f: f64) -> f64 {
    let i = C::new(1.0, 0.0) / impedance(hot, f);
    let p_re = hot.re * i.norm_sqr();
    let p_r2 = match &hot.l2r2 {
        Some((l2, r2)) => {
            let zl = C::new(0.0, 2.0 * PI * f * l2.c[0]);
            let ir2 = i * zl / (zl + r2.c[0]);
            r2.c[0] * ir2.norm_sqr()
        }
        None => 0.0,
    };
    (t.rtv + t.rtm) * p_re + t.rtm * p_r2
}

/// Thermal power handling of `p` for a voice-coil rise of `dt_max` K, or `None` without
/// thermal parameters.
pub fn thermal_handling(p: &Parameters, dt_max: f64) -> Option<ThermalHandling> {
    let t = p.thermal.as_ref()?;
    let hot = Parameters { re: p.re * (1.0 + t.alpha * dt_max), ..p.clone() };
    let freqs = crate::distortion::log_frequencies(10.0, 20_000.0, 24);
    let (f_sine, worst) =
        freqs.iter().map(|&f| (f, heating_per_v2(&hot, t, f))).fold((0.0, 0.0), |a, b| if b.1 > a.1 { b } else { a });
    let fs = 48_000.0;
    let noise = generate(&Excitation::Iec, &SignalSpec { fs, seconds: 8.0, rms: 1.0, fade: 0.0, seed: 1 }).ok()?;
    let spec = rfft(&noise);
    let (mut heat, mut power) = (0.0, 0.0);
    for (k, c) in spec.iter().enumerate().skip(1) {
        let f = k as f64 * fs / noise.len() as f64;
        if f > 20_000.0 {
            break;
        }
        heat += c.norm_sqr() * heating_per_v2(&hot, t, f);
        power += c.norm_sqr();
    }
    let iec = heat / power;
    let volts_iec = (dt_max / iec).sqrt();
    Some(ThermalHandling {
        dt_max,
        tau_v: t.rtv * t.ctv,
        tau_m: t.rtm * t.ctm,
        p_max: dt_max / (t.rtv + t.rtm),
        volts_sine: (dt_max / worst).sqrt(),
        f_sine,
        volts_iec,
        p_nominal_iec: volts_iec * volts_iec / p.re,
    })
}

/// Limits, shift, polarity and thermal handling of a set over its reached range.
#[derive(Clone, Debug)]
pub struct Diagnosis {
    pub limits: Limits,
    pub polarity: Polarity,
    pub thermal: Option<ThermalHandling>,
}

pub fn diagnose(p: &Parameters, range: [f64; 2], thresholds: Thresholds, dt_max: f64) -> Diagnosis {
    let limits = limits_with(p, range, thresholds);
    let polarity = polarity(p, limits.reach);
    Diagnosis { thermal: thermal_handling(p, dt_max), limits, polarity }
}

impl Diagnosis {
    /// The coil rest-position shift that would centre Bl (m, + = out), as text advice too.
    pub fn bl_shift_advice(&self) -> String {
        match self.limits.xsym {
            Some(s) if s.abs() < 0.02 * self.limits.reach.max(1e-9) => {
                format!("Bl(x) is symmetric within {:.2} mm: no shift needed", 0.02 * self.limits.reach * 1e3)
            }
            Some(s) => format!(
                "Bl(x) is centred at {:+.2} mm: move the voice-coil rest position {:.2} mm {}",
                s * 1e3,
                s.abs() * 1e3,
                if s > 0.0 { "outward (coil out, away from the back plate)" } else { "inward (toward the back plate)" }
            ),
            None => "the Bl(x) symmetry point lies outside the reached range".into(),
        }
    }

    pub fn to_json(&self) -> Value {
        let pol = &self.polarity;
        json!({
            "limits": coilscope_core::result::LimitsRecord::from(&self.limits),
            "bl_shift": {"shift": self.limits.xsym, "amplitude": self.limits.xsym_amplitude, "advice": self.bl_shift_advice(), "unit": "m"},
            "polarity": {"at": pol.at, "Le_minus": pol.le_minus, "Le_plus": pol.le_plus, "asymmetry": pol.asymmetry, "verdict": pol.verdict,
                "rule": "Le rises toward the back plate (x < 0); a rise toward x > 0 suggests a reversed x axis or connection"},
            "thermal": self.thermal.as_ref().map(|t| json!({
                "dT_max": t.dt_max, "tau_v": t.tau_v, "tau_m": t.tau_m, "P_max": t.p_max,
                "volts_sine": t.volts_sine, "f_sine": t.f_sine, "volts_iec": t.volts_iec, "P_nominal_iec": t.p_nominal_iec,
                "units": {"dT_max": "K", "tau_v": "s", "tau_m": "s", "P_max": "W", "volts_sine": "V rms", "f_sine": "Hz", "volts_iec": "V rms", "P_nominal_iec": "W"},
                "definitions": "steady state Tv = (Rtv + Rtm) P_Re + Rtm P_R2 with Re at the hot temperature; P_max = dT/(Rtv+Rtm); P_nominal_iec = volts_iec^2 / Re",
            })),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use coilscope_core::{embedded_driver, Poly};

    #[test]
    fn polarity_follows_the_le_slope() {
        let mut p = embedded_driver("sb17cac35-4").unwrap();
        p.le = Poly { c: vec![1e-3, -2e-2] };
        assert_eq!(polarity(&p, 0.004).verdict, "consistent");
        p.le = Poly { c: vec![1e-3, 2e-2] };
        assert_eq!(polarity(&p, 0.004).verdict, "reversed?");
        p.le = Poly { c: vec![1e-3, 0.0, 1.0] };
        assert_eq!(polarity(&p, 0.004).verdict, "inconclusive");
    }

    #[test]
    fn thermal_limit_of_a_resistor_is_the_closed_form() {
        // With Bl = 0 and no inductance the driver is a resistor Re: P = U^2 / Re_hot at every
        // frequency, so U = sqrt(dT Re_hot / (Rtv + Rtm)) for the sine and for noise alike.
        let mut p = embedded_driver("sb17cac35-4").unwrap();
        p.bl = Poly::constant(1e-9);
        p.le = Poly::constant(1e-12);
        p.l2r2 = None;
        let t = p.thermal.clone().unwrap();
        let h = thermal_handling(&p, 40.0).unwrap();
        let u = (40.0 * p.re * (1.0 + t.alpha * 40.0) / (t.rtv + t.rtm)).sqrt();
        assert!((h.volts_sine - u).abs() < 1e-6 * u, "{} vs {u}", h.volts_sine);
        assert!((h.volts_iec - u).abs() < 1e-6 * u, "{} vs {u}", h.volts_iec);
        assert!((h.p_max - 40.0 / (t.rtv + t.rtm)).abs() < 1e-12);
    }
}

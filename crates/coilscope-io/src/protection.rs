//! The protection model of one unit (`coilscope export --protection`, `"format":
//! "coilscope.protection/1"`, docs/formats.md): what a speaker-protection controller needs to
//! keep this unit inside its excursion and temperature limits, and the unit's calibration.
//!
//! - `model`: the unit's whole parameter set in the contract's own format (Bl(x), Kms(x),
//!   Le(x) as power series, Mms, Rms, Re, the LR-2 branch, creep, LR-3, Le(i), Rms(v), the
//!   thermal network), so that the controller's model is the one the measurement identified.
//! - `creep_bank`: creep written out as the bank of springs and dampers the model integrates
//!   (`Mms dv/dt` gains `Kc x - sum_k dK (x - y_k)`, `dy_k/dt = (x - y_k) / tau_k`), so that a
//!   controller need not derive it from the LOG creep factor.
//! - `excursion`: `x_lim`, the smallest of IEC 62458's XBl, XC and XL at the given thresholds,
//!   or the measured reach where none lies inside it (`limited_by: "reach"`: the model is not
//!   known past what the measurement reached).
//! - `thermal`: the coil's absolute temperature limit and the network's time constants.
//! - `calibration`: `Re` at the temperature it was measured at, the copper's `alpha`, `Re`
//!   referred to 20 and 25 C (what smart-amplifier calibration records hold: Cirrus's calR and
//!   calAmbient, TI's R0, NXP's R25C), and the unit's id.

use crate::IoError;
use coilscope_core::limits::{limits_with, Thresholds};
use coilscope_core::params::Parameters;
use serde_json::{json, Value};

/// The format tag of a protection file.
pub const PROTECTION_FORMAT: &str = "coilscope.protection/1";

/// What a protection file says beside the unit's parameter set.
#[derive(Clone, Debug, PartialEq)]
pub struct ProtectionOptions {
    /// The unit's id (its serial number): what the calibration belongs to.
    pub unit_id: String,
    /// The unit's temperature (degrees C) when its `Re` was measured.
    pub measured_at: f64,
    /// The coil's absolute temperature limit (degrees C).
    pub t_limit: f64,
    /// The IEC 62458 thresholds that define the excursion limit.
    pub thresholds: Thresholds,
}

/// A unit's calibration record.
#[derive(Clone, Debug, PartialEq)]
pub struct Calibration {
    pub unit_id: String,
    /// The voice coil's DC resistance (ohm) at `measured_at`.
    pub re: f64,
    /// Degrees C.
    pub measured_at: f64,
    /// The coil's temperature coefficient (1/K), referred to `measured_at`'s `Re`.
    pub alpha: f64,
}

impl Calibration {
    /// `Re` (ohm) at `t` degrees C: `Re (1 + alpha (t - measured_at))`.
    pub fn re_at(&self, t: f64) -> f64 {
        self.re * (1.0 + self.alpha * (t - self.measured_at))
    }
}

/// A protection file, read back.
#[derive(Clone, Debug, PartialEq)]
pub struct Protection {
    pub model: Parameters,
    /// The excursion limit (m, either way from rest).
    pub x_lim: f64,
    /// What sets it: `XBl`, `XC`, `XL` or `reach`.
    pub limited_by: String,
    /// The coil's absolute temperature limit (degrees C).
    pub t_limit: f64,
    pub calibration: Calibration,
}

/// The protection file of the unit whose identified set is `p`. Refused: a set without its
/// measured range `x_range` (the limits are searched in it) or without `thermal`.
pub fn protection(p: &Parameters, o: &ProtectionOptions) -> Result<Value, String> {
    let range = p.x_range.ok_or("the set has no x_range (the range its curves were measured over): export a result of `identify` or `measure`, or give x_range in the set")?;
    let t = p.thermal.as_ref().ok_or("the set has no thermal parameters (parameters.thermal): the protection model needs them; measure them with a long-term test, `coilscope measure ... --duration 600 --volts V`")?;
    o.thresholds.validate()?;
    if o.unit_id.trim().is_empty() {
        return Err("the unit's id is empty: give --unit-id (its serial number)".into());
    }
    if !(o.measured_at.is_finite() && (-40.0..=150.0).contains(&o.measured_at)) {
        return Err(format!(
            "--measured-at {} C: give the unit's temperature when its Re was measured (-40 .. 150 C)",
            o.measured_at
        ));
    }
    if !(o.t_limit.is_finite() && o.t_limit > o.measured_at) {
        return Err(format!(
            "--t-limit {} C: give the coil's absolute temperature limit, above the {} C it was measured at",
            o.t_limit, o.measured_at
        ));
    }
    let l = limits_with(p, range, o.thresholds);
    let (x_lim, limited_by) = [("XBl", l.xbl), ("XC", l.xc), ("XL", l.xl)]
        .into_iter()
        .filter_map(|(name, x)| x.map(|x| (x, name)))
        .fold((l.reach, "reach"), |best, c| if c.0 < best.0 { c } else { best });
    let creep_bank = coilscope_core::model::ExtModel::<f64>::lift_from(p).creep.map(|c| {
        json!({
            "dK": c.dk,
            "Kc": c.kc,
            "tau": c.rate.iter().map(|r| 1.0 / r).collect::<Vec<f64>>(),
        })
    });
    let (tau_coil, tau_magnet) = crate::export::thermal_time_constants(t.rtv, t.ctv, t.rtm, t.ctm);
    let cal = Calibration { unit_id: o.unit_id.clone(), re: p.re, measured_at: o.measured_at, alpha: t.alpha };
    Ok(json!({
        "format": PROTECTION_FORMAT,
        "model": p.to_json_value(),
        "creep_bank": creep_bank,
        "excursion": {
            "x_lim": x_lim,
            "limited_by": limited_by,
            "XBl": l.xbl,
            "XC": l.xc,
            "XL": l.xl,
            "reach": l.reach,
            "x_range": range,
            "thresholds": {"Bl": o.thresholds.bl, "Cms": o.thresholds.cms, "Le": o.thresholds.le},
        },
        "thermal": {"t_limit": o.t_limit, "tau_coil": tau_coil, "tau_magnet": tau_magnet},
        "calibration": {
            "unit_id": cal.unit_id,
            "Re": cal.re,
            "measured_at": cal.measured_at,
            "alpha": cal.alpha,
            "Re_20C": cal.re_at(20.0),
            "Re_25C": cal.re_at(25.0),
        },
    }))
}

/// A protection file read back from its JSON text (`origin` names it in errors).
pub fn protection_from_json(text: &str, origin: &str) -> Result<Protection, IoError> {
    let e = |m: String| IoError(format!("{origin}: {m}"));
    let v: Value = serde_json::from_str(text).map_err(|x| e(format!("not valid JSON ({x})")))?;
    match v.get("format").and_then(Value::as_str) {
        Some(PROTECTION_FORMAT) => {}
        other => return Err(e(format!("format {other:?}: expected \"{PROTECTION_FORMAT}\""))),
    }
    let num = |path: &[&str]| -> Result<f64, IoError> {
        let mut at = &v;
        for k in path {
            at = at.get(k).ok_or_else(|| e(format!("missing key `{}`", path.join("."))))?;
        }
        at.as_f64().ok_or_else(|| e(format!("`{}` = {at}: expected a number", path.join("."))))
    };
    let text_at = |path: [&str; 2]| -> Result<String, IoError> {
        v.get(path[0])
            .and_then(|o| o.get(path[1]))
            .and_then(Value::as_str)
            .map(str::to_string)
            .ok_or_else(|| e(format!("`{}` missing or not text", path.join("."))))
    };
    let model = v.get("model").ok_or_else(|| e("missing key `model` (the unit's parameter set)".into()))?;
    let model = Parameters::from_json_value(model, &format!("{origin} (model)")).map_err(|x| IoError(x.to_string()))?;
    Ok(Protection {
        model,
        x_lim: num(&["excursion", "x_lim"])?,
        limited_by: text_at(["excursion", "limited_by"])?,
        t_limit: num(&["thermal", "t_limit"])?,
        calibration: Calibration {
            unit_id: text_at(["calibration", "unit_id"])?,
            re: num(&["calibration", "Re"])?,
            measured_at: num(&["calibration", "measured_at"])?,
            alpha: num(&["calibration", "alpha"])?,
        },
    })
}

/// A protection file read from `path`.
pub fn load_protection(path: &std::path::Path) -> Result<Protection, IoError> {
    let text = std::fs::read_to_string(path).map_err(|x| IoError(format!("{}: cannot read ({x})", path.display())))?;
    protection_from_json(&text, &path.display().to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn opts() -> ProtectionOptions {
        ProtectionOptions {
            unit_id: "SN-0042".into(),
            measured_at: 23.0,
            t_limit: 120.0,
            thresholds: Thresholds::default(),
        }
    }

    #[test]
    fn a_protection_file_round_trips_with_its_calibration() {
        let mut p = coilscope_core::embedded_driver("sb17cac35-4").unwrap().with_typical_creep();
        p.l3r3 = Some((2e-4, 3.0));
        let v = protection(&p, &opts()).unwrap();
        let back = protection_from_json(&v.to_string(), "unit.json").unwrap();
        assert_eq!(back.model, p);
        assert_eq!(
            back.calibration,
            Calibration {
                unit_id: "SN-0042".into(),
                re: p.re,
                measured_at: 23.0,
                alpha: p.thermal.as_ref().unwrap().alpha
            }
        );
        assert_eq!(back.t_limit, 120.0);
        // Referred to another temperature by the copper's coefficient.
        let c = &back.calibration;
        assert!((v["calibration"]["Re_25C"].as_f64().unwrap() - c.re * (1.0 + 2.0 * c.alpha)).abs() < 1e-12);
        // The excursion limit is IEC 62458's smallest, inside the measured range.
        let l = limits_with(&p, p.x_range.unwrap(), Thresholds::default());
        let found: Vec<f64> = [l.xbl, l.xc, l.xl].into_iter().flatten().collect();
        let want = found.iter().copied().fold(l.reach, f64::min);
        assert_eq!(back.x_lim, want);
        assert!(back.x_lim > 0.0 && back.x_lim <= l.reach);
        // Creep written out as the model's bank.
        let bank = coilscope_core::model::ExtModel::<f64>::lift_from(&p).creep.unwrap();
        assert_eq!(v["creep_bank"]["dK"].as_f64().unwrap(), bank.dk);
        assert_eq!(v["creep_bank"]["tau"].as_array().unwrap().len(), bank.rate.len());
    }

    #[test]
    fn what_a_protection_file_cannot_be_made_of_is_refused_with_the_reason() {
        let p = coilscope_core::embedded_driver("sb17cac35-4").unwrap();
        let no_range = Parameters { x_range: None, ..p.clone() };
        assert!(protection(&no_range, &opts()).unwrap_err().contains("x_range"));
        let no_heat = Parameters { thermal: None, ..p.clone() };
        assert!(protection(&no_heat, &opts()).unwrap_err().contains("thermal"));
        let cold = ProtectionOptions { t_limit: 10.0, ..opts() };
        assert!(protection(&p, &cold).unwrap_err().contains("--t-limit"));
        let nameless = ProtectionOptions { unit_id: " ".into(), ..opts() };
        assert!(protection(&p, &nameless).unwrap_err().contains("--unit-id"));
        let e = protection_from_json("{\"format\": \"coilscope.result/1\"}", "x.json").unwrap_err();
        assert!(e.0.contains("x.json") && e.0.contains(PROTECTION_FORMAT), "{e}");
        let mut v = protection(&p, &opts()).unwrap();
        v["calibration"]["Re"] = json!("3.9");
        let e = protection_from_json(&v.to_string(), "unit.json").unwrap_err();
        assert!(e.0.contains("calibration.Re"), "{e}");
    }
}

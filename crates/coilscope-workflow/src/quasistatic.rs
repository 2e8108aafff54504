//! `coilscope quasistatic`: the static and quasi-static point-by-point measurement (IEC 62458
//! 10.2/10.3), of a virtual driver or of a driver played through any [`Played`] source, and
//! the result file it writes.

use coilscope_core::excitation::{generate, Excitation, SignalSpec};
use coilscope_core::result::{Fit, ResultFile, Uncertainty, Warning};
use coilscope_core::simulate::{simulate, SimOptions};
use coilscope_core::small_signal::thiele_small;
use coilscope_core::Parameters;
use coilscope_ident::quasi_static::{quasi_static, Offset, Played, Push, QuasiStatic, QuasiStaticOptions};
use serde_json::json;

/// The small signal played at every working point: pink noise 5 Hz - 16 kHz, 2 s, 1 V RMS
/// (scaled to the point's level by the method).
pub fn small_signal(fs: f64) -> Result<Vec<f64>, String> {
    generate(
        &Excitation::Pink { f_lo: 5.0, f_hi: 16000.0, crest: None },
        &SignalSpec { fs, seconds: 2.0, rms: 1.0, fade: 0.0, seed: 1 },
    )
}

/// How far and how long: what the user chooses for either kind of driver.
#[derive(Clone, Copy, Debug)]
pub struct QuasiRequest {
    /// Working points (odd: one at rest).
    pub points: usize,
    /// The outermost points as a share of the range (0 .. 1].
    pub reach: f64,
    /// Seconds each point's offset is held before its small signal.
    pub hold_s: f64,
    /// Power-series order of the fitted curves.
    pub order: usize,
}

impl QuasiRequest {
    /// The request's own values checked, with what would be valid.
    pub fn check(&self) -> Result<(), String> {
        if !(self.reach > 0.0 && self.reach <= 1.0) {
            return Err(format!("--reach {} is not valid (0 .. 1 of the range)", self.reach));
        }
        if !(0.5..=600.0).contains(&self.hold_s) {
            return Err(format!("--hold {} s is not valid (0.5 .. 600 s)", self.hold_s));
        }
        Ok(())
    }
}

/// The method's options for a virtual driver: its own range and mass, a small signal of about
/// 2 % of the range at the resonance (a linear estimate), and the offset named (`current`,
/// `mass`, or `pressure`, which needs the set's Sd).
pub fn virtual_options(
    p: &Parameters,
    req: &QuasiRequest,
    offset: &str,
    origin: &str,
) -> Result<QuasiStaticOptions, String> {
    req.check()?;
    if let Some(e) = &p.enclosure {
        return Err(format!("{origin}: the set puts the driver in a {} box (`enclosure`); the quasi-static method measures the suspension in free air (in a box it would add the air's stiffness to Kms(x)): remove `enclosure`", e.type_name()));
    }
    let range = p
        .x_range
        .ok_or_else(|| format!("{origin}: the set has no x_range: the working points need the range they may go to"))?;
    let ts = thiele_small(p);
    let per_volt = p.bl.c[0] / (p.re * p.kms.c[0]) * ts.qts.max(0.3);
    let ac_volts = (0.02 * range[1].min(-range[0]) / per_volt).clamp(0.01, 1.0);
    let offset = match offset {
        "mass" => Offset::Mass,
        "pressure" => Offset::Pressure {
            sd: p.sd.ok_or_else(|| {
                format!("{origin}: --offset pressure needs the diaphragm's area: the set has no Sd (m^2)")
            })?,
        },
        "current" => Offset::Current,
        other => return Err(format!("--offset {other}: give current, mass or pressure")),
    };
    Ok(QuasiStaticOptions {
        mms: p.mms,
        points: req.points,
        reach: req.reach,
        range,
        hold_s: req.hold_s,
        record_s: 2.0,
        ac_volts,
        order: req.order,
        fs: 48000.0,
        offset,
    })
}

/// The quasi-static measurement of a virtual driver with the set `p`: each working point is a
/// simulation of the set with the point's push (a force, or an added mass).
pub fn virtual_quasistatic(p: &Parameters, opts: &QuasiStaticOptions) -> Result<QuasiStatic, String> {
    let fs = opts.fs;
    let play = |d: &[f64], push: Push| {
        let q = Parameters { mms: p.mms + push.added_mass, ..p.clone() };
        simulate(&q, fs, d, &SimOptions { force: push.force, ..Default::default() })
            .map(|t| Played::from((t.u, t.i, t.x)))
            .map_err(|e| e.to_string())
    };
    quasi_static(play, &small_signal(fs)?, opts)
}

/// The share of the asked reach the points reached on their shorter side, where below 95 %:
/// the offset a point needs grows as Bl falls and Kms rises, so the points may stop short.
pub fn reach_short(q: &QuasiStatic, opts: &QuasiStaticOptions) -> Option<f64> {
    let [lo, hi] = q.params.x_range?;
    let share = (lo / (opts.reach * opts.range[0])).min(hi / (opts.reach * opts.range[1]));
    (share < 0.95).then_some(share)
}

/// The result file of a quasi-static measurement: the fitted set (named `name`, so that
/// `report --compare` can tell two drivers apart), the method, the points' bands, the limits
/// over the points' span, and every working point under `quasi_static`. Untrusted when the
/// method warned.
pub fn result_file(q: &QuasiStatic, opts: &QuasiStaticOptions, name: Option<String>, device: &str) -> ResultFile {
    let fit = Fit {
        trustworthy: Some(q.warnings.is_empty()),
        warnings: Some(q.warnings.iter().map(|w| Warning::new("quasi-static", w.clone())).collect()),
        method: Some(format!(
            "quasi-static point by point (seed paper 3.2.1; IEC 62458 10.2/10.3): offsets by {}, static displacement and force balance for Kms, the small-signal impedance at each point for Bl and Le; power series fitted to the points",
            opts.offset_name()
        )),
        residual_rel: f64::NAN,
        x_range: q.params.x_range.unwrap_or([0.0, 0.0]),
        order: Some(opts.order),
        ..Default::default()
    };
    let lim = coilscope_core::limits::limits(&q.params, fit.x_range);
    let qp = Parameters { name, ..q.params.clone() };
    let mut unc = Uncertainty::new(format!(
        "bands of the series from the working points' sds (each point's small-signal fit, at least {} % of the value), scaled up by the series fit's chi^2 per degree of freedom where above 1",
        100.0 * coilscope_ident::quasi_static::POINT_SD_FLOOR
    ));
    for (which, band) in ["Bl", "Kms", "Le"].iter().zip(&q.bands) {
        unc.set_band(which, band.clone());
    }
    let mut r = ResultFile::new("quasi-static", device, qp, fit, unc, Some(&lim));
    let pressure_of = |force: f64| match opts.offset {
        Offset::Pressure { sd } => force / sd,
        _ => 0.0,
    };
    r.other.insert(
        "quasi_static".into(),
        json!({
            "offset": opts.offset_name(),
            "points": q.points.iter().map(|w| json!({"U_dc": w.u_dc, "I_dc": w.i_dc, "force_N": w.force, "added_mass_kg": w.push.added_mass, "pressure_Pa": pressure_of(w.force), "x_dc": w.x_dc, "Re_dc": w.re_dc, "Bl": w.bl, "Bl_eff": w.bl_eff, "Kms_static": w.kms_static, "k_tangent": w.k_tangent, "k_eff": w.k_eff, "Le": w.le})).collect::<Vec<_>>(),
            "k_dynamic_rest": q.k_dynamic_rest,
            "rest_drift_m": q.rest_drift,
            "hold_s": opts.hold_s,
        }),
    );
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request() -> QuasiRequest {
        QuasiRequest { points: 7, reach: 0.8, hold_s: 1.0, order: 4 }
    }

    #[test]
    fn a_virtual_driver_without_a_range_or_in_a_box_is_refused_by_name() {
        let mut p = coilscope_core::params::embedded_driver("sb17cac35-4").expect("embedded");
        p.x_range = None;
        let e = virtual_options(&p, &request(), "current", "SB17.json").unwrap_err();
        assert!(e.contains("SB17.json") && e.contains("x_range"), "{e}");
        let e = virtual_options(&p, &QuasiRequest { reach: 1.5, ..request() }, "current", "SB17.json").unwrap_err();
        assert!(e.contains("--reach 1.5"), "{e}");
    }

    #[test]
    fn the_pressure_offset_needs_the_diaphragms_area() {
        let mut p = coilscope_core::params::embedded_driver("sb17cac35-4").expect("embedded");
        p.sd = None;
        let e = virtual_options(&p, &request(), "pressure", "SB17.json").unwrap_err();
        assert!(e.contains("Sd"), "{e}");
        let o = virtual_options(&p, &request(), "mass", "SB17.json").expect("mass offset");
        assert_eq!(o.offset, Offset::Mass);
        assert!(o.ac_volts > 0.0 && o.ac_volts <= 1.0);
    }
}

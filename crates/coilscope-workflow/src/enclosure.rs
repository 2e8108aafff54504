//! `coilscope linear --enclosure`: the box a known driver works into, from the driver's
//! impedance in the box ([`coilscope_ident::box_fit`]), with its warnings and verdict.

use crate::linear::LinearInput;
use coilscope_core::result::{Fit, ResultFile, Uncertainty};
use coilscope_core::small_signal::thiele_small;
use coilscope_core::{Complex64, Parameters};
use coilscope_ident::box_fit::{fit_box, BoxChoice, BoxFit};
use coilscope_ident::checks::Warning;

/// How to fit the box.
#[derive(Clone, Debug)]
pub struct BoxRequest {
    pub origin: String,
    pub choice: BoxChoice,
    /// A passive radiator's area (m^2); without it the fit takes Sd and says so.
    pub sp: Option<f64>,
    /// The fitted band (Hz); default: fs / 8 to 12 fs of the driver, within the data.
    pub band: Option<[f64; 2]>,
}

/// The outcome of [`fit_enclosure`].
pub struct BoxOutcome {
    pub fit: BoxFit,
    /// The driver with its box (`enclosure`), as the result carries it.
    pub params: Parameters,
    /// The result file, warnings and verdict attached.
    pub result: ResultFile,
    pub warnings: Vec<Warning>,
    /// Points fitted and the band (Hz).
    pub points: usize,
    pub band: [f64; 2],
}

/// A relative residual above which the box does not explain the impedance (a measured
/// curve's noise and the driver's lumped model stay below 1 %).
pub const RESIDUAL_LIMIT: f64 = 0.02;

/// The largest excursion, as a share of the driver's range, at which a record measures the
/// small-signal box: the box reads small as the level rises (Vb 9 % low at 85-90 % of the
/// range in the independent simulator's records; the error grows as the square of the level,
/// so 0.5 % at a quarter).
pub const LOW_LEVEL: f64 = 0.25;

/// Coherence a record's impedance bin needs to be fitted.
pub const MIN_COHERENCE: f64 = 0.99;

/// The box of `driver` (a parameter set with Sd, measured in free air) from `input`, the
/// driver's impedance in the box (a curve, or a record of voltage and current at a low
/// level).
pub fn fit_enclosure(input: &LinearInput, driver: &Parameters, req: &BoxRequest) -> Result<BoxOutcome, String> {
    if driver.sd.is_none() {
        return Err(format!(
            "{}: the driver's radiating area Sd is needed for the box's volume: give it in the driver's set or with --sd",
            req.origin
        ));
    }
    let f0 = thiele_small(driver).fs;
    let [lo, hi] = req.band.unwrap_or([f0 / 8.0, 12.0 * f0]);
    let (f, z, magnitude_only): (Vec<f64>, Vec<Complex64>, bool) = match input {
        LinearInput::Curve(c) => {
            let keep: Vec<usize> = (0..c.f.len()).filter(|&k| c.f[k] >= lo && c.f[k] <= hi).collect();
            (keep.iter().map(|&k| c.f[k]).collect(), keep.iter().map(|&k| c.z[k]).collect(), c.magnitude_only)
        }
        LinearInput::Record(r) => {
            let fs = r.fs as f64;
            // Bins of fs / 50 at most: a box's resonances are a few Hz wide.
            let seg = ((fs * 50.0 / f0) as usize).next_power_of_two().min(r.u.len() / 3).max(256);
            let h1 = coilscope_ident::linear::h1_impedance(&r.u, &r.i, fs, seg);
            let keep: Vec<usize> = (1..h1.f.len())
                .filter(|&k| h1.f[k] >= lo && h1.f[k] <= hi && h1.coherence[k] > MIN_COHERENCE)
                .collect();
            (keep.iter().map(|&k| h1.f[k]).collect(), keep.iter().map(|&k| h1.z[k]).collect(), false)
        }
    };
    if f.len() < 20 {
        return Err(format!(
            "{}: {} usable points between {lo:.1} and {hi:.1} Hz (the driver's fs is {f0:.1} Hz); a box needs 20 or more around it{}",
            req.origin,
            f.len(),
            if matches!(input, LinearInput::Record(_)) { " with coherence above 0.99: play longer or louder (but low: the cone at a few % of its range)" } else { "" }
        ));
    }
    let fit =
        fit_box(&f, &z, magnitude_only, driver, req.choice, req.sp).map_err(|e| format!("{}: {e}", req.origin))?;
    let mut warnings = Vec::new();
    if !(fit.residual < RESIDUAL_LIMIT) {
        warnings.push(Warning::new(
            "residual-above-noise",
            format!("the {} box leaves {:.1} % of the impedance unexplained: the driver's set is not this driver (measure it in free air first), the data are not of this driver in a box, or the level was high (the box reads small at high level)", fit.enclosure.type_name(), 100.0 * fit.residual),
        ));
    }
    for key in &fit.on_bound {
        warnings.push(Warning::new(
            "on-bound",
            format!("{key} ended on the search's bound: the impedance does not show it"),
        ));
    }
    if fit.sd.iter().any(|(_, sd)| !sd.is_finite()) {
        warnings.push(Warning::new(
            "no-uncertainty",
            "the box's covariance is singular: some of its values are not determined by the data".into(),
        ));
    }
    if fit.sp_assumed {
        warnings.push(Warning::new(
            "radiator-area-assumed",
            "the radiator's area Sp is not known (--sp): Sd was taken for it, so Mmp, Kmp and Rmp are over the wrong area squared; the volume and the radiator's tuning hold".into(),
        ));
    }
    let params = Parameters { enclosure: Some(fit.enclosure.clone()), ..driver.clone() };
    // A record's excursion, from its current through the fitted network.
    let mut x_reached = [0.0, 0.0];
    if let LinearInput::Record(r) = input {
        let x = coilscope_ident::linear::predicted_displacement(&params, &r.i, r.fs as f64);
        x_reached = x.iter().fold([0.0f64, 0.0f64], |[lo, hi], &v| [lo.min(v), hi.max(v)]);
        if let Some([rlo, rhi]) = driver.x_range {
            let share = (x_reached[0] / rlo).max(x_reached[1] / rhi);
            if share > LOW_LEVEL {
                warnings.push(Warning::new(
                    "large-signal-record",
                    format!("the cone reached {:.0} % of the driver's range: the box's small-signal values read off at this level (the volume reads small, about 9 % at 85 %); record at a low level, the cone below {:.0} % of its range", 100.0 * share, 100.0 * LOW_LEVEL),
                ));
            }
        }
    }
    let mut uncertainty = Uncertainty::new("the box's values: the larger of the classical and the clustered sandwich covariance of the relative impedance error; the driver's values are held");
    for (k, sd) in &fit.sd {
        uncertainty.set(k, *sd);
    }
    let band = [f[0], f[f.len() - 1]];
    let fit_record = Fit {
        method: Some(format!("enclosure: {} box, the driver's set held", fit.enclosure.type_name())),
        residual_rel: fit.residual,
        band_hz: Some(band),
        bins: Some(f.len()),
        x_range: x_reached,
        model: format!("enclosure {}", fit.enclosure.type_name()),
        models_note: (!fit.why.is_empty()).then(|| format!("auto: {}; tried {:?}", fit.why, fit.trials)),
        converged: Some(true),
        phase_note: magnitude_only.then(|| "the file has no phase: the box fitted to |Z| alone".to_string()),
        ..Default::default()
    };
    let mut result = ResultFile::new("linear", &req.origin, params.clone(), fit_record, uncertainty, None);
    crate::attach_warnings(&mut result, None, &warnings);
    Ok(BoxOutcome { fit, params, result, warnings, points: f.len(), band })
}

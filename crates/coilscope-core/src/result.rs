//! The identification result file (`"format": "coilscope.result/1"`, `docs/formats.md`)
//! as typed serde structs: `linear`, `identify` and `measure` build a [`ResultFile`], the
//! report and scripts read one back, and every key the contract names is a field here.
//!
//! * Units are SI, as in the parameter set; `limits.Ak` is in %.
//! * A field a command does not produce is absent from its file (`Option`, skipped), so a
//!   linear result has no `thermal` and a result of `identify` no `measurement`.
//! * Reading is lenient where the contract is: every object but `parameters` may be missing,
//!   a `null` number (JSON's NaN) reads as NaN, and keys this version does not know are kept
//!   in [`ResultFile::other`] and written back unchanged.
//! * The standard deviations in [`Uncertainty`] are under the parameter schema's keys
//!   ([`crate::schema`]): `Re`, `Mms`, `creep.lambda`, `L3`, `Le_i` (one per coefficient), and
//!   the curves' bands as `Bl_band`, `Kms_band`, `Le_band`.

use crate::limits::Limits;
use crate::small_signal::ThieleSmall;
use crate::Parameters;
use serde::{Deserialize, Deserializer, Serialize, Serializer};
use std::borrow::Cow;
use std::collections::BTreeMap;

/// The `format` of a result file.
pub const RESULT_FORMAT: &str = "coilscope.result/1";

/// A result file.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ResultFile {
    /// [`RESULT_FORMAT`].
    pub format: String,
    /// `linear` or `large-signal`.
    #[serde(default)]
    pub kind: String,
    /// The recording (path) or the device the result is of.
    #[serde(default)]
    pub recording: String,
    /// The identified parameter set.
    pub parameters: Parameters,
    #[serde(default)]
    pub fit: Fit,
    /// Thiele/Small figures of `parameters` at rest.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub small_signal: Option<ThieleSmall>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub limits: Option<LimitsRecord>,
    #[serde(default)]
    pub uncertainty: Uncertainty,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub thermal: Option<Thermal>,
    /// What a dynamic measurement (`measure`) did.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub measurement: Option<MeasurementRecord>,
    /// The post-inverse estimate with a measured displacement, against this result.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cross_check: Option<CrossCheck>,
    /// The measurement chain, as estimated or calibrated (`docs/formats.md`,
    /// "Extensions").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub chain: Option<crate::chain::Chain>,
    /// Keys this version does not know (written by a newer tool): kept and written back.
    #[serde(flatten)]
    pub other: serde_json::Map<String, serde_json::Value>,
}

/// `fit`: how the parameters were found and how well they explain the record.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(default)]
pub struct Fit {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub method: Option<String>,
    /// `||i_measured - i_model|| / ||i_measured||` over the fitted record.
    #[serde(deserialize_with = "nan_if_null")]
    pub residual_rel: f64,
    /// The residual over its noise floor (`measure`).
    #[serde(skip_serializing_if = "Option::is_none", deserialize_with = "some_nan_if_null")]
    pub residual_excess: Option<f64>,
    /// `[x_min, x_max]` the record reached (m).
    pub x_range: [f64; 2],
    /// Fitted band (Hz), `linear`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub band_hz: Option<[f64; 2]>,
    /// How the fitted band was chosen, `linear` on an impedance curve: where the lumped
    /// model stops holding (cone break-up), or that it holds over the whole curve.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub band_note: Option<String>,
    /// `linear` on an impedance curve without a phase column: how it was fitted (to |Z|
    /// alone). Absent when the file has its phase.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub phase_note: Option<String>,
    /// Frequency bins fitted, `linear`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bins: Option<usize>,
    /// Power-series order of the curves.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub order: Option<usize>,
    /// The model's effects (`LR-2`, `LR-2+creep`, ...).
    pub model: String,
    /// The effect sets tried on held-out data, with their errors.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub models_tried: Option<Vec<ModelTrial>>,
    /// How the online estimator chose its effects (`measure`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub models_note: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub order_trials: Option<Vec<OrderTrial>>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub iterations: Option<usize>,
    /// Online updates (`measure`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub updates: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub converged: Option<bool>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stop_reason: Option<String>,
    /// Integration steps per sample (the residual runs, the Jacobian's runs); `schemes`
    /// says of which method.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub substeps: Option<[usize; 2]>,
    /// The integration scheme of the residual runs and of the Jacobian's: `"rk4"` (classical
    /// RK4 sub-steps) or `"exponential"` (the electrical network integrated exactly).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub schemes: Option<[String; 2]>,
    /// Start of the record left out of the residual while the model settles (s).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub settle_s: Option<f64>,
    /// `linear`: what set the absolute scale.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub scale: Option<Scale>,
    /// `linear`: the motional branch's Res (ohm), Cmes (F), Lces (H).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub motional: Option<BTreeMap<String, f64>>,
    #[serde(rename = "Mms_source", skip_serializing_if = "Option::is_none")]
    pub mms_source: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub noise_floor: Option<NoiseFloor>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub warnings: Option<Vec<Warning>>,
    /// False when there are warnings or the fit did not converge.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub trustworthy: Option<bool>,
}

/// One effect set tried on held-out data.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct ModelTrial {
    pub model: String,
    /// `linear`: the fit's residual with this set.
    #[serde(default, skip_serializing_if = "Option::is_none", deserialize_with = "some_nan_if_null")]
    pub residual_rel: Option<f64>,
    /// `identify`: the error on the held-out part (absent: not fitted, see `screen_gain`).
    #[serde(default, skip_serializing_if = "Option::is_none", deserialize_with = "some_nan_if_null")]
    pub validation_rel: Option<f64>,
    /// `identify`'s effects screen: the most one Gauss-Newton step with the added effect
    /// would lower the estimation part's relative current error by, at the estimate before
    /// it. Below 0.001 the model was not fitted.
    #[serde(default, skip_serializing_if = "Option::is_none", deserialize_with = "some_nan_if_null")]
    pub screen_gain: Option<f64>,
    /// `identify`'s effects search: the model that took the round this one was screened in,
    /// before this one was fitted (its screen gain was more than `EFFECT_RIVAL_RATIO` times
    /// this one's: `coilscope_ident::large`'s constant, 3). This model was not fitted in that
    /// round.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub outscored_by: Option<String>,
    /// `identify`'s effects search: this model's fit went on alone before a trial that had
    /// gone on from it was taken, because that trial's gain was within what this model's own
    /// fit had left to gain; the held-out error before (`validation_rel`: after). The trial
    /// is taken only when it beats this model's new error by the bar.
    #[serde(default, skip_serializing_if = "Option::is_none", deserialize_with = "some_nan_if_null")]
    pub validation_rel_before: Option<f64>,
}

/// One power-series order tried on held-out data.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(default)]
pub struct OrderTrial {
    pub order: usize,
    #[serde(deserialize_with = "nan_if_null")]
    pub estimation_rel: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub validation_rel: f64,
    pub iterations: usize,
}

/// `fit.scale` of a linear result.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Scale {
    /// `mms`, `added-mass` or `displacement`.
    pub method: String,
    #[serde(rename = "Mms", default, skip_serializing_if = "Option::is_none")]
    pub mms: Option<f64>,
    /// The standard deviation (kg) of the given mass (`Mms` given, or the added mass), where
    /// the user gave one (`--mms 15.3g±0.3g`): it is in the sds of what the scale moves.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mass_sd: Option<f64>,
    /// kg.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub added_mass: Option<f64>,
    /// Hz.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fs_with_mass: Option<f64>,
    /// The displacement channel's delay against the current (samples, positive when it
    /// lags: a sensor's own), estimated with the displacement scale and taken out.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sensor_delay_samples: Option<f64>,
}

/// A finding that makes a result doubtful.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Warning {
    /// Stable key for scripts: `residual-above-noise`, `dc-offset-current`, `large-signal-record`,
    /// `current-delay`, `on-bound`, `not-converged`, ...
    pub code: Cow<'static, str>,
    pub message: String,
}

impl Warning {
    pub fn new(code: &'static str, message: String) -> Self {
        Warning { code: Cow::Borrowed(code), message }
    }
}

/// The residual against its noise floor.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize)]
#[serde(default)]
pub struct NoiseFloor {
    /// RMS of the residual (its unit).
    #[serde(rename = "residual_rms", deserialize_with = "nan_if_null")]
    pub rms: f64,
    /// RMS that white noise at the floor would have over the whole band (0 .. fs/2).
    #[serde(deserialize_with = "nan_if_null")]
    pub floor_rms: f64,
    /// `rms / floor_rms`: about 1 for a fit down to the sensor noise.
    #[serde(deserialize_with = "nan_if_null")]
    pub ratio: f64,
    /// Mean of the residual (a DC offset the model cannot make).
    #[serde(deserialize_with = "nan_if_null")]
    pub dc: f64,
}

/// `limits`: XBl, XC, XL, Xsym (m) and Ak (%) over the reached range. A limit beyond the
/// reach is `null`, with `<key>_beyond` the reach.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(default)]
pub struct LimitsRecord {
    #[serde(rename = "XBl")]
    pub xbl: Option<f64>,
    #[serde(rename = "XBl_beyond", skip_serializing_if = "Option::is_none")]
    pub xbl_beyond: Option<f64>,
    #[serde(rename = "XC")]
    pub xc: Option<f64>,
    #[serde(rename = "XC_beyond", skip_serializing_if = "Option::is_none")]
    pub xc_beyond: Option<f64>,
    #[serde(rename = "XL")]
    pub xl: Option<f64>,
    #[serde(rename = "XL_beyond", skip_serializing_if = "Option::is_none")]
    pub xl_beyond: Option<f64>,
    #[serde(rename = "Xsym")]
    pub xsym: Option<f64>,
    #[serde(rename = "Xsym_amplitude", deserialize_with = "nan_if_null")]
    pub xsym_amplitude: f64,
    #[serde(rename = "Ak", deserialize_with = "nan_if_null")]
    pub ak: f64,
    pub range: [f64; 2],
    pub units: BTreeMap<String, String>,
    /// The thresholds: `Bl` (of Bl(0)), `Cms` (of Cms(0)), `Le` (deviation from Le(0)).
    pub thresholds: BTreeMap<String, f64>,
    pub definitions: String,
}

impl From<&Limits> for LimitsRecord {
    fn from(l: &Limits) -> Self {
        let beyond = |v: Option<f64>| v.is_none().then_some(l.reach);
        let th = &l.thresholds;
        LimitsRecord {
            xbl: l.xbl,
            xbl_beyond: beyond(l.xbl),
            xc: l.xc,
            xc_beyond: beyond(l.xc),
            xl: l.xl,
            xl_beyond: beyond(l.xl),
            xsym: l.xsym,
            xsym_amplitude: l.xsym_amplitude,
            ak: l.ak,
            range: l.range,
            units: [("XBl", "m"), ("XC", "m"), ("XL", "m"), ("Xsym", "m"), ("Ak", "%")].iter().map(|(k, u)| (k.to_string(), u.to_string())).collect(),
            thresholds: [("Bl", th.bl), ("Cms", th.cms), ("Le", th.le)].iter().map(|(k, v)| (k.to_string(), *v)).collect(),
            definitions: format!(
                "XBl: min(Bl(x),Bl(-x)) = {:.0} % Bl(0); XC: min(Cms(x),Cms(-x)) = {:.0} % Cms(0); XL: |Le(+-x)/Le(0) - 1| = {:.0} %; Xsym: Bl(s+A) = Bl(s-A) at A = Xsym_amplitude; Ak = (Kms(a)-Kms(-a))/max(Kms(+-a)) at the symmetric reach a",
                100.0 * th.bl,
                100.0 * th.cms,
                100.0 * th.le
            ),
        }
    }
}

/// `uncertainty`: standard deviations under the parameter schema's keys, and bands of the
/// curves on a grid over `fit.x_range`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Uncertainty {
    /// How the numbers were found.
    #[serde(default)]
    pub note: String,
    #[serde(rename = "Bl_band", default, skip_serializing_if = "Option::is_none")]
    pub bl_band: Option<Band>,
    #[serde(rename = "Kms_band", default, skip_serializing_if = "Option::is_none")]
    pub kms_band: Option<Band>,
    #[serde(rename = "Le_band", default, skip_serializing_if = "Option::is_none")]
    pub le_band: Option<Band>,
    /// sd of each value, by key.
    #[serde(flatten)]
    pub sd: BTreeMap<String, Sd>,
}

/// The standard deviation of one value.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Sd {
    /// Of a number (its unit).
    Value(#[serde(deserialize_with = "nan_if_null")] f64),
    /// Of each coefficient of a series (`Le_i`, `Rms_v`); 0 where a coefficient is fixed.
    Coefficients(#[serde(deserialize_with = "nans_if_null")] Vec<f64>),
}

impl Uncertainty {
    pub fn new(note: impl Into<String>) -> Self {
        Uncertainty { note: note.into(), ..Default::default() }
    }

    /// Set the sd of `key`.
    pub fn set(&mut self, key: &str, sd: f64) {
        self.sd.insert(key.to_string(), Sd::Value(sd));
    }

    /// Set the sd of each coefficient of the series `key`.
    pub fn set_coefficients(&mut self, key: &str, sd: Vec<f64>) {
        self.sd.insert(key.to_string(), Sd::Coefficients(sd));
    }

    /// The sd of `key` (a number), if the result has one.
    pub fn value(&self, key: &str) -> Option<f64> {
        match self.sd.get(key) {
            Some(Sd::Value(v)) => Some(*v),
            _ => None,
        }
    }

    /// Carry a moving mass known to `sd_rel` (relative sd) into the sds of what it scales,
    /// each in quadrature with what it had, the scale's share alone under `scale.KEY`: Bl,
    /// Kms, Rms and Mms at rest ([`crate::mass::mass_power`]), and the Bl, Kms and Le bands
    /// at every point, each as the scale moves it ([`crate::mass::curve_mass_sensitivity`]).
    /// For a fit that took the mass as exact; nothing changes at `sd_rel` 0.
    pub fn carry_mass_sd(&mut self, p: &crate::Parameters, sd_rel: f64) {
        if !(sd_rel > 0.0) {
            return;
        }
        for (key, share) in crate::mass::scale_share(p, sd_rel) {
            let had = self.value(key).unwrap_or(0.0);
            self.set(key, had.hypot(share));
            self.set(&format!("scale.{key}"), share);
        }
        for (which, curve) in [("Bl", &p.bl), ("Kms", &p.kms), ("Le", &p.le)] {
            let band = match which {
                "Bl" => self.bl_band.as_mut(),
                "Kms" => self.kms_band.as_mut(),
                _ => self.le_band.as_mut(),
            };
            if let Some(b) = band {
                for ((sd, v), &x) in b.sd.iter_mut().zip(&b.value).zip(&b.x) {
                    let rel = crate::mass::curve_mass_sensitivity(which, curve, x);
                    *sd = sd.hypot(rel * sd_rel * v.abs());
                }
            }
        }
        self.note.push_str(&format!(
            "; the moving mass's sd ({:.2} % of it) carried into Bl, Kms, Rms and Mms and the Bl, Kms and Le bands as the scale moves them (scale.KEY: its share at rest)",
            100.0 * sd_rel
        ));
    }

    /// The band of the curve `which` (`Bl`, `Kms`, `Le`).
    pub fn band(&self, which: &str) -> Option<&Band> {
        match which {
            "Bl" => self.bl_band.as_ref(),
            "Kms" => self.kms_band.as_ref(),
            "Le" => self.le_band.as_ref(),
            _ => None,
        }
    }

    /// Set the band of the curve `which` (`Bl`, `Kms`, `Le`).
    pub fn set_band(&mut self, which: &str, band: Band) {
        match which {
            "Bl" => self.bl_band = Some(band),
            "Kms" => self.kms_band = Some(band),
            "Le" => self.le_band = Some(band),
            other => panic!("set_band: {other} is not a curve with a band (Bl, Kms, Le)"),
        }
    }
}

/// A curve with its standard deviation on a grid of displacements.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Band {
    /// m.
    pub x: Vec<f64>,
    #[serde(deserialize_with = "nans_if_null")]
    pub value: Vec<f64>,
    #[serde(deserialize_with = "nans_if_null")]
    pub sd: Vec<f64>,
}

/// `thermal`: the voice coil's temperature over the record.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(default)]
pub struct Thermal {
    pub note: String,
    /// Time constants of the heating terms in Re(t) (s), `identify`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub heating_terms_tau_s: Option<Vec<f64>>,
    /// `(t s, Re ohm)`, `identify`.
    #[serde(rename = "Re_track", skip_serializing_if = "Option::is_none")]
    pub re_track: Option<Vec<(f64, f64)>>,
    /// Cold Re and its sd (ohm), `measure`.
    #[serde(rename = "Re_cold", skip_serializing_if = "Option::is_none")]
    pub re_cold: Option<f64>,
    #[serde(rename = "Re_cold_sd", skip_serializing_if = "Option::is_none")]
    pub re_cold_sd: Option<f64>,
    /// Re at the end (ohm), `measure`.
    #[serde(rename = "Re_end", skip_serializing_if = "Option::is_none")]
    pub re_end: Option<f64>,
    /// `(t s, rise K)`.
    #[serde(rename = "dT_track")]
    pub dt_track: Vec<(f64, f64)>,
    /// Rise at the end (K).
    #[serde(rename = "dT_end")]
    pub dt_end: Option<f64>,
}

/// `measurement`: what a dynamic measurement did.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct MeasurementRecord {
    /// Largest peak excursion of the live model (m).
    pub x_peak_max: f64,
    /// Largest voice-coil rise (K).
    #[serde(rename = "dTv_max")]
    pub dtv_max: f64,
    /// What held the level (`excursion`, `temperature`, `level`, ...).
    pub limited_by: String,
    pub stop_reason: String,
    pub seconds: f64,
    pub device: String,
    pub excitation: String,
    /// The small-signal stage's set and its Thiele/Small figures.
    pub small_signal: SmallSignalStage,
    /// `(t s, what)`.
    #[serde(default)]
    pub protection_events: Vec<(f64, String)>,
    #[serde(default)]
    pub live_model_resets: usize,
    /// Live distortion (seed paper 4.2), once per second after the small-signal stage: each
    /// nonlinearity's contribution relative to the signal, from the live model.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub distortion: Vec<DistortionPoint>,
    /// The excursion limit in force at the end (m): `--target-x`, or where the estimated
    /// Kms(x)/Kms(0) reaches the stiffness limit; absent when none was set.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub x_limit: Option<f64>,
    /// The voice-coil temperature limit of the run (K, `--max-dt`).
    #[serde(rename = "max_dT", default, skip_serializing_if = "Option::is_none")]
    pub max_dt: Option<f64>,
}

/// `measurement.distortion[]`: `[Bl, Kms, Le]` contributions (RMS over the second, relative
/// to the signal's RMS) in displacement, current and sound pressure (cone acceleration), and
/// the dominant nonlinearity in displacement and in sound pressure.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct DistortionPoint {
    pub t: f64,
    pub x: [f64; 3],
    pub i: [f64; 3],
    pub p: [f64; 3],
    pub dominant_x: String,
    pub dominant_p: String,
}

/// `measurement.small_signal`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SmallSignalStage {
    pub parameters: Parameters,
    pub thiele_small: ThieleSmall,
}

/// `cross_check`: another estimate of the same record.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CrossCheck {
    pub method: String,
    pub parameters: Parameters,
    /// Largest difference over the reached range, relative to this result's value at rest.
    pub max_rel_difference: BTreeMap<String, f64>,
}

/// The result of a measurement that stopped before anything was estimated: no parameters,
/// `fit.trustworthy = false`, and `measurement.error` saying why.
#[derive(Clone, Debug, Serialize)]
pub struct FailedResult {
    pub format: &'static str,
    pub kind: &'static str,
    pub recording: String,
    pub fit: Fit,
    pub measurement: FailedMeasurement,
}

/// `measurement` of a [`FailedResult`].
#[derive(Clone, Debug, Serialize)]
pub struct FailedMeasurement {
    /// `failed`.
    pub stop_reason: &'static str,
    pub error: String,
    pub device: String,
    pub excitation: String,
}

impl FailedResult {
    pub fn new(error: &str, device: &str, excitation: &str) -> Self {
        FailedResult {
            format: RESULT_FORMAT,
            kind: "large-signal",
            recording: device.into(),
            fit: Fit {
                converged: Some(false),
                trustworthy: Some(false),
                stop_reason: Some(error.into()),
                warnings: Some(vec![]),
                ..Default::default()
            },
            measurement: FailedMeasurement {
                stop_reason: "failed",
                error: error.into(),
                device: device.into(),
                excitation: excitation.into(),
            },
        }
    }
}

/// Why a result file could not be read.
#[derive(Debug, thiserror::Error)]
#[error("{message}")]
pub struct ResultError {
    /// Starts with the file's name.
    pub message: String,
}

impl ResultFile {
    /// A result of `kind` (`linear`, `large-signal`) with the figures that follow from the
    /// set: Thiele/Small at rest and, for a reached range, the limits.
    pub fn new(
        kind: &str,
        recording: &str,
        parameters: Parameters,
        fit: Fit,
        uncertainty: Uncertainty,
        limits: Option<&Limits>,
    ) -> Self {
        ResultFile {
            format: RESULT_FORMAT.into(),
            kind: kind.into(),
            recording: recording.into(),
            small_signal: Some(crate::small_signal::thiele_small(&parameters)),
            parameters,
            fit,
            limits: limits.map(LimitsRecord::from),
            uncertainty,
            thermal: None,
            measurement: None,
            cross_check: None,
            chain: None,
            other: Default::default(),
        }
    }

    /// Read a result from JSON text; `origin` names it in errors.
    pub fn from_json_str(text: &str, origin: &str) -> Result<Self, ResultError> {
        let err = |message: String| ResultError { message: format!("{origin}: {message}") };
        let v: serde_json::Value = serde_json::from_str(text).map_err(|e| err(format!("not JSON ({e})")))?;
        Self::from_json_value(v, origin)
    }

    /// Read a result from a JSON value; `origin` names it in errors.
    pub fn from_json_value(v: serde_json::Value, origin: &str) -> Result<Self, ResultError> {
        let err = |message: String| ResultError { message: format!("{origin}: {message}") };
        match v.get("format").and_then(|f| f.as_str()) {
            Some(f) if f == RESULT_FORMAT => {}
            Some(f) if f.starts_with("coilscope.result/") => return Err(err(format!("format {f:?} is a result version this coilscope does not read (it reads {RESULT_FORMAT:?}): a newer coilscope wrote it"))),
            Some(f) => return Err(err(format!("format {f:?} is not a result ({RESULT_FORMAT:?})"))),
            None => return Err(err(format!("no `format` key: a result file has \"format\": {RESULT_FORMAT:?}"))),
        }
        // The parameter set first, for its own errors (they name the key and what is valid).
        let pv = v.get("parameters").ok_or_else(|| err("the result has no `parameters` object".into()))?;
        Parameters::from_json_value(pv, &format!("{origin} (parameters)"))
            .map_err(|e| ResultError { message: e.to_string() })?;
        serde_json::from_value(v)
            .map_err(|e| err(format!("not a valid result ({e}); see docs/formats.md in coilscope's repository")))
    }

    /// As JSON.
    pub fn to_json_value(&self) -> serde_json::Value {
        serde_json::to_value(self).expect("a result always serialises (maps have string keys)")
    }
}

impl Serialize for Parameters {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        self.to_json_value().serialize(s)
    }
}

impl<'de> Deserialize<'de> for Parameters {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let v = serde_json::Value::deserialize(d)?;
        Parameters::from_json_value(&v, "parameters").map_err(serde::de::Error::custom)
    }
}

impl Serialize for ThieleSmall {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        ThieleSmallRecord {
            fs: self.fs,
            qms: self.qms,
            qes: self.qes,
            qts: self.qts,
            cms: self.cms,
            vas: self.vas,
            rms_fs: self.rms_fs,
        }
        .serialize(s)
    }
}

impl<'de> Deserialize<'de> for ThieleSmall {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let r = ThieleSmallRecord::deserialize(d)?;
        Ok(ThieleSmall { fs: r.fs, qms: r.qms, qes: r.qes, qts: r.qts, cms: r.cms, vas: r.vas, rms_fs: r.rms_fs })
    }
}

/// `small_signal` of a result: fs (Hz), Qms, Qes, Qts, Cms (m/N), Vas (m^3, null without Sd),
/// and `Rms_fs` (kg/s): the mechanical resistance at fs, the viscous `Rms` plus creep's loss
/// there, which Qms and Qts include (see [`ThieleSmall`]; NaN when a file predates it).
#[derive(Serialize, Deserialize)]
struct ThieleSmallRecord {
    #[serde(deserialize_with = "nan_if_null")]
    fs: f64,
    #[serde(rename = "Qms", deserialize_with = "nan_if_null")]
    qms: f64,
    #[serde(rename = "Qes", deserialize_with = "nan_if_null")]
    qes: f64,
    #[serde(rename = "Qts", deserialize_with = "nan_if_null")]
    qts: f64,
    #[serde(rename = "Cms", deserialize_with = "nan_if_null")]
    cms: f64,
    #[serde(rename = "Vas", default)]
    vas: Option<f64>,
    #[serde(rename = "Rms_fs", default = "nan", deserialize_with = "nan_if_null")]
    rms_fs: f64,
}

fn nan() -> f64 {
    f64::NAN
}

/// JSON writes NaN as `null`: read it back as NaN.
fn nan_if_null<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

fn some_nan_if_null<'de, D: Deserializer<'de>>(d: D) -> Result<Option<f64>, D::Error> {
    Ok(Some(nan_if_null(d)?))
}

fn nans_if_null<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<f64>, D::Error> {
    Ok(Vec::<Option<f64>>::deserialize(d)?.into_iter().map(|v| v.unwrap_or(f64::NAN)).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A mass's sd joins each sd it scales in quadrature, its share alone under `scale.KEY`,
    /// the bands point by point with the curve's slope; an exact mass changes nothing.
    #[test]
    fn a_masss_sd_joins_what_the_scale_moves() {
        let p = crate::embedded_driver("sb17cac35-4").unwrap();
        let xs = vec![-4e-3, 0.0, 4e-3];
        let band =
            |f: &crate::Poly| Band { x: xs.clone(), value: xs.iter().map(|&x| f.eval(x)).collect(), sd: vec![0.0; 3] };
        let mut u = Uncertainty::new("test");
        u.set("Bl", 0.01);
        u.set("Re", 1e-3);
        for (w, f) in [("Bl", &p.bl), ("Kms", &p.kms), ("Le", &p.le)] {
            u.set_band(w, band(f));
        }
        let before = u.clone();
        u.carry_mass_sd(&p, 0.0);
        assert_eq!(u, before);
        u.carry_mass_sd(&p, 0.02);
        let share = 0.5 * 0.02 * p.bl.c[0];
        assert!((u.value("scale.Bl").unwrap() - share).abs() < 1e-12);
        assert!((u.value("Bl").unwrap() - 0.01f64.hypot(share)).abs() < 1e-12);
        assert!((u.value("Kms").unwrap() - 0.02 * p.kms.c[0]).abs() < 1e-9);
        assert!((u.value("Mms").unwrap() - 0.02 * p.mms).abs() < 1e-15);
        assert_eq!(u.value("Re"), Some(1e-3));
        assert!(u.value("scale.Re").is_none());
        // At rest the bands move by the curve's power; off rest the slope adds its part.
        let kb = u.band("Kms").unwrap();
        assert!((kb.sd[1] - 0.02 * p.kms.c[0]).abs() < 1e-9);
        let (f, df) = p.kms.eval_d(4e-3);
        assert!((kb.sd[2] - (1.0 + 0.5 * 4e-3 * df / f).abs() * 0.02 * f).abs() < 1e-9);
        assert_eq!(u.band("Le").unwrap().sd[1], 0.0);
        assert!(u.band("Le").unwrap().sd[2] > 0.0);
    }

    fn example() -> ResultFile {
        let p = crate::embedded_driver("sb17cac35-4").unwrap();
        let lim = crate::limits::limits(&p, [-3e-3, 3e-3]);
        let mut u = Uncertainty::new("test");
        u.set("Re", 1e-3);
        u.set("Mms", f64::NAN);
        u.set_coefficients("Le_i", vec![0.0, 1e-3, f64::NAN]);
        u.set_band("Bl", Band { x: vec![-1e-3, 0.0, 1e-3], value: vec![5.0, 5.1, f64::NAN], sd: vec![0.01; 3] });
        let fit = Fit {
            residual_rel: 1e-3,
            x_range: [-3e-3, 3e-3],
            model: "LR-2".into(),
            warnings: Some(vec![Warning::new("on-bound", "x".into())]),
            ..Default::default()
        };
        let mut r = ResultFile::new("large-signal", "rec.wav", p, fit, u, Some(&lim));
        r.thermal = Some(Thermal {
            note: "n".into(),
            dt_track: vec![(0.0, 0.0), (1.0, 2.5)],
            dt_end: Some(2.5),
            ..Default::default()
        });
        r
    }

    #[test]
    fn a_result_round_trips_with_nan_as_null_and_every_key_typed() {
        let r = example();
        let v = r.to_json_value();
        assert_eq!(v["format"], RESULT_FORMAT);
        assert!(v["uncertainty"]["Mms"].is_null());
        assert_eq!(v["uncertainty"]["Bl_band"]["value"][2], serde_json::Value::Null);
        assert_eq!(v["limits"]["XBl"], serde_json::Value::Null, "SB17's XBl (5.1 mm) lies beyond 3 mm");
        assert_eq!(v["limits"]["XBl_beyond"], 3e-3);
        assert_eq!(v["thermal"]["dT_track"][1], serde_json::json!([1.0, 2.5]));
        assert!(v.get("measurement").is_none());
        let back = ResultFile::from_json_value(v.clone(), "mem").unwrap();
        assert!(back.other.is_empty(), "{:?}", back.other.keys());
        assert!(back.uncertainty.value("Mms").unwrap().is_nan());
        assert_eq!(back.uncertainty.value("Re"), Some(1e-3));
        assert!(matches!(back.uncertainty.sd.get("Le_i"), Some(Sd::Coefficients(c)) if c.len() == 3 && c[2].is_nan()));
        assert_eq!(back.to_json_value(), v);
    }

    #[test]
    fn unknown_keys_are_kept_and_bad_files_are_named() {
        let mut v = example().to_json_value();
        v["chain"] = serde_json::json!({"delay_i": 1e-5});
        let back = ResultFile::from_json_value(v.clone(), "mem").unwrap();
        assert_eq!(back.to_json_value()["chain"]["delay_i"], 1e-5);
        v["fit"]["x_range"] = "wide".into();
        let e = ResultFile::from_json_value(v, "r.json").unwrap_err().to_string();
        assert!(e.starts_with("r.json: ") && e.contains("invalid type"), "{e}");
        let e = ResultFile::from_json_str(r#"{"format": "coilscope.parameters/1"}"#, "p.json").unwrap_err().to_string();
        assert!(e.contains("p.json") && e.contains("not a result"), "{e}");
        let mut v = example().to_json_value();
        v["format"] = "coilscope.result/2".into();
        let e = ResultFile::from_json_value(v, "new.json").unwrap_err().to_string();
        assert!(e.contains("new.json") && e.contains("\"coilscope.result/2\"") && e.contains("does not read"), "{e}");
    }
}

//! What a measurement is asked and what it gives: the options, the stages and stop reasons,
//! the live state, the trace and the [`Measurement`] with its result file.

use super::*;

/// Options (SI units).
#[derive(Clone, Debug)]
pub struct MeasureOptions {
    /// Moving mass (kg): the absolute scale.
    pub mms: f64,
    /// Target peak excursion (m); `None`: the safe range found from Kms(x).
    pub target_x: Option<f64>,
    /// Largest voice-coil temperature rise (K).
    pub max_dt: f64,
    /// Largest stiffness increase Kms(x)/Kms(0) inside the excursion.
    pub kms_limit: f64,
    /// Largest drive level (V rms).
    pub max_volts: f64,
    /// Level of the small-signal stage (V rms).
    pub start_volts: f64,
    pub small_seconds: f64,
    pub ramp_db_per_s: f64,
    /// Stop without convergence after this long (s).
    pub max_seconds: f64,
    /// Long-term test: run this long (s), whatever the convergence.
    pub duration: Option<f64>,
    /// Long-term test at a fixed level (V rms): the high-pass keeps x in range.
    pub hold_volts: Option<f64>,
    /// Long-term test with a cooling phase: `(after s, V rms)`: from `after` seconds on the
    /// level is held at the lower `V`, so the coil and the magnet cool under a small,
    /// known power. Heating and cooling together separate the coil's path from the magnet's
    /// (the thermal fit's Rtm and Ctm), and cooling at a lower velocity shows convection.
    pub cool: Option<(f64, f64)>,
    /// Block length (s).
    pub block: f64,
    /// Seconds between recursive updates.
    pub update_seconds: f64,
    /// Power-series order.
    pub order: usize,
    /// Set from outside (a Ctrl-C handler) to stop after the current block; the result
    /// keeps the estimate so far, with `StopReason::Interrupted`.
    pub interrupt: Option<std::sync::Arc<std::sync::atomic::AtomicBool>>,
    /// Temperature coefficient of the coil's resistance (1/K).
    pub alpha: f64,
    /// Cut-off of the excitation's high-pass at the start (Hz).
    pub hp_hz: f64,
}

impl Default for MeasureOptions {
    fn default() -> Self {
        MeasureOptions {
            mms: f64::NAN,
            target_x: None,
            max_dt: 50.0,
            kms_limit: 2.0,
            max_volts: 20.0,
            start_volts: 0.2,
            small_seconds: 2.0,
            ramp_db_per_s: 3.0,
            max_seconds: 60.0,
            duration: None,
            hold_volts: None,
            cool: None,
            block: 0.1,
            update_seconds: 1.0,
            order: 6,
            interrupt: None,
            alpha: 0.00393,
            hp_hz: 5.0,
        }
    }
}

impl MeasureOptions {
    /// Check the limits; the message names the option and what is valid.
    pub fn validate(&self) -> Result<(), String> {
        let check = |ok: bool, msg: String| if ok { Ok(()) } else { Err(msg) };
        check(
            self.mms.is_finite() && self.mms > 0.0 && self.mms < 2.0,
            format!("--mms {} kg is not valid (0 .. 2 kg; give kg, not g)", self.mms),
        )?;
        if let Some(x) = self.target_x {
            check(
                x.is_finite() && x > 0.0 && x < 0.1,
                format!("--target-x {} mm is not valid (0 .. 100 mm)", x * 1e3),
            )?;
        }
        check(
            self.max_dt.is_finite() && self.max_dt > 0.0 && self.max_dt <= 300.0,
            format!("--max-dt {} K is not valid (0 .. 300 K)", self.max_dt),
        )?;
        check(
            self.kms_limit.is_finite() && self.kms_limit > 1.0,
            format!("--kms-limit {} is not valid (> 1, e.g. 2)", self.kms_limit),
        )?;
        check(
            self.max_volts.is_finite() && self.max_volts > 0.0 && self.max_volts <= 1000.0,
            format!("--max-volts {} V is not valid (more than 0, at most 1000 V rms)", self.max_volts),
        )?;
        check(
            self.start_volts > 0.0 && self.start_volts <= self.max_volts,
            format!(
                "--start-volts {} V is not valid (more than 0, at most --max-volts {} V)",
                self.start_volts, self.max_volts
            ),
        )?;
        if let Some(d) = self.duration {
            check(
                d.is_finite() && d >= self.small_seconds + 1.0,
                format!("--duration {d} s is not valid (at least {} s)", self.small_seconds + 1.0),
            )?;
        }
        if let Some(v) = self.hold_volts {
            check(
                v > 0.0 && v <= self.max_volts,
                format!("--volts {v} V is not valid (more than 0, at most --max-volts {} V)", self.max_volts),
            )?;
        }
        if let Some((after, v)) = self.cool {
            let (d, hold) = (self.duration.unwrap_or(0.0), self.hold_volts.unwrap_or(0.0));
            check(
                self.duration.is_some() && self.hold_volts.is_some(),
                "--cool-after/--cool-volts need a long-term test at a fixed level (--duration S --volts V)".to_string(),
            )?;
            check(
                after.is_finite() && after > self.small_seconds && after < d,
                format!(
                    "--cool-after {after} s is not valid (between the small-signal stage, {} s, and --duration {d} s)",
                    self.small_seconds
                ),
            )?;
            check(
                v.is_finite() && v > 0.0 && v < hold,
                format!("--cool-volts {v} V is not valid (0 .. --volts {hold} V: the cooling level is the lower one)"),
            )?;
        }
        check((2..=8).contains(&self.order), format!("--order {} is not valid (2 ..= 8)", self.order))?;
        check(
            self.max_seconds >= self.small_seconds + 2.0,
            format!("--max-seconds {} s is not valid (at least {} s)", self.max_seconds, self.small_seconds + 2.0),
        )?;
        Ok(())
    }
}

/// Stage of the measurement.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stage {
    Small,
    Ramp,
    Hold,
}

impl Stage {
    pub fn name(&self) -> &'static str {
        match self {
            Stage::Small => "small-signal",
            Stage::Ramp => "ramp",
            Stage::Hold => "hold",
        }
    }
}

/// What limits the drive level (or holds it) at a block.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LimitedBy {
    /// The quiet small-signal stage.
    SmallSignal,
    /// Nothing: the level rises.
    Ramp,
    /// The excursion limit (target or stiffness limit): the gain is held or cut.
    Excursion,
    /// The excursion limit in a long-term test at a fixed level: the high-pass is raised.
    ExcursionHighPass,
    /// The ramp explores in steps toward the stiffness limit.
    Exploration,
    /// The ramp waits for the estimate: the last update still moved the curves by more than
    /// [`RAMP_SETTLE`] within the reach.
    Settling,
    /// The voice-coil temperature limit.
    Temperature,
    /// `max_volts`.
    MaxVolts,
    /// A replay: the level was set when it was recorded.
    Replay,
}

impl LimitedBy {
    /// The name written to result files and shown on the terminal.
    pub fn name(&self) -> &'static str {
        match self {
            LimitedBy::SmallSignal => "small-signal stage",
            LimitedBy::Ramp => "ramp",
            LimitedBy::Excursion => "excursion",
            LimitedBy::ExcursionHighPass => "excursion (high-pass)",
            LimitedBy::Exploration => "exploration",
            LimitedBy::Settling => "settling",
            LimitedBy::Temperature => "temperature",
            LimitedBy::MaxVolts => "max-volts",
            LimitedBy::Replay => "replay",
        }
    }
}

/// Why a measurement stopped.
#[derive(Clone, Debug, PartialEq)]
pub enum StopReason {
    /// The estimate converged (held-out check passed); `updates`: the stable updates.
    Converged { t: f64, residual: f64, updates: usize },
    /// `max_seconds` passed without convergence.
    NoConvergence { max_seconds: f64 },
    /// A long-term test ran its duration.
    DurationOver { seconds: f64 },
    /// The replayed recording ended before convergence.
    ReplayEnded { seconds: f64 },
    /// The device returned an empty block.
    DeviceEmpty,
    /// Stopped from outside (Ctrl-C).
    Interrupted { t: f64 },
    /// The device or the live model failed after the estimate existed: the estimate so far is
    /// kept, and the message says what happened.
    Failed { t: f64, message: String },
}

impl StopReason {
    /// Short key for result files and the database (`measurement.stop_reason`).
    pub fn key(&self) -> &'static str {
        match self {
            StopReason::Converged { .. } => "converged",
            StopReason::NoConvergence { .. } => "no-convergence",
            StopReason::DurationOver { .. } => "duration-over",
            StopReason::ReplayEnded { .. } => "replay-ended",
            StopReason::DeviceEmpty => "device-empty",
            StopReason::Interrupted { .. } => "interrupted",
            StopReason::Failed { .. } => "failed",
        }
    }

    /// Whether the run did what was asked (converged, or a long-term test ran its course).
    pub fn is_success(&self) -> bool {
        matches!(self, StopReason::Converged { .. } | StopReason::DurationOver { .. })
    }

    /// One sentence for people, naming what to do where something can be done.
    pub fn describe(&self) -> String {
        match self {
            StopReason::Converged { t, residual, updates } => format!(
                "converged after {t:.1} s: window residual {residual:.2e}, Bl/Kms curves changed by < {} % and Le by < {} % (over 90 % of the range the driver keeps visiting at the final level) at each of the last {updates} updates, and their bands are within {:.2} % (Bl, Kms) and {:.2} % (Le) of the values at rest",
                100.0 * CONVERGED_BL_KMS,
                100.0 * CONVERGED_LE,
                100.0 * CONVERGED_SD_BL_KMS,
                100.0 * CONVERGED_SD_LE
            ),
            StopReason::NoConvergence { max_seconds } => format!("no convergence within {max_seconds} s (--max-seconds): the best estimate is kept; raise --max-seconds, or check the residual and warnings"),
            StopReason::DurationOver { seconds } => format!("long-term test: the duration of {seconds} s is over"),
            StopReason::ReplayEnded { seconds } => {
                format!("the replayed recording ended after {seconds:.1} s before the estimate converged: the best estimate is kept; a replay needs about 2 s of quiet (small-signal) lead-in, then 8 s or more at high level")
            }
            StopReason::DeviceEmpty => "the device delivered no samples".into(),
            StopReason::Interrupted { t } => format!("interrupted at {t:.1} s: the estimate so far is kept"),
            StopReason::Failed { t, message } => format!("failed at {t:.1} s: {message}; the estimate so far is kept (not trustworthy)"),
        }
    }
}

impl std::fmt::Display for LimitedBy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::fmt::Display for StopReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.describe())
    }
}

/// What observers see after every block.
#[derive(Clone, Debug)]
pub struct Live {
    pub t: f64,
    pub stage: Stage,
    /// Drive level (V rms of the unit signal times the gain).
    pub volts: f64,
    pub f_hp: f64,
    /// Live model displacement over the block (m).
    pub x_min: f64,
    pub x_max: f64,
    /// Estimated voice-coil temperature rise (K) and Re (ohm).
    pub dtv: f64,
    pub re: f64,
    /// Current error of the live model over the block.
    pub residual: f64,
    /// Excursion limit in force (m).
    pub x_limit: Option<f64>,
    /// What limits the level now.
    pub limited_by: LimitedBy,
    /// Whether a recursive update ran after this block, and its window residual.
    pub update: Option<f64>,
    /// After an update: the new estimate, and the largest change of Bl/Kms and of Le since
    /// the previous one (relative to the value at rest, over 90 % of the range).
    pub estimate: Option<Parameters>,
    pub change: Option<(f64, f64)>,
    /// The block's live distortion (after the small-signal stage).
    pub distortion: Option<coilscope_analysis::live_distortion::Contributions>,
    /// The block's signals, as envelopes: the measured u and i, and the live model's x and v
    /// (empty during the small-signal stage, before there is a model).
    pub trace: Trace,
    /// After an update: Bl, Kms and Le with their sds on [`LIVE_BAND_POINTS`] points over
    /// the estimator's reach (the bands the result will carry, as they converge).
    pub bands: Vec<(&'static str, coilscope_core::result::Band)>,
    /// Seconds until the run is expected to converge, from the rate its bands narrow at the
    /// held level (a run of fixed duration: until its end); `None` while the level still
    /// moves or before the first bands.
    pub eta: Option<f64>,
    /// When the run stops at the latest (s): `--max-seconds`, or the fixed duration.
    pub end: f64,
}

/// Bins of a block's [`Trace`].
pub const TRACE_BINS: usize = 20;
/// Points of a band ([`Live::bands`], and the result's).
pub const LIVE_BAND_POINTS: usize = 41;

/// A block's signals for a live view: the minimum and maximum over each of [`TRACE_BINS`]
/// equal parts of the block (an envelope keeps every crest a plain decimation would skip).
#[derive(Clone, Debug, Default)]
pub struct Trace {
    /// Seconds one bin spans.
    pub dt: f64,
    /// Voltage (V) and current (A) as measured.
    pub u: Vec<[f64; 2]>,
    pub i: Vec<[f64; 2]>,
    /// The live model's displacement (m) and velocity (m/s).
    pub x: Vec<[f64; 2]>,
    pub v: Vec<[f64; 2]>,
}

/// Bl, Kms and Le of `p` with the online estimator's sds on `xs`: the result's bands, and
/// the live page's as they converge. Each sd holds the estimator's statistical one and, in
/// quadrature, the systematic part `identify`'s bands carry
/// ([`coilscope_ident::large::CURVE_SYSTEMATIC_REL`] of the value: what the model's
/// discretisation leaves against an independent simulator).
///
/// And the last update's step from `prev`, the estimate before it, at each point.
///
/// The Le band also carries `le_model_rel` of the value: how far the small-signal stage's Le
/// moved to a model with more effects that fitted it as well ([`LinearFit::le_model_rel`];
/// the online estimator keeps the stage's model, so the data never chose between the two).
///
/// [`LinearFit::le_model_rel`]: coilscope_ident::linear::LinearFit::le_model_rel
pub(super) fn curve_bands(
    p: &Parameters,
    prev: Option<&Parameters>,
    on: &Online,
    xs: &[f64],
    le_model_rel: f64,
) -> [(&'static str, Band); 3] {
    let sys = coilscope_ident::large::CURVE_SYSTEMATIC_REL;
    [("Bl", &p.bl), ("Kms", &p.kms), ("Le", &p.le)].map(|(which, f)| {
        let value: Vec<f64> = xs.iter().map(|&x| f.eval(x)).collect();
        let model = if which == "Le" { le_model_rel } else { 0.0 };
        // The last update's step at each point, in quadrature: a recursive estimate that
        // still moves there is not at its posterior, whatever its covariance says (at the
        // edges of a microspeaker's reach, where its stiffness doubles, the estimate lagged
        // the data by 0.3-0.5 % with an sd of 0.06 %).
        let step = |x: f64| {
            prev.map_or(0.0, |q| {
                let g = match which {
                    "Bl" => &q.bl,
                    "Kms" => &q.kms,
                    _ => &q.le,
                };
                (f.eval(x) - g.eval(x)).abs()
            })
        };
        let sd = xs
            .iter()
            .zip(&value)
            .map(|(&x, v)| on.curve_sd(which, x).hypot(sys * v).hypot(model * v).hypot(step(x)))
            .collect();
        (which, Band { x: xs.to_vec(), value, sd })
    })
}

/// `[min, max]` of each of `bins` equal parts of `s` (fewer when `s` is shorter).
pub fn envelope(s: impl ExactSizeIterator<Item = f64> + Clone, bins: usize) -> Vec<[f64; 2]> {
    let n = s.len();
    let bins = bins.min(n);
    let mut out = vec![[f64::INFINITY, f64::NEG_INFINITY]; bins];
    for (k, v) in s.enumerate() {
        let b = &mut out[k * bins / n];
        b[0] = b[0].min(v);
        b[1] = b[1].max(v);
    }
    out
}

/// The outcome.
pub struct Measurement {
    pub params: Parameters,
    /// Small-signal parameters from the first stage.
    pub small: Parameters,
    pub online: Online,
    pub converged: bool,
    pub stop_reason: StopReason,
    pub seconds: f64,
    /// Range of x the live model reached at the final level (m).
    pub x_range: [f64; 2],
    pub x_peak_max: f64,
    pub dtv_max: f64,
    /// Cold voice-coil resistance (ohm): the small-signal stage's record fitted with the final
    /// model when the run converged (`coilscope_ident::online::fit_re`, heating within the
    /// stage removed), otherwise the stage's impedance fit; the reference of the temperature
    /// estimate.
    pub re_cold: f64,
    /// Standard deviation of `re_cold` (ohm; NaN when it came from no fit).
    pub re_cold_sd: f64,
    /// Le's model uncertainty from the small-signal stage (relative; in the Le band):
    /// [`coilscope_ident::linear::LinearFit::le_model_rel`].
    pub le_model_rel: f64,
    /// The estimate before the last update (its step widens the bands where it still
    /// moved), when there was one.
    pub before_last: Option<Parameters>,
    /// Voice-coil resistance at the end of the run (ohm): hot.
    pub re_end: f64,
    /// Temperature coefficient of the coil's resistance used for the rise (1/K).
    pub alpha: f64,
    /// Last window residual.
    pub residual_rel: f64,
    /// Relative current error above the noise floor on the last held-out window.
    pub residual_excess: f64,
    pub updates: usize,
    /// What limited the drive level at the end (excursion, temperature, ...).
    pub limited_by: LimitedBy,
    /// Protection events: (t, what).
    pub events: Vec<(f64, String)>,
    /// (t, dT) once per second.
    pub dt_track: Vec<(f64, f64)>,
    /// The two-node thermal model fitted to the run's tracked rise and powers (a run of at
    /// least [`THERMAL_FIT_MIN_S`]); also in `params.thermal`. `Err`: why it was not fitted.
    pub thermal_fit: Option<Result<coilscope_ident::thermal::ThermalFit, String>>,
    /// What the thermal fit saw: every block after the small-signal stage.
    pub thermal_track: coilscope_ident::thermal::ThermalTrack,
    /// Live distortion, one point per second ([`coilscope_analysis::live_distortion`]).
    pub distortion: Vec<coilscope_core::result::DistortionPoint>,
    /// The excursion limit in force at the end (m), and the temperature limit (K).
    pub x_limit: Option<f64>,
    pub max_dt: f64,
    pub truth: Option<Truth>,
    pub excitation: String,
    pub device: String,
    pub mms_source: String,
    /// The model reported (`fit.model`): the estimator's, less the large-signal effects the
    /// data did not show ([`Online::insignificant_effects`], named in `dropped`).
    pub effects: Effects,
    pub dropped: Effects,
}

/// Seconds at the end of the small-signal stage in which the drive fades out (raised cosine)
/// and then stays silent, so that the record the impedance fit sees starts and ends at rest:
/// its whole-record DFT relation `I = U / Z` is then exact. A record cut off in motion
/// carries a transient that the fit otherwise takes up in the LR-2 branch (18WU: Re -> 0,
/// L2 = 0.96 H).
pub(super) const SMALL_FADE_S: f64 = 0.1;
pub(super) const SMALL_REST_S: f64 = 0.3;

/// Fade-out and rest at the end of the small-signal stage; `start` is the absolute index of
/// `drive[0]`.
pub(super) fn small_stage_envelope(drive: &mut [f64], start: usize, fs: f64, small_seconds: f64) {
    let fade_at = small_seconds - SMALL_REST_S - SMALL_FADE_S;
    for (k, v) in drive.iter_mut().enumerate() {
        let t = (start + k) as f64 / fs - fade_at;
        if t > 0.0 {
            *v *= if t < SMALL_FADE_S { 0.5 + 0.5 * (std::f64::consts::PI * t / SMALL_FADE_S).cos() } else { 0.0 };
        }
    }
}

/// `Some(reach)` (m) when a record's first seconds are large-signal: the linear fit's error
/// is explained by the large-signal terms (`coilscope_ident::linear::linear_warnings`).
pub(super) fn loud_start(
    lin: &coilscope_ident::linear::LinearFit,
    p: &Parameters,
    u: &[f64],
    i: &[f64],
    fs: f64,
) -> Option<f64> {
    let (_, w) = coilscope_ident::linear::linear_warnings(lin, p, u, i, fs);
    w.iter()
        .any(|w| w.code == "large-signal-record")
        .then(|| coilscope_ident::linear::predicted_displacement(p, i, fs).iter().fold(0.0f64, |a, v| a.max(v.abs())))
}

/// The batch large-signal fit (`coilscope identify`, order 4) of a record's first seconds, as
/// the online estimator's start, with the sd of its Re (ohm) and the reach (m); `None` if it
/// cannot be made (the linear start is kept).
pub(super) fn batch_start(u: &[f64], i: &[f64], fs: f64, mms: f64) -> Option<(Parameters, f64, f64)> {
    use coilscope_ident::large::{identify, IdentifyError, IdentifyOptions};
    // The LR-2 model: the online estimator has no creep or LR-3 yet.
    let opts = IdentifyOptions {
        mms,
        order: Some(4),
        effects: EffectsChoice::Fixed(Effects::NONE),
        chain: false,
        ..Default::default()
    };
    let fit = match identify(u, i, fs, "replay start", &opts, |_| {}) {
        Ok(f) => f,
        Err(IdentifyError::NotConverged { best, .. }) => *best,
        Err(_) => return None,
    };
    let re_sd = fit.sd().iter().find(|(k, _)| *k == "Re").map_or(f64::NAN, |(_, v)| *v);
    let reach = fit.x_range[1].max(-fit.x_range[0]);
    Some((Parameters { x_range: None, ..fit.params }, re_sd, reach))
}

impl Measurement {
    /// What makes the result doubtful, named (empty for a converged fit to the noise).
    /// What the estimator did with the effects it was offered beyond those reported.
    pub fn models_note(&self) -> String {
        let mut notes = vec![];
        if self.dropped != Effects::NONE {
            notes.push(format!(
                "estimated with {} as well; within {} sd of none, not reported",
                self.dropped.in_words(),
                coilscope_ident::online::INSIGNIFICANT_SD
            ));
        }
        if notes.is_empty() {
            "every effect estimated is reported".to_string()
        } else {
            notes.join("; ")
        }
    }

    pub fn warnings(&self) -> Vec<coilscope_ident::checks::Warning> {
        let mut w = Vec::new();
        if self.residual_excess.is_finite() && self.residual_excess > CONVERGED_EXCESS {
            w.push(coilscope_ident::checks::Warning::new(
                "residual-above-noise",
                format!(
                    "the final model leaves {:.2} % of the current unexplained above the noise floor on data it had not seen (converged fits leave < {} %): the curves do not describe this driver. {}",
                    100.0 * self.residual_excess,
                    100.0 * CONVERGED_EXCESS,
                    if self.online.resets > 0 || !self.device.starts_with("virtual") {
                        "Likely causes: a record that starts loud (the start model is a linear fit of large-signal data: give a record with 2 s of quiet lead-in), a wiring or chain problem, or a driver with effects the model lacks"
                    } else {
                        "Likely causes: a measurement stopped before the estimate settled, or a driver with effects the model lacks"
                    }
                ),
            ));
        }
        w
    }

    /// The result file (`coilscope.result/1`, plus `measurement.*`).
    pub fn result(&self) -> ResultFile {
        let mut unc = Uncertainty::new("standard deviations from the online estimator's covariance (information from every window; sensor noise and the residual's level; Mms taken as exact). Bands: value and sd on a grid over fit.x_range");
        let [lo, hi] = self.x_range;
        let xs: Vec<f64> =
            (0..LIVE_BAND_POINTS).map(|k| lo + (hi - lo) * k as f64 / (LIVE_BAND_POINTS - 1) as f64).collect();
        for (which, band) in curve_bands(&self.params, self.before_last.as_ref(), &self.online, &xs, self.le_model_rel)
        {
            unc.set_band(which, band);
        }
        // Re is the cold value: its sd is the small-signal fit's. Of the rest, the effects the
        // final model keeps.
        unc.set("Re", self.re_cold_sd);
        if let Some(Ok(f)) = &self.thermal_fit {
            for (k, name) in coilscope_ident::thermal::ThermalFit::NAMES.iter().enumerate() {
                unc.set(&format!("thermal.{name}"), f.sd[k]);
            }
            if let Some((_, sd)) = f.rv {
                unc.set("thermal.rv", sd);
            }
        }
        let kept = self.effects.keys();
        self.online.layout.uncertainties(
            &self.online.theta,
            &|j, k| self.online.cov[(j, k)],
            &|e| kept.contains(&e.key),
            &mut unc,
        );
        let warnings = self.warnings();
        let fit = Fit {
            method: Some("online recursive output error (parallel model, exact Jacobians on sliding windows, Kalman update of the parameters)".into()),
            residual_rel: self.residual_rel,
            residual_excess: Some(self.residual_excess),
            trustworthy: Some(self.converged && warnings.is_empty()),
            warnings: Some(warnings),
            x_range: self.x_range,
            order: Some(self.online.layout.order),
            model: self.effects.model_name(),
            models_note: Some(self.models_note()),
            converged: Some(self.converged),
            stop_reason: Some(self.stop_reason.describe()),
            updates: Some(self.updates),
            mms_source: Some(self.mms_source.clone()),
            ..Default::default()
        };
        let lim = coilscope_core::limits::limits(&self.params, self.x_range);
        let mut r = ResultFile::new("large-signal", &self.device, self.params.clone(), fit, unc, Some(&lim));
        r.thermal = Some(Thermal {
            note: format!(
                "voice-coil temperature rise from the tracked Re: (Re(t)/Re_cold - 1)/alpha, alpha = {} 1/K; Re_cold is the small-signal stage's record refitted with the final model when converged, else the stage's impedance fit{}",
                self.alpha,
                match &self.thermal_fit {
                    Some(Ok(f)) if !f.convection_note.is_empty() => format!(". Thermal fit: {}", f.convection_note),
                    Some(Err(e)) => format!(". No thermal parameters: the thermal fit failed: {e}"),
                    None => format!(". No thermal parameters: the run was shorter than the thermal fit's {THERMAL_FIT_MIN_S} s"),
                    _ => String::new(),
                }
            ),
            re_cold: Some(self.re_cold),
            re_cold_sd: Some(self.re_cold_sd),
            re_end: Some(self.re_end),
            dt_end: Some((self.re_end / self.re_cold - 1.0) / self.alpha),
            dt_track: self.dt_track.clone(),
            ..Default::default()
        });
        r.measurement = Some(MeasurementRecord {
            x_peak_max: self.x_peak_max,
            dtv_max: self.dtv_max,
            limited_by: self.limited_by.name().into(),
            stop_reason: self.stop_reason.key().into(),
            seconds: self.seconds,
            device: self.device.clone(),
            excitation: self.excitation.clone(),
            small_signal: SmallSignalStage {
                parameters: self.small.clone(),
                thiele_small: coilscope_core::small_signal::thiele_small(&self.small),
            },
            protection_events: self.events.clone(),
            live_model_resets: self.online.resets,
            distortion: self.distortion.clone(),
            x_limit: self.x_limit,
            max_dt: Some(self.max_dt),
        });
        r
    }
}

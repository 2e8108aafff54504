//! The measurement: a pure loop over blocks (source -> high-pass -> gain -> device ->
//! online identification -> controller), with observers for the terminal and the database.
//!
//! Stages:
//! 1. **Small**: the first [`MeasureOptions::small_seconds`] at `start_volts`: the linear
//!    (impedance) fit gives the small-signal parameters, the start of the online estimator.
//! 2. **Ramp**: the gain rises by [`MeasureOptions::ramp_db_per_s`] while the online
//!    estimator follows, until a limit binds: the target excursion (`target_x`, or the safe
//!    range where Kms(x)/Kms(0) reaches `kms_limit`), the voice-coil temperature rise
//!    `max_dt`, or `max_volts`. The ramp never outruns its estimate: the level aims at most
//!    1.6 times (1.25 times near the stiffness limit) past the reach the last update checked
//!    (a trust region: beyond it the curves are extrapolated), and it waits while the last
//!    update still moved the curves by more than [`RAMP_SETTLE`] or the estimate missed more
//!    than [`RAMP_EXCESS`] of the held-out current (`LimitedBy::Settling`). The peak memory
//!    starts with the small stage's crests (the noise repeats every 8 s), and the series
//!    basis is scaled to the linear reach at 4 V, whatever the start level.
//! 3. **Hold**: at that level until the estimate has converged (window residual below 2 %,
//!    curves changing by less than 0.3 % (Bl, Kms) and 1 % (Le) at two updates, over 90 %
//!    of the 80th percentile of the block peaks since the level was last changed), or for
//!    `duration` in a long-term test. A change of level by more than 5 % restarts the hold.
//!
//! Music does not excite every band the small-signal impedance fit needs (Re and the L2/R2
//! branch are told apart only by a broad spectrum), so under music the small-signal stage
//! plays quiet IEC noise; the music starts with the ramp.
//!
//! Protection acts on every block: the live model's peak excursion is compared with the
//! limit and the gain cut at once when it is passed; the temperature (from the tracked Re)
//! carried one second ahead along its trend (the tracking lag), holds the gain at 85 % of
//! `max_dt` and cuts it (power ~ gain^2) above 92 %, waiting the tracking lag before cutting
//! again. The temperature reference is the small-signal fit's Re; the published cold Re is that
//! stage's record refitted with the final model (`coilscope_ident::online::fit_re`). In a
//! long-term test at a fixed level (`hold_volts`) the excursion is kept in range by raising
//! the cut-off of the high-pass instead, so the electrical power stays.

use crate::device::{Device, Truth};
use crate::signal::{HighPass, Source};
use crate::store::{StateRow, Store};
use coilscope_core::excitation::Excitation;
use coilscope_core::params::Parameters;
use coilscope_core::poly::Poly;
use coilscope_core::result::{Band, Fit, MeasurementRecord, ResultFile, SmallSignalStage, Thermal, Uncertainty};
use coilscope_ident::linear::{fit_linear_record, scale_by_mms, Effects, EffectsChoice, Ends, LinearOptions};

/// The small stage's linear fit: ends free (a replay's first seconds are cut from the running
/// record; a controlled stage fades out with the cone still moving a little), creep and LR-3
/// chosen by the data as in `linear`; the online estimator keeps what it chose, and adds
/// creep (when the stage found none), Le(i) and Rms(v) (see [`OnlineOptions::effects`]).
/// Seconds at full level (stage Hold) after which the online estimator stops estimating the
/// large-signal effects the data have not shown ([`Online::drop_effects`]): the time the
/// convergence test waits as well.
const PRUNE_AFTER_HOLD_S: f64 = 2.0;
const SMALL_STAGE_FIT: LinearOptions = LinearOptions { ends: Ends::Fitted, effects: EffectsChoice::Auto, chain: false };
use coilscope_ident::online::{Online, OnlineOptions};

/// Seconds of peak-excursion memory of the controller.
const PEAK_MEMORY_S: f64 = 8.0;
/// Share of the excursion limit the controller aims the largest remembered peak at.
const X_AIM: f64 = 0.92;
/// Near the stiffness limit (Kms ratio past 3/4 of the way to it), the aim stays within
/// this multiple of the reach the last update checked for the stiffness limit.
const EXPLORE: f64 = 1.25;
/// Far from it (Kms ratio below half the way to it), the aim stays within this multiple.
const EXPLORE_FAR: f64 = 1.6;
/// The ramp raises the level only while the estimate keeps up with it: while the last update
/// moved Bl(x) or Kms(x) by more than this (relative to the value at rest, within the reach),
/// the level holds. The curves at the edge of the reach are extrapolated until the data there
/// has been seen often enough; a ramp that outruns them finds the stiffness limit only after
/// it has passed it (SB17 started at 0.5 V: the update at 11.1 s moved Kms by 10 %, the driver
/// reached 6 mm against a limit at 5 mm).
pub const RAMP_SETTLE: f64 = 0.03;
/// The same while the estimate misses more than this share of the current (above the noise
/// floor) on the held-out window before the last update: it has fallen behind the level.
pub const RAMP_EXCESS: f64 = 0.01;
/// The largest basis scale of the curves, in small-signal reaches.
const X_REF_SMALL: f64 = 20.0;
/// A measurement's basis scale: the linear response's reach at this drive level (V rms).
const X_REF_VOLTS: f64 = 4.0;

/// A replay's restart: when the window error before an update passes RESTART_RESIDUAL, the
/// estimator restarts from a batch fit of the last RESTART_S seconds, at most MAX_RESTARTS
/// times.
const RESTART_RESIDUAL: f64 = 0.1;
const RESTART_S: f64 = 2.0;
const MAX_RESTARTS: usize = 3;

/// Seconds of data per recursive update.
const ONLINE_WINDOW_S: f64 = 0.3;
/// Drift of the values at rest per sqrt(second) in a long-term test (relative): a ferrite
/// magnet's Bl falls by about 0.2 % per kelvin, and a suspension softens as it warms.
const LONG_TERM_DRIFT: f64 = 1e-4;
/// Drift of the values at rest per kelvin of the coil's rise (relative sd): the suspension
/// and the magnet change by 0.1-0.2 % per kelvin of their own, and within seconds they see
/// about a tenth of the coil's rise. On a coil heating 3 K a second (a microspeaker) the
/// estimate must follow: without it the fast-heating microspeaker's bands held the truth
/// within 2 sd on 54-86 % of their points.
const DRIFT_PER_KELVIN: f64 = 1e-4;
/// Largest relative current error of the live model over a block for its x to count as reached.
const TRACKING_RESIDUAL: f64 = 0.2;

/// Seconds of temperature estimates the trend is taken over, and how far ahead (s) the
/// protection looks along it (about the lag of the Re tracking).
const THERMAL_TREND_S: f64 = 1.0;
const THERMAL_LAG_S: f64 = 1.0;

/// Convergence: largest change of Bl(x), Kms(x) and of Le(x) per update (relative to the
/// value at rest), at each of the last two updates.
const CONVERGED_BL_KMS: f64 = 0.003;
const CONVERGED_LE: f64 = 0.01;
/// Convergence: largest relative current error above the noise floor on the held-out window
/// (the window before an update, which the previous estimate has not seen). Good fits of the
/// virtual drivers sit at 0.07-0.2 %; a replay started from a linear fit of large-signal data
/// that "converged" with Kms 43 % off sat at 1.9 %.
pub const CONVERGED_EXCESS: f64 = 0.005;
/// The larger of two values, NaN when either is: a missing sd is never the narrowest.
fn nan_max(a: f64, b: f64) -> f64 {
    if a.is_nan() || b.is_nan() {
        f64::NAN
    } else {
        a.max(b)
    }
}

/// Seconds of data the stable updates must span.
const CONVERGED_SPAN_S: f64 = 2.0;
/// Convergence also asks the estimate to be as precise as the accuracy a converged run
/// stands for: three sd of Bl(x) and Kms(x) within 2 %, and of Le(x) within 5 %, of their
/// values at rest over the reach. A settled estimate whose bands are wider has not seen enough
/// of the driver to say so (drawn small drivers ended "converged" with Kms 4-19 % off and
/// sds of 1-2.4 %): the run goes on, and ends loud if the data never narrow them.
const CONVERGED_SD_BL_KMS: f64 = 0.02 / 3.0;
const CONVERGED_SD_LE: f64 = 0.05 / 3.0;

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
            format!("--max-volts {} V is not valid (0 .. 1000 V rms)", self.max_volts),
        )?;
        check(
            self.start_volts > 0.0 && self.start_volts <= self.max_volts,
            format!("--start-volts {} V is not valid (0 .. max-volts {} V)", self.start_volts, self.max_volts),
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
                format!("--volts {v} V is not valid (0 .. max-volts {} V)", self.max_volts),
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
/// The Le band also carries `le_model_rel` of the value: how far the small-signal stage's Le
/// moved to a model with more effects that fitted it as well ([`LinearFit::le_model_rel`];
/// the online estimator keeps the stage's model, so the data never chose between the two).
///
/// [`LinearFit::le_model_rel`]: coilscope_ident::linear::LinearFit::le_model_rel
fn curve_bands(p: &Parameters, on: &Online, xs: &[f64], le_model_rel: f64) -> [(&'static str, Band); 3] {
    let sys = coilscope_ident::large::CURVE_SYSTEMATIC_REL;
    [("Bl", &p.bl), ("Kms", &p.kms), ("Le", &p.le)].map(|(which, f)| {
        let value: Vec<f64> = xs.iter().map(|&x| f.eval(x)).collect();
        let model = if which == "Le" { le_model_rel } else { 0.0 };
        let sd = xs.iter().zip(&value).map(|(&x, v)| on.curve_sd(which, x).hypot(sys * v).hypot(model * v)).collect();
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
const SMALL_FADE_S: f64 = 0.1;
const SMALL_REST_S: f64 = 0.3;

/// Fade-out and rest at the end of the small-signal stage; `start` is the absolute index of
/// `drive[0]`.
fn small_stage_envelope(drive: &mut [f64], start: usize, fs: f64, small_seconds: f64) {
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
fn loud_start(lin: &coilscope_ident::linear::LinearFit, p: &Parameters, u: &[f64], i: &[f64], fs: f64) -> Option<f64> {
    let (_, w) = coilscope_ident::linear::linear_warnings(lin, p, u, i, fs);
    w.iter()
        .any(|w| w.code == "large-signal-record")
        .then(|| coilscope_ident::linear::predicted_displacement(p, i, fs).iter().fold(0.0f64, |a, v| a.max(v.abs())))
}

/// The batch large-signal fit (`coilscope identify`, order 4) of a record's first seconds, as
/// the online estimator's start, with the sd of its Re (ohm) and the reach (m); `None` if it
/// cannot be made (the linear start is kept).
fn batch_start(u: &[f64], i: &[f64], fs: f64, mms: f64) -> Option<(Parameters, f64, f64)> {
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

/// What the controller sees after a block (SI units).
#[derive(Clone, Debug)]
pub struct ControlInput {
    /// The present drive level (V rms).
    pub gain: f64,
    /// Length of the block just played (s).
    pub block_seconds: f64,
    /// Largest |x| of the live model over the block (m).
    pub peak: f64,
    /// Largest remembered block peak per volt (m/V): the last 8 s and the small stage.
    pub per_volt: f64,
    /// The excursion limit in force (m): the target, the stiffness limit, or none yet.
    pub x_limit: Option<f64>,
    /// Largest Kms(x)/Kms(0) of the estimate within 1.3 times the reach.
    pub kms_ratio: f64,
    /// The reach (m) the last update checked the curves over.
    pub checked_reach: f64,
    /// Largest change of Bl(x)/Kms(x) at the last update (relative to the value at rest).
    pub last_change: Option<f64>,
    /// Current error above the noise floor on the last held-out window (NaN before one).
    pub last_excess: f64,
    /// Estimated voice-coil rise (K), and carried one second ahead along its trend.
    pub dtv: f64,
    pub dtv_ahead: f64,
    /// Whether the temperature has cut the level (cleared below 75 % of the limit).
    pub temp_cut: bool,
    /// Seconds since the temperature last cut the level (infinite if never).
    pub since_temp_cut: f64,
    /// The excitation high-pass's cut-off (Hz).
    pub hp_fc: f64,
}

/// The controller's decision for the next block.
#[derive(Clone, Debug, PartialEq)]
pub struct ControlDecision {
    /// The next drive level (V rms).
    pub gain: f64,
    pub why: LimitedBy,
    /// A new high-pass cut-off (Hz), in a long-term test at a fixed level.
    pub hp_fc: Option<f64>,
    pub temp_cut: bool,
    /// Protection events, for people.
    pub events: Vec<String>,
}

/// The controller: one pure decision per block, its policies in order (each is unit-tested
/// below):
///
/// 1. **Ramp**: `ramp_db_per_s` (a third of it near the stiffness limit), or the fixed level
///    of a long-term test.
/// 2. **Excursion**: above 98 % of the limit, cut at once to 90 %; otherwise aim the largest
///    remembered peak at `X_AIM` of the limit. At a fixed level the high-pass rises instead.
/// 3. **Trust region** (`Exploration`): never aim past 1.6 times the reach the last update
///    checked (1.25 times near the stiffness limit): beyond it the curves are extrapolated.
/// 4. **Settling**: no rise while the last update moved the curves by more than
///    [`RAMP_SETTLE`] or missed more than [`RAMP_EXCESS`] of the held-out current.
/// 5. **Temperature**: above 92 % of `max_dt` (ahead), cut to 85 % (power ~ gain^2); above
///    85 %, or after a cut until the coil is below 75 %, no rise.
/// 6. **`max_volts`**.
pub fn control(opts: &MeasureOptions, c: &ControlInput) -> ControlDecision {
    let gain = c.gain;
    let (peak, per_volt, kms_ratio, checked_reach, dtv, dtv_ahead) =
        (c.peak, c.per_volt, c.kms_ratio, c.checked_reach, c.dtv, c.dtv_ahead);
    let mut events = Vec::new();
    let mut hp_fc = None;
    let mut temp_cut = c.temp_cut;
    // Near the stiffness limit the ramp slows to a third.
    let ramp = if kms_ratio > 0.75 * opts.kms_limit { opts.ramp_db_per_s / 3.0 } else { opts.ramp_db_per_s };
    let step = 10f64.powf(ramp * c.block_seconds / 20.0);
    let mut g = opts.hold_volts.map_or(gain * step, |v| v.min(gain * step));
    let mut why = LimitedBy::Ramp;
    if let Some(xl) = c.x_limit {
        if opts.hold_volts.is_some() {
            // Fixed level: the high-pass keeps x in range.
            if peak > 0.97 * xl {
                let fc = (c.hp_fc.max(5.0) * 1.25).min(2000.0);
                events.push(format!(
                    "excursion {:.2} mm near the limit {:.2} mm: high-pass raised to {fc:.1} Hz",
                    peak * 1e3,
                    xl * 1e3
                ));
                hp_fc = Some(fc);
                why = LimitedBy::ExcursionHighPass;
            } else if gain * per_volt < 0.8 * xl && c.hp_fc > opts.hp_hz {
                hp_fc = Some((c.hp_fc / 1.05).max(opts.hp_hz));
            }
        } else if peak > 0.98 * xl {
            g = gain * 0.9 * xl / peak;
            events.push(format!(
                "excursion {:.2} mm above 98 % of the limit {:.2} mm: gain cut to {g:.3} V",
                peak * 1e3,
                xl * 1e3
            ));
            why = LimitedBy::Excursion;
        } else if g * per_volt > X_AIM * xl {
            g = X_AIM * xl / per_volt.max(1e-12);
            why = LimitedBy::Excursion;
        }
    }
    // The trust region: the curves beyond the checked reach are extrapolated, so the level
    // never aims past EXPLORE_FAR times it, EXPLORE times once the suspension stiffens (the
    // limit is looked for 1.3 times the reach ahead, so it is seen before it is hit). A ramp of
    // 3 dB/s otherwise grows the reach by 1.5 between two updates, past a stiffness limit the
    // estimate has not yet seen.
    let explore = if kms_ratio > 1.0 + 0.5 * (opts.kms_limit - 1.0) { EXPLORE } else { EXPLORE_FAR };
    if opts.hold_volts.is_none() && checked_reach > 0.0 && g * per_volt > explore * checked_reach {
        let cap = explore * checked_reach / per_volt.max(1e-12);
        if cap < g {
            g = cap.max(gain.min(g));
            why = LimitedBy::Exploration;
        }
    }
    if opts.hold_volts.is_none()
        && g > gain
        && (c.last_change.is_some_and(|b| b > RAMP_SETTLE) || c.last_excess > RAMP_EXCESS)
    {
        g = gain;
        why = LimitedBy::Settling;
    }
    // Margins for what is left of the tracking lag and for the cold Re's error (0.05 % of Re
    // is 0.13 K): hold at 85 %, cut to 85 % above 92 %. A cut shows in the tracked temperature
    // only after the tracking lag: within THERMAL_LAG_S of one, the level holds rather than
    // cutting again (cuts compounded block after block took a 2 s coil from 3.6 V to 1.7 V,
    // it cooled, the ramp came back, and the level hunted for a minute), unless the coil is
    // heading past the limit itself.
    if dtv_ahead > 0.92 * opts.max_dt && c.since_temp_cut < THERMAL_LAG_S && dtv_ahead <= opts.max_dt {
        if g > gain {
            g = gain;
            why = LimitedBy::Temperature;
        }
    } else if dtv_ahead > 0.92 * opts.max_dt {
        let cut = gain * (0.85 * opts.max_dt / dtv_ahead).sqrt();
        if cut < g {
            g = cut;
            events.push(format!(
                "voice-coil rise {dtv:.2} K (heading for {dtv_ahead:.2} K) above 92 % of {} K: gain cut to {g:.3} V",
                opts.max_dt
            ));
            why = LimitedBy::Temperature;
        }
    } else if (dtv_ahead > 0.85 * opts.max_dt || (temp_cut && dtv_ahead > 0.75 * opts.max_dt)) && g > gain {
        // After a cut the level stays until the coil has cooled to 75 % (no hunting around
        // the limit: every change of level restarts the hold).
        g = gain;
        why = LimitedBy::Temperature;
    }
    if why == LimitedBy::Temperature && g < gain {
        temp_cut = true;
    } else if dtv_ahead < 0.75 * opts.max_dt {
        temp_cut = false;
    }
    if g > opts.max_volts {
        g = opts.max_volts;
        why = LimitedBy::MaxVolts;
    }
    ControlDecision { gain: g, why, hp_fc, temp_cut, events }
}

/// The online estimator's options. A replay makes no update from an estimate that misses
/// more than [`RESTART_RESIDUAL`] of the window: it restarts from a batch fit once it has
/// [`RESTART_S`] of the new level, and until then the last good model runs on (a step from
/// that far ran PTT4's replay away 0.6 s after its level jumped).
fn online_options(opts: &MeasureOptions, x_ref: f64, controllable: bool) -> OnlineOptions {
    // A long-term test lets the values at rest follow the suspension and the magnet as they
    // warm over minutes.
    let drift = if opts.duration.is_some() { LONG_TERM_DRIFT } else { 0.0 };
    OnlineOptions {
        order: opts.order,
        x_ref,
        window: ONLINE_WINDOW_S,
        max_before: if controllable { f64::INFINITY } else { RESTART_RESIDUAL },
        drift,
        ..Default::default()
    }
}

/// The eddy-current branch an estimate drove to nothing: L2 and R2 both a hair from zero (the
/// replay of SB17's independent real-chain record without its calibration ended with L2 =
/// -4e-14 H, R2 = -2e-11 ohm). Such a branch is the same model as none (its impedance is at
/// most min(R2, w L2)), but a set with a non-positive L2 or R2 does not read back, so the
/// report refused the result `measure` had just written. It is taken out; a branch that is
/// not negligible is kept as estimated. Returns whether it was taken out.
fn drop_vanished_branch(p: &mut Parameters, [lo, hi]: [f64; 2]) -> bool {
    let Some((l2, r2)) = &p.l2r2 else { return false };
    let (l2_min, l2_max) = l2.min_max_on(lo, hi);
    let (r2_min, r2_max) = r2.min_max_on(lo, hi);
    if l2_min > 0.0 && r2_min > 0.0 {
        return false;
    }
    // |Z2| <= min(R2, w L2): negligible against Re up to 100 kHz.
    let z2 = r2_min.abs().max(r2_max.abs()).min(2.0 * std::f64::consts::PI * 1e5 * l2_min.abs().max(l2_max.abs()));
    if z2 < 1e-6 * p.re {
        p.l2r2 = None;
        return true;
    }
    false
}

/// Largest relative change of a curve over `[-r, r]`, relative to its value at rest.
fn curve_change(a: &Poly, b: &Poly, r: f64) -> f64 {
    let b0 = b.eval(0.0).abs().max(1e-300);
    (0..=40).map(|k| -r + 2.0 * r * k as f64 / 40.0).map(|x| (a.eval(x) - b.eval(x)).abs() / b0).fold(0.0, f64::max)
}

/// The `q` quantile (0..1) of `v` (0 if empty).
fn percentile(v: &[f64], q: f64) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s[((s.len() - 1) as f64 * q).round() as usize]
}

/// The smallest |x| within `reach` where max(Kms(x), Kms(-x)) / Kms(0) reaches `limit`.
pub fn kms_limit_crossing(kms: &Poly, reach: f64, limit: f64) -> Option<f64> {
    let k0 = kms.eval(0.0);
    (1..=200).map(|k| reach * k as f64 / 200.0).find(|&x| kms.eval(x).max(kms.eval(-x)) / k0 >= limit)
}

/// The measurement as a stepper: [`Engine::step`] plays one block and makes every decision
/// that follows it (identification, protection, convergence); [`Engine::finish`] turns the
/// state into the [`Measurement`]. [`measure`] is the loop over it; a live view, a test or
/// another front end can drive the steps itself.
pub struct Engine<'a> {
    device: &'a mut dyn Device,
    source: &'a mut Source,
    opts: MeasureOptions,
    fs: f64,
    /// Samples per block.
    nb: usize,
    hp: HighPass,
    /// The small-signal stage's excitation under music (quiet IEC noise).
    pilot: Option<Source>,
    controllable: bool,
    gain: f64,
    stage: Stage,
    u_small: Vec<f64>,
    i_small: Vec<f64>,
    online: Option<Online>,
    /// Standard deviation of the cold Re (ohm).
    re_cold_sd: f64,
    /// Le's model uncertainty from the small-signal stage (relative).
    le_model_rel: f64,
    small: Option<Parameters>,
    samples: usize,
    /// Block peaks per volt over the last PEAK_MEMORY_S (and the small stage's).
    recent_peaks: Vec<f64>,
    prev_est: Option<Parameters>,
    /// A replay's last RESTART_S seconds (for a restart from a batch fit) and the restarts.
    recent_u: Vec<f64>,
    recent_i: Vec<f64>,
    restarts: usize,
    /// Largest change of Bl/Kms and of Le at each update.
    changes: Vec<(f64, f64)>,
    auto_limit: Option<f64>,
    /// The stiffness limit once it lies inside the reach (seen in the data, not extrapolated).
    seen_limit: Option<f64>,
    /// Largest Kms(x)/Kms(0) of the estimate within 1.3 times the reach.
    kms_ratio: f64,
    /// The reach at the last update: how far the stiffness limit has been looked for.
    checked_reach: f64,
    hold_since: f64,
    /// Whether the insignificant effects were dropped at full level.
    pruned: bool,
    steady_blocks: usize,
    events: Vec<(f64, String)>,
    dt_track: Vec<(f64, f64)>,
    /// Every block after the small-signal stage: the tracked rise and the powers.
    thermal_track: coilscope_ident::thermal::ThermalTrack,
    /// The live distortion: the meter, the sums of squares of the current second's blocks,
    /// and one point per second.
    meter: Option<coilscope_analysis::live_distortion::DistortionMeter>,
    dist_sum: ([f64; 9], usize),
    distortion: Vec<coilscope_core::result::DistortionPoint>,
    x_peak_max: f64,
    dtv_max: f64,
    hold_range: [f64; 2],
    /// Block peaks |x| since the hold (re)started.
    hold_peaks: Vec<f64>,
    /// The gain at which the hold (re)started.
    hold_gain: f64,
    last_residual: f64,
    /// Relative current error above the noise floor on the last held-out window.
    last_excess: f64,
    /// The widest bands over the reach at the last update, relative to the values at rest:
    /// (Bl and Kms, Le).
    widest: Option<(f64, f64)>,
    updates: usize,
    /// Recent temperature estimates (one per block) for the trend.
    dtv_recent: Vec<f64>,
    /// The coil's estimated rise at the last update (K).
    dtv_at_update: f64,
    /// Whether the temperature has cut the level (cleared once the coil is below 75 %).
    temp_cut: bool,
    /// When the temperature last cut the level (s; minus infinity if never).
    last_temp_cut: f64,
    converged: bool,
    /// What limited the level at the last block.
    last_why: LimitedBy,
    stop_reason: Option<StopReason>,
    blocks: usize,
    /// Blocks per second: the database commits and the dT track are once a second.
    per_second: usize,
    /// Seconds after which the run stops (duration or max_seconds).
    end: f64,
}

impl<'a> Engine<'a> {
    /// Check the options and set up the run (nothing is played yet).
    pub fn new(device: &'a mut dyn Device, source: &'a mut Source, opts: &MeasureOptions) -> Result<Self, String> {
        opts.validate()?;
        let fs = device.fs();
        // The small-signal stage needs every band of the impedance (Re and the L2/R2 branch
        // are told apart only by a broad spectrum): under music it plays quiet IEC noise.
        let pilot = if source.persistent() { None } else { Some(Source::noise(&Excitation::Iec, fs, 0)?) };
        let controllable = device.controllable();
        Ok(Engine {
            device,
            source,
            opts: opts.clone(),
            fs,
            nb: ((opts.block * fs) as usize).max(64),
            hp: HighPass::new(fs, opts.hp_hz),
            pilot,
            controllable,
            gain: opts.start_volts,
            stage: Stage::Small,
            u_small: Vec::new(),
            i_small: Vec::new(),
            online: None,
            re_cold_sd: f64::NAN,
            le_model_rel: 0.0,
            small: None,
            samples: 0,
            recent_peaks: Vec::new(),
            prev_est: None,
            recent_u: Vec::new(),
            recent_i: Vec::new(),
            restarts: 0,
            changes: Vec::new(),
            auto_limit: None,
            seen_limit: None,
            kms_ratio: 1.0,
            checked_reach: 0.0,
            hold_since: f64::INFINITY,
            pruned: false,
            steady_blocks: 0,
            events: Vec::new(),
            dt_track: Vec::new(),
            thermal_track: Default::default(),
            meter: None,
            dist_sum: ([0.0; 9], 0),
            distortion: Vec::new(),
            x_peak_max: 0.0,
            dtv_max: 0.0,
            hold_range: [0.0, 0.0],
            hold_peaks: Vec::new(),
            hold_gain: 0.0,
            last_residual: f64::NAN,
            last_excess: f64::NAN,
            widest: None,
            updates: 0,
            dtv_recent: Vec::new(),
            dtv_at_update: 0.0,
            temp_cut: false,
            last_temp_cut: f64::NEG_INFINITY,
            converged: false,
            last_why: LimitedBy::SmallSignal,
            stop_reason: None,
            blocks: 0,
            per_second: (1.0 / opts.block).round().max(1.0) as usize,
            end: opts.duration.unwrap_or(opts.max_seconds),
        })
    }

    /// Why the run stopped, once it has (`None` while it runs).
    pub fn stop_reason(&self) -> Option<&StopReason> {
        self.stop_reason.as_ref()
    }

    /// Play one block and decide what follows: `Ok(Some(live))` after a block, `Ok(None)`
    /// once the run has stopped ([`Engine::stop_reason`] says why); an error only where
    /// nothing can be kept (before the small-signal stage is complete, or the store failed).
    /// `store` (if any) gets the block's state, once a second a commit, and every estimate.
    pub fn step(&mut self, mut store: Option<&mut Store>) -> Result<Option<Live>, String> {
        if self.stop_reason.is_some() {
            return Ok(None);
        }
        let t = self.samples as f64 / self.fs;
        if t >= self.end {
            self.stop_reason = Some(match self.opts.duration {
                Some(seconds) => StopReason::DurationOver { seconds },
                None => StopReason::NoConvergence { max_seconds: self.opts.max_seconds },
            });
            if let (None, Some((bl_kms, le))) = (self.opts.duration, self.widest) {
                if !(bl_kms <= CONVERGED_SD_BL_KMS && le <= CONVERGED_SD_LE) {
                    self.events.push((t, format!("the bands stayed wider than a converged run's: sd up to {:.2} % (Bl, Kms) and {:.2} % (Le) of the values at rest over the reach, against {:.2} % and {:.2} %: the record does not pin this driver's curves down (a driver whose current hardly shows its motion, or a reach too small for its nonlinearities)", 100.0 * bl_kms, 100.0 * le, 100.0 * CONVERGED_SD_BL_KMS, 100.0 * CONVERGED_SD_LE)));
                    if le > CONVERGED_SD_LE && self.le_model_rel > CONVERGED_SD_LE {
                        self.events.push((t, format!("Le is not pinned down by the model: at the small-signal stage a model with more effects (an LR-3 branch, creep) fitted as well and moved Le by {:.1} %, a choice the record cannot make; measure at a higher --start-volts, or fit the choice with `linear` on a longer quiet record", 100.0 * self.le_model_rel)));
                    }
                }
            }
            return Ok(None);
        }
        if self.opts.interrupt.as_ref().is_some_and(|f| f.load(std::sync::atomic::Ordering::Relaxed)) {
            self.stop_reason = Some(StopReason::Interrupted { t });
            return Ok(None);
        }
        let mut drive = match self.pilot.as_mut() {
            Some(p) if self.stage == Stage::Small => p.next_block(self.nb),
            _ => self.source.next_block(self.nb),
        };
        self.hp.process(&mut drive);
        drive.iter_mut().for_each(|v| *v *= self.gain);
        if self.stage == Stage::Small && self.controllable {
            small_stage_envelope(&mut drive, self.samples, self.fs, self.opts.small_seconds);
        }
        let played = match self.device.play(&drive) {
            Ok(b) => b,
            // Once there is an estimate, a failure ends the run with it kept (the result is
            // written, marked failed); before that there is nothing to keep.
            Err(message) if self.online.is_some() => {
                self.stop_reason = Some(StopReason::Failed { t, message });
                return Ok(None);
            }
            Err(e) => return Err(e),
        };
        let Some(blk) = played else {
            self.stop_reason = Some(StopReason::ReplayEnded { seconds: t });
            return Ok(None);
        };
        let n = blk.u.len();
        if n == 0 {
            self.stop_reason = Some(StopReason::DeviceEmpty);
            return Ok(None);
        }
        self.samples += n;
        self.blocks += 1;
        let t = self.samples as f64 / self.fs;
        let mut live = Live {
            t,
            stage: self.stage,
            volts: self.gain,
            f_hp: self.hp.fc,
            x_min: 0.0,
            x_max: 0.0,
            dtv: 0.0,
            re: f64::NAN,
            residual: f64::NAN,
            x_limit: None,
            limited_by: LimitedBy::Ramp,
            update: None,
            estimate: None,
            change: None,
            distortion: None,
            trace: Trace {
                dt: n as f64 / self.fs / TRACE_BINS.min(n) as f64,
                u: envelope(blk.u.iter().copied(), TRACE_BINS),
                i: envelope(blk.i.iter().copied(), TRACE_BINS),
                ..Default::default()
            },
            bands: vec![],
        };
        match self.online.as_mut() {
            None => {
                self.u_small.extend_from_slice(&blk.u);
                self.i_small.extend_from_slice(&blk.i);
                live.limited_by = LimitedBy::SmallSignal;
                if t >= self.opts.small_seconds {
                    // A replay's first seconds are a segment cut from the running record; a
                    // controlled stage fades out, with the cone still moving a little.
                    let lin = fit_linear_record(&self.u_small, &self.i_small, self.fs, "small-signal stage", &SMALL_STAGE_FIT, |_| {})
                        .map_err(|e| format!("{e} (the small-signal stage at {:.3} V rms: raise --start-volts if the level is too low against noise)", self.opts.start_volts))?;
                    let p = scale_by_mms(&lin, self.opts.mms)?;
                    // Reach of the small stage: the series basis and the runaway limit scale from it.
                    let x_lin = coilscope_ident::linear::predicted_displacement(&p, &self.i_small, self.fs);
                    let x_small = x_lin.iter().fold(0.0f64, |a, v| a.max(v.abs())).max(1e-6);
                    // The controller's peak memory starts with the small stage's blocks (before
                    // its fade): the noise repeats every 8 s, and a crest first played quietly
                    // here comes back at full level one period later (SB17 from 1 V: a crest at
                    // 1.4 s of the period came back at 9.4 s as 6 mm against 4.1 mm remembered).
                    if self.controllable {
                        let quiet_from = ((self.opts.small_seconds - SMALL_REST_S - SMALL_FADE_S) * self.fs) as usize;
                        for b in x_lin[..quiet_from.min(x_lin.len())].chunks(self.nb).filter(|b| b.len() == self.nb) {
                            self.recent_peaks
                                .push(b.iter().fold(0.0f64, |a, v| a.max(v.abs())) / self.opts.start_volts);
                        }
                    }
                    // Basis scale: the expected reach, never more than X_REF_SMALL times the
                    // small-signal reach (a far target leaves the curves ill-conditioned at first).
                    // A controlled stage scales it to the drive level: the reach of the
                    // linear response at X_REF_VOLTS, whatever the start level (from 1 V, 20
                    // small reaches put SB17's x_ref at 14 mm, and the series' prior held
                    // Kms(x) at 1.5 where the driver reached 2.2 at 5.5 mm).
                    let x_expect = if self.controllable {
                        x_small * X_REF_VOLTS / self.opts.start_volts
                    } else {
                        X_REF_SMALL * x_small
                    };
                    let mut x_ref = self.opts.target_x.map_or(x_expect, |t| t.min(x_expect)).max(2.0 * x_small);
                    // A replay that starts loud (no quiet lead-in) has no small-signal stage: a
                    // linear fit of large-signal data is a biased start (Kms 20-45 % off), from
                    // which the online estimator does not recover. Start from a batch
                    // large-signal fit of the same seconds, with the basis at their reach.
                    self.re_cold_sd = lin.sigma_rel[0] * p.re;
                    self.le_model_rel = lin.le_model_rel;
                    let p = match (self.controllable, loud_start(&lin, &p, &self.u_small, &self.i_small, self.fs)) {
                        (false, Some(reach)) => {
                            self.events.push((t, format!("the replay starts at large signal (x about {:.2} mm): the start is a batch large-signal fit of its first {:.1} s", reach * 1e3, self.opts.small_seconds)));
                            x_ref = 1.5 * reach;
                            match batch_start(&self.u_small, &self.i_small, self.fs, self.opts.mms) {
                                Some((b, sd, _)) => {
                                    self.re_cold_sd = sd;
                                    b
                                }
                                None => p,
                            }
                        }
                        _ => p,
                    };
                    let mut on = Online::new(&p, self.fs, online_options(&self.opts, x_ref, self.controllable))
                        .map_err(|e| e.0)?;
                    on.push(&self.u_small, &self.i_small).map_err(|e| e.0)?;
                    self.online = Some(on);
                    self.meter = Some(coilscope_analysis::live_distortion::DistortionMeter::new(&p, self.fs));
                    self.small = Some(p);
                    self.stage = if self.controllable { Stage::Ramp } else { Stage::Hold };
                    if !self.controllable {
                        self.hold_since = t;
                    }
                }
            }
            Some(on) => {
                if !self.controllable {
                    self.recent_u.extend_from_slice(&blk.u);
                    self.recent_i.extend_from_slice(&blk.i);
                    let keep = (RESTART_S * self.fs) as usize;
                    if self.recent_u.len() > keep {
                        let cut = self.recent_u.len() - keep;
                        self.recent_u.drain(..cut);
                        self.recent_i.drain(..cut);
                    }
                }
                let st = match on.push(&blk.u, &blk.i) {
                    Ok(st) => st,
                    Err(e) => {
                        self.stop_reason = Some(StopReason::Failed { t, message: e.0 });
                        return Ok(None);
                    }
                };
                // The temperature reference is the small-signal fit's Re: a record that ends at
                // rest (the stage's closing fade and rest), with the coil still cold.
                let re0 = self.small.as_ref().map_or(f64::NAN, |p| p.re);
                let dtv = (on.re() / re0 - 1.0) / self.opts.alpha;
                self.dtv_recent.push(dtv);
                if self.dtv_recent.len() as f64 * self.opts.block > THERMAL_TREND_S {
                    self.dtv_recent.remove(0);
                }
                // The Re tracking lags the coil by about a second: protect on the estimate
                // carried forward along its trend over the last second.
                let slope = (self.dtv_recent.last().unwrap() - self.dtv_recent[0])
                    / ((self.dtv_recent.len() - 1).max(1) as f64 * self.opts.block);
                let dtv_ahead = dtv + THERMAL_LAG_S * slope.max(0.0);
                if let Some(c) = self.meter.as_mut().and_then(|m| m.process(&st.traj)) {
                    use coilscope_analysis::live_distortion::Contributions;
                    live.distortion = Some(c);
                    let f = c.flat();
                    for (a, v) in self.dist_sum.0.iter_mut().zip(&f) {
                        *a += v * v;
                    }
                    self.dist_sum.1 += 1;
                    if let Some(s) = store.as_deref_mut() {
                        s.push_distortion(t, f, Contributions::dominant(&c.x), Contributions::dominant(&c.p));
                    }
                    if self.blocks.is_multiple_of(self.per_second) {
                        // RMS over the second's blocks.
                        let n = self.dist_sum.1 as f64;
                        let m = Contributions::from_flat(&self.dist_sum.0.map(|a| (a / n).sqrt()));
                        self.distortion.push(coilscope_core::result::DistortionPoint {
                            t,
                            x: m.x,
                            i: m.i,
                            p: m.p,
                            dominant_x: Contributions::dominant(&m.x).into(),
                            dominant_p: Contributions::dominant(&m.p).into(),
                        });
                        self.dist_sum = ([0.0; 9], 0);
                    }
                }
                if st.samples > 0 {
                    let tt = &mut self.thermal_track;
                    tt.t.push(t);
                    tt.dtv.push(dtv);
                    tt.pv.push(on.re() * st.i_sq / st.samples as f64);
                    tt.pm.push(st.pm_sum / st.samples as f64);
                    // The live model's mean coil speed (the convection cooling's input).
                    tt.speed.push(if st.traj.is_empty() {
                        f64::NAN
                    } else {
                        st.traj.iter().map(|s| s[1].abs()).sum::<f64>() / st.traj.len() as f64
                    });
                }
                live.x_min = st.x_min;
                live.x_max = st.x_max;
                live.trace.x = envelope(st.traj.iter().map(|s| s[0]), TRACE_BINS);
                live.trace.v = envelope(st.traj.iter().map(|s| s[1]), TRACE_BINS);
                live.re = on.re();
                live.dtv = dtv;
                live.residual = st.residual_rel();
                self.x_peak_max = self.x_peak_max.max(st.x_max.max(-st.x_min));
                self.dtv_max = self.dtv_max.max(dtv);
                // The reached range counts only blocks where the live model follows the
                // measured current (a model that ran away and fell back shows no real x).
                if self.stage == Stage::Hold && st.residual_rel() < TRACKING_RESIDUAL {
                    self.hold_range = [self.hold_range[0].min(st.x_min), self.hold_range[1].max(st.x_max)];
                    self.hold_peaks.push(st.x_max.max(-st.x_min));
                }
                // Recursive update. A replay is not real time: it updates once per window, so
                // every recorded sample is used.
                let every = if self.controllable {
                    self.opts.update_seconds
                } else {
                    self.opts.update_seconds.min(ONLINE_WINDOW_S)
                };
                if on.since_update() >= every {
                    if let Some(up) = on.update() {
                        self.updates += 1;
                        // The values at rest drift as the driver warms: by DRIFT_PER_KELVIN of
                        // the coil's rise since the last update.
                        let warmed = (dtv - self.dtv_at_update).abs();
                        self.dtv_at_update = dtv;
                        on.drift_values_at_rest((DRIFT_PER_KELVIN * warmed).powi(2));
                        // A replay has no ramp: the level can jump far past what the estimate
                        // knows (a quiet lead-in, then the loud part), and the online update
                        // from a model that misses 10 % of the current runs away. Restart it
                        // from a batch large-signal fit of the last seconds instead.
                        if !self.controllable
                            && up.before > RESTART_RESIDUAL
                            && self.restarts < MAX_RESTARTS
                            && self.recent_u.len() as f64 >= RESTART_S * self.fs - 1.0
                        {
                            if let Some((b, _, reach)) =
                                batch_start(&self.recent_u, &self.recent_i, self.fs, self.opts.mms)
                            {
                                let fresh = Online::new(
                                    &b,
                                    self.fs,
                                    online_options(&self.opts, 1.5 * reach.max(1e-6), self.controllable),
                                )
                                .and_then(|mut f| f.push(&self.recent_u, &self.recent_i).map(|_| f));
                                if let Ok(f) = fresh {
                                    *on = f;
                                    self.restarts += 1;
                                    self.events.push((t, format!("the estimate missed {:.0} % of the current (the level jumped past what it knew): restarted from a batch large-signal fit of the last {RESTART_S} s", 100.0 * up.before)));
                                    self.prev_est = None;
                                    self.changes.clear();
                                    self.hold_peaks.clear();
                                    self.hold_range = [0.0, 0.0];
                                    self.hold_since = t;
                                }
                            }
                        }
                        self.last_residual = up.before;
                        self.last_excess = up.before * (1.0 - 1.0 / up.floor_ratio.max(1.0).powi(2)).sqrt();
                        // At full level for a while, the large-signal effects the data did not
                        // show stop being estimated (each made every update a fifth dearer).
                        if self.controllable
                            && !self.pruned
                            && self.stage == Stage::Hold
                            && t - self.hold_since >= PRUNE_AFTER_HOLD_S
                        {
                            self.pruned = true;
                            let d = on.drop_effects(on.insignificant_effects());
                            if d != Effects::NONE {
                                self.events.push((t, format!("at full level for {PRUNE_AFTER_HOLD_S} s the data show no {}: no longer estimated", d.in_words())));
                            }
                        }

                        live.update = Some(up.before);
                        let est = on.parameters();
                        let reach = on.reach;
                        if let Some(prev) = &self.prev_est {
                            // Over the range the driver keeps visiting at the present level:
                            // the 80th percentile of the block peaks since the hold (re)started.
                            // The outermost peaks come a few times a period (noise) or a bar
                            // (music); the curves there follow them by a few percent from update
                            // to update and are judged by their uncertainty bands instead.
                            let dense = percentile(&self.hold_peaks, 0.8);
                            let r = 0.9 * if dense > 0.0 { dense } else { reach };
                            let c_bk = curve_change(&est.bl, &prev.bl, r).max(curve_change(&est.kms, &prev.kms, r));
                            let c_le = curve_change(&est.le, &prev.le, r);
                            self.changes.push((c_bk, c_le));
                            live.change = Some((c_bk, c_le));
                        }
                        // The safe range: where the stiffness rises past the user's limit.
                        // Looked for a little beyond the reach (the estimate extrapolated), so
                        // the ramp stops before the driver gets there. A crossing inside the
                        // reach has been seen and stays; one beyond it is provisional and is
                        // looked at again at every update (the extrapolation improves as the
                        // reach grows toward it).
                        let crossing = kms_limit_crossing(&est.kms, 1.3 * reach, self.opts.kms_limit);
                        if let Some(x) = crossing.filter(|&x| x <= reach) {
                            self.seen_limit = Some(self.seen_limit.map_or(x, |a: f64| a.min(x)));
                        }
                        let new_limit = match (self.seen_limit, crossing) {
                            (Some(a), Some(b)) => Some(a.min(b)),
                            (a, b) => a.or(b),
                        };
                        // A replay has no controller: its limits are not events.
                        match (self.auto_limit, new_limit) {
                            _ if !self.controllable => {}
                            (None, Some(x)) => self.events.push((t, format!("Kms(x)/Kms(0) reaches {} at |x| = {:.2} mm: excursion limited there", self.opts.kms_limit, x * 1e3))),
                            (Some(a), Some(x)) if (x / a - 1.0).abs() > 0.05 => self.events.push((t, format!("Kms(x)/Kms(0) reaches {} at |x| = {:.2} mm (was {:.2} mm): excursion limit moved", self.opts.kms_limit, x * 1e3, a * 1e3))),
                            (Some(a), None) => self.events.push((t, format!("the stiffness limit at {:.2} mm, extrapolated beyond the reach, is no longer predicted: the ramp explores on", a * 1e3))),
                            _ => {}
                        }
                        self.auto_limit = new_limit;
                        if let Some(s) = store.as_deref_mut() {
                            let mut pj = est.clone();
                            pj.x_range = Some([-reach, reach]);
                            s.push_estimate(t, up.before, &pj.to_json_value());
                        }
                        let k0 = est.kms.eval(0.0);
                        self.kms_ratio = (0..=20)
                            .map(|k| 1.3 * reach * k as f64 / 20.0)
                            .map(|x| est.kms.eval(x).max(est.kms.eval(-x)) / k0)
                            .fold(0.0, f64::max);
                        self.checked_reach = reach;
                        let xs: Vec<f64> = (0..LIVE_BAND_POINTS)
                            .map(|k| reach * (2.0 * k as f64 / (LIVE_BAND_POINTS - 1) as f64 - 1.0))
                            .collect();
                        let bands = curve_bands(&est, on, &xs, self.le_model_rel);
                        // The widest band over the reach, relative to the curve at rest (NaN
                        // when the covariance gave none: not precise).
                        let widest = |which: &str| {
                            let b = &bands.iter().find(|(w, _)| *w == which).expect("three bands").1;
                            let at_rest = b.value[LIVE_BAND_POINTS / 2].abs();
                            b.sd.iter().fold(0.0, |m, &s| nan_max(m, s)) / at_rest
                        };
                        let w = (nan_max(widest("Bl"), widest("Kms")), widest("Le"));
                        self.widest = Some(w);
                        let precise = w.0 <= CONVERGED_SD_BL_KMS && w.1 <= CONVERGED_SD_LE;
                        live.bands = bands.into();
                        live.estimate = Some(est.clone());
                        if let Some(m) = self.meter.as_mut() {
                            m.set_params(&est);
                        }
                        self.prev_est = Some(est);
                        // Convergence: at level for 2 s, small window error, stable curves.
                        // The stable updates must span CONVERGED_SPAN_S (2 updates at the
                        // real-time cadence of 1 s, more when a replay updates every window).
                        let n = self.changes.len();
                        let k = ((CONVERGED_SPAN_S / every).round() as usize).max(2);
                        // Not while the ramp only pauses to explore toward the stiffness limit.
                        if self.opts.duration.is_none()
                            && self.stage == Stage::Hold
                            && !matches!(self.last_why, LimitedBy::Exploration | LimitedBy::Settling)
                            && t - self.hold_since >= 2.0
                            && n >= k
                            && up.before < 0.02
                            && self.last_excess <= CONVERGED_EXCESS
                            && self.changes[n - k..].iter().all(|&(b, l)| b < CONVERGED_BL_KMS && l < CONVERGED_LE)
                            && precise
                        {
                            self.converged = true;
                            self.stop_reason = Some(StopReason::Converged { t, residual: up.before, updates: k });
                        }
                    }
                }
                // Controller.
                if self.controllable {
                    let x_limit = match (self.opts.target_x, self.auto_limit) {
                        (Some(a), Some(b)) => Some(a.min(b)),
                        (a, b) => a.or(b),
                    };
                    live.x_limit = x_limit;
                    // Peak excursion per volt over the last 8 s (the noise's period): noise
                    // peaks come rarely, so the level is set from the largest one seen.
                    let peak = st.x_max.max(-st.x_min);
                    self.recent_peaks.push(peak / self.gain);
                    if self.recent_peaks.len() as f64 * self.opts.block > PEAK_MEMORY_S {
                        self.recent_peaks.remove(0);
                    }
                    let per_volt = self.recent_peaks.iter().cloned().fold(0.0, f64::max);
                    // The cooling phase of a long-term test: the held level drops.
                    let cooling = self.opts.cool.filter(|&(after, _)| t >= after).map(|(_, v)| MeasureOptions {
                        hold_volts: Some(v),
                        interrupt: None,
                        ..self.opts.clone()
                    });
                    let d = control(
                        cooling.as_ref().unwrap_or(&self.opts),
                        &ControlInput {
                            since_temp_cut: t - self.last_temp_cut,
                            gain: self.gain,
                            block_seconds: n as f64 / self.fs,
                            peak,
                            per_volt,
                            x_limit,
                            kms_ratio: self.kms_ratio,
                            checked_reach: self.checked_reach,
                            last_change: self.changes.last().map(|c| c.0),
                            last_excess: self.last_excess,
                            dtv,
                            dtv_ahead,
                            temp_cut: self.temp_cut,
                            hp_fc: self.hp.fc,
                        },
                    );
                    let (g, why) = (d.gain, d.why);
                    if why == LimitedBy::Temperature && g < self.gain {
                        self.last_temp_cut = t;
                    }
                    self.temp_cut = d.temp_cut;
                    if let Some(fc) = d.hp_fc {
                        self.hp.set(fc);
                    }
                    self.events.extend(d.events.into_iter().map(|e| (t, e)));
                    live.limited_by = why;
                    if self.stage == Stage::Ramp {
                        if g <= self.gain * 1.0001 {
                            self.steady_blocks += 1;
                        } else {
                            self.steady_blocks = 0;
                        }
                        if self.steady_blocks >= 3 {
                            self.stage = Stage::Hold;
                            self.hold_since = t;
                            self.hold_range = [0.0, 0.0];
                            self.hold_peaks.clear();
                            self.hold_gain = g;
                        }
                    } else if g < 0.95 * self.hold_gain {
                        // The level fell (temperature, excursion): the range and the
                        // convergence start again at the new level.
                        self.hold_since = t;
                        self.hold_range = [0.0, 0.0];
                        self.hold_peaks.clear();
                        self.hold_gain = g;
                    } else if g > 1.05 * self.hold_gain {
                        // The ramp went on (exploration): not converged at a level yet.
                        self.hold_since = t;
                        self.hold_gain = g;
                    }
                    self.gain = g;
                } else {
                    live.limited_by = LimitedBy::Replay;
                }
                if self.blocks.is_multiple_of(self.per_second) {
                    self.dt_track.push((t, dtv));
                }
            }
        }
        live.stage = self.stage;
        self.last_why = live.limited_by;
        if let Some(s) = store {
            s.push_state(StateRow {
                t,
                stage: self.stage.name().into(),
                u_rms: coilscope_core::simulate::rms(&blk.u),
                i_rms: coilscope_core::simulate::rms(&blk.i),
                gain: live.volts,
                f_hp: live.f_hp,
                x_min: live.x_min,
                x_max: live.x_max,
                dtv: live.dtv,
                re: live.re,
                residual: live.residual,
            });
            if self.blocks.is_multiple_of(self.per_second) {
                s.commit(t)?;
            }
        }
        if self.converged {
            return Ok(None);
        }
        Ok(Some(live))
    }

    /// The outcome: the estimate, the cold Re (refitted on the small-signal stage when the
    /// run converged) and everything the run decided. An error if the small-signal stage was
    /// never complete.
    pub fn finish(self) -> Result<Measurement, String> {
        let seconds = self.samples as f64 / self.fs;
        let Some(on) = self.online else {
            return Err(format!(
                "the measurement ended after {seconds:.2} s, before the small-signal stage ({} s) was complete",
                self.opts.small_seconds
            ));
        };
        // `Re` of a parameter set is the value at ambient temperature (formats.md): the cold
        // estimate. The hot value at the end lives under `thermal` (`Measurement::re_end`).
        let mut params = on.parameters();
        let re_end = params.re;
        let later = on.insignificant_effects();
        let dropped = later.union(on.dropped);
        if dropped.creep {
            params.creep = None;
        }
        if dropped.le_i {
            params.le_i = None;
        }
        if dropped.rms_v {
            params.rms_v = None;
        }
        let effects = on.layout.effects.without(dropped);
        let hold_range = if self.hold_range == [0.0, 0.0] { [-on.reach, on.reach] } else { self.hold_range };
        params.x_range = Some(hold_range);
        drop_vanished_branch(&mut params, hold_range);
        let small = self.small.expect("set with the estimator");
        let mut re_cold = small.re;
        let mut re_cold_sd = self.re_cold_sd;
        // A converged model refits the cold Re on the small-signal stage's record (it starts
        // and ends at rest, the coil still cold): unlike the linear fit, it does not read the
        // stage's distortion as resistance.
        if self.controllable && self.converged {
            let start = Parameters { re: re_cold, ..params.clone() };
            if let Some((re, sd)) = coilscope_ident::online::fit_re(&start, &self.u_small, &self.i_small, self.fs)
                .filter(|&(re, _)| (re / re_cold - 1.0).abs() < 0.01)
            {
                re_cold = re;
                re_cold_sd = sd;
            }
        }
        params.re = re_cold;
        // The track is referred to the small-signal fit's Re (`small.re`): its sd, as a
        // temperature, is an offset the fit cannot see.
        let offset_sd = self.re_cold_sd / small.re / self.opts.alpha;
        let thermal_fit = (seconds >= THERMAL_FIT_MIN_S)
            .then(|| fit_thermal_track(&self.thermal_track, if offset_sd.is_finite() { offset_sd } else { 0.0 }));
        if let Some(Ok(f)) = &thermal_fit {
            let [rtv, ctv, rtm, ctm] = f.values;
            params.thermal = Some(coilscope_core::params::Thermal {
                alpha: self.opts.alpha,
                rtv,
                ctv,
                rtm,
                ctm,
                rv: f.rv.map_or(0.0, |r| r.0),
            });
        }
        Ok(Measurement {
            params,
            small,
            converged: self.converged,
            stop_reason: self.stop_reason.unwrap_or(StopReason::DeviceEmpty),
            seconds,
            x_range: hold_range,
            x_peak_max: self.x_peak_max,
            dtv_max: self.dtv_max,
            re_cold,
            re_cold_sd,
            le_model_rel: self.le_model_rel,
            re_end,
            alpha: self.opts.alpha,
            limited_by: self.last_why,
            residual_rel: self.last_residual,
            residual_excess: self.last_excess,
            updates: self.updates,
            events: self.events,
            dt_track: self.dt_track,
            thermal_fit,
            thermal_track: self.thermal_track,
            distortion: self.distortion,
            truth: self.device.truth(),
            excitation: self.source.name().to_string(),
            device: self.device.describe(),
            mms_source: String::new(),
            online: on,
            effects,
            dropped,
        })
    }
}

/// Shortest run (s) whose thermal track is fitted ([`coilscope_ident::thermal`]): the coil's
/// time constant is seconds to tens of seconds, the magnet's minutes to an hour.
pub const THERMAL_FIT_MIN_S: f64 = 120.0;

/// The thermal fit of a run's track, from start values read off the track itself: the
/// total resistance from the last rise over the mean coil power, split 60/40 between coil
/// and magnet, a coil time constant of 10 s and a magnet one of 10 minutes.
fn fit_thermal_track(
    tr: &coilscope_ident::thermal::ThermalTrack,
    offset_sd: f64,
) -> Result<coilscope_ident::thermal::ThermalFit, String> {
    let n = tr.t.len();
    if n == 0 {
        return Err("no blocks were tracked".into());
    }
    let tail = n.saturating_sub(n / 10).min(n - 1);
    let p_mean = tr.pv[tail..].iter().sum::<f64>() / (n - tail) as f64;
    let rise = tr.dtv[tail..].iter().sum::<f64>() / (n - tail) as f64;
    let r_total = if p_mean > 0.0 && rise > 0.0 { rise / p_mean } else { 3.0 };
    let (rtv, rtm) = (0.6 * r_total, 0.4 * r_total);
    coilscope_ident::thermal::fit_thermal(tr, [rtv, 10.0 / rtv, rtm, 600.0 / rtm], offset_sd)
}

/// Run a measurement: [`Engine::step`] until it stops, then [`Engine::finish`]. `observe`
/// sees every block; `store` (if any) gets the decimated states (one per block) and every
/// estimate.
pub fn measure(
    device: &mut dyn Device,
    source: &mut Source,
    opts: &MeasureOptions,
    mut store: Option<&mut Store>,
    mut observe: impl FnMut(&Live),
) -> Result<Measurement, String> {
    let mut engine = Engine::new(device, source, opts)?;
    while let Some(live) = engine.step(store.as_deref_mut())? {
        observe(&live);
    }
    engine.finish()
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
        for (which, band) in curve_bands(&self.params, &self.online, &xs, self.le_model_rel) {
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
        });
        r
    }
}

#[cfg(test)]
mod control_tests {
    //! One test per controller policy: each sets up the situation the policy is for
    //! and checks the level it chooses against the rule's own arithmetic.
    use super::*;

    fn opts() -> MeasureOptions {
        MeasureOptions { mms: 0.015, ..Default::default() }
    }

    /// Nothing binds: 1 V, 0.1 s blocks, 0.5 mm/V remembered, no limit, cold coil.
    fn quiet() -> ControlInput {
        ControlInput {
            gain: 1.0,
            block_seconds: 0.1,
            peak: 0.5e-3,
            per_volt: 0.5e-3,
            x_limit: None,
            kms_ratio: 1.0,
            checked_reach: 0.0,
            last_change: None,
            last_excess: f64::NAN,
            dtv: 0.0,
            dtv_ahead: 0.0,
            temp_cut: false,
            since_temp_cut: f64::INFINITY,
            hp_fc: 5.0,
        }
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() <= 1e-12 * b.abs().max(1.0)
    }

    #[test]
    fn the_ramp_rises_3_db_per_second_and_a_third_of_it_near_the_stiffness_limit() {
        let d = control(&opts(), &quiet());
        assert_eq!(d.why, LimitedBy::Ramp);
        assert!(close(d.gain, 10f64.powf(3.0 * 0.1 / 20.0)), "{}", d.gain);
        let d = control(&opts(), &ControlInput { kms_ratio: 1.6, ..quiet() });
        assert!(close(d.gain, 10f64.powf(1.0 * 0.1 / 20.0)), "{}", d.gain);
        assert!(d.events.is_empty());
    }

    #[test]
    fn a_peak_above_98_percent_of_the_limit_cuts_the_level_at_once() {
        let d = control(&opts(), &ControlInput { x_limit: Some(4e-3), peak: 4.2e-3, per_volt: 4.2e-3, ..quiet() });
        assert_eq!(d.why, LimitedBy::Excursion);
        assert!(close(d.gain, 0.9 * 4e-3 / 4.2e-3), "{}", d.gain);
        assert_eq!(d.events.len(), 1);
        assert!(d.events[0].contains("gain cut"), "{:?}", d.events);
    }

    #[test]
    fn the_largest_remembered_peak_is_aimed_at_92_percent_of_the_limit() {
        let d = control(&opts(), &ControlInput { x_limit: Some(4e-3), peak: 3.0e-3, per_volt: 3.9e-3, ..quiet() });
        assert_eq!(d.why, LimitedBy::Excursion);
        assert!(close(d.gain * 3.9e-3, X_AIM * 4e-3), "{}", d.gain);
        assert!(d.events.is_empty(), "aiming is not an event");
    }

    #[test]
    fn the_level_never_aims_past_the_trust_region_of_the_checked_reach() {
        // 1 mm/V and 1 mm checked: far from the stiffness limit at most 1.6 mm is aimed at.
        let far = ControlInput { gain: 1.59, per_volt: 1e-3, peak: 1e-3, checked_reach: 1e-3, ..quiet() };
        let d = control(&opts(), &far);
        assert_eq!(d.why, LimitedBy::Exploration);
        assert!(close(d.gain, EXPLORE_FAR * 1e-3 / 1e-3), "{}", d.gain);
        // Near it (Kms ratio past half the way to the limit) at most 1.25 mm; a level already
        // above the cap is held, not cut (the cap is no protection limit).
        let near = ControlInput { kms_ratio: 1.6, ..far };
        let d = control(&opts(), &near);
        assert_eq!(d.why, LimitedBy::Exploration);
        assert!(close(d.gain, 1.59), "{}", d.gain);
        // Just below the cap, the (slowed) ramp step is cut to it.
        let d = control(&opts(), &ControlInput { gain: 1.245, ..near });
        assert_eq!(d.why, LimitedBy::Exploration);
        assert!(close(d.gain, EXPLORE), "{}", d.gain);
        // Inside the region the ramp goes on.
        let d = control(&opts(), &ControlInput { gain: 1.0, ..far });
        assert_eq!(d.why, LimitedBy::Ramp);
    }

    #[test]
    fn the_ramp_waits_for_an_estimate_that_still_moves_or_misses_the_held_out_current() {
        let d = control(&opts(), &ControlInput { last_change: Some(0.05), ..quiet() });
        assert_eq!((d.gain, d.why), (1.0, LimitedBy::Settling));
        let d = control(&opts(), &ControlInput { last_change: Some(0.01), last_excess: 0.02, ..quiet() });
        assert_eq!((d.gain, d.why), (1.0, LimitedBy::Settling));
        let d = control(&opts(), &ControlInput { last_change: Some(0.01), last_excess: 0.002, ..quiet() });
        assert_eq!(d.why, LimitedBy::Ramp);
        // Waiting never undoes a cut.
        let d =
            control(&opts(), &ControlInput { last_change: Some(0.05), x_limit: Some(4e-3), peak: 4.2e-3, ..quiet() });
        assert_eq!(d.why, LimitedBy::Excursion);
        assert!(d.gain < 1.0);
    }

    #[test]
    fn the_temperature_cuts_above_92_percent_holds_above_85_and_after_a_cut_until_75() {
        let o = opts();
        let hot = o.max_dt * 0.95;
        let d = control(&o, &ControlInput { dtv: hot, dtv_ahead: hot, ..quiet() });
        assert_eq!(d.why, LimitedBy::Temperature);
        assert!(close(d.gain, (0.85 / 0.95f64).sqrt()), "{}", d.gain);
        assert!(d.temp_cut && d.events.len() == 1);
        // Within a second of a cut the level holds (the cut has not shown yet), unless the coil
        // heads past the limit itself.
        let d = control(&o, &ControlInput { dtv: hot, dtv_ahead: hot, since_temp_cut: 0.5, temp_cut: true, ..quiet() });
        assert_eq!((d.gain, d.why), (1.0, LimitedBy::Temperature));
        let d = control(
            &o,
            &ControlInput { dtv: hot, dtv_ahead: 1.1 * o.max_dt, since_temp_cut: 0.5, temp_cut: true, ..quiet() },
        );
        assert!(d.gain < 1.0 && d.why == LimitedBy::Temperature);
        let d = control(&o, &ControlInput { dtv_ahead: 0.88 * o.max_dt, ..quiet() });
        assert_eq!((d.gain, d.why, d.temp_cut), (1.0, LimitedBy::Temperature, false));
        let d = control(&o, &ControlInput { dtv_ahead: 0.8 * o.max_dt, temp_cut: true, ..quiet() });
        assert_eq!((d.gain, d.why, d.temp_cut), (1.0, LimitedBy::Temperature, true));
        let d = control(&o, &ControlInput { dtv_ahead: 0.7 * o.max_dt, temp_cut: true, ..quiet() });
        assert_eq!((d.why, d.temp_cut), (LimitedBy::Ramp, false));
    }

    #[test]
    fn max_volts_is_the_last_word() {
        let d = control(&opts(), &ControlInput { gain: 20.0, ..quiet() });
        assert_eq!((d.gain, d.why), (20.0, LimitedBy::MaxVolts));
    }

    #[test]
    fn a_long_term_test_at_a_fixed_level_raises_the_high_pass_instead_of_cutting() {
        let o = MeasureOptions { hold_volts: Some(1.0), ..opts() };
        let d = control(
            &o,
            &ControlInput { x_limit: Some(4e-3), peak: 3.95e-3, per_volt: 3.95e-3, hp_fc: 20.0, ..quiet() },
        );
        assert_eq!(d.why, LimitedBy::ExcursionHighPass);
        assert_eq!(d.gain, 1.0);
        assert_eq!(d.hp_fc, Some(25.0));
        // Far below the limit it comes back down, never below the start's cut-off.
        let d = control(&o, &ControlInput { x_limit: Some(4e-3), peak: 1e-3, per_volt: 1e-3, hp_fc: 5.1, ..quiet() });
        assert_eq!(d.hp_fc, Some(o.hp_hz));
    }
}

#[cfg(test)]
mod branch_tests {
    use super::*;

    #[test]
    fn a_vanished_branch_is_taken_out_and_a_real_one_kept() {
        let base = coilscope_core::embedded_driver("sb17cac35-4").unwrap();
        let range = [-4.19e-3, 4.65e-3];
        // The replay's estimate: L2 -4e-14 H, R2 -2e-11 ohm.
        let mut p = Parameters {
            l2r2: Some((Poly::constant(-4.4e-14), Poly::constant(-2.4e-11))),
            x_range: Some(range),
            ..base.clone()
        };
        assert!(p.validate("vanished").is_err());
        assert!(drop_vanished_branch(&mut p, range));
        assert!(p.l2r2.is_none());
        p.validate("vanished").unwrap();
        // A physical branch, and an unphysical one that is not negligible: kept as estimated.
        for l2r2 in [(Poly::constant(5.4e-4), Poly::constant(0.29)), (Poly::constant(-1e-4), Poly::constant(0.3))] {
            let mut q = Parameters { l2r2: Some(l2r2.clone()), ..base.clone() };
            assert!(!drop_vanished_branch(&mut q, range));
            assert_eq!(q.l2r2, Some(l2r2));
        }
    }

    #[test]
    fn envelope_keeps_every_extreme_of_each_part() {
        // 10 samples in 4 parts: sample k falls in part k * 4 / 10 (3, 2, 3, 2 samples).
        let s = [0.0, 5.0, -1.0, 2.0, -7.0, 3.0, 1.0, 0.5, 9.0, -2.0];
        let e = envelope(s.iter().copied(), 4);
        assert_eq!(e, vec![[-1.0, 5.0], [-7.0, 2.0], [0.5, 3.0], [-2.0, 9.0]]);
        let all_min = e.iter().map(|b| b[0]).fold(f64::INFINITY, f64::min);
        let all_max = e.iter().map(|b| b[1]).fold(f64::NEG_INFINITY, f64::max);
        assert_eq!((all_min, all_max), (-7.0, 9.0));
        // Fewer samples than parts: one part per sample.
        assert_eq!(envelope([1.0, 2.0].into_iter(), 20), vec![[1.0, 1.0], [2.0, 2.0]]);
        assert!(envelope(std::iter::empty::<f64>(), 20).is_empty());
    }
}

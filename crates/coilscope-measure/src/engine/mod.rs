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
//!
//! The parts: `measurement` (the options, stages, stop reasons, live state and the
//! [`Measurement`] with its result file) and `control` (the controller, a pure function);
//! here, the constants of the policy, the [`Engine`] stepper and [`measure`], its loop.

use crate::device::{Device, Truth};
use crate::signal::{HighPass, Source};
use coilscope_core::excitation::Excitation;
use coilscope_core::params::Parameters;
use coilscope_core::poly::Poly;
use coilscope_core::result::{Band, Fit, MeasurementRecord, ResultFile, SmallSignalStage, Thermal, Uncertainty};
use coilscope_db::{StateRow, Store};
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

mod control;
mod measurement;

pub use control::*;
pub use measurement::*;

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
    /// The estimate before `prev_est` (the result's bands carry the last step).
    before_last: Option<Parameters>,
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
    /// When the last update expected the run to converge (s; [`Engine::expected_convergence`]).
    eta_at: Option<f64>,
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
            before_last: None,
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
            eta_at: None,
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

    /// When the run is expected to converge (s), judged at an update at `t` from the widest
    /// bands `w` (Bl and Kms, Le; relative), the update cadence `every` (s) and the `k`
    /// stable updates convergence asks for. At the held level a recursive estimate's bands
    /// narrow as one over the square root of the data there and its change per update as one
    /// over the data: the hold so far times (band / target)^2, and times (change / limit),
    /// is the hold each needs. Then the 2 s of hold, the `k` stable updates once the changes
    /// are small, and the update grid (convergence is judged at updates). `None` while the
    /// level moves (ramp, exploration, settling).
    fn expected_convergence(&self, t: f64, w: (f64, f64), every: f64, k: usize) -> Option<f64> {
        if self.opts.duration.is_some()
            || self.stage != Stage::Hold
            || matches!(self.last_why, LimitedBy::Exploration | LimitedBy::Settling)
        {
            return None;
        }
        let held = (t - self.hold_since).max(every);
        let precise = (w.0 / CONVERGED_SD_BL_KMS).powi(2).max((w.1 / CONVERGED_SD_LE).powi(2));
        let (c_bk, c_le) = self.changes.last().copied().unwrap_or((f64::INFINITY, f64::INFINITY));
        let steady = (c_bk / CONVERGED_BL_KMS).max(c_le / CONVERGED_LE);
        if !(precise.is_finite() && steady.is_finite()) {
            return None;
        }
        // Updates still needed below the change limit after this one.
        let stable_left =
            self.changes.iter().rev().take_while(|&&(b, l)| b < CONVERGED_BL_KMS && l < CONVERGED_LE).count();
        let to_steady = held * (steady - 1.0).max(0.0);
        let stable = if steady > 1.0 {
            to_steady + (k - 1) as f64 * every
        } else {
            k.saturating_sub(stable_left) as f64 * every
        };
        let wait = (held * (precise - 1.0)).max(stable).max(2.0 - held).max(0.0);
        // The first update at or after that.
        Some(t + (wait / every).ceil().max(1.0) * every)
    }

    /// Seconds until the run is expected to converge ([`Live::eta`]): from the last update's
    /// [`Engine::expected_convergence`], counting down; a run of fixed duration: its end.
    fn eta(&self, t: f64) -> Option<f64> {
        let left = (self.end - t).max(0.0);
        if self.opts.duration.is_some() {
            return Some(left);
        }
        if self.stage != Stage::Hold || matches!(self.last_why, LimitedBy::Exploration | LimitedBy::Settling) {
            return None;
        }
        self.eta_at.map(|at| (at - t).max(0.0).min(left))
    }

    /// The excursion limit in force: the user's `--target-x` or the limit the run found
    /// itself (`auto_limit`), the smaller where both are.
    fn x_limit(&self) -> Option<f64> {
        match (self.opts.target_x, self.auto_limit) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
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
            eta: None,
            end: self.end,
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
                    // The statistical part of the cold Re's sd: it is also the offset the
                    // thermal fit weighs the tracked rise by, and a model choice's share
                    // (which moves Re and the rise's reference alike) weakened that fit
                    // until it left out the convection (Rtv 29 % off).
                    // (A fit without an sd keeps NaN: `max` would make it 0.)
                    let (sd, model) = (lin.sigma_rel[0], lin.model_rel[0]);
                    let stat = if sd.is_nan() { sd } else { (sd * sd - model * model).max(0.0).sqrt() };
                    self.re_cold_sd = stat * p.re;
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
                                    self.before_last = None;
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
                        let bands = curve_bands(&est, self.prev_est.as_ref(), on, &xs, self.le_model_rel);
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
                        self.before_last = self.prev_est.replace(est);
                        // Convergence: at level for 2 s, small window error, stable curves.
                        // The stable updates must span CONVERGED_SPAN_S (2 updates at the
                        // real-time cadence of 1 s, more when a replay updates every window).
                        let n = self.changes.len();
                        let k = ((CONVERGED_SPAN_S / every).round() as usize).max(2);
                        self.eta_at = self.expected_convergence(t, w, every, k);
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
                    let x_limit = self.x_limit();
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
        live.eta = self.eta(t);
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
        let x_limit = self.x_limit();
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
            before_last: self.before_last.clone(),
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
            x_limit,
            max_dt: self.opts.max_dt,
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

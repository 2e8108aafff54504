//! Large-signal identification from voltage and current (seed section 3.2.2.2): the
//! **output error of the parallel model**.
//!
//! The model of [`coilscope_core::model`] is driven by the measured voltage; its current is
//! compared with the measured current, and Levenberg-Marquardt minimises
//! `sum_m (i_model[m] - i_meas[m])^2` over
//!
//! * `Re(t)`: the voice-coil resistance, piecewise linear in time (knots every
//!   [`IdentifyOptions::knot_seconds`]), so the heating of the coil during the record is
//!   tracked, whatever the thermal constants; `Re` of the result is the value at the start and
//!   the voice-coil temperature rise follows as `(Re(t)/Re(0) - 1)/alpha`;
//! * `Le(x)`, `Bl(x)`, `Kms(x)`: power series of the selected order;
//! * `L2`, `R2` (constants) and `Rms`; `Mms` is given (it fixes the absolute scale).
//!
//! The series are parametrised internally by Legendre polynomials in `x / x_ref` (well
//! conditioned at order 8) and converted to the contract's power series in metres.
//!
//! Exact Jacobians: the same model runs on vector dual numbers ([`num_dual::DualSVec64`]),
//! [`CHUNK`] parameters at a time; the chunks are independent and run on all cores. The
//! Jacobian runs use the fewest RK4 sub-steps that keep the fast electrical mode inside
//! RK4's accurate region (`|lambda| h <= 1.5`); the residual uses the simulator's own count.
//!
//! The solver ([`crate::lm::lm_step`]) is a pure state transition; [`identify`] hands every
//! iteration to an observer (progress bars, logs) as a [`Progress`].
//!
//! The parts, each in its file: `layout` (the unknowns and the model runs on them),
//! `problem` (the output error, its residual and Jacobians), `chain_setup` (the measurement
//! chain inside it), `search` (the stages' windows, stops and effect screening) and `record`
//! (the work on one record, from the start to the final fit); here, the options, the result
//! ([`LargeFit`]) and [`identify`].

use crate::linear::{
    check_channels, fit_linear_record, scale_by_mms, Effects, EffectsChoice, LinearFit, LinearOptions,
};
use crate::lm::{lm_step_accelerated, AtLastTrial, LmState, Problem};
use coilscope_core::enclosure::{BoxKind, BoxModel, Enclosure, KMP_TERMS};
use coilscope_core::integrate::{Electrical, FlushTiny, Rates, Scheme, Stepper};
use coilscope_core::jet::Jet;
use coilscope_core::model::{idx, ExtModel, Model, Parts, NBOX, NEXT, NLR3, NSTATE};
use coilscope_core::params::Parameters;
use coilscope_core::poly::Poly;
use coilscope_core::result::{Fit, ModelTrial, ResultFile, Sd, Thermal, Uncertainty};
use coilscope_core::schema;
use nalgebra::{DMatrix, DVector};
use num_dual::{DualNum, DualSVec64};
use std::ops::Range;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

mod chain_setup;
mod layout;
mod problem;
mod record;
mod search;
#[cfg(test)]
mod tests;

pub use chain_setup::*;
pub use layout::*;
pub use problem::*;
pub use record::*;
pub use search::*;

/// Options of [`identify`].
#[derive(Clone, Debug)]
pub struct IdentifyOptions {
    /// Moving mass (kg): the absolute scale.
    pub mms: f64,
    /// Power-series order of Bl, Kms and Le; `None`: chosen by validation on held-out data.
    pub order: Option<usize>,
    /// Start values; `None`: the linear (impedance) fit of the same record, scaled by `mms`.
    pub init: Option<Parameters>,
    /// Seconds between the knots of the `Re(t)` track.
    pub knot_seconds: f64,
    /// Share of the search window used for estimation while the order and the effects are
    /// chosen (the rest of the window validates).
    pub estimation_share: f64,
    /// Seconds of the record the order and effects search works on (the final fit takes the
    /// whole record): the shortest prefix of at least this length, in steps of half of it,
    /// whose estimation part reaches [`SEARCH_REACH`] of the record's excursion on both sides
    /// and whose validation part [`SEARCH_VALIDATION_REACH`] of it ([`search_window`]);
    /// 0 or a record shorter than that: the whole record.
    pub search_seconds: f64,
    /// LM iterations of the final fit.
    pub max_iterations: usize,
    /// Worker threads for the Jacobian (0: all cores).
    pub threads: usize,
    /// Creep and LR-3: chosen on held-out data, or given.
    pub effects: EffectsChoice,
    /// Estimate the measurement chain with the driver ([`ChainSetup`]): the delay, both
    /// corners, offsets and hum, all of them, from the start values of a linear fit with the
    /// chain.
    pub chain: bool,
    /// Without `chain`: estimate it when the record shows one. The linear fit with the chain
    /// runs beside the start's (as with `chain`), and when it keeps a delay or a corner that
    /// stands out of its sd ([`crate::linear::CHAIN_SIGNIFICANCE`]) the fit takes the chain
    /// ([`LargeFit::chain_detected`] says what was seen); otherwise it is the plain fit.
    pub detect_chain: bool,
    /// The driver is in a box ([`InBox`]): the box's values are identified with the
    /// driver's. `None`: free air.
    pub enclosure: Option<InBox>,
}

/// A driver identified in its box ([`IdentifyOptions::enclosure`]). The start is the joint
/// small-signal fit of the driver and the box ([`crate::box_fit::fit_driver_in_box`]) on the
/// record's first seconds, unless [`IdentifyOptions::init`] gives a set with its
/// `enclosure`; the large-signal fit then has the box's values among its unknowns
/// ([`BoxUnknowns`]).
#[derive(Clone, Debug, PartialEq)]
pub struct InBox {
    pub choice: crate::box_fit::BoxChoice,
    /// The driver's radiating area (m^2).
    pub sd: f64,
    /// A closed box's net volume (m^3), which the terminals cannot separate from the
    /// suspension's stiffness; with a port or a radiator a start for the fit, or `None`.
    pub vb: Option<f64>,
    /// The port's area (m^2): the quadratic loss is then reported as `port_loss`.
    pub port_area: Option<f64>,
    /// The radiator's area (m^2); `None`: `Sd`.
    pub sp: Option<f64>,
}

impl Default for IdentifyOptions {
    fn default() -> Self {
        IdentifyOptions {
            mms: f64::NAN,
            order: None,
            init: None,
            knot_seconds: 2.0,
            estimation_share: 0.7,
            search_seconds: 5.0,
            max_iterations: 40,
            threads: 0,
            effects: EffectsChoice::Auto,
            chain: false,
            detect_chain: false,
            enclosure: None,
        }
    }
}

/// What the fit is doing, for observers.
#[derive(Clone, Debug, PartialEq)]
pub enum Stage {
    /// Order `n` fitted on the estimation part.
    Estimate { order: usize },
    /// The chosen order fitted on the whole record.
    Final { order: usize },
}

/// One observed iteration.
#[derive(Clone, Debug)]
pub struct Progress<'a> {
    pub stage: Stage,
    pub state: &'a LmState,
    /// `||r|| / ||i||` over the fitted samples at this state.
    pub residual_rel: f64,
}

/// Validation record of one candidate order: `||i_model - i|| / ||i||` on the estimation part
/// and on the held-out part.
pub use coilscope_core::result::OrderTrial;

/// A large-signal fit.
#[derive(Clone, Debug)]
pub struct LargeFit {
    /// The identified parameters (`Re` at the start, `x_range` = the reached range).
    pub params: Parameters,
    pub layout: Layout,
    pub theta: Vec<f64>,
    /// Covariance of theta (noise only; see [`LargeFit::sd`]).
    pub cov: Option<DMatrix<f64>>,
    /// `||i_model - i|| / ||i||` over the fitted samples.
    pub residual_rel: f64,
    /// Range of x the model reached on this record (m).
    pub x_range: [f64; 2],
    pub order: usize,
    pub trials: Vec<OrderTrial>,
    /// The models with effects tried at the chosen order, with their held-out current error
    /// (empty when the effects were given).
    pub effect_trials: Vec<(String, f64)>,
    /// The models of `effect_trials` whose fit went on alone before a trial from them could
    /// be taken (`base_goes_on_alone`), with their held-out error before
    /// (`effect_trials` holds the error after).
    pub effect_went_on: Vec<(String, f64)>,
    /// The models the effects search screened (`screen_effects`); those below
    /// [`EFFECT_SCREEN_GAIN`] or outscored by the round's winner ([`EFFECT_RIVAL_RATIO`])
    /// were not fitted (not in `effect_trials`).
    pub effect_screens: Vec<EffectScreen>,
    pub iterations: usize,
    pub converged: bool,
    /// Why the final fit stopped.
    pub stop_reason: String,
    /// `(t, Re(t))` at the knots.
    pub re_track: Vec<(f64, f64)>,
    /// Sub-steps of the residual and of the Jacobian runs.
    pub substeps: (usize, usize),
    /// Their schemes.
    pub schemes: (Scheme, Scheme),
    /// Samples skipped at the start while the unknown initial state settles.
    pub settle: usize,
    /// Sample rate (Hz).
    pub fs: f64,
    /// The linear start (None when the caller gave one).
    pub linear: Option<LinearFit>,
    /// The predicted current and displacement of the final model (A, m): the driver's
    /// physical current, behind the chain.
    pub i_model: Vec<f64>,
    pub x_model: Vec<f64>,
    /// The measurement chain estimated with the driver (None: `IdentifyOptions::chain` off,
    /// and no chain found with `IdentifyOptions::detect_chain`).
    pub chain: Option<coilscope_core::chain::Chain>,
    /// What made the fit take the chain when it looked for one (`detect_chain`).
    pub chain_detected: Option<String>,
    /// The driver's voltage and current behind the estimated chain (the recorded ones without
    /// a chain): what `i_model` is to be compared with.
    pub u_phys: Vec<f64>,
    pub i_phys: Vec<f64>,
    /// The order search's evidence on the truncation of the power series: the curves of the
    /// chosen order and of the next one tried (and not kept), both fitted on the estimation
    /// part (None: the order was given, or no higher order was tried). Their difference is
    /// the bands' truncation part ([`LargeFit::band`]).
    pub truncation: Option<Truncation>,
}

/// Bl(x), Kms(x) and Le(x) fitted at the chosen order and at the next order the search tried,
/// on the same data ([`LargeFit::truncation`]).
#[derive(Clone, Debug)]
pub struct Truncation {
    pub next_order: usize,
    pub chosen: [Poly; 3],
    pub next: [Poly; 3],
}

impl Truncation {
    fn of(lay_chosen: &Layout, th_chosen: &[f64], lay_next: &Layout, th_next: &[f64]) -> Self {
        let (a, b) = (lay_chosen.parameters(th_chosen), lay_next.parameters(th_next));
        Truncation { next_order: lay_next.order, chosen: [a.bl, a.kms, a.le], next: [b.bl, b.kms, b.le] }
    }

    /// |next(x) - chosen(x)| of `Bl`, `Kms` or `Le`.
    pub fn at(&self, which: &str, x: f64) -> f64 {
        let k = match which {
            "Bl" => 0,
            "Kms" => 1,
            _ => 2,
        };
        (self.next[k].eval(x) - self.chosen[k].eval(x)).abs()
    }
}

/// A fit that could not be made, or whose result cannot be trusted.
#[derive(Clone, Debug)]
pub enum IdentifyError {
    /// Bad input: the message names the file and what would be valid.
    Input(String),
    /// The excitation did not reach far enough for the nonlinearities to show.
    TooSmall(String),
    /// The fit did not converge; the best estimate so far is kept.
    NotConverged { message: String, best: Box<LargeFit> },
}

impl std::fmt::Display for IdentifyError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            IdentifyError::Input(m) | IdentifyError::TooSmall(m) => f.write_str(m),
            IdentifyError::NotConverged { message, .. } => f.write_str(message),
        }
    }
}

/// Identify the large-signal parameters from voltage `u` (V) and current `i` (A) sampled at
/// `fs`. `origin` names the recording in messages.
pub fn identify(
    u_rec: &[f64],
    i_rec: &[f64],
    fs: f64,
    origin: &str,
    opts: &IdentifyOptions,
    mut observe: impl FnMut(&Progress),
) -> Result<LargeFit, IdentifyError> {
    let fit = identify_record(u_rec, i_rec, fs, origin, opts, &mut observe);
    // The fit's spare Jacobians (up to 2 x 90 MB) are not kept past it.
    release_spare_jacobians();
    fit
}

/// A function of x with its standard deviation on a grid (a confidence band: +- 2 sd is
/// about 95 %).
pub use coilscope_core::result::Band;

impl LargeFit {
    /// Covariance of theta entries `j` and `k` (NaN without a covariance).
    fn cov_theta(&self, j: usize, k: usize) -> f64 {
        self.cov.as_ref().map_or(f64::NAN, |c| c[(j, k)])
    }

    /// Standard deviations (SI) of the fitted constants, in the schema's order: Re (at the
    /// start), L2, R2, L3, R3, creep.lambda, Rms, as the layout has them ([`Layout::sd_of`]).
    pub fn sd(&self) -> Vec<(&'static str, f64)> {
        schema::ENTRIES
            .iter()
            .filter_map(|e| match self.layout.sd_of(e.key, &self.theta, &|j, k| self.cov_theta(j, k)) {
                Some(Sd::Value(v)) => Some((e.key, v)),
                _ => None,
            })
            .collect()
    }

    /// The systematic part of a curve's band, relative to its value: [`LE_DELAY_SYSTEMATIC_REL`]
    /// for Le when the chain's delay was estimated, else [`CURVE_SYSTEMATIC_REL`].
    pub fn systematic_rel(&self, which: &str) -> f64 {
        let delay = self.chain.as_ref().is_some_and(|c| c.fitted.iter().any(|f| f == "delay_i"));
        if which == "Le" && delay {
            LE_DELAY_SYSTEMATIC_REL
        } else {
            CURVE_SYSTEMATIC_REL
        }
    }

    /// Band of `Bl`, `Kms` or `Le` over the reached range (`points` x values).
    pub fn band(&self, which: &str, points: usize) -> Band {
        let f = match which {
            "Bl" => &self.params.bl,
            "Kms" => &self.params.kms,
            _ => &self.params.le,
        };
        let [lo, hi] = self.x_range;
        let x: Vec<f64> = (0..points).map(|k| lo + (hi - lo) * k as f64 / (points - 1).max(1) as f64).collect();
        let value = x.iter().map(|&x| f.eval(x)).collect();
        let sd = x
            .iter()
            .zip(&value)
            .map(|(&x, v): (&f64, &f64)| {
                let stat = self.cov.as_ref().map_or(f64::NAN, |c| self.layout.curve_sd(c, which, x));
                let trunc = self.truncation.as_ref().map_or(0.0, |t| t.at(which, x));
                stat.hypot(self.systematic_rel(which) * v).hypot(trunc)
            })
            .collect();
        Band { x, value, sd }
    }

    /// Voice-coil temperature rise at the knots (K), from `Re(t)` and the copper coefficient.
    pub fn temperature_track(&self, alpha: f64) -> Vec<(f64, f64)> {
        let r0 = self.re_track[0].1;
        self.re_track.iter().map(|&(t, r)| (t, (r / r0 - 1.0) / alpha)).collect()
    }

    /// The effects search's models (`fit.models_tried`): each one fitted with its held-out
    /// error, then each one the screen left out, with its screen gain (and none fitted).
    pub fn models_tried(&self) -> Vec<ModelTrial> {
        let screen = |m: &str| self.effect_screens.iter().find(|s| s.model.model_name() == m).map(|s| s.gain);
        let before = |m: &str| self.effect_went_on.iter().find(|(w, _)| w == m).map(|(_, v)| *v);
        let fitted = self.effect_trials.iter().map(|(m, v)| ModelTrial {
            model: m.clone(),
            validation_rel: Some(*v),
            screen_gain: screen(m),
            validation_rel_before: before(m),
            ..Default::default()
        });
        let skipped = self.effect_screens.iter().filter(|s| s.not_fitted()).map(|s| ModelTrial {
            model: s.model.model_name(),
            screen_gain: Some(s.gain),
            outscored_by: s.outscored_by.map(|e| e.model_name()),
            ..Default::default()
        });
        fitted.chain(skipped).collect()
    }

    /// The result file (`"format": "coilscope.result/1"`).
    pub fn result(&self, recording: &str, mms_source: &str) -> ResultFile {
        let mut unc = Uncertainty::new(format!(
            "standard deviations from the final Jacobian and the residual variance (sensor noise; Mms is taken as exact). Bands: value and sd on a grid over fit.x_range, the sd including a systematic 0.01 % of the value (measured against an independent simulator and its anti-alias chain; Re's sd too); with the chain estimated, a systematic {DELAY_SYSTEMATIC_SAMPLES:.1e} sample on its delay, carried to what correlates with it, and {:.2} % of Le(x) in place of the 0.01 % (what the delay and Le share){}; +-2 sd is about 95 %",
            LE_DELAY_SYSTEMATIC_REL * 100.0,
            match &self.truncation {
                Some(t) => format!("; and the power series' truncation: the difference between the curves of order {} and of order {} (the next the order search tried), both fitted on the same data", self.order, t.next_order),
                None => String::new(),
            }
        ));
        self.layout.uncertainties(&self.theta, &|j, k| self.cov_theta(j, k), &|_| true, &mut unc);
        // The cold Re carries the same systematic share as the curves: the first knot of the
        // Re(t) track is where the coil's heating within a knot interval biases it.
        if let Some(v) = unc.value("Re") {
            unc.set("Re", v.hypot(CURVE_SYSTEMATIC_REL * self.params.re));
        }
        for which in ["Bl", "Kms", "Le"] {
            unc.set_band(which, self.band(which, 41));
        }
        let fit = Fit {
            method: Some("output-error (parallel model): measured voltage in, current compared".into()),
            residual_rel: self.residual_rel,
            x_range: self.x_range,
            order: Some(self.order),
            model: self.layout.effects.model_name(),
            models_tried: Some(self.models_tried()),
            order_trials: Some(self.trials.clone()),
            iterations: Some(self.iterations),
            converged: Some(self.converged),
            stop_reason: Some(self.stop_reason.clone()),
            substeps: Some([self.substeps.0, self.substeps.1]),
            schemes: Some([self.schemes.0.name().to_string(), self.schemes.1.name().to_string()]),
            settle_s: Some(self.settle as f64 / self.fs),
            mms_source: Some(mms_source.into()),
            ..Default::default()
        };
        let lim = coilscope_core::limits::limits(&self.params, self.x_range);
        let mut r = ResultFile::new("large-signal", recording, self.params.clone(), fit, unc, Some(&lim));
        let alpha = 0.00393;
        let temps = self.temperature_track(alpha);
        r.thermal = Some(Thermal {
            note: if self.layout.heat_taus.is_empty() {
                format!("Re(t) tracked piecewise linearly (knots every {:.2} s); temperature rise = (Re(t)/Re(0) - 1)/alpha with alpha = 0.00393 1/K (copper)", self.layout.knot_dt)
            } else {
                format!("Re(t) tracked piecewise linearly (knots every {:.2} s) plus heating terms, first-order responses to the measured i^2 with time constants {:?} s (the knots could not follow the heating); temperature rise = (Re(t)/Re(0) - 1)/alpha with alpha = 0.00393 1/K (copper)", self.layout.knot_dt, self.layout.heat_taus)
            },
            heating_terms_tau_s: Some(self.layout.heat_taus.clone()),
            re_track: Some(self.re_track.clone()),
            dt_end: temps.last().map(|t| t.1),
            dt_track: temps,
            ..Default::default()
        });
        r.chain = self.chain.clone();
        r
    }
}

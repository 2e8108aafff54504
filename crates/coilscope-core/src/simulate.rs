//! The virtual transducer: the model driven by a sampled voltage.
//!
//! [`Simulator`] integrates [`crate::model::Model`] sample by sample (band-limited input,
//! RK4 sub-steps, see [`crate::integrate`]) and guards the valid range: a trajectory that
//! leaves the parameters' `x_range` (plus a margin) or becomes non-finite stops with a
//! [`SimError`] that names the time and the state.

use crate::integrate::{exp_steps_for, substeps_for, Electrical, Scheme, Stepper, STIFF_LIMIT};
use crate::model::{ext_idx, idx, ExtModel, ExtState, Model, State, NBOX, NCREEP, NEXT, NSTATE};

/// The model a simulation integrates, one sample at a time: [`Model`] (six states, the fast
/// path, with Le(i) and Rms(v)), or [`ExtModel`] when the set has creep, LR-3 or a box (their
/// states kept here, [`NBOX`] of them, of which a set without a box integrates the first
/// [`NEXT`]; the first six mirror the caller's state, which stays the one source of x, v, i,
/// ...).
#[derive(Clone, Debug)]
pub struct Plant {
    model: Model<f64>,
    ext: Option<(ExtModel<f64>, [f64; NBOX])>,
    /// A constant external force on the cone over the moving mass (m/s^2; 0: none).
    accel: f64,
}

/// A system with a constant acceleration added to its velocity's rate: an external force
/// on the cone (`SimOptions::force`).
struct Pushed<'a, S> {
    sys: &'a S,
    accel: f64,
}

impl<S: crate::integrate::Dynamics<f64, N>, const N: usize> crate::integrate::Dynamics<f64, N> for Pushed<'_, S> {
    #[inline]
    fn deriv(&self, y: &[f64; N], u: f64) -> [f64; N] {
        let mut d = self.sys.deriv(y, u);
        d[idx::V] += self.accel;
        d
    }
}

/// One sample of `sys` with `stepper`, pushed by the external acceleration `accel` (m/s^2)
/// where it is not zero.
fn pushed_sample<S: Electrical<f64, N>, const N: usize>(
    stepper: &Stepper,
    sys: &S,
    accel: f64,
    y: &[f64; N],
    dt: f64,
    u_points: &[f64],
) -> [f64; N] {
    if accel == 0.0 {
        stepper.sample(sys, y, dt, u_points)
    } else {
        stepper.sample(&Pushed { sys, accel }, y, dt, u_points)
    }
}

impl<S: Electrical<f64, N>, const N: usize> Electrical<f64, N> for Pushed<'_, S> {
    #[inline]
    fn electrical(&self, y: &[f64; N]) -> [[f64; 2]; 2] {
        self.sys.electrical(y)
    }

    #[inline]
    fn input(&self, y: &[f64; N]) -> f64 {
        self.sys.input(y)
    }
}

impl Plant {
    pub fn new(params: &Parameters) -> Self {
        Plant {
            model: Model::new(params),
            ext: params.needs_ext_states().then(|| (ExtModel::new(params), [0.0; NBOX])),
            accel: 0.0,
        }
    }

    /// The plant with a constant external force `force` (N, + pushes the coil out) on the
    /// cone: an added mass under gravity, or a pressure on the diaphragm.
    pub fn with_force(params: &Parameters, force: f64) -> Self {
        Plant { accel: force / params.mms, ..Plant::new(params) }
    }

    /// Change the external force and the parameters (an added mass) mid-run; the extended
    /// states (creep, LR-3, ...) carry on where they were.
    pub fn set_force(&mut self, params: &Parameters, force: f64) {
        let ext = self.ext.take().map(|(_, s)| s);
        *self = Plant::with_force(params, force);
        if let (Some((_, s)), Some(old)) = (self.ext.as_mut(), ext) {
            *s = old;
        }
    }

    /// Why the model is not valid at `state` (`None`: it is). With `Le_i`, the voice coil's
    /// incremental inductance `Le(x) h(i)` must stay above [`MIN_INCREMENTAL_LE`] of `Le(x)`:
    /// past that, the series is extrapolated beyond any measured current (and at zero the
    /// current equation is singular).
    pub fn invalid_at(&self, state: &State<f64>) -> Option<String> {
        self.model.le_i.as_ref()?;
        let i = state[idx::I];
        let h = self.model.le_i_incremental(i);
        (!(h >= MIN_INCREMENTAL_LE)).then(|| format!("Le_i drives the incremental inductance to {:.0} % of Le(x) at i = {i:.3} A (below {:.0} %: the flux series is extrapolated past its valid current)", 100.0 * h, 100.0 * MIN_INCREMENTAL_LE))
    }

    /// The rates of the six observed states at `state` under the input `u`, with the
    /// extended states (creep, LR-3) where the plant carries them and the external force.
    pub fn deriv(&self, state: &State<f64>, u: f64) -> State<f64> {
        let mut d = match &self.ext {
            None => self.model.deriv(state, u),
            Some((model, s)) => {
                let mut full = *s;
                full[..NSTATE].copy_from_slice(state);
                let d = model.deriv_n(&full, u);
                std::array::from_fn(|k| d[k])
            }
        };
        d[idx::V] += self.accel;
        d
    }

    /// The extended states (LR-3's current, creep's damper positions) the plant carries
    /// beside the six observed ones; `None` for a set without them.
    pub fn ext_state(&self) -> Option<ExtState<f64>> {
        self.ext.as_ref().map(|(_, s)| std::array::from_fn(|k| s[k]))
    }

    /// The box's states ([`crate::enclosure::NBOXSTATE`]: its gauge pressure in Pa, then the
    /// port's flow in m^3/s or the radiator's excursion in m and velocity in m/s); `None`
    /// without a box.
    pub fn box_state(&self) -> Option<[f64; crate::enclosure::NBOXSTATE]> {
        let (model, s) = self.ext.as_ref()?;
        model.enclosure.as_ref()?;
        Some(std::array::from_fn(|k| s[ext_idx::BOX + k]))
    }

    /// Put creep's damper positions on their periodic orbit after a window of `period`
    /// seconds that started at `start` (a state of [`Plant::ext_state`]). Each damper
    /// follows `dy/dt = (x - y) / tau`, linear in `y`: over a window,
    /// `y(T) = e^(-T/tau) y(0) + F`, and the orbit a periodic `x` leads to starts at
    /// `F / (1 - e^(-T/tau))`. The slowest damper relaxes in 3.2 s: a periodic steady state
    /// reached by running window after window would take tens of seconds, and with this
    /// jump it takes a few windows.
    pub fn settle_creep_to_period(&mut self, start: &ExtState<f64>, period: f64) {
        let Some((model, s)) = self.ext.as_mut() else { return };
        let Some(bank) = &model.creep else { return };
        for k in 0..NCREEP {
            let j = ext_idx::Y0 + k;
            let decay = (-period * bank.rate[k]).exp();
            s[j] = (s[j] - decay * start[j]) / (1.0 - decay);
        }
    }

    /// Advance `state` by one sample period `dt` with `stepper`, the input at the points of
    /// [`Stepper::fill`].
    pub fn step(&mut self, stepper: &Stepper, state: &mut State<f64>, dt: f64, u_points: &[f64]) {
        let accel = self.accel;
        match &mut self.ext {
            None => *state = pushed_sample(stepper, &self.model, accel, state, dt, u_points),
            Some((model, s)) => {
                s[..NSTATE].copy_from_slice(state);
                if model.enclosure.is_some() {
                    *s = pushed_sample(stepper, &*model, accel, s, dt, u_points);
                } else {
                    // Without a box its states stay at zero: integrate the first NEXT.
                    let e: ExtState<f64> = std::array::from_fn(|k| s[k]);
                    s[..NEXT].copy_from_slice(&pushed_sample(stepper, &*model, accel, &e, dt, u_points));
                }
                state.copy_from_slice(&s[..NSTATE]);
            }
        }
    }
}
use crate::params::Parameters;
use std::fmt;

/// The smallest incremental inductance factor `h(i) = d(i g(i))/di` of `Le_i` a simulation
/// accepts (see [`Plant::invalid_at`]).
pub const MIN_INCREMENTAL_LE: f64 = 0.5;

/// How far past `x_range` a trajectory may extrapolate before the simulation stops,
/// as a fraction of the range's half-width on that side.
pub const RANGE_MARGIN: f64 = 0.10;

/// Simulation options.
#[derive(Clone, Debug)]
pub struct SimOptions {
    /// Steps per sample; `None` chooses them from the driver's electrical rates
    /// ([`crate::integrate::exp_steps_for`], or [`substeps_for`] for RK4).
    pub substeps: Option<usize>,
    /// The integration scheme; `None`: the cheaper at its accuracy
    /// ([`Stepper::for_rates`]), or classical RK4 when `substeps` is given (a tiny-step
    /// reference).
    pub scheme: Option<Scheme>,
    /// Initial state (rest by default).
    pub initial: State<f64>,
    /// Allowed extrapolation past `x_range` (fraction of the half-width).
    pub range_margin: f64,
    /// A constant external force on the cone (N, + pushes the coil out) from the start: an
    /// added mass under gravity (give the set `Mms` with the mass added) or a pressure on the
    /// diaphragm (`p Sd`). The quasi-static method's offsets without current.
    pub force: f64,
}

impl Default for SimOptions {
    fn default() -> Self {
        SimOptions { substeps: None, scheme: None, initial: [0.0; NSTATE], range_margin: RANGE_MARGIN, force: 0.0 }
    }
}

/// Why a simulation stopped.
#[derive(Clone, Debug, PartialEq)]
pub enum SimError {
    /// The state left the region where the model is valid.
    OutOfRange { t: f64, sample: usize, state: State<f64>, reason: String },
    /// Bad arguments (sample rate, empty input, non-finite input).
    Input(String),
}

fn fmt_state(s: &State<f64>) -> String {
    format!(
        "x = {:.4} mm, v = {:.4} m/s, i = {:.4} A, i2 = {:.4} A, dTv = {:.3} K, dTm = {:.3} K",
        s[idx::X] * 1e3,
        s[idx::V],
        s[idx::I],
        s[idx::I2],
        s[idx::TV],
        s[idx::TM]
    )
}

impl fmt::Display for SimError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            SimError::OutOfRange { t, sample, state, reason } => {
                write!(f, "simulation stopped at t = {t:.6} s (sample {sample}): {reason}; state: {}. Lower the level, add a high-pass, or use parameters measured over a wider range", fmt_state(state))
            }
            SimError::Input(m) => write!(f, "{m}"),
        }
    }
}

impl std::error::Error for SimError {}

/// The simulated signals at the sample instants.
#[derive(Clone, Debug, Default)]
pub struct Trace {
    pub fs: f64,
    pub u: Vec<f64>,
    pub x: Vec<f64>,
    pub v: Vec<f64>,
    pub i: Vec<f64>,
    pub i2: Vec<f64>,
    pub tv: Vec<f64>,
    pub tm: Vec<f64>,
    /// Steps per sample that were used, of [`Trace::scheme`].
    pub substeps: usize,
    /// The integration scheme that was used.
    pub scheme: Scheme,
    /// Largest excursion past `x_range` (m, 0 if none): extrapolated, within the margin.
    pub range_excess: f64,
    /// The box's states at the sample instants ([`Plant::box_state`]: gauge pressure in Pa,
    /// then the port's flow in m^3/s or the radiator's excursion in m and velocity in m/s);
    /// empty in free air.
    pub boxed: Vec<[f64; crate::enclosure::NBOXSTATE]>,
}

/// Summary figures of a trace (the same keys as `shared/recordings/*.info.json`).
#[derive(Clone, Debug, PartialEq)]
pub struct Summary {
    pub x_min: f64,
    pub x_max: f64,
    /// 0.5 and 99.5 percentiles of x.
    pub x_p01: f64,
    pub x_p99: f64,
    pub u_rms: f64,
    pub i_rms: f64,
    /// Mean electrical input power (W).
    pub p_mean: f64,
    pub dt_end: f64,
    pub dt_max: f64,
    pub dtm_end: f64,
}

pub fn rms(s: &[f64]) -> f64 {
    if s.is_empty() {
        return 0.0;
    }
    (s.iter().map(|x| x * x).sum::<f64>() / s.len() as f64).sqrt()
}

fn percentile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let pos = q * (sorted.len() - 1) as f64;
    let lo = pos.floor() as usize;
    let hi = pos.ceil() as usize;
    sorted[lo] + (sorted[hi] - sorted[lo]) * (pos - lo as f64)
}

impl Trace {
    pub fn summary(&self) -> Summary {
        let mut xs = self.x.clone();
        xs.sort_by(f64::total_cmp);
        let n = self.u.len().max(1) as f64;
        Summary {
            x_min: xs.first().copied().unwrap_or(0.0),
            x_max: xs.last().copied().unwrap_or(0.0),
            x_p01: percentile(&xs, 0.005),
            x_p99: percentile(&xs, 0.995),
            u_rms: rms(&self.u),
            i_rms: rms(&self.i),
            p_mean: self.u.iter().zip(&self.i).map(|(u, i)| u * i).sum::<f64>() / n,
            dt_end: self.tv.last().copied().unwrap_or(0.0),
            dt_max: self.tv.iter().copied().fold(0.0, f64::max),
            dtm_end: self.tm.last().copied().unwrap_or(0.0),
        }
    }
}

/// The virtual transducer.
#[derive(Clone, Debug)]
pub struct Simulator {
    plant: Plant,
    pub params: Parameters,
    pub fs: f64,
    stepper: Stepper,
    /// Hard bounds on x (x_range plus margin), if the set has a range.
    bounds: Option<[f64; 2]>,
    range: Option<[f64; 2]>,
    pub state: State<f64>,
    scratch: Vec<f64>,
}

impl Simulator {
    pub fn new(params: &Parameters, fs: f64, opts: &SimOptions) -> Result<Self, SimError> {
        if !(fs.is_finite() && (1000.0..=1.0e6).contains(&fs)) {
            return Err(SimError::Input(format!("sample rate {fs} Hz is not valid (1 kHz .. 1 MHz)")));
        }
        let stepper = match (opts.scheme, opts.substeps) {
            (None, None) => Stepper::for_rates(params.rates(), fs),
            (None, Some(n)) | (Some(Scheme::Rk4), Some(n)) => Stepper::new(Scheme::Rk4, n),
            (Some(Scheme::Rk4), None) => Stepper::new(Scheme::Rk4, substeps_for(params.rates().total(), fs)),
            (Some(Scheme::Exponential), n) => {
                Stepper::new(Scheme::Exponential, n.unwrap_or_else(|| exp_steps_for(params.rates(), fs)))
            }
            (Some(Scheme::ExpCurrent), n) => {
                Stepper::new(Scheme::ExpCurrent, n.unwrap_or_else(|| exp_current_steps(params, fs)))
            }
            (Some(s @ (Scheme::Midpoint | Scheme::ExpMidpoint)), _) => {
                return Err(SimError::Input(format!(
                    "the {} rule is the search's Jacobian scheme, not a simulation's: take rk4 or exponential",
                    s.name()
                )))
            }
        };
        let points = stepper.points();
        let bounds = params.x_range.map(|[lo, hi]| [lo * (1.0 + opts.range_margin), hi * (1.0 + opts.range_margin)]);
        Ok(Simulator {
            plant: Plant::with_force(params, opts.force),
            params: params.clone(),
            fs,
            stepper,
            bounds,
            range: params.x_range,
            state: opts.initial,
            scratch: vec![0.0; points],
        })
    }

    /// Sub-steps per sample.
    pub fn substeps(&self) -> usize {
        self.stepper.n()
    }

    fn check(&self, s: &State<f64>, m: usize) -> Result<(), SimError> {
        let t = m as f64 / self.fs;
        let fail = |reason: String| Err(SimError::OutOfRange { t, sample: m, state: *s, reason });
        if s.iter().any(|v| !v.is_finite()) {
            return fail("the state is no longer finite (the integration diverged)".into());
        }
        if let Some(why) = self.plant.invalid_at(s) {
            return fail(why);
        }
        let x = s[idx::X];
        match self.bounds {
            Some([lo, hi]) => {
                if x < lo || x > hi {
                    let r = self.range.unwrap_or([lo, hi]);
                    return fail(format!("x = {:.3} mm is outside x_range [{:.3}, {:.3}] mm (+{:.0} % margin), where the parameters are not valid", x * 1e3, r[0] * 1e3, r[1] * 1e3, 100.0 * (hi / r[1] - 1.0)));
                }
            }
            None => {
                let p = &self.params;
                for (name, v) in [("Bl", p.bl.eval(x)), ("Kms", p.kms.eval(x)), ("Le", p.le.eval(x))] {
                    if !(v > 0.0) {
                        return fail(format!(
                            "{name}({:.3} mm) = {v:.4e} is not positive (the set has no x_range)",
                            x * 1e3
                        ));
                    }
                }
            }
        }
        Ok(())
    }

    /// Run over a whole voltage record, calling `observe(m, state)` with the state at each
    /// sample instant `m / fs` (before the step to `m + 1`).
    pub fn run(&mut self, u: &[f64], mut observe: impl FnMut(usize, &State<f64>)) -> Result<(), SimError> {
        self.run_boxed(u, |m, s, _| observe(m, s))
    }

    /// [`Simulator::run`], observing the box's states too ([`Plant::box_state`]; `None` in
    /// free air).
    pub fn run_boxed(
        &mut self,
        u: &[f64],
        mut observe: impl FnMut(usize, &State<f64>, Option<[f64; crate::enclosure::NBOXSTATE]>),
    ) -> Result<(), SimError> {
        if let Some(k) = u.iter().position(|v| !v.is_finite()) {
            return Err(SimError::Input(format!("input voltage sample {k} is not finite ({})", u[k])));
        }
        let dt = 1.0 / self.fs;
        for m in 0..u.len() {
            self.check(&self.state, m)?;
            observe(m, &self.state, self.plant.box_state());
            self.stepper.fill(u, m, &mut self.scratch);
            self.plant.step(&self.stepper, &mut self.state, dt, &self.scratch);
        }
        Ok(())
    }
}

/// Steps per sample of [`Scheme::ExpCurrent`]: what it leaves to RK4's weights (the rates of
/// [`Parameters::rates`] less the current's own decay `Re / Le`: the LR-2 branch's coupling
/// and decay, an LR-3 branch) resolved as RK4's sub-steps are ([`STIFF_LIMIT`]), at least
/// one. A woofer: one (SB17 leaves 3.2e3 /s, 0.07 per sample at 48 kHz); the stiff
/// microspeakers of `testdata/drivers`: 9 and 11 at 48 kHz (their current then within
/// 1.9-2.2e-6 of 256 RK4 sub-steps), where [`Scheme::Exponential`] takes 3.
pub fn exp_current_steps(p: &Parameters, fs: f64) -> usize {
    let (lo, hi) = p.x_range.map_or((0.0, 0.0), |r| (r[0], r[1]));
    let left = (p.rates().total() - p.re / p.le.min_max_on(lo, hi).0).max(0.0);
    ((left / fs / STIFF_LIMIT).ceil() as usize).max(1)
}

/// Simulate a voltage record `u` (V, sampled at `fs`) and return the trace.
pub fn simulate(params: &Parameters, fs: f64, u: &[f64], opts: &SimOptions) -> Result<Trace, SimError> {
    if u.is_empty() {
        return Err(SimError::Input("the input voltage has no samples".into()));
    }
    let mut sim = Simulator::new(params, fs, opts)?;
    let n = u.len();
    let mut tr = Trace {
        fs,
        u: u.to_vec(),
        x: Vec::with_capacity(n),
        v: Vec::with_capacity(n),
        i: Vec::with_capacity(n),
        i2: Vec::with_capacity(n),
        tv: Vec::with_capacity(n),
        tm: Vec::with_capacity(n),
        substeps: sim.substeps(),
        scheme: sim.stepper.scheme,
        range_excess: 0.0,
        boxed: Vec::new(),
    };
    let range = params.x_range;
    let mut excess: f64 = 0.0;
    sim.run_boxed(u, |_, s, b| {
        if let Some(b) = b {
            tr.boxed.push(b);
        }
        tr.x.push(s[idx::X]);
        tr.v.push(s[idx::V]);
        tr.i.push(s[idx::I]);
        tr.i2.push(s[idx::I2]);
        tr.tv.push(s[idx::TV]);
        tr.tm.push(s[idx::TM]);
        if let Some([lo, hi]) = range {
            excess = excess.max(lo - s[idx::X]).max(s[idx::X] - hi);
        }
    })?;
    tr.range_excess = excess;
    Ok(tr)
}

/// The gain that makes `unit` (a voltage signal, scaled linearly) drive the driver to a peak
/// excursion of `target` (m, either direction), within 2 %, found by simulating up to six
/// times (and up to six more runs that left the model's range); returns the gain and the trace
/// at that gain (after six runs outside 2 %, the last run's). What a test or a virtual measurement uses to play "at 85 % of x_range".
///
/// The peak grows faster than the gain where the suspension softens or creep lets the cone
/// drift: a gain scaled from a quieter run can push it past the range, where the model is not
/// valid (a drawn microspeaker with creep: 0.33 mm of a 0.30 mm range at 5.6 s). Such a run
/// is not the answer: the gain backs off halfway to the last one that ran (a quarter when
/// none has yet) and tries again.
pub fn gain_for_peak(
    params: &Parameters,
    fs: f64,
    unit: &[f64],
    target: f64,
    opts: &SimOptions,
) -> Result<(f64, Trace), SimError> {
    let mut g = 1.0;
    let mut last = None;
    // The largest gain that ran within the range, and the runs past it so far.
    let (mut ran, mut out) = (0.0f64, 0);
    let mut runs = 0;
    while runs < 6 {
        let u: Vec<f64> = unit.iter().map(|v| v * g).collect();
        let t = match simulate(params, fs, &u, opts) {
            Ok(t) => t,
            Err(SimError::OutOfRange { .. }) if out < 6 => {
                out += 1;
                g = if ran > 0.0 { 0.5 * (ran + g) } else { 0.25 * g };
                continue;
            }
            Err(e) => return Err(e),
        };
        runs += 1;
        let s = t.summary();
        let peak = s.x_max.max(-s.x_min);
        if !(peak > 0.0) {
            return Err(SimError::Input("the signal does not move the driver".into()));
        }
        if (peak / target - 1.0).abs() < 0.02 {
            return Ok((g, t));
        }
        ran = ran.max(g);
        let next = g * target / peak;
        last = Some((g, t));
        g = next;
    }
    // The last run: the gain it ran at, with its trace.
    Ok(last.expect("at least one run"))
}

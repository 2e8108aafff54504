//! Forward sensitivities: the Jacobian columns of the output error by the sensitivity
//! equation, in `f64`, instead of dual numbers.
//!
//! A column `S = dy/dtheta_k` of the state's derivative by one unknown obeys the model's
//! linearisation along the run, `S' = F(t) S + G_k(t)`, with `F = df/dy` and `G_k = df/dtheta_k`
//! ([`coilscope_core::model::Model::deriv_partials`]). Each sample the model takes its RK4
//! step in `f64` and records its four stages' states and partials; each column then takes the
//! RK4 step of the linear system with those stages' `F` and `G`, which is the exact
//! derivative of the model's step: the dual numbers' column to rounding (2e-15,
//! `the_jacobian_on_jets_is_num_duals_to_the_last_bit`). The dual numbers carry every operation
//! of the model's step once per column; here a column costs a step of a linear system
//! whose coefficients are known. The columns take that step side by side ([`Columns`]: one
//! array over the columns for each state and `G` row, RK4's stages one loop each over all of
//! them, vectorised), and a Jacobian takes one pass a worker ([`widths`]), since each pass
//! takes the model's step with its partials again (SB17's order-4 Jacobian on one core
//! 1.3x faster than on dual numbers, the values to the last bit).
//!
//! Only the model without states of its effects' own (no creep or LR-3; `Le(i)` and `Rms(v)`
//! are in) at one RK4 step per sample (the woofers' final fit, the online estimator's
//! windows) or one step of the midpoint rule (the woofers' search stages:
//! [`Columns::midpoint_step`], 1.77x); every other Jacobian keeps its dual numbers. The
//! exponential method's (stiff drivers) was tried as the method's
//! step of the sensitivity equation, `A` frozen as in the model's step: on the microspeaker its columns
//! were 1.2-1.5 % (Re(t)), 0.3-0.6 % (Bl, Kms, Rms), 1 % (L2) and 29-36 % (Le(x), R2) off a
//! reference of eight steps, against the dual numbers' 0.06-0.08 %, 0.04-0.07 %, 0.3 %,
//! 0.4-2.3 % and 2.2 %, and as far off in the fluxes' coordinates (`psi = Le i`): a stiff
//! step's stages do not carry the current's lag behind the drive, which the network's
//! columns are. The derivative of the discrete step (the matrix functions' derivatives by
//! the network's entries) is what it needs; built and measured, it gave the jets' columns to
//! 1.3e-13, and no faster than the jets (a
//! column's derivative of the five-stage step is about 500 operations a sample), so the
//! stiff drivers keep their jets.

use crate::large::{knot_at, re_at, Layout, HEAT_SCALE};
#[cfg(test)]
use coilscope_core::integrate::TINY_LANE;
use coilscope_core::integrate::{flush_tiny_lanes, midpoint_sample, rk4_step, Dynamics, Scheme, Stepper};
use coilscope_core::model::{idx, DerivPartials, Model, State, NSTATE};
#[cfg(test)]
use std::cell::Cell;
use std::cell::RefCell;
use std::sync::atomic::{AtomicBool, Ordering};

/// The stages an RK4 step records.
const STAGES: usize = 4;

/// What a Jacobian column is the derivative by.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Column {
    /// A knot of `Re(t)`.
    Knot(usize),
    /// A heating term of `Re(t)`.
    Heat(usize),
    /// The Legendre coefficient `k` of `Le(x)`, `Bl(x)`, `Kms(x)`.
    Le(usize),
    Bl(usize),
    Kms(usize),
    Rms,
    L2,
    R2,
    /// `Le(i)`'s coefficient `c_1` or `c_2`.
    LeI(usize),
    /// `Rms(v)`'s coefficient of `v^2`.
    RmsV,
}

/// The columns of `layout`'s unknowns, in theta's order; `None` when the layout has one this
/// module does not take (creep's, LR-3's).
fn columns(layout: &Layout) -> Option<Vec<Column>> {
    let s = layout.slots();
    let mut c = vec![None; s.n];
    for (k, j) in s.re.clone().enumerate() {
        c[j] = Some(Column::Knot(k));
    }
    for (k, j) in s.heat.clone().enumerate() {
        c[j] = Some(Column::Heat(k));
    }
    for (k, j) in s.le.clone().enumerate() {
        c[j] = Some(Column::Le(k));
    }
    for (k, j) in s.bl.clone().enumerate() {
        c[j] = Some(Column::Bl(k));
    }
    for (k, j) in s.kms.clone().enumerate() {
        c[j] = Some(Column::Kms(k));
    }
    c[s.rms] = Some(Column::Rms);
    if let Some(j) = s.l2 {
        c[j] = Some(Column::L2);
    }
    if let Some(j) = s.r2 {
        c[j] = Some(Column::R2);
    }
    if let Some(j) = s.le_i {
        c[j] = Some(Column::LeI(0));
        c[j + 1] = Some(Column::LeI(1));
    }
    if let Some(j) = s.rms_v {
        c[j] = Some(Column::RmsV);
    }
    c.into_iter().collect()
}

/// Whether [`pass`] computes `layout`'s columns with `stepper`'s steps: the model without
/// states of its effects' own (no creep, no LR-3; Le(i) and Rms(v) are in) at one RK4 step
/// per sample (a woofer's final fit) or one step of the midpoint rule (a woofer's search
/// stages, [`crate::large::OutputError::searching`]).
pub(crate) fn applies(layout: &Layout, stepper: &Stepper) -> bool {
    !layout.needs_ext_states() && matches!(stepper.scheme, Scheme::Rk4 | Scheme::Midpoint) && stepper.points() == 3
}

/// What a model run beside a Jacobian's passes (the residual's, with all its sub-steps)
/// costs, in columns of a pass by the sensitivity equation: SB17's order-4 problem over 8 s
/// on one core (`jacobian_order4_widths`, `residual_order4`) ran its residual in
/// 100 ms, each column of a pass in 17 ms and each pass's own model step with its partials
/// in 80 ms.
pub(crate) const RUN_COLUMNS: usize = 6;

/// The widths of the passes of an `n`-column Jacobian by the sensitivity equation on
/// `threads` workers, `leads` of which first run a model run each (the residual beside the
/// Jacobian, [`RUN_COLUMNS`] columns' worth): one pass a worker, so that all end together,
/// the passes of the workers that start at once first (a queue takes its tasks in order),
/// then those of the workers the runs held (narrower by what the run cost them, none when it
/// cost them their share). Every pass takes the model's step with its partials again, so
/// that more passes than workers cost that step for nothing; the dual numbers' passes
/// ([`crate::large::pass_widths`]) are as wide as their registers hold.
pub(crate) fn widths(n: usize, threads: usize, leads: usize) -> Vec<usize> {
    let k = threads.clamp(1, n.max(1));
    let leads = if k > leads { leads } else { 0 };
    let held = ((n + leads * RUN_COLUMNS) / k).saturating_sub(RUN_COLUMNS);
    let free = k - leads;
    let rest = n - leads * held;
    let mut w: Vec<usize> = (0..free).map(|j| rest / free + usize::from(j < rest % free)).collect();
    w.extend(std::iter::repeat_n(held, leads));
    w.retain(|&w| w > 0);
    w
}

/// The model's step that records its stages: their states and partials, in the order the
/// scheme evaluates them.
struct Recording<'a> {
    model: &'a Model<f64>,
    stages: &'a RefCell<Stages>,
}

/// The stages' states and partials of one step, and how many were recorded.
#[derive(Default)]
struct Stages {
    states: [State<f64>; STAGES],
    partials: [DerivPartials; STAGES],
    n: usize,
}

impl Dynamics<f64, NSTATE> for Recording<'_> {
    #[inline]
    fn deriv(&self, y: &State<f64>, u: f64) -> State<f64> {
        let (d, p) = self.model.deriv_partials(y, u).expect("a fit's model (applies)");
        let mut st = self.stages.borrow_mut();
        let k = st.n;
        st.states[k] = *y;
        st.partials[k] = p;
        st.n += 1;
        d
    }
}

/// One column's sensitivity equation over a step: `S' = F_s S + G_s` at the step's stage `s`
/// (RK4 evaluates its stages in the order the model's step recorded them): the slow, plain
/// reference of [`Columns::rk4_step`], which steps every column at once.
#[cfg(test)]
struct Linear<'a> {
    partials: &'a [DerivPartials; STAGES],
    /// `G_s`'s rows `dv/dt`, `di/dt`, `di2/dt`.
    g: &'a [[f64; 3]; STAGES],
    stage: Cell<usize>,
}

#[cfg(test)]
impl Dynamics<f64, NSTATE> for Linear<'_> {
    #[inline]
    fn deriv(&self, s: &State<f64>, _u: f64) -> State<f64> {
        let k = self.stage.get();
        self.stage.set(k + 1);
        let (p, g) = (&self.partials[k], &self.g[k]);
        let (x, v, i, i2) = (s[idx::X], s[idx::V], s[idx::I], s[idx::I2]);
        [
            v,
            p.v_state[0] * x + p.v_state[1] * v + p.v_state[2] * i + g[0],
            p.i_state[0] * x + p.i_state[1] * v + p.i_state[2] * i + p.i_state[3] * i2 + g[1],
            p.i2_state[0] * i + p.i2_state[1] * i2 + g[2],
            0.0,
            0.0,
        ]
    }
}

/// The Jacobian columns `cols` of `layout` at `th` (f64; with spare heating columns, the
/// heated layout and its heating terms at zero), each the current's sensitivity over the
/// samples `fit`, column `k` at `block[k * fit.len() ..]`: the dual numbers' pass
/// ([`crate::large::OutputError`]'s `jacobian_run`) by the sensitivity equation. The run is
/// [`crate::large`]'s `run_model`'s: `Re` from the knots (and heating terms) at each sample,
/// the input points from `stepper`, `y = 0` at the start. A run that leaves the finite
/// numbers or is stopped (`stop`, looked at every 4096 samples) leaves the rest at zero.
#[allow(clippy::too_many_arguments)]
pub(crate) fn pass(
    layout: &Layout,
    heat: &[Vec<f64>],
    th: &[f64],
    cols: &[usize],
    u: &[f64],
    fs: f64,
    stepper: &Stepper,
    fit: std::ops::Range<usize>,
    stop: Option<&AtomicBool>,
    block: &mut [f64],
) {
    pass_on(layout, heat, th, cols, u, fs, stepper, fit, stop, block, true);
}

/// [`pass`], compiled for AVX when `avx` and the CPU has it, for the baseline otherwise (the
/// test that the two give the same bits).
#[allow(clippy::too_many_arguments)]
pub(crate) fn pass_on(
    layout: &Layout,
    heat: &[Vec<f64>],
    th: &[f64],
    cols: &[usize],
    u: &[f64],
    fs: f64,
    stepper: &Stepper,
    fit: std::ops::Range<usize>,
    stop: Option<&AtomicBool>,
    block: &mut [f64],
    avx: bool,
) {
    let (knots, sizes, dt) = (layout.model(th).1, layout.heat_sizes(th), 1.0 / fs);
    // Re(t) as the model's runs take it, and its weights on the knots.
    let re = |m: usize| {
        let t = m as f64 * dt;
        let (k, w) = knot_at(knots.len(), layout.knot_dt, t);
        (re_at(&knots, layout.knot_dt, t, m, (&sizes, heat)), k, w)
    };
    let run = Run { u, steps: 0..fit.end, first_row: fit.start, y0: [0.0; NSTATE] };
    pass_from_on(layout, heat, th, cols, fs, stepper, &run, re, stop, block, avx);
}

/// A run of [`pass_from`]: the drive `u`, the samples `steps` of it the run steps over from
/// the state `y0`, and the first of them the Jacobian's rows start at.
pub(crate) struct Run<'a> {
    pub u: &'a [f64],
    pub steps: std::ops::Range<usize>,
    pub first_row: usize,
    pub y0: State<f64>,
}

/// [`pass`] over `run`, with `re(m)` the coil's resistance at sample `m` and its knot `k` and
/// weight `w` (`Re = (1 - w) knot_k + w knot_{k+1}`; with one
/// knot its column is `Re`'s): the online estimator's windows start from the live state,
/// with their own `Re` ramp.
///
/// On a CPU with AVX the pass runs compiled for it (checked at run time: the binary keeps to
/// the x86-64 baseline), the columns' steps four to a register instead of two; the values
/// are the same to the last bit, since the operations and their order are the same and
/// nothing is contracted into a fused multiply-add
/// (`the_avx_pass_is_the_baseline_pass_to_the_last_bit`).
#[allow(clippy::too_many_arguments)]
pub(crate) fn pass_from(
    layout: &Layout,
    heat: &[Vec<f64>],
    th: &[f64],
    cols: &[usize],
    fs: f64,
    stepper: &Stepper,
    run: &Run,
    re: impl Fn(usize) -> (f64, usize, f64),
    stop: Option<&AtomicBool>,
    block: &mut [f64],
) {
    pass_from_on(layout, heat, th, cols, fs, stepper, run, re, stop, block, true);
}

/// [`pass_from`] compiled for AVX when `avx` and the CPU has it, for the baseline otherwise.
#[allow(clippy::too_many_arguments)]
fn pass_from_on(
    layout: &Layout,
    heat: &[Vec<f64>],
    th: &[f64],
    cols: &[usize],
    fs: f64,
    stepper: &Stepper,
    run: &Run,
    re: impl Fn(usize) -> (f64, usize, f64),
    stop: Option<&AtomicBool>,
    block: &mut [f64],
    avx: bool,
) {
    #[cfg(target_arch = "x86_64")]
    if avx && std::arch::is_x86_feature_detected!("avx") {
        // SAFETY: the CPU has AVX (checked just above).
        return unsafe { pass_from_avx(layout, heat, th, cols, fs, stepper, run, re, stop, block) };
    }
    let _ = avx;
    pass_from_body(layout, heat, th, cols, fs, stepper, run, re, stop, block);
}

/// [`pass_from`] compiled for AVX.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
#[allow(clippy::too_many_arguments)]
fn pass_from_avx(
    layout: &Layout,
    heat: &[Vec<f64>],
    th: &[f64],
    cols: &[usize],
    fs: f64,
    stepper: &Stepper,
    run: &Run,
    re: impl Fn(usize) -> (f64, usize, f64),
    stop: Option<&AtomicBool>,
    block: &mut [f64],
) {
    pass_from_body(layout, heat, th, cols, fs, stepper, run, re, stop, block);
}

/// [`pass_from`]'s work, inlined into each of its two callers (the baseline's and AVX's).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn pass_from_body(
    layout: &Layout,
    heat: &[Vec<f64>],
    th: &[f64],
    cols: &[usize],
    fs: f64,
    stepper: &Stepper,
    run: &Run,
    re: impl Fn(usize) -> (f64, usize, f64),
    stop: Option<&AtomicBool>,
    block: &mut [f64],
) {
    let all = columns(layout).expect("a layout without creep or LR-3 (applies)");
    let kinds: Vec<Column> = cols.iter().map(|&c| all[c]).collect();
    let mut model = layout.model(th).0;
    let sc = &layout.scales;
    let legendre = layout.legendre_table();
    let (rows, dt) = (run.steps.end - run.first_row, 1.0 / fs);
    let n_knots = layout.slots().re.len();
    let mut y = run.y0;
    let n = cols.len();
    let mut sens = Columns::new(n);
    let mut pf = vec![0.0; stepper.points()];
    // Per stage: P_j(x / x_ref) and P_j'(x / x_ref) / x_ref.
    let mut basis = vec![(0.0, 0.0); legendre.len()];
    let stages = RefCell::new(Stages::default());
    let midpoint = stepper.scheme == Scheme::Midpoint;
    for m in run.steps.clone() {
        if !y[idx::I].is_finite() || (m % 4096 == 0 && stop.is_some_and(|s| s.load(Ordering::Relaxed))) {
            return;
        }
        if m >= run.first_row {
            for (k, s) in sens.s[2].iter().enumerate() {
                block[k * rows + m - run.first_row] = *s;
            }
        }
        let (re_m, knot, w) = re(m);
        model.re = re_m;
        stepper.fill(run.u, m, &mut pf);
        stages.borrow_mut().n = 0;
        let sys = Recording { model: &model, stages: &stages };
        y = if midpoint { midpoint_sample(&sys, &y, dt, &pf) } else { rk4_step(&sys, &y, dt, pf[0], pf[1], pf[2]) };
        let st = stages.borrow();
        let partials = &st.partials;
        for (s, (state, p)) in st.states[..st.n].iter().zip(partials).enumerate() {
            let xi = state[idx::X] / layout.x_ref;
            for (b, poly) in basis.iter_mut().zip(legendre) {
                let (mut v, mut d) = (0.0, 0.0);
                for c in poly.iter().rev() {
                    d = d * xi + v;
                    v = v * xi + c;
                }
                *b = (v, d / layout.x_ref);
            }
            let [g0, g1, g2] = &mut sens.g[s];
            for (c, kind) in kinds.iter().enumerate() {
                [g0[c], g1[c], g2[c]] = match *kind {
                    Column::Knot(j) => [
                        0.0,
                        p.re * sc.re
                            * if n_knots == 1 {
                                1.0
                            } else if j == knot {
                                1.0 - w
                            } else if j == knot + 1 {
                                w
                            } else {
                                0.0
                            },
                        0.0,
                    ],
                    Column::Heat(j) => [0.0, p.re * sc.re * HEAT_SCALE * heat[j][m], 0.0],
                    Column::Le(j) => {
                        let (b, db) = (basis[j].0 * sc.le, basis[j].1 * sc.le);
                        [p.dle[0] * db, p.le * b + p.dle[1] * db, 0.0]
                    }
                    Column::Bl(j) => [p.bl[0] * basis[j].0 * sc.bl, p.bl[1] * basis[j].0 * sc.bl, 0.0],
                    Column::Kms(j) => [p.kms * basis[j].0 * sc.kms, 0.0, 0.0],
                    Column::Rms => [p.rms * sc.rms, 0.0, 0.0],
                    Column::L2 => [0.0, 0.0, p.l2 * sc.l2],
                    Column::R2 => [0.0, p.r2[0] * sc.r2, p.r2[1] * sc.r2],
                    Column::LeI(j) => [p.le_i[j][0], p.le_i[j][1], 0.0],
                    Column::RmsV => [p.rms_v2 * sc.rms, 0.0, 0.0],
                };
            }
        }
        if midpoint {
            sens.midpoint_step(partials, dt);
        } else {
            sens.rk4_step(partials, dt);
        }
        sens.flush_tiny();
    }
}

/// The columns' sensitivities `S = (x, v, i, i2)` (the thermal states are off) and each
/// stage's `G` rows `dv/dt`, `di/dt`, `di2/dt`, one array over the columns each (structure
/// of arrays): the columns' RK4 steps share the stages' `F` and run side by side, two to a
/// vector register, instead of one six-state step at a time.
struct Columns {
    s: [Vec<f64>; 4],
    g: [[Vec<f64>; 3]; STAGES],
    /// The step's scratch: the last stage's rates, and the sum of the rates so far.
    k: [Vec<f64>; 4],
    sum: [Vec<f64>; 4],
}

impl Columns {
    fn new(n: usize) -> Self {
        fn zeros<const R: usize>(n: usize) -> [Vec<f64>; R] {
            std::array::from_fn(|_| vec![0.0; n])
        }
        Columns { s: zeros(n), g: std::array::from_fn(|_| zeros(n)), k: zeros(n), sum: zeros(n) }
    }

    /// The sensitivities below [`TINY_LANE`] set to zero ([`flush_tiny_lanes`]), as the dual
    /// numbers' runs set their lanes ([`coilscope_core::integrate::FlushTiny`]): a column
    /// that stops being driven (an `Re(t)` knot's after its interval) decays through the
    /// subnormal range, where every operation takes the processor's microcode assist.
    #[inline(always)]
    fn flush_tiny(&mut self) {
        for s in self.s.iter_mut() {
            flush_tiny_lanes(s);
        }
    }

    /// Every column's step of the explicit midpoint rule over `h` at the two recorded
    /// stages: `S + h (F_2 (S + h/2 k_1) + G_2)`, `k_1 = F_1 S + G_1` (the model's
    /// [`midpoint_sample`], a search stage's Jacobian).
    #[inline(always)]
    fn midpoint_step(&mut self, p: &[DerivPartials; STAGES], h: f64) {
        self.stage::<0>(&p[0], 0.0);
        self.stage::<1>(&p[1], 0.5 * h);
        let n = self.s[0].len();
        for (s, k) in self.s.iter_mut().zip(&self.k) {
            for (s, k) in s[..n].iter_mut().zip(&k[..n]) {
                *s += k * h;
            }
        }
    }

    /// Every column's RK4 step of `S' = F_s S + G_s` over `h` at the recorded stages: the
    /// arithmetic of [`rk4_step`] on [`Linear`], operation for operation (the same values to
    /// the last bit, `the_columns_step_is_linear_rk4_to_the_last_bit`). Stage by stage over
    /// all columns, so that a loop holds one stage's nine partials in registers (a loop over
    /// the whole step per column spilled them: 1.3x slower).
    #[inline(always)]
    fn rk4_step(&mut self, p: &[DerivPartials; STAGES], h: f64) {
        self.stage::<0>(&p[0], 0.0);
        self.stage::<1>(&p[1], 0.5 * h);
        self.stage::<2>(&p[2], 0.5 * h);
        self.stage::<3>(&p[3], h);
        let h6 = h / 6.0;
        let n = self.s[0].len();
        for (s, a) in self.s.iter_mut().zip(&self.sum) {
            for (s, a) in s[..n].iter_mut().zip(&a[..n]) {
                *s += a * h6;
            }
        }
    }

    /// RK4's stage `ST` over every column: the rates at `S + a k` (`axpy`; `S` at the first
    /// stage) into `k`, and into the weights' sum as [`rk4_step`] takes it,
    /// `(k1 + (k2 + k3) 2) + k4`. One loop a stage holds its nine partials in registers, and
    /// `ST` a constant leaves the loop without a branch (vectorised, two columns at once).
    #[inline(always)]
    fn stage<const ST: usize>(&mut self, p: &DerivPartials, a: f64) {
        let n = self.s[0].len();
        let (pv, pi, p2) = (p.v_state, p.i_state, p.i2_state);
        let [sx, sv, si, si2] = &self.s;
        let (sx, sv, si, si2) = (&sx[..n], &sv[..n], &si[..n], &si2[..n]);
        let [g0, g1, g2] = &self.g[ST];
        let (g0, g1, g2) = (&g0[..n], &g1[..n], &g2[..n]);
        let [kx, kv, ki, ki2] = &mut self.k;
        let (kx, kv, ki, ki2) = (&mut kx[..n], &mut kv[..n], &mut ki[..n], &mut ki2[..n]);
        let [ax, av, ai, ai2] = &mut self.sum;
        let (ax, av, ai, ai2) = (&mut ax[..n], &mut av[..n], &mut ai[..n], &mut ai2[..n]);
        for c in 0..n {
            let (x, v, i, i2) = if ST == 0 {
                (sx[c], sv[c], si[c], si2[c])
            } else {
                (sx[c] + kx[c] * a, sv[c] + kv[c] * a, si[c] + ki[c] * a, si2[c] + ki2[c] * a)
            };
            let k = [
                v,
                pv[0] * x + pv[1] * v + pv[2] * i + g0[c],
                pi[0] * x + pi[1] * v + pi[2] * i + pi[3] * i2 + g1[c],
                p2[0] * i + p2[1] * i2 + g2[c],
            ];
            if ST == 0 {
                [ax[c], av[c], ai[c], ai2[c]] = k;
            } else if ST == 2 {
                [ax[c], av[c], ai[c], ai2[c]] = [
                    ax[c] + (kx[c] + k[0]) * 2.0,
                    av[c] + (kv[c] + k[1]) * 2.0,
                    ai[c] + (ki[c] + k[2]) * 2.0,
                    ai2[c] + (ki2[c] + k[3]) * 2.0,
                ];
            } else if ST == 3 {
                [ax[c], av[c], ai[c], ai2[c]] = [ax[c] + k[0], av[c] + k[1], ai[c] + k[2], ai2[c] + k[3]];
            }
            [kx[c], kv[c], ki[c], ki2[c]] = k;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng;

    /// One pass a worker, the columns shared evenly; beside a model run, the pass of the
    /// run's worker the narrower by the run's cost.
    #[test]
    fn the_passes_are_one_a_worker() {
        assert_eq!(widths(23, 2, 0), vec![12, 11]);
        assert_eq!(widths(23, 2, 1), vec![15, 8]);
        assert_eq!(widths(25, 1, 1), vec![25]);
        assert_eq!(widths(1, 2, 0), vec![1]);
        assert_eq!(widths(5, 2, 1), vec![5]);
        assert_eq!(widths(0, 2, 0), Vec::<usize>::new());
        assert_eq!(widths(20, 4, 2), vec![8, 8, 2, 2]);
        for n in 1..40 {
            for t in 1..5 {
                for leads in 0..3 {
                    let w = widths(n, t, leads);
                    let k = t.min(n);
                    assert_eq!(w.iter().sum::<usize>(), n, "{n} columns, {t} workers, {leads} runs: {w:?}");
                    assert!(!w.is_empty() && w.len() <= k, "{n}, {t}, {leads}: {w:?}");
                    // Each worker's load in columns (a run RUN_COLUMNS), the runs' workers last.
                    let loads: Vec<usize> = if leads == 0 || k <= leads {
                        w.clone()
                    } else {
                        (0..k)
                            .map(|j| if j < k - leads { w[j] } else { RUN_COLUMNS + w.get(j).copied().unwrap_or(0) })
                            .collect()
                    };
                    let spread = loads.iter().max().unwrap() - loads.iter().min().unwrap();
                    assert!(
                        spread <= if leads == 0 || k <= leads { 1 } else { RUN_COLUMNS },
                        "{n}, {t}, {leads}: {w:?}, loads {loads:?}"
                    );
                }
            }
        }
    }

    /// A column that is no longer driven decays to zero, not through the subnormal range:
    /// a critically damped mode of 2000 rad/s and currents decaying at 5000 /s, `G` zero,
    /// from sensitivities of 1e-250 to 1e-270 (the same steps unflushed do pass through
    /// it).
    #[test]
    fn an_undriven_column_decays_to_zero_not_into_subnormals() {
        let h = 1.0 / 48000.0;
        let p = DerivPartials {
            v_state: [-4e6, -4e3, 0.0],
            i_state: [0.0, 0.0, -5e3, 0.0],
            i2_state: [0.0, -5e3],
            ..Default::default()
        };
        let partials = [p; STAGES];
        let (mut flushed, mut plain) = (Columns::new(3), Columns::new(3));
        for cols in [&mut flushed, &mut plain] {
            for s in cols.s.iter_mut() {
                s.copy_from_slice(&[1e-250, -3e-260, 2e-270]);
            }
        }
        let mut subnormal_seen = false;
        for _ in 0..20000 {
            flushed.rk4_step(&partials, h);
            flushed.flush_tiny();
            plain.rk4_step(&partials, h);
            subnormal_seen |= plain.s.iter().flatten().any(|v| v.is_subnormal());
            assert!(flushed.s.iter().flatten().all(|v| *v == 0.0 || v.abs() >= TINY_LANE), "{:?}", flushed.s);
        }
        assert!(subnormal_seen, "the unflushed columns pass through the subnormal range");
        assert!(flushed.s.iter().flatten().all(|v| *v == 0.0), "{:?}", flushed.s);
    }

    /// The columns' step side by side is each column's six-state RK4 step of [`Linear`] to
    /// the last bit: random stage partials, `G` rows and starting sensitivities (seeded),
    /// column counts 1 to 29 (odd ones leave a lane of the vector loop alone), 200 steps.
    #[test]
    fn the_columns_step_is_linear_rk4_to_the_last_bit() {
        let mut rng = coilscope_core::excitation::named_rng(1, "sensitivity columns");
        let mut r = |scale: f64| scale * (2.0 * rng.random::<f64>() - 1.0);
        let h = 1.0 / 48000.0;
        for n in [1, 2, 7, 12, 29] {
            let mut cols = Columns::new(n);
            for s in cols.s.iter_mut() {
                s.iter_mut().for_each(|v| *v = r(1e-3));
            }
            let mut plain: Vec<State<f64>> =
                (0..n).map(|c| [cols.s[0][c], cols.s[1][c], cols.s[2][c], cols.s[3][c], 0.0, 0.0]).collect();
            for _ in 0..200 {
                // Rates like a woofer's: the mechanical mode ~1e3-1e4 /s, the electrical ~1e4.
                let partials: [DerivPartials; STAGES] = std::array::from_fn(|_| DerivPartials {
                    v_state: [r(1e7), r(1e2), r(1e3)],
                    i_state: [r(1e5), r(1e4), r(2e4), r(1e4)],
                    i2_state: [r(1e4), r(1e4)],
                    ..Default::default()
                });
                let mut g = [[[0.0; 3]; STAGES]; 0].to_vec();
                g.resize(n, [[0.0; 3]; STAGES]);
                for (c, gc) in g.iter_mut().enumerate() {
                    for s in 0..STAGES {
                        gc[s] = [r(10.0), r(100.0), r(1.0)];
                        for k in 0..3 {
                            cols.g[s][k][c] = gc[s][k];
                        }
                    }
                }
                cols.rk4_step(&partials, h);
                for (s, gc) in plain.iter_mut().zip(&g) {
                    *s = rk4_step(&Linear { partials: &partials, g: gc, stage: Cell::new(0) }, s, h, 0.0, 0.0, 0.0);
                }
            }
            for c in 0..n {
                for k in 0..4 {
                    assert_eq!(
                        cols.s[k][c].to_bits(),
                        plain[c][k].to_bits(),
                        "{n} columns: column {c}, state {k}: {} vs {}",
                        cols.s[k][c],
                        plain[c][k]
                    );
                }
                assert!(plain[c].iter().all(|v| v.is_finite()) && plain[c][2] != 0.0);
            }
        }
    }
}

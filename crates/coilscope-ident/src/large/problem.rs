//! The output-error problem ([`OutputError`]): the residual runs, the exact Jacobians on
//! dual numbers in passes over both cores, and their storage.

use super::*;

/// Parameters per dual-number pass of the Jacobian. Measured with the
/// `jacobian_order4` bench (23 columns, 8 s, both cores, medians of 5, repeated): 826 ms
/// (width 4), 618 (6), 565 (8), 680 (10), 753 (12), 874 (16). At width 8 each pass's value
/// part and the dual numbers' `Option` test are shared by twice the columns of width 4, and
/// it still fits the registers; against width 4, `identify_8s` takes 4.75 s instead of 5.93
/// (SB17), 4.78 instead of 5.96 (PTT4), 6.95 instead of 9.03 (18WU), the effects search
/// 11.26 instead of 14.85, with every result bit-identical.
pub const CHUNK: usize = 8;
/// The widths of `identify`'s Jacobian passes and the cost of one pass of each, in units of
/// an 8-lane pass ([`CHUNK`]). Measured on [`Jet`]s (the benches
/// `jacobian_order4_widths` and `jacobian_microspeaker_widths`, medians of 5 and of 3, two
/// cores): a woofer's RK4 pass (SB17, 23 columns) 4 lanes 0.57, 10 lanes 1.22, 12 lanes
/// 1.53 (16 lanes 2.24, in passes of 16 and 7); the microspeaker's exponential pass (17
/// columns) 0.55, 1.31 and 1.70.
/// Up to 12 lanes a pass costs about the same per lane (0.125-0.14 of an 8-lane pass), so
/// that what counts is how evenly the passes share the cores: SB17's 23 columns took 475 ms
/// in passes of 8, 8 and 7 (two in turn on one core), 363-367 ms in passes of 12 and 11
/// (one each). Sixteen lanes no longer fit the registers. Every column is the same
/// arithmetic at any width (the Jacobian is bit-identical:
/// `a_jacobian_in_wide_passes_is_the_jacobian`).
///
/// (On num-dual's dual numbers, which the passes ran on before [`Jet`]s, a 10-lane pass cost
/// 1.13 of an 8-lane one and a 12-lane one 2.6: 8 lanes, with 10 where it saved a pass, were
/// the choice there.)
pub const PASS_COSTS: [(usize, f64); 4] = [(CHUNK_SHORT, 0.56), (CHUNK, 1.0), (CHUNK_TEN, 1.27), (CHUNK_WIDE, 1.6)];
/// The narrowest pass.
pub const CHUNK_SHORT: usize = 4;
/// The pass between [`CHUNK`] and [`CHUNK_WIDE`].
pub const CHUNK_TEN: usize = 10;
/// The widest pass.
pub const CHUNK_WIDE: usize = 12;

/// The columns of each dual-number pass of an `n`-column Jacobian on `threads` workers.
///
/// `wide_ok`: the passes whose set of widths ([`PASS_COSTS`]) ends soonest when the workers
/// take them in turn, widest first (each pass costing its width's cost), and of those the
/// one that costs least in all; the columns fill them in order, the last ones holding fewer
/// (a pass takes the narrowest width that holds its columns). On two cores: 17 columns in
/// passes of 10 and 7, 23 in 8, 8, 4 and 3, 26 in 10, 8, 4 and 4, 35 in 10, 10, 8 and 7 (one
/// core: 24 in three of 8, the fewest lanes).
/// `wide_ok` false: passes of [`CHUNK`] only (the online estimator's, whose passes are
/// 8-wide).
pub fn pass_widths(n: usize, threads: usize, wide_ok: bool) -> Vec<usize> {
    let threads = threads.max(1);
    if n == 0 {
        return vec![];
    }
    if !wide_ok {
        return (0..n.div_ceil(CHUNK)).map(|k| CHUNK.min(n - k * CHUNK)).collect();
    }
    // When the workers take the passes in turn, widest first (the order they are queued).
    let wall = |costs: &[f64]| {
        let mut load = vec![0.0f64; threads];
        for &c in costs {
            let k = (0..threads).min_by(|&a, &b| load[a].total_cmp(&load[b])).expect("a worker");
            load[k] += c;
        }
        load.into_iter().fold(0.0, f64::max)
    };
    // Every count of each width whose capacity holds n with no pass to spare.
    let caps: Vec<usize> = PASS_COSTS.iter().map(|&(w, _)| n.div_ceil(w)).collect();
    let mut best: Option<(f64, f64, Vec<usize>)> = None;
    let mut counts = vec![0usize; PASS_COSTS.len()];
    loop {
        let cap: usize = counts.iter().zip(&PASS_COSTS).map(|(c, (w, _))| c * w).sum();
        let narrowest = counts.iter().zip(&PASS_COSTS).find(|(c, _)| **c > 0).map(|(_, (w, _))| *w);
        if narrowest.is_some_and(|wmin| cap >= n && cap - wmin < n) {
            let mut passes: Vec<(usize, f64)> = vec![];
            for (c, &(w, cost)) in counts.iter().zip(&PASS_COSTS).rev() {
                passes.extend(std::iter::repeat_n((w, cost), *c));
            }
            let costs: Vec<f64> = passes.iter().map(|p| p.1).collect();
            let (t, total) = (wall(&costs), costs.iter().sum::<f64>());
            if best.as_ref().is_none_or(|b| t < b.0 - 1e-9 || (t < b.0 + 1e-9 && total < b.1 - 1e-9)) {
                best = Some((t, total, passes.iter().map(|p| p.0).collect()));
            }
        }
        // The next count vector (odometer over 0 ..= caps).
        let mut k = 0;
        while k < counts.len() && counts[k] == caps[k] {
            counts[k] = 0;
            k += 1;
        }
        if k == counts.len() {
            break;
        }
        counts[k] += 1;
    }
    let mut widths = best.expect("n columns fit some passes").2;
    // The columns fill the passes in order; the last ones hold fewer.
    let mut excess = widths.iter().sum::<usize>() - n;
    for w in widths.iter_mut().rev() {
        let cut = excess.min(*w - 1);
        *w -= cut;
        excess -= cut;
    }
    widths
}

/// The widths of the passes of an `n`-column Jacobian of `layout` with `stepper`'s steps on
/// `threads` workers, `leads` of which first run a model run each: by the sensitivity
/// equation one pass a worker ([`crate::sensitivity::widths`]), which is how those passes are
/// computed when it applies; else the dual numbers' ([`pass_widths`], `wide_ok` as there).
pub(crate) fn passes_for(
    layout: &Layout,
    stepper: &Stepper,
    n: usize,
    threads: usize,
    leads: usize,
    wide_ok: bool,
) -> Vec<usize> {
    if crate::sensitivity::applies(layout, stepper) {
        crate::sensitivity::widths(n, threads, leads)
    } else {
        pass_widths(n, threads, wide_ok)
    }
}

/// Samples between two looks of a model run at its stop flag ([`run_model`]).
pub(super) const STOP_POLL: usize = 4096;
/// Highest power-series order.
pub const MAX_ORDER: usize = 8;
/// Lowest power-series order.
pub const MIN_ORDER: usize = 2;

/// Ascending power coefficients of the Legendre polynomials `P_0 .. P_n`.
pub fn legendre(n: usize) -> Vec<Vec<f64>> {
    let mut p = vec![vec![1.0], vec![0.0, 1.0]];
    for k in 1..n {
        let kf = k as f64;
        let mut next = vec![0.0; k + 2];
        for (j, c) in p[k].iter().enumerate() {
            next[j + 1] += (2.0 * kf + 1.0) * c / (kf + 1.0);
        }
        for (j, c) in p[k - 1].iter().enumerate() {
            next[j] -= kf * c / (kf + 1.0);
        }
        p.push(next);
    }
    p.truncate(n + 1);
    p
}

/// A search stage's last Jacobian ([`OutputError::keeping_search`]), computed one accepted
/// step before the stage's end.
pub(crate) struct KeptJacobian {
    pub(super) j: DMatrix<f64>,
}

impl KeptJacobian {
    /// Hands the matrix's storage back for the next Jacobian.
    pub(super) fn recycle(self) {
        recycle_jacobian(self.j);
    }
}

/// For each unknown of `to` followed by `n_chain` chain unknowns, its index in the theta of
/// `from` (followed by the same chain unknowns), `None` where `from` has no such unknown: the
/// map of [`OutputError::seed_first`] from a stage whose model `to`'s holds (a lower order,
/// fewer effects). A Legendre coefficient is the same unknown at every order (`P_k` does not
/// depend on the order). `None` when the two do not share knots, basis and scales, or
/// `from` has an unknown `to` lacks.
pub(super) fn column_map(from: &Layout, to: &Layout, n_chain: usize) -> Option<Vec<Option<usize>>> {
    let (a, b) = (from.slots(), to.slots());
    let same = a.re.len() == b.re.len()
        && from.x_ref == to.x_ref
        && from.knot_dt == to.knot_dt
        && from.has_l2r2 == to.has_l2r2
        && from.order <= to.order
        && to.effects.union(from.effects) == to.effects
        && from.heat_taus.is_empty()
        && to.heat_taus.is_empty()
        && from.scales == to.scales
        && from.enclosure == to.enclosure;
    if !same {
        return None;
    }
    let mut map = vec![None; b.n + n_chain];
    let mut range = |x: &Range<usize>, y: &Range<usize>| {
        for (k, c) in y.clone().enumerate().take(x.len()) {
            map[c] = Some(x.start + k);
        }
    };
    range(&a.re, &b.re);
    range(&a.le, &b.le);
    range(&a.bl, &b.bl);
    range(&a.kms, &b.kms);
    let one = |k: Option<usize>| k.map_or(0..0, |k| k..k + 1);
    let two = |k: Option<usize>| k.map_or(0..0, |k| k..k + 2);
    for (x, y) in [
        (one(a.l2), one(b.l2)),
        (one(a.r2), one(b.r2)),
        (one(Some(a.rms)), one(Some(b.rms))),
        (one(a.lambda), one(b.lambda)),
        (two(a.le_i), two(b.le_i)),
        (one(a.rms_v), one(b.rms_v)),
    ] {
        range(&x, &y);
    }
    // LR-3's columns in other coordinates ([`Layout::lr3_tau`]) are new columns: L3's at a
    // fixed tau3 is not L3's at a fixed R3.
    if from.lr3_tau == to.lr3_tau {
        range(&one(a.l3), &one(b.l3));
        range(&one(a.r3), &one(b.r3));
    }
    range(&a.enclosure, &b.enclosure);
    for k in 0..n_chain {
        map[b.n + k] = Some(a.n + k);
    }
    Some(map)
}

/// Where a kept Jacobian was computed ([`OutputError::keeping_last`]).
pub(super) struct JacobianAt {
    pub(super) theta: Vec<f64>,
    /// The residual at theta (whitened, as the Jacobian).
    pub(super) residual: DVector<f64>,
    /// The spare heating columns ([`OutputError::with_spare_heat`]).
    pub(super) spare: Option<DMatrix<f64>>,
}

/// The output-error problem over one record.
pub struct OutputError<'a> {
    pub layout: Layout,
    pub u: &'a [f64],
    pub i: &'a [f64],
    pub fs: f64,
    /// Samples whose residual enters the cost.
    pub fit: Range<usize>,
    /// Displacement beyond which a trial is rejected as a runaway (m).
    pub x_limit: f64,
    pub threads: usize,
    /// The heating terms' shapes over the whole record ([`heat_shapes`] of `i`).
    pub heat: Vec<Vec<f64>>,
    /// The residual runs' steps and the Jacobian's ([`Stepper::for_rates`],
    /// [`Stepper::for_jacobian`]).
    pub(super) stepper: Stepper,
    pub(super) stepper_jac: Stepper,
    /// The start model's electrical rates, which chose the steps.
    pub(super) rates: Rates,
    /// The last Jacobian computed (LM's last iteration): reused for the covariance and the
    /// final fit's chord iterations, which share it (no copy of the matrix). Kept only when
    /// [`OutputError::keeping_last`] says so (a copy of up to 50 MB per iteration), or, moved
    /// instead of copied, [`OutputError::keeping_search`] (a search stage's, for the next
    /// stage's first iteration).
    pub(super) last_jacobian: std::sync::Mutex<Option<std::sync::Arc<DMatrix<f64>>>>,
    /// Where [`OutputError::last_jacobian`] was computed: theta, the residual there and the
    /// spare heating columns computed with it ([`OutputError::with_spare_heat`]).
    pub(super) last_jacobian_at: std::sync::Mutex<Option<JacobianAt>>,
    /// The heated layout ([`Layout::with_heat`] of [`HEAT_TAUS`]) and its heating shapes, when
    /// this problem's Jacobians also compute the heating terms' columns
    /// ([`OutputError::with_spare_heat`]).
    pub(super) spare: Option<(Layout, Vec<Vec<f64>>)>,
    /// The last residual run's theta, displacement and current over `0 .. fit.end`, for
    /// [`OutputError::trace`] at the same theta (the final fit's result is traced where its
    /// last residual was run: one run of the whole record fewer). Kept as the Jacobian is.
    pub(super) last_trace: std::sync::Mutex<Option<(Vec<f64>, Vec<f64>, Vec<f64>)>>,
    pub(super) keep_last: bool,
    /// Keep the last Jacobian as [`Problem::recycle`] hands it back, without a copy
    /// ([`OutputError::keeping_search`]).
    pub(super) keep_search: bool,
    /// The last residual and its theta: LM evaluates a trial, accepts it, then asks for the
    /// residual and Jacobian at the same theta.
    pub(super) last_residual: std::sync::Mutex<Option<(Vec<f64>, DVector<f64>)>>,
    /// The Jacobian computed alongside a trial's residual ([`Problem::residual_ahead`]) and
    /// its theta, for the [`Problem::residual_jacobian`] call that follows.
    pub(super) ahead: std::sync::Mutex<Option<(Vec<f64>, DMatrix<f64>, Option<DMatrix<f64>>)>>,
    /// The measurement chain, estimated with the driver: its unknowns follow the layout's in
    /// theta. `u` and `i` are then the record behind the chain's start values (for norms and
    /// the heating shapes); the runs use [`ChainSetup::voltage`] and [`ChainSetup::target`].
    pub chain: Option<&'a ChainSetup>,
    /// Jacobians computed to the end so far (alone or alongside a residual run): what a fit
    /// cost, in its largest unit.
    pub jacobians: AtomicUsize,
}

impl<'a> OutputError<'a> {
    /// `rates`: the start model's electrical rates ([`Parameters::rates`]), which choose the
    /// integration steps.
    pub fn new(
        layout: Layout,
        u: &'a [f64],
        i: &'a [f64],
        fs: f64,
        fit: Range<usize>,
        rates: Rates,
        x_limit: f64,
        threads: usize,
    ) -> Self {
        let heat = heat_shapes(i, fs, &layout.heat_taus);
        let (stepper, stepper_jac) = Stepper::for_fit(rates, fs);
        OutputError {
            layout,
            u,
            i,
            fs,
            fit,
            x_limit,
            threads: threads.max(1),
            heat,
            stepper,
            stepper_jac,
            rates,
            last_jacobian: Default::default(),
            last_jacobian_at: Default::default(),
            spare: None,
            last_trace: Default::default(),
            keep_last: false,
            keep_search: false,
            last_residual: Default::default(),
            ahead: Default::default(),
            chain: None,
            jacobians: AtomicUsize::new(0),
        }
    }

    /// The problem that keeps its last Jacobian and its last residual run's trace (the final
    /// fit's: `chords`, the covariance, the fitted model's trace).
    pub fn keeping_last(mut self) -> Self {
        self.keep_last = true;
        self
    }

    /// The problem of a search stage that keeps its last Jacobian (moved, not copied, when LM
    /// hands it back) for the next stage to start on ([`OutputError::take_kept`],
    /// [`OutputError::seed_first`]).
    pub(crate) fn keeping_search(mut self) -> Self {
        self.keep_search = !self.keep_last;
        self
    }

    /// The last Jacobian a [`OutputError::keeping_search`] problem computed.
    pub(crate) fn take_kept(&self) -> Option<KeptJacobian> {
        let j = self.last_jacobian.lock().expect("jacobian cache").take()?;
        std::sync::Arc::try_unwrap(j).ok().map(|j| KeptJacobian { j })
    }

    /// `j` as [`OutputError::last_jacobian`], the one it replaces handed back for its storage.
    pub(super) fn keep_jacobian(&self, j: DMatrix<f64>) {
        let old = self.last_jacobian.lock().expect("jacobian cache").replace(std::sync::Arc::new(j));
        if let Some(Ok(old)) = old.map(std::sync::Arc::try_unwrap) {
            recycle_jacobian(old);
        }
    }

    /// Seeds the first Jacobian of a fit that starts at `theta` from `kept`, the last one of a
    /// search stage whose model this one's holds (a lower order, an effect fewer: the same
    /// samples, knots, chain and whitening). Column `c` is `kept`'s column `map[c]` (computed
    /// where that stage's last Jacobian was, one accepted step before its end), or, where
    /// `map[c]` is `None`, computed here at `theta` in one pass beside the residual run at
    /// `theta` (both then cached for the fit's first iteration). A search stage started with
    /// a whole Jacobian of its own; the unknowns they share hardly moved since the last one
    /// (the stage ended on a step the linearised model predicted within 2 %), and LM accepts
    /// only steps that lower the exact cost. With no new column (the same layout, fitted on
    /// from where that stage stopped) the first Jacobian is the kept one. Returns false,
    /// seeding nothing, when the shapes do not fit or more than [`CHUNK_WIDE`] columns are
    /// new.
    pub(crate) fn seed_first(&self, theta: &[f64], kept: &KeptJacobian, map: &[Option<usize>]) -> bool {
        let (rows, nl) = (self.fit.len(), self.n_layout());
        let fresh: Vec<usize> = (0..map.len()).filter(|&c| map[c].is_none()).collect();
        let fits = map.len() == theta.len()
            && kept.j.nrows() == rows
            && map.iter().flatten().all(|&b| b < kept.j.ncols())
            && fresh.iter().all(|&c| c < nl)
            && fresh.len() <= CHUNK_WIDE
            && self.spare.is_none()
            && self.layout.physical(theta);
        if !fits {
            return false;
        }
        let (u, _) = self.signals(theta);
        let pass = || self.columns_at(theta, &fresh, &u);
        let block = if self.threads >= 2 && !fresh.is_empty() {
            std::thread::scope(|scope| {
                let h = scope.spawn(|| self.residual(theta));
                let block = pass();
                h.join().expect("a model run does not panic");
                block
            })
        } else {
            self.residual(theta);
            pass()
        };
        let mut j = DMatrix::from_vec(rows, theta.len(), jacobian_storage(rows * theta.len()));
        let mut fresh_cols = block.chunks_exact(rows.max(1));
        for (c, from) in map.iter().enumerate() {
            match from {
                Some(b) => j.column_mut(c).copy_from(&kept.j.column(*b)),
                None => j.column_mut(c).copy_from_slice(fresh_cols.next().expect("one block per fresh column")),
            }
        }
        *self.ahead.lock().expect("jacobian ahead") = Some((theta.to_vec(), j, None));
        true
    }

    /// The Jacobian's columns `cols` (at most [`CHUNK_WIDE`], of the layout's unknowns) at
    /// `theta` on the drive `u` ([`OutputError::signals`]), whitened as the Jacobian's: one
    /// pass, column `k` at `block[k * rows ..]`.
    pub(super) fn columns_at(&self, theta: &[f64], cols: &[usize], u: &[f64]) -> Vec<f64> {
        let rows = self.fit.len();
        let mut block = vec![0.0; rows * cols.len()];
        self.jacobian_columns(&theta[..self.n_layout()], cols, u, None, &mut block);
        if let Some(ch) = self.chain {
            for col in block.chunks_exact_mut(rows.max(1)) {
                ch.whiten(col);
            }
        }
        block
    }

    /// The problem whose Jacobians also compute the columns of the heating terms
    /// ([`HEAT_TAUS`], at zero), kept with the last Jacobian for a fit with them that starts
    /// where this one's last Jacobian was computed (`OutputError::extending`) instead of
    /// computing its first Jacobian afresh. They cost lanes in each pass (the microspeaker's
    /// 17 columns in two passes of 10 instead of 9 and 8: 0.99 -> 1.23 s beside the residual
    /// run) and save a Jacobian (1.2 s of its 9). A layout that has heating terms: the
    /// problem as it was.
    pub fn with_spare_heat(mut self) -> Self {
        if self.layout.heat_taus.is_empty() {
            let heated = self.layout.clone().with_heat(&HEAT_TAUS);
            let shapes = heat_shapes(self.i, self.fs, &heated.heat_taus);
            self.spare = Some((heated, shapes));
        }
        self
    }

    /// The problem of a search stage (order or effects): its Jacobians take
    /// [`Stepper::for_search_jacobian`]'s steps (a woofer's: the midpoint rule, two
    /// evaluations of the model per sample instead of four). Its residual runs are the
    /// final fit's.
    pub fn searching(mut self) -> Self {
        self.stepper_jac = Stepper::for_search_jacobian(self.rates, self.fs);
        self
    }

    /// The problem with the chain's unknowns after the layout's.
    pub fn with_chain(mut self, chain: Option<&'a ChainSetup>) -> Self {
        self.chain = chain;
        self
    }

    /// Unknowns of the layout (the chain's follow).
    pub(super) fn n_layout(&self) -> usize {
        self.layout.slots().n
    }

    /// The drive and the current to match at theta.
    pub(super) fn signals(&self, th: &[f64]) -> (std::borrow::Cow<'_, [f64]>, std::borrow::Cow<'_, [f64]>) {
        match self.chain {
            None => (self.u.into(), self.i.into()),
            Some(c) => {
                let tc = &th[self.n_layout()..];
                (c.voltage(tc).0.into(), c.target(tc).into())
            }
        }
    }

    /// `(t, Re(t))` of theta: at the knots, or every 0.1 s with heating terms.
    pub fn re_track(&self, th: &[f64]) -> Vec<(f64, f64)> {
        let lay = &self.layout;
        let knots = lay.re_track(th);
        if lay.heat_taus.is_empty() {
            return knots.iter().enumerate().map(|(k, r)| (k as f64 * lay.knot_dt, *r)).collect();
        }
        let sizes = lay.heat_sizes(th);
        let step = ((0.1 * self.fs) as usize).max(1);
        (0..self.u.len())
            .step_by(step)
            .map(|m| {
                let t = m as f64 / self.fs;
                (t, re_at(&knots, lay.knot_dt, t, m, (&sizes, &self.heat)))
            })
            .collect()
    }

    /// Steps per sample of the residual and of the Jacobian runs.
    pub fn substeps(&self) -> (usize, usize) {
        (self.stepper.n(), self.stepper_jac.n())
    }

    /// The schemes of the residual and of the Jacobian runs.
    pub fn schemes(&self) -> (Scheme, Scheme) {
        (self.stepper.scheme, self.stepper_jac.scheme)
    }

    /// Simulated trace of the model `theta` over `u[..len]`: (x, i) per sample.
    pub fn trace(&self, th: &[f64], len: usize) -> Result<(Vec<f64>, Vec<f64>), usize> {
        if let Some((t, x, i)) = self.last_trace.lock().expect("trace cache").as_ref() {
            if t.as_slice() == th && x.len() >= len {
                return Ok((x[..len].to_vec(), i[..len].to_vec()));
            }
        }
        let mut x = Vec::with_capacity(len);
        let mut i = Vec::with_capacity(len);
        let (u, _) = self.signals(th);
        run_layout(&self.layout, th, &self.heat, &u, self.fs, &self.stepper, len, self.x_limit, None, |_, s| {
            x.push(s[idx::X]);
            i.push(s[idx::I]);
        })?;
        Ok((x, i))
    }

    /// The residual of theta, whitened when the chain says so ([`ChainSetup::whiten`]).
    pub(super) fn residual_vec(&self, th: &[f64]) -> Option<DVector<f64>> {
        let (u, i) = self.signals(th);
        self.residual_whitened(th, &u, &i)
    }

    /// The residual of theta with the Re(t) knots `knots` (indices into theta) fitted to
    /// this problem's samples, the rest held: Gauss-Newton steps on those columns alone
    /// (at most `steps`, each kept only when it lowers the error). Re enters the current
    /// almost linearly, so one step lands near the optimum.
    ///
    /// What a held-out score needs: the coil's temperature on the held-out part is a state,
    /// not a property of the model under test. Extrapolated from the estimation part it
    /// dominated the score of a fast-heating microspeaker (a held-out current error ten
    /// times the fitted part's, 1.9 % against 0.17 %), and no effect could show its gain
    /// through it: an LR-3 branch twelve times Le was left out with Le(x) 122 % off.
    pub(super) fn residual_with_re_fitted(&self, th: &[f64], knots: &[usize], steps: usize) -> Option<DVector<f64>> {
        let mut r = self.residual_vec(th)?;
        if knots.is_empty() || knots.len() > CHUNK_WIDE {
            return Some(r);
        }
        let (nl, rows) = (self.n_layout(), self.fit.len());
        let mut th = th.to_vec();
        for _ in 0..steps {
            let (u, _) = self.signals(&th);
            let mut block = vec![0.0; rows * knots.len()];
            self.jacobian_columns(&th[..nl], knots, &u, None, &mut block);
            if let Some(c) = self.chain {
                for col in block.chunks_mut(rows) {
                    c.whiten(col);
                }
            }
            let j = DMatrix::from_vec(rows, knots.len(), block);
            let Ok(step) = j.svd(true, true).solve(&r, 1e-12) else { break };
            let mut next = th.clone();
            for (k, &c) in knots.iter().enumerate() {
                next[c] -= step[k];
            }
            match self.residual_vec(&next) {
                Some(r2) if r2.norm_squared() < r.norm_squared() => (th, r) = (next, r2),
                _ => break,
            }
        }
        Some(r)
    }

    /// [`OutputError::residual_with`], whitened when the chain says so.
    pub(super) fn residual_whitened(&self, th: &[f64], u: &[f64], i: &[f64]) -> Option<DVector<f64>> {
        Some(self.whitened(self.residual_with(th, u, i)?))
    }

    /// A residual whitened when the chain says so ([`ChainSetup::whiten`]).
    pub(super) fn whitened(&self, mut r: DVector<f64>) -> DVector<f64> {
        if let Some(c) = self.chain {
            c.whiten(r.as_mut_slice());
        }
        r
    }

    /// [`Problem::residual`]'s run, without the caches: the whitened residual of theta and,
    /// with [`OutputError::keeping_last`], the run's trace. A runaway or unphysical theta
    /// gets an infinite residual (and cost), so LM rejects it and raises the damping.
    #[allow(clippy::type_complexity)]
    pub(super) fn residual_run(&self, th: &[f64]) -> (DVector<f64>, Option<(Vec<f64>, Vec<f64>)>) {
        let run = self.layout.physical(th).then(|| {
            let (u, i) = self.signals(th);
            self.residual_traced(th, &u, &i)
        });
        match run.flatten() {
            Some((r, trace)) => (self.whitened(r), trace),
            None => (DVector::from_element(self.fit.len(), f64::INFINITY), None),
        }
    }

    /// The residual of theta for a given drive `u` and current to match `i`.
    pub(super) fn residual_with(&self, th: &[f64], u: &[f64], i: &[f64]) -> Option<DVector<f64>> {
        let (r, trace) = self.residual_traced(th, u, i)?;
        if let Some((xs, is)) = trace {
            *self.last_trace.lock().expect("trace cache") = Some((th.to_vec(), xs, is));
        }
        Some(r)
    }

    /// [`OutputError::residual_with`] that returns the run's trace (displacement and
    /// current; with [`OutputError::keeping_last`]) instead of keeping it.
    #[allow(clippy::type_complexity)]
    pub(super) fn residual_traced(
        &self,
        th: &[f64],
        u: &[f64],
        i: &[f64],
    ) -> Option<(DVector<f64>, Option<(Vec<f64>, Vec<f64>)>)> {
        let start = self.fit.start;
        let mut r = DVector::zeros(self.fit.len());
        let cap = if self.keep_last { self.fit.end } else { 0 };
        let (mut xs, mut is) = (Vec::with_capacity(cap), Vec::with_capacity(cap));
        run_layout(
            &self.layout,
            th,
            &self.heat,
            u,
            self.fs,
            &self.stepper,
            self.fit.end,
            self.x_limit,
            None,
            |m, s| {
                if m >= start {
                    r[m - start] = s[idx::I] - i[m];
                }
                if cap > 0 {
                    xs.push(s[idx::X]);
                    is.push(s[idx::I]);
                }
            },
        )
        .ok()?;
        Some((r, (cap > 0).then_some((xs, is))))
    }

    /// The residuals of two thetas, one run per core, and the index of the one with the lower
    /// cost (the first on a tie), which the residual and trace caches then hold (two runs of
    /// [`Problem::residual`] at once would race for them).
    pub(super) fn better_of_two(&self, th: [&[f64]; 2]) -> ([DVector<f64>; 2], usize) {
        let runs = parallel_map(2, self.threads.min(2), |k| self.residual_run(th[k]));
        let [(r0, t0), (r1, t1)]: [_; 2] = runs.try_into().unwrap_or_else(|_| unreachable!("two runs"));
        let k = usize::from(r1.norm_squared() < r0.norm_squared());
        let trace = if k == 0 { t0 } else { t1 };
        if let Some((xs, is)) = trace {
            *self.last_trace.lock().expect("trace cache") = Some((th[k].to_vec(), xs, is));
        }
        let rs = [r0, r1];
        *self.last_residual.lock().expect("residual cache") = Some((th[k].to_vec(), rs[k].clone()));
        (rs, k)
    }

    /// The residual's derivative (whitened, as the Jacobian's columns) w.r.t. an error of
    /// `dc_u` (per V) at theta: what the covariance needs to carry the drive's unknown mean
    /// ([`ChainSetup::dc_u_sd`]) into the driver's parameters. Two runs of the model.
    pub(super) fn dc_u_column(&self, th: &[f64], c: &ChainSetup) -> Option<DVector<f64>> {
        let tc = &th[self.n_layout()..];
        let (u, _) = c.voltage(tc);
        let target = c.target(tc);
        let shape = coilscope_core::chain::offset_behind(u.len(), c.values(tc)[1], self.fs);
        let h = 1e-4 * coilscope_core::simulate::rms(&u).max(1e-12);
        // dc_u up by h takes h times the shape off the drive.
        let ua: Vec<f64> = u.iter().zip(&shape).map(|(v, o)| v - h * o).collect();
        let ub: Vec<f64> = u.iter().zip(&shape).map(|(v, o)| v + h * o).collect();
        let mut col = (self.residual_with(th, &ua, &target)? - self.residual_with(th, &ub, &target)?) / (2.0 * h);
        c.whiten(col.as_mut_slice());
        Some(col)
    }

    /// The chain's Jacobian columns (see [`ChainSetup`]).
    pub(super) fn chain_columns(&self, th: &[f64], c: &ChainSetup) -> Vec<Vec<f64>> {
        let nl = self.n_layout();
        let fit = self.fit.clone();
        let on = c.terms.on();
        // The current to match does not depend on hp_u.
        let target = c.target(&th[nl..]);
        // The two thetas of unknown `k`'s central difference of step `h`, and their distance.
        let pair = |k: usize, h: f64| -> (Vec<f64>, Vec<f64>, f64) {
            let (mut a, mut b) = (th.to_vec(), th.to_vec());
            a[k] += h;
            b[k] -= h;
            (a, b, 2.0 * h)
        };
        // Unknown `k` changes the drive: its column by a difference, two runs of the model.
        let drive_column = |k: usize, h: f64| -> Vec<f64> {
            let (a, b, d) = pair(k, h);
            let ra = self.residual_with(&a, &c.voltage(&a[nl..]).0, &target);
            let rb = self.residual_with(&b, &c.voltage(&b[nl..]).0, &target);
            match (ra, rb) {
                (Some(ra), Some(rb)) => ra.iter().zip(rb.iter()).map(|(x, y)| (x - y) / d).collect(),
                _ => vec![0.0; fit.len()],
            }
        };
        // The columns, in theta's order: (unknown, step, changes the drive) for the terms
        // that are on and a free dc_u, then the basis.
        let mut terms = vec![];
        let mut k = nl;
        // The delay, when on, is the chain's first unknown.
        let delay_at = on[0].then_some(nl);
        for (n, on) in on.into_iter().enumerate() {
            if on {
                terms.push((k, if n == 0 { 1e-3 } else { 1e-3 * th[k].abs().max(0.1) }, n == 1));
                k += 1;
            }
        }
        if c.dc_u_free {
            // dc_u: one unit of step.
            terms.push((k, 1.0, true));
        }
        // The basis, delayed as the target takes it off (see ChainSetup::target).
        let tau = c.values(&th[nl..])[0];
        let spectra = (tau != 0.0).then(|| c.basis_delayer(-tau, self.threads));
        let phases = spectra.as_ref().and_then(|s| s.first()).map(|s| s.phases_shared(-tau));
        // Independent columns (model runs, FFT delays): spread over the workers.
        parallel_map(terms.len() + c.basis.len(), self.threads, |j| match terms.get(j) {
            Some(&(k, h, true)) => drive_column(k, h),
            Some(&(k, h, false)) => {
                let (a, b, d) = pair(k, h);
                // The delay's two targets share the current behind the coupling, less the
                // basis (the same values as two calls of `target`).
                let (ta, tb) = if delay_at == Some(k) {
                    let [ta, tb]: [Vec<f64>; 2] = c
                        .targets_delayed(&th[nl..], &[c.values(&a[nl..])[0], c.values(&b[nl..])[0]])
                        .try_into()
                        .unwrap_or_else(|_| unreachable!("two delays, two targets"));
                    (ta, tb)
                } else {
                    (c.target(&a[nl..]), c.target(&b[nl..]))
                };
                fit.clone().map(|m| -(ta[m] - tb[m]) / d).collect()
            }
            None => match (&spectra, &phases) {
                (Some(sp), Some(ph)) => sp[j - terms.len()].delayed_range(ph, fit.clone()),
                _ => c.basis[j - terms.len()].1[fit.clone()].to_vec(),
            },
        })
    }

    /// Jacobian columns `c0 .. c0 + cnt` of the current w.r.t. theta: one run of the model on
    /// dual numbers of one of [`PASS_COSTS`]'s widths (the narrowest that holds `cnt`).
    pub(super) fn jacobian_pass(
        &self,
        th: &[f64],
        c0: usize,
        cnt: usize,
        u: &[f64],
        stop: Option<&AtomicBool>,
        block: &mut [f64],
    ) {
        let cols: Vec<usize> = (c0..c0 + cnt).collect();
        self.jacobian_columns(th, &cols, u, stop, block)
    }

    /// The Jacobian columns `cols` (at most [`CHUNK_WIDE`]) at `th`, in one run of the model
    /// on dual numbers of one of [`PASS_COSTS`]'s widths (the narrowest that holds them):
    /// column `cols[k]` at `block[k * rows ..]`. With spare heating columns
    /// ([`OutputError::with_spare_heat`]) `cols` may name them, after the layout's. On
    /// [`Jet`]s, not num-dual's dual numbers: the microspeaker's Jacobian took 0.96-1.04 s on
    /// those, 0.70 s on jets; SB17's order-4 one 505 and 475-481 ms.
    pub(super) fn jacobian_columns(
        &self,
        th: &[f64],
        cols: &[usize],
        u: &[f64],
        stop: Option<&AtomicBool>,
        block: &mut [f64],
    ) {
        // The plain model at one step per sample (the final fit's): by the sensitivity
        // equation (crate::sensitivity), in f64.
        let (layout, heat) = match &self.spare {
            Some((l, h)) => (l, h),
            None => (&self.layout, &self.heat),
        };
        if crate::sensitivity::applies(layout, &self.stepper_jac) {
            let th: std::borrow::Cow<[f64]> =
                if self.spare.is_some() { [th, &[0.0; HEAT_TAUS.len()]].concat().into() } else { th.into() };
            crate::sensitivity::pass(
                layout,
                heat,
                &th,
                cols,
                u,
                self.fs,
                &self.stepper_jac,
                self.fit.clone(),
                stop,
                block,
            );
            return;
        }
        fn lanes<const N: usize>(
            p: &OutputError,
            th: &[f64],
            cols: &[usize],
            u: &[f64],
            stop: Option<&AtomicBool>,
            block: &mut [f64],
        ) {
            // With spare heating columns: the heated layout, its heating terms at zero (the
            // same run: Re + 0 h is Re) after the layout's entries.
            let (layout, heat, th) = match &p.spare {
                Some((l, h)) => (l, h, std::borrow::Cow::Owned([th, &[0.0; HEAT_TAUS.len()]].concat())),
                None => (&p.layout, &p.heat, std::borrow::Cow::Borrowed(th)),
            };
            let thd: Vec<Jet<N>> = th
                .iter()
                .enumerate()
                .map(|(j, &t)| {
                    cols.iter().position(|&c| c == j).map_or(Jet::constant(t), |k| Jet::constant(t).derivative(k))
                })
                .collect();
            p.jacobian_run(layout, heat, &thd, cols.len(), u, stop, block);
        }
        match cols.len() {
            0 => {}
            n if n <= CHUNK_SHORT => lanes::<CHUNK_SHORT>(self, th, cols, u, stop, block),
            n if n <= CHUNK => lanes::<CHUNK>(self, th, cols, u, stop, block),
            n if n <= CHUNK_TEN => lanes::<CHUNK_TEN>(self, th, cols, u, stop, block),
            _ => lanes::<CHUNK_WIDE>(self, th, cols, u, stop, block),
        }
    }

    /// One run of `layout` on the seeded `thd`: the first `cnt` lanes of the current's
    /// derivative over the fitted samples, lane `k` at `block[k * rows ..]`.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn jacobian_run<const N: usize>(
        &self,
        layout: &Layout,
        heat: &[Vec<f64>],
        thd: &[Jet<N>],
        cnt: usize,
        u: &[f64],
        stop: Option<&AtomicBool>,
        block: &mut [f64],
    ) {
        let (start, rows) = (self.fit.start, self.fit.len());
        // A run that fails here ran away at a theta whose f64 run did not: leave zeros.
        let _ =
            run_layout(layout, thd, heat, u, self.fs, &self.stepper_jac, self.fit.end, f64::INFINITY, stop, |m, s| {
                if m >= start {
                    let e = &s[idx::I].eps;
                    for k in 0..cnt {
                        block[k * rows + m - start] = e[k];
                    }
                }
            });
    }

    /// All Jacobian columns, passes spread over `threads` workers.
    pub fn jacobian(&self, th: &[f64]) -> DMatrix<f64> {
        self.jacobian_and_spare(th).0
    }

    /// [`OutputError::jacobian`] and the spare heating columns computed with it
    /// ([`OutputError::with_spare_heat`]).
    pub(super) fn jacobian_and_spare(&self, th: &[f64]) -> (DMatrix<f64>, Option<DMatrix<f64>>) {
        let (u, _) = self.signals(th);
        self.jacobian_with_spare(th, &u, &self.pass_widths(0), &[], &AtomicBool::new(false))
            .expect("nothing stops these passes")
    }

    /// The widths of the Jacobian's passes beside `leads` model runs ([`passes_for`]), over
    /// the spare heating columns too ([`OutputError::with_spare_heat`]).
    pub(super) fn pass_widths(&self, leads: usize) -> Vec<usize> {
        let layout = self.spare.as_ref().map_or(&self.layout, |(l, _)| l);
        passes_for(layout, &self.stepper_jac, self.pass_columns(), self.threads, leads, true)
    }

    /// The columns the Jacobian's passes compute: the layout's, and the spare heating
    /// columns after them.
    pub(super) fn pass_columns(&self) -> usize {
        self.n_layout() + if self.spare.is_some() { HEAT_TAUS.len() } else { 0 }
    }

    /// The Jacobian at `th` in passes of `widths` (summing to [`OutputError::pass_columns`];
    /// [`jacobian_passes`] with the `lead` tasks before the passes, `None` when one of them
    /// stops them) and, with spare heating columns, those columns (whitened as the Jacobian
    /// is).
    pub(super) fn jacobian_with_spare(
        &self,
        th: &[f64],
        u: &[f64],
        widths: &[usize],
        lead: &[&(dyn Fn() -> bool + Sync)],
        stop: &AtomicBool,
    ) -> Option<(DMatrix<f64>, Option<DMatrix<f64>>)> {
        let (nl, rows) = (self.n_layout(), self.fit.len());
        let jl = jacobian_passes(rows, widths, self.threads, lead, stop, |c0, w, block| {
            self.jacobian_pass(&th[..nl], c0, w, u, Some(stop), block)
        })?;
        self.jacobians.fetch_add(1, Ordering::Relaxed);
        let (jl, spare) = if self.spare.is_some() {
            // The spare columns are the passes' last: the layout's are the storage's start.
            let mut v: Vec<f64> = jl.data.into();
            let mut h = DMatrix::from_vec(rows, HEAT_TAUS.len(), v.split_off(rows * nl));
            if let Some(c) = self.chain {
                for mut col in h.column_iter_mut() {
                    c.whiten(col.as_mut_slice());
                }
            }
            (DMatrix::from_vec(rows, nl, v), Some(h))
        } else {
            (jl, None)
        };
        Some((self.with_chain_columns(th, jl), spare))
    }

    /// [`OutputError::jacobian`] in passes of the given widths (summing to
    /// `OutputError::pass_columns`): the tests' and the benches' (`PASS_COSTS`).
    pub fn jacobian_in(&self, th: &[f64], widths: &[usize]) -> DMatrix<f64> {
        let (u, _) = self.signals(th);
        self.jacobian_with_spare(th, &u, widths, &[], &AtomicBool::new(false)).expect("nothing stops these passes").0
    }

    /// The layout's Jacobian columns `jl` with the chain's after them, all whitened (as the
    /// residual is) when the chain is estimated.
    pub(super) fn with_chain_columns(&self, th: &[f64], jl: DMatrix<f64>) -> DMatrix<f64> {
        let nl = self.n_layout();
        let Some(c) = self.chain else { return jl };
        let mut j = DMatrix::from_vec(self.fit.len(), th.len(), jacobian_storage(self.fit.len() * th.len()));
        j.columns_mut(0, nl).copy_from(&jl);
        recycle_jacobian(jl);
        for (k, col) in self.chain_columns(th, c).into_iter().enumerate() {
            j.column_mut(nl + k).copy_from_slice(&col);
        }
        let rows = j.nrows();
        c.whiten_columns(j.as_mut_slice(), rows, self.threads);
        j
    }

    /// Where this problem (a final fit's with heating terms, [`HEAT_TAUS`]) starts from
    /// `from` (the same fit without them: the same record, chain and steps): the theta
    /// `from`'s last Jacobian was computed at, the heating terms at zero. The residual there
    /// and the Jacobian of the first iteration are `from`'s, with its spare heating columns
    /// ([`OutputError::with_spare_heat`]) between the layout's and the chain's: at that theta
    /// they are this problem's (the heating terms at zero change no run). `None` when `from`
    /// kept no spare columns.
    pub(super) fn extending(&self, from: &OutputError) -> Option<Vec<f64>> {
        let (nl, nf) = (self.n_layout(), from.n_layout());
        let nh = self.layout.slots().heat;
        let j_from = from.last_jacobian.lock().expect("jacobian cache").clone()?;
        let at = from.last_jacobian_at.lock().expect("jacobian cache");
        let JacobianAt { theta: at, residual, spare: Some(spare) } = at.as_ref()? else { return None };
        if nh != (nf..nl)
            || self.layout.heat_taus != HEAT_TAUS
            || at.len() != j_from.ncols()
            || spare.nrows() != j_from.nrows()
            || j_from.nrows() != self.fit.len()
        {
            return None;
        }
        let theta = heat_at_zero(at, nf, nl);
        let rows = self.fit.len();
        let mut j = DMatrix::from_vec(rows, theta.len(), jacobian_storage(rows * theta.len()));
        j.columns_mut(0, nf).copy_from(&j_from.columns(0, nf));
        j.columns_mut(nf, nh.len()).copy_from(spare);
        j.columns_mut(nl, theta.len() - nl).copy_from(&j_from.columns(nf, j_from.ncols() - nf));
        *self.last_residual.lock().expect("residual cache") = Some((theta.clone(), residual.clone()));
        *self.ahead.lock().expect("jacobian ahead") = Some((theta.clone(), j, None));
        Some(theta)
    }
}

/// `f(0) .. f(n - 1)` in order, computed by `threads` workers taking the indices in turn.
pub(crate) fn parallel_map<T: Send>(n: usize, threads: usize, f: impl Fn(usize) -> T + Sync) -> Vec<T> {
    let next = AtomicUsize::new(0);
    let work = || {
        let mut out = vec![];
        loop {
            let k = next.fetch_add(1, Ordering::Relaxed);
            if k >= n {
                break out;
            }
            out.push((k, f(k)));
        }
    };
    let mut done: Vec<(usize, T)> = if threads.min(n) <= 1 {
        work()
    } else {
        std::thread::scope(|scope| {
            let hs: Vec<_> = (0..threads.min(n)).map(|_| scope.spawn(work)).collect();
            hs.into_iter().flat_map(|h| h.join().expect("a worker panicked")).collect()
        })
    };
    done.sort_by_key(|(k, _)| *k);
    done.into_iter().map(|(_, v)| v).collect()
}

/// A Jacobian of `rows` rows from its passes: `pass(c0, w, block)` writes the `w = widths[p]`
/// columns `c0 .. c0 + w` of pass `p` into `block`, their part of the matrix's column-major
/// storage (`block[k * rows + row]` is column `c0 + k`). The passes are independent;
/// `threads` workers take them in turn, each writing where the matrix keeps it (no copy).
///
/// `lead` runs before the passes, each a task of its own (the residual run of
/// [`Problem::residual_ahead`] and the work alongside it): the passes take the workers they
/// leave idle. When one returns false, `stop` is set, the passes stop (a pass polls
/// `stop`) and `None` is returned; the lead tasks always run.
pub(crate) fn jacobian_passes(
    rows: usize,
    widths: &[usize],
    threads: usize,
    lead: &[&(dyn Fn() -> bool + Sync)],
    stop: &AtomicBool,
    pass: impl Fn(usize, usize, &mut [f64]) + Sync,
) -> Option<DMatrix<f64>> {
    let n: usize = widths.iter().sum();
    let mut storage = jacobian_storage(rows * n);
    {
        let mut rest = storage.as_mut_slice();
        let mut blocks = Vec::with_capacity(widths.len());
        for &w in widths {
            let (b, r) = rest.split_at_mut(w * rows);
            blocks.push(std::sync::Mutex::new(b));
            rest = r;
        }
        let starts: Vec<usize> = widths.iter().scan(0, |c, &w| Some(std::mem::replace(c, *c + w))).collect();
        parallel_map(lead.len() + blocks.len(), threads, |k| match lead.get(k) {
            Some(f) => {
                if !f() {
                    stop.store(true, Ordering::Relaxed);
                }
            }
            None if stop.load(Ordering::Relaxed) => {}
            None => {
                let b = k - lead.len();
                let mut block = blocks[b].lock().expect("Jacobian block");
                // Recycled storage holds an earlier matrix: the pass starts from zeros (a
                // pass leaves the entries of a run that failed at zero), on its own core.
                block.fill(0.0);
                pass(starts[b], widths[b], &mut block);
            }
        });
    }
    if stop.load(Ordering::Relaxed) {
        recycle_storage(storage);
        return None;
    }
    Some(DMatrix::from_vec(rows, n, storage))
}

/// Storage of Jacobians no longer read, for the next ones ([`jacobian_storage`]).
pub(super) static SPARE_JACOBIANS: std::sync::Mutex<Vec<Vec<f64>>> = std::sync::Mutex::new(Vec::new());
/// Most spare Jacobians kept.
pub(super) const SPARE_KEPT: usize = 2;

/// Storage for a Jacobian of `len` entries: a recycled one ([`recycle_jacobian`]) when
/// there is one, its entries stale (the caller writes every entry), else a new one.
///
/// Why: a Jacobian of the whole record is 50-90 MB (29 columns of 240 000-384 000 rows), and
/// the allocator takes a block that large fresh from the system each time and gives it back
/// when it is freed, so that every new matrix's first writes were page faults, each a page
/// zeroed by the kernel: 7 % of 18WU's `identify` (perf), most of it on the thread that then
/// waits for the passes.
pub(crate) fn jacobian_storage(len: usize) -> Vec<f64> {
    let mut spare = SPARE_JACOBIANS.lock().unwrap_or_else(|e| e.into_inner());
    // The smallest spare that holds `len`, else the largest (grown).
    let fits = (0..spare.len()).filter(|&k| spare[k].capacity() >= len).min_by_key(|&k| spare[k].capacity());
    let pick = fits.or_else(|| (0..spare.len()).max_by_key(|&k| spare[k].capacity()));
    let Some(k) = pick else {
        // New storage from the allocator's zeroed pages: nothing is written here (the passes
        // write their blocks on their own cores).
        return vec![0.0; len];
    };
    let mut v = spare.swap_remove(k);
    drop(spare);
    // Grown to `len` exactly (not doubled).
    v.reserve_exact(len.saturating_sub(v.len()));
    v.resize(len, 0.0);
    v
}

/// Hands a Jacobian that is no longer read back for the next one ([`jacobian_storage`]).
pub(crate) fn recycle_jacobian(j: DMatrix<f64>) {
    recycle_storage(j.data.into());
}

pub(super) fn recycle_storage(v: Vec<f64>) {
    let mut spare = SPARE_JACOBIANS.lock().unwrap_or_else(|e| e.into_inner());
    spare.push(v);
    if spare.len() > SPARE_KEPT {
        let smallest = (0..spare.len()).min_by_key(|&k| spare[k].capacity()).expect("not empty");
        spare.swap_remove(smallest);
    }
}

/// Frees the spare Jacobians ([`identify`] does at its end).
pub fn release_spare_jacobians() {
    SPARE_JACOBIANS.lock().unwrap_or_else(|e| e.into_inner()).clear();
}

impl Problem for OutputError<'_> {
    fn residual_jacobian(&self, theta: &[f64]) -> (DVector<f64>, DMatrix<f64>) {
        let r = self.residual(theta);
        let ahead = self.ahead.lock().expect("jacobian ahead").take();
        let (j, spare) = match ahead {
            Some((th, j, spare)) if th.as_slice() == theta => (j, spare),
            _ => self.jacobian_and_spare(theta),
        };
        if self.keep_last {
            let mut copy = jacobian_storage(j.len());
            copy.copy_from_slice(j.as_slice());
            self.keep_jacobian(DMatrix::from_vec(j.nrows(), j.ncols(), copy));
            *self.last_jacobian_at.lock().expect("jacobian cache") =
                Some(JacobianAt { theta: theta.to_vec(), residual: r.clone(), spare });
        }
        (r, j)
    }
    fn recycle(&self, j: DMatrix<f64>) {
        // A search stage keeps the matrix itself (`keeping_search`): LM hands back the one it
        // just asked for.
        if self.keep_search {
            self.keep_jacobian(j);
        } else {
            recycle_jacobian(j);
        }
    }
    fn residual(&self, theta: &[f64]) -> DVector<f64> {
        if let Some((th, r)) = self.last_residual.lock().expect("residual cache").as_ref() {
            if th.as_slice() == theta {
                return r.clone();
            }
        }
        let (r, trace) = self.residual_run(theta);
        if let Some((xs, is)) = trace {
            *self.last_trace.lock().expect("trace cache") = Some((theta.to_vec(), xs, is));
        }
        *self.last_residual.lock().expect("residual cache") = Some((theta.to_vec(), r.clone()));
        r
    }

    /// The residual run (one core, f64, all sub-steps) and the Jacobian's passes (dual
    /// numbers) as one queue of tasks, the residual first, over `threads` workers: the
    /// passes fill the cores the residual leaves idle. As soon as the residual says the
    /// Jacobian is not wanted (a rejected trial, a stage that ends), the passes stop (within
    /// `STOP_POLL` samples) and nothing is kept. The Jacobian is the one
    /// [`OutputError::jacobian`] computes (the same passes).
    fn residual_ahead(
        &self,
        theta: &[f64],
        wanted: &(dyn Fn(&DVector<f64>) -> bool + Sync),
        alongside: Option<&(dyn Fn() + Sync)>,
    ) -> DVector<f64> {
        let cached =
            self.last_residual.lock().expect("residual cache").as_ref().is_some_and(|(th, _)| th.as_slice() == theta);
        if self.threads < 2 || cached || !self.layout.physical(theta) {
            if let Some(f) = alongside {
                f();
            }
            return self.residual(theta);
        }
        let (u, i) = self.signals(theta);
        let stop = AtomicBool::new(false);
        let r = std::sync::Mutex::new(None);
        let first = || {
            let res = self
                .residual_whitened(theta, &u, &i)
                .unwrap_or_else(|| DVector::from_element(self.fit.len(), f64::INFINITY));
            let go = wanted(&res);
            *r.lock().expect("residual") = Some(res);
            go
        };
        let side = || {
            if let Some(f) = alongside {
                f();
            }
            true
        };
        let lead: Vec<&(dyn Fn() -> bool + Sync)> =
            if alongside.is_some() { vec![&first, &side] } else { vec![&first] };
        let j = self.jacobian_with_spare(theta, &u, &self.pass_widths(lead.len()), &lead, &stop);
        let r = r.into_inner().expect("residual").expect("the first task is the residual");
        *self.last_residual.lock().expect("residual cache") = Some((theta.to_vec(), r.clone()));
        if let Some((j, spare)) = j {
            *self.ahead.lock().expect("jacobian ahead") = Some((theta.to_vec(), j, spare));
        }
        r
    }
}

/// The start with Le restored when the small-signal fit moved all the coil's inductance into
/// the LR-2 branch (Le below [`LE_VANISHED`] of Le + L2: zero in all but rounding): then the
/// electrical equation has no time constant and the start model cannot run. On a 0.1 g microspeaker heating 68 K during
/// the record the impedance fit gave Le = 0, L2 44 uH, R2 22 ohm (true: 30 uH, 15 uH, 2 ohm),
/// and `identify` stopped with "the start model diverged at sample 1". Above the branch's
/// corner R2 / (2 pi L2) (here 79 kHz) the two are one inductance, so the start shares it
/// equally and the fit separates them.
pub(super) fn split_vanished_le(mut p: Parameters) -> Parameters {
    // A branch that vanished itself (L2 or R2 at zero in all but rounding: the impedance fit
    // of a record through an AC-coupled, skewed chain, SB17 `-real-chain`: L2 1e-68 H) is
    // restarted at L2 = 2 Le, R2 = Re / 4 (the middle of the bundled drivers' ratios): the
    // output error rejects non-positive branches and cannot leave zero.
    if let Some((l2, r2)) = &mut p.l2r2 {
        if l2.c[0] < LE_VANISHED * p.le.c[0] || r2.c[0] < LE_VANISHED * p.re {
            l2.c[0] = 2.0 * p.le.c[0];
            r2.c[0] = 0.25 * p.re;
        }
        let total = p.le.c[0] + l2.c[0];
        if p.le.c[0] < LE_VANISHED * total {
            p.le.c[0] = 0.5 * total;
            l2.c[0] = 0.5 * total;
        }
    }
    p
}

/// Share of Le in Le + L2 below which the small-signal start's Le counts as vanished. At 5 % it
/// also took the SB17 creep record, whose start has a small but real Le, and that fit failed.
pub(super) const LE_VANISHED: f64 = 1e-3;

//! [`identify`]'s work on one record: the start, the chain, the order and effects searches,
//! and the final fit.

use super::*;

/// The chain of a final theta (`nl` layout unknowns) with its sds from `cov`.
pub(super) fn chain_of(
    c: &ChainSetup,
    th: &[f64],
    nl: usize,
    cov: Option<&DMatrix<f64>>,
    dc_u_sd: f64,
) -> coilscope_core::chain::Chain {
    let fs = c.terms.fs;
    let tc = &th[nl..];
    let sd = |k: usize| cov.map_or(f64::NAN, |m| crate::lm::sd_from_variance(m[(nl + k, nl + k)]));
    let [_, _, fi] = c.values(tc);
    let mut out = crate::linear::ChainEstimate { values: c.values(tc), sd: c.terms.sds(cov, nl), on: c.terms.on(), fs }
        .to_chain();
    out.dc_u = c.voltage(tc).1;
    let sd_dc = match c.dc_u_index() {
        Some(km) => sd(km) * c.u_unit,
        None => {
            // Held, dc_u follows hp_u (ChainSetup::voltage): its sd is hp_u's, carried
            // through, and the drive's own mean's (ChainSetup::dc_u_sd).
            let fu = c.values(tc)[1];
            let h = 1e-3 * fu.abs().max(0.1);
            let slope = (c.dc_u(fu + h) - c.dc_u(fu - h)) / (2.0 * h);
            let sd_u = c.terms.on()[1].then(|| out.sd.get("hp_u").copied()).flatten().unwrap_or(0.0);
            (slope * sd_u).hypot(dc_u_sd)
        }
    };
    out.sd.insert("dc_u".into(), sd_dc);
    out.fitted.push("dc_u".into());
    let k = c.basis_index();
    // The offset behind a coupling of corner fi: its inverse maps dc to dc (1 + K) plus a ramp
    // 2 K dc per sample. Read off the ramp where the ramp is the larger part over the record
    // (2 K n >= 1): the constant also takes what the inverted coupling makes of the hum (a
    // sinusoid plus a constant set by its phase at the start), which put the current's offset
    // 1.1 % off at 24 sd (PTT4 through every effect of a card); the ramp has none of it.
    let kk = (std::f64::consts::PI * fi / fs).tan();
    let a = c.basis[0].1[0];
    let n = c.basis[0].1.len() as f64;
    let (dc_i, sd_i) = if 2.0 * kk * n >= 1.0 {
        (a * tc[k + 1] / (2.0 * kk * n), a * sd(k + 1) / (2.0 * kk * n))
    } else {
        (a * tc[k] / (1.0 + kk), a * sd(k) / (1.0 + kk))
    };
    out.dc_i = dc_i;
    out.sd.insert("dc_i".into(), sd_i);
    out.fitted.push("dc_i".into());
    // Hum: the mains family with the larger lines.
    let lines = |mains: f64| -> Vec<[f64; 2]> {
        (1..=crate::linear::HUM_HARMONICS)
            .filter_map(|h| {
                let f = mains * h as f64;
                let at = |w: &str| c.basis.iter().position(|(name, _)| name == &format!("{w} {f}")).map(|p| tc[k + p]);
                Some((a * at("cos")?, a * at("sin")?)).map(|(cc, cs)| [cc.hypot(cs), (-cs).atan2(cc)])
            })
            .collect()
    };
    let power = |l: &[[f64; 2]]| l.iter().map(|v| v[0] * v[0]).sum::<f64>();
    let (l50, l60) = (lines(50.0), lines(60.0));
    let (f, l) = if power(&l50) >= power(&l60) { (50.0, l50) } else { (60.0, l60) };
    out.hum = Some(coilscope_core::chain::Hum { f, u: vec![], i: l });
    out.fitted.push("hum".into());
    out
}

/// Relative RMS of `r` against `i` (same length).
pub(super) fn rel(r: &DVector<f64>, i: &[f64]) -> f64 {
    r.norm() / i.iter().map(|v| v * v).sum::<f64>().sqrt()
}

/// [`identify`]'s work.
pub(super) fn identify_record(
    u_rec: &[f64],
    i_rec: &[f64],
    fs: f64,
    origin: &str,
    opts: &IdentifyOptions,
    observe: &mut dyn FnMut(&Progress),
) -> Result<LargeFit, IdentifyError> {
    use IdentifyError::*;
    let (u, i) = (u_rec, i_rec);
    if u.len() != i.len() {
        return Err(Input(format!(
            "{origin}: voltage and current have different lengths ({} and {})",
            u.len(),
            i.len()
        )));
    }
    check_channels(u, i, fs, opts.chain || opts.detect_chain, origin).map_err(Input)?;
    if let Some(o) = opts.order {
        if !(MIN_ORDER..=MAX_ORDER).contains(&o) {
            return Err(Input(format!("power-series order {o} is not valid ({MIN_ORDER} ..= {MAX_ORDER})")));
        }
    }
    if !(opts.mms.is_finite() && opts.mms > 0.0 && opts.mms < 2.0) {
        return Err(Input(format!("moving mass {} kg is not valid (0 .. 2 kg; give kg, not g)", opts.mms)));
    }
    let seconds = u.len() as f64 / fs;
    // The linear fits of the first seconds: the start's and, with the chain, the chain's
    // (below). They are independent, and run side by side.
    let m_start = u.len().min((4.0 * fs) as usize);
    let (start_fit, chain_fit) = std::thread::scope(|scope| {
        let chain_fit = (opts.chain || opts.detect_chain).then(|| {
            scope.spawn(|| {
                let lin_opts = LinearOptions { chain: true, ..LinearOptions::LARGE_SIGNAL_START };
                fit_linear_record(&u[..m_start], &i[..m_start], fs, origin, &lin_opts, |_| {})
            })
        });
        // The start needs no more than a few seconds (the fit is O(n) per iteration). The
        // small-signal effects are chosen as in `linear`: on a large coil with an LR-3
        // branch the LR-2 fit alone landed on fs = 1.4 kHz and Re 3x too high, and the
        // start model then hardly moved. The order search below starts from
        // the LR-2 part of that fit; the effects are chosen again on held-out data.
        let start_fit = opts.init.is_none().then(|| {
            let lin_opts = LinearOptions { effects: EffectsChoice::Auto, ..LinearOptions::LARGE_SIGNAL_START };
            fit_linear_record(&u[..m_start], &i[..m_start], fs, origin, &lin_opts, |_| {})
        });
        (start_fit, chain_fit.map(|h| h.join().expect("a linear fit does not panic")))
    });
    // Start values.
    let (start, mut linear) = match (&opts.init, start_fit) {
        (Some(p), _) => (p.clone(), None),
        (None, fit) => {
            let lin = fit.expect("fitted when no start is given").map_err(Input)?;
            (split_vanished_le(scale_by_mms(&lin, opts.mms).map_err(Input)?), Some(lin))
        }
    };
    // The start fit's LR-2 model, from which the effects search's linear fits (creep, LR-3) on
    // the same seconds grow ([`crate::linear::fit_linear_record_from`]).
    let start_lr2 = linear.as_ref().map(|l| l.lr2.clone());
    // The measurement chain. Its start values come from a linear fit of its own, whose driver
    // is a second candidate for the driver's start (chosen below by which misses less). All
    // three of delay and corners are estimated, whatever that fit kept: on a large-signal
    // record its sds are wide (distortion is most of its residual: SB17 with a 0.3-sample delay
    // gave 0.34 +- 0.09), too wide to decide. Offsets and hum are always in.
    let mut chain_start = None;
    // Looking for a chain: the linear fit with it kept a delay or a corner (each at
    // CHAIN_SIGNIFICANCE sd or more), so the fit takes the chain; else it is a plain record.
    let mut chain_detected = None;
    let chain_fit = match chain_fit {
        Some(Ok(lin)) if !opts.chain => {
            // What the chain fit kept, in the ranges of a card (a skew of 0.05 sample or more,
            // a corner of 0.2-20 Hz) and lowering the fit's error power by CHAIN_SEEN_GAIN of
            // it: a large-signal record's linear misfit puts a few hundredths of a sample and
            // a corner of 10 Hz at several sd into a chain that is not there.
            let gain = linear.as_ref().map_or(1.0, |l| 1.0 - (lin.residual_rel / l.residual_rel).powi(2));
            let seen = lin.chain.as_ref().filter(|_| gain >= CHAIN_SEEN_GAIN).map(chain_seen).unwrap_or_default();
            if seen.is_empty() {
                None
            } else {
                chain_detected = Some(format!(
                    "the small-signal fit of the first {:.1} s found {}",
                    m_start as f64 / fs,
                    seen.join(", ")
                ));
                Some(Ok(lin))
            }
        }
        Some(Err(_)) if !opts.chain => None,
        other => other,
    };
    let (setup, mut cth) = if let Some(fit) = chain_fit {
        let lin_chain = fit.map_err(Input)?;
        let est = lin_chain.chain.clone();
        if opts.init.is_none() {
            chain_start = scale_by_mms(&lin_chain, opts.mms).ok().map(|p| (split_vanished_le(p), lin_chain.clone()));
        }
        let mut setup =
            ChainSetup::new(u_rec, i_rec, crate::linear::ChainTerms { fs, delay: true, hp_u: true, hp_i: true });
        let values = est.map_or([0.0; 3], |c| c.values);
        // Whiten at the start's current corner (at most 10 Hz, the excitation's lower end).
        setup.whiten_hz = values[2].clamp(0.0, 10.0);
        let th = setup.theta0(&values);
        (Some(setup), th)
    } else {
        (None, vec![])
    };
    let (u0, i0) = match &setup {
        Some(s) => (s.voltage(&cth).0, s.target(&cth)),
        None => (u_rec.to_vec(), i_rec.to_vec()),
    };
    let (u, i) = (&u0[..], &i0[..]);
    let setup = setup.as_ref();
    // theta of a layout followed by the chain's unknowns.
    let join = |mut th: Vec<f64>, cth: &[f64]| {
        th.extend_from_slice(cth);
        th
    };
    let threads = if opts.threads == 0 {
        std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
    } else {
        opts.threads
    };
    let n_re = ((seconds / opts.knot_seconds).ceil() as usize + 1).max(2);
    let knot_dt = seconds / (n_re - 1) as f64;
    // Settling: the unknown initial state decays with the mechanical time constant.
    let settle_of = |st: &Parameters| ((5.0 * 2.0 * st.mms / st.rms.max(1e-9)).clamp(0.02, 0.25) * fs) as usize;
    // The start model's run over the record: its displacement, and the share of the current
    // it misses after settling; Err(sample) where it diverged.
    // The box's unknowns, relative to the start's box.
    let box_unknowns = |st: &Parameters, x_ref: f64| -> Option<BoxUnknowns> {
        opts.enclosure.as_ref()?;
        Some(BoxUnknowns::new(st.enclosure.as_ref()?, st.sd?, x_ref))
    };
    let run_start = |st: &Parameters| -> Result<(Vec<f64>, f64), usize> {
        // Reach of the start model: the basis scale, and the runaway limit.
        let probe = Layout::new(MIN_ORDER, n_re, knot_dt, 1e-3, Scales::of(st), st.l2r2.is_some(), opts.mms)
            .with_box(box_unknowns(st, 1e-3));
        let th0 = join(probe.theta_from(st, None), &cth);
        let pr = OutputError::new(probe, u, i, fs, 0..u.len(), st.rates(), f64::INFINITY, threads).with_chain(setup);
        let (x0, i_start) = pr.trace(&th0, u.len())?;
        let settled_part = settle_of(st).min(u.len())..u.len();
        // With the chain estimated, its start (the corners from a linear fit, 40 % off on a
        // large-signal record) leaves a slow drift in the drive and in the current to match,
        // which the fit takes out and which says nothing of the start's driver: the miss is
        // then judged behind a second-order high-pass at START_MISS_HP_HZ.
        let mut e: Vec<f64> = settled_part.clone().map(|m| i_start[m] - i[m]).collect();
        let mut t = i[settled_part].to_vec();
        if setup.is_some() {
            for v in [&mut e, &mut t] {
                for _ in 0..2 {
                    let mut f = coilscope_core::chain::HighPass::new(START_MISS_HP_HZ, fs);
                    v.iter_mut().for_each(|x| *x = f.push(*x));
                }
            }
        }
        Ok((x0, rel(&DVector::from_vec(e), &t)))
    };
    let mut start = Parameters { mms: opts.mms, thermal: None, ..start };
    // In a box: the driver and the box from the start fit's impedance, jointly.
    // The joint fit's other ends ([`crate::box_fit::BoxFit::alternatives`]), tried below.
    let mut box_alternatives: Vec<Parameters> = Vec::new();
    let mut in_box = |p: Parameters, lin: Option<&LinearFit>| -> Result<Parameters, IdentifyError> {
        let (Some(b), Some(lin)) = (&opts.enclosure, lin) else {
            return Ok(p);
        };
        if p.enclosure.is_some() {
            return Ok(p);
        }
        let h1 = &lin.h1;
        let keep: Vec<usize> = (1..h1.f.len())
            .filter(|&k| h1.f[k] >= lin.band[0] && h1.f[k] <= lin.band[1] && h1.usable(k, BOX_START_COHERENCE))
            .collect();
        let f: Vec<f64> = keep.iter().map(|&k| h1.f[k]).collect();
        let z: Vec<coilscope_core::Complex64> = keep.iter().map(|&k| h1.z[k]).collect();
        let (f, z) = crate::box_fit::log_spaced(&f, &z, BOX_START_POINTS, f[0], f[f.len() - 1].min(BOX_START_TOP_HZ));
        let p = Parameters { sd: Some(b.sd), ..p };
        let (driver, fit) = crate::box_fit::fit_driver_in_box(&f, &z, false, &p, b.choice, b.sp, b.vb)
            .map_err(|e| Input(format!("{origin}: {e}")))?;
        let with_port = |mut d: Parameters| {
            if let (Some(a), Some(e)) = (b.port_area, d.enclosure.as_mut()) {
                if let BoxKind::Vented { port_area, .. } = &mut e.kind {
                    *port_area = Some(a);
                }
            }
            Parameters { mms: opts.mms, thermal: None, ..d }
        };
        box_alternatives.extend(fit.alternatives.into_iter().map(with_port));
        Ok(with_port(driver))
    };
    start = in_box(start, linear.as_ref())?;
    // With the chain, the start from the linear fit without it can miss the driver (SB17 with
    // the voltage channel 0.28 sample late, 4.5 / 1.4 Hz coupling and 1 % offsets: the fit
    // without the chain missed 100 % of the current); the one with the chain can lose the
    // LR-2 branch (SB17 with AC coupling: R2 -> 1e-132 ohm). The one that misses less wins.
    // The two runs (one core each) side by side.
    let alt = match chain_start {
        Some((alt, lin)) => Some((in_box(Parameters { mms: opts.mms, thermal: None, ..alt }, Some(&lin))?, lin)),
        None => None,
    };
    let (mut started, other) = std::thread::scope(|scope| {
        let other = alt.as_ref().map(|(a, _)| scope.spawn(|| run_start(a)));
        (run_start(&start), other.map(|h| h.join().expect("a model run does not panic")))
    });
    let miss = |r: &Result<(Vec<f64>, f64), usize>| r.as_ref().map_or(f64::INFINITY, |(_, m)| *m);
    if let (Some((alt, lin)), Some(other)) = (alt, other) {
        if miss(&other) < miss(&started) {
            (start, started, linear) = (alt, other, Some(lin));
        }
    }
    // In a box: the joint fit's other ends, where one misses less of the current.
    for alt in box_alternatives {
        let other = run_start(&alt);
        if miss(&other) < miss(&started) {
            (start, started) = (alt, other);
        }
    }
    // A start outside physics (a resistance or inductance at zero: with a faster-falling LM
    // damping once tried, the impedance fit of 1 s cut mid-signal from SB17 ended on
    // Re = 0, and the start model's NaN read "diverged at sample 1") cannot run; say what it
    // was.
    // The start's values, for the messages below.
    let start_values = |p: &Parameters| {
        let l2r2 =
            p.l2r2.as_ref().map_or(String::new(), |(l2, r2)| format!(", L2 {:.3e} H, R2 {:.3e} ohm", l2.c[0], r2.c[0]));
        format!(
            "Re {:.3e} ohm, Le {:.3e} H{l2r2}, Bl {:.3e} T m, Kms {:.3e} N/m, Rms {:.3e} kg/s",
            p.re, p.le.c[0], p.bl.c[0], p.kms.c[0], p.rms
        )
    };
    let start_origin = if opts.init.is_some() { "the one given" } else { "the impedance fit of the record" };
    let l2r2_ok = start.l2r2.as_ref().is_none_or(|(l2, r2)| l2.c[0] > 0.0 && r2.c[0] > 0.0);
    if !(start.re > 0.0 && start.le.c[0] > 0.0 && start.bl.c[0] != 0.0 && start.kms.c[0] > 0.0 && l2r2_ok) {
        return Err(Input(format!(
            "{origin}: the small-signal start ({start_origin}) is not physical ({}) over this {seconds:.2} s record: the record is too short or too irregular for it; record longer (2 s or more is typical)",
            start_values(&start)
        )));
    }
    // A start whose resonance left the record's band lost its motional branch (an impedance
    // fit from a wrong resonance once ended at Cmes = 4.7e36 F, a resonance of 1e-66 Hz, and
    // the length check below asked for a record of 1.7e66 s).
    let f_res = start.resonance_hz();
    if !(f_res >= 0.5 && f_res <= 0.5 * fs) {
        return Err(Input(format!(
            "{origin}: the small-signal start ({start_origin}) has its resonance at {f_res:.3e} Hz, outside the record's band ({}): its fit lost the driver's motional part: check that channel 2 is the current, that the driver moves, and that the excitation covers its resonance (`coilscope linear` on the record shows the impedance it sees)",
            start_values(&start)
        )));
    }
    let rates = start.rates();
    let settle = settle_of(&start);
    // A record is refused for what it lacks, not for its length (a 0.5 s record at 96 kHz
    // reaching +-2 mm gives Bl and Kms within 0.1 %): after the start model has settled it
    // must hold MIN_RESONANCE_PERIODS of the resonance, where the mechanical parameters
    // show. Reach is checked by the order search (`TooSmall`), the uncertainty says the rest.
    let periods = (u.len().saturating_sub(settle)) as f64 / fs * f_res;
    if !(periods >= MIN_RESONANCE_PERIODS) {
        return Err(Input(format!(
            "{origin}: {seconds:.3} s holds {periods:.1} periods of the resonance ({f_res:.1} Hz) after the start model settles ({:.3} s); a large-signal fit needs at least {MIN_RESONANCE_PERIODS}: record at least {:.2} s (2 s or more is typical)",
            settle as f64 / fs,
            settle as f64 / fs + MIN_RESONANCE_PERIODS / f_res
        )));
    }
    let scales = Scales::of(&start);
    let has_l2r2 = start.l2r2.is_some();
    let (x0, start_miss) = started.map_err(|m| {
        let stepper = Stepper::for_fit(rates, fs).0;
        Input(format!(
            "{origin}: the start model diverged at sample {m} (small-signal start: {}, {} {} steps per sample)",
            start_values(&start),
            stepper.n(),
            stepper.scheme.name()
        ))
    })?;
    // A start that misses most of the current is no start: the large-signal fit cannot
    // recover from it, and what it ends on says nothing about the record (the first second of
    // a 3 s SB17 record, cut mid-signal: the impedance fit's model missed 99.98 % of the
    // current, and the search ended in "too small to identify anything nonlinear").
    if !(start_miss <= START_MISS) {
        return Err(Input(format!(
            "{origin}: the small-signal start ({}) misses {:.0} % of the current over this {seconds:.2} s record: the record is too short or too irregular for it; record longer (2 s or more is typical)",
            start_origin,
            100.0 * start_miss
        )));
    }
    let reach0 = x0.iter().fold(0.0f64, |a, v| a.max(v.abs())).max(1e-6);
    let x_ref = reach0;
    let x_limit = 8.0 * reach0;
    if opts.enclosure.is_some() && start.enclosure.is_none() {
        return Err(Input(format!(
            "{origin}: a fit in a box needs the box's start: the set given as the start has no enclosure"
        )));
    }
    let boxed = box_unknowns(&start, x_ref);
    let layout_for = |order: usize| {
        Layout::new(order, n_re, knot_dt, x_ref, scales.clone(), has_l2r2, opts.mms).with_box(boxed.clone())
    };

    // Order selection: increasing orders on the estimation part, warm-started.
    let n = u.len();
    let share = opts.estimation_share.clamp(0.3, 0.9);
    let search_end = search_window(&x0, fs, opts.search_seconds, share);
    let split = ((share * search_end as f64) as usize).max(settle + 1);
    let mut trials = Vec::new();
    let mut current = start.clone();
    let mut re_track: Option<Vec<f64>> = None;
    // Per order tried: (order, theta for the whole record, validation error, the estimation
    // part's Re(t) track, the stage's last Jacobian, what its Gauss-Newton model left to
    // gain: `LmState::gn_left`).
    type Kept = Option<std::sync::Arc<KeptJacobian>>;
    let mut best_by_order: Vec<(usize, Vec<f64>, f64, Vec<f64>, Kept, (f64, bool))> = Vec::new();
    // Where the next search stage starts: the last stage's Re(t) track on the estimation part
    // (`re_track` continues it over the held-out part, for the final fit), and its layout and
    // last Jacobian, which seed the next stage's first ([`OutputError::seed_first`]).
    let mut search_track: Option<Vec<f64>> = None;
    let mut prev_kept: Option<(Layout, std::sync::Arc<KeptJacobian>)> = None;
    // A given order skips the search.
    let orders: Vec<usize> = if opts.order.is_some() { vec![] } else { vec![2, 4, 6, 8] };
    let mut linear_rel = None;
    let norm_est = i[settle..split].iter().map(|v| v * v).sum::<f64>().sqrt();
    // The order-0 stage, kept to finish it when the baseline decides (see below).
    let mut order0 = None;
    if opts.order.is_none() {
        // A linear time-domain fit (order 0) on the estimation part: the baseline that the
        // nonlinear terms must improve on. At most ORDER0_FIRST_ITERATIONS here: on a record
        // whose curves are far from constant it crawls (18WU: 7 iterations of 1-5 % each,
        // gain ratios 0.7-1.5, a fifth of the whole fit), and the order-2 stage that starts
        // from it moves the same way in one step. It is finished below when its value decides
        // whether the excitation is too small.
        let lay = layout_for(0);
        let th = join(lay.theta_from(&current, None), &cth);
        let prob = OutputError::new(lay.clone(), u, i, fs, settle..split, rates, x_limit, threads)
            .with_chain(setup)
            .searching()
            .keeping_search();
        let s = solve(&prob, th, &Stage::Estimate { order: 0 }, 1e-3, ORDER0_FIRST_ITERATIONS, None, None, observe);
        cth = s.theta[lay.slots().n..].to_vec();
        linear_rel = Some((2.0 * s.cost).sqrt() / norm_est);
        current = Parameters { mms: opts.mms, ..lay.parameters(&s.theta) };
        re_track = Some(lay.re_track(&s.theta));
        search_track = re_track.clone();
        prev_kept = kept_if_converged(&prob, &s).map(|k| (lay.clone(), k));
        order0 = Some((prob, s));
    }
    // Fit a layout on the estimation part (from `from` and an Re(t) track), then score it on
    // the held-out part: (LM state, estimation error, theta for the whole record, validation
    // error, the stage's last Jacobian). `seed`: a stage whose model this one's holds, and its
    // last Jacobian, on which the first iteration starts (with this layout's new columns).
    // `follow`: the stage follows a curved valley (`solve_following`), to ALONE_TOL.
    let estimate_validate_for = |lay: &Layout,
                                 from: &Parameters,
                                 track: Option<&[f64]>,
                                 cth: &[f64],
                                 seed: Option<&(Layout, std::sync::Arc<KeptJacobian>)>,
                                 max_it: usize,
                                 follow: bool,
                                 observe: &mut dyn FnMut(&Progress)| {
        let th = join(lay.theta_from(from, track), cth);
        let prob = OutputError::new(lay.clone(), u, i, fs, settle..split, rates, x_limit, threads)
            .with_chain(setup)
            .searching()
            .keeping_search();
        if let Some((base, kept)) = seed {
            if let Some(map) = column_map(base, lay, cth.len()) {
                prob.seed_first(&th, kept, &map);
            }
        }
        // The held-out part: Re(t) knots beyond the estimation part were not identified;
        // continue the track linearly from its last identified interval.
        let t_split = split as f64 / fs;
        let sl = lay.slots();
        let held_out = |theta: &[f64]| {
            let mut th_val = theta.to_vec();
            let re_at = |t: f64| {
                let k = ((t / knot_dt).floor() as usize).min(n_re - 2);
                let w = t / knot_dt - k as f64;
                theta[sl.re.start + k] * (1.0 - w) + theta[sl.re.start + k + 1] * w
            };
            let (ra, rb) = (re_at(t_split - knot_dt), re_at(t_split));
            for k in 0..n_re {
                let tk = k as f64 * knot_dt;
                if tk > t_split - knot_dt {
                    th_val[sl.re.start + k] = rb + (rb - ra) * (tk - t_split) / knot_dt;
                }
            }
            th_val
        };
        let full =
            OutputError::new(lay.clone(), u, i, fs, split..search_end, rates, x_limit, threads).with_chain(setup);
        // The held-out score fits the coil's temperature there (the Re(t) knots whose
        // intervals reach into the held-out part; the model held): what is scored is the
        // model, not how well the estimation part's track extrapolates
        // ([`OutputError::residual_with_re_fitted`]).
        let (t_end, t_from) = (search_end as f64 / fs, t_split - knot_dt);
        let held_knots: Vec<usize> = (0..n_re)
            .filter(|&k| {
                let tk = k as f64 * knot_dt;
                tk > t_from && tk < t_end + knot_dt
            })
            .map(|k| sl.re.start + k)
            .collect();
        let validate = |th_val: &[f64]| {
            full.residual_with_re_fitted(th_val, &held_knots, HELD_OUT_RE_STEPS)
                .map(|r| rel(&r, &i[split..search_end]))
                .unwrap_or(f64::INFINITY)
        };
        // The validation run of a trial likely to end the stage runs beside the trial's own
        // residual run (on the core that run leaves idle): (trial theta, validation error).
        let early = std::sync::Mutex::new(None::<(Vec<f64>, f64)>);
        let work = |theta: &[f64]| {
            let val = validate(&held_out(theta));
            *early.lock().expect("validation") = Some((theta.to_vec(), val));
        };
        let at_last = AtLastTrial {
            likely: &|predicted, lambda| predicted < SEARCH_SETTLED_DECREASE && lambda <= SEARCH_SETTLED_LAMBDA,
            work: &work,
        };
        let s = solve_following(
            &prob,
            th,
            &Stage::Estimate { order: lay.order },
            if follow { ALONE_TOL } else { 1e-3 },
            max_it,
            Some(&at_last),
            None,
            follow,
            observe,
        );
        let est = (2.0 * s.cost).sqrt() / i[settle..split].iter().map(|v| v * v).sum::<f64>().sqrt();
        let th_val = held_out(&s.theta);
        let val = match early.into_inner().expect("validation") {
            Some((t, v)) if t == s.theta => v,
            _ => validate(&th_val),
        };
        let kept = kept_if_converged(&prob, &s);
        (s, est, th_val, val, kept)
    };
    let estimate_validate = |lay: &Layout,
                             from: &Parameters,
                             track: Option<&[f64]>,
                             cth: &[f64],
                             seed: Option<&(Layout, std::sync::Arc<KeptJacobian>)>,
                             observe: &mut dyn FnMut(&Progress)| {
        estimate_validate_for(lay, from, track, cth, seed, SEARCH_MAX_ITERATIONS, false, observe)
    };
    for &order in &orders {
        let lay = layout_for(order);
        let (s, est, th_val, val, kept) =
            estimate_validate(&lay, &current, search_track.as_deref(), &cth, prev_kept.as_ref(), observe);
        cth = th_val[lay.slots().n..].to_vec();
        trials.push(OrderTrial { order, estimation_rel: est, validation_rel: val, iterations: s.iteration });
        current = Parameters { mms: opts.mms, ..lay.parameters(&s.theta) };
        re_track = Some(lay.re_track(&th_val));
        search_track = Some(lay.re_track(&s.theta));
        prev_kept = kept.clone().map(|k| (lay.clone(), k));
        best_by_order.push((order, th_val.clone(), val, lay.re_track(&s.theta), kept, (s.gn_left, s.converged)));
        // The orders the choice below can no longer take (more than 2 % above the best so
        // far) need no Jacobian for the effects search.
        let best = best_by_order.iter().map(|b| b.2).fold(f64::INFINITY, f64::min);
        for b in best_by_order.iter_mut().filter(|b| b.2 > 1.02 * best) {
            b.4 = None;
        }
        if order == MIN_ORDER {
            // An order-0 stage stopped by its iteration cap is finished when the decision is
            // near (its error can only fall, and the gain with it).
            if let (Some(lin), Some((prob0, s0))) = (linear_rel, order0.take()) {
                if !s0.converged
                    && s0.iteration >= ORDER0_FIRST_ITERATIONS
                    && 1.0 - est / lin < ORDER0_FINISH_BELOW_GAIN
                {
                    let s = solve(&prob0, s0.theta, &Stage::Estimate { order: 0 }, 1e-3, 10, None, None, observe);
                    linear_rel = Some(lin.min((2.0 * s.cost).sqrt() / norm_est));
                }
            }
            if let Some(lin) = linear_rel {
                // The nonlinear terms must explain a real part of what the linear model misses.
                let gain = 1.0 - est / lin;
                if gain < 0.05 {
                    let (lo, hi) = x0.iter().fold((0.0f64, 0.0f64), |(a, b), v| (a.min(*v), b.max(*v)));
                    return Err(TooSmall(format!(
                        "{origin}: the excitation is too small to identify anything nonlinear: x reached only {:.3} .. {:.3} mm, and nonlinear terms improve the current error by {:.1} % (linear {:.3e}, order 2 {:.3e}); raise the level until the driver reaches a good part of its rated excursion",
                        lo * 1e3,
                        hi * 1e3,
                        100.0 * gain,
                        lin,
                        est
                    )));
                }
            }
        }
        // Stop raising the order once validation stops improving by 2 %.
        if best_by_order.len() >= 2 {
            let prev = best_by_order[best_by_order.len() - 2].2;
            if val > 0.98 * prev {
                break;
            }
        }
    }
    let order = match opts.order {
        Some(o) => o,
        None => {
            let best = best_by_order.iter().map(|b| b.2).fold(f64::INFINITY, f64::min);
            best_by_order.iter().find(|b| b.2 <= 1.02 * best).map(|b| b.0).unwrap_or(MIN_ORDER)
        }
    };
    let mut val_at_order = None;
    let at_order = best_by_order.iter().position(|b| b.0 == order);
    // The next order tried on the same data: how much the curves would move with it.
    let mut truncation = at_order.and_then(|k| {
        let next = best_by_order.get(k + 1)?;
        Some(Truncation::of(&layout_for(order), &best_by_order[k].1, &layout_for(next.0), &next.1))
    });
    // The chosen order's last Jacobian, for the effects search's first trials.
    let mut at_kept: Option<(Layout, std::sync::Arc<KeptJacobian>)> = None;
    // What the stage of the model taken so far left to gain (its `LmState::gn_left`), and
    // whether it converged.
    let (mut at_left, mut at_converged) = (f64::NAN, true);
    if let Some((_, th, val, est_track, kept, left)) = at_order.map(|k| &best_by_order[k]) {
        (at_left, at_converged) = *left;
        let lay = layout_for(order);
        current = Parameters { mms: opts.mms, ..lay.parameters(th) };
        re_track = Some(lay.re_track(th));
        search_track = Some(est_track.clone());
        cth = th[lay.slots().n..].to_vec();
        val_at_order = Some(*val);
        at_kept = kept.clone().map(|k| (lay, k));
    }
    drop(prev_kept);
    for b in best_by_order.iter_mut() {
        b.4 = None;
    }

    // The effects of real drivers (creep, LR-3, Le(i), Rms(v)): the data decide, as for the
    // order. Forward selection at the chosen order: an effect is kept when it lowers the
    // held-out current error by EFFECT_MIN_GAIN_HELD_OUT or more (and creep's lambda comes
    // out positive). Every effect not yet in is screened in every round: a dominant one masks
    // the others (with all four in the record, only LR-3 lowered the error by 5 % on its own).
    // A round fits its candidates best screen gain first and, once one has passed, skips those
    // it outscores by EFFECT_RIVAL_RATIO; the lowest held-out error of those fitted is taken.
    let mut effect_trials: Vec<(String, f64)> = Vec::new();
    let mut effect_went_on: Vec<(String, f64)> = Vec::new();
    let mut effect_screens: Vec<EffectScreen> = Vec::new();
    let effects = match opts.effects {
        EffectsChoice::Fixed(e) => e,
        EffectsChoice::Auto => {
            let base_val = match val_at_order {
                Some(v) => v,
                None => {
                    let lay = layout_for(order);
                    let (s, _, _, val, kept) =
                        estimate_validate(&lay, &current, search_track.as_deref(), &cth, None, observe);
                    search_track = Some(lay.re_track(&s.theta));
                    at_kept = kept.map(|k| (lay, k));
                    (at_left, at_converged) = (s.gn_left, s.converged);
                    val
                }
            };
            effect_trials.push((Effects::NONE.model_name(), base_val));
            let (mut at, mut at_val) = (Effects::NONE, base_val);
            // The candidates' linear start fits by their small-signal effects: a fit depends
            // on nothing else the rounds change, and each round after the first asks again
            // for those of the effects not yet in (SB17 `-real-leirv`: creep's and LR-3's
            // fits in each of its three rounds, 0.6 s a round).
            let mut lin_fits: Vec<(Effects, Option<LinearFit>)> = Vec::new();
            loop {
                let singles = [
                    Effects { creep: true, ..Effects::NONE },
                    Effects { lr3: true, ..Effects::NONE },
                    Effects { le_i: true, ..Effects::NONE },
                    Effects { rms_v: true, ..Effects::NONE },
                ];
                let cands: Vec<(Effects, Effects)> =
                    singles.iter().filter(|&&one| at.union(one) != at).map(|&one| (one, at.union(one))).collect();
                // The screen: every candidate is scored on one pass at the present estimate
                // (creep from a vanishing one, LR-3 from a vanishing branch in L3 and tau3,
                // Le(i) and Rms(v) from zero), and not fitted (nor its linear start) when it
                // could lower the estimation part's current error by less than
                // EFFECT_SCREEN_GAIN ([`screen_effects`]). Each trial was a stage of its own
                // (the 0.1 g microspeaker, which holds none of the effects: 5.7 s of its 12 s).
                let screened: Vec<Effects> = cands.iter().map(|c| c.0).collect();
                let gains = match at_kept.as_ref() {
                    Some(base) if !screened.is_empty() => {
                        let prob_for = |lay: Layout| {
                            OutputError::new(lay, u, i, fs, settle..split, rates, x_limit, threads)
                                .with_chain(setup)
                                .searching()
                        };
                        screen_effects(base, &screened, at, &current, search_track.as_deref(), &cth, &prob_for)
                    }
                    _ => vec![None; screened.len()],
                };
                let mut round: Vec<EffectScreen> = screened
                    .iter()
                    .zip(gains)
                    .filter_map(|(&one, g)| {
                        g.map(|gain| EffectScreen { model: at.union(one), added: one, gain, outscored_by: None })
                    })
                    .collect();
                let gain_in =
                    |round: &[EffectScreen], one: Effects| round.iter().find(|s| s.added == one).map(|s| s.gain);
                let mut cands: Vec<(Effects, Effects)> =
                    cands.into_iter().filter(|c| !round.iter().any(|s| s.added == c.0 && s.screened_out())).collect();
                // The highest screen gain first (a candidate the screen could not score first
                // of all: it is always fitted).
                cands.sort_by(|a, b| {
                    gain_in(&round, b.0)
                        .unwrap_or(f64::INFINITY)
                        .total_cmp(&gain_in(&round, a.0).unwrap_or(f64::INFINITY))
                });
                // (effects, validation error, what taking it takes over, its stage's
                // `gn_left` and whether it converged, its iterations).
                let mut best: Option<(Effects, f64, Taken, (f64, bool), usize)> = None;
                // The eddy-current branches and creep act at small signal too: their start
                // values come from the linear fit with the same effects on the first
                // seconds (from L2/R2 of the LR-2 fit, which absorbed the second branch,
                // LR-3 fell into a worse minimum). Le(i) and Rms(v) start from none. The
                // candidates' linear fits are independent: they run side by side (each
                // uses the cores only in part: SB17's creep and LR-3 fits took 0.63 and
                // 0.46 s in turn).
                // They start from the start fit's LR-2 model when they fit the samples it was
                // fitted on (not behind an estimated chain, whose correction moves them).
                let same = u[..m_start] == u_rec[..m_start] && i[..m_start] == i_rec[..m_start];
                let lr2 = start_lr2.as_ref().filter(|_| same);
                let needs_fit = |&(one, _): &(Effects, Effects)| one.creep || one.lr3;
                // The linear fits of the candidates that will be fitted whatever the others
                // do: those the top one cannot outscore (EFFECT_RIVAL_RATIO), side by side. A
                // later one's fit is made when its trial comes.
                let top = cands.first().and_then(|c| gain_in(&round, c.0));
                let contender = |c: &(Effects, Effects)| match (top, gain_in(&round, c.0)) {
                    (Some(t), Some(g)) => g * EFFECT_RIVAL_RATIO >= t,
                    _ => true,
                };
                let lin_fit_for = |lin_fits: &mut Vec<(Effects, Option<LinearFit>)>, wanted: &[Effects]| {
                    let missing: Vec<Effects> =
                        wanted.iter().copied().filter(|key| lin_fits.iter().all(|(k, _)| k != key)).collect();
                    let fitted = parallel_map(missing.len(), missing.len(), |k| {
                        linear_start_fit(&u[..m_start], &i[..m_start], fs, origin, missing[k], lr2)
                    });
                    lin_fits.extend(missing.into_iter().zip(fitted));
                };
                lin_fit_for(
                    &mut lin_fits,
                    &cands
                        .iter()
                        .filter(|c| needs_fit(c) && contender(c))
                        .map(|&(_, e)| e.small_signal())
                        .collect::<Vec<_>>(),
                );
                for (one, e) in cands {
                    // Outscored by the candidate that passed the held-out bar
                    // (EFFECT_RIVAL_RATIO): not fitted in this round.
                    if let Some((taken, ..)) = &best {
                        if let (Some(g), Some(gt)) =
                            (gain_in(&round, one), round.iter().find(|s| s.model == *taken).map(|s| s.gain))
                        {
                            if g * EFFECT_RIVAL_RATIO < gt {
                                if let Some(s) = round.iter_mut().find(|s| s.added == one) {
                                    s.outscored_by = Some(*taken);
                                }
                                continue;
                            }
                        }
                    }
                    let lin = if needs_fit(&(one, e)) {
                        lin_fit_for(&mut lin_fits, &[e.small_signal()]);
                        lin_fits.iter().find(|(k, _)| *k == e.small_signal()).and_then(|(_, f)| f.as_ref())
                    } else {
                        None
                    };
                    let mut lay = layout_for(order).with_effects(e);
                    let mut from = current.clone();
                    if let Some(lin) = lin {
                        if e.lr3 {
                            from.l2r2 = Some((Poly::constant(lin.p[2]), Poly::constant(lin.p[3])));
                            from.l3r3 = lin.lr3.map(|(v, _)| (v[0], v[1]));
                        }
                        if e.creep && current.creep.is_none() {
                            from.creep = lin
                                .creep
                                .filter(|c| c.0 > 0.0)
                                .map(|(lambda, _)| coilscope_core::params::Creep { lambda, f_ref: None });
                        }
                    }
                    // A second start for LR-3 and creep: the present estimate with a vanishing
                    // branch (LR3_VANISHING of the typical one) or creep (CREEP_VANISHING).
                    // On a record without a second branch the linear fit's start missed 8 % of
                    // the current against the present estimate's 0.04 %, and the stage crawled
                    // 10 iterations back (a third of the effects search). The start that misses
                    // less on the estimation part is taken.
                    let vanishing = if one.lr3 {
                        let (l2, r2) = current.l2r2.as_ref().map_or((0.0, 0.0), |(l, r)| (l.eval(0.0), r.eval(0.0)));
                        (l2 > 0.0).then(|| Parameters {
                            l3r3: Some((LR3_VANISHING * 0.5 * l2, LR3_VANISHING * 3.0 * r2)),
                            ..current.clone()
                        })
                    } else if one.creep && current.creep.is_none() {
                        Some(Parameters {
                            creep: Some(coilscope_core::params::Creep { lambda: CREEP_VANISHING, f_ref: None }),
                            ..current.clone()
                        })
                    } else {
                        None
                    };
                    // A trial from the present estimate (Le(i) and Rms(v) at zero, a vanishing
                    // branch or creep) starts on the chosen stage's last Jacobian.
                    let mut nested = !(one.creep || one.lr3);
                    if let Some(vanishing) = vanishing {
                        let prob = OutputError::new(lay.clone(), u, i, fs, settle..split, rates, x_limit, threads)
                            .with_chain(setup)
                            .searching();
                        let miss = |p: &Parameters| {
                            prob.residual(&join(lay.theta_from(p, search_track.as_deref()), &cth)).norm_squared()
                        };
                        // The two runs side by side (each takes one core).
                        let (a, b) = std::thread::scope(|scope| {
                            let h = scope.spawn(|| miss(&vanishing));
                            let b = miss(&from);
                            (h.join().expect("a model run does not panic"), b)
                        });
                        if a < b {
                            from = vanishing;
                            nested = true;
                            // A vanishing branch grows or shrinks in L3 at its corner
                            // (Slots::r3); the fits after this trial go on in L3 and R3.
                            if one.lr3 {
                                lay = lay.with_lr3_tau();
                            }
                        }
                    }
                    let seed = at_kept.as_ref().filter(|_| nested);
                    let max_it = if lay.lr3_tau { LR3_TAU_ITERATIONS } else { SEARCH_MAX_ITERATIONS };
                    let (mut s, _, mut th_val, mut val, mut kept) =
                        estimate_validate_for(&lay, &from, search_track.as_deref(), &cth, seed, max_it, false, observe);
                    // A branch the record holds: the trial goes on in L3 and R3 (Slots::r3).
                    if lay.lr3_tau && !s.converged {
                        let n = lay.slots().n;
                        let (p, track) =
                            (Parameters { mms: opts.mms, ..lay.parameters(&s.theta) }, lay.re_track(&s.theta));
                        lay.lr3_tau = false;
                        let done = s.iteration;
                        (s, _, th_val, val, kept) = estimate_validate_for(
                            &lay,
                            &p,
                            Some(&track),
                            &s.theta[n..],
                            None,
                            SEARCH_MAX_ITERATIONS - done,
                            false,
                            observe,
                        );
                        s.iteration += done;
                    }
                    effect_trials.push((e.model_name(), val));
                    let lambda_ok = lay.slots().lambda.is_none_or(|k| s.theta[k] > 0.0);
                    if lambda_ok
                        && val < (1.0 - EFFECT_MIN_GAIN_HELD_OUT) * at_val
                        && best.as_ref().is_none_or(|b| val < b.1)
                    {
                        best = Some((
                            e,
                            val,
                            Taken::of(lay, opts.mms, &s.theta, &th_val, kept),
                            (s.gn_left, s.converged),
                            s.iteration,
                        ));
                    }
                }
                // A trial goes on from where the model taken so far stopped, so its held-out
                // gain holds what that model's own stage left to gain. When the best trial's
                // gain is within that (and the bar) of the base, or the base's stage did not
                // converge, the base goes on alone (in the second case for as many
                // iterations as the trial took), and the trial must beat it again
                // ([`held_out_gain_is_within_reach`]); if it does not, the base as it got
                // there is taken and the search ends.
                if let Some(b) = &best {
                    if let Some(budget) = base_goes_on_alone(b.1, b.4, at_val, at_left, at_converged) {
                        let lay =
                            at_kept.as_ref().map_or_else(|| layout_for(order).with_effects(at), |(l, _)| l.clone());
                        let (s, _, th_val, val, kept) = estimate_validate_for(
                            &lay,
                            &current,
                            search_track.as_deref(),
                            &cth,
                            at_kept.as_ref(),
                            budget,
                            true,
                            observe,
                        );
                        if !(b.1 < (1.0 - EFFECT_MIN_GAIN_HELD_OUT) * val) {
                            if let Some(t) = effect_trials.iter_mut().rev().find(|t| t.0 == at.model_name()) {
                                effect_went_on.push((t.0.clone(), t.1));
                                t.1 = val;
                            }
                            Taken { current, re_track, search_track, cth, at_kept } =
                                Taken::of(lay, opts.mms, &s.theta, &th_val, kept);
                            best = None;
                        }
                    }
                }
                effect_screens.extend(round);
                match best {
                    Some((e, val, taken, left, _)) => {
                        (at, at_val) = (e, val);
                        (at_left, at_converged) = left;
                        Taken { current, re_track, search_track, cth, at_kept } = taken;
                    }
                    None => break at,
                }
            }
        }
    };
    // A missing effect can hide what a higher order would explain (SB17 with LR-3 stopped at
    // order 2): with effects chosen, raise the order again while it lowers the held-out
    // error by 2 %.
    let mut order = order;
    if opts.order.is_none() && effects != Effects::NONE {
        // The chosen effects fitted on from where their trial stopped (on its last Jacobian),
        // at the chosen order, then one order higher at a time. A trial is a search stage that
        // may stop before it converges, and the orders above compare with this fit. Taking
        // the trial's own validation error instead, 18WU `-real-all` compared order 8 with
        // 1.77e-3 where the fit gets 1.61e-3, and kept order 6. Given effects: fitted here,
        // from the order's stage without them. Each stage taken starts the next (started
        // instead from the trial's parameters with this fit's Re(t) track, where the fit
        // moved on far, 18WU `-real-all`'s order-6 stage started 70x above it).
        // The pair without the effects no longer applies: the search below makes its own (none
        // at the highest order, as above).
        truncation = None;
        let (mut cur_th, mut cur) = (Vec::new(), f64::INFINITY);
        let mut next = order;
        while next <= MAX_ORDER {
            let lay = layout_for(next).with_effects(effects);
            let (s, est, th_val, val, kept) =
                estimate_validate(&lay, &current, search_track.as_deref(), &cth, at_kept.as_ref(), observe);
            if next > order {
                trials.push(OrderTrial { order: next, estimation_rel: est, validation_rel: val, iterations: 0 });
                if !(val < 0.98 * cur) {
                    truncation = Some(Truncation::of(&layout_for(order).with_effects(effects), &cur_th, &lay, &th_val));
                    break;
                }
            }
            (order, cur) = (next, val);
            Taken { current, re_track, search_track, cth, at_kept } = Taken::of(lay, opts.mms, &s.theta, &th_val, kept);
            cur_th = th_val;
            next += 2;
        }
    }
    drop(at_kept);

    // The final fit's chain. Behind an AC coupling the voltage channel's offset is free (see
    // ChainSetup), starting at the held value. The whitening follows the search's current
    // corner: the linear start gave 0 behind 1.5-4.7 Hz couplings, and unwhitened, the
    // sensor noise's random walk behind the inverted coupling pulled the current's offset
    // 1.1 % off at 32 sd (PTT4 through every effect of a card).
    let final_setup;
    let setup = match setup {
        Some(c) => {
            let [_, fu, fi] = c.values(&cth);
            let whiten_hz = fi.clamp(0.0, 10.0);
            let free = c.dc_u_free || fu > DC_COUPLED_HZ;
            if free != c.dc_u_free || (whiten_hz - c.whiten_hz).abs() > 0.1 * whiten_hz.max(c.whiten_hz) {
                if free && !c.dc_u_free {
                    cth.insert(c.terms.count(), c.voltage(&cth).1 / c.u_unit);
                }
                final_setup = ChainSetup { dc_u_free: free, whiten_hz, ..c.clone() };
                Some(&final_setup)
            } else {
                Some(c)
            }
        }
        None => None,
    };

    // Final fit on the whole record.
    let lay = layout_for(order).with_effects(effects);
    let th = join(lay.theta_from(&current, re_track.as_deref()), &cth);
    // A start whose Re(t) track already bends as the heating test asks (below) computes the
    // heating terms' columns with its Jacobians (OutputError::with_spare_heat): the fit with
    // them then starts on its last Jacobian. The woofers' tracks bend by 1-3e-5, the
    // microspeakers' by 1.5e-2 and 6.5e-2.
    let heat_likely = track_bend(&lay.re_track(&th)) > KNOT_BEND;
    let prob =
        OutputError::new(lay.clone(), u, i, fs, settle..n, rates, x_limit, threads).with_chain(setup).keeping_last();
    let prob = if heat_likely { prob.with_spare_heat() } else { prob };
    // Heating faster than the knots can follow (see HEAT_TAUS): the knots bend by more than
    // KNOT_BEND between neighbours and the residual is above its floor. Then the heating
    // terms join Re(t), kept when they lower the residual by HEAT_MIN_GAIN. The test is made
    // as soon as the fit is within EARLY_TEST_BELOW of its end: when the heating terms are
    // kept, the rest of this fit was work for nothing (the microspeaker: a 3.9 s Jacobian);
    // when not, it is resumed.
    let wants_heat = |r: &DVector<f64>, th: &[f64]| {
        let bend = track_bend(&lay.re_track(th));
        let excess = crate::checks::noise_floor(r.as_slice(), fs).ratio;
        (bend > KNOT_BEND && excess > HEAT_TRY_RATIO, excess)
    };
    // The test of the state the fit stopped at, when it said yes.
    let stopped_early = std::cell::Cell::new(None);
    let early = |s: &LmState| {
        let test = wants_heat(&prob.residual(&s.theta), &s.theta);
        if test.0 {
            stopped_early.set(Some(test));
        }
        test.0
    };
    // With heating likely, the test is first made on the first Jacobian, on the state and
    // residual its first step predicts (the linearised model, which the microspeakers'
    // first steps follow at gain ratio 1.000): when it says yes, that step's residual run
    // (the microspeaker's 0.22 s) is saved, and the fit with the heating terms starts where
    // it would have (on that Jacobian, `OutputError::extending`); when it says no, the fit
    // goes on from it as before, with the test above.
    let at_start = heat_likely.then(|| {
        prob.residual_ahead(&th, &|_| true, None);
        let start = LmState::new(&prob, th.clone());
        let (r0, j0) = prob.residual_jacobian(&th);
        let test = damped_from(&crate::lm::gram(&j0), &j0.tr_mul(&r0), &th, start.lambda).map(|(th1, _)| {
            let step = DVector::from_iterator(th.len(), th1.iter().zip(&th).map(|(a, b)| a - b));
            wants_heat(&(&r0 + &j0 * step), &th1)
        });
        // The Jacobian back where the fit's first iteration takes it.
        let spare = prob.last_jacobian_at.lock().expect("jacobian cache").as_ref().and_then(|at| at.spare.clone());
        *prob.ahead.lock().expect("jacobian ahead") = Some((th.clone(), j0, spare));
        (start, test)
    });
    let s = match at_start {
        Some((start, Some(test))) if test.0 => {
            observe(&Progress {
                stage: Stage::Final { order },
                state: &start,
                residual_rel: rel(&prob.residual(&start.theta), &i[settle..n]),
            });
            stopped_early.set(Some(test));
            start
        }
        _ => solve(&prob, th, &Stage::Final { order }, 1e-4, opts.max_iterations, None, Some(&early), observe),
    };
    let r = prob.residual(&s.theta);
    let residual_rel = rel(&r, &i[settle..n]);
    let (try_heat, excess) = stopped_early.get().unwrap_or_else(|| wants_heat(&r, &s.theta));
    let (lay, prob, s, r, residual_rel, excess) = {
        let heated = try_heat.then(|| {
            let lay_h = lay.clone().with_heat(&HEAT_TAUS);
            let prob_h = OutputError::new(lay_h.clone(), u, i, fs, settle..n, rates, x_limit, threads)
                .with_chain(setup)
                .keeping_last();
            // Where the fit's last Jacobian was computed, on it and its spare heating
            // columns (OutputError::extending); else where the fit stopped.
            let th = prob_h.extending(&prob).unwrap_or_else(|| heat_at_zero(&s.theta, lay.slots().n, lay_h.slots().n));
            let s_h = solve(&prob_h, th, &Stage::Final { order }, 1e-4, opts.max_iterations, None, None, observe);
            let r_h = prob_h.residual(&s_h.theta);
            let rel_h = rel(&r_h, &i[settle..n]);
            (rel_h < (1.0 - HEAT_MIN_GAIN) * residual_rel).then(|| {
                let excess_h = crate::checks::noise_floor(r_h.as_slice(), fs).ratio;
                (lay_h, prob_h, s_h, r_h, rel_h, excess_h)
            })
        });
        match heated.flatten() {
            Some(h) => h,
            None if stopped_early.get().is_some() => {
                let s = solve(&prob, s.theta, &Stage::Final { order }, 1e-4, opts.max_iterations, None, None, observe);
                let r = prob.residual(&s.theta);
                let residual_rel = rel(&r, &i[settle..n]);
                let excess = crate::checks::noise_floor(r.as_slice(), fs).ratio;
                (lay, prob, s, r, residual_rel, excess)
            }
            None => (lay, prob, s, r, residual_rel, excess),
        }
    };
    let (x_model, i_model) =
        prob.trace(&s.theta, n).map_err(|m| Input(format!("{origin}: the fitted model diverged at sample {m}")))?;
    // Covariance from the Jacobian of LM's last iteration (the accepted step after it is
    // below the convergence tolerance) and the final residual: the cluster-robust sandwich
    // over blocks of COVARIANCE_BLOCK_S, which holds when the residual is coloured (the
    // classical sigma^2 (J^T J)^-1 takes it as white), then widened by the residual's excess
    // over its noise floor (see MODEL_ERROR_RATIO).
    let jac = prob.last_jacobian.lock().expect("jacobian cache").take();
    let cov = match &jac {
        Some(j) if r.len() > j.ncols() => {
            crate::lm::sandwich_covariance(j, &r, ((COVARIANCE_BLOCK_S * fs) as usize).max(1))
        }
        _ => crate::lm::covariance(&prob, &s.theta),
    };
    let cov = cov.map(|c| if excess > MODEL_ERROR_RATIO { c * (excess * excess) } else { c });
    // The drive's own mean, which dc_u's convention takes as 0 (ChainSetup::voltage): on a
    // DC-coupled voltage channel the curves shift with it, and nothing in the record can
    // say by how much (through DC-coupled cards of the harsh world the truth was 5-23 sd
    // outside bands that left it out).
    let dc_u_sd = setup.filter(|c| !c.dc_u_free).map(|c| c.dc_u_sd(&s.theta[lay.slots().n..]));
    let cov = match (cov, setup, dc_u_sd, &jac) {
        (Some(cv), Some(c), Some(sd), Some(j)) => match prob.dc_u_column(&s.theta, c) {
            Some(col) => Some(with_nuisance(cv, j, &col, sd)),
            None => Some(cv),
        },
        (cv, ..) => cv,
    };
    let cov = match (cov, setup) {
        (Some(c), Some(ch)) if ch.terms.delay => Some(with_systematic(c, lay.slots().n, DELAY_SYSTEMATIC_SAMPLES)),
        (c, _) => c,
    };
    let x_range = x_model.iter().fold([0.0f64, 0.0f64], |[a, b], v| [a.min(*v), b.max(*v)]);
    // The two branches in their canonical order (LR-2 the larger), with their covariance.
    let mut s = s;
    let cov = match branch_swap(&lay, &s.theta) {
        Some(pairs) => {
            for &(a, b) in &pairs {
                s.theta.swap(a, b);
            }
            cov.map(|mut c| {
                for &(a, b) in &pairs {
                    c.swap_rows(a, b);
                    c.swap_columns(a, b);
                }
                c
            })
        }
        None => cov,
    };
    let mut params = lay.parameters(&s.theta);
    params.x_range = Some(x_range);
    let stop_reason = if s.converged {
        format!("converged: cost decrease below 1e-4 after {} iterations", s.iteration)
    } else if s.iteration >= opts.max_iterations {
        format!(
            "stopped at the iteration limit ({}), last relative cost decrease {:.2e}",
            opts.max_iterations, s.last_decrease
        )
    } else {
        "no step lowered the cost any further".to_string()
    };
    let converged = s.converged || s.last_decrease == 0.0;
    let re_track = prob.re_track(&s.theta);
    let chain = setup.map(|c| chain_of(c, &s.theta, lay.slots().n, cov.as_ref(), dc_u_sd.unwrap_or(0.0)));
    let (u_phys, i_phys) = {
        let (a, b) = prob.signals(&s.theta);
        (a.into_owned(), b.into_owned())
    };
    let fit = LargeFit {
        params,
        layout: lay,
        theta: s.theta.clone(),
        cov,
        residual_rel,
        x_range,
        order,
        trials,
        effect_trials,
        effect_went_on,
        effect_screens,
        iterations: s.iteration,
        converged,
        stop_reason: stop_reason.clone(),
        re_track,
        substeps: prob.substeps(),
        schemes: prob.schemes(),
        settle,
        fs,
        linear,
        i_model,
        x_model,
        chain,
        chain_detected,
        u_phys,
        i_phys,
        truncation,
    };
    if !converged {
        return Err(NotConverged {
            message: format!(
                "{origin}: the large-signal fit did not converge ({stop_reason}); the best estimate is kept"
            ),
            best: Box::new(fit),
        });
    }
    Ok(fit)
}

/// Coherence an impedance bin of the start fit needs for the joint small-signal fit of the
/// driver and its box.
pub const BOX_START_COHERENCE: f64 = 0.97;

/// Points, log-spaced, of the joint small-signal fit of a driver and its box, and the
/// highest frequency (Hz) they reach: a box and the driver's mechanics show below it, and
/// the coil's inductance is the large-signal fit's to find.
pub const BOX_START_POINTS: usize = 200;
pub const BOX_START_TOP_HZ: f64 = 3000.0;

/// Share of the start fit's error power that the linear fit with the chain must remove for
/// `IdentifyOptions::detect_chain` to take the chain.
pub const CHAIN_SEEN_GAIN: f64 = 0.02;

/// What a linear fit's chain estimate kept (each at [`crate::linear::CHAIN_SIGNIFICANCE`] sd
/// or more) in the ranges a sound card has, in words.
pub(super) fn chain_seen(c: &crate::linear::ChainEstimate) -> Vec<String> {
    let mut seen = vec![];
    let corner = |f: f64| (0.2..=20.0).contains(&f);
    if c.on[0] && c.values[0].abs() >= 0.05 {
        seen.push(format!("the current {:+.3} +- {:.3} samples late against the voltage", c.values[0], c.sd[0]));
    }
    if c.on[1] && corner(c.values[1]) {
        seen.push(format!("the voltage channel AC-coupled at {:.2} +- {:.2} Hz", c.values[1], c.sd[1]));
    }
    if c.on[2] && corner(c.values[2]) {
        seen.push(format!("the current channel AC-coupled at {:.2} +- {:.2} Hz", c.values[2], c.sd[2]));
    }
    seen
}

/// The LR-2 and LR-3 branches are the same form in series, and the model is the same with
/// the two exchanged: a fit may end with either one in either place. The result names them
/// in one order, LR-2 the branch with the larger inductance (`L2 >= L3`), as the test worlds
/// and the shared `-real-all` records have them (L3 = L2 / 2 and 0.6 L2). Returns the slot
/// pairs `(L2, L3)` and `(R2, R3)` to exchange when `th` has them the other way (both slots
/// of a pair in the same units: [`Layout::lr3_of`] outside tau3 coordinates). SB17 with a
/// branch of L2 / 2 at twice tau2 came out as L2 0.2706 mH, R2 0.0726 ohm, L3 0.5397 mH, R3
/// 0.2899 ohm: the truth's branches, exchanged.
pub(super) fn branch_swap(lay: &Layout, th: &[f64]) -> Option<[(usize, usize); 2]> {
    let sl = lay.slots();
    let (l2, r2, l3, r3) = (sl.l2?, sl.r2?, sl.l3?, sl.r3?);
    (!lay.lr3_tau && th[l3] > th[l2]).then_some([(l2, l3), (r2, r3)])
}

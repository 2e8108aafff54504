//! The fit over the bins: the model candidates (creep, LR-3) grown and chosen on the data,
//! and the covariance of the result.

use super::*;

/// The noise floor of the bins of `prob` at `theta`, relative as its residual: a record's
/// from the spectrum of its error ([`CurrentError::residual_and_floor`]), an impedance
/// curve's (`fs` none) from the roughness of its residual ([`CurrentError::roughness_floor`]).
fn noise_floor(prob: &CurrentError, theta: &[f64], fs: Option<f64>) -> f64 {
    if fs.is_some() {
        prob.residual_and_floor(theta).1
    } else {
        prob.roughness_floor(theta)
    }
}

/// The fit proper, on the bins of `prob` (their `u`, `i` and weights set, `norm` too), from
/// the start `p0` found on `h1` in `band`; `fs` is the record's rate (none for an impedance
/// curve: no chain, no skew check); `lr2`: the LR-2 model's fit on these bins, taken instead
/// of fitting it ([`fit_linear_record_from`]).
#[allow(clippy::too_many_arguments)]
pub(super) fn fit_bins(
    prob: CurrentError,
    h1: ImpedanceEstimate,
    band: [f64; 2],
    p0: [f64; 7],
    opts: &LinearOptions,
    fs: Option<f64>,
    lr2: Option<&Lr2Fit>,
    origin: &str,
    observe: &mut dyn FnMut(&LmState),
) -> Result<LinearFit, String> {
    let map = prob.map.clone();
    let n_chain = prob.chain.map_or(0, |c| c.count());
    // LM to convergence, or to a plateau: the cost lowered by less than PLATEAU_REL over
    // the last PLATEAU_ITERATIONS iterations. An effect the record does not have leaves a
    // flat direction along which LM creeps for ever (LR-3 on 18WU's small stage: 200
    // iterations, 4 s on 40 000 bins, the cost the same to 1e-9).
    let run = |p: &CurrentError, theta: Vec<f64>, max_iter: usize, observe: &mut dyn FnMut(&LmState)| {
        let mut s = LmState::new(p, theta);
        observe(&s);
        let mut costs = std::collections::VecDeque::from([s.cost]);
        while !s.converged && s.iteration < max_iter {
            s = lm_step(p, &s);
            // The damping after an accepted step follows how well the model predicted it
            // (`lambda_after_gain`).
            if s.last_decrease > 0.0 && s.gain_ratio.is_finite() {
                s.lambda = lambda_after_gain(s.step_lambda, s.gain_ratio);
            }
            observe(&s);
            costs.push_back(s.cost);
            if costs.len() > PLATEAU_ITERATIONS {
                let old = costs.pop_front().expect("not empty");
                if old - s.cost <= PLATEAU_REL * s.cost {
                    s.converged = true;
                }
            }
        }
        s
    };
    let better =
        |s: &LmState, b: &LmState| (s.converged && !b.converged) || (s.converged == b.converged && s.cost < b.cost);
    // Fit one model (the LR-2 quantities plus `effects`) from several starts: each start is
    // scouted on every k-th bin (at most SCOUT_BINS), the best is polished on all of them,
    // so the answer is the full-data optimum at a fraction of the cost.
    // A candidate whose scout residual is not below `gate` is not polished (it cannot win:
    // the effect does not gain its share of the excess on the scout bins). Returns
    // the problem, the state, the scout's residual and whether it was polished.
    // The problem of a model with `effects` on these bins.
    let with_effects = |effects: Effects| {
        let mut pr = CurrentError {
            f: prob.f.clone(),
            u: prob.u.clone(),
            i: prob.i.clone(),
            w: prob.w.clone(),
            map: prob.map.clone(),
            effects,
            chain: prob.chain,
            ..prob
        };
        pr.norm = prob.norm;
        pr
    };
    // `min_ln_le`: a start whose run ends with ln Le below it traded the voice coil's
    // inductance for an added branch ([`LE_COLLAPSE`]): it is taken only if every start did.
    let solve = |effects: Effects,
                 starts: &[Vec<f64>],
                 gate: f64,
                 min_ln_le: f64,
                 observe: &mut dyn FnMut(&LmState)|
     -> (CurrentError, LmState, f64, bool) {
        let pr = with_effects(effects);
        let scout = (pr.f.len() > 2 * SCOUT_BINS).then(|| thin(&pr, SCOUT_BINS));
        let scout_iterations =
            if gate.is_finite() && scout.is_some() { CANDIDATE_SCOUT_ITERATIONS } else { MAX_ITERATIONS };
        // The starts are independent: they run on all cores, each keeping its LM states,
        // which the observer then sees start by start, as if they had run in turn.
        let on = scout.as_ref().unwrap_or(&pr);
        let runs: Vec<(LmState, Vec<LmState>)> = std::thread::scope(|scope| {
            let handles: Vec<_> = starts
                .iter()
                .map(|th| {
                    scope.spawn(move || {
                        let mut seen = vec![];
                        let s = run(on, th.clone(), scout_iterations, &mut |st: &LmState| seen.push(st.clone()));
                        (s, seen)
                    })
                })
                .collect();
            handles.into_iter().map(|h| h.join().expect("an LM run does not panic")).collect()
        });
        let mut best: Option<LmState> = None;
        let kept = |s: &LmState| s.theta[1] >= min_ln_le;
        for (s, seen) in runs {
            seen.iter().for_each(&mut *observe);
            let replace = match best.as_ref() {
                None => true,
                Some(b) => (kept(&s) && !kept(b)) || (kept(&s) == kept(b) && better(&s, b)),
            };
            if replace {
                best = Some(s);
            }
        }
        let mut s = best.expect("at least one start");
        let scout_rel = scout.as_ref().unwrap_or(&pr).residual_rel(&s.theta);
        let polish = scout.is_some() && scout_rel < gate;
        if polish {
            s = run(&pr, s.theta.clone(), MAX_ITERATIONS, observe);
        }
        (pr, s, scout_rel, polish || scout.is_none())
    };
    // The LR-2 branch trades off against Re and Le: start from the heuristic guess and from
    // corners spread over the band, and keep the lowest cost among the converged runs (each
    // start is a full LM run, observed like any other).
    let q0 = ParamMap::q_of(&p0);
    // ln tau of corners at a quarter, a half and three quarters of the band (log scale): the
    // branches' starts spread over it.
    let spread_ln_tau =
        [0.25, 0.5, 0.75].map(|frac: f64| (1.0 / (2.0 * PI * (band[0] * (band[1] / band[0]).powf(frac)))).ln());
    let mut starts = vec![q0];
    for ln_tau in spread_ln_tau {
        for r2f in [0.25, 1.0, 4.0] {
            let mut q = q0;
            q[2] = ln_tau;
            q[3] += f64::ln(r2f);
            starts.push(q);
        }
    }
    let n_t = prob.n_transient;
    let base_starts: Vec<Vec<f64>> = starts
        .iter()
        .map(|q| {
            let mut th = map.theta(q);
            th.resize(7 + n_t + n_chain, 0.0);
            th
        })
        .collect();
    // Each fitted model with its current residual (on all bins; a candidate left unpolished
    // keeps its scout's, and cannot be chosen), and its scout residual.
    let (mut scout_r, mut polished): (Vec<f64>, Vec<bool>) = (vec![], vec![]);
    pub(super) fn with_residual(
        scout_r: &mut Vec<f64>,
        polished: &mut Vec<bool>,
        (pr, s, sr, done): (CurrentError, LmState, f64, bool),
    ) -> (CurrentError, LmState, f64) {
        let r = if done { pr.residual_rel(&s.theta) } else { sr };
        scout_r.push(sr);
        polished.push(done);
        (pr, s, r)
    }
    let base = match lr2 {
        Some(b) => (with_effects(Effects::NONE), b.state.clone(), b.scout_rel, b.polished),
        None => solve(Effects::NONE, &base_starts, f64::INFINITY, f64::NEG_INFINITY, observe),
    };
    let lr2 = Lr2Fit { state: base.1.clone(), scout_rel: base.2, polished: base.3 };
    // theta[1] is ln Le (unbounded); below this a model with more effects took Le's place
    // ([`LE_COLLAPSE`]).
    let min_ln_le = base.1.theta[1] + LE_COLLAPSE.ln();
    let mut fitted = vec![with_residual(&mut scout_r, &mut polished, base)];
    // Starts of a model with more effects, from a fitted one: creep from lambda = 0.05 (the
    // middle of what Klippel's LPM reports), LR-3 from a corner 4x above and 4x below LR-2's
    // with R3 = 2.5 R2 and R2 (the branches are named by their corners afterwards).
    let grow = |from: &(CurrentError, LmState, f64), to: Effects| -> Vec<Vec<f64>> {
        let (pr, s, _) = from;
        let (th0, ext0) = (&s.theta, pr.ext(&s.theta));
        let base = &th0[..7];
        let trans = th0[pr.t0()..].to_vec();
        let lambda = ext0.creep.map_or(0.05, |c| c.lambda);
        let lr3s: Vec<(f64, f64)> = match (to.lr3, ext0.lr3) {
            (false, _) => vec![],
            (true, Some((l3, r3))) => vec![((l3 / r3).ln(), r3.ln())],
            (true, None) => {
                let q = map.q(base);
                let r2 = q[3];
                // And corners spread over the band, as LR-2's starts are: a second branch
                // far from where the LR-2 model put its one is reached from none of the two
                // beside it (a microspeaker with its branches at 7 and 17 kHz: LR-3's fit
                // stayed above LR-2's error from both).
                let mut v = vec![(q[2] - 4f64.ln(), r2 + 2.5f64.ln()), (q[2] + 4f64.ln(), r2)];
                v.extend(spread_ln_tau.map(|ln_tau| (ln_tau, r2)));
                // And at the band's top: a small coil's branches sit high (a microspeaker's at
                // 3.2 and 9.8 kHz on a band to 20 kHz; from the starts below, its fit made one
                // branch a 0.08 ohm resistor at 3 Hz beside Re, which came out 0.8 % low, and
                // Le took the other, 37 % high).
                v.push(((1.0 / (2.0 * PI * band[1])).ln(), r2));
                v
            }
        };
        let mut out = vec![];
        for &(ltau3, lr3) in if lr3s.is_empty() { &[(0.0, 0.0)][..] } else { &lr3s[..] } {
            let mut th = base.to_vec();
            if to.creep {
                th.push(lambda);
            }
            if to.lr3 {
                th.push(bounded_theta(ltau3, map.lo[2], map.hi[2], 0.01));
                th.push(lr3);
            }
            th.extend_from_slice(&trans);
            out.push(th);
        }
        out
    };
    let chosen = match opts.effects {
        EffectsChoice::Fixed(e) if e == Effects::NONE => 0,
        EffectsChoice::Fixed(e) => {
            let st = grow(&fitted[0], e);
            fitted.push(with_residual(&mut scout_r, &mut polished, solve(e, &st, f64::INFINITY, min_ln_le, observe)));
            1
        }
        EffectsChoice::Auto => {
            // Forward selection: add the effect that lowers the residual most, while one pays
            // ([`effect_pays`]: a share of the excess over the noise floor, well above what
            // noise gives) and creep's lambda is physical. The floor of a record is the
            // lowest any fitted model shows (a model's misfit can only raise it); an averaged
            // curve has none.
            let floor_of = |f: &(CurrentError, LmState, f64)| noise_floor(&f.0, &f.1.theta, fs);
            let mut floor = floor_of(&fitted[0]);
            let bins = prob.f.len();
            let mut at = 0;
            loop {
                let cur = fitted[at].0.effects;
                let mut cands = vec![];
                if !cur.creep {
                    cands.push(Effects { creep: true, ..cur });
                }
                if !cur.lr3 {
                    cands.push(Effects { lr3: true, ..cur });
                }
                // A candidate is polished on every bin when its scout gains the share of the
                // excess (the relative floor is the same on the scout's thinned bins).
                let r_cur = fitted[at].2;
                let gate =
                    (scout_r[at].powi(2) - EFFECT_MIN_SHARE * (scout_r[at].powi(2) - floor * floor).max(0.0)).sqrt();
                let first = fitted.len();
                for e in cands {
                    let st = grow(&fitted[at], e);
                    let f = with_residual(&mut scout_r, &mut polished, solve(e, &st, gate, min_ln_le, observe));
                    if polished[fitted.len()] {
                        floor = floor.min(floor_of(&f));
                    }
                    fitted.push(f);
                }
                let mut best: Option<(usize, f64)> = None;
                for k in first..fitted.len() {
                    let (pr, s, r) = &fitted[k];
                    let lambda_ok = pr.idx_lambda().is_none_or(|j| s.theta[j] > 0.0);
                    let unknowns = n_extra(pr.effects) - n_extra(cur);
                    if polished[k]
                        && lambda_ok
                        && s.theta[1] >= min_ln_le
                        && effect_pays(r_cur, *r, floor, bins, unknowns)
                        && best.is_none_or(|(_, rb)| *r < rb)
                    {
                        best = Some((k, *r));
                    }
                }
                match best {
                    Some((k, _)) => at = k,
                    None => break at,
                }
            }
        }
    };
    let tried: Vec<(String, f64)> = fitted.iter().map(|(pr, _, r)| (pr.effects.model_name(), *r)).collect();
    // Models with more effects than the chosen one that the data do not tell from it (on
    // the scout's bins, where every candidate has a residual; the relative floor is the
    // same there): the spread of their parameters is the model choice's uncertainty.
    let model_rel = {
        let ce = fitted[chosen].0.effects;
        let qc = map.q(&fitted[chosen].1.theta[..7]);
        let scout_bins = SCOUT_BINS.min(prob.f.len());
        let floor = noise_floor(&fitted[chosen].0, &fitted[chosen].1.theta, fs);
        let alike: Vec<[f64; 7]> = (0..fitted.len())
            .filter(|&k| k != chosen && fitted[k].0.effects.union(ce) == fitted[k].0.effects)
            .filter(|&k| {
                !effect_pays(scout_r[k], scout_r[chosen], floor, scout_bins, n_extra(fitted[k].0.effects) - n_extra(ce))
            })
            .map(|k| map.q(&fitted[k].1.theta[..7]))
            .collect();
        model_spread(&qc, &alike)
    };
    let le_model_rel = model_rel[1];
    let (mut prob, mut s, _) = fitted.swap_remove(chosen);
    // Name the branches by their corners: LR-2 is the lower one.
    if let Some(k3) = prob.idx_lr3() {
        let q = map.q(&s.theta[..7]);
        let (ltau3, _) = prob.tau3(s.theta[k3]);
        if ltau3 > q[2] {
            let (ltau2, lr2, lr3) = (q[2], q[3], s.theta[k3 + 1]);
            let mut qn = q;
            qn[2] = ltau3;
            qn[3] = lr3;
            let th = map.theta(&qn);
            s.theta[2] = th[2];
            s.theta[3] = th[3];
            s.theta[k3] = bounded_theta(ltau2, map.lo[2], map.hi[2], 1e-9);
            s.theta[k3 + 1] = lr2;
        }
    }
    let free_of = |prob: &CurrentError, th: &[f64]| -> Vec<usize> {
        let inside = |t: f64| (1e-3..=1.0 - 1e-3).contains(&logistic(t));
        (0..th.len())
            .filter(|&k| (k >= 7 && Some(k) != prob.idx_lr3()) || (k < 7 && !map.lo[k].is_finite()) || inside(th[k]))
            .collect()
    };
    // The chain: keep the quantities whose estimates stand out of their sds (a corner also
    // positive), hold the others at 0 and fit again.
    if let Some(terms) = prob.chain {
        let ci = prob.chain_index();
        let cov = covariance_of(&prob, &s.theta, &free_of(&prob, &s.theta));
        let vals = terms.values(&s.theta[ci..]);
        let sds = terms.sds(cov.as_ref(), ci);
        // (NaN sds, those off or without a covariance, compare false: not significant.)
        let significant = |n: usize| {
            terms.on()[n]
                && vals[n].abs() > CHAIN_SIGNIFICANCE * sds[n]
                && vals[n].abs() >= CHAIN_MIN[n]
                && (n == 0 || vals[n] > 0.0)
        };
        let keep = ChainTerms { delay: significant(0), hp_u: significant(1), hp_i: significant(2), ..terms };
        if keep != terms {
            let mut th = s.theta[..ci].to_vec();
            let kv = keep.on();
            th.extend((0..3).filter(|&n| kv[n]).map(|n| vals[n]));
            let pr = CurrentError {
                f: prob.f.clone(),
                u: prob.u.clone(),
                i: prob.i.clone(),
                w: prob.w.clone(),
                map: prob.map.clone(),
                chain: (keep.count() > 0).then_some(keep),
                ..prob
            };
            s = run(&pr, th, MAX_ITERATIONS, observe);
            prob = pr;
        }
    }
    let mut p = map.params(&s.theta);
    let ext = prob.ext(&s.theta);
    // Relative sd of p_k is the sd of ln p_k: the covariance of theta mapped to q (and
    // ln L2 = q2 + q3).
    // A coordinate that ended on its bound is held there (its logistic's slope is ~0, which
    // would make J^T J singular and every sd NaN): it leaves the covariance, with sd 0.
    let dq = map.dq(&s.theta);
    let inside = |t: f64| (1e-3..=1.0 - 1e-3).contains(&logistic(t));
    let cov = covariance_of(&prob, &s.theta, &free_of(&prob, &s.theta));
    let mut sigma_rel: [f64; 7] = match &cov {
        Some(c) => {
            let cq = |a: usize, b: usize| c[(a, b)] * dq[a] * dq[b];
            std::array::from_fn(|k| {
                sd_from_variance(if k == 2 { cq(2, 2) + cq(3, 3) + 2.0 * cq(2, 3) } else { cq(k, k) })
            })
        }
        None => [f64::NAN; 7],
    };
    let creep = prob.idx_lambda().map(|k| (s.theta[k], cov.as_ref().map_or(f64::NAN, |c| sd_from_variance(c[(k, k)]))));
    let mut lr3 = prob.idx_lr3().map(|k| {
        let (l3, r3) = ext.lr3.expect("LR-3 fitted");
        let d3 = prob.tau3(s.theta[k]).1;
        let sd = cov.as_ref().map_or([f64::NAN; 2], |c| {
            let (a, b) = (k, k + 1);
            [sd_from_variance(c[(a, a)] * d3 * d3 + c[(b, b)] + 2.0 * c[(a, b)] * d3), sd_from_variance(c[(b, b)])]
        });
        ([l3, r3], sd)
    });
    for (sd, m) in sigma_rel.iter_mut().zip(model_rel) {
        *sd = sd.hypot(m);
    }
    let residual_rel = prob.residual_rel(&s.theta);
    if !s.converged {
        return Err(format!(
            "{origin}: the impedance fit did not converge in {} iterations (residual {residual_rel:.3e})",
            s.iteration
        ));
    }
    let mut at_bound = map.at_bound(&s.theta);
    if let Some(k) = prob.idx_lr3() {
        if !inside(s.theta[k]) {
            at_bound.push("L3/R3 corner");
        }
    }
    if s.theta[1] < min_ln_le {
        at_bound.push("Le");
    }
    let chain = fs.filter(|_| opts.chain).map(|fs| {
        let terms = prob.chain.unwrap_or(ChainTerms { fs, delay: false, hp_u: false, hp_i: false });
        let ci = prob.chain_index();
        let on = terms.on();
        let sds = terms.sds(cov.as_ref(), ci);
        ChainEstimate {
            values: terms.values(&s.theta[ci..]),
            sd: std::array::from_fn(|n| if on[n] { sds[n] } else { 0.0 }),
            on,
            fs,
        }
    });
    // Skewed channels: a current recorded late by tau samples multiplies U/I by
    // e^{j 2 pi f tau / fs}, which no passive circuit does. Let the same fit shift the current
    // channel: if that explains most of the error, the channels are skewed. With the chain
    // estimated, its delay is in the model (and reported there).
    let current_delay = match fs {
        Some(fs) if !opts.chain => {
            let mut check = CurrentError {
                chain: Some(ChainTerms { fs, delay: true, hp_u: false, hp_i: false }),
                ..thin(&prob, SCOUT_BINS)
            };
            check.norm = prob_norm(&check);
            let mut th = s.theta.clone();
            th.push(0.0);
            let base = LmState::new(&check, th.clone()).cost;
            let d = run(&check, th, MAX_ITERATIONS, &mut |_| {});
            let at = check.chain_index();
            (d.converged && d.cost < 0.25 * base && d.theta[at].abs() >= 0.05)
                .then(|| (d.theta[at], 1.0 - (d.cost / base).sqrt()))
        }
        _ => None,
    };
    let transient = Transient { c: prob.transient(&s.theta).to_vec(), omega0: prob.omega0 };
    if lr3_named_first(&mut p, &mut sigma_rel, &mut lr3) {
        for b in at_bound.iter_mut() {
            *b = match *b {
                "L2/R2 corner" => "L3/R3 corner",
                "L3/R3 corner" => "L2/R2 corner",
                other => other,
            };
        }
    }
    Ok(LinearFit {
        p,
        sigma_rel,
        residual_rel,
        band,
        bins: prob.f.len(),
        iterations: s.iteration,
        h1,
        at_bound,
        current_delay,
        transient,
        effects: prob.effects,
        creep,
        lr3,
        tried,
        le_model_rel,
        model_rel,
        chain,
        lr2,
        magnitude_only: prob.magnitude_only,
    })
}

/// The relative spread of the impedance model's parameters `[Re, Le, L2, R2, Res, Cmes,
/// Lces]` from the chosen model (natural coordinates `chosen`, [`ParamMap::q`]) to the
/// models that fit the data as well (`alike`): the largest `|p_alike / p_chosen - 1|` of
/// each, at most 1. The branch (L2, R2) gets none: a model with a second branch shares the
/// para-inductance between two branches by definition, and names them by their corners.
pub(super) fn model_spread(chosen: &[f64; 7], alike: &[[f64; 7]]) -> [f64; 7] {
    std::array::from_fn(|k| {
        if k == 2 || k == 3 {
            return 0.0;
        }
        let d = alike.iter().map(|q| (q[k] - chosen[k]).abs()).fold(0.0, f64::max);
        (d.exp() - 1.0).min(1.0)
    })
}

/// Bins per cluster of the linear fit's robust covariance (see [`covariance_of`]).
pub(super) const COVARIANCE_CLUSTER_BINS: usize = 16;

/// Covariance of theta over its `free` entries only (the others held fixed, with zero rows
/// and columns): the cluster-robust [`sandwich_covariance`] over clusters of
/// [`COVARIANCE_CLUSTER_BINS`] neighbouring bins. The classical `sigma^2 (J^T J)^-1` took the
/// residual as white with one level; its largest part is distortion and leakage
/// concentrated near the resonance, and there its sds were 2-5x too small (52 %
/// of the truths within 2 sd, 87 % once the leakage was fitted; see
/// `linear_sigmas_cover_the_truth_over_seeds`).
pub(super) fn covariance_of(p: &CurrentError, theta: &[f64], free: &[usize]) -> Option<DMatrix<f64>> {
    let (r, j) = p.residual_jacobian(theta);
    let jf = j.select_columns(free);
    let cf = sandwich_covariance(&jf, &r, 2 * COVARIANCE_CLUSTER_BINS)?;
    let mut c = DMatrix::zeros(theta.len(), theta.len());
    for (a, &ka) in free.iter().enumerate() {
        for (b, &kb) in free.iter().enumerate() {
            c[(ka, kb)] = cf[(a, b)];
        }
    }
    Some(c)
}

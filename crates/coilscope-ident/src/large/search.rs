//! The searches of `identify`: the window each stage fits, when a stage has settled, the
//! solver's runs, and the screening of the effects before a round of trials.

use super::*;

/// Largest share of the current (relative RMS after settling) the start model may miss
/// before `identify` refuses the record: large records start at 2-5 % (SB17, 18WU, PTT4 at
/// 85 % of their range).
pub const START_MISS: f64 = 0.5;
/// Corner (Hz) of the second-order high-pass the start's miss is judged behind when the chain
/// is estimated (the excitation's usual lower end).
pub const START_MISS_HP_HZ: f64 = 10.0;

/// Periods of the resonance a record must hold after the start model settles. Measured
/// (0.5 s at 96 kHz to +-2 mm, 70 dB): 18WU (23.6 Hz, 5.9 periods) within 0.03 % (Bl, Kms);
/// the same driver with three times its mass (13.6 Hz, 3.4 periods) Bl 6.7 %, Re 9 % off at
/// a residual 70 times its floor.
pub const MIN_RESONANCE_PERIODS: f64 = 4.0;

/// Share of the record's excursion (each side, of the start model's trace) the estimation
/// part of the search window must reach ([`search_window`]).
pub const SEARCH_REACH: f64 = 0.95;
/// Share of the record's excursion the validation part of the search window must reach.
pub const SEARCH_VALIDATION_REACH: f64 = 0.65;

/// End (samples) of the window the order and effects search fits and validates on: the
/// shortest prefix of `seconds`, `1.5 seconds`, `2 seconds`, ... of the record whose first
/// `share` (the estimation part) reaches [`SEARCH_REACH`] of the excursion `x` (the start
/// model's trace) reaches on each side over the whole record, and whose rest (the
/// validation part) [`SEARCH_VALIDATION_REACH`] of it; the whole record when none does or
/// `seconds` is 0.
///
/// Every stage of the search is an output-error fit whose cost is proportional to the
/// samples it runs over; the search only ranks models (orders, effects) and hands its
/// estimate to the final fit, which runs over the whole record. A prefix that misses the
/// record's loud part (a level ramp, music) would rank the orders on less reach than the
/// final fit has: then the window grows until it holds it.
pub fn search_window(x: &[f64], fs: f64, seconds: f64, share: f64) -> usize {
    let n = x.len();
    let step = (0.5 * seconds * fs) as usize;
    if !(seconds > 0.0) || step == 0 {
        return n;
    }
    let extent = |part: &[f64]| part.iter().fold((0.0f64, 0.0f64), |(a, b), v| (a.min(*v), b.max(*v)));
    let (lo, hi) = extent(x);
    let reaches = |part: &[f64], share: f64| {
        let (a, b) = extent(part);
        a <= share * lo && b >= share * hi
    };
    let mut end = 2 * step;
    while end < n {
        let split = (share * end as f64) as usize;
        if reaches(&x[..split], SEARCH_REACH) && reaches(&x[split..end], SEARCH_VALIDATION_REACH) {
            return end;
        }
        end += step;
    }
    n
}

/// Gauss-Newton steps on the held-out part's Re(t) knots before a search stage's held-out
/// score (`OutputError::residual_with_re_fitted`): Re enters the current almost linearly.
/// A second step chose the same models on the microspeakers whose LR-3 the extrapolated
/// track had hidden, and cost 10-15 % of their fits.
pub const HELD_OUT_RE_STEPS: usize = 1;

/// A search stage ([`Stage::Estimate`]) stops after an accepted step that lowered the cost by
/// less than this share, ...
pub const SEARCH_SETTLED_DECREASE: f64 = 0.05;
/// ... taken with damping at most [`SEARCH_SETTLED_LAMBDA`], whose gain ratio (actual over
/// predicted decrease) is within this of 1.
pub const SEARCH_SETTLED_GAIN: f64 = 0.02;
/// Largest damping of a settling step (relative to the diagonal of `J^T J`).
pub const SEARCH_SETTLED_LAMBDA: f64 = 1e-2;

/// Whether the last step of a search stage leaves nothing the search needs: the linearised
/// model predicted the step's decrease to within [`SEARCH_SETTLED_GAIN`] and the step was
/// (nearly) the undamped Gauss-Newton step to that model's minimum, so what is left is of
/// the order of `decrease * |1 - gain ratio|`: below 1e-3 of the cost, the search's own
/// tolerance. The output error converges quadratically once near (measured, SB17 8 s:
/// decreases 4.2e-2 then 1.0e-4, 1.4e-2 then 1.8e-6, 3.0e-2 then 9e-7, every gain ratio
/// within 0.3 % of 1), and the search only ranks models by held-out error (2 % and 5 %
/// steps): the iteration that confirmed convergence was a whole Jacobian for nothing. The
/// final fit keeps its tolerance (its last Jacobian is the covariance's).
///
/// And Gauss-Newton's step must not promise more ([`LmState::gn_left`] below
/// [`SEARCH_SETTLED_DECREASE`]): a step held back by its damping can be predicted within 2 %
/// and gain 2 % while LM crawls along a curved valley. 18WU `-real-all`'s LR-3 trial
/// settled so at 3.48e-3 of the current with 32 % left by that measure (and its refit at
/// 1.97e-3, with 41 %), where the fit goes on to 6.6e-4; the stages that settle where the
/// error converges quadratically leave 1e-6 to 2.5e-2 (18WU, PTT4).
pub(super) fn settled(s: &LmState) -> bool {
    s.last_decrease < SEARCH_SETTLED_DECREASE
        && (s.gain_ratio - 1.0).abs() < SEARCH_SETTLED_GAIN
        && s.step_lambda <= SEARCH_SETTLED_LAMBDA
        && s.gn_left < SEARCH_SETTLED_DECREASE
}

/// LM's next step from `theta` on the linearised model of the last Jacobian `j` (computed one
/// accepted step earlier or more; damping `lambda`, as [`crate::lm::lm_step`] damps): the
/// step `d` with `(A + lambda diag A) d = -g`, `A = J^T J` (given: `a`), `g = J^T r(theta)`,
/// and its predicted cost decrease `-(g^T d + 1/2 d^T A d)` (absolute). `None` when the damped system is
/// singular. (Undamped, `A` is singular in a search stage: the Re(t) knots past its
/// estimation part have no rows.)
#[cfg(test)]
pub(super) fn chord_step(
    prob: &OutputError,
    j: &DMatrix<f64>,
    a: &DMatrix<f64>,
    theta: &[f64],
    lambda: f64,
) -> Option<(Vec<f64>, f64)> {
    damped_from(a, &j.tr_mul(&prob.residual(theta)), theta, lambda)
}

/// [`chord_step`] given `g = J^T r(theta)`: the damped step's end and its predicted decrease.
pub(super) fn damped_from(a: &DMatrix<f64>, g: &DVector<f64>, theta: &[f64], lambda: f64) -> Option<(Vec<f64>, f64)> {
    let (d, predicted) = crate::lm::damped_step(a, g, lambda)?;
    Some((theta.iter().zip(d.iter()).map(|(t, d)| t + d).collect(), predicted))
}

/// Chord iterations: the final fit's steps on its last Jacobian while its linearised model
/// holds. After an accepted step that was (nearly) the undamped Gauss-Newton step
/// ([`SEARCH_SETTLED_LAMBDA`]) and whose decrease the linearised model predicted to within
/// [`FINAL_SETTLED_GAIN`], the next steps are computed on the last Jacobian `J` with each new
/// residual ([`chord_step`]: `J^T J` once, `J^T r` per step), one residual run each instead of
/// a Jacobian and a residual run, the damping divided by [`FINAL_FAST_DIVISOR`] after each
/// step whose decrease the model predicted within [`FINAL_FAST_GAIN`]. The first such step's
/// prediction matched the full iteration's actual decrease to 1 % (3.245e-2 against 3.26e-2,
/// 3.438e-2 against 3.44e-2, 1.600e-6 against 1.57e-6, SB17:
/// `a_chord_step_predicts_the_next_iteration`).
///
/// The iterations end (`End`, converged) at the first step that lowers the cost by less than
/// `tol`, as a full iteration would have ended (at such a step the gain ratio is no test:
/// SB17's was 0.984 at 1.8e-6). When that is the first chord step, the last Jacobian stays
/// the covariance's (one accepted step behind, as a full iteration's is); after more, the
/// state has moved by more than the tolerance since it, and the Jacobian at the end is
/// computed for the covariance (alongside the last step's residual run when that step
/// promised less than twice the tolerance). A step that promised less than the tolerance
/// and did not lower the cost ends them too, at the state before it (converged: the state is
/// at the optimum within the tolerance, as `lm_step_ahead`'s `settle_below` has it), with
/// the covariance's Jacobian computed there. Another step that does not lower the cost, or
/// whose decrease the model missed by more than [`FINAL_FAST_GAIN`], hands the state back to
/// full iterations (`Go`). The microspeaker's fit with heating terms moved its error by 60-70 %
/// per full iteration at gain ratio 1.000 while the damping fell from 1e-4 to 1e-7: four
/// Jacobians of 3.7-4.4 s, where each chord step is a 0.4 s residual run.
///
/// With two cores each chord step but the last is taken beside a bolder one (the damping
/// divided by [`CHORD_BOLD_DIVISOR`]), one residual run per core, and the lower cost kept
/// ([`OutputError::better_of_two`]): the microspeaker's fit with heating terms then reaches
/// its end in two chord steps instead of four (1.48e-3 to 4.73e-4 in one). A last step
/// (promising less than twice the tolerance) runs beside the Jacobian at its end instead; when
/// it promised less than the tolerance and did not lower the cost, that Jacobian (a step
/// below the tolerance from the end) is kept as the covariance's, not computed once more.
///
/// `early`: the caller's test of a state whose next step promises less than
/// [`EARLY_TEST_BELOW`] (but not less than `tol`), made once; when it says yes the state is
/// returned unconverged (`End`).
///
/// The fit does not stop *before* the last step: a relative decrease `d` left on the table is
/// about `sqrt(d m)` sds of movement over `m` residuals (1e-4 on 288 000 rows: 5 sd; SB17's
/// 1.6e-6: 0.7 sd). The search stages keep their full iterations: with chord steps there,
/// the order search's truncation term (the difference of two search fits) moved and 18WU's
/// `-real-all` bands went from 2.89 to 3.03 sd.
pub(super) fn chords(
    prob: &OutputError,
    s: LmState,
    tol: f64,
    max_it: usize,
    early: Option<&dyn Fn(&LmState) -> bool>,
    report: &mut dyn FnMut(&LmState),
) -> Chords {
    if !may_settle(&s, FINAL_SETTLED_GAIN) {
        return Chords::Go(s);
    }
    let Some(j) = prob.last_jacobian.lock().expect("jacobian cache").clone() else { return Chords::Go(s) };
    let a = crate::lm::gram(&j);
    let (mut s, mut taken, mut tested) = (s, 0usize, false);
    while s.iteration < max_it {
        let r_end = prob.residual(&s.theta);
        let g = j.tr_mul(&r_end);
        let Some((theta, predicted)) = damped_from(&a, &g, &s.theta, s.lambda) else { break };
        let predicted_rel = predicted / s.cost.max(1e-300);
        if !tested && predicted_rel >= tol && predicted_rel < EARLY_TEST_BELOW {
            tested = true;
            if early.is_some_and(|f| f(&s)) {
                return Chords::End(s);
            }
        }
        let ends = |cost: f64| cost < s.cost && (s.cost - cost) / s.cost < tol;
        let last_try = taken > 0 && predicted_rel < 2.0 * tol;
        // A bolder step beside this one on the idle core, the better of the two taken.
        let lambda_bold = (s.lambda / CHORD_BOLD_DIVISOR).max(1e-12);
        let bold = (!last_try && prob.threads >= 2).then(|| damped_from(&a, &g, &s.theta, lambda_bold)).flatten();
        let (theta, predicted, lambda_taken, r) = match bold {
            Some((theta_b, predicted_b)) => {
                let ([r0, r1], k) = prob.better_of_two([&theta, &theta_b]);
                if k == 1 {
                    (theta_b, predicted_b, lambda_bold, r1)
                } else {
                    (theta, predicted, s.lambda, r0)
                }
            }
            None => {
                // A step that promises less than the tolerance keeps the Jacobian computed
                // beside it even when it does not lower the cost: it is the covariance's
                // then (below), within a step of the end that moves the cost by less than
                // the tolerance.
                let keep = |r: &DVector<f64>| {
                    let c = 0.5 * r.norm_squared();
                    ends(c) || (predicted_rel < tol && !(c.is_finite() && c < s.cost))
                };
                let r = if last_try { prob.residual_ahead(&theta, &keep, None) } else { prob.residual(&theta) };
                (theta, predicted, s.lambda, r)
            }
        };
        let cost = 0.5 * r.norm_squared();
        if !(cost.is_finite() && cost < s.cost) {
            if predicted_rel < tol {
                // A step that promised less than the tolerance and did not lower the cost:
                // the state is at the optimum within the tolerance (as `lm_step_ahead`'s
                // `settle_below`), and a full iteration would take a Jacobian and a residual
                // run to move it by less (the microspeaker's fit with heating terms, on a
                // Jacobian one step further back: 2.4e-6). The covariance's Jacobian is the
                // one computed beside that step's residual run (`keep` above), or computed
                // at the end.
                let end = LmState { iteration: s.iteration + 1, converged: true, last_decrease: 0.0, ..s };
                let beside = prob.ahead.lock().expect("jacobian ahead").as_ref().is_some_and(|(th, ..)| *th == theta);
                prob.residual_jacobian(if beside { &theta } else { &end.theta });
                // The caches back at the end (the trial's run replaced them).
                *prob.last_residual.lock().expect("residual cache") = Some((end.theta.clone(), r_end));
                report(&end);
                return Chords::End(end);
            }
            break;
        }
        let (dec, gain) = ((s.cost - cost) / s.cost, (s.cost - cost) / predicted);
        let trusted = (gain - 1.0).abs() < FINAL_FAST_GAIN;
        let lambda = (lambda_taken / if trusted { FINAL_FAST_DIVISOR } else { 3.0 }).max(1e-12);
        s = LmState {
            theta,
            cost,
            lambda,
            iteration: s.iteration + 1,
            last_decrease: dec,
            gain_ratio: gain,
            step_lambda: lambda_taken,
            gn_left: f64::NAN,
            converged: dec < tol,
        };
        taken += 1;
        report(&s);
        if s.converged {
            if taken > 1 {
                // The covariance's Jacobian, at the end (computed alongside the last residual
                // run when that was asked for).
                prob.residual_jacobian(&s.theta);
            }
            return Chords::End(s);
        }
        if !trusted {
            break;
        }
    }
    Chords::Go(s)
}

/// What [`chords`] left.
pub(super) enum Chords {
    /// The fit ends with this state (converged, or unconverged for the `early` test).
    End(LmState),
    /// Full iterations go on from this state.
    Go(LmState),
}

/// Whether [`chords`] steps on after `s`.
pub(super) fn may_settle(s: &LmState, gain_tol: f64) -> bool {
    s.step_lambda <= SEARCH_SETTLED_LAMBDA && (s.gain_ratio - 1.0).abs() < gain_tol
}

/// Largest `|1 - gain ratio|` of a last step the final fit trusts its linearised model after
/// (`chords`).
pub const FINAL_SETTLED_GAIN: f64 = 0.01;

/// Size of the vanishing LR-3 branch the effects search also starts from, relative to the
/// typical start (L3 = 0.5 L2, R3 = 3 R2; the branch's time constant is the typical one's).
///
/// Kept at 0.02. With L3 and R3 as the fit's unknowns, a trial from here
/// on a record without LR-3 crawled 10 iterations back (PTT4: 1.9 s of a 5.7 s `identify`);
/// with L3 and tau3 (see `Slots::r3`'s doc) it takes 3. Smaller starts fail both ways:
/// - L3 and R3 at 1e-3: the chain sweep's PTT4 (AC-coupled card, every effect
///   in the record, seed 1706) never grew the branch (LR-2 + creep, Bl 3 % off);
/// - L3 and tau3 at 1e-3: that case passed and the trials without LR-3 took 2
///   iterations, but the harsh world's PTT4 (seeds 2 and 34) and large coil (seed 4) kept
///   the branch small (L3 1.7e-5 H against 2.75e-4): tau3's column scales with L3, so from a
///   corner far off the fit grows L3 only as far as that corner allows.
pub const LR3_VANISHING: f64 = 0.02;

/// Size of the LR-3 branch the effects screen scores from (`screen_effects`), in units of
/// the typical one (L3 = L2 / 2, R3 = 3 R2): small enough to leave the residual as it is
/// (the trial's [`LR3_VANISHING`] branch moved the microspeaker's current error from
/// 5.421e-3 to 5.427e-3, which a screen would count as a gain), while L3's column at its
/// corner does not depend on the size and tau3's only scales with it.
pub const LR3_SCREEN: f64 = 1e-6;

/// Creep factor of the vanishing creep the effects search also starts from (a typical
/// driver's is 0.03-0.1): on records without creep the linear fit's creep start missed
/// 5-8e-3 of the current (PTT4, 18WU, SB17) against this one's 4-8e-4, and the creep trial
/// took 3-4 iterations instead of 2 (0.35-0.45 s of the effects search). Creep acts in proportion
/// to lambda, so the trial grows it from here when the
/// record holds it; where it does, the linear fit's start misses less and is taken. The
/// screen (`screen_effects`) scores creep from zero instead.
pub const CREEP_VANISHING: f64 = 1e-3;

/// Iterations of a search stage (order or effect trial) at most.
pub const SEARCH_MAX_ITERATIONS: usize = 12;

/// Iterations of the effects search's trial from a vanishing LR-3 branch in tau3 coordinates
/// ([`Slots::r3`]) before it goes on in L3 and R3 when it has not settled: on a record
/// without the branch it settles in 2-3 (PTT4); where the record holds one, tau3 bends the
/// valley and the trial crawled to its 12th iteration (18WU `-real-all`: 6.5e-3 of the
/// current to 1.78e-3, where L3 and R3 then reach 6.6e-4).
pub const LR3_TAU_ITERATIONS: usize = 3;

/// Iterations of the order-0 (linear) stage before the order search goes on from it.
pub const ORDER0_FIRST_ITERATIONS: usize = 3;
/// The order-0 stage is finished (up to 10 iterations) when order 2's gain over it is below
/// this: five times the [`identify`]'s "too small" threshold of 5 %, so that its error would
/// have to fall by a fifth more for the decision to change (18WU's crawl fell by 5 % in four
/// more iterations; its gain is 65 %).
pub const ORDER0_FINISH_BELOW_GAIN: f64 = 0.25;

/// Run LM on `prob` from `theta` until an accepted step lowers the cost by less than `tol`
/// (relative; Gauss-Newton's next step would gain far less) or `max_it` iterations. Returns the last state.
/// A search stage also stops once [`settled`]; the final fit takes [`chords`] when its model holds.
///
/// `early` (final fit): a test of a state within [`EARLY_TEST_BELOW`] of the end; when it
/// says yes the fit returns that state unconverged (the caller may resume it).
#[allow(clippy::too_many_arguments)]
pub(super) fn solve(
    prob: &OutputError,
    theta: Vec<f64>,
    stage: &Stage,
    tol: f64,
    max_it: usize,
    at_last: Option<&AtLastTrial>,
    early: Option<&dyn Fn(&LmState) -> bool>,
    observe: &mut dyn FnMut(&Progress),
) -> LmState {
    solve_following(prob, theta, stage, tol, max_it, at_last, early, false, observe)
}

/// [`solve`], and with `follow` a search stage that follows a curved valley as the final fit
/// does: geodesic acceleration after a step the linearised model missed by
/// [`FINAL_FAST_GAIN`] or more, and no end at a settled step ([`settled`]), only below `tol`
/// or at `max_it`. For the model taken so far when it goes on alone before a trial is
/// compared with it (the effects search in [`identify`]).
#[allow(clippy::too_many_arguments)]
pub(super) fn solve_following(
    prob: &OutputError,
    theta: Vec<f64>,
    stage: &Stage,
    tol: f64,
    max_it: usize,
    at_last: Option<&AtLastTrial>,
    early: Option<&dyn Fn(&LmState) -> bool>,
    follow: bool,
    observe: &mut dyn FnMut(&Progress),
) -> LmState {
    let norm_i = prob.i[prob.fit.clone()].iter().map(|v| v * v).sum::<f64>().sqrt();
    let report = |s: &LmState, observe: &mut dyn FnMut(&Progress)| {
        observe(&Progress { stage: stage.clone(), state: s, residual_rel: (2.0 * s.cost).sqrt() / norm_i });
    };
    // The start's residual with its Jacobian alongside (the first iteration needs both).
    prob.residual_ahead(&theta, &|_| max_it > 0, None);
    let mut s = LmState::new(prob, theta);
    report(&s, observe);
    // Whether the loop below goes on from an accepted state: its Jacobian is then computed
    // alongside the trial's residual ([`lm_step_ahead`]). The same tests as the loop's, the
    // final fit's chord step counted as an end (it uses the last Jacobian).
    let goes_on = |n: &LmState| {
        let ends = n.iteration >= max_it
            || n.last_decrease < tol
            || n.converged
            || match stage {
                Stage::Estimate { .. } => !follow && settled(n),
                Stage::Final { .. } => may_settle(n, FINAL_SETTLED_GAIN),
            };
        !ends
    };
    while s.iteration < max_it {
        // Geodesic acceleration in the final fit, after a step whose decrease the linearised
        // model missed by FINAL_FAST_GAIN or more (a curved valley; where the model holds
        // the acceleration is negligible and its residual run would be wasted). The
        // slow-branch record (`branch_order`): 16 iterations of a full Jacobian at gain ratios 0.18-0.98, 10
        // with it (final fit 12.8 -> 7.5 s). The search stages keep their straight steps:
        // where they stop moves the order search's truncation term (see chords), and 18WU's
        // `-real-all` effect trials did not gain (51 against 53 iterations, same time).
        let accelerate = (follow || matches!(stage, Stage::Final { .. }))
            && s.iteration > 0
            && !((s.gain_ratio - 1.0).abs() < FINAL_FAST_GAIN);
        let mut next = lm_step_accelerated(prob, &s, &goes_on, at_last, tol, accelerate);
        if matches!(stage, Stage::Final { .. }) && (next.gain_ratio - 1.0).abs() < FINAL_FAST_GAIN {
            next.lambda = (next.step_lambda / FINAL_FAST_DIVISOR).max(1e-12);
        }
        let stalled = next.last_decrease == 0.0;
        s = next;
        report(&s, observe);
        if stalled {
            break;
        }
        if s.last_decrease < tol || s.converged || (!follow && matches!(stage, Stage::Estimate { .. }) && settled(&s)) {
            s.converged = true;
            break;
        }
        if matches!(stage, Stage::Final { .. }) {
            match chords(prob, s, tol, max_it, early, &mut |st| report(st, observe)) {
                Chords::End(end) => {
                    s = end;
                    break;
                }
                Chords::Go(go) => s = go,
            }
        }
    }
    s
}

/// The chord steps' bolder step (`chords`): with two cores, each chord step is taken
/// beside one with the damping divided by this, one residual run per core, and the one with
/// the lower cost is kept. The microspeaker's fit with heating terms (gain ratios 1.000,
/// the damping falling by [`FINAL_FAST_DIVISOR`] per step) took four chord steps to the
/// error the undamped step reached (1.48e-3, 9.3e-4, 5.2e-4, 4.70e-4, 4.69e-4), with one
/// core idle.
pub const CHORD_BOLD_DIVISOR: f64 = 100.0;

/// A final fit hands its state to the caller's `early` test (`solve`) once the next step
/// predicts a decrease below this share of the cost: within 1 % of its end, the fit's
/// residual and Re(t) track are what the converged fit's would be for the heating test (the
/// microspeaker: 2e-4 left after the first step; converging it took a 3.9 s Jacobian, then
/// the heating terms replaced that fit).
pub const EARLY_TEST_BELOW: f64 = 1e-2;

/// The final fit's damping after an accepted step whose decrease the linearised model
/// predicted within [`FINAL_FAST_GAIN`] is the step's divided by this (3 otherwise, as
/// [`crate::lm::lm_step`] does): the model holds, so LM should approach the Gauss-Newton
/// step quickly. With heating terms the microspeaker's final fit moved its error by 30-50 %
/// per iteration at gain ratio 1.000 with the damping falling by 3: 9 iterations of a 3.9 s
/// Jacobian, 6 with this. The search stages keep 3 (where they stop moves the order
/// search's truncation term: with 10 there, 18WU's `-real-all` bands went from 2.70 to
/// 3.05 sd).
pub const FINAL_FAST_DIVISOR: f64 = 10.0;
/// `|1 - gain ratio|` below which [`FINAL_FAST_DIVISOR`] applies.
pub const FINAL_FAST_GAIN: f64 = 0.05;

/// What the effects search (its trial taken, or its base gone on alone) and the order
/// raising after it take over from a search stage they adopt: the parameters (with the given mass)
/// and Re(t) track scored on the held-out
/// part, the stage's own track (the next stage's start), the chain's unknowns, and the
/// stage's last Jacobian with its layout (the next stage's seed).
pub(super) struct Taken {
    pub(super) current: Parameters,
    pub(super) re_track: Option<Vec<f64>>,
    pub(super) search_track: Option<Vec<f64>>,
    pub(super) cth: Vec<f64>,
    pub(super) at_kept: Option<(Layout, std::sync::Arc<KeptJacobian>)>,
}

impl Taken {
    /// The stage of layout `lay` that ended at `theta` (its estimation part), `th_val`
    /// (that with the Re(t) track continued over the held-out part) and `kept`.
    pub(super) fn of(
        lay: Layout,
        mms: f64,
        theta: &[f64],
        th_val: &[f64],
        kept: Option<std::sync::Arc<KeptJacobian>>,
    ) -> Self {
        Taken {
            current: Parameters { mms, ..lay.parameters(th_val) },
            re_track: Some(lay.re_track(th_val)),
            search_track: Some(lay.re_track(theta)),
            cth: th_val[lay.slots().n..].to_vec(),
            at_kept: kept.map(|k| (lay, k)),
        }
    }
}

/// The last Jacobian of a search stage that converged, for the next stage to start on
/// ([`OutputError::seed_first`]). A stage stopped by its iteration cap may still be moving:
/// 18WU's order-0 stage, capped at [`ORDER0_FIRST_ITERATIONS`] while it crawled (gain ratios
/// 0.74-1.49), seeded an order-2 stage that then took 5 iterations instead of 4 (gain ratios
/// 0.66-0.94).
pub(super) fn kept_if_converged(prob: &OutputError, s: &LmState) -> Option<std::sync::Arc<KeptJacobian>> {
    let kept = prob.take_kept()?;
    if s.converged {
        Some(std::sync::Arc::new(kept))
    } else {
        kept.recycle();
        None
    }
}

/// The linear fit with the small-signal `effects` that starts a candidate of the effects
/// search ([`LinearOptions::LARGE_SIGNAL_START`] otherwise); `None` when it fails.
pub(super) fn linear_start_fit(
    u: &[f64],
    i: &[f64],
    fs: f64,
    origin: &str,
    effects: Effects,
    lr2: Option<&crate::linear::Lr2Fit>,
) -> Option<LinearFit> {
    let lin_opts = LinearOptions { effects: EffectsChoice::Fixed(effects), ..LinearOptions::LARGE_SIGNAL_START };
    crate::linear::fit_linear_record_from(u, i, fs, origin, &lin_opts, lr2, |_| {}).ok()
}

/// One candidate of the effects search's screen (`screen_effects`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EffectScreen {
    /// The model the candidate makes: the round's effects and `added`.
    pub model: Effects,
    /// The effect the candidate adds.
    pub added: Effects,
    /// The most one Gauss-Newton step with it would lower the estimation part's relative
    /// current error by; below [`EFFECT_SCREEN_GAIN`] the model was not fitted.
    pub gain: f64,
    /// The model that took the round before this one was fitted: its screen gain was more
    /// than [`EFFECT_RIVAL_RATIO`] times this one's (this model was not fitted in the round).
    pub outscored_by: Option<Effects>,
}

impl EffectScreen {
    /// The screen left the model out: its gain is below [`EFFECT_SCREEN_GAIN`].
    pub fn screened_out(&self) -> bool {
        self.gain < EFFECT_SCREEN_GAIN
    }

    /// The model was not fitted: screened out, or outscored by the one that took the round.
    pub fn not_fitted(&self) -> bool {
        self.screened_out() || self.outscored_by.is_some()
    }
}

/// The decrease of `0.5 |r|^2` a Gauss-Newton step in the unknowns `cols` predicts, from the
/// Gram matrix `gram` (`J^T J`) and the gradient `grad` (`J^T r`) of all unknowns:
/// `0.5 g^T G^-1 g` over those columns, scaled to a unit diagonal. `None` when the columns'
/// Gram matrix is singular (an unknown without a column).
pub(super) fn gauss_newton_decrease(gram: &DMatrix<f64>, grad: &DVector<f64>, cols: &[usize]) -> Option<f64> {
    let d: Vec<f64> = cols.iter().map(|&c| gram[(c, c)]).collect();
    if d.iter().any(|&v| !(v > 0.0)) {
        return None;
    }
    let s: Vec<f64> = d.iter().map(|v| v.sqrt().recip()).collect();
    let n = cols.len();
    let g = DMatrix::from_fn(n, n, |a, b| gram[(cols[a], cols[b])] * s[a] * s[b]);
    let b = DVector::from_fn(n, |a, _| grad[cols[a]] * s[a]);
    let x = g.cholesky()?.solve(&b);
    Some(0.5 * b.dot(&x))
}

/// What each screened candidate of an effects round would gain at most, as the relative
/// current error on the estimation part: `1 - sqrt(1 - d / c)` with `c = 0.5 |r|^2` at the
/// present estimate and `d` the Gauss-Newton decrease with the candidate's columns less the
/// decrease without them ([`gauss_newton_decrease`]). At the present estimate with every
/// screened effect at zero or nearly (creep at zero, an LR-3 branch at [`LR3_SCREEN`] of
/// the typical one, in L3 and tau3), on the round's base Jacobian (as
/// [`OutputError::seed_first`] maps it) with the screened effects' columns computed there,
/// each on the smallest model that has it: LR-3's on the base with the branch (the 3 x 3
/// network), creep's on the base with the creep bank, Le(i)'s and Rms(v)'s on the base's
/// own model, and the residual run on the base's model, these four runs on the cores in
/// turn. With one model with every effect (17 states and the 3 x 3 network) running all the
/// columns in one pass, the 0.1 g microspeaker's screen took 0.95 s instead of 0.47, the same gains
/// within 5e-7 (the test below compares the two at every
/// candidate). Their unknowns act nearly linearly from there: Le(i)'s and Rms(v)'s
/// coefficients, creep's lambda, and a branch's L3 at a given corner (its impedance
/// `j w L3 / (1 + j w tau3)`), with tau3's column moving the corner to first order. `None`
/// for a candidate the pass could not score (the base Jacobian's layout does not map, a
/// singular Gram matrix, no LR-2 branch to size LR-3 by).
///
/// The screen's model is the base model itself (its current error the base's to 1e-5):
/// creep's lambda is zero, where the bank's springs vanish and lambda's column does not.
/// When the screen started from the trials' [`CREEP_VANISHING`] instead, that start
/// missed the current by 23-36 % more than the base (in cost) on the bundled woofers'
/// records; the step with creep's column won that back and it counted as creep's gain
/// (1.0-3.5 %, against 4e-10 to 2e-6 from zero), and LR-3's by the columns' overlap
/// (1.8-2.8e-3): two trials fitted and dropped on every record without the effects
/// (`the_effects_screen_scores_from_the_base_model_itself`).
#[allow(clippy::too_many_arguments)]
pub(super) fn screen_effects<'a>(
    base: &(Layout, std::sync::Arc<KeptJacobian>),
    screened: &[Effects],
    at: Effects,
    current: &Parameters,
    track: Option<&[f64]>,
    cth: &[f64],
    prob_for: &dyn Fn(Layout) -> OutputError<'a>,
) -> Vec<Option<f64>> {
    let none = vec![None; screened.len()];
    let all = screened.iter().fold(at, |a, &e| a.union(e));
    let lr3_new = all.lr3 && !at.lr3;
    // The base's layout with the effects `e` too (LR-3's in the screen's coordinates).
    let layout_with = |e: Effects| {
        let l = base.0.clone().with_effects(at.union(e));
        if lr3_new && e.lr3 {
            l.with_lr3_tau()
        } else {
            l
        }
    };
    let lay = layout_with(all);
    let mut from = if all.creep && current.creep.is_none() {
        Parameters { creep: Some(coilscope_core::params::Creep { lambda: 0.0, f_ref: None }), ..current.clone() }
    } else {
        current.clone()
    };
    if lr3_new {
        let (l2, r2) = current.l2r2.as_ref().map_or((0.0, 0.0), |(l, r)| (l.eval(0.0), r.eval(0.0)));
        if !(l2 > 0.0 && r2 > 0.0) {
            return none;
        }
        from.l3r3 = Some((LR3_SCREEN * 0.5 * l2, LR3_SCREEN * 3.0 * r2));
    }
    let theta_of = |l: &Layout| {
        let mut th = l.theta_from(&from, track);
        th.extend_from_slice(cth);
        th
    };
    let th = theta_of(&lay);
    let Some(map) = column_map(&base.0, &lay, cth.len()) else { return none };
    if map.len() != th.len() || map.iter().flatten().any(|&b| b >= base.1.j.ncols()) || !lay.physical(&th) {
        return none;
    }
    let sl = lay.slots();
    let own = |e: Effects| -> Vec<usize> {
        let mut c = Vec::new();
        if e.creep {
            c.extend(sl.lambda);
        }
        if e.le_i {
            c.extend(sl.le_i.map(|k| [k, k + 1]).into_iter().flatten());
        }
        if e.rms_v {
            c.extend(sl.rms_v);
        }
        if e.lr3 {
            c.extend(sl.l3);
            c.extend(sl.r3);
        }
        c
    };
    // The new columns by the model that needs them: LR-3's on the 3 x 3 network, creep's
    // on the creep bank's states, Le(i)'s and Rms(v)'s on the base's model, each a pass of
    // its own, and the residual run on the base's model (the screen's model, to LR-3's
    // 1e-6 of a branch). One model with every effect (17 states, the 3 x 3 network) ran
    // all the columns in one pass.
    let plain = screened.iter().filter(|e| !e.needs_ext_states()).fold(Effects::NONE, |a, &e| a.union(e));
    let groups: Vec<Effects> =
        [Effects { lr3: lr3_new, ..Effects::NONE }, Effects { creep: all.creep && !at.creep, ..Effects::NONE }, plain]
            .into_iter()
            .filter(|&g| g != Effects::NONE)
            .collect();
    let fresh: Vec<usize> = (0..map.len()).filter(|&c| map[c].is_none()).collect();
    let mut parts: Vec<(OutputError, Vec<f64>, Vec<usize>, Vec<usize>)> = Vec::new();
    for &g in &groups {
        let lay_g = layout_with(g);
        let th_g = theta_of(&lay_g);
        let Some(map_g) = column_map(&lay_g, &lay, cth.len()) else { return none };
        let mine: Vec<usize> = fresh.iter().copied().filter(|c| own(g).contains(c)).collect();
        let Some(cols_g) = mine.iter().map(|&c| map_g[c]).collect::<Option<Vec<usize>>>() else { return none };
        let prob_g = prob_for(lay_g);
        if cols_g.len() > CHUNK_WIDE || !prob_g.layout.physical(&th_g) {
            return none;
        }
        parts.push((prob_g, th_g, cols_g, mine));
    }
    if parts.iter().map(|p| p.3.len()).sum::<usize>() != fresh.len() {
        return none;
    }
    let prob = prob_for(layout_with(Effects::NONE));
    let th_base = theta_of(&prob.layout);
    let (u, _) = prob.signals(&th_base);
    // The passes in `groups`' order (the costliest first), the residual run after them.
    let mut done = parallel_map(parts.len() + 1, prob.threads, |k| match parts.get(k) {
        Some((p, t, c, _)) => (p.columns_at(t, c, &u), None),
        None => (Vec::new(), Some(prob.residual(&th_base))),
    });
    let Some(r) = done.pop().and_then(|d| d.1) else { return none };
    let rows = r.len();
    if base.1.j.nrows() != rows {
        return none;
    }
    let mut j = DMatrix::from_vec(rows, th.len(), jacobian_storage(rows * th.len()));
    for (c, b) in map.iter().enumerate() {
        if let Some(b) = b {
            j.column_mut(c).copy_from(&base.1.j.column(*b));
        }
    }
    for ((_, _, _, mine), (block, _)) in parts.iter().zip(&done) {
        for (&c, col) in mine.iter().zip(block.chunks_exact(rows.max(1))) {
            j.column_mut(c).copy_from_slice(col);
        }
    }
    let cost = 0.5 * r.norm_squared();
    let gram = crate::lm::gram(&j);
    let grad = j.tr_mul(&r);
    recycle_jacobian(j);
    let new: Vec<usize> = screened.iter().flat_map(|&e| own(e)).collect();
    // (Re(t) knots past the estimation part have no column there.)
    let base_cols: Vec<usize> = (0..th.len()).filter(|c| !new.contains(c) && gram[(*c, *c)] > 0.0).collect();
    let Some(d0) = gauss_newton_decrease(&gram, &grad, &base_cols) else { return none };
    screened
        .iter()
        .map(|&e| {
            let mut cols = base_cols.clone();
            cols.extend(own(e));
            let d = gauss_newton_decrease(&gram, &grad, &cols)?;
            Some(1.0 - (1.0 - ((d - d0) / cost).clamp(0.0, 1.0)).sqrt())
        })
        .collect()
}

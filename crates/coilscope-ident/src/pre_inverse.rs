//! Pre-inverse identification (seed paper 3.2.2.2.3, Fig. 6): the inverse model runs ahead
//! of the transducer as a controller ([`coilscope_core::inverse`]), and its parameters are
//! adapted until the transducer's output follows the controller's input, here the
//! displacement of a fixed linear reference (the small-signal parameters, which the user
//! measured first).
//!
//! The error `e = x_measured - x_reference` is not linear in the parameters, and it reaches
//! them only through the transducer, so, as the paper proposes:
//!
//! - **gradient filtering**: the sensitivity of the error to parameter `k` is the change of
//!   the drive, `d drive / d theta_k` (the controller, differentiated by a finite step),
//!   filtered by the transducer from drive to displacement. The transducer is not known (that
//!   is the point), so its linear reference stands in for it: that filter is exact for the
//!   linear part and off by the nonlinearity's share, which slows the adaptation but does not
//!   move its fixed point (at `e = 0` the step is zero whatever the filter);
//! - **intermittent updates**: the transducer plays a whole block with the parameters held;
//!   then one damped Gauss-Newton (Levenberg-Marquardt) step on that block's error updates
//!   them for the next block. A step that raised the error is taken back and the damping
//!   raised.
//!
//! Adapted: the power series of Bl(x) and Kms(x), rest values included (to `order`). Le(x)
//! and the rest stay as the start set gives them: at the low frequencies that move the cone
//! the displacement hardly depends on them.

use coilscope_core::inverse::{compensate_to, CompensateOptions};
use coilscope_core::poly::Poly;
use coilscope_core::simulate::{rms, simulate, SimOptions};
use coilscope_core::Parameters;
use nalgebra::{DMatrix, DVector};

/// Options of [`adapt`].
#[derive(Clone, Debug)]
pub struct PreInverseOptions {
    /// Power-series order of Bl(x) and Kms(x).
    pub order: usize,
    /// Blocks (updates) at most.
    pub max_updates: usize,
    /// Stop when the block's error (RMS, relative to the reference's RMS) is below this.
    pub tol: f64,
    /// The controller's limits.
    pub limits: CompensateOptions,
}

impl Default for PreInverseOptions {
    fn default() -> Self {
        PreInverseOptions { order: 4, max_updates: 20, tol: 1e-4, limits: CompensateOptions::default() }
    }
}

/// One block: the error it played with, and the parameters after its update.
#[derive(Clone, Debug)]
pub struct Update {
    pub block: usize,
    /// RMS of `x - x_reference` over the RMS of `x_reference`, with the parameters held
    /// during the block.
    pub error_rel: f64,
    /// Whether the block's parameters lowered the error against the block before (a step
    /// that did not is taken back).
    pub accepted: bool,
    pub damping: f64,
    pub params: Parameters,
}

/// The adapted controller.
#[derive(Clone, Debug)]
pub struct PreInverseFit {
    /// The parameters with the lowest block error.
    pub params: Parameters,
    pub updates: Vec<Update>,
    /// The block error fell below `tol`.
    pub converged: bool,
}

fn theta_of(p: &Parameters, order: usize) -> Vec<f64> {
    let coef = |f: &Poly, j: usize| f.c.get(j).copied().unwrap_or(0.0);
    (0..=order).map(|j| coef(&p.bl, j)).chain((0..=order).map(|j| coef(&p.kms, j))).collect()
}

fn with_theta(p: &Parameters, th: &[f64], order: usize) -> Parameters {
    let mut q = p.clone();
    q.bl = Poly { c: th[..=order].to_vec() };
    q.kms = Poly { c: th[order + 1..].to_vec() };
    q
}

/// Adapt the controller from `start` so that `play` (the transducer: a drive in volts, the
/// measured displacement in metres back, from rest) follows `reference` driven by `input`,
/// one update per block. `observe` sees each block.
pub fn adapt(
    start: &Parameters,
    reference: &Parameters,
    input: &[f64],
    fs: f64,
    mut play: impl FnMut(&[f64]) -> Result<Vec<f64>, String>,
    opts: &PreInverseOptions,
    mut observe: impl FnMut(&Update),
) -> Result<PreInverseFit, String> {
    adapt_blocks(start, reference, input, fs, &mut play, opts, &mut observe)
}

/// [`adapt`]'s work, compiled once (not for each caller's `play` and `observe`).
fn adapt_blocks(
    start: &Parameters,
    reference: &Parameters,
    input: &[f64],
    fs: f64,
    play: &mut dyn FnMut(&[f64]) -> Result<Vec<f64>, String>,
    opts: &PreInverseOptions,
    observe: &mut dyn FnMut(&Update),
) -> Result<PreInverseFit, String> {
    let order = opts.order;
    let x_ref = simulate(reference, fs, input, &SimOptions::default()).map_err(|e| format!("the reference: {e}"))?.x;
    let drive_of = |th: &[f64]| {
        compensate_to(&with_theta(start, th, order), reference, fs, input, &opts.limits)
            .map(|c| c.drive)
            .map_err(|e| format!("the controller: {e}"))
    };
    let mut th = theta_of(start, order);
    let mut best: Option<(f64, Vec<f64>)> = None;
    let mut damping: f64 = 1e-3;
    let mut updates = vec![];
    let mut converged = false;
    for block in 0..opts.max_updates {
        let drive = drive_of(&th)?;
        let x = play(&drive)?;
        if x.len() != x_ref.len() {
            return Err(format!("the transducer returned {} samples for a drive of {}", x.len(), x_ref.len()));
        }
        let e: Vec<f64> = x.iter().zip(&x_ref).map(|(a, b)| a - b).collect();
        let err = rms(&e) / rms(&x_ref).max(1e-300);
        let accepted = best.as_ref().is_none_or(|(b, _)| err < *b);
        if accepted {
            best = Some((err, th.clone()));
            damping = (damping * 0.3).max(1e-6);
        } else {
            // Take the step back: the next block plays the best parameters' neighbour.
            th = best.as_ref().expect("a best block").1.clone();
            damping *= 10.0;
        }
        let u = Update { block, error_rel: err, accepted, damping, params: with_theta(start, &th, order) };
        observe(&u);
        updates.push(u);
        if accepted && err < opts.tol {
            converged = true;
            break;
        }
        // The error of the parameters the step starts from (the best block's).
        let (e0, drive0) = if accepted {
            (DVector::from_vec(e), drive)
        } else {
            let d = drive_of(&th)?;
            let x0 = play(&d)?;
            (DVector::from_iterator(x0.len(), x0.iter().zip(&x_ref).map(|(a, b)| a - b)), d)
        };
        // Filtered gradient: d drive / d theta_k through the linear reference.
        let mut j = DMatrix::zeros(e0.len(), th.len());
        for k in 0..th.len() {
            let scale = if k <= order { th[0].abs() } else { th[order + 1].abs() };
            let h = 1e-4 * scale
                / start.x_range.map_or(1.0, |[lo, hi]| hi.min(-lo)).powi(((k % (order + 1)) as i32).max(0));
            let mut tk = th.clone();
            tk[k] += h;
            let dk = drive_of(&tk)?;
            let dd: Vec<f64> = dk.iter().zip(&drive0).map(|(a, b)| a - b).collect();
            let xk = simulate(reference, fs, &dd, &SimOptions { range_margin: f64::INFINITY, ..Default::default() })
                .map_err(|e| format!("the gradient filter: {e}"))?
                .x;
            for (r, v) in xk.iter().enumerate() {
                j[(r, k)] = v / h;
            }
        }
        // Levenberg-Marquardt step with column scaling.
        let norms: Vec<f64> = (0..th.len()).map(|k| j.column(k).norm().max(1e-300)).collect();
        for (k, s) in norms.iter().enumerate() {
            j.column_mut(k).scale_mut(1.0 / s);
        }
        let mut a = j.tr_mul(&j);
        for k in 0..th.len() {
            a[(k, k)] += damping * (1.0 + a[(k, k)]);
        }
        let g = j.tr_mul(&e0);
        let step = a.cholesky().ok_or("the filtered gradient is singular: the input does not excite every coefficient (raise its level or its bandwidth, or lower the order)")?.solve(&g);
        th = th.iter().zip(step.iter().zip(&norms)).map(|(t, (s, n))| t - s / n).collect();
    }
    let (_, th_best) = best.expect("at least one block");
    Ok(PreInverseFit { params: with_theta(start, &th_best, order), updates, converged })
}

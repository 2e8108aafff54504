//! Thermal parameters from a long measurement (seed paper 4.2, the long-term test): the
//! two-node model of `docs/formats.md`,
//!
//! ```text
//! Ctv dTv/dt = Pv - (Tv - Tm) / Rtv,   Ctm dTm/dt = Pm + (Tv - Tm) / Rtv - Tm / Rtm,
//! ```
//!
//! fitted to the voice-coil rise the run tracked (from Re) under the powers it measured
//! (`Pv = Re(T) i^2` from the measured current, `Pm = R2 (i - i2)^2` from the live model's
//! LR-2 branch), block by block from a cold start.
//!
//! The unknowns are the logarithms of Rtv, Ctv, Rtm, Ctm (all positive). The model takes the
//! network's exact solution over each block with the block's powers held ([`HeldStep`]). The
//! sds are the cluster-robust sandwich over blocks of [`COVARIANCE_BLOCK_S`] (the tracked
//! rise's error is correlated over a second or more), so a parameter the run cannot tell (the
//! magnet's, in a run much shorter than its time constant) comes out with the large sd it
//! deserves rather than a false precision.

use crate::lm::{lm_step, LmState, Problem};
use coilscope_core::model::{HeldStep, ThermalModel};
use nalgebra::{DMatrix, DVector};

/// Seconds per cluster of the sandwich covariance.
pub const COVARIANCE_BLOCK_S: f64 = 10.0;

/// What a run tracked, one entry per block: time at the block's end (s), the estimated coil
/// rise (K), the mean coil power and the mean magnet (eddy-current) power (W) over the block.
#[derive(Clone, Debug, Default)]
pub struct ThermalTrack {
    pub t: Vec<f64>,
    pub dtv: Vec<f64>,
    pub pv: Vec<f64>,
    pub pm: Vec<f64>,
    /// The mean coil speed |v| over each block (m/s), for the convection cooling; empty:
    /// not known (the fit then has no convection).
    pub speed: Vec<f64>,
}

/// The fitted two-node model: `[Rtv K/W, Ctv J/K, Rtm K/W, Ctm J/K]` and their sds.
#[derive(Clone, Debug)]
pub struct ThermalFit {
    pub values: [f64; 4],
    pub sd: [f64; 4],
    /// How far the tracked rise lags the coil (s), fitted with the four, and its sd.
    pub lag_s: f64,
    pub lag_sd: f64,
    /// RMS of the tracked rise less the model's (K).
    pub residual_k: f64,
    /// The largest tracked rise (K).
    pub peak_k: f64,
    /// Convection cooling `rv` (s/m, `Rtv(v) = Rtv / (1 + rv |v|)`) and its sd, when the data
    /// supports it (see [`fit_thermal`]); `None`: not in the model.
    pub rv: Option<(f64, f64)>,
    /// What the convection test found (the fitted rv with its sd and the residuals with and
    /// without it), for the result's note.
    pub convection_note: String,
}

impl ThermalFit {
    pub const NAMES: [&'static str; 4] = ["Rtv", "Ctv", "Rtm", "Ctm"];
}

struct Fit<'a> {
    tr: &'a ThermalTrack,
    /// theta carries `rv` (s/m) after the lag.
    convection: bool,
}

impl Fit<'_> {
    fn n_theta(&self) -> usize {
        if self.convection {
            6
        } else {
            5
        }
    }

    /// The tracked rise the model predicts: the coil rise `lag` seconds before each block end
    /// (theta `[ln Rtv, ln Ctv, ln Rtm, ln Ctm, lag (, rv)]`; the Re tracking follows the coil
    /// with a lag of a fraction of a second, which would otherwise read as heat capacity: Ctv
    /// 0.8 % high at 4.5 of its sds on SB17).
    fn tracked(&self, th: &[f64]) -> Vec<f64> {
        let rv = if self.convection { th[5] } else { 0.0 };
        let rise = self.rise(&th[..4], rv);
        let lag = th[4];
        let t = &self.tr.t;
        // Linear interpolation on the block ends (0 K at t = 0). The query times rise with k,
        // so the block they fall in only moves forward.
        let mut j = 0;
        (0..t.len())
            .map(|k| {
                let tq = t[k] - lag;
                while j < t.len() && t[j] < tq {
                    j += 1;
                }
                let (t0, r0) = if j == 0 { (0.0, 0.0) } else { (t[j - 1], rise[j - 1]) };
                let (t1, r1) = if j < t.len() { (t[j], rise[j]) } else { (t0, r0) };
                if t1 > t0 {
                    r0 + (r1 - r0) * (tq - t0) / (t1 - t0)
                } else {
                    r0
                }
            })
            .collect()
    }

    /// The coil rise at every block end for `[ln Rtv, ln Ctv, ln Rtm, ln Ctm]` and convection
    /// `rv`: the model's own network ([`ThermalModel`]) under the block's powers and mean
    /// speed, by its exact solution ([`HeldStep`]: one matrix exponential for every run of
    /// blocks of one length and speed, and no step-size limit where a trial point makes the
    /// coil's time constant short).
    fn rise(&self, th: &[f64], rv: f64) -> Vec<f64> {
        let [rtv, ctv, rtm, ctm] = [th[0].exp(), th[1].exp(), th[2].exp(), th[3].exp()];
        let m = ThermalModel::new(0.0, rtv, ctv, rtm, ctm, rv);
        let mut y = [0.0, 0.0];
        let mut t0 = 0.0;
        let mut step: Option<HeldStep> = None;
        let mut out = Vec::with_capacity(self.tr.t.len());
        for k in 0..self.tr.t.len() {
            let speed = if rv == 0.0 { 0.0 } else { self.tr.speed.get(k).copied().unwrap_or(0.0) };
            let h = self.tr.t[k] - t0;
            let s = match step {
                Some(s) if s.is_for(h, speed) => s,
                _ => *step.insert(HeldStep::new(&m, h, speed)),
            };
            y = s.apply(y, self.tr.pv[k], self.tr.pm[k]);
            t0 = self.tr.t[k];
            out.push(y[0]);
        }
        out
    }
}

impl Problem for Fit<'_> {
    fn residual(&self, th: &[f64]) -> DVector<f64> {
        let r = self.tracked(th);
        DVector::from_iterator(r.len(), r.iter().zip(&self.tr.dtv).map(|(a, b)| a - b))
    }

    fn residual_jacobian(&self, th: &[f64]) -> (DVector<f64>, DMatrix<f64>) {
        let r = self.residual(th);
        let mut j = DMatrix::zeros(r.len(), self.n_theta());
        for c in 0..self.n_theta() {
            let h = match c {
                0..=3 => 1e-6,
                4 => 1e-3,
                _ => 1e-4,
            };
            let mut tp = th.to_vec();
            tp[c] += h;
            let mut tm = th.to_vec();
            tm[c] -= h;
            let (a, b) = (self.tracked(&tp), self.tracked(&tm));
            for k in 0..r.len() {
                j[(k, c)] = (a[k] - b[k]) / (2.0 * h);
            }
        }
        (r, j)
    }
}

/// Fit the two-node model to `track` from `start` (`[Rtv, Ctv, Rtm, Ctm]`). `offset_sd` (K):
/// the sd of an offset of the whole tracked rise that the data cannot see, from the cold Re
/// it is referred to (`sd(Re_cold) / Re_cold / alpha`); it goes into the sds
/// ([`crate::large::with_nuisance`]): 0.025 K of offset under 3 W is 0.25 % of Rtv. Refused:
/// a track without heat (the coil rose by less than 1 K), or of fewer than 100 blocks.
pub fn fit_thermal(track: &ThermalTrack, start: [f64; 4], offset_sd: f64) -> Result<ThermalFit, String> {
    let n = track.t.len();
    if n < 100
        || track.dtv.len() != n
        || track.pv.len() != n
        || track.pm.len() != n
        || !(track.speed.is_empty() || track.speed.len() == n)
    {
        return Err(format!("the thermal track has {n} blocks (at least 100, with rise and powers for each)"));
    }
    let peak = track.dtv.iter().fold(0.0f64, |a, v| a.max(*v));
    if !(peak >= 1.0) {
        return Err(format!(
            "the voice coil rose by only {peak:.2} K: too little heat to fit the thermal model (play louder or longer)"
        ));
    }
    if start.iter().any(|v| !(*v > 0.0 && v.is_finite())) {
        return Err(format!("thermal start values {start:?} must be positive"));
    }
    let plain = fit_variant(track, start, offset_sd, None)?;
    // Convection, when the data supports it: the speed must change over the run (a fixed
    // level moves the coil at one speed, where rv only rescales Rtv), the fitted rv must
    // stand clear of zero (3 sd) and lower the residual by 5 % or more. (At a fixed level,
    // SB17 without convection: rv -0.67 +- 0.20 s/m at an unchanged residual: the sd of rv
    // alone is not a safe test where the speed hardly changes.)
    let speeds: Vec<f64> = track.speed.iter().copied().filter(|v| v.is_finite()).collect();
    let (lo, hi) = speeds.iter().fold((f64::INFINITY, 0.0f64), |a, &v| (a.0.min(v), a.1.max(v)));
    if speeds.len() < n || !(hi > 0.0) || hi < 1.5 * lo {
        let mut f = plain;
        f.convection_note = if speeds.is_empty() {
            "convection not tested: no speed track".into()
        } else {
            format!("convection not tested: the coil's mean speed stayed within {:.3} .. {:.3} m/s (a level schedule with a cooling phase tells it)", lo, hi)
        };
        return Ok(f);
    }
    // A convection fit the track cannot support (a singular covariance) leaves the plain fit.
    let with = match fit_variant(track, start, offset_sd, Some(&plain)) {
        Ok(w) => w,
        Err(e) => {
            let mut f = plain;
            f.convection_note = format!("convection not supported by the data (its fit: {e})");
            return Ok(f);
        }
    };
    let (rv, sd) = with.rv.expect("the convection variant fits rv");
    let supported = rv > 3.0 * sd && with.residual_k < 0.95 * plain.residual_k;
    let note = format!(
        "convection {}: rv {rv:.4} +- {sd:.4} s/m; the tracked rise's residual {:.4} K with it, {:.4} K without",
        if supported {
            "kept (rv above 3 sd, the residual 5 % or more lower)"
        } else {
            "not supported by the data (left out)"
        },
        with.residual_k,
        plain.residual_k
    );
    let mut f = if supported { with } else { ThermalFit { rv: None, ..plain } };
    f.convection_note = note;
    Ok(f)
}

/// One fit of [`fit_thermal`]: without convection (`from` `None`, multi-start), or with it
/// from the plain fit `from`.
fn fit_variant(
    track: &ThermalTrack,
    start: [f64; 4],
    offset_sd: f64,
    from: Option<&ThermalFit>,
) -> Result<ThermalFit, String> {
    let n = track.t.len();
    let peak = track.dtv.iter().fold(0.0f64, |a, v| a.max(*v));
    let prob = Fit { tr: track, convection: from.is_some() };
    let starts: Vec<Vec<f64>> = match from {
        Some(f) => {
            // The plain fit's Rtv is the mean of Rtv(v) over the run: start the resistance at
            // rest that much higher.
            let mean_speed = track.speed.iter().sum::<f64>() / n as f64;
            [0.0, 0.5, 2.0]
                .iter()
                .map(|&rv| {
                    let mut th: Vec<f64> = f.values.iter().map(|v| v.ln()).collect();
                    th[0] += (1.0 + rv * mean_speed).ln();
                    th.extend([f.lag_s, rv]);
                    th
                })
                .collect()
        }
        None => {
            // The valley of the magnet is long and flat (a run shorter than the magnet's
            // time constant barely bends its rise): from one start LM can slide along it to
            // Rtm -> inf (SB17, 10 min: Rtm 1e53 at twice the cost of the truth). Start also
            // from magnet time constants of 5, 15 and 50 minutes with the resistance split
            // 40/60 and 60/40, and keep the lowest cost.
            let r_total = start[0] + start[2];
            let mut starts = vec![start];
            for tau_m in [300.0, 900.0, 3000.0] {
                for share in [0.4, 0.6] {
                    let (rtv, rtm) = (share * r_total, (1.0 - share) * r_total);
                    starts.push([rtv, start[0] * start[1] / rtv, rtm, tau_m / rtm]);
                }
            }
            starts.iter().map(|st| st.iter().map(|v| v.ln()).chain([0.5]).collect()).collect()
        }
    };
    let mut best: Option<LmState> = None;
    for st in starts {
        let mut s = LmState::new(&prob, st);
        for _ in 0..100 {
            s = lm_step(&prob, &s);
            if s.converged || s.last_decrease < 1e-10 {
                break;
            }
        }
        if best.as_ref().is_none_or(|b| s.cost < b.cost) {
            best = Some(s);
        }
    }
    let s = best.expect("at least one start");
    let (r, j) = prob.residual_jacobian(&s.theta);
    let dt = (track.t[n - 1] - track.t[0]) / (n - 1) as f64;
    let cluster = ((COVARIANCE_BLOCK_S / dt.max(1e-9)) as usize).max(1);
    let cov = crate::lm::sandwich_covariance(&j, &r, cluster)
        .ok_or("the thermal fit's covariance is singular: the track does not tell the parameters apart")?;
    // An offset of the tracked rise adds to it: the residual moves by -1 per kelvin.
    let cov = if offset_sd > 0.0 {
        crate::large::with_nuisance(cov, &j, &DVector::from_element(n, -1.0), offset_sd)
    } else {
        cov
    };
    let values: [f64; 4] = std::array::from_fn(|k| s.theta[k].exp());
    // sd of exp(theta) to first order.
    let sd: [f64; 4] = std::array::from_fn(|k| values[k] * crate::lm::sd_from_variance(cov[(k, k)]));
    let rv = prob.convection.then(|| (s.theta[5], crate::lm::sd_from_variance(cov[(5, 5)])));
    Ok(ThermalFit {
        values,
        sd,
        lag_s: s.theta[4],
        lag_sd: crate::lm::sd_from_variance(cov[(4, 4)]),
        residual_k: (r.norm_squared() / n as f64).sqrt(),
        peak_k: peak,
        rv,
        convection_note: String::new(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The two-node model itself, simulated finely, with a noisy tracked rise: the fit finds it.
    #[test]
    fn the_fit_recovers_a_simulated_two_node_network() {
        let truth = [2.5, 6.0, 1.5, 1000.0];
        let dt = 0.1;
        let mut tr = ThermalTrack::default();
        // 10 minutes: 8 W into the coil, 1 W into the magnet, off for the last 2 minutes.
        for k in 1..=6000 {
            let t = k as f64 * dt;
            let on = t < 480.0;
            tr.t.push(t);
            tr.pv.push(if on { 8.0 } else { 0.0 });
            tr.pm.push(if on { 1.0 } else { 0.0 });
            tr.dtv.push(0.0);
        }
        let clean = Fit { tr: &tr, convection: false }.rise(&truth.map(f64::ln), 0.0);
        let mut rng = 12345u64;
        for (k, v) in clean.iter().enumerate() {
            // Deterministic small noise (0.05 K).
            rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let u = (rng >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
            // Tracked 0.3 s late.
            let late = if k >= 3 { clean[k - 3] } else { 0.0 };
            let _ = v;
            tr.dtv[k] = late + 0.05 * 3.46 * u;
        }
        let fit = fit_thermal(&tr, [3.0, 10.0, 3.0, 300.0], 0.0).unwrap();
        assert!((fit.lag_s - 0.3).abs() < 0.05, "lag {} +- {}", fit.lag_s, fit.lag_sd);
        for k in 0..4 {
            let z = (fit.values[k] - truth[k]).abs() / fit.sd[k];
            assert!(
                (fit.values[k] / truth[k] - 1.0).abs() < 0.05 && z < 4.0,
                "{}: {} +- {} (true {})",
                ThermalFit::NAMES[k],
                fit.values[k],
                fit.sd[k],
                truth[k]
            );
        }
        assert!(fit_thermal(
            &ThermalTrack {
                dtv: vec![0.1; 200],
                t: (0..200).map(|k| k as f64).collect(),
                pv: vec![0.0; 200],
                pm: vec![0.0; 200],
                speed: vec![]
            },
            truth,
            0.0
        )
        .unwrap_err()
        .contains("too little heat"));
    }
}

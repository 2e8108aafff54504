//! Checks that make a doubtful result loud: what a fit's residual says about the record.
//!
//! * [`noise_floor`]: the sensor-noise floor of a residual, estimated from the data alone.
//!   Sensor noise is white, model error is not: the Welch spectrum of the residual is flat at
//!   the noise floor except where the model misses something. The **median** bin over the
//!   band is the floor (robust against the bins the model misses); the **mean** is the whole
//!   residual. Their ratio says how far above the noise the fit ended.
//! * [`explained_share`]: how much of a residual given regressors explain (the linear fit
//!   uses it with the first-order effects of Bl(x), Kms(x) and Le(x) on the current, to tell
//!   a large-signal record from noise).
//!
//! [`Warning`]s name the likely cause and what to do; every command writes them to
//! `fit.warnings` and prints them.

use nalgebra::{DMatrix, DVector};
use realfft::RealFftPlanner;

pub use coilscope_core::result::{NoiseFloor, Warning};

/// The noise floor of `r` sampled at `fs`: Welch periodogram (Hann, 50 % overlap, about
/// 50 Hz resolution), the median of its bins from 0.02 to 0.45 fs taken as the white floor.
/// For chi-square distributed Welch bins with many averages the median is within a few
/// percent of the mean, so white noise gives a ratio near 1.
pub fn noise_floor(r: &[f64], _fs: f64) -> NoiseFloor {
    let n = r.len();
    let dc = r.iter().sum::<f64>() / n.max(1) as f64;
    let rms = (r.iter().map(|v| v * v).sum::<f64>() / n.max(1) as f64).sqrt();
    let seg = 1024usize.min(n.next_power_of_two() / 2).max(16);
    if n < 2 * seg {
        return NoiseFloor { rms, floor_rms: rms, ratio: 1.0, dc };
    }
    let mut planner = RealFftPlanner::<f64>::new();
    let fft = planner.plan_fft_forward(seg);
    let win: Vec<f64> = (0..seg).map(|k| 0.5 - 0.5 * (2.0 * std::f64::consts::PI * k as f64 / seg as f64).cos()).collect();
    let wss: f64 = win.iter().map(|w| w * w).sum();
    let mut psd = vec![0.0; seg / 2 + 1];
    let (mut buf, mut out) = (vec![0.0; seg], fft.make_output_vec());
    let mut count = 0;
    let mut start = 0;
    while start + seg <= n {
        for k in 0..seg {
            buf[k] = r[start + k] * win[k];
        }
        fft.process(&mut buf, &mut out).expect("lengths are consistent");
        for (p, c) in psd.iter_mut().zip(out.iter()) {
            *p += c.norm_sqr();
        }
        count += 1;
        start += seg / 2;
    }
    // One-sided power per bin such that the sum over bins 1..seg/2 is the mean square.
    let norm = 2.0 / (count as f64 * wss * seg as f64);
    let lo = (0.02 * seg as f64) as usize;
    let hi = (0.45 * seg as f64) as usize;
    let median = median(psd[lo.max(1)..hi].iter().map(|p| p * norm).collect());
    // White noise: every one of the seg/2 bins holds `median`.
    let floor_rms = (median * (seg / 2) as f64).sqrt().max(1e-300);
    NoiseFloor { rms, floor_rms, ratio: rms / floor_rms, dc }
}

/// The median of `v` (the upper one of an even count; `v` not empty).
pub(crate) fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Ratio of the residual to its floor above which a fit is said not to describe the record.
pub const RESIDUAL_RATIO_WARN: f64 = 3.0;

/// Warnings about a current residual `r` (A) of a fit: far above its noise floor, and a DC
/// offset on the current channel when that is what the excess is. `what` names the fit in
/// the message. An excess over the floor smaller than `min_excess` (relative to `i_rms`) is
/// not material: a linear fit of a record at 0.3 mm sees the nonlinearities above 70 dB of
/// noise, yet its parameters are within 0.25 %.
pub fn residual_warnings(r: &[f64], fs: f64, what: &str, i_rms: f64, min_excess: f64) -> (NoiseFloor, Vec<Warning>) {
    let nf = noise_floor(r, fs);
    let mut w = Vec::new();
    let excess = (nf.rms.powi(2) - nf.floor_rms.powi(2)).max(0.0).sqrt() / i_rms.max(1e-300);
    if excess < min_excess {
        return (nf, w);
    }
    if nf.dc.abs() > 0.5 * nf.rms && nf.dc.abs() > 3.0 * nf.floor_rms {
        w.push(Warning::new(
            "dc-offset-current",
            format!(
                "the current channel carries a DC offset of {:.3e} A that no driver model makes ({:.0} % of the residual): re-zero the interface, use an AC-coupled current input, or high-pass channel 2 before fitting",
                nf.dc,
                100.0 * nf.dc.powi(2) / nf.rms.powi(2)
            ),
        ));
    }
    if nf.ratio > RESIDUAL_RATIO_WARN {
        w.push(Warning::new(
            "residual-above-noise",
            format!(
                "the {what} leaves a current error {:.1} times its noise floor (residual {:.3e} A rms, floor {:.3e} A rms): the model does not describe this record. Likely causes: a wiring or channel problem (inverted, delayed or offset current), a recording chain that AC-couples or skews the channels, or a driver with effects the model lacks (creep, a second eddy-current branch)",
                nf.ratio, nf.rms, nf.floor_rms
            ),
        ));
    }
    (nf, w)
}

/// Share (0..1) of the power of `r` that a least-squares combination of `regressors`
/// explains (each regressor as long as `r`; at most 40 000 rows are used).
pub fn explained_share(r: &[f64], regressors: &[Vec<f64>]) -> f64 {
    let n = regressors.iter().map(|g| g.len()).fold(r.len(), usize::min);
    if n < 100 || regressors.is_empty() {
        return 0.0;
    }
    let step = (n / 40_000).max(1);
    let rows: Vec<usize> = (0..n).step_by(step).collect();
    let scale: Vec<f64> = regressors.iter().map(|g| g.iter().fold(0.0f64, |a, v| a.max(v.abs())).max(1e-300)).collect();
    let a = DMatrix::from_fn(rows.len(), regressors.len(), |k, c| regressors[c][rows[k]] / scale[c]);
    let b = DVector::from_fn(rows.len(), |k, _| r[rows[k]]);
    let total = b.norm_squared();
    if total <= 0.0 {
        return 0.0;
    }
    match a.clone().svd(true, true).solve(&b, 1e-12) {
        Ok(sol) => (1.0 - (&a * sol - &b).norm_squared() / total).clamp(0.0, 1.0),
        Err(_) => 0.0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use coilscope_core::excitation::named_rng;
    use rand::Rng;
    use rand_distr::StandardNormal;

    fn white(n: usize, sd: f64, seed: u64) -> Vec<f64> {
        let mut rng = named_rng(seed, "checks/white");
        (0..n).map(|_| sd * rng.sample::<f64, _>(StandardNormal)).collect()
    }

    #[test]
    fn white_noise_sits_at_its_floor() {
        for seed in 1..6 {
            let r = white(96_000, 1e-4, seed);
            let nf = noise_floor(&r, 48000.0);
            assert!((nf.ratio - 1.0).abs() < 0.1, "seed {seed}: ratio {}", nf.ratio);
            assert!((nf.floor_rms / 1e-4 - 1.0).abs() < 0.1, "seed {seed}: floor {}", nf.floor_rms);
            let (_, w) = residual_warnings(&r, 48000.0, "test fit", 1.0, 0.0);
            assert!(w.is_empty(), "{w:?}");
        }
    }

    #[test]
    fn a_low_frequency_model_error_and_a_dc_offset_are_named() {
        let fs = 48000.0;
        let mut r = white(96_000, 1e-4, 7);
        // A model error at 40 Hz, ten times the noise.
        for (k, v) in r.iter_mut().enumerate() {
            *v += 1.4e-3 * (2.0 * std::f64::consts::PI * 40.0 * k as f64 / fs).sin();
        }
        let (nf, w) = residual_warnings(&r, fs, "test fit", 1.0, 0.0);
        assert!(nf.ratio > 5.0, "{}", nf.ratio);
        assert!(w.iter().any(|w| w.code == "residual-above-noise"), "{w:?}");
        let r: Vec<f64> = white(96_000, 1e-4, 8).iter().map(|v| v + 2e-3).collect();
        let (_, w) = residual_warnings(&r, fs, "test fit", 1.0, 0.0);
        assert!(w.iter().any(|w| w.code == "dc-offset-current" && w.message.contains("2.000e-3")), "{w:?}");
    }

    #[test]
    fn the_explained_share_tells_noise_from_a_modelled_error() {
        let n = 48_000;
        let g: Vec<f64> = (0..n).map(|k| (k as f64 * 0.003).sin() * (k as f64 * 0.011).sin()).collect();
        let noise = white(n, 1e-3, 3);
        assert!(explained_share(&noise, std::slice::from_ref(&g)) < 0.01);
        let r: Vec<f64> = (0..n).map(|k| 0.01 * g[k] + noise[k]).collect();
        assert!(explained_share(&r, &[g]) > 0.9);
    }
}

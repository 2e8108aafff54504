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

/// The Welch periodogram of `r` (Hann, 50 % overlap, segments of 1024 samples, about 50 Hz
/// at 48 kHz): its bins from 0.02 to 0.45 fs as the power each would give the mean square if
/// every one of the `seg / 2` bins held it, sorted, and the number of segments averaged.
/// `None` for a record shorter than two segments.
fn welch_levels(r: &[f64]) -> Option<(Vec<f64>, usize)> {
    let n = r.len();
    let seg = 1024usize.min(n.next_power_of_two() / 2).max(16);
    if n < 2 * seg {
        return None;
    }
    let mut planner = RealFftPlanner::<f64>::new();
    let fft = planner.plan_fft_forward(seg);
    let win: Vec<f64> =
        (0..seg).map(|k| 0.5 - 0.5 * (2.0 * std::f64::consts::PI * k as f64 / seg as f64).cos()).collect();
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
    // One-sided power per bin such that the sum over bins 1..seg/2 is the mean square; times
    // seg/2: the mean square of white noise at that bin's level.
    let norm = 2.0 / (count as f64 * wss * seg as f64) * (seg / 2) as f64;
    let lo = (0.02 * seg as f64) as usize;
    let hi = (0.45 * seg as f64) as usize;
    let mut levels: Vec<f64> = psd[lo.max(1)..hi].iter().map(|p| p * norm).collect();
    levels.sort_by(f64::total_cmp);
    Some((levels, count))
}

/// The noise floor of `r` sampled at `fs`: Welch periodogram (Hann, 50 % overlap, about
/// 50 Hz resolution), the median of its bins from 0.02 to 0.45 fs taken as the white floor.
/// For chi-square distributed Welch bins with many averages the median is within a few
/// percent of the mean, so white noise gives a ratio near 1.
pub fn noise_floor(r: &[f64], _fs: f64) -> NoiseFloor {
    let n = r.len();
    let dc = r.iter().sum::<f64>() / n.max(1) as f64;
    let rms = (r.iter().map(|v| v * v).sum::<f64>() / n.max(1) as f64).sqrt();
    let Some((levels, _)) = welch_levels(r) else {
        return NoiseFloor { rms, floor_rms: rms, ratio: 1.0, dc };
    };
    let floor_rms = levels[levels.len() / 2].sqrt().max(1e-300);
    NoiseFloor { rms, floor_rms, ratio: rms / floor_rms, dc }
}

/// The floor of the quietest quarter of the band: the 25th percentile of the Welch bins
/// (as [`noise_floor`]'s), divided by where that percentile of white noise lies below its
/// mean (`1 - 0.674 sqrt(2 / nu)`, `nu` about 1.9 degrees of freedom per segment with Hann
/// windows at 50 % overlap). White noise gives the median's floor; a model error spread over
/// more than half the band raises the median, not this (a microspeaker fitted without its
/// LR-3 branch: the median said 2.4 times the floor, this 4.3).
pub fn quiet_floor_rms(r: &[f64]) -> Option<f64> {
    let (levels, count) = welch_levels(r)?;
    let nu = 1.9 * count as f64;
    let below = (1.0 - 0.674 * (2.0 / nu).sqrt()).max(0.2);
    Some((levels[levels.len() / 4] / below).sqrt().max(1e-300))
}

/// The median of `v` (the upper one of an even count; `v` not empty).
pub(crate) fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// How far (in RMS) the quietest quarter of a residual's band must lie below its median for
/// [`residual_warnings`] to take it as the floor: white noise puts them within a few percent.
pub const QUIET_FLOOR_GAP: f64 = 1.5;

/// Ratio of the residual to its floor above which a fit is said not to describe the record.
pub const RESIDUAL_RATIO_WARN: f64 = 3.0;

/// Warnings about a current residual `r` (A) of a fit: far above its noise floor, and a DC
/// offset on the current channel when that is what the excess is. `what` names the fit in
/// the message. An excess over the floor smaller than `min_excess` (relative to `i_rms`) is
/// not material: a linear fit of a record at 0.3 mm sees the nonlinearities above 70 dB of
/// noise, yet its parameters are within 0.25 %.
pub fn residual_warnings(r: &[f64], fs: f64, what: &str, i_rms: f64, min_excess: f64) -> (NoiseFloor, Vec<Warning>) {
    let mut nf = noise_floor(r, fs);
    // Where the quietest quarter of the band lies well below the median, the model's own
    // error fills most of the band: the quiet quarter is the floor.
    if let Some(q) = quiet_floor_rms(r).filter(|q| *q < nf.floor_rms / QUIET_FLOOR_GAP) {
        nf.floor_rms = q;
        nf.ratio = nf.rms / q;
    }
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

/// Share of a fit's current error that a skew of the current channel explains, above which
/// the channels are said to be skewed ([`residual_delay`]).
pub const DELAY_SHARE_WARN: f64 = 0.3;

/// A skew of the current channel seen in a time-domain fit's error `r` = recorded -
/// modelled current, `i_model` the model's current on the same samples: a current recorded
/// `tau` samples late is `i(n - tau) ~ i(n) - tau i'(n)`, so the error holds `-tau i'(n)`
/// (the model's parameters take some of it: what they could not is what is left). Returns
/// `(tau, share)`, tau in samples (positive: late) and the share of the error's power that
/// the shift explains, when that share is [`DELAY_SHARE_WARN`] or more and the shift at
/// least 0.02 sample.
///
/// `identify` looks at its final error with this when the chain is not estimated: on a
/// large-signal record the small-signal check ([`crate::linear::LinearFit::current_delay`])
/// is blind, because the driver's nonlinearity dominates the linear model's error (SB17 at
/// 4.4 mm with the current 0.5 sample late: 7.8 % current error, Re 1.9 %, Bl 1.4 % and Le
/// 35 % off, and no warning before).
pub fn residual_delay(r: &[f64], i_model: &[f64]) -> Option<(f64, f64)> {
    let n = r.len().min(i_model.len());
    if n < 3 {
        return None;
    }
    let (mut rd, mut dd, mut rr) = (0.0, 0.0, 0.0);
    for k in 1..n - 1 {
        let d = 0.5 * (i_model[k + 1] - i_model[k - 1]);
        rd += r[k] * d;
        dd += d * d;
        rr += r[k] * r[k];
    }
    if dd <= 0.0 || rr <= 0.0 {
        return None;
    }
    let tau = -rd / dd;
    let share = rd * rd / (dd * rr);
    (share >= DELAY_SHARE_WARN && tau.abs() >= 0.02).then_some((tau, share))
}

/// [`drive_explained_ratio`] at or above which a fit's error is said to follow the drive:
/// a third of the error's power explained by the drive, a misfit 0.7 times the noise. Fits
/// that describe their record measured 1.000-1.008 (our records and the independent ones,
/// with the chain and the effects chosen).
pub const DRIVE_RATIO_WARN: f64 = 1.2;

/// A time-domain fit's error that follows the drive: the model misses something the drive
/// makes (a skewed or AC-coupled channel, an effect the model lacks), even when the error's
/// spectrum looks flat. [`noise_floor`] takes the median of the error's spectrum as its
/// floor, which a broadband misfit lifts with it: SB17's independent record through a real
/// chain fitted without the chain leaves 6.3 % of the current (0.035 A) against a "floor"
/// of 0.013 A, ratio 2.6, under [`RESIDUAL_RATIO_WARN`], and no warning was given.
///
/// Regresses `r` (recorded - modelled current) on what the fitted model knows: its current
/// and the voltage at lags -4..=4 samples (any short linear filter of them: a skew, a
/// mis-fitted inductance), their low-passes at 2 and 20 Hz (AC coupling, creep, a slow
/// eddy-current branch), a constant and a ramp (offsets), and the shapes of the missing
/// nonlinear effects (i^3 and i^2 i' for Le(i), v^3 for Rms(v), x i and x^2 i). Returns
/// `sqrt(power of r / power of what is left)`: about 1 for noise (the voltage channel's own
/// noise reaches `r` through the model, but its share of the voltage is far too small for
/// one coefficient per regressor to single it out: 1.000 on our 70 dB records). Warn at
/// [`DRIVE_RATIO_WARN`].
pub fn drive_explained_ratio(r: &[f64], u: &[f64], i_model: &[f64], x_model: &[f64], fs: f64) -> f64 {
    let n = [r.len(), u.len(), i_model.len(), x_model.len()].into_iter().min().unwrap_or(0);
    const L: usize = 4;
    if n < 100 + 2 * L {
        return 1.0;
    }
    let m = n - 2 * L;
    let at =
        |s: &[f64], lag: isize| -> Vec<f64> { (0..m).map(|k| s[(k as isize + L as isize + lag) as usize]).collect() };
    let mut g: Vec<Vec<f64>> = Vec::new();
    for lag in -(L as isize)..=(L as isize) {
        g.push(at(i_model, lag));
        g.push(at(u, lag));
    }
    let i0 = at(i_model, 0);
    let di: Vec<f64> = (0..m).map(|k| 0.5 * (i_model[k + L + 1] - i_model[k + L - 1])).collect();
    let x0 = at(x_model, 0);
    let v: Vec<f64> = (0..m).map(|k| 0.5 * fs * (x_model[k + L + 1] - x_model[k + L - 1])).collect();
    g.push(vec![1.0; m]);
    g.push((0..m).map(|k| k as f64 / m as f64).collect());
    g.push(i0.iter().map(|a| a * a * a).collect());
    g.push(i0.iter().zip(&di).map(|(a, d)| a * a * d).collect());
    g.push(v.iter().map(|a| a * a * a).collect());
    g.push(x0.iter().zip(&i0).map(|(x, a)| x * a).collect());
    g.push(x0.iter().zip(&i0).map(|(x, a)| x * x * a).collect());
    // The slow misfits (AC coupling, creep, a slow eddy-current branch) are far longer than
    // the lags: leaky integrals of the current and the voltage (first-order low-passes at 2
    // and 20 Hz).
    for fc in [2.0, 20.0] {
        let a = (-2.0 * std::f64::consts::PI * fc / fs).exp();
        for s in [i_model, u] {
            let mut y = 0.0;
            let full: Vec<f64> = s[..n]
                .iter()
                .map(|v| {
                    y = a * y + (1.0 - a) * v;
                    y
                })
                .collect();
            g.push(full[L..L + m].to_vec());
        }
    }
    let share = explained_share(&r[L..L + m], &g);
    (1.0 / (1.0 - share).max(1e-12)).sqrt()
}

/// The `residual-follows-drive` warning of the time-domain fit `what` (`r` = recorded -
/// modelled current, on the samples of `u`, `i_model` and `x_model`): when
/// [`drive_explained_ratio`] reaches [`DRIVE_RATIO_WARN`] and the misfit it explains is at
/// least `min_misfit` of the current's RMS `i_rms` (`linear` asks for its material 0.5 %).
pub fn drive_warning(
    r: &[f64],
    u: &[f64],
    i_model: &[f64],
    x_model: &[f64],
    fs: f64,
    what: &str,
    i_rms: f64,
    min_misfit: f64,
) -> Option<Warning> {
    let ratio = drive_explained_ratio(r, u, i_model, x_model, fs);
    let rms = (r.iter().map(|v| v * v).sum::<f64>() / r.len().max(1) as f64).sqrt();
    let misfit = rms * (1.0 - 1.0 / (ratio * ratio)).max(0.0).sqrt() / i_rms.max(1e-300);
    (ratio >= DRIVE_RATIO_WARN && misfit >= min_misfit).then(|| {
        Warning::new(
            "residual-follows-drive",
            format!(
                "{:.2} % of the current is a misfit of the {what} that follows the drive, not noise (its error is {ratio:.2} times what is left once the drive and the model's own current explain what they can; the median of its spectrum, taken as the noise floor, rises with such a misfit and hides it): the model does not describe this record. Likely causes: a recording chain that AC-couples or skews the channels (--chain auto, or calibrate the card and give --chain FILE), a DC offset, a large-signal record fitted as linear (coilscope identify), or effects the model lacks (--effects auto)",
                100.0 * misfit
            ),
        )
    })
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
    fn a_model_error_over_most_of_the_band_is_measured_from_its_quiet_quarter() {
        let fs = 48000.0;
        // White noise: the quiet quarter's floor is the median's, and the result unchanged.
        for seed in 1..4 {
            let r = white(96_000, 1e-4, seed);
            let q = quiet_floor_rms(&r).unwrap();
            assert!((q / noise_floor(&r, fs).floor_rms - 1.0).abs() < 0.05, "seed {seed}: {q}");
        }
        // Noise plus an error over 1-14 kHz (three fifths of the band the floor is read in),
        // 600 tones three times the noise in all: the median bin lies in the error, the quiet
        // quarter does not.
        let mut r = white(96_000, 1e-4, 9);
        let (tones, a) = (600, 3e-4 * (2.0f64 / 600.0).sqrt());
        for t in 0..tones {
            let f = 1000.0 + 13000.0 * t as f64 / tones as f64;
            let phase = 2.0 * std::f64::consts::PI * ((t * 7919) % 1000) as f64 / 1000.0;
            for (k, v) in r.iter_mut().enumerate() {
                *v += a * (2.0 * std::f64::consts::PI * f * k as f64 / fs + phase).sin();
            }
        }
        let median_ratio = noise_floor(&r, fs).ratio;
        let (nf, w) = residual_warnings(&r, fs, "test fit", 1.0, 0.0);
        assert!(median_ratio < RESIDUAL_RATIO_WARN, "the median alone {median_ratio:.2}");
        assert!(nf.ratio > RESIDUAL_RATIO_WARN && (nf.floor_rms / 1e-4 - 1.0).abs() < 0.15, "{nf:?}");
        assert!(w.iter().any(|w| w.code == "residual-above-noise"), "{w:?}");
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

    /// A band-limited "current" (sum of tones up to 5 kHz) and its copy `tau` samples late
    /// (exact for the tones), with noise of 1e-3 of it.
    fn tones(n: usize, fs: f64, tau: f64) -> Vec<f64> {
        let f = [37.0, 113.0, 421.0, 1290.0, 4870.0];
        (0..n)
            .map(|k| {
                f.iter()
                    .enumerate()
                    .map(|(j, f)| (2.0 * std::f64::consts::PI * f * (k as f64 - tau) / fs + j as f64).sin())
                    .sum()
            })
            .collect()
    }

    #[test]
    fn a_skew_in_the_error_is_found_with_its_sign_and_noise_is_not() {
        let (n, fs) = (48_000, 48000.0);
        let model = tones(n, fs, 0.0);
        for (seed, tau) in [(1u64, 0.3), (2, -0.2), (3, 0.05)] {
            let noise = white(n, 1e-3, seed);
            let rec: Vec<f64> = tones(n, fs, tau).iter().zip(&noise).map(|(a, b)| a + b).collect();
            let r: Vec<f64> = rec.iter().zip(&model).map(|(a, b)| a - b).collect();
            let (got, share) =
                residual_delay(&r, &model).unwrap_or_else(|| panic!("seed {seed}: a skew of {tau} not found"));
            // First order in tau, with a central difference for i': within 10 % (6 % here,
            // the 4.9 kHz tone's difference is 7 % short of its derivative).
            assert!((got - tau).abs() < 0.1 * tau.abs() + 2e-3, "seed {seed}: {got} for {tau}");
            assert!(share > 0.5, "seed {seed}: {share}");
            assert!(residual_delay(&noise, &model).is_none(), "seed {seed}: noise called a skew");
        }
    }

    #[test]
    fn an_error_that_follows_the_drive_is_told_from_noise() {
        let (n, fs) = (48_000, 48000.0);
        let i = tones(n, fs, 0.0);
        let u: Vec<f64> = i.iter().map(|v| 4.0 * v).collect();
        let x: Vec<f64> = tones(n, fs, 7.0).iter().map(|v| 1e-3 * v).collect();
        for seed in 1..4u64 {
            let noise = white(n, 1e-3, seed);
            let ratio = drive_explained_ratio(&noise, &u, &i, &x, fs);
            assert!(ratio < 1.01, "seed {seed}: noise gives {ratio}");
            // An AC coupling left in the current: its first-order high-pass at 3 Hz removes
            // i's low-passed part, 30 times the noise.
            let a = (-2.0 * std::f64::consts::PI * 3.0 / fs).exp();
            let mut lp = 0.0;
            let r: Vec<f64> = i
                .iter()
                .zip(&noise)
                .map(|(v, e)| {
                    lp = a * lp + (1.0 - a) * v;
                    e - lp
                })
                .collect();
            let ratio = drive_explained_ratio(&r, &u, &i, &x, fs);
            assert!(ratio > 3.0, "seed {seed}: an AC coupling gives {ratio}");
            // Le(i) left out: i^2 i', at the noise's level.
            let r: Vec<f64> = (0..n)
                .map(|k| noise[k] + if k > 0 && k + 1 < n { 2e-2 * i[k] * i[k] * (i[k + 1] - i[k - 1]) } else { 0.0 })
                .collect();
            let ratio = drive_explained_ratio(&r, &u, &i, &x, fs);
            assert!(ratio > DRIVE_RATIO_WARN, "seed {seed}: Le(i) left out gives {ratio}");
        }
    }
}

//! The recording chain in the small-signal fit: what a sound card adds (skew, AC coupling,
//! offsets, mains hum), the checks that refuse a record it spoils, and the chain's estimate.

use super::*;

/// The chain quantities a linear fit estimated: `[delay_i samples, hp_u Hz, hp_i Hz]`, their
/// sds, and which the data asked for (the others held at 0).
#[derive(Clone, Debug, PartialEq)]
pub struct ChainEstimate {
    pub values: [f64; 3],
    pub sd: [f64; 3],
    pub on: [bool; 3],
    /// Sample rate of the record (Hz).
    pub fs: f64,
}

/// A chain quantity is kept when its estimate is this many sds from 0 (and a corner comes out
/// positive); otherwise it is held at 0 and the fit repeated.
pub const CHAIN_SIGNIFICANCE: f64 = 4.0;

/// Smallest delay (samples) and corners (Hz) a fit keeps: below these a chain quantity
/// changes nothing a driver's parameters depend on (a 0.005-sample delay turns the phase at
/// 10 kHz by 0.4 degrees), however precisely it is measured.
pub const CHAIN_MIN: [f64; 3] = [0.005, 0.05, 0.05];

/// Mains hum's lines: the bins within this many Hz of a harmonic of 50 or 60 Hz (up to
/// [`HUM_HARMONICS`]) are left out of a fit that estimates the chain.
pub const HUM_GUARD_HZ: f64 = 0.75;
pub const HUM_HARMONICS: usize = 6;

/// The mains lines (Hz): the harmonics of 50 Hz, then those of 60 Hz not among them (300 Hz
/// is a line of both), up to [`HUM_HARMONICS`].
pub fn mains_lines() -> Vec<f64> {
    let mut lines: Vec<f64> = vec![];
    for mains in [50.0, 60.0] {
        for k in 1..=HUM_HARMONICS {
            let f = mains * k as f64;
            if !lines.contains(&f) {
                lines.push(f);
            }
        }
    }
    lines
}

/// Mains hum between the channels: in the current the voltage does not explain, `E = I -
/// U / Z` (whole-record DFT, `Z` the H1 estimate), so that the excitation, which fills the
/// bins around a line in either channel alone, is taken out and the hum stands against the
/// noise. Hum on the current channel shows in `E` as itself, hum on the voltage channel as
/// `-hum / Z`. Returns the strongest line `(Hz, amplitude relative to the current's RMS,
/// dB above the median of E's bins 2 to 10 Hz away)`; the amplitude is 0 for a line less
/// than 10 dB above its neighbourhood. `None` for a record too short to resolve the lines.
pub fn mains_hum(u: &[f64], i: &[f64], fs: f64) -> Option<(f64, f64, f64)> {
    let n = u.len();
    let df = fs / n as f64;
    if df > 0.5 || n != i.len() {
        return None;
    }
    let h1 = h1_impedance(u, i, fs, segment_length(n, fs));
    let (us, is) = (rfft(u), rfft(i));
    let total: f64 = is.iter().skip(1).map(|c| c.norm_sqr()).sum();
    if total <= 0.0 {
        return None;
    }
    let e = |k: usize| -> f64 {
        let z = h1.z[h1.bin(k as f64 * df)];
        if z.norm() > 0.0 && z.is_finite() {
            (is[k] - us[k] / z).norm_sqr()
        } else {
            is[k].norm_sqr()
        }
    };
    let bin = |f: f64| (f / df).round() as usize;
    mains_lines()
        .into_iter()
        .filter(|&f| bin(f + 10.0) < is.len())
        .map(|f| {
            // The line's power over +-2 bins (a line between bins leaks into its neighbours).
            let (k0, k1) = (bin(f).saturating_sub(2), bin(f) + 2);
            let p_line: f64 = (k0..=k1).map(e).sum();
            let neigh: Vec<f64> =
                (bin(f - 10.0)..=bin(f + 10.0)).filter(|&k| (k as f64 * df - f).abs() >= 2.0).map(e).collect();
            let floor = crate::checks::median(neigh).max(1e-300) * 5.0;
            let db = 10.0 * (p_line / floor).log10();
            let rel = if db > 10.0 { ((p_line - floor) / total).sqrt() } else { 0.0 };
            (f, rel, db)
        })
        .max_by(|a, b| a.1.total_cmp(&b.1))
}

/// A channel's mean, relative to its RMS, above which [`chain_signs`] names an offset. A
/// driver's current and voltage have next to no mean over a record of a zero-mean drive (the
/// current at DC is the voltage's over Re, and the cone ends where it started): drawn
/// drivers with Le(i), Rms(v) and 40 K of heating left up to 0.2 % of the current's RMS. An
/// offset below this is left to the fit's own checks (`dc-offset-current`).
pub const OFFSET_SIGN: f64 = 5e-3;

/// What a measurement chain leaves in a record that shows without a fit: mains hum standing
/// out of the current's error ([`mains_hum`]), and a mean on either channel above
/// [`OFFSET_SIGN`] of its RMS. One sentence per sign (empty: none). The skew and AC coupling
/// need the driver's model: the fit looks for them (`IdentifyOptions::detect_chain`).
pub fn chain_signs(u: &[f64], i: &[f64], fs: f64) -> Vec<String> {
    let mut signs = vec![];
    if let Some((f, rel, db)) = mains_hum(u, i, fs) {
        if rel > 0.0 {
            signs.push(format!(
                "mains hum at {f:.0} Hz ({:.2} % of the current's RMS, {db:.0} dB above the noise next to it)",
                100.0 * rel
            ));
        }
    }
    for (name, x, unit) in [("voltage", u, "V"), ("current", i, "A")] {
        let r = rms(x);
        let mean = x.iter().sum::<f64>() / x.len().max(1) as f64;
        if r > 0.0 && mean.abs() > OFFSET_SIGN * r {
            signs.push(format!(
                "an offset of {mean:.3e} {unit} on the {name} channel ({:.2} % of its RMS)",
                100.0 * mean.abs() / r
            ));
        }
    }
    signs
}

/// The voltage record of a `driver+shunt` wiring made into that of a `terminals` wiring: the
/// shunt's drop as the voltage channel recorded it taken out
/// ([`coilscope_core::chain::Chain::remove_shunt_drop`]), through `chain` when it is known
/// (ideal or calibrated), or through the chain estimated here (`None`): a linear fit of the
/// record as it is, with the chain estimated, in which the shunt is simply part of Re (the
/// delay, the corners and the gain do not depend on it). A `terminals` wiring is returned as
/// it is.
pub fn remove_shunt_drop(
    u_rec: &[f64],
    i_rec: &[f64],
    fs: f64,
    wiring: coilscope_core::chain::SenseWiring,
    chain: Option<&coilscope_core::chain::Chain>,
    origin: &str,
) -> Result<Vec<f64>, String> {
    let rs = wiring.series_ohm();
    if rs == 0.0 {
        return Ok(u_rec.to_vec());
    }
    let estimated;
    let c = match chain {
        Some(c) => c,
        None => {
            let opts = LinearOptions { chain: true, ..Default::default() };
            let fit = fit_linear_record(u_rec, i_rec, fs, origin, &opts, |_| {})?;
            estimated = fit.chain.as_ref().map(|c| c.to_chain()).unwrap_or_default();
            &estimated
        }
    };
    Ok(c.remove_shunt_drop(u_rec, i_rec, rs, fs))
}

/// Hum above which a channel is refused even when the chain is estimated (its relative
/// amplitude: -20 dB of the channel); without the chain, hum above [`HUM_REFUSED_IDEAL`]
/// (-40 dB: 3 % on a 4 s SB17 record left a residual 13x the noise floor) is refused with
/// the advice to estimate it.
pub const HUM_REFUSED: f64 = 0.1;
pub const HUM_REFUSED_IDEAL: f64 = 0.01;

/// Refuse a record whose hum would dominate the fit: see [`HUM_REFUSED`].
pub fn check_hum(u: &[f64], i: &[f64], fs: f64, chain_estimated: bool, origin: &str) -> Result<(), String> {
    if let Some((f, rel, db)) = mains_hum(u, i, fs) {
        let what = format!("{origin}: mains hum at {f:.0} Hz between the channels (on the current, or on the voltage through the driver) is {:.1} % of the current's RMS, {db:.0} dB above the noise next to it", 100.0 * rel);
        if rel > HUM_REFUSED {
            return Err(format!("{what}: far above the noise floor, it would dominate any fit. Fix the ground loop (one ground point, a balanced input, the shunt's ground at the card)"));
        }
        if !chain_estimated && rel > HUM_REFUSED_IDEAL {
            return Err(format!("{what}: fix the ground loop, or let the fit take the hum with --chain auto"));
        }
    }
    Ok(())
}

/// The current channel carries the voltage (or the load is a resistor): `U/I` flat in
/// magnitude (within 2 % between its 5th and 95th percentiles) and in phase (within 1
/// degree) over the coherent band, which no loudspeaker's impedance is.
pub(super) fn current_is_voltage(h1: &ImpedanceEstimate, bins: &[usize]) -> Option<(f64, f64)> {
    let mut mags: Vec<f64> = bins.iter().map(|&k| h1.z[k].norm()).collect();
    mags.sort_by(f64::total_cmp);
    let (lo, hi) = (mags[mags.len() / 20], mags[mags.len() * 19 / 20]);
    let phase = bins.iter().map(|&k| h1.z[k].arg().abs()).fold(0.0, f64::max).to_degrees();
    (hi / lo < 1.02 && phase < 1.0).then(|| (crate::checks::median(mags), phase))
}

/// True when `f` (Hz) is within [`HUM_GUARD_HZ`] of a mains line.
pub fn near_hum(f: f64) -> bool {
    mains_lines().iter().any(|m| (f - m).abs() <= HUM_GUARD_HZ)
}

impl ChainEstimate {
    /// As a result's `chain` (the delay in s at sample rate `fs`).
    pub fn to_chain(&self) -> coilscope_core::chain::Chain {
        let fs = self.fs;
        let mut c = coilscope_core::chain::Chain {
            source: Some("estimated".into()),
            delay_i: self.values[0] / fs,
            hp_u: self.values[1],
            hp_i: self.values[2],
            ..Default::default()
        };
        for (n, key) in ChainTerms::NAMES.iter().enumerate() {
            if self.on[n] {
                c.sd.insert(key.to_string(), if n == 0 { self.sd[0] / fs } else { self.sd[n] });
                c.fitted.push(key.to_string());
            }
        }
        c
    }
}

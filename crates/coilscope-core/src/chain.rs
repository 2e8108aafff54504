//! The measurement chain: what a sound card and a sense resistor do between the driver's
//! terminals (physical `u`, `i`) and the recorded channels.
//!
//! The model, per channel, in the order a real interface applies it:
//!
//! ```text
//! recorded = HP_fc( delayed(physical) ) + dc + hum
//! ```
//!
//! * **Delay** (`delay_i`, s): the current channel sampled late against the voltage
//!   (`i_rec(t) = i(t - delay_i)`); fractional, done on the whole record by FFT (band-limited,
//!   zero-padded so nothing wraps around).
//! * **AC coupling** (`hp_u`, `hp_i`, Hz): first-order Butterworth high-pass, discretised with
//!   the bilinear transform (pre-warped corner): `y[n] = g (x[n] - x[n-1]) + a y[n-1]`,
//!   `K = tan(pi fc / fs)`, `a = (1 - K) / (1 + K)`, `g = 1 / (1 + K)`. A corner of 0 is a wire.
//!   Its inverse ([`hp_inverse`]) is exact: `x[n] = x[n-1] + (y[n] - a y[n-1]) / g`.
//! * **DC** (`dc_u`, `dc_i`, V, A): added after the coupling (an ADC offset, a sense amplifier's
//!   offset), so it reaches the record but not the driver.
//! * **Hum** ([`Hum`]): mains and its harmonics, added to the record.
//!
//! Conventions and keys are those of `docs/formats.md` ("Extensions": a result's
//! `chain`). Everything is SI; the delay is in seconds (the fits work in samples and convert).

use crate::recent::Recent;
use realfft::num_complex::Complex64;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::f64::consts::PI;
use std::sync::Arc;

/// Mains hum on the recorded channels: peak amplitude and phase (rad, of a cosine at `t = 0`)
/// of each harmonic `k f` (`k = 1, 2, ...`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Hum {
    /// Mains frequency (Hz): 50 or 60.
    pub f: f64,
    /// `[peak V, phase rad]` on the voltage channel, harmonic 1, 2, ...
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub u: Vec<[f64; 2]>,
    /// `[peak A, phase rad]` on the current channel (as estimated by a fit: what the voltage
    /// channel's hum drives through the driver is included here).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub i: Vec<[f64; 2]>,
}

impl Hum {
    /// The hum of `lines` (harmonics of `f` Hz) at time `t` (s).
    pub fn at(f: f64, lines: &[[f64; 2]], t: f64) -> f64 {
        lines.iter().enumerate().map(|(k, [a, ph])| a * (2.0 * PI * (k + 1) as f64 * f * t + ph).cos()).sum()
    }

    fn signal(f: f64, lines: &[[f64; 2]], n: usize, fs: f64) -> Vec<f64> {
        (0..n).map(|m| Hum::at(f, lines, m as f64 / fs)).collect()
    }
}

/// The measurement chain (result key `chain`). Absent quantities are 0 (a wire).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Chain {
    /// How the values were found: `estimated` (jointly with the driver), `calibrated` (a chain
    /// file), `simulated` (a virtual chain).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub source: Option<String>,
    /// Current channel late against the voltage (s).
    pub delay_i: f64,
    /// First-order AC-coupling corner of the voltage channel (Hz; 0: DC-coupled).
    pub hp_u: f64,
    /// The same for the current channel (Hz).
    pub hp_i: f64,
    /// Gain of the current channel against the voltage channel (recorded / true; absent:
    /// 1): a sense resistor's tolerance, or two converter channels' different gains, as a
    /// calibration measures it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gain_i: Option<f64>,
    /// Offset on the recorded voltage (V). Behind a DC-coupled voltage channel a record
    /// cannot tell it from a DC on the driver (that only moves the rest position); an
    /// estimate there is the convention that the drive has no mean over the record, so the
    /// curves' x = 0 is the rest position under the record's mean drive, and its sd is the
    /// drive's own mean's (`coilscope_ident::large::ChainSetup`).
    pub dc_u: f64,
    /// Offset on the recorded current (A).
    pub dc_i: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub hum: Option<Hum>,
    /// Sense resistor (ohm), where the wiring puts its drop into the voltage channel.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sense_ohm: Option<f64>,
    /// `terminals` (voltage measured at the driver) or `driver+shunt`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sense_wiring: Option<String>,
    /// Standard deviations of the estimated quantities, under their keys (`delay_i`, ...).
    #[serde(skip_serializing_if = "BTreeMap::is_empty")]
    pub sd: BTreeMap<String, f64>,
    /// Which quantities the data asked for (estimated ones; the others were held at 0).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub fitted: Vec<String>,
    /// Keys this version does not know: kept and written back.
    #[serde(flatten)]
    pub other: serde_json::Map<String, serde_json::Value>,
}

/// Bilinear first-order high-pass coefficients `(g, a)` for corner `fc` (Hz) at `fs`.
pub fn hp_coefficients(fc: f64, fs: f64) -> (f64, f64) {
    let k = (PI * fc / fs).tan();
    ((1.0 / (1.0 + k)), (1.0 - k) / (1.0 + k))
}

/// [`hp`] one sample at a time (for streams: a card's channel block by block).
#[derive(Clone, Copy, Debug)]
pub struct HighPass {
    g: f64,
    a: f64,
    x1: f64,
    y1: f64,
}

impl HighPass {
    /// At rest, corner `fc` (Hz) at `fs`.
    pub fn new(fc: f64, fs: f64) -> Self {
        let (g, a) = hp_coefficients(fc, fs);
        HighPass { g, a, x1: 0.0, y1: 0.0 }
    }
    /// The next output for input `x`.
    pub fn push(&mut self, x: f64) -> f64 {
        self.y1 = self.g * (x - self.x1) + self.a * self.y1;
        self.x1 = x;
        self.y1
    }
}

/// [`hp_inverse`] one sample at a time.
#[derive(Clone, Copy, Debug)]
pub struct HighPassInverse {
    g: f64,
    a: f64,
    x: f64,
    y1: f64,
}

impl HighPassInverse {
    /// At rest, undoing a corner `fc` (Hz) at `fs`.
    pub fn new(fc: f64, fs: f64) -> Self {
        let (g, a) = hp_coefficients(fc, fs);
        HighPassInverse { g, a, x: 0.0, y1: 0.0 }
    }
    /// The input whose high-pass output is `y` next.
    pub fn push(&mut self, y: f64) -> f64 {
        self.x += (y - self.a * self.y1) / self.g;
        self.y1 = y;
        self.x
    }
}

/// First-order bilinear high-pass of `x` (starting from rest).
pub fn hp(x: &[f64], fc: f64, fs: f64) -> Vec<f64> {
    let mut f = HighPass::new(fc, fs);
    x.iter().map(|&v| f.push(v)).collect()
}

/// The exact inverse of [`hp`]: the signal whose high-pass is `y`.
pub fn hp_inverse(y: &[f64], fc: f64, fs: f64) -> Vec<f64> {
    let mut f = HighPassInverse::new(fc, fs);
    y.iter().map(|&v| f.push(v)).collect()
}

/// Frequency response of [`hp`] at `f` (Hz).
pub fn hp_response(fc: f64, f: f64, fs: f64) -> Complex64 {
    hp_response_at(hp_coefficients(fc, fs), Complex64::from_polar(1.0, -2.0 * PI * f / fs))
}

/// [`hp_response`] from the filter's coefficients `(g, a)` ([`hp_coefficients`]) and `zi =
/// e^{-j 2 pi f / fs}`: for callers that evaluate one filter at many frequencies, or many
/// filters at one frequency, and take each of the two once.
pub fn hp_response_at((g, a): (f64, f64), zi: Complex64) -> Complex64 {
    g * (1.0 - zi) / (1.0 - a * zi)
}

/// `x` delayed by `samples` (fractional, may be negative: an advance), band-limited by FFT over
/// the record zero-padded by at least 256 samples on the delayed side, so that nothing wraps.
pub fn delay(x: &[f64], samples: f64) -> Vec<f64> {
    delays(x, &[samples]).pop().expect("one delay, one signal")
}

/// [`delay`] of `x` by each of `samples`, the same values to the last bit: one spectrum per
/// padding (two delays that round up to the same number of samples share it).
pub fn delays(x: &[f64], samples: &[f64]) -> Vec<Vec<f64>> {
    let mut spectra: Vec<DelaySpectrum> = Vec::new();
    samples
        .iter()
        .map(|&s| {
            if s == 0.0 || x.is_empty() {
                return x.to_vec();
            }
            let pad = delay_pad(s);
            let k = spectra.iter().position(|sp| sp.pad == pad).unwrap_or_else(|| {
                spectra.push(DelaySpectrum::new(x, pad));
                spectra.len() - 1
            });
            spectra[k].delayed(&spectra[k].phases_shared(s))
        })
        .collect()
}

/// The zero padding (samples each side) [`delay`] uses for a delay of `samples`.
pub fn delay_pad(samples: f64) -> usize {
    256 + samples.abs().ceil() as usize
}

/// A signal's spectrum as [`delay`] computes it (zero-padded by `pad` each side to a power of
/// two), kept to delay the same signal by other amounts that use the same padding: each then
/// costs one inverse FFT, and signals of one length share the phase factors
/// ([`DelaySpectrum::phases`]). [`delay`] is this, in one go: the results are the same to the
/// last bit.
#[derive(Clone, Debug)]
pub struct DelaySpectrum {
    len: usize,
    /// Zero padding on each side (samples).
    pub pad: usize,
    /// Transform length.
    pub n: usize,
    spec: Vec<Complex64>,
}

impl DelaySpectrum {
    pub fn new(x: &[f64], pad: usize) -> Self {
        let n = (x.len() + 2 * pad).next_power_of_two().max(2);
        let mut buf = vec![0.0; n];
        buf[pad..pad + x.len()].copy_from_slice(x);
        DelaySpectrum { len: x.len(), pad, n, spec: crate::fft::rfft(&buf) }
    }

    /// The factor of each bin for a delay of `samples` (and the inverse transform's `1 / n`).
    pub fn phases(&self, samples: f64) -> Vec<Complex64> {
        let n = self.n as f64;
        (0..self.spec.len()).map(|k| Complex64::from_polar(1.0 / n, -2.0 * PI * k as f64 * samples / n)).collect()
    }

    /// [`DelaySpectrum::phases`], shared: the factors of the last few delays asked for at
    /// this transform length are kept (a fit asks for the same delay for its current to match
    /// and for its basis columns; each set is `n / 2 + 1` sines and cosines).
    pub fn phases_shared(&self, samples: f64) -> Arc<Vec<Complex64>> {
        static KEPT: Recent<(usize, u64), Vec<Complex64>> = Recent::new(KEPT_PHASES);
        KEPT.get_or_compute((self.n, samples.to_bits()), || self.phases(samples))
    }

    /// The signal delayed as `phases` says.
    pub fn delayed(&self, phases: &[Complex64]) -> Vec<f64> {
        self.delayed_range(phases, 0..self.len)
    }

    /// Samples `range` of [`DelaySpectrum::delayed`] (the same values to the last bit),
    /// without copying the rest.
    pub fn delayed_range(&self, phases: &[Complex64], range: std::ops::Range<usize>) -> Vec<f64> {
        assert!(range.end <= self.len, "samples {range:?} of a signal of {}", self.len);
        debug_assert_eq!(phases.len(), self.spec.len(), "phase factors of another transform length");
        let spec: Vec<Complex64> = self.spec.iter().zip(phases).map(|(c, p)| c * p).collect();
        // The Nyquist bin of a real signal cannot carry a fractional shift (its phase would
        // make it complex): `irfft` keeps its real part only (it is empty for a band-limited
        // record).
        let mut y = crate::fft::irfft_owned(spec, self.n);
        let from = self.pad + range.start;
        y.copy_within(from..from + range.len(), 0);
        y.truncate(range.len());
        y
    }
}

/// Sets of phase factors [`DelaySpectrum::phases_shared`] keeps.
const KEPT_PHASES: usize = 4;

impl Chain {
    /// What an estimated chain of a record at `fs` fitted, in words, with its sds.
    pub fn describe_fitted(&self, fs: f64) -> String {
        let fitted = |k: &str| self.fitted.iter().any(|f| f == k);
        let sd = |k: &str| self.sd.get(k).copied().unwrap_or(f64::NAN);
        let mut parts = vec![];
        if fitted("delay_i") {
            parts.push(format!(
                "current {:.3} +- {:.3} samples late ({:.2} us)",
                self.delay_i * fs,
                sd("delay_i") * fs,
                1e6 * self.delay_i
            ));
        }
        if fitted("hp_u") {
            parts.push(format!("voltage AC-coupled at {:.2} +- {:.2} Hz", self.hp_u, sd("hp_u")));
        }
        if fitted("hp_i") {
            parts.push(format!("current AC-coupled at {:.2} +- {:.2} Hz", self.hp_i, sd("hp_i")));
        }
        if fitted("dc_i") {
            parts.push(format!("offsets {:.3e} V, {:.3e} +- {:.1e} A", self.dc_u, self.dc_i, sd("dc_i")));
        }
        if let Some(h) = &self.hum {
            parts.push(format!(
                "hum at {} Hz: {}",
                h.f,
                h.i.iter().map(|l| format!("{:.2e}", l[0])).collect::<Vec<_>>().join(", ") + " A"
            ));
        }
        if parts.is_empty() {
            "ideal (no delay or AC coupling found)".to_string()
        } else {
            parts.join(", ")
        }
    }

    /// What the record adds after the coupling, per channel: offset plus hum, `n` samples.
    fn additive(&self, n: usize, fs: f64) -> (Vec<f64>, Vec<f64>) {
        let (mut hu, mut hi) = match &self.hum {
            Some(h) => (Hum::signal(h.f, &h.u, n, fs), Hum::signal(h.f, &h.i, n, fs)),
            None => (vec![0.0; n], vec![0.0; n]),
        };
        hu.iter_mut().for_each(|v| *v += self.dc_u);
        hi.iter_mut().for_each(|v| *v += self.dc_i);
        (hu, hi)
    }

    /// Channel records of the physical `u` (V) and `i` (A) at `fs`.
    pub fn apply(&self, u: &[f64], i: &[f64], fs: f64) -> (Vec<f64>, Vec<f64>) {
        let mut ur = hp(u, self.hp_u, fs);
        let g = self.gain_i.unwrap_or(1.0);
        let mut ir: Vec<f64> = hp(&delay(i, self.delay_i * fs), self.hp_i, fs).into_iter().map(|v| g * v).collect();
        let n = u.len();
        let (au, ai) = self.additive(n, fs);
        for m in 0..n {
            ur[m] += au[m];
            ir[m] += ai[m];
        }
        (ur, ir)
    }

    /// The physical `u`, `i` of channel records (the exact inverse of [`Chain::apply`]).
    pub fn invert(&self, u_rec: &[f64], i_rec: &[f64], fs: f64) -> (Vec<f64>, Vec<f64>) {
        let n = u_rec.len();
        let (au, ai) = self.additive(n, fs);
        let uc: Vec<f64> = (0..n).map(|m| u_rec[m] - au[m]).collect();
        let ic: Vec<f64> = (0..n).map(|m| i_rec[m] - ai[m]).collect();
        let g = self.gain_i.unwrap_or(1.0);
        (
            hp_inverse(&uc, self.hp_u, fs),
            delay(&hp_inverse(&ic, self.hp_i, fs), -self.delay_i * fs).into_iter().map(|v| v / g).collect(),
        )
    }

    /// The physical `u`, `i` behind the records of a new measurement through a *calibrated*
    /// chain (delay, corners, gain known; this record's offsets not): each channel's offset
    /// is the one that leaves no mean and no trend behind its coupling ([`voltage_behind`]),
    /// and hum is left in (the fit leaves its bins out). Returns `(u, i, dc_u, dc_i)`.
    pub fn invert_calibrated(&self, u_rec: &[f64], i_rec: &[f64], fs: f64) -> (Vec<f64>, Vec<f64>, f64, f64) {
        let (u, dc_u) = voltage_behind(u_rec, self.hp_u, fs);
        let (i, dc_i) = voltage_behind(i_rec, self.hp_i, fs);
        let g = self.gain_i.unwrap_or(1.0);
        (u, delay(&i, -self.delay_i * fs).into_iter().map(|v| v / g).collect(), dc_u, dc_i)
    }

    /// What the chain multiplies the recorded `U/I` by at `f`: `Z_rec = Z * ratio`.
    pub fn impedance_factor(&self, f: f64, fs: f64) -> Complex64 {
        hp_response(self.hp_u, f, fs) / hp_response(self.hp_i, f, fs)
            * Complex64::from_polar(1.0 / self.gain_i.unwrap_or(1.0), 2.0 * PI * f * self.delay_i)
    }

    /// True when every quantity is 0 (an ideal chain).
    pub fn is_ideal(&self) -> bool {
        self.delay_i == 0.0
            && self.hp_u == 0.0
            && self.hp_i == 0.0
            && self.gain_i.is_none_or(|g| g == 1.0)
            && self.dc_u == 0.0
            && self.dc_i == 0.0
            && self.hum.is_none()
    }
}

/// Where the voltage channel is connected against the current-sense resistor (result keys
/// `sense_wiring`, `sense_ohm`).
///
/// * **`terminals`** (preferred): the voltage channel measures across the driver's terminals
///   alone (a differential input, or the shunt on the high side with the voltage probe at the
///   driver). Nothing is subtracted, so the shunt's tolerance and its self-heating reach only
///   the current's scale, never Re.
/// * **`driver+shunt`**: the voltage channel measures across driver and shunt in series (a
///   low-side shunt with single-ended, ground-referenced inputs: what most sound cards allow).
///   It records `u + Rs i`; coilscope subtracts `Rs i` as the voltage channel's chain would
///   have recorded it ([`Chain::remove_shunt_drop`]). An error `dRs` in the given resistance
///   goes one to one into Re (and `dRs / (alpha Re)` into the temperature rise), so measure
///   the shunt four-wire and keep it small against Re.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum SenseWiring {
    #[default]
    Terminals,
    DriverPlusShunt {
        /// The sense resistor (ohm).
        ohm: f64,
    },
}

impl SenseWiring {
    /// The names used on the command line and in results.
    pub const NAMES: [&'static str; 2] = ["terminals", "driver+shunt"];

    /// `--sense-wiring NAME` with `--sense-ohm OHM` (needed for `driver+shunt`); the message
    /// names the option, the value and what is valid.
    pub fn parse(wiring: &str, ohm: Option<f64>) -> Result<Self, String> {
        match wiring.trim() {
            "terminals" => Ok(SenseWiring::Terminals),
            "driver+shunt" | "series" => match ohm {
                Some(r) if r.is_finite() && r > 0.0 && r < 100.0 => Ok(SenseWiring::DriverPlusShunt { ohm: r }),
                Some(r) => Err(format!("--sense-ohm {r} is not valid: the sense resistor in ohm (0 .. 100), measured four-wire")),
                None => Err("--sense-wiring driver+shunt needs --sense-ohm OHM: the sense resistor whose drop the voltage channel also records".to_string()),
            },
            other => Err(format!("--sense-wiring {other:?} is not valid: give `terminals` (the voltage channel across the driver alone) or `driver+shunt` (across driver and sense resistor in series)")),
        }
    }

    pub fn name(&self) -> &'static str {
        match self {
            SenseWiring::Terminals => Self::NAMES[0],
            SenseWiring::DriverPlusShunt { .. } => Self::NAMES[1],
        }
    }

    /// The resistance whose drop the voltage channel records besides the driver's (ohm).
    pub fn series_ohm(&self) -> f64 {
        match self {
            SenseWiring::Terminals => 0.0,
            SenseWiring::DriverPlusShunt { ohm } => *ohm,
        }
    }

    /// The voltage at the voltage channel's input for the driver's physical `u` and `i`.
    pub fn channel_voltage(&self, u: &[f64], i: &[f64]) -> Vec<f64> {
        let rs = self.series_ohm();
        u.iter().zip(i).map(|(u, i)| u + rs * i).collect()
    }

    /// Put this wiring into a chain's keys (`sense_wiring`, and `sense_ohm` for
    /// `driver+shunt`).
    pub fn mark(&self, c: &mut Chain) {
        c.sense_wiring = Some(self.name().to_string());
        c.sense_ohm = match self {
            SenseWiring::Terminals => None,
            SenseWiring::DriverPlusShunt { ohm } => Some(*ohm),
        };
    }
}

impl Chain {
    /// The voltage record a `terminals` wiring would have given, from the records `u_rec`,
    /// `i_rec` of a `driver+shunt` wiring with the sense resistor `rs` (ohm) through this
    /// chain: `u_rec - rs HP_u(i)`, where `i` is the physical current behind the current
    /// record (its coupling and gain inverted, its offset the one that leaves no mean and no
    /// trend, its delay taken out) and `HP_u` the voltage channel's coupling. Exact for the
    /// chain's model up to the current channel's hum, which reaches the voltage as `rs` times
    /// itself (for -60 dB hum on the current, about -100 dB on the voltage).
    pub fn remove_shunt_drop(&self, u_rec: &[f64], i_rec: &[f64], rs: f64, fs: f64) -> Vec<f64> {
        if rs == 0.0 {
            return u_rec.to_vec();
        }
        let (i, _) = voltage_behind(i_rec, self.hp_i, fs);
        let g = self.gain_i.unwrap_or(1.0);
        let i: Vec<f64> = delay(&i, -self.delay_i * fs).into_iter().map(|v| v / g).collect();
        let i_u = hp(&i, self.hp_u, fs);
        u_rec.iter().zip(&i_u).map(|(u, i)| u - rs * i).collect()
    }
}

/// What a unit offset on a channel AC-coupled at `fc` (Hz) becomes behind the coupling's
/// inverse, `n` samples: `hp_inverse(1)`, i.e. `1/g + 2 K m` at sample `m`.
pub fn offset_behind(n: usize, fc: f64, fs: f64) -> Vec<f64> {
    hp_inverse(&vec![1.0; n], fc, fs)
}

/// The physical voltage behind a voltage channel AC-coupled at `hp_u` (Hz) with an unknown
/// offset: `hp_inverse(u_rec - dc_u)`, with `dc_u` the offset that leaves the result without a
/// mean and a trend (an offset left in would be integrated into a ramp). Returns the voltage
/// and `dc_u`.
pub fn voltage_behind(u_rec: &[f64], hp_u: f64, fs: f64) -> (Vec<f64>, f64) {
    let x = hp_inverse(u_rec, hp_u, fs);
    let ones = offset_behind(u_rec.len(), hp_u, fs);
    let (xo, oo) = x.iter().zip(&ones).fold((0.0, 0.0), |(a, b), (x, o)| (a + x * o, b + o * o));
    let dc = if oo > 0.0 { xo / oo } else { 0.0 };
    (x.iter().zip(&ones).map(|(x, o)| x - dc * o).collect(), dc)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};

    /// One spectrum delayed by several amounts of the same padding is [`delay`] of each, to the
    /// last bit (what the fit's Jacobian relies on to compute the basis once).
    #[test]
    fn a_kept_spectrum_delays_as_delay_does() {
        let x = noise(17, 5000);
        let s = DelaySpectrum::new(&x, delay_pad(0.7));
        for tau in [0.7, -0.3, 0.05, -0.999] {
            assert_eq!(delay_pad(tau), s.pad);
            assert_eq!(s.delayed(&s.phases(tau)), delay(&x, tau), "tau {tau}");
        }
    }

    /// A part of a delayed signal ([`DelaySpectrum::delayed_range`]) is
    /// that part of [`DelaySpectrum::delayed`], the shared phase factors are
    /// [`DelaySpectrum::phases`], to the last bit, also when more delays are asked for than
    /// are kept (`KEPT_PHASES`), and [`delays`] is [`delay`] of each amount.
    #[test]
    fn a_delayed_range_shared_phases_and_delays_are_the_plain_ones() {
        let x = noise(23, 3000);
        let s = DelaySpectrum::new(&x, delay_pad(0.4));
        for round in 0..2 {
            for tau in [0.4, -0.25, 0.125, -0.9, 0.6, 0.01] {
                let shared = s.phases_shared(tau);
                assert_eq!(*shared, s.phases(tau), "round {round}, tau {tau}");
                let whole = s.delayed(&shared);
                assert_eq!(whole.len(), x.len());
                for r in [0..3000, 0..1, 17..2900, 2999..3000, 5..5] {
                    assert_eq!(
                        s.delayed_range(&shared, r.clone()),
                        whole[r.clone()].to_vec(),
                        "tau {tau}, range {r:?}"
                    );
                }
            }
        }
        // Several delays of one signal, spectra shared where the paddings agree, are each
        // delay's own (a zero delay: the signal itself).
        let taus = [0.4, 0.6, -0.4, 1.7, 0.0, 0.4];
        for (d, &tau) in delays(&x, &taus).iter().zip(&taus) {
            assert_eq!(d, &delay(&x, tau), "tau {tau}");
        }
        assert_eq!(delay(&x, 0.0), x);
    }

    fn noise(seed: u64, n: usize) -> Vec<f64> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        // Band-limited, starting and ending at rest.
        let w: Vec<f64> = (0..n).map(|_| StandardNormal.sample(&mut rng)).collect();
        let mut y = hp(&w, 20.0, 48000.0);
        // Four one-pole low-passes: nearly nothing left near Nyquist, as after an ADC's
        // anti-alias filter (a fractional delay is exact only for a band-limited signal).
        for _ in 0..4 {
            let mut s = 0.0;
            for v in y.iter_mut() {
                s = 0.9 * s + 0.1 * *v;
                *v = s;
            }
        }
        let fade = n / 10;
        for k in 0..fade {
            let g = k as f64 / fade as f64;
            y[k] *= g;
            y[n - 1 - k] *= g;
        }
        y
    }

    #[test]
    fn hp_matches_its_analytic_response_and_inverse() {
        let fs = 48000.0;
        // Response of a long sinusoid in steady state against hp_response.
        for (fc, f) in [(2.0, 10.0), (4.0, 50.0), (3.0, 1000.0)] {
            let n = 480000;
            let x: Vec<f64> = (0..n).map(|m| (2.0 * PI * f * m as f64 / fs).cos()).collect();
            let y = hp(&x, fc, fs);
            let h = hp_response(fc, f, fs);
            for m in n - 1000..n {
                let want = h.norm() * (2.0 * PI * f * m as f64 / fs + h.arg()).cos();
                assert!((y[m] - want).abs() < 1e-9, "fc {fc} f {f}: {} vs {want}", y[m]);
            }
            // The analog prototype s / (s + wc), pre-warped at the corner: -3 dB there.
            assert!((hp_response(fc, fc, fs).norm() - 0.5f64.sqrt()).abs() < 1e-9);
        }
        let x = noise(1, 20000);
        let back = hp_inverse(&hp(&x, 3.0, 48000.0), 3.0, 48000.0);
        let err = x.iter().zip(&back).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
        assert!(err < 1e-9, "{err}");
    }

    #[test]
    fn fractional_delay_is_an_exact_phase_shift_and_invertible() {
        let fs = 48000.0;
        let f = 1234.5;
        let n = 4800;
        // A windowed tone: delaying it by d samples equals evaluating it at t - d/fs.
        let env = |t: f64| (PI * t / (n as f64 / fs)).sin().powi(4);
        let sig = |t: f64| env(t) * (2.0 * PI * f * t).sin();
        let x: Vec<f64> = (0..n).map(|m| sig(m as f64 / fs)).collect();
        for d in [0.3, -0.25, 1.7] {
            let y = delay(&x, d);
            for m in 100..n - 100 {
                let want = sig((m as f64 - d) / fs);
                assert!((y[m] - want).abs() < 1e-6, "d {d} m {m}: {} vs {want}", y[m]);
            }
            let back = delay(&y, -d);
            let err = x.iter().zip(&back).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
            assert!(err < 1e-9, "{err}");
        }
    }

    #[test]
    fn chain_inverts_exactly_and_finds_the_voltage_offset() {
        let fs = 48000.0;
        let n = 96000;
        let (u, i) = (noise(2, n), noise(3, n));
        let c = Chain {
            delay_i: 0.3 / fs,
            hp_u: 2.0,
            hp_i: 4.0,
            dc_u: 0.01,
            dc_i: 1e-3,
            hum: Some(Hum { f: 50.0, u: vec![[1e-3, 0.2], [0.0, 0.0], [5e-4, 1.0]], i: vec![[1e-4, -0.5]] }),
            ..Chain::default()
        };
        let (ur, ir) = c.apply(&u, &i, fs);
        let (ub, ib) = c.invert(&ur, &ir, fs);
        // Exact but at the record's ends: what a fractional delay moves past them is not
        // recorded (the sinc's tails; this test noise is not band-limited).
        let err = |a: &[f64], b: &[f64]| (2000..n - 2000).map(|m| (a[m] - b[m]).abs()).fold(0.0, f64::max);
        assert!(err(&u, &ub) < 1e-9 && err(&i, &ib) < 1e-7, "{} {}", err(&u, &ub), err(&i, &ib));
        // The offset from the record alone (no hum on this one).
        let c2 = Chain { hum: None, ..c };
        let (ur, _) = c2.apply(&u, &i, fs);
        let (ub, dc) = voltage_behind(&ur, 2.0, fs);
        let rms = (u.iter().map(|v| v * v).sum::<f64>() / n as f64).sqrt();
        assert!((dc - 0.01).abs() < 1e-4 * rms, "dc {dc}");
        assert!(err(&u, &ub) < 3e-3 * rms, "{}", err(&u, &ub) / rms);
        // The impedance factor: the recorded U/I of a resistor.
        let z = c2.impedance_factor(100.0, fs);
        let want = hp_response(2.0, 100.0, fs)
            / (hp_response(4.0, 100.0, fs) * Complex64::from_polar(1.0, -2.0 * PI * 100.0 * 0.3 / fs));
        assert!((z - want).norm() < 1e-12);
    }

    #[test]
    fn the_shunt_drop_comes_out_through_any_chain() {
        // A driver+shunt record through a skewed, AC-coupled chain with offsets and a gain
        // error: removing the drop gives the terminals record of the same chain.
        let fs = 48000.0;
        let n = 96000;
        let (u, i) = (noise(4, n), noise(5, n));
        let rs = 0.47;
        let w = SenseWiring::DriverPlusShunt { ohm: rs };
        for c in [
            Chain::default(),
            Chain {
                delay_i: 0.4 / fs,
                hp_u: 1.0,
                hp_i: 5.0,
                dc_u: 0.02,
                dc_i: -2e-3,
                gain_i: Some(1.03),
                ..Chain::default()
            },
            Chain { delay_i: -0.2 / fs, hp_u: 3.0, hp_i: 3.0, ..Chain::default() },
        ] {
            let (ur, ir) = c.apply(&w.channel_voltage(&u, &i), &i, fs);
            let (ut, _) = c.apply(&u, &i, fs);
            let got = c.remove_shunt_drop(&ur, &ir, rs, fs);
            let rms = (ut.iter().map(|v| v * v).sum::<f64>() / n as f64).sqrt();
            // The offset of the current found from the record (as for invert_calibrated)
            // leaves rs times a small constant; the rest is exact away from the ends.
            let err = (2000..n - 2000).map(|m| (got[m] - ut[m]).abs()).fold(0.0, f64::max) / rms;
            assert!(err < 2e-3 * rs, "{c:?}: {err:.2e}");
            // Without the removal the error is the whole drop.
            let raw = (2000..n - 2000).map(|m| (ur[m] - ut[m]).abs()).fold(0.0, f64::max) / rms;
            assert!(raw > 100.0 * err, "{raw:.2e} vs {err:.2e}");
        }
        assert_eq!(SenseWiring::parse("driver+shunt", Some(0.1)).unwrap(), SenseWiring::DriverPlusShunt { ohm: 0.1 });
        assert_eq!(SenseWiring::parse("terminals", None).unwrap(), SenseWiring::Terminals);
        for (w, r, say) in
            [("driver+shunt", None, "--sense-ohm"), ("driver+shunt", Some(-1.0), "-1"), ("both", None, "terminals")]
        {
            let e = SenseWiring::parse(w, r).unwrap_err();
            assert!(e.contains(say), "{e}");
        }
    }

    #[test]
    fn chain_round_trips_as_json_with_unknown_keys() {
        let text =
            r#"{"delay_i":6.25e-6,"hp_u":2.0,"hp_i":4.0,"dc_i":0.001,"hum":{"f":50.0,"i":[[1e-4,0.5]]},"future":1}"#;
        let c: Chain = serde_json::from_str(text).unwrap();
        assert_eq!(c.hp_i, 4.0);
        assert_eq!(c.other["future"], 1);
        let back: Chain = serde_json::from_str(&serde_json::to_string(&c).unwrap()).unwrap();
        assert_eq!(back, c);
    }
}

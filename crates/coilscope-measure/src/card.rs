//! The sound card's measurement chain, block by block: correcting a calibrated chain during a
//! measurement ([`Corrected`]), and a simulated card that records a device through a chain
//! ([`SimulatedCard`]) so that the whole card path runs and is tested without hardware.
//!
//! A measurement cannot wait for the whole record, as `linear` and `identify` do
//! ([`coilscope_core::chain::Chain::invert_calibrated`]). Per block, [`ChainCorrector`]:
//!
//! * **Offsets**: each channel's offset is the mean of the second half of a silent lead-in
//!   ([`LEAD_IN_SECONDS`], [`ChainCorrector::offsets_from_silence`]), taken out first.
//! * **AC coupling**: each channel's first-order coupling at its corner `fc` is inverted
//!   exactly and a common first-order high-pass at [`RESIDUAL_HP`] (0.01 Hz) put in its place,
//!   so that what the lead-in leaves of the offset (noise / sqrt(12 000)) ends as a constant
//!   `fc / 0.01 Hz` times it, not as a ramp. The residual high-pass acts on the drive and the
//!   current alike (0.03 degrees at 20 Hz; at 0.1 Hz it moved SB17's Kms by 0.4 % through the
//!   nonlinear part, at 0.01 Hz by 0.06 %).
//! * **Delay**: the voltage is delayed by the current channel's delay (a windowed-sinc
//!   fractional delay, [`FracDelay`]), and both channels by [`LATENCY`] samples more, so that
//!   they are aligned with each other (a device's blocks need not be aligned with the drive).
//! * **Gain**: the current is divided by `gain_i`.
//! * **Wiring**: a `driver+shunt` voltage channel loses the shunt's drop, `Rs i`, after the
//!   alignment ([`coilscope_core::chain::SenseWiring`]).
//!
//! Hum is not removed here (the online fit's noise takes it; `linear` and `identify` fit it).

use crate::device::{Block, Device, Truth};
use coilscope_core::chain::{Chain, HighPass, HighPassInverse, Hum, SenseWiring};
use std::collections::VecDeque;
use std::f64::consts::PI;

/// The common high-pass left on both channels by the correction (Hz).
pub const RESIDUAL_HP: f64 = 0.01;
/// Seconds of silence recorded before a corrected measurement, for the offsets.
pub const LEAD_IN_SECONDS: f64 = 0.5;
/// Half-length of the fractional-delay filter: its latency (samples).
pub const LATENCY: usize = 32;

/// A fractional delay of `LATENCY + frac` samples (`|frac| < LATENCY`): a Kaiser-windowed
/// sinc of `2 LATENCY + 1` taps, normalised to unit gain at DC. Its pass band is flat within
/// 1e-4 up to 0.4 fs.
pub struct FracDelay {
    taps: Vec<f64>,
    hist: VecDeque<f64>,
}

impl FracDelay {
    pub fn new(frac: f64) -> Self {
        assert!(frac.abs() < LATENCY as f64, "fractional delay {frac} beyond the filter's {LATENCY} samples");
        let h = LATENCY as f64;
        let d = h + frac;
        let beta = 10.0;
        let half = h + 1.0;
        let mut taps: Vec<f64> = (0..=2 * LATENCY)
            .map(|k| {
                let t = k as f64 - d;
                let sinc = if t.abs() < 1e-12 { 1.0 } else { (PI * t).sin() / (PI * t) };
                let r = (t / half).clamp(-1.0, 1.0);
                sinc * bessel_i0(beta * (1.0 - r * r).sqrt()) / bessel_i0(beta)
            })
            .collect();
        let s: f64 = taps.iter().sum();
        taps.iter_mut().for_each(|v| *v /= s);
        FracDelay { taps, hist: std::iter::repeat_n(0.0, 2 * LATENCY + 1).collect() }
    }

    /// The next output for input `x`.
    pub fn push(&mut self, x: f64) -> f64 {
        self.hist.pop_back();
        self.hist.push_front(x);
        self.hist.iter().zip(&self.taps).map(|(a, b)| a * b).sum()
    }
}

/// The modified Bessel function of the first kind, order 0 (power series).
fn bessel_i0(x: f64) -> f64 {
    let (mut sum, mut term, q) = (1.0, 1.0, x * x / 4.0);
    for k in 1..60 {
        term *= q / (k * k) as f64;
        sum += term;
        if term < 1e-17 * sum {
            break;
        }
    }
    sum
}

/// One channel's AC coupling at `fc` and offset undone, [`RESIDUAL_HP`] put in its place.
struct Uncouple {
    /// The channel's offset (recorded units), found in the silent lead-in.
    dc: f64,
    inverse: HighPassInverse,
    residual: HighPass,
}

impl Uncouple {
    fn new(fc: f64, fs: f64) -> Self {
        Uncouple { dc: 0.0, inverse: HighPassInverse::new(fc, fs), residual: HighPass::new(RESIDUAL_HP, fs) }
    }
    fn push(&mut self, y: f64) -> f64 {
        self.residual.push(self.inverse.push(y - self.dc))
    }
}

/// The current channel's delay in samples, if the streamed filters can take it.
fn streamed_delay(chain: &Chain, fs: f64) -> Result<f64, String> {
    let tau = chain.delay_i * fs;
    if tau.is_finite() && tau.abs() < LATENCY as f64 - 1.0 {
        Ok(tau)
    } else {
        Err(format!("the chain's delay_i {:.3e} s ({tau:.2} samples) is beyond what a streamed chain takes (|delay| < {} samples)", chain.delay_i, LATENCY - 1))
    }
}

/// The streaming correction of a calibrated chain and a wiring (see the module docs).
pub struct ChainCorrector {
    u: Uncouple,
    i: Uncouple,
    delay_u: FracDelay,
    delay_i: FracDelay,
    gain_i: f64,
    rs: f64,
}

impl ChainCorrector {
    pub fn new(chain: &Chain, wiring: SenseWiring, fs: f64) -> Result<Self, String> {
        let tau = streamed_delay(chain, fs)?;
        Ok(ChainCorrector {
            u: Uncouple::new(chain.hp_u, fs),
            i: Uncouple::new(chain.hp_i, fs),
            delay_u: FracDelay::new(tau),
            delay_i: FracDelay::new(0.0),
            gain_i: chain.gain_i.unwrap_or(1.0),
            rs: wiring.series_ohm(),
        })
    }

    /// Samples of silence to record before the measurement, for the offsets (0.5 s: a whole
    /// number of 50 and 60 Hz periods, so that hum averages out).
    pub fn lead_in(fs: f64) -> usize {
        (LEAD_IN_SECONDS * fs).round() as usize
    }

    /// Take each channel's offset from a record of silence (the second half of it: the first
    /// holds the card's and the driver's settling). Returns `(dc_u, dc_i)` (recorded units).
    ///
    /// An offset left in would be integrated by the coupling's inverse into a ramp; what a
    /// 0.5 s lead-in leaves (the noise over 12 000 samples) becomes, behind [`RESIDUAL_HP`], a
    /// constant of `dc_error fc / RESIDUAL_HP`.
    pub fn offsets_from_silence(&mut self, u_rec: &[f64], i_rec: &[f64]) -> (f64, f64) {
        let half = |x: &[f64]| {
            let t = &x[x.len() / 2..];
            if t.is_empty() {
                0.0
            } else {
                t.iter().sum::<f64>() / t.len() as f64
            }
        };
        self.u.dc = half(u_rec);
        self.i.dc = half(i_rec);
        (self.u.dc, self.i.dc)
    }

    /// The corrected `(u, i)` of one recorded sample pair (both [`LATENCY`] + delay later).
    pub fn push(&mut self, u_rec: f64, i_rec: f64) -> (f64, f64) {
        let u = self.delay_u.push(self.u.push(u_rec));
        let i = self.delay_i.push(self.i.push(i_rec)) / self.gain_i;
        (u - self.rs * i, i)
    }
}

/// A device whose blocks are corrected for a calibrated chain and a wiring.
///
/// Its first block is preceded by [`LEAD_IN_SECONDS`] of silence on the device, whose record
/// gives the channels' offsets ([`ChainCorrector::offsets_from_silence`]).
pub struct Corrected<D> {
    inner: D,
    corrector: ChainCorrector,
    what: String,
    led_in: bool,
    offsets: (f64, f64),
}

impl<D: Device> Corrected<D> {
    /// The offsets found in the lead-in: `(dc_u V, dc_i A)` as recorded.
    pub fn offsets(&self) -> (f64, f64) {
        self.offsets
    }

    pub fn new(inner: D, chain: &Chain, wiring: SenseWiring) -> Result<Self, String> {
        let corrector = ChainCorrector::new(chain, wiring, inner.fs())?;
        let what = format!(
            "corrected for its chain (current {:.3} samples late, AC coupling {:.2} / {:.2} Hz, gain {:.4}; {} wiring)",
            chain.delay_i * inner.fs(),
            chain.hp_u,
            chain.hp_i,
            chain.gain_i.unwrap_or(1.0),
            wiring.name()
        );
        Ok(Corrected { inner, corrector, what, led_in: false, offsets: (0.0, 0.0) })
    }
}

impl<D: Device> Device for Corrected<D> {
    fn fs(&self) -> f64 {
        self.inner.fs()
    }
    fn play(&mut self, drive: &[f64]) -> Result<Option<Block>, String> {
        if !self.led_in {
            self.led_in = true;
            let n = ChainCorrector::lead_in(self.inner.fs());
            if self.inner.controllable() && n > 0 {
                let Some(b) = self.inner.play(&vec![0.0; n])? else { return Ok(None) };
                self.offsets = self.corrector.offsets_from_silence(&b.u, &b.i);
            }
        }
        let Some(b) = self.inner.play(drive)? else { return Ok(None) };
        let (u, i) = b.u.iter().zip(&b.i).map(|(&u, &i)| self.corrector.push(u, i)).unzip();
        Ok(Some(Block { u, i }))
    }
    fn truth(&self) -> Option<Truth> {
        self.inner.truth()
    }
    fn controllable(&self) -> bool {
        self.inner.controllable()
    }
    fn describe(&self) -> String {
        format!("{}, {}", self.inner.describe(), self.what)
    }
}

/// A chain applied block by block, as a card records: per channel
/// `HP_fc(delayed) + dc + hum`, the current `gain_i` times that (as
/// [`Chain::apply`], the delay by [`FracDelay`] and both channels [`LATENCY`] samples late).
pub struct ChainStream {
    hp_u: HighPass,
    hp_i: HighPass,
    delay_u: FracDelay,
    delay_i: FracDelay,
    chain: Chain,
    fs: f64,
    n: usize,
}

impl ChainStream {
    pub fn new(chain: &Chain, fs: f64) -> Result<Self, String> {
        let tau = streamed_delay(chain, fs)?;
        Ok(ChainStream {
            hp_u: HighPass::new(chain.hp_u, fs),
            hp_i: HighPass::new(chain.hp_i, fs),
            delay_u: FracDelay::new(0.0),
            delay_i: FracDelay::new(tau),
            chain: chain.clone(),
            fs,
            n: 0,
        })
    }

    /// The recorded `(u, i)` of one physical sample pair at the channels' inputs.
    pub fn push(&mut self, u: f64, i: f64) -> (f64, f64) {
        let t = self.n as f64 / self.fs;
        self.n += 1;
        let (hu, hi) = self.chain.hum.as_ref().map_or((0.0, 0.0), |h| (Hum::at(h.f, &h.u, t), Hum::at(h.f, &h.i, t)));
        let ur = self.hp_u.push(self.delay_u.push(u)) + self.chain.dc_u + hu;
        let ir = self.chain.gain_i.unwrap_or(1.0) * self.hp_i.push(self.delay_i.push(i)) + self.chain.dc_i + hi;
        (ur, ir)
    }
}

/// A device recorded through a simulated sound card: its physical voltage and current pass
/// the wiring (a `driver+shunt` voltage channel adds `Rs i`), the chain ([`ChainStream`]),
/// and 24-bit converters at the given full scales (V, A), as a real card's would.
pub struct SimulatedCard<D> {
    inner: D,
    wiring: SenseWiring,
    stream: ChainStream,
    full_scale: (f64, f64),
    clipped: usize,
}

impl<D: Device> SimulatedCard<D> {
    pub fn new(inner: D, chain: &Chain, wiring: SenseWiring, full_scale: (f64, f64)) -> Result<Self, String> {
        let stream = ChainStream::new(chain, inner.fs())?;
        Ok(SimulatedCard { inner, wiring, stream, full_scale, clipped: 0 })
    }

    /// Samples that reached a converter's full scale.
    pub fn clipped(&self) -> usize {
        self.clipped
    }
}

/// A 24-bit converter at full scale `fs_value`: the value of the code nearest to `v`, clipped
/// (and counted).
fn convert(v: f64, fs_value: f64, clipped: &mut usize) -> f64 {
    let full = 8_388_607.0;
    let code = (v / fs_value * full).round();
    if code.abs() > full {
        *clipped += 1;
    }
    code.clamp(-full, full) / full * fs_value
}

impl<D: Device> Device for SimulatedCard<D> {
    fn fs(&self) -> f64 {
        self.inner.fs()
    }
    fn play(&mut self, drive: &[f64]) -> Result<Option<Block>, String> {
        let Some(b) = self.inner.play(drive)? else { return Ok(None) };
        let rs = self.wiring.series_ohm();
        let mut out = Block { u: Vec::with_capacity(b.u.len()), i: Vec::with_capacity(b.i.len()) };
        let (mut cu, mut ci) = (0, 0);
        for (&u, &i) in b.u.iter().zip(&b.i) {
            let (ur, ir) = self.stream.push(u + rs * i, i);
            out.u.push(convert(ur, self.full_scale.0, &mut cu));
            out.i.push(convert(ir, self.full_scale.1, &mut ci));
        }
        self.clipped += cu + ci;
        // A clipped sample is a wrong sample: refused, as the sound card refuses it.
        if cu + ci > 0 {
            let (what, n, fsv, unit) =
                if cu > 0 { ("voltage", cu, self.full_scale.0, "V") } else { ("current", ci, self.full_scale.1, "A") };
            return Err(format!("the simulated card's {what} channel clipped ({n} samples at its full scale of {fsv} {unit}): raise its full scale (measure: --u-volts-fs, --i-volts-fs) or lower --max-volts"));
        }
        Ok(Some(out))
    }
    fn truth(&self) -> Option<Truth> {
        self.inner.truth()
    }
    fn controllable(&self) -> bool {
        self.inner.controllable()
    }
    fn describe(&self) -> String {
        format!("{} through a simulated card", self.inner.describe())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use coilscope_core::chain::hp;
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};

    /// Band-limited noise from rest (as after an ADC's anti-alias filter), 5 Hz .. ~6 kHz.
    fn noise(seed: u64, n: usize) -> Vec<f64> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let w: Vec<f64> = (0..n).map(|_| StandardNormal.sample(&mut rng)).collect();
        let mut y = hp(&hp(&w, 5.0, 48000.0), 5.0, 48000.0);
        for _ in 0..8 {
            let mut s = 0.0;
            for v in y.iter_mut() {
                s = 0.85 * s + 0.15 * *v;
                *v = s;
            }
        }
        y
    }

    fn rms(x: &[f64]) -> f64 {
        (x.iter().map(|v| v * v).sum::<f64>() / x.len() as f64).sqrt()
    }

    #[test]
    fn the_fractional_delay_is_flat_up_to_0_4_fs() {
        for frac in [0.0, 0.3, -0.45, 0.5] {
            let d = FracDelay::new(frac);
            let worst = (1..=80)
                .map(|k| {
                    let w = 2.0 * PI * 0.4 * k as f64 / 80.0;
                    let h: coilscope_core::Complex64 = d
                        .taps
                        .iter()
                        .enumerate()
                        .map(|(m, t)| coilscope_core::Complex64::from_polar(*t, -w * m as f64))
                        .sum();
                    (h - coilscope_core::Complex64::from_polar(1.0, -w * (LATENCY as f64 + frac))).norm()
                })
                .fold(0.0, f64::max);
            println!("frac {frac}: worst {worst:.2e}");
            assert!(worst < 1e-4, "frac {frac}: {worst:.2e}");
        }
    }

    #[test]
    fn the_streamed_chain_matches_the_whole_record_chain() {
        // The oracle: Chain::apply (an FFT delay over the whole record, the exact IIR).
        let fs = 48000.0;
        let n = 48000;
        let (u, i) = (noise(1, n), noise(2, n));
        let c = Chain {
            delay_i: 0.37 / fs,
            hp_u: 1.5,
            hp_i: 4.5,
            gain_i: Some(1.02),
            dc_u: 0.01,
            dc_i: -0.003,
            hum: Some(Hum { f: 50.0, u: vec![[1e-3, 0.3]], i: vec![[2e-4, -1.0], [0.0, 0.0], [1e-4, 0.5]] }),
            ..Default::default()
        };
        let (ua, ia) = c.apply(&u, &i, fs);
        let mut s = ChainStream::new(&c, fs).unwrap();
        let (us, is): (Vec<f64>, Vec<f64>) = u.iter().zip(&i).map(|(&a, &b)| s.push(a, b)).unzip();
        // The stream is LATENCY samples late, its hum and offset are not (they are added at
        // the record); compare the chain's filtered part.
        let (ua0, ia0) = Chain { hum: None, dc_u: 0.0, dc_i: 0.0, ..c.clone() }.apply(&u, &i, fs);
        let (mut eu, mut ei) = (0.0f64, 0.0f64);
        for m in 2000..n - 2000 {
            eu = eu.max((us[m + LATENCY] - (ua[m + LATENCY] - ua0[m + LATENCY]) - ua0[m]).abs());
            ei = ei.max((is[m + LATENCY] - (ia[m + LATENCY] - ia0[m + LATENCY]) - ia0[m]).abs());
        }
        assert!(eu < 1e-4 * rms(&ua0) && ei < 1e-4 * rms(&ia0), "{:.2e} {:.2e}", eu / rms(&ua0), ei / rms(&ia0));
    }

    #[test]
    fn the_corrector_undoes_a_card_to_a_common_residual_high_pass() {
        let fs = 48000.0;
        let n = 10 * 48000;
        let (u, i) = (noise(3, n), noise(4, n));
        let rs = 0.1;
        let w = SenseWiring::DriverPlusShunt { ohm: rs };
        for c in [
            Chain {
                delay_i: 0.3 / fs,
                hp_u: 2.0,
                hp_i: 4.0,
                gain_i: Some(0.985),
                dc_u: 0.01 * 4.0,
                dc_i: 0.01 * 4.0,
                ..Default::default()
            },
            Chain { delay_i: -0.45 / fs, hp_u: 5.0, hp_i: 1.0, dc_u: -0.02, ..Default::default() },
            Chain::default(),
        ] {
            let mut card = ChainStream::new(&c, fs).unwrap();
            let mut fix = ChainCorrector::new(&c, w, fs).unwrap();
            // The lead-in: silence through the card, with sensor noise.
            let lead = ChainCorrector::lead_in(fs);
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
            let mut sensor = move || 1e-4 * <StandardNormal as Distribution<f64>>::sample(&StandardNormal, &mut rng);
            let (lu, li): (Vec<f64>, Vec<f64>) =
                (0..lead).map(|_| card.push(0.0, 0.0)).map(|(a, b)| (a + sensor(), b + sensor())).unzip();
            let (dc_u, dc_i) = fix.offsets_from_silence(&lu, &li);
            assert!((dc_u - c.dc_u).abs() < 1e-5 && (dc_i - c.dc_i).abs() < 1e-5, "{dc_u} {dc_i}");
            let mut card = ChainStream::new(&c, fs).unwrap();
            let (uc, ic): (Vec<f64>, Vec<f64>) = u
                .iter()
                .zip(&i)
                .map(|(&a, &b)| {
                    let (ur, ir) = card.push(a + rs * b, b);
                    fix.push(ur, ir)
                })
                .unzip();
            // Both channels are the physical ones through RESIDUAL_HP, 2 LATENCY + delay late
            // (the card's LATENCY + its delay on the current; the corrector's LATENCY + the
            // delay on the voltage).
            let (ut, it) = (hp(&u, RESIDUAL_HP, fs), hp(&i, RESIDUAL_HP, fs));
            let tau = c.delay_i * fs;
            let (ud, id) = (
                coilscope_core::chain::delay(&ut, 2.0 * LATENCY as f64 + tau),
                coilscope_core::chain::delay(&it, 2.0 * LATENCY as f64 + tau),
            );
            // What the lead-in leaves of the offset (1e-4 noise over its 12 000 samples: about
            // 1e-6) is integrated into a ramp that the residual high-pass bends into a constant
            // of fc / RESIDUAL_HP times it (over its 16 s time constant); besides that, from
            // the start, within 1e-4 of the channel's RMS.
            let check = |a: &[f64], b: &[f64], fc: f64, what: &str| {
                let worst = (2000..n - 2000).map(|m| (a[m] - b[m]).abs()).fold(0.0, f64::max);
                let bound = 3.0 * 1e-4 / (lead as f64 / 2.0).sqrt() * fc.max(RESIDUAL_HP) / RESIDUAL_HP;
                assert!(
                    worst < bound + 1e-4 * rms(b),
                    "{c:?} {what}: {worst:.2e} (offset bound {bound:.1e}, rms {:.2e})",
                    rms(b)
                );
            };
            check(&uc, &ud, c.hp_u, "u");
            check(&ic, &id, c.hp_i, "i");
        }
    }

    #[test]
    fn a_delay_beyond_the_filter_is_refused() {
        let c = Chain { delay_i: 40.0 / 48000.0, ..Default::default() };
        let e = ChainCorrector::new(&c, SenseWiring::Terminals, 48000.0).err().unwrap();
        assert!(e.contains("delay_i"), "{e}");
    }
}

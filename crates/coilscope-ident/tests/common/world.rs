//! coilscope's own harsh virtual world for the identification sweeps: a driver with any of a
//! real driver's effects, recorded through a sound card's chain with sensor noise.
//!
//! The effects are scaled to the record (Le down 3 % and 0.5 % asymmetric at its peak current,
//! Rms up 35 % at its peak velocity, LOG creep lambda 0.05, L3 = 0.5 L2 and R3 = 3 R2), so
//! that every driver sees the same strength of each.

use coilscope_core::chain::{Chain, Hum};
use coilscope_core::excitation::{add_sensor_noise, generate, named_rng, Excitation, SignalSpec};
use coilscope_core::params::Creep;
use coilscope_core::simulate::{gain_for_peak, SimOptions, Summary};
use coilscope_core::{embedded_driver, Parameters, Poly};
use coilscope_ident::linear::Effects;
use rand::Rng;

/// An embedded driver, or one of `testdata/drivers/` (the large coil, the microspeakers).
pub fn driver(name: &str) -> Parameters {
    embedded_driver(name).unwrap_or_else(|| {
        let path = format!("{}/../../testdata/drivers/{name}.json", env!("CARGO_MANIFEST_DIR"));
        Parameters::from_json_str(&std::fs::read_to_string(&path).unwrap(), &path).unwrap()
    })
}

/// A record of `p` as `coilscope simulate` makes it: `seconds` of pink noise (10 Hz - 8 kHz,
/// crest 3) at `fs`, scaled so the true peak reaches `share` of the range, coil heating on, 70 dB
/// sensor noise. Returns (u, i, the true trace's summary).
pub fn pink_record(p: &Parameters, fs: f64, seconds: f64, share: f64, seed: u64) -> (Vec<f64>, Vec<f64>, Summary) {
    let [lo, hi] = p.x_range.unwrap();
    let unit = generate(
        &Excitation::Pink { f_lo: 10.0, f_hi: 8000.0, crest: Some(3.0) },
        &SignalSpec { fs, seconds, rms: 1.0, fade: 0.05, seed },
    )
    .unwrap();
    let (_, tr) = gain_for_peak(p, fs, &unit, share * hi.min(-lo), &SimOptions::default()).unwrap();
    let s = tr.summary();
    let (mut u, mut i) = (tr.u, tr.i);
    add_sensor_noise(&mut u, 70.0, seed, "sensor-noise/voltage");
    add_sensor_noise(&mut i, 70.0, seed, "sensor-noise/current");
    (u, i, s)
}

pub fn peak(s: &[f64]) -> f64 {
    s.iter().fold(0.0f64, |a, v| a.max(v.abs()))
}

/// A record of the harsh world and the truth behind it.
pub struct Record {
    /// The recorded channels (through the chain, with sensor noise).
    pub u: Vec<f64>,
    pub i: Vec<f64>,
    pub fs: f64,
    /// The driver as simulated (its effects included).
    pub truth: Parameters,
    /// The simulated trace's summary (reached range).
    pub summary: Summary,
    /// The effects' true strengths: creep lambda, Le(i)'s g2, Rms(v)'s c2.
    pub lambda: f64,
    pub g2: f64,
    pub c2: f64,
    /// The chain the record went through (ideal when none).
    pub chain: Chain,
}

/// 8 s (or `seconds`) of pink noise (10 Hz - 8 kHz, crest factor 3) at `fs` reaching 85 % of
/// `name`'s x_range, coil heating on, with `effects`, through `card(u, i)` (the physical
/// channels give the card its scale), then 70 dB sensor noise on each channel.
pub fn record(
    name: &str,
    seed: u64,
    effects: Effects,
    fs: f64,
    seconds: f64,
    card: impl Fn(&[f64], &[f64]) -> Chain,
) -> Record {
    let plain = driver(name);
    let [lo, hi] = plain.x_range.unwrap();
    let target = 0.85 * hi.min(-lo);
    let unit = generate(
        &Excitation::Pink { f_lo: 10.0, f_hi: 8000.0, crest: Some(3.0) },
        &SignalSpec { fs, seconds, rms: 1.0, fade: 0.05, seed },
    )
    .unwrap();
    // The peak current and velocity of the plain driver at this level scale the effects.
    let (_, tr0) = gain_for_peak(&plain, fs, &unit, target, &SimOptions::default()).unwrap();
    let (i_pk, v_pk) = (peak(&tr0.i), peak(&tr0.v));
    let (l2, r2) = plain.l2r2.as_ref().map(|(l, r)| (l.c[0], r.c[0])).unwrap();
    let (lambda, g2, c2) = (0.05, -0.03 / (i_pk * i_pk), 0.35 * plain.rms / (v_pk * v_pk));
    let truth = Parameters {
        creep: effects.creep.then_some(Creep { lambda, f_ref: None }),
        l3r3: effects.lr3.then_some((0.5 * l2, 3.0 * r2)),
        le_i: effects.le_i.then(|| Poly { c: vec![1.0, 0.005 / i_pk, g2] }),
        rms_v: effects.rms_v.then(|| Poly { c: vec![plain.rms, 0.0, c2] }),
        ..plain.clone()
    };
    let (_, tr) = gain_for_peak(&truth, fs, &unit, target, &SimOptions::default()).unwrap();
    let summary = tr.summary();
    let chain = card(&tr.u, &tr.i);
    // An ideal card leaves the channels as they are, to the bit (a zero corner's filter is a
    // wire only up to rounding).
    let (mut u, mut i) = if chain.is_ideal() { (tr.u, tr.i) } else { chain.apply(&tr.u, &tr.i, fs) };
    add_sensor_noise(&mut u, 70.0, seed, "sensor-noise/voltage");
    add_sensor_noise(&mut i, 70.0, seed, "sensor-noise/current");
    Record { u, i, fs, truth, summary, lambda, g2, c2, chain }
}

/// What a sound card may do to the channels, within the bounds the chain estimate is tested to.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Card {
    /// A wire.
    Ideal,
    /// The current channel 0.1-0.5 sample late.
    CurrentLate,
    /// The voltage channel 0.1-0.5 sample late.
    VoltageLate,
    /// First-order AC coupling at 1-5 Hz on each channel.
    Coupling,
    /// Offsets of up to 1 % of each channel's peak, either sign.
    Offsets,
    /// Mains hum (50 or 60 Hz, the third harmonic at half) at -60 dB of each channel's RMS.
    Hum,
    /// All of the above at once (either channel late).
    All,
}

impl Card {
    /// The card's chain for physical channels `u`, `i` at `fs`; the values drawn from the
    /// named RNG `card/<seed>` within those bounds.
    pub fn chain(self, seed: u64, u: &[f64], i: &[f64], fs: f64) -> Chain {
        let mut rng = named_rng(seed, "card");
        let mut c = Chain::default();
        let late = rng.random_range(0.1..0.5) / fs;
        let (fu, fi) = (rng.random_range(1.0..5.0), rng.random_range(1.0..5.0));
        let mut offset =
            |scale: f64| (if rng.random_bool(0.5) { 1.0 } else { -1.0 }) * rng.random_range(0.2..1.0) * 1e-2 * scale;
        let (du, di) = (offset(peak(u)), offset(peak(i)));
        let mains = if rng.random_bool(0.5) { 50.0 } else { 60.0 };
        // -60 dB of the channel's RMS: a line of peak a has RMS a / sqrt(2); the third harmonic
        // at half of the fundamental.
        let rms = coilscope_core::simulate::rms;
        let (au, ai) = (1e-3 * rms(u) * 2f64.sqrt() / 1.25f64.sqrt(), 1e-3 * rms(i) * 2f64.sqrt() / 1.25f64.sqrt());
        // 6.28, not TAU: the seeded phases of the recorded cases stay the ones their figures
        // came from.
        #[allow(clippy::approx_constant)]
        let ph: [f64; 4] = std::array::from_fn(|_| rng.random_range(0.0..6.28));
        let hum = Hum {
            f: mains,
            u: vec![[au, ph[0]], [0.0, 0.0], [0.5 * au, ph[1]]],
            i: vec![[ai, ph[2]], [0.0, 0.0], [0.5 * ai, ph[3]]],
        };
        let voltage_late = rng.random_bool(0.5);
        match self {
            Card::Ideal => {}
            Card::CurrentLate => c.delay_i = late,
            Card::VoltageLate => c.delay_i = -late,
            Card::Coupling => (c.hp_u, c.hp_i) = (fu, fi),
            Card::Offsets => (c.dc_u, c.dc_i) = (du, di),
            Card::Hum => c.hum = Some(hum),
            Card::All => {
                c.delay_i = if voltage_late { -late } else { late };
                (c.hp_u, c.hp_i, c.dc_u, c.dc_i) = (fu, fi, du, di);
                c.hum = Some(hum);
            }
        }
        c
    }
}

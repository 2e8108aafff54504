//! Wall time of the fits that end a long measurement and a card's calibration, one core:
//! `cargo bench -p coilscope-ident --bench fits`.
//!
//! - `thermal_fit_10min`: [`fit_thermal`] on a 10-minute track of 0.1 s blocks (6000), the
//!   length `measure --duration 600` tracks: SB17's network (Rtv 3.2 K/W, Ctv 9 J/K, Rtm
//!   1.1 K/W, Ctm 700 J/K) heated at 3 W for 5 minutes and at a sixteenth of that for the
//!   rest, tracked 0.2 s late with 0.02 K of noise; `convection` adds rv 1.5 s/m with the
//!   coil's speed following the level (the fit then also tries the convection variant).
//! - `calibrate_40s`: [`calibrate`] on 40 s at 48 kHz of pink noise through a 4.7 ohm
//!   resistor and a card with 0.3 samples of delay, 2 and 4 Hz corners and 80 dB noise.

use coilscope_core::chain::Chain;
use coilscope_core::excitation::{add_sensor_noise, generate, Excitation, SignalSpec};
use coilscope_core::model::ThermalModel;
use coilscope_ident::calibrate::calibrate;
use coilscope_ident::thermal::{fit_thermal, ThermalTrack};
use std::sync::OnceLock;

fn main() {
    divan::main();
}

fn track(rv: f64) -> ThermalTrack {
    let m = ThermalModel::new(0.00393, 3.2, 9.0, 1.1, 700.0, rv);
    let mut tr = ThermalTrack::default();
    let mut y = [0.0, 0.0];
    let mut clean = vec![];
    let mut rng = 7u64;
    for k in 1..=6000 {
        let t = k as f64 * 0.1;
        let loud = t < 300.0;
        let (pv, pm, speed) = if loud { (3.0, 0.2, 0.4) } else { (3.0 / 16.0, 0.2 / 16.0, 0.1) };
        y = m.held_step(y, pv, pm, speed, 0.1);
        clean.push(y[0]);
        rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        let noise = 0.02 * 3.46 * ((rng >> 11) as f64 / (1u64 << 53) as f64 - 0.5);
        tr.t.push(t);
        tr.pv.push(pv);
        tr.pm.push(pm);
        tr.speed.push(speed);
        tr.dtv.push(if k > 2 { clean[k - 3] } else { 0.0 } + noise);
    }
    tr
}

#[divan::bench(args = [false, true], sample_count = 3, sample_size = 1)]
fn thermal_fit_10min(b: divan::Bencher, convection: bool) {
    let tr = track(if convection { 1.5 } else { 0.0 });
    b.bench_local(|| {
        let f = fit_thermal(&tr, [3.0, 10.0, 1.5, 400.0], 0.0).unwrap();
        assert!((f.values[0] / 3.2 - 1.0).abs() < 0.05, "Rtv {}", f.values[0]);
        f
    });
}

#[divan::bench(sample_count = 3, sample_size = 1)]
fn calibrate_40s(b: divan::Bencher) {
    static REC: OnceLock<(Vec<f64>, Vec<f64>)> = OnceLock::new();
    let fs = 48000.0;
    let (u, i) = REC.get_or_init(|| {
        let u = generate(
            &Excitation::Pink { f_lo: 0.3, f_hi: 0.45 * fs, crest: None },
            &SignalSpec { fs, seconds: 40.0, rms: 1.0, fade: 0.0, seed: 1 },
        )
        .unwrap();
        let i: Vec<f64> = u.iter().map(|v| v / 4.7).collect();
        let chain = Chain { delay_i: 0.3 / fs, hp_u: 2.0, hp_i: 4.0, ..Default::default() };
        let (mut ur, mut ir) = chain.apply(&u, &i, fs);
        add_sensor_noise(&mut ur, 80.0, 1, "sensor-noise/voltage");
        add_sensor_noise(&mut ir, 80.0, 1, "sensor-noise/current");
        (ur, ir)
    });
    b.bench_local(|| {
        let c = calibrate(u, i, fs, 4.7, "bench").unwrap();
        assert!((c.chain.hp_i / 4.0 - 1.0).abs() < 0.05, "hp_i {}", c.chain.hp_i);
        c
    });
}

//! `measure --card` uses the calibration. The card path, headless: the virtual
//! driver recorded through a simulated sound card of our own ([`SimulatedCard`]: the current
//! 0.3 sample late, AC coupling at 2 Hz and 4 Hz, the current channel 1.5 % hot, offsets of
//! 50 mV and 10 mA (1 % of the channels' peaks at full level), 50 Hz hum 60 dB below the
//! small-signal stage's channels, a 0.1 ohm shunt in the voltage channel, 24-bit converters
//! at 100 V and 30 A full scale), measured through [`Corrected`] with the card's chain file.
//!
//! The measurement does not remove hum: at -36 dB of the small-signal stage (3 mV, 0.5 mA)
//! the level ramp stalls and the run does not converge (open). A clipped converter is refused
//! (at 20 V full scale PTT4's IEC-noise peaks clip, and the fit was off by 3 % before this was
//! caught).
//!
//! Bounds (the measurement's accuracy bounds, as in `measure_truth`): over the range reached, Bl(x),
//! Kms(x) within 2 %, Le(x) within 5 %; Re (cold) and Rms within 1 %. Without the correction,
//! the same card moves Re by more than 2 % (the gain and the shunt).

use coilscope_core::chain::{Chain, Hum, SenseWiring};
use coilscope_core::excitation::Excitation;
use coilscope_core::{embedded_driver, Parameters, Poly};
use coilscope_measure::card::{Corrected, SimulatedCard};
use coilscope_measure::device::{Device, VirtualDevice};
use coilscope_measure::signal::Source;
use coilscope_measure::{measure, MeasureOptions, Measurement};
use std::path::Path;

use coilscope_testkit::slice;

fn worst(f: &Poly, g: &Poly, [lo, hi]: [f64; 2]) -> f64 {
    (0..=400)
        .map(|k| lo + (hi - lo) * k as f64 / 400.0)
        .map(|x| (f.eval(x) - g.eval(x)).abs())
        .fold(0.0, coilscope_testkit::check::nan_max)
        / g.eval(0.0).abs()
}

fn card(fs: f64) -> Chain {
    Chain {
        delay_i: 0.3 / fs,
        hp_u: 2.0,
        hp_i: 4.0,
        gain_i: Some(1.015),
        dc_u: 0.05,
        dc_i: 0.01,
        hum: Some(Hum { f: 50.0, u: vec![[3e-4, 0.4]], i: vec![[5e-5, -1.2], [0.0, 0.0], [2e-5, 0.3]] }),
        ..Default::default()
    }
}

const WIRING: SenseWiring = SenseWiring::DriverPlusShunt { ohm: 0.1 };

fn run(p: &Parameters, device: &mut dyn Device) -> Measurement {
    let [lo, hi] = p.x_range.unwrap();
    let mut src = Source::noise(&Excitation::Iec, 48000.0, 2).unwrap();
    let opts = MeasureOptions { mms: p.mms, target_x: Some(0.85 * hi.min(-lo)), ..Default::default() };
    measure(device, &mut src, &opts, None, |_| {}).unwrap_or_else(|e| panic!("{e}"))
}

/// `(Bl, Kms, Le, Re cold, Rms)` relative errors.
fn errors(m: &Measurement, p: &Parameters) -> [f64; 5] {
    let (q, r) = (&m.params, m.x_range);
    [
        worst(&q.bl, &p.bl, r),
        worst(&q.kms, &p.kms, r),
        worst(&q.le, &p.le, r),
        (m.re_cold / p.re - 1.0).abs(),
        (q.rms / p.rms - 1.0).abs(),
    ]
}

#[test]
fn measure_through_a_calibrated_card_gives_the_driver() {
    let fs = 48000.0;
    let mut bad = vec![];
    for name in ["sb17cac35-4", "ptt4.0w04-01a"] {
        let p = embedded_driver(name).unwrap();
        let virt = VirtualDevice::new(&p, fs, (1e-4, 1e-4), 1).unwrap();
        let sim = SimulatedCard::new(virt, &card(fs), WIRING, (100.0, 30.0)).unwrap();
        // The calibration knows the chain's delay, corners and gain, not this run's offsets
        // or hum (as `coilscope calibrate` writes it).
        let cal = Chain { dc_u: 0.0, dc_i: 0.0, hum: None, ..card(fs) };
        let mut dev = Corrected::new(sim, &cal, WIRING).unwrap();
        let m = run(&p, &mut dev);
        let (dc_u, dc_i) = dev.offsets();
        let e = errors(&m, &p);
        println!(
            "{name}: {} in {:.1} s, offsets {dc_u:.4} V {dc_i:.4} A; Bl {:.3} %, Kms {:.3} %, Le {:.3} %, Re(cold) {:.3} %, Rms {:.3} %; x {:.2}..{:.2} mm",
            m.stop_reason,
            m.seconds,
            100.0 * e[0],
            100.0 * e[1],
            100.0 * e[2],
            100.0 * e[3],
            100.0 * e[4],
            m.x_range[0] * 1e3,
            m.x_range[1] * 1e3
        );
        if !m.converged {
            bad.push(format!("{name}: {}", m.stop_reason));
        }
        if !(e[0] <= 0.02 && e[1] <= 0.02 && e[2] <= 0.05 && e[3] <= 0.01 && e[4] <= 0.01) {
            bad.push(format!(
                "{name}: Bl {:.4}, Kms {:.4}, Le {:.4}, Re {:.4}, Rms {:.4}",
                e[0], e[1], e[2], e[3], e[4]
            ));
        }
        if (dc_u - 0.05).abs() > 1e-3 || (dc_i - 0.01).abs() > 1e-4 {
            bad.push(format!("{name}: offsets {dc_u} V, {dc_i} A (true 0.05, 0.01)"));
        }
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

#[test]
fn the_same_card_without_its_calibration_is_off() {
    let fs = 48000.0;
    let p = embedded_driver("sb17cac35-4").unwrap();
    let virt = VirtualDevice::new(&p, fs, (1e-4, 1e-4), 1).unwrap();
    // The offsets alone would stop the run (a DC current through the driver's model); the
    // gain and the shunt are what a careless user would not see.
    let c = Chain { dc_u: 0.0, dc_i: 0.0, hum: None, ..card(fs) };
    let mut dev = SimulatedCard::new(virt, &c, WIRING, (100.0, 30.0)).unwrap();
    let m = run(&p, &mut dev);
    let e = errors(&m, &p);
    println!(
        "uncorrected: Bl {:.3} %, Kms {:.3} %, Le {:.3} %, Re(cold) {:.3} %, Rms {:.3} %",
        100.0 * e[0],
        100.0 * e[1],
        100.0 * e[2],
        100.0 * e[3],
        100.0 * e[4]
    );
    // Off: at least two of them more than twice the calibrated path's bounds (Bl, Kms 2 %,
    // Le 5 %, Re, Rms 1 %). (Through the IEC Table II signal: Le 19.7 %, Rms 17.8 %, Re
    // 1.13 %; through the signal before it, Re was 2 % off too.)
    let bounds = [0.02, 0.02, 0.05, 0.01, 0.01];
    let off = e.iter().zip(bounds).filter(|(v, b)| **v > 2.0 * b).count();
    assert!(off >= 2, "only {off} of Bl, Kms, Le, Re, Rms are off by more than twice their bounds: {e:?}");
}

/// Off the tested path: other drivers (18WU, the 0.1 g microspeaker of `testdata/drivers`),
/// rates (44.1, 96 kHz), seeds and cards (the delay on either side, corners 1-5 Hz, gains
/// 0.98-1.02, either wiring). Every run must either converge within the bounds above or stop
/// with a reason that is not success (never a converged wrong answer); the bundled drivers
/// must converge. One card per CI run (`COILSCOPE_SWEEP_SLICE`); measured 4 of 4.
#[test]
#[ignore = "release-profile sweep: cargo test --release -p coilscope-measure --test card_path -- --ignored"]
fn cards_drivers_rates_and_seeds() {
    let micro = coilscope_io::load_parameters(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../testdata/drivers/microspeaker-0g1.json").to_str().unwrap(),
    )
    .unwrap();
    let cases: Vec<(Parameters, f64, u64, Chain, SenseWiring)> = slice::in_slice(
        "card_path sweep",
        vec![
            (
                embedded_driver("18wu-4741t-00").unwrap(),
                48000.0,
                3,
                Chain {
                    delay_i: -0.4 / 48000.0,
                    hp_u: 5.0,
                    hp_i: 1.0,
                    gain_i: Some(0.98),
                    dc_u: -0.1,
                    dc_i: 0.02,
                    ..Default::default()
                },
                WIRING,
            ),
            (
                embedded_driver("ptt4.0w04-01a").unwrap(),
                44100.0,
                4,
                Chain {
                    delay_i: 0.5 / 44100.0,
                    hp_u: 1.0,
                    hp_i: 3.0,
                    gain_i: Some(1.02),
                    dc_u: 0.02,
                    dc_i: -0.005,
                    ..Default::default()
                },
                SenseWiring::Terminals,
            ),
            (
                embedded_driver("sb17cac35-4").unwrap(),
                96000.0,
                5,
                Chain {
                    delay_i: 0.1 / 96000.0,
                    hp_u: 3.0,
                    hp_i: 5.0,
                    gain_i: Some(1.01),
                    dc_u: 0.01,
                    dc_i: 0.01,
                    ..Default::default()
                },
                SenseWiring::DriverPlusShunt { ohm: 0.22 },
            ),
            (
                micro,
                48000.0,
                6,
                Chain {
                    delay_i: 0.3 / 48000.0,
                    hp_u: 2.0,
                    hp_i: 4.0,
                    gain_i: Some(1.015),
                    dc_u: 0.005,
                    dc_i: 0.001,
                    ..Default::default()
                },
                SenseWiring::DriverPlusShunt { ohm: 0.5 },
            ),
        ],
    );
    let mut bad = vec![];
    let mut passed = 0;
    for (p, fs, seed, c, w) in cases {
        let name = p.name.clone().unwrap_or_default();
        let virt = VirtualDevice::new(&p, fs, (1e-4, 1e-4), seed).unwrap();
        let sim = SimulatedCard::new(virt, &c, w, (100.0, 30.0)).unwrap();
        let mut dev = Corrected::new(sim, &Chain { dc_u: 0.0, dc_i: 0.0, ..c.clone() }, w).unwrap();
        let [lo, hi] = p.x_range.unwrap();
        let mut src = Source::noise(&Excitation::Iec, fs, seed).unwrap();
        let opts = MeasureOptions { mms: p.mms, target_x: Some(0.85 * hi.min(-lo)), ..Default::default() };
        let m = match measure(&mut dev, &mut src, &opts, None, |_| {}) {
            Ok(m) => m,
            Err(e) => {
                bad.push(format!("{name} at {fs} Hz: {e}"));
                continue;
            }
        };
        let e = errors(&m, &p);
        println!(
            "{name} at {fs} Hz, {}: {} in {:.1} s; Bl {:.3} %, Kms {:.3} %, Le {:.3} %, Re {:.3} %, Rms {:.3} %",
            w.name(),
            if m.converged { "converged" } else { "not converged" },
            m.seconds,
            100.0 * e[0],
            100.0 * e[1],
            100.0 * e[2],
            100.0 * e[3],
            100.0 * e[4]
        );
        let within = e[0] <= 0.02 && e[1] <= 0.02 && e[2] <= 0.05 && e[3] <= 0.01 && e[4] <= 0.01;
        let bundled = !name.to_lowercase().contains("micro");
        if m.converged && !within {
            bad.push(format!("{name} at {fs} Hz: converged on a wrong answer: {e:?}"));
        } else if bundled && !m.converged {
            bad.push(format!("{name} at {fs} Hz: {}", m.stop_reason));
        } else {
            passed += 1;
        }
    }
    println!("{passed} of {} passed", passed + bad.len());
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

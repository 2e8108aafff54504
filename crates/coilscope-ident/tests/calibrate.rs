//! `calibrate` recovers a sound card's chain from a simulated resistor (or
//! loopback) record: the delay within 0.01 sample, the corners within 5 %, the gain within
//! 0.1 %, with the truth inside 3 sd. Equal corners cancel in `U/I` and are reported as not
//! resolved. Swept over delays on either channel (negative: the
//! voltage late), corners 0 (DC-coupled) to 5 Hz, rates 44.1 / 48 / 96 kHz, with offsets and
//! hum on the channels and 80 dB sensor noise.

use coilscope_core::chain::{Chain, Hum};
use coilscope_core::excitation::{add_sensor_noise, generate, Excitation, SignalSpec};
use coilscope_ident::calibrate::calibrate;

struct Case {
    fs: f64,
    delay: f64,
    hp_u: f64,
    hp_i: f64,
    gain: f64,
    resistor: f64,
    seed: u64,
}

/// A resistor record through `c`'s chain: 40 s of pink noise from 0.3 Hz, 1 V RMS.
fn record(c: &Case) -> (Vec<f64>, Vec<f64>, Chain) {
    let u = generate(
        &Excitation::Pink { f_lo: 0.3, f_hi: 0.45 * c.fs, crest: None },
        &SignalSpec { fs: c.fs, seconds: 40.0, rms: 1.0, fade: 0.0, seed: c.seed },
    )
    .unwrap();
    let i: Vec<f64> = u.iter().map(|v| v / c.resistor).collect();
    let peak_i = i.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let chain = Chain {
        delay_i: c.delay / c.fs,
        hp_u: c.hp_u,
        hp_i: c.hp_i,
        gain_i: Some(c.gain),
        dc_u: 0.004,
        dc_i: -0.01 * peak_i,
        hum: Some(Hum {
            f: 50.0,
            u: vec![[1e-3, 0.3]],
            i: vec![[1e-3 * peak_i, 1.0], [0.0, 0.0], [3e-4 * peak_i, -0.5]],
        }),
        ..Default::default()
    };
    let (mut ur, mut ir) = chain.apply(&u, &i, c.fs);
    add_sensor_noise(&mut ur, 80.0, c.seed, "sensor-noise/voltage");
    add_sensor_noise(&mut ir, 80.0, c.seed, "sensor-noise/current");
    (ur, ir, chain)
}

#[test]
fn calibrate_recovers_delay_corners_and_gain_over_a_sweep() {
    let cases = [
        Case { fs: 48000.0, delay: 0.3, hp_u: 2.0, hp_i: 4.0, gain: 1.0, resistor: 4.7, seed: 1 },
        Case { fs: 48000.0, delay: 0.1, hp_u: 1.0, hp_i: 5.0, gain: 0.98, resistor: 4.7, seed: 2 },
        Case { fs: 48000.0, delay: -0.5, hp_u: 5.0, hp_i: 1.5, gain: 1.02, resistor: 8.2, seed: 3 },
        Case { fs: 44100.0, delay: 0.5, hp_u: 3.0, hp_i: 3.0, gain: 1.0, resistor: 1.0, seed: 4 },
        Case { fs: 96000.0, delay: -0.2, hp_u: 1.5, hp_i: 0.0, gain: 0.995, resistor: 2.2, seed: 5 },
        Case { fs: 96000.0, delay: 0.0, hp_u: 0.0, hp_i: 2.5, gain: 1.0, resistor: 4.7, seed: 6 },
    ];
    for c in &cases {
        let (u, i, truth) = record(c);
        let cal = calibrate(&u, &i, c.fs, c.resistor, "resistor.wav").unwrap();
        let got = &cal.chain;
        if c.hp_u == c.hp_i {
            // Equal corners cancel in U/I: not resolvable by a resistor, and said so.
            assert!(got.hp_u == 0.0 && got.hp_i == 0.0 && !got.fitted.iter().any(|k| k.starts_with("hp")), "{:?}", got);
            assert!(got.other["note"].as_str().unwrap().contains("only their difference"));
        }
        let sd = |k: &str| got.sd[k];
        let label =
            format!("{} Hz, delay {} sample, corners {} / {} Hz, gain {}", c.fs, c.delay, c.hp_u, c.hp_i, c.gain);
        println!(
            "{label}: delay {:.4} +- {:.4} sample, hp_u {:.3} +- {:.3}, hp_i {:.3} +- {:.3} Hz, gain {:.5} +- {:.1e}, residual {:.2}x noise, {} bins",
            got.delay_i * c.fs,
            sd("delay_i") * c.fs,
            got.hp_u,
            got.sd.get("hp_u").copied().unwrap_or(f64::NAN),
            got.hp_i,
            got.sd.get("hp_i").copied().unwrap_or(f64::NAN),
            got.gain_i.unwrap(),
            sd("gain_i"),
            cal.residual_in_noise,
            cal.bins
        );
        assert!((got.delay_i - truth.delay_i).abs() * c.fs < 0.01, "{label}: delay {} sample", got.delay_i * c.fs);
        let resolved = if c.hp_u == c.hp_i {
            vec![]
        } else {
            vec![("hp_u", got.hp_u, truth.hp_u), ("hp_i", got.hp_i, truth.hp_i)]
        };
        for (k, g, t) in resolved {
            // 5 %, or 0.05 Hz for a DC-coupled channel.
            assert!((g - t).abs() <= (0.05 * t).max(0.05), "{label}: {k} {g:.3} Hz");
            assert!((g - t).abs() <= 3.0 * sd(k) + 1e-3, "{label}: {k} {g:.4} +- {:.4} Hz, truth {t}", sd(k));
        }
        let g = got.gain_i.unwrap();
        assert!((g / c.gain - 1.0).abs() < 1e-3, "{label}: gain {g}");
        assert!((g - c.gain).abs() <= 3.0 * sd("gain_i"), "{label}: gain {g} +- {:.2e}", sd("gain_i"));
        assert!(
            (got.delay_i - truth.delay_i).abs() <= 3.0 * sd("delay_i"),
            "{label}: delay {} +- {} sample",
            got.delay_i * c.fs,
            sd("delay_i") * c.fs
        );
    }
}

#[test]
fn calibrate_refuses_a_driver_an_inverted_current_and_a_short_record() {
    let c = Case { fs: 48000.0, delay: 0.3, hp_u: 2.0, hp_i: 4.0, gain: 1.0, resistor: 4.7, seed: 7 };
    let (u, i, _) = record(&c);
    let inv: Vec<f64> = i.iter().map(|v| -v).collect();
    let e = calibrate(&u, &inv, c.fs, 4.7, "r.wav").unwrap_err();
    assert!(e.contains("r.wav") && e.contains("inverted"), "{e}");
    let e = calibrate(&u[..48000 * 10], &i[..48000 * 10], c.fs, 4.7, "r.wav").unwrap_err();
    assert!(e.contains("too short"), "{e}");
    // A driver instead of a resistor.
    let p = coilscope_core::embedded_driver("sb17cac35-4").unwrap();
    let uu = generate(
        &Excitation::Pink { f_lo: 0.3, f_hi: 20000.0, crest: None },
        &SignalSpec { fs: 48000.0, seconds: 40.0, rms: 0.3, fade: 0.05, seed: 8 },
    )
    .unwrap();
    let tr = coilscope_core::simulate(&p, 48000.0, &uu, &coilscope_core::SimOptions::default()).unwrap();
    let e = calibrate(&tr.u, &tr.i, 48000.0, 3.37, "driver.wav").unwrap_err();
    assert!(e.contains("does not look like a resistor"), "{e}");
}

//! Virtual measurements against the truth.
//!
//! The virtual transducer is the core simulator with the driver's thermal model and sensor
//! noise of 0.1 mV / 0.1 mA rms; the excitation is IEC 60268-1 noise unless said otherwise.
//! Tolerances (the identification's accuracy bounds): over the range reached at the final level,
//! Bl(x), Kms(x) within 2 %, Le(x) within 5 % of the true value at rest; Re (cold), Rms within
//! 1 %. Protection: the true peak excursion and voice-coil rise stay within 5 % of their limits.

use coilscope_core::excitation::Excitation;
use coilscope_core::{embedded_driver, Parameters, Poly};
use coilscope_measure::device::VirtualDevice;
use coilscope_measure::engine::kms_limit_crossing;
use coilscope_measure::signal::Source;
use coilscope_measure::{measure, MeasureOptions, Measurement};

fn worst(f: &Poly, g: &Poly, [lo, hi]: [f64; 2]) -> f64 {
    (0..=400)
        .map(|k| lo + (hi - lo) * k as f64 / 400.0)
        .map(|x| (f.eval(x) - g.eval(x)).abs())
        .fold(0.0, coilscope_testkit::check::nan_max)
        / g.eval(0.0).abs()
}

fn run(p: &Parameters, source: &mut Source, opts: MeasureOptions, seed: u64) -> Measurement {
    let mut dev = VirtualDevice::new(p, 48000.0, (1e-4, 1e-4), seed).unwrap();
    match measure(&mut dev, source, &opts, None, |_| {}) {
        Ok(m) => m,
        Err(e) => panic!("{e}"),
    }
}

fn assert_truth(label: &str, m: &Measurement, p: &Parameters) {
    let q = &m.params;
    let r = m.x_range;
    let (e_bl, e_k, e_le) = (worst(&q.bl, &p.bl, r), worst(&q.kms, &p.kms, r), worst(&q.le, &p.le, r));
    let (e_re, e_rms) = ((m.re_cold / p.re - 1.0).abs(), (q.rms / p.rms - 1.0).abs());
    let e_re_small = m.small.re / p.re - 1.0;
    println!(
        "{label}: {} in {:.1} s; Bl {:.3} %, Kms {:.3} %, Le {:.3} %, Re(cold) {:.3} % (small-signal fit {:.3} %), Rms {:.3} %, x {:.2}..{:.2} mm, true peak {:.2} mm, true dT max {:.1} K, limited by {}",
        m.stop_reason,
        m.seconds,
        100.0 * e_bl,
        100.0 * e_k,
        100.0 * e_le,
        100.0 * e_re,
        100.0 * e_re_small,
        100.0 * e_rms,
        r[0] * 1e3,
        r[1] * 1e3,
        m.truth.unwrap().x_peak * 1e3,
        m.truth.unwrap().dtv_max,
        m.limited_by
    );
    assert!(m.converged, "{label}: {}", m.stop_reason);
    assert!(m.seconds <= 60.0, "{label}: {} s", m.seconds);
    assert!(e_bl <= 0.02 && e_k <= 0.02 && e_le <= 0.05, "{label}: Bl {e_bl}, Kms {e_k}, Le {e_le}");
    assert!(e_re <= 0.01 && e_rms <= 0.01, "{label}: Re {e_re}, Rms {e_rms}");
    // `Re` of the result is the cold value (the truth at ambient), not the hot one.
    let e_re_param = (q.re / p.re - 1.0).abs();
    assert!(e_re_param <= 0.001, "{label}: parameters.Re {} vs cold truth {}", q.re, p.re);
    let j = m.result().to_json_value();
    assert_eq!(j["parameters"]["Re"].as_f64(), Some(q.re));
    assert!(j["thermal"]["Re_end"].as_f64().unwrap() >= q.re, "{label}: the hot Re lives under thermal");
}

fn converges_from_silence(names: &[&str]) {
    for &name in names {
        let p = embedded_driver(name).unwrap();
        let [lo, hi] = p.x_range.unwrap();
        let target = 0.85 * hi.min(-lo);
        let mut src = Source::noise(&Excitation::Iec, 48000.0, 2).unwrap();
        let mut dev = VirtualDevice::new(&p, 48000.0, (1e-4, 1e-4), 1).unwrap();
        let mut etas = Vec::new();
        let opts = MeasureOptions { mms: p.mms, target_x: Some(target), ..Default::default() };
        let m = match measure(&mut dev, &mut src, &opts, None, |l| etas.push((l.t, l.eta, l.end, l.update.is_some()))) {
            Ok(m) => m,
            Err(e) => panic!("{name}: {e}"),
        };
        assert_truth(name, &m, &p);
        // The terminal's ETA: given once the level holds, never past the run's end, counting
        // down between updates, and the one given in the last second before convergence
        // pointing at it within 1.5 s. (Earlier ones are estimates from the bands' and the
        // changes' rates, not checked against the end: the level may still move.)
        let given: Vec<(f64, f64, bool)> = etas.iter().filter_map(|&(t, e, _, up)| e.map(|e| (t, e, up))).collect();
        let shown: Vec<String> = given.iter().step_by(10).map(|(t, e, _)| format!("{t:.0}:{e:.1}")).collect();
        println!("{name}: ETA (t: s left) {}, converged at {:.1} s", shown.join(" "), m.seconds);
        assert!(!given.is_empty(), "{name}: no ETA in a run that converged");
        assert!(etas.iter().all(|&(t, e, end, _)| e.is_none_or(|e| e >= 0.0 && t + e <= end + 1e-9) && end == 60.0));
        for pair in given.windows(2) {
            let ((t0, e0, _), (t1, e1, up)) = (pair[0], pair[1]);
            let counted = ((t0 + e0) - (t1 + e1)).abs() < 1e-6 || (e1 == 0.0 && e0 <= t1 - t0 + 1e-6);
            assert!(counted || up || t1 - t0 > 0.11, "{name}: the ETA jumped between updates: {pair:?}");
        }
        if let Some(&(t, e, _)) = given.last().filter(|(t, _, _)| *t >= m.seconds - 1.0) {
            assert!(
                (t + e - m.seconds).abs() <= 1.5,
                "{name}: at {t} s the ETA said {e} s, converged at {}",
                m.seconds
            );
        }
        let truth = m.truth.unwrap();
        assert!(
            truth.x_peak <= 1.05 * target,
            "{name}: true peak {} mm over the target {} mm",
            truth.x_peak * 1e3,
            target * 1e3
        );
        // The result carries the measurement keys.
        let j = m.result().to_json_value();
        for k in ["x_peak_max", "dTv_max", "seconds"] {
            assert!(j["measurement"][k].as_f64().is_some(), "{name}: measurement.{k}");
        }
    }
}

#[test]
fn sb17_and_ptt4_converge_from_silence_within_a_minute() {
    converges_from_silence(&["sb17cac35-4", "ptt4.0w04-01a"]);
}

#[test]
fn w18wu_converges_from_silence_within_a_minute() {
    converges_from_silence(&["18wu-4741t-00"]);
}

#[test]
fn a_target_beyond_the_range_is_held_at_the_safe_stiffness_limit() {
    // Target 2x the driver's valid range: the controller must stop where Kms(x)/Kms(0) = 2.
    for name in ["sb17cac35-4", "ptt4.0w04-01a"] {
        let p = embedded_driver(name).unwrap();
        let [lo, hi] = p.x_range.unwrap();
        let safe = kms_limit_crossing(&p.kms, hi.max(-lo) * 1.5, 2.0).unwrap();
        let mut src = Source::noise(&Excitation::Iec, 48000.0, 3).unwrap();
        let m = run(
            &p,
            &mut src,
            MeasureOptions { mms: p.mms, target_x: Some(2.0 * hi.max(-lo)), max_seconds: 30.0, ..Default::default() },
            2,
        );
        let t = m.truth.unwrap();
        println!("{name}: true safe limit {:.2} mm, true peak {:.2} mm, {}", safe * 1e3, t.x_peak * 1e3, m.stop_reason);
        assert!(
            t.x_peak <= 1.05 * safe,
            "{name}: true peak {} mm beyond the safe limit {} mm",
            t.x_peak * 1e3,
            safe * 1e3
        );
    }
}

#[test]
fn a_low_temperature_limit_holds() {
    // 3 K: a tenth of a percent of Re. The cold Re and the tracking lag both matter here.
    for (name, seed) in [("sb17cac35-4", 3), ("18wu-4741t-00", 4)] {
        let p = embedded_driver(name).unwrap();
        let [lo, hi] = p.x_range.unwrap();
        let mut src = Source::noise(&Excitation::Iec, 48000.0, 4).unwrap();
        let max_dt = 3.0;
        let m = run(
            &p,
            &mut src,
            MeasureOptions {
                mms: p.mms,
                target_x: Some(0.85 * hi.min(-lo)),
                max_dt,
                duration: Some(30.0),
                ..Default::default()
            },
            seed,
        );
        let t = m.truth.unwrap();
        println!("{name}: true dT max {:.2} K (limit {max_dt} K), estimated {:.2} K", t.dtv_max, m.dtv_max);
        assert!(t.dtv_max <= 1.05 * max_dt, "{name}: true voice-coil rise {} K", t.dtv_max);
        assert!(
            t.dtv_max >= 0.6 * max_dt,
            "{name}: the level must have been raised toward the limit ({} K)",
            t.dtv_max
        );
        // The estimate follows the truth (it is what the protection acts on).
        assert!(
            (m.dtv_max - t.dtv_max).abs() <= 0.1 * max_dt,
            "{name}: estimated {} K, true {} K",
            m.dtv_max,
            t.dtv_max
        );
    }
}

#[test]
fn music_excitation_converges() {
    // "Music": bass notes and chords under a beat, written to a WAV and read back as the
    // excitation (what --music does).
    let fs = 48000.0;
    let n = (12.0 * fs) as usize;
    let notes = [41.2, 55.0, 49.0, 65.4];
    let x: Vec<f64> = (0..n)
        .map(|k| {
            let t = k as f64 / fs;
            let bar = (t / 1.5) as usize % 4;
            let f = notes[bar];
            let beat = (-((t % 0.5) * 12.0)).exp();
            let s = (2.0 * std::f64::consts::PI * f * t).sin()
                + 0.5 * (2.0 * std::f64::consts::PI * 2.0 * f * t).sin()
                + 0.3 * (2.0 * std::f64::consts::PI * 5.04 * f * t).sin();
            let hat = if (t % 0.25) < 0.02 { ((k * 7919) % 1000) as f64 / 500.0 - 1.0 } else { 0.0 };
            0.25 * (s * (0.6 + 0.4 * beat)
                + 0.5 * hat
                + 0.2
                    * (2.0 * std::f64::consts::PI * 880.0 * t).sin()
                    * (2.0 * std::f64::consts::PI * 0.7 * t).sin().abs())
        })
        .collect();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("music.wav");
    let spec = hound::WavSpec {
        channels: 1,
        sample_rate: 48000,
        bits_per_sample: 16,
        sample_format: hound::SampleFormat::Int,
    };
    let mut w = hound::WavWriter::create(&path, spec).unwrap();
    for v in &x {
        w.write_sample((v * 32767.0) as i16).unwrap();
    }
    w.finalize().unwrap();
    let p = embedded_driver("sb17cac35-4").unwrap();
    let [lo, hi] = p.x_range.unwrap();
    let mut src = Source::music(&path, fs).unwrap();
    let m =
        run(&p, &mut src, MeasureOptions { mms: p.mms, target_x: Some(0.85 * hi.min(-lo)), ..Default::default() }, 5);
    assert_truth("sb17 music", &m, &p);
    // A music file at another rate is refused with the fix named.
    let e = Source::music(&path, 44100.0).err().unwrap();
    assert!(e.contains("music.wav") && e.contains("48000"), "{e}");
}

#[test]
fn bad_limits_get_clear_errors() {
    let p = embedded_driver("sb17cac35-4").unwrap();
    for (opts, key) in [
        (MeasureOptions { mms: p.mms, target_x: Some(-1e-3), ..Default::default() }, "--target-x"),
        (MeasureOptions { mms: p.mms, max_dt: 0.0, ..Default::default() }, "--max-dt"),
        (MeasureOptions { mms: p.mms, kms_limit: 0.5, ..Default::default() }, "--kms-limit"),
        (MeasureOptions { mms: 15.0, ..Default::default() }, "--mms"),
        (MeasureOptions { mms: p.mms, start_volts: 50.0, ..Default::default() }, "--start-volts"),
        (MeasureOptions { mms: p.mms, duration: Some(1.0), ..Default::default() }, "--duration"),
    ] {
        let e = opts.validate().unwrap_err();
        assert!(e.contains(key), "{key}: {e}");
    }
    assert!(VirtualDevice::new(&p, 1000.0, (1e-4, 1e-4), 1).is_err());
    assert!(Source::music(std::path::Path::new("/nonexistent/song.wav"), 48000.0).err().unwrap().contains("song.wav"));
}

#[test]
fn other_sample_rates_converge() {
    // 44.1 kHz (a CD-rate sound card) and 96 kHz: same accuracy, same protection.
    let p = embedded_driver("ptt4.0w04-01a").unwrap();
    let [lo, hi] = p.x_range.unwrap();
    for fs in [44100.0, 96000.0] {
        let target = 0.85 * hi.min(-lo);
        let mut dev = VirtualDevice::new(&p, fs, (1e-4, 1e-4), 6).unwrap();
        let mut src = Source::noise(&Excitation::Iec, fs, 2).unwrap();
        let m = measure(
            &mut dev,
            &mut src,
            &MeasureOptions { mms: p.mms, target_x: Some(target), ..Default::default() },
            None,
            |_| {},
        )
        .unwrap();
        assert_truth(&format!("ptt4 at {fs} Hz"), &m, &p);
        assert!(m.truth.unwrap().x_peak <= 1.05 * target);
    }
}

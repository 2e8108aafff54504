//! The measurement never runs away, and never claims a wrong convergence.
//!
//! A sweep of `measure` on the virtual transducer (sensor noise 0.1 mV / 0.1 mA, coil heating
//! on, IEC noise from silence, auto range): the three bundled drivers and two microspeakers of
//! our own (`testdata/drivers`: 0.1 g at +-0.5 mm and 2.7 g at +-3 mm, Le 30 uH), over seeds,
//! plus other sample rates, start levels, no sensor noise and music. Every run must:
//!
//! * keep the true peak excursion within 5 % of the driver's valid range;
//! * never end in an error (run-away, NaN) and never end "converged" on curves more than 2 %
//!   (Bl, Kms) / 5 % (Le) off over the reached range, nor with the cold Re more than 0.1 % off
//!   (bundled drivers);
//! * either converge, or stop with a specific reason that is not success.
//!
//! Slow in a debug build: run with `cargo test --release -p coilscope-measure --test
//! measure_seed_sweep -- --ignored` (`.ci/run` does).

use coilscope_core::excitation::Excitation;
use coilscope_core::{embedded_driver, Parameters, Poly};
use coilscope_io::load_parameters;
use coilscope_measure::device::VirtualDevice;

use coilscope_measure::signal::Source;
use coilscope_measure::{measure, MeasureOptions};
use coilscope_testkit::slice;

fn worst(f: &Poly, g: &Poly, [lo, hi]: [f64; 2]) -> f64 {
    (0..=400)
        .map(|k| lo + (hi - lo) * k as f64 / 400.0)
        .map(|x| (f.eval(x) - g.eval(x)).abs())
        .fold(0.0, coilscope_testkit::check::nan_max)
        / g.eval(0.0).abs()
}

fn driver(name: &str) -> Parameters {
    embedded_driver(name).unwrap_or_else(|| {
        load_parameters(&format!("{}/../../testdata/drivers/{name}.json", env!("CARGO_MANIFEST_DIR"))).unwrap()
    })
}

struct Case {
    label: String,
    p: Parameters,
    fs: f64,
    seed: u64,
    noise: (f64, f64),
    start_volts: f64,
    music: bool,
    /// Whether the cold Re is held to 0.1 % (coils that heat by a few K/s at most).
    re_cold: bool,
}

fn case(name: &str, seed: u64) -> Case {
    Case {
        label: format!("{name} seed {seed}"),
        p: driver(name),
        fs: 48000.0,
        seed,
        noise: (1e-4, 1e-4),
        start_volts: 0.2,
        music: false,
        re_cold: !name.starts_with("micro"),
    }
}

/// Synthetic music: bass notes, chords and a hat (as in `measure_truth`), at `fs`.
fn music_file(dir: &std::path::Path, fs: f64) -> std::path::PathBuf {
    let n = (12.0 * fs) as usize;
    let notes = [41.2, 55.0, 49.0, 65.4];
    let path = dir.join("music.wav");
    let spec = hound::WavSpec {
        channels: 1,
        sample_rate: fs as u32,
        bits_per_sample: 16,
        sample_format: hound::SampleFormat::Int,
    };
    let mut w = hound::WavWriter::create(&path, spec).unwrap();
    for k in 0..n {
        let t = k as f64 / fs;
        let f = notes[(t / 1.5) as usize % 4];
        let beat = (-((t % 0.5) * 12.0)).exp();
        let s = (2.0 * std::f64::consts::PI * f * t).sin()
            + 0.5 * (2.0 * std::f64::consts::PI * 2.0 * f * t).sin()
            + 0.3 * (2.0 * std::f64::consts::PI * 5.04 * f * t).sin();
        let hat = if (t % 0.25) < 0.02 { ((k * 7919) % 1000) as f64 / 500.0 - 1.0 } else { 0.0 };
        w.write_sample((0.25 * (s * (0.6 + 0.4 * beat) + 0.5 * hat) * 32767.0) as i16).unwrap();
    }
    w.finalize().unwrap();
    path
}

/// |estimate - truth| / sd of the three curves at the points of the bands the result file
/// publishes (over the reached range; the sd with every part the result carries: the
/// covariance's, the systematic share, Le's model share, how far the estimate still moved).
/// A curve without a band gives NaN, which no check passes.
fn band_z(m: &coilscope_measure::Measurement, truth: &Parameters) -> Vec<f64> {
    let result = m.result();
    let mut z = Vec::new();
    for (which, g) in [("Bl", &truth.bl), ("Kms", &truth.kms), ("Le", &truth.le)] {
        match result.uncertainty.band(which) {
            Some(b) => z.extend((0..b.x.len()).map(|k| (b.value[k] - g.eval(b.x[k])).abs() / b.sd[k])),
            None => z.push(f64::NAN),
        }
    }
    z
}

/// Run the cases; returns the failures (one line each) and prints one line per run, and the
/// share of band points (converged runs) that hold the truth within 2 sd.
fn sweep(cases: Vec<Case>) -> (usize, Vec<String>) {
    let dir = tempfile::tempdir().unwrap();
    let mut failures = Vec::new();
    let mut passed = 0;
    let mut zs: Vec<f64> = Vec::new();
    for c in cases {
        let [lo, hi] = c.p.x_range.unwrap();
        let range = hi.min(-lo);
        let mut dev = VirtualDevice::new(&c.p, c.fs, c.noise, c.seed).unwrap();
        let mut src = if c.music {
            Source::music(&music_file(dir.path(), c.fs), c.fs).unwrap()
        } else {
            Source::noise(&Excitation::Iec, c.fs, c.seed).unwrap()
        };
        let opts = MeasureOptions { mms: c.p.mms, start_volts: c.start_volts, ..Default::default() };
        let m = match measure(&mut dev, &mut src, &opts, None, |_| {}) {
            Ok(m) => m,
            Err(e) => {
                failures.push(format!("{}: error: {e}", c.label));
                continue;
            }
        };
        if let coilscope_measure::StopReason::Failed { message, .. } = &m.stop_reason {
            failures.push(format!("{}: failed: {message}", c.label));
            continue;
        }
        let t = m.truth.unwrap();
        let q = &m.params;
        // Scored over the range the driver truly reached, not the one the estimator reports.
        let r = [t.x_min, t.x_max];
        let (e_bl, e_k, e_le) = (worst(&q.bl, &c.p.bl, r), worst(&q.kms, &c.p.kms, r), worst(&q.le, &c.p.le, r));
        let e_re = (q.re / c.p.re - 1.0).abs();
        let z = band_z(&m, &c.p);
        let z2 = z.iter().filter(|&&v| v <= 2.0).count() as f64 / z.len() as f64;
        if m.converged {
            zs.extend(&z);
        }
        let line = format!(
            "{}: bands hold the truth at 2 sd on {:.0} % of points (largest {:.1} sd); {} after {:.1} s; reach {:.2}..{:.2} mm (true {:.2}..{:.2}), true peak {:.2} mm of {:.2}; dT true {:.1} K, estimated {:.1} K; Bl {:.2} %, Kms {:.2} %, Le {:.2} %, Re(cold) {:.3} % (sd {:.3} %)",
            c.label,
            100.0 * z2,
            z.iter().cloned().fold(0.0, coilscope_testkit::check::nan_max),
            m.stop_reason.key(),
            m.seconds,
            m.x_range[0] * 1e3,
            m.x_range[1] * 1e3,
            t.x_min * 1e3,
            t.x_max * 1e3,
            t.x_peak * 1e3,
            range * 1e3,
            t.dtv_max,
            m.dtv_max,
            100.0 * e_bl,
            100.0 * e_k,
            100.0 * e_le,
            100.0 * e_re,
            100.0 * m.re_cold_sd / q.re
        );
        println!("{line}");
        let mut bad = Vec::new();
        if t.x_peak > 1.05 * range {
            bad.push("protection: true peak beyond the range + 5 %");
        }
        // How far a run must get: 60 % of the safe range (the driver's range, or where its true
        // Kms(x)/Kms(0) reaches the limit, if nearer), unless the coil's temperature held it:
        // the controller says so, or the true rise reached 85 % of the limit (the 2.7 g coil
        // converges at 45 K of 50 with the ramp paused, a level the temperature would not let
        // it pass).
        let safe = coilscope_measure::engine::kms_limit_crossing(&c.p.kms, range, opts.kms_limit).unwrap_or(range);
        let held_by_heat = m.limited_by == coilscope_measure::LimitedBy::Temperature || t.dtv_max >= 0.85 * opts.max_dt;
        if m.converged && t.x_peak < 0.6 * safe && !held_by_heat {
            bad.push("stopped short: the true peak is below 60 % of the safe range");
        }
        if t.dtv_max > 1.05 * opts.max_dt {
            bad.push("protection: true voice-coil rise beyond the limit + 5 %");
        }
        if !q.bl.c.iter().chain(&q.kms.c).chain(&q.le.c).all(|v| v.is_finite()) {
            bad.push("NaN in the result");
        }
        if m.converged {
            if !(e_bl <= 0.02 && e_k <= 0.02 && e_le <= 0.05) {
                bad.push("converged on curves off the truth");
            }
            // 0.1 %, or three of its reported standard deviations where the start level
            // leaves less signal than that (a quiet start, music).
            if c.re_cold && e_re > 0.001f64.max(3.0 * m.re_cold_sd / q.re) {
                bad.push("cold Re off by more than 0.1 % and 3 sd");
            }
        } else if m.stop_reason.is_success() {
            bad.push("not converged, yet the stop reason says success");
        }
        if bad.is_empty() {
            passed += 1;
        } else {
            failures.push(format!("{line}: {}", bad.join(", ")));
        }
    }
    if !zs.is_empty() {
        let z2 = zs.iter().filter(|&&v| v <= 2.0).count() as f64 / zs.len() as f64;
        println!("band coverage: {:.1} % of {} points within 2 sd (a Gaussian band: 95 %)", 100.0 * z2, zs.len());
        // The published bands are claims: they must hold the truth (counted over every point
        // of every converged run of the sweep).
        if z2 < 0.9 {
            failures.push(format!(
                "the bands hold the truth within 2 sd on only {:.1} % of {} points",
                100.0 * z2,
                zs.len()
            ));
        }
    }
    (passed, failures)
}

fn check(cases: Vec<Case>) {
    let cases = slice::in_slice("measure_seed_sweep", cases);
    let n = cases.len();
    let (passed, failures) = sweep(cases);
    println!("{passed} passed, {} failed (of {n} runs)", failures.len());
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

const SEEDS: u64 = 12;

#[test]
#[ignore = "release-profile sweep: cargo test --release -p coilscope-measure --test measure_seed_sweep -- --ignored"]
fn sb17_over_seeds() {
    check((1..=SEEDS).map(|s| case("sb17cac35-4", s)).collect());
}

#[test]
#[ignore = "release-profile sweep: cargo test --release -p coilscope-measure --test measure_seed_sweep -- --ignored"]
fn ptt4_over_seeds() {
    check((1..=SEEDS).map(|s| case("ptt4.0w04-01a", s)).collect());
}

#[test]
#[ignore = "release-profile sweep: cargo test --release -p coilscope-measure --test measure_seed_sweep -- --ignored"]
fn w18wu_over_seeds() {
    check((1..=SEEDS).map(|s| case("18wu-4741t-00", s)).collect());
}

#[test]
#[ignore = "release-profile sweep: cargo test --release -p coilscope-measure --test measure_seed_sweep -- --ignored"]
fn microspeakers_over_seeds() {
    check((1..=SEEDS).map(|s| case("microspeaker-0g1", s)).collect());
}

/// A coil with a 2 s thermal time constant (the 2.7 g set at +-3 mm, Rtv 40 K/W, Ctv
/// 0.05 J/K) heats by 25 K/s at full level. The Re tracker used to discard steps over 1 % per
/// 0.25 s, so the estimate lagged by 6-7 K, and the temperature cuts compounded block after
/// block: the coil reached 53-64 K against a 50 K limit and the level hunted. The tracker now
/// takes steps up to 5 % when the Re direction explains most of the block's error, and the
/// controller waits a second after a cut before cutting again.
#[test]
#[ignore = "release-profile sweep: cargo test --release -p coilscope-measure --test measure_seed_sweep -- --ignored"]
fn fast_heating_microspeaker_over_seeds() {
    check((1..=SEEDS).map(|s| case("microspeaker-2g7", s)).collect());
}

#[test]
#[ignore = "release-profile sweep: cargo test --release -p coilscope-measure --test measure_seed_sweep -- --ignored"]
fn rates_start_levels_no_noise_and_music() {
    let mut cases = Vec::new();
    for name in ["sb17cac35-4", "18wu-4741t-00"] {
        for fs in [44100.0, 96000.0] {
            cases.push(Case { label: format!("{name} at {fs} Hz"), fs, ..case(name, 3) });
        }
        cases.push(Case { label: format!("{name} start 0.05 V"), start_volts: 0.05, ..case(name, 4) });
        cases.push(Case { label: format!("{name} without sensor noise"), noise: (0.0, 0.0), ..case(name, 5) });
    }
    cases.push(Case { label: "sb17cac35-4 music".into(), music: true, ..case("sb17cac35-4", 6) });
    check(cases);
}

/// Louder starts and music on the largest driver. Before the ramp waited for its estimate
/// (`RAMP_SETTLE`, `RAMP_EXCESS`), kept a trust region on the reach everywhere, remembered the
/// small stage's crests, and scaled the series basis to the drive level, SB17 started at
/// 0.5 V or 1 V was driven past its range and 18WU under music too; the cold Re of a 1 V
/// start read 0.11 % high until the final model refitted it on the small stage.
#[test]
#[ignore = "release-profile sweep: cargo test --release -p coilscope-measure --test measure_seed_sweep -- --ignored"]
fn start_levels_up_to_1v_and_music_on_18wu() {
    let mut cases = Vec::new();
    for v in [0.5, 1.0] {
        cases.push(Case { label: format!("sb17cac35-4 start {v} V"), start_volts: v, ..case("sb17cac35-4", 4) });
        cases.push(Case { label: format!("18wu-4741t-00 start {v} V"), start_volts: v, ..case("18wu-4741t-00", 4) });
        cases.push(Case { label: format!("ptt4.0w04-01a start {v} V"), start_volts: v, ..case("ptt4.0w04-01a", 5) });
    }
    cases.push(Case { label: "18wu-4741t-00 music".into(), music: true, ..case("18wu-4741t-00", 6) });
    cases.push(Case { label: "ptt4.0w04-01a music".into(), music: true, ..case("ptt4.0w04-01a", 7) });
    check(cases);
}

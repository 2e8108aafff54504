//! Large-signal identification against the truth.
//!
//! Recordings: 8 s at 48 kHz of pink noise (10 Hz - 8 kHz, crest factor 3) whose level makes
//! the driver reach 85 % of its `x_range`, with the two-node thermal model on (the coil heats
//! by 1-3 K during the record) and Gaussian sensor noise on both channels. Plus the
//! independent recordings of `shared/recordings` (6 s, another simulator).
//!
//! Tolerances: over the range the record reached, the largest error of Bl(x), Kms(x) and
//! Le(x) relative to the true value at rest, and of Re and Rms, at about 4 times the figures
//! the README publishes (`AT_70_DB`, `AT_60_DB`, `INDEPENDENT`); `residual_rel` <= 1 %. The
//! measured errors are printed by every test (`--nocapture`).

use coilscope_core::excitation::{add_sensor_noise, generate, Excitation, SignalSpec};
use coilscope_core::simulate::{gain_for_peak, SimOptions};
use coilscope_core::{embedded_driver, Parameters, Poly};
use coilscope_ident::large::{identify, IdentifyError, IdentifyOptions, LargeFit};
use coilscope_ident::linear::{Effects, EffectsChoice};

/// The LR-2 model: these tests are about accuracy in its world (the choice of effects is
/// tested in real_driver_recordings.rs), and Auto would triple their time.
const LR2: EffectsChoice = EffectsChoice::Fixed(Effects::NONE);
use std::path::Path;

mod common;
use common::{worst, Errors};

struct Rec {
    fs: f64,
    u: Vec<f64>,
    i: Vec<f64>,
    /// What the truth reached.
    x_range: [f64; 2],
}

/// A large-signal recording reaching `share` of the driver's x_range.
fn record(p: &Parameters, fs: f64, seconds: f64, share: f64, snr_db: f64, seed: u64) -> Rec {
    let [lo, hi] = p.x_range.unwrap();
    let target = share * hi.min(-lo);
    let unit = generate(
        &Excitation::Pink { f_lo: 10.0, f_hi: 8000.0, crest: Some(3.0) },
        &SignalSpec { fs, seconds, rms: 1.0, fade: 0.05, seed },
    )
    .unwrap();
    let (_, tr) = gain_for_peak(p, fs, &unit, target, &SimOptions::default()).unwrap();
    let s = tr.summary();
    if seconds >= 8.0 {
        assert!(s.dt_end > 0.5, "the coil must heat during the record ({} K)", s.dt_end);
    }
    let (mut u, mut i) = (tr.u, tr.i);
    add_sensor_noise(&mut u, snr_db, seed, "sensor-noise/voltage");
    add_sensor_noise(&mut i, snr_db, seed, "sensor-noise/current");
    Rec { fs, u, i, x_range: [s.x_min, s.x_max] }
}

struct Tol {
    bl_kms: f64,
    le: f64,
    re_rms: f64,
}
/// The tolerances protect the README's figures: each fails at about 4 times what
/// is published. 70 dB, own simulator (3 drivers, 44.1 / 96 kHz, a start with Kms 2x off):
/// Bl, Kms <= 0.005 %, Le <= 0.015 %, Re, Rms <= 0.002 %.
const AT_70_DB: Tol = Tol { bl_kms: 2e-4, le: 6e-4, re_rms: 1e-4 };
/// 60 dB (18WU): Bl, Kms <= 0.03 %, Le <= 0.035 %, Re, Rms <= 0.015 %.
const AT_60_DB: Tol = Tol { bl_kms: 1.2e-3, le: 1.4e-3, re_rms: 6e-4 };
/// The independent simulator's recordings (6 s, 70 dB): Bl, Kms, Le <= 0.012 %, Re, Rms
/// <= 0.01 %.
const INDEPENDENT: Tol = Tol { bl_kms: 5e-4, le: 5e-4, re_rms: 4e-4 };

fn assert_truth(label: &str, fit: &LargeFit, truth: &Parameters, range: [f64; 2], tol: &Tol) {
    let q = &fit.params;
    let e = Errors::of(q, truth, range);
    println!(
        "{label}: order {}, residual {:.2e}, errors {e}, x {:.2}..{:.2} mm (truth {:.2}..{:.2})",
        fit.order,
        fit.residual_rel,
        fit.x_range[0] * 1e3,
        fit.x_range[1] * 1e3,
        range[0] * 1e3,
        range[1] * 1e3
    );
    assert!(e.bl <= tol.bl_kms, "{label}: Bl off by {:.3} %", 100.0 * e.bl);
    assert!(e.kms <= tol.bl_kms, "{label}: Kms off by {:.3} %", 100.0 * e.kms);
    assert!(e.le <= tol.le, "{label}: Le off by {:.3} %", 100.0 * e.le);
    assert!(e.re <= tol.re_rms, "{label}: Re off by {:.3} %", 100.0 * e.re);
    assert!(e.rms <= tol.re_rms, "{label}: Rms off by {:.3} %", 100.0 * e.rms);
    assert!(fit.residual_rel <= 0.01, "{label}: residual {}", fit.residual_rel);
    // The reported range is the one reached (never extrapolated), within 2 %.
    for k in 0..2 {
        assert!((fit.x_range[k] / range[k] - 1.0).abs() < 0.02, "{label}: x_range {:?} vs {:?}", fit.x_range, range);
    }
    assert_eq!(q.x_range, Some(fit.x_range));
}

fn run(rec: &Rec, opts: IdentifyOptions) -> LargeFit {
    match identify(&rec.u, &rec.i, rec.fs, "test", &opts, |_| {}) {
        Ok(f) => f,
        Err(e) => panic!("{e}"),
    }
}

#[test]
fn three_drivers_at_70_db() {
    for name in ["sb17cac35-4", "ptt4.0w04-01a", "18wu-4741t-00"] {
        let p = embedded_driver(name).unwrap();
        let rec = record(&p, 48000.0, 8.0, 0.85, 70.0, 11);
        let fit = run(&rec, IdentifyOptions { mms: p.mms, effects: LR2, ..Default::default() });
        assert_truth(&format!("{name} 70 dB"), &fit, &p, rec.x_range, &AT_70_DB);
        // The voice-coil heating is tracked: Re rises over the record.
        assert!(fit.re_track.last().unwrap().1 > fit.re_track[0].1 * 1.001, "{name}: {:?}", fit.re_track);
    }
}

#[test]
fn noisier_sensors_at_60_db() {
    let p = embedded_driver("18wu-4741t-00").unwrap();
    let rec = record(&p, 48000.0, 8.0, 0.85, 60.0, 12);
    let fit = run(&rec, IdentifyOptions { mms: p.mms, effects: LR2, ..Default::default() });
    assert_truth("18wu 60 dB", &fit, &p, rec.x_range, &AT_60_DB);
}

#[test]
fn other_sample_rates() {
    for (name, fs) in [("sb17cac35-4", 44100.0), ("ptt4.0w04-01a", 96000.0)] {
        let p = embedded_driver(name).unwrap();
        let rec = record(&p, fs, 8.0, 0.85, 70.0, 13);
        let fit = run(&rec, IdentifyOptions { mms: p.mms, effects: LR2, ..Default::default() });
        assert_truth(&format!("{name} at {fs} Hz"), &fit, &p, rec.x_range, &AT_70_DB);
    }
}

#[test]
fn start_with_kms_twice_too_high() {
    // A linear estimate 2x off in Kms (the rest at the truth's values at rest), fixed order.
    let p = embedded_driver("sb17cac35-4").unwrap();
    let rec = record(&p, 48000.0, 8.0, 0.85, 70.0, 14);
    let c0 = |f: &Poly| Poly::constant(f.eval(0.0));
    let start = Parameters {
        le: c0(&p.le),
        bl: c0(&p.bl),
        kms: Poly::constant(2.0 * p.kms.eval(0.0)),
        l2r2: p.l2r2.clone(),
        thermal: None,
        x_range: None,
        ..p.clone()
    };
    let fit = run(
        &rec,
        IdentifyOptions { mms: p.mms, effects: LR2, init: Some(start), order: Some(4), ..Default::default() },
    );
    assert_eq!(fit.order, 4);
    assert_truth("sb17 from Kms x2", &fit, &p, rec.x_range, &AT_70_DB);
}

#[test]
fn uncertainty_bands_cover_the_truth_and_shrink_with_noise() {
    let p = embedded_driver("ptt4.0w04-01a").unwrap();
    let mut widths = vec![];
    for snr in [70.0, 50.0] {
        let rec = record(&p, 48000.0, 8.0, 0.85, snr, 15);
        let fit = run(&rec, IdentifyOptions { mms: p.mms, effects: LR2, order: Some(4), ..Default::default() });
        let b = fit.band("Bl", 21);
        let mut z_max: f64 = 0.0;
        for (k, &x) in b.x.iter().enumerate() {
            assert!(b.sd[k] > 0.0 && b.sd[k].is_finite());
            z_max = z_max.max((b.value[k] - p.bl.eval(x)).abs() / b.sd[k]);
        }
        println!("{snr} dB: Bl band sd at rest {:.2e}, worst |error|/sd {z_max:.1}", b.sd[10]);
        // The band holds the truth (measured: within 1.0 sd at both levels).
        assert!(z_max < 3.0, "{snr} dB: Bl error is {z_max:.1} sd");
        // The statistical part (the band adds a systematic 0.01 % of the value in quadrature).
        let sys = coilscope_ident::large::CURVE_SYSTEMATIC_REL * b.value[10];
        widths.push((b.sd[10].powi(2) - sys * sys).max(0.0).sqrt());
        for (k, v) in fit.sd() {
            assert!(v > 0.0 && v.is_finite(), "{k}: {v}");
        }
    }
    // 20 dB more noise: the band's statistical part widens by about 10x.
    let ratio = widths[1] / widths[0];
    assert!(ratio > 5.0 && ratio < 20.0, "{widths:?}");
}

/// The shared reference data; a test that needs it fails when it is missing (with
/// `COILSCOPE_NO_SHARED=1` such tests are compiled as ignored: reported as skipped).
fn shared() -> &'static Path {
    let p = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../../../shared"));
    assert!(
        p.exists(),
        "../shared is missing; set COILSCOPE_NO_SHARED=1 to skip the reference tests (reported as ignored)"
    );
    p
}

#[test]
#[cfg_attr(no_shared, ignore = "../shared is missing (COILSCOPE_NO_SHARED=1): skipped")]
fn independent_reference_recordings() {
    let dir = shared();
    for name in ["sb17cac35-4", "ptt4.0w04-01a", "18wu-4741t-00"] {
        let p = embedded_driver(name).unwrap();
        let path = dir.join(format!("recordings/{name}-large.wav"));
        let rec = coilscope_io::read_recording(&path, None).unwrap();
        let info: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(dir.join(format!("recordings/{name}-large.info.json"))).unwrap(),
        )
        .unwrap();
        let range = [info["x_min"].as_f64().unwrap(), info["x_max"].as_f64().unwrap()];
        let r = Rec { fs: rec.fs as f64, u: rec.u, i: rec.i, x_range: range };
        let fit = run(&r, IdentifyOptions { mms: p.mms, effects: LR2, ..Default::default() });
        assert_truth(&format!("{name} (independent)"), &fit, &p, range, &INDEPENDENT);
        // The heating the other simulator put in: within 15 % (it runs 8 % hotter than the
        // spec's model).
        let dt = fit.temperature_track(0.00393).last().unwrap().1;
        let dt_ref = info["dT_end"].as_f64().unwrap();
        assert!((dt / dt_ref - 1.0).abs() < 0.15, "{name}: dT {dt} vs {dt_ref}");
    }
}

#[test]
#[cfg_attr(no_shared, ignore = "../shared is missing (COILSCOPE_NO_SHARED=1): skipped")]
fn independent_small_signal_record_gives_curves_over_its_small_range() {
    // +-0.27 mm at 70 dB: the nonlinearity is still above the noise, so the fit is made, and
    // its x_range says where the curves hold.
    let dir = shared();
    let p = embedded_driver("sb17cac35-4").unwrap();
    let rec = coilscope_io::read_recording(&dir.join("recordings/sb17cac35-4-small.wav"), None).unwrap();
    let info: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("recordings/sb17cac35-4-small.info.json")).unwrap())
            .unwrap();
    let range = [info["x_min"].as_f64().unwrap(), info["x_max"].as_f64().unwrap()];
    let r = Rec { fs: rec.fs as f64, u: rec.u, i: rec.i, x_range: range };
    let fit = run(&r, IdentifyOptions { mms: p.mms, effects: LR2, ..Default::default() });
    assert_truth("sb17 small (independent)", &fit, &p, range, &INDEPENDENT);
    assert!(fit.x_range[1] < 0.3e-3 && fit.x_range[0] > -0.3e-3);
}

#[test]
fn excitation_too_small_is_refused_with_the_reached_range() {
    // About 0.03 mm at 60 dB: the nonlinear terms are buried in the noise.
    let p = embedded_driver("sb17cac35-4").unwrap();
    let rec = record(&p, 48000.0, 3.0, 0.005, 60.0, 19);
    match identify(
        &rec.u,
        &rec.i,
        rec.fs,
        "small.wav",
        &IdentifyOptions { mms: p.mms, effects: LR2, ..Default::default() },
        |_| {},
    ) {
        Err(IdentifyError::TooSmall(m)) => {
            println!("{m}");
            assert!(m.contains("small.wav") && m.contains("mm") && m.contains("too small"), "{m}");
        }
        other => panic!("expected TooSmall, got {:?}", other.map(|f| (f.residual_rel, f.trials))),
    }
}

#[test]
fn clipped_input_is_refused() {
    let p = embedded_driver("sb17cac35-4").unwrap();
    let mut rec = record(&p, 48000.0, 3.0, 0.5, 70.0, 16);
    let peak = rec.u.iter().fold(0.0f64, |a, v| a.max(v.abs()));
    rec.u.iter_mut().for_each(|v| *v = v.clamp(-0.6 * peak, 0.6 * peak));
    let err = identify(
        &rec.u,
        &rec.i,
        rec.fs,
        "clip.wav",
        &IdentifyOptions { mms: p.mms, effects: LR2, ..Default::default() },
        |_| {},
    )
    .unwrap_err();
    let m = err.to_string();
    assert!(m.contains("clip.wav") && m.contains("clipped") && m.contains("voltage"), "{m}");
}

#[test]
fn a_fit_stopped_early_says_why_and_keeps_its_best_estimate() {
    let p = embedded_driver("sb17cac35-4").unwrap();
    let rec = record(&p, 48000.0, 3.0, 0.85, 70.0, 17);
    let c0 = |f: &Poly| Poly::constant(f.eval(0.0));
    let start = Parameters {
        le: c0(&p.le),
        bl: c0(&p.bl),
        kms: Poly::constant(2.0 * p.kms.eval(0.0)),
        thermal: None,
        x_range: None,
        ..p.clone()
    };
    let opts = IdentifyOptions {
        mms: p.mms,
        effects: LR2,
        init: Some(start),
        order: Some(4),
        max_iterations: 1,
        ..Default::default()
    };
    match identify(&rec.u, &rec.i, rec.fs, "early.wav", &opts, |_| {}) {
        Err(IdentifyError::NotConverged { message, best }) => {
            assert!(message.contains("did not converge") && message.contains("iteration limit"), "{message}");
            assert!(!best.converged && best.iterations == 1);
            assert!(best.residual_rel.is_finite());
        }
        other => panic!("expected NotConverged, got {:?}", other.map(|f| f.iterations)),
    }
}

#[test]
fn bad_options_are_named() {
    let p = embedded_driver("sb17cac35-4").unwrap();
    let rec = record(&p, 48000.0, 3.0, 0.5, 70.0, 18);
    let e = identify(&rec.u, &rec.i, rec.fs, "a.wav", &IdentifyOptions { mms: 15.0, ..Default::default() }, |_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("moving mass 15") && e.contains("kg"), "{e}");
    let e = identify(
        &rec.u,
        &rec.i,
        rec.fs,
        "a.wav",
        &IdentifyOptions { mms: p.mms, effects: LR2, order: Some(12), ..Default::default() },
        |_| {},
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("order 12") && e.contains("2 ..= 8"), "{e}");
    let e = identify(
        &rec.u[..48000],
        &rec.i[..48000],
        rec.fs,
        "a.wav",
        &IdentifyOptions { mms: p.mms, effects: LR2, ..Default::default() },
        |_| {},
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("a.wav") && e.contains("too short"), "{e}");
    // A start outside physics is named, not run into NaN ("diverged at sample 1").
    let mut bad = p.clone();
    bad.re = 0.0;
    let e = identify(
        &rec.u,
        &rec.i,
        rec.fs,
        "a.wav",
        &IdentifyOptions { mms: p.mms, effects: LR2, init: Some(bad), ..Default::default() },
        |_| {},
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("a.wav")
            && e.contains("not physical")
            && e.contains("Re 0.000e0 ohm")
            && e.contains("the one given"),
        "{e}"
    );
}

#[test]
#[cfg_attr(no_shared, ignore = "../shared is missing (COILSCOPE_NO_SHARED=1): skipped")]
fn post_inverse_with_measured_displacement_gives_the_whole_set_including_mms() {
    // The equation-error estimate on the independent laser record (x measured, 70 dB):
    // Bl, Kms within 2 %, Le within 5 %, Mms and Rms within 1 %, Re within 1 % (it sees the
    // mean Re of a coil that heats by 1 K).
    let dir = shared();
    let p = embedded_driver("sb17cac35-4").unwrap();
    let rec = coilscope_io::read_recording(&dir.join("recordings/sb17cac35-4-large-laser.wav"), None).unwrap();
    let x = rec.x.clone().unwrap();
    let (l2, r2) = p.l2r2.as_ref().map(|(a, b)| (a.c[0], b.c[0])).unwrap();
    let q =
        coilscope_ident::post_inverse::post_inverse(&rec.u, &rec.i, &x, rec.fs as f64, 4, Some((l2, r2)), "laser.wav")
            .unwrap();
    let range = q.x_range.unwrap();
    let (e_bl, e_k, e_le) = (worst(&q.bl, &p.bl, range), worst(&q.kms, &p.kms, range), worst(&q.le, &p.le, range));
    let (e_m, e_r, e_re) = ((q.mms / p.mms - 1.0).abs(), (q.rms / p.rms - 1.0).abs(), (q.re / p.re - 1.0).abs());
    println!(
        "post-inverse: Bl {:.3} %, Kms {:.3} %, Le {:.3} %, Mms {:.3} %, Rms {:.3} %, Re {:.3} %",
        100.0 * e_bl,
        100.0 * e_k,
        100.0 * e_le,
        100.0 * e_m,
        100.0 * e_r,
        100.0 * e_re
    );
    assert!(e_bl < 0.02 && e_k < 0.02 && e_le < 0.05);
    assert!(e_m < 0.01 && e_r < 0.01 && e_re < 0.01);
    // A displacement channel of the wrong polarity is named.
    let flipped: Vec<f64> = x.iter().map(|v| -v).collect();
    let e = coilscope_ident::post_inverse::post_inverse(
        &rec.u,
        &rec.i,
        &flipped,
        rec.fs as f64,
        4,
        Some((l2, r2)),
        "laser.wav",
    )
    .unwrap_err();
    assert!(e.contains("laser.wav") && e.contains("polarity"), "{e}");
}

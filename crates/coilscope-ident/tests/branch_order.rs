//! The LR-2 and LR-3 branches are the same form in series, so
//! a fit may end with either one in either place. SB17 with a second branch of half L2 at
//! twice tau2 (a 43 Hz corner, slower than its LR-2 branch) once came out of `identify` as L2 0.2706
//! mH, R2 0.0726 ohm, L3 0.5397 mH, R3 0.2899 ohm: the truth's two branches, exchanged. The
//! result names the larger branch LR-2 (`L2 >= L3`, as every world of ours and the shared
//! `-real-all` records have it).
//!
//! The record: 8 s of pink noise at 48 kHz to 85 % of x_range, 70 dB sensor noise; the
//! effects chosen on held-out data. Checked: LR-3 chosen and no other effect (creep was once
//! taken too); L2, R2, L3, R3 each within 5 % of
//! its own truth (measured 0.2-1.0 %); Bl(x) and Kms(x) within 0.02 % over the reached range
//! (measured 0.002 %).
//!
//! Two records: 85 % of x_range (above) and 3 V RMS of the CLI's pink noise.
//! The first also bounds its final fit's iterations (geodesic acceleration).
//!
//! Release profile (about a minute each): `cargo test --release -p coilscope-ident --test
//! branch_order -- --ignored`.

mod common;
use coilscope_core::embedded_driver;
use coilscope_core::excitation::{add_sensor_noise, generate, Excitation, SignalSpec};
use coilscope_core::simulate::{gain_for_peak, simulate, SimOptions};
use coilscope_ident::large::{identify, IdentifyOptions};
use common::Errors;

/// SB17 with a second branch of half its L2 at twice its time constant: the truth, and its
/// L2, R2, L3, R3.
fn slow_branch_sb17() -> (coilscope_core::Parameters, [f64; 4]) {
    let sb17 = embedded_driver("sb17cac35-4").unwrap();
    let (l2, r2) = sb17.l2r2.as_ref().map(|(l, r)| (l.eval(0.0), r.eval(0.0))).unwrap();
    let (l3, r3) = (0.5 * l2, 0.5 * l2 / (2.0 * l2 / r2));
    (coilscope_core::Parameters { l3r3: Some((l3, r3)), ..sb17 }, [l2, r2, l3, r3])
}

/// `identify` (the effects chosen) of a trace with 70 dB of sensor noise on both channels.
fn identify_noisy(
    mut u: Vec<f64>,
    mut i: Vec<f64>,
    fs: f64,
    truth: &coilscope_core::Parameters,
    origin: &str,
) -> coilscope_ident::large::LargeFit {
    add_sensor_noise(&mut u, 70.0, 1, "sensor-noise/voltage");
    add_sensor_noise(&mut i, 70.0, 1, "sensor-noise/current");
    identify(&u, &i, fs, origin, &IdentifyOptions { mms: truth.mms, ..Default::default() }, |_| {}).unwrap()
}

#[test]
#[ignore = "release-profile: cargo test --release -p coilscope-ident --test branch_order -- --ignored"]
fn a_slow_second_branch_is_named_lr3() {
    let (truth, [l2, r2, l3, r3]) = slow_branch_sb17();
    let fs = 48000.0;
    let [lo, hi] = truth.x_range.unwrap();
    let unit = generate(
        &Excitation::Pink { f_lo: 10.0, f_hi: 8000.0, crest: Some(3.0) },
        &SignalSpec { fs, seconds: 8.0, rms: 1.0, fade: 0.05, seed: 1 },
    )
    .unwrap();
    let (_, tr) = gain_for_peak(&truth, fs, &unit, 0.85 * hi.min(-lo), &SimOptions::default()).unwrap();
    let fit = identify_noisy(tr.u, tr.i, fs, &truth, "sb17 slow LR-3");
    let q = &fit.params;
    let (gl2, gr2) = q.l2r2.as_ref().map(|(l, r)| (l.eval(0.0), r.eval(0.0))).unwrap();
    let (gl3, gr3) = q.l3r3.unwrap_or((0.0, 0.0));
    let e = Errors::of(q, &truth, fit.x_range);
    println!("{}: {e}; L2 {gl2:.4e} R2 {gr2:.4} L3 {gl3:.4e} R3 {gr3:.4} (true {l2:.4e} {r2:.4} {l3:.4e} {r3:.4}); final fit {} iterations", fit.layout.effects.model_name(), fit.iterations);
    let mut bad = vec![];
    if !fit.layout.effects.lr3 {
        bad.push(format!("LR-3 not chosen: {}", fit.layout.effects.model_name()));
    }
    // The record has no creep, Le(i) or Rms(v). Creep's trial once lowered the
    // held-out error by 1.2 % only because it went on fitting the branch where LR-3's trial
    // stopped (held_out_gain_is_within_reach).
    let chosen = fit.layout.effects;
    if chosen.creep || chosen.le_i || chosen.rms_v {
        bad.push(format!("an effect the record lacks taken: {}", chosen.model_name()));
    }
    // The result says why: LR-2+LR-3 went on alone, and the trial with creep is within the
    // 1 % bar of where it got to.
    let tried = fit.models_tried();
    let val = |m: &str| tried.iter().find(|t| t.model == m).and_then(|t| t.validation_rel);
    let went_on = tried.iter().find(|t| t.model == "LR-2+LR-3").and_then(|t| t.validation_rel_before);
    match (went_on, val("LR-2+LR-3"), val("LR-2+LR-3+creep")) {
        (Some(before), Some(after), Some(creep)) if after < before && creep >= 0.99 * after => {}
        other => bad.push(format!("models tried: (LR-2+LR-3 before it went on alone, after, with creep) {other:?}")),
    }
    for (name, got, want) in [("L2", gl2, l2), ("R2", gr2, r2), ("L3", gl3, l3), ("R3", gr3, r3)] {
        if (got / want - 1.0).abs() > 0.05 {
            bad.push(format!("{name} {got:.4e}, true {want:.4e}"));
        }
    }
    if !(e.bl <= 2e-4 && e.kms <= 2e-4) {
        bad.push(format!("{e}"));
    }
    // Without geodesic acceleration the final fit crawls along the valley of the two branches, 16 iterations
    // of a full Jacobian each (gain ratios 0.18-0.98, each step cut short where the valley
    // turns); with geodesic acceleration after a step the linearised model missed
    // (`lm_step_accelerated`) it takes 10 (an iteration count, not a time).
    if fit.iterations > 12 {
        bad.push(format!(
            "the final fit took {} iterations (10 with geodesic acceleration, 16 without)",
            fit.iterations
        ));
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

/// Seen through the CLI: the same driver driven at 3 V RMS (`coilscope
/// simulate --excitation pink --volts 3 --seconds 8 --snr-db 70`, +-5.2 mm) once came out as
/// `LR-2+LR-3+Rms(v)`. Its LR-3 trial had not converged (its Gauss-Newton model promised
/// 4.5 % more), and creep, Le(i) and Rms(v), each going on from it, lowered the held-out error
/// by 5.4-6.4 %; Rms(v) was taken by 0.002 %. A base whose stage did not converge now goes on
/// alone for as many iterations as the trial took before the trial is compared with it
/// (`identify`'s effects search; here it gets as far as Le(i) from its zero start).
#[test]
#[ignore = "release-profile: cargo test --release -p coilscope-ident --test branch_order -- --ignored"]
fn a_slow_second_branch_at_3_v_takes_no_other_effect() {
    let (truth, _) = slow_branch_sb17();
    let fs = 48000.0;
    let u = generate(
        &Excitation::Pink { f_lo: 10.0, f_hi: 8000.0, crest: None },
        &SignalSpec { fs, seconds: 8.0, rms: 3.0, fade: 0.05, seed: 1 },
    )
    .unwrap();
    let tr = simulate(&truth, fs, &u, &SimOptions::default()).unwrap();
    let fit = identify_noisy(tr.u, tr.i, fs, &truth, "sb17 slow LR-3 at 3 V");
    let e = Errors::of(&fit.params, &truth, fit.x_range);
    let tried: Vec<String> = fit
        .models_tried()
        .iter()
        .map(|t| format!("{} {:?} (before {:?})", t.model, t.validation_rel, t.validation_rel_before))
        .collect();
    println!("{}: {e}; tried {tried:?}", fit.layout.effects.model_name());
    let chosen = fit.layout.effects;
    assert!(
        chosen.lr3 && !chosen.creep && !chosen.le_i && !chosen.rms_v,
        "{} taken (the record has LR-2 and LR-3 only); tried {tried:?}",
        chosen.model_name()
    );
    assert!(e.bl <= 2e-4 && e.kms <= 2e-4, "{e}");
}

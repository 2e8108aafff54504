//! `identify` on the independent simulator's real-driver recordings
//! (`shared/recordings/*-real-creep.wav`, `*-real-lr3.wav`: SB17 with LOG creep lambda 0.07,
//! and with an LR-3 branch L3 = 0.6 L2, R3 = 2.5 R2), the effects chosen on held-out data,
//! against the truth (the driver file plus the record's `world`): the right model; Bl(x)
//! within 2 % and Kms(x) within 3 % over the reached range; Re within 0.5 %; lambda within
//! 20 %; L3, R3 within 5 %; the truth within 3 sd of the bands; no residual-above-noise
//! warning. And the plain large records of
//! the three drivers keep the LR-2 model (no effect found where there is none).
//!
//! And `-real-leirv` (flux modulation and velocity-dependent loss): both chosen, their
//! coefficients within 20 % and 3 sd.
//!
//! The effects screen: an effect a record holds scores at least ten times the
//! screen's bar in the round that takes it; on the plain records Le(i) and Rms(v) are screened
//! out, not fitted.
//!
//! Release-profile (each identify with the effects' trials takes 20-40 s):
//! `cargo test --release -p coilscope-ident --test real_driver_recordings -- --ignored`.

mod common;
use coilscope_core::{embedded_driver, Parameters};
use coilscope_ident::large::{identify, IdentifyOptions, LargeFit};
use coilscope_ident::linear::Effects;
use common::Errors;
use std::path::Path;

fn run(file: &str, truth: &Parameters) -> (LargeFit, Vec<f64>) {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/recordings");
    let rec = coilscope_io::read_recording(&dir.join(file), None).unwrap();
    let fs = rec.fs as f64;
    let fit = identify(&rec.u, &rec.i, fs, file, &IdentifyOptions { mms: truth.mms, ..Default::default() }, |_| {})
        .unwrap_or_else(|e| panic!("{file}: {e}"));
    (fit, rec.i)
}

/// Checks shared by the records; returns the problems.
fn check(file: &str, fit: &LargeFit, i: &[f64], truth: &Parameters, want: Effects) -> Vec<String> {
    let mut bad = vec![];
    let q = &fit.params;
    let e = Errors::of(q, truth, fit.x_range);
    let r: Vec<f64> = i[fit.settle..].iter().zip(&fit.i_model[fit.settle..]).map(|(a, b)| a - b).collect();
    let (floor, warnings) = coilscope_ident::checks::residual_warnings(
        &r,
        fit.fs,
        "large-signal fit",
        coilscope_core::simulate::rms(i),
        0.0,
    );
    println!(
        "{file}: model {} ({:?}), order {}, {e}, residual {:.2e} ({:.1}x floor), lambda {:?}, L3/R3 {:?}",
        fit.layout.effects.model_name(),
        fit.effect_trials,
        fit.order,
        fit.residual_rel,
        floor.rms / floor.floor_rms,
        q.creep.as_ref().map(|c| c.lambda),
        q.l3r3
    );
    // The bands: the truth within 3 sd at every point of the reached range.
    let zmax = common::band_z(fit, truth, &["Bl", "Kms", "Le"]);
    println!("{file}: the truth within {zmax:.2} sd of the bands");
    if zmax > 3.0 {
        bad.push(format!("{file}: the truth lies {zmax:.1} sd outside the bands"));
    }
    if fit.layout.effects != want {
        bad.push(format!("{file}: chose {}, not {}", fit.layout.effects.model_name(), want.model_name()));
    }
    bad.extend(common::screen_problems(file, fit, want));
    if !(e.bl <= 0.02 && e.kms <= 0.03 && e.re <= 0.005) {
        bad.push(format!("{file}: {e}"));
    }
    if !warnings.is_empty() {
        bad.push(format!("{file}: {}", warnings.iter().map(|w| w.message.clone()).collect::<Vec<_>>().join("; ")));
    }
    bad
}

#[test]
#[cfg_attr(no_shared, ignore = "../shared is missing (COILSCOPE_NO_SHARED=1): skipped")]
#[ignore = "release-profile sweep: cargo test --release -p coilscope-ident --test real_driver_recordings -- --ignored"]
fn identify_finds_creep_in_the_independent_real_creep_record() {
    let truth = embedded_driver("sb17cac35-4").unwrap();
    let (fit, i) = run("sb17cac35-4-real-creep.wav", &truth);
    let mut bad = check("sb17cac35-4-real-creep.wav", &fit, &i, &truth, Effects { creep: true, ..Effects::NONE });
    let lambda = fit.params.creep.as_ref().map_or(0.0, |c| c.lambda);
    if (lambda / 0.07 - 1.0).abs() > 0.2 {
        bad.push(format!("lambda {lambda} vs 0.07"));
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

#[test]
#[cfg_attr(no_shared, ignore = "../shared is missing (COILSCOPE_NO_SHARED=1): skipped")]
#[ignore = "release-profile sweep: cargo test --release -p coilscope-ident --test real_driver_recordings -- --ignored"]
fn identify_finds_lr3_in_the_independent_real_lr3_record() {
    let truth = embedded_driver("sb17cac35-4").unwrap();
    let (fit, i) = run("sb17cac35-4-real-lr3.wav", &truth);
    let mut bad = check("sb17cac35-4-real-lr3.wav", &fit, &i, &truth, Effects { lr3: true, ..Effects::NONE });
    let (l2, r2) = truth.l2r2.as_ref().map(|(l, r)| (l.c[0], r.c[0])).unwrap();
    let (l3, r3) = fit.params.l3r3.unwrap_or((0.0, 0.0));
    if (l3 / (0.6 * l2) - 1.0).abs() > 0.05 || (r3 / (2.5 * r2) - 1.0).abs() > 0.05 {
        bad.push(format!("L3 {l3} vs {}, R3 {r3} vs {}", 0.6 * l2, 2.5 * r2));
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

/// Flux modulation and velocity-dependent loss (`-real-leirv`: `Le_i` = [1, 0, -0.015],
/// `Rms_v` = Rms (1 + 0.8 v^2)): both chosen, g2 and c2 within 20 % and within 3 sd, g1
/// (zero in the truth) within 3 sd of zero, Rms within 5 %.
#[test]
#[cfg_attr(no_shared, ignore = "../shared is missing (COILSCOPE_NO_SHARED=1): skipped")]
#[ignore = "release-profile sweep: cargo test --release -p coilscope-ident --test real_driver_recordings -- --ignored"]
fn identify_finds_le_i_and_rms_v_in_the_independent_real_leirv_record() {
    let file = "sb17cac35-4-real-leirv.wav";
    let truth = embedded_driver("sb17cac35-4").unwrap();
    let (fit, i) = run(file, &truth);
    let mut bad = check(file, &fit, &i, &truth, Effects { le_i: true, rms_v: true, ..Effects::NONE });
    let unc = &fit.result(file, "given").to_json_value()["uncertainty"];
    let sd = |k: &str, j: usize| unc[k][j].as_f64().unwrap_or(f64::NAN);
    let g = fit.params.le_i.as_ref().map_or(vec![1.0, 0.0, 0.0], |g| g.c.clone());
    let c2 = fit.params.rms_v.as_ref().map_or(0.0, |r| r.c[2]);
    let (g2_true, c2_true) = (-0.015, 0.284);
    println!("{file}: g1 {:.3e} +- {:.1e}, g2 {:.5e} +- {:.1e} (true {g2_true}), Rms {:.5} (true {}), c2 {c2:.5} +- {:.1e} (true {c2_true})", g[1], sd("Le_i", 1), g[2], sd("Le_i", 2), fit.params.rms, truth.rms, sd("Rms_v", 2));
    for (name, got, want, s) in [("g2", g[2], g2_true, sd("Le_i", 2)), ("c2", c2, c2_true, sd("Rms_v", 2))] {
        if (got / want - 1.0).abs() > 0.2 || (got - want).abs() > 3.0 * s {
            bad.push(format!("{name} {got:.5} +- {s:.5} vs {want}"));
        }
    }
    if g[1].abs() > 3.0 * sd("Le_i", 1) {
        bad.push(format!("g1 {:.5} +- {:.5} vs 0", g[1], sd("Le_i", 1)));
    }
    if (fit.params.rms / truth.rms - 1.0).abs() > 0.05 {
        bad.push(format!("Rms {} vs {}", fit.params.rms, truth.rms));
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

#[test]
#[cfg_attr(no_shared, ignore = "../shared is missing (COILSCOPE_NO_SHARED=1): skipped")]
#[ignore = "release-profile sweep: cargo test --release -p coilscope-ident --test real_driver_recordings -- --ignored"]
fn plain_large_records_keep_the_lr2_model() {
    let mut bad = vec![];
    for name in ["sb17cac35-4", "ptt4.0w04-01a", "18wu-4741t-00"] {
        let truth = embedded_driver(name).unwrap();
        let file = format!("{name}-large.wav");
        let (fit, i) = run(&file, &truth);
        bad.extend(check(&file, &fit, &i, &truth, Effects::NONE));
        // Le(i) and Rms(v), which these records lack, are left out by the screen, not fitted
        // (measured: 5e-6 to 1e-5 on SB17, against a bar of 1e-3).
        for added in [Effects { le_i: true, ..Effects::NONE }, Effects { rms_v: true, ..Effects::NONE }] {
            if !fit.effect_screens.iter().any(|s| s.added == added && s.screened_out()) {
                bad.push(format!("{file}: {} was not screened out", added.model_name()));
            }
        }
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

/// Honest uncertainty under model error: with the LR-2 model forced on the creep and LR-3
/// records (residual 13-20x the noise floor), the fit is several percent off, the
/// residual-above-noise warning names it, and the bands of Bl and Kms and the sd of Re still
/// hold the truth within 3 sd (the sandwich covariance widened by the residual's excess;
/// measured 0.6-1.4 sd, against 30-300 sd with the classical covariance).
#[test]
#[cfg_attr(no_shared, ignore = "../shared is missing (COILSCOPE_NO_SHARED=1): skipped")]
#[ignore = "release-profile sweep: cargo test --release -p coilscope-ident --test real_driver_recordings -- --ignored"]
fn a_forced_model_without_the_effect_widens_its_bands_to_the_error() {
    use coilscope_ident::linear::EffectsChoice;
    let truth = embedded_driver("sb17cac35-4").unwrap();
    let mut bad = vec![];
    for file in ["sb17cac35-4-real-creep.wav", "sb17cac35-4-real-lr3.wav"] {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/recordings");
        let rec = coilscope_io::read_recording(&dir.join(file), None).unwrap();
        let fit = identify(
            &rec.u,
            &rec.i,
            rec.fs as f64,
            file,
            &IdentifyOptions { mms: truth.mms, effects: EffectsChoice::Fixed(Effects::NONE), ..Default::default() },
            |_| {},
        )
        .unwrap();
        let e = Errors::of(&fit.params, &truth, fit.x_range);
        let r: Vec<f64> = rec.i[fit.settle..].iter().zip(&fit.i_model[fit.settle..]).map(|(a, b)| a - b).collect();
        let (_, warnings) = coilscope_ident::checks::residual_warnings(
            &r,
            fit.fs,
            "large-signal fit",
            coilscope_core::simulate::rms(&rec.i),
            0.0,
        );
        let z = common::band_z(&fit, &truth, &["Bl", "Kms"]);
        let z_re = (fit.params.re - truth.re).abs() / fit.sd()[0].1;
        println!("{file}, LR-2 forced: {e}, residual {:.2e}, truth within {z:.2} sd (Bl, Kms), Re {z_re:.2} sd, warnings {:?}", fit.residual_rel, warnings.iter().map(|w| w.code.as_ref()).collect::<Vec<_>>());
        if !(e.bl > 0.005 || e.kms > 0.005) {
            bad.push(format!("{file}: the forced model is not off ({e}): the test lost its point"));
        }
        if z > 3.0 || z_re > 3.0 {
            bad.push(format!("{file}: the truth lies {z:.1} sd (Bl, Kms) and {z_re:.1} sd (Re) outside"));
        }
        if !warnings.iter().any(|w| w.code == "residual-above-noise") {
            bad.push(format!("{file}: no residual-above-noise warning"));
        }
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

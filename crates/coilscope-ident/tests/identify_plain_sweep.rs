//! `identify` never fails on plain records.
//!
//! Plain records as `coilscope simulate` makes them: 6 s of pink noise (10 Hz - 8 kHz, crest
//! factor 3) at a level that takes the driver to 70 % of its range, coil heating on, 70 dB
//! sensor noise. Eight seeds on each bundled driver and on a driver with a large,
//! semi-inductive coil (`testdata/drivers/large-coil.json`: Le 2.9 mH, L2 6.7 mH), where two
//! seeds of four once ended with "the start model diverged at sample 1". Every fit must
//! converge. Measured over the 32 records: Bl, Kms, Le <= 0.02 % over the reached range, Re,
//! Rms <= 0.008 % (the README's figures); the test fails at 0.1 % and 0.04 % (the accuracy
//! bounds are 2 %, 5 % and 1 %), or when the truth lies more than 3 sd outside a band.
//!
//! Slow in a debug build: `cargo test --release -p coilscope-ident --test
//! identify_plain_sweep -- --ignored` (`.ci/run` runs it).

use coilscope_ident::large::{identify, IdentifyOptions, Progress, Stage};
// The LR-2 model: what this sweep tests is that the fit never fails; the choice of effects
// (and that plain records keep LR-2) is tested in real_driver_recordings.rs.
use coilscope_ident::linear::{Effects, EffectsChoice};

mod common;
use common::world::{driver, pink_record as record};
use common::Errors;

const FS: f64 = 48000.0;

fn sweep(name: &str) {
    let p = driver(name);
    let fs = FS;
    let mut failures = Vec::new();
    for seed in common::slice::in_slice(name, (1..=8u64).collect()) {
        let (u, i, s) = record(&p, fs, 6.0, 0.7, seed);
        let label = format!("{name} seed {seed}");
        match identify(
            &u,
            &i,
            fs,
            &label,
            &IdentifyOptions { mms: p.mms, effects: EffectsChoice::Fixed(Effects::NONE), ..Default::default() },
            |_| {},
        ) {
            Ok(fit) => {
                let e = Errors::of(&fit.params, &p, [s.x_min, s.x_max]);
                let z = common::band_z(&fit, &p, &["Bl", "Kms", "Le"]);
                let line = format!(
                    "{label}: order {}, residual {:.2e}, {e}, the truth within {z:.2} sd of the bands",
                    fit.order, fit.residual_rel
                );
                println!("{line}");
                if !(e.bl <= 1e-3 && e.kms <= 1e-3 && e.le <= 1e-3 && e.re <= 4e-4 && e.rms <= 4e-4) {
                    failures.push(format!("{line}: beyond 5x the published figures"));
                }
                if !(z <= 3.0) {
                    failures.push(format!("{line}: the bands miss the truth"));
                }
            }
            Err(e) => failures.push(format!("{label}: {e}")),
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
#[ignore = "release-profile sweep: cargo test --release -p coilscope-ident --test identify_plain_sweep -- --ignored"]
fn identify_never_fails_on_sb17() {
    sweep("sb17cac35-4");
}

#[test]
#[ignore = "release-profile sweep: cargo test --release -p coilscope-ident --test identify_plain_sweep -- --ignored"]
fn identify_never_fails_on_ptt4() {
    sweep("ptt4.0w04-01a");
}

#[test]
#[ignore = "release-profile sweep: cargo test --release -p coilscope-ident --test identify_plain_sweep -- --ignored"]
fn identify_never_fails_on_18wu() {
    sweep("18wu-4741t-00");
}

#[test]
#[ignore = "release-profile sweep: cargo test --release -p coilscope-ident --test identify_plain_sweep -- --ignored"]
fn identify_never_fails_on_a_large_semi_inductive_coil() {
    sweep("large-coil");
}

/// Microspeakers heat fast: a 2 s thermal time constant (Rtv 40 K/W, Ctv 0.05 J/K). The 0.1 g
/// set driven to 85 % of its +-0.5 mm heats 65 K in 8 s, the 2.7 g set at 40 % of +-3 mm 47 K.
/// The `Re(t)` knots 2 s apart could not follow (Re 1.6 % off, Le 0.6 %, the residual 15x
/// its floor); `identify` now adds heating terms to `Re(t)` (`large::HEAT_TAUS`). Measured:
/// Bl, Kms <= 0.01 %, Le 0.012-0.082 %, Re <= 0.016 %, the residual 1.02-1.11x
/// its floor.
/// The test fails at Bl, Kms 0.1 %, Le 0.2 %, Re 0.1 %, or a residual above 2x its floor,
/// or when a fit that ends with heating terms took a step without them first (the
/// heating test is made on the first Jacobian's linearised step, which saves
/// the microspeaker that step's residual run).
///
/// Two cases that used to fail:
/// * the 0.1 g set with seed 2 (68 K): the small-signal start put all the inductance into
///   L2 (Le = 0) and the start model could not run ("diverged at sample 1"); the start now
///   shares it (`large::split_vanished_le`);
/// * the 2.7 g set at 50 % and 96 kHz (106 K): L2 ran to -4e15 H (a branch that acts as a
///   resistor) and Re came out 19 % high; trials with a non-positive or unbounded branch are
///   now rejected (`Layout::physical`). Checked with the CLI (Re 0.03 %, Bl 0.00 % at rest,
///   Le 2 %: L2/R2 has a 7 us time constant, under a sample at 96 kHz); not in this list, whose
///   Le bound is 0.2 %.
#[test]
#[ignore = "release-profile sweep: cargo test --release -p coilscope-ident --test identify_plain_sweep -- --ignored"]
fn identify_follows_the_fast_heating_of_microspeakers() {
    let cases = vec![
        ("microspeaker-0g1", 0.85, 1, FS),
        ("microspeaker-2g7", 0.4, 1, FS),
        ("microspeaker-2g7", 0.4, 2, FS),
        ("microspeaker-0g1", 0.85, 2, FS),
    ];
    fast_heating(common::slice::in_slice("microspeakers", cases));
}

fn fast_heating(cases: Vec<(&str, f64, u64, f64)>) {
    let mut failures = Vec::new();
    for (name, share, seed, fs) in cases {
        let p = driver(name);
        let (u, i, s) = record(&p, fs, 8.0, share, seed);
        let label =
            format!("{name} at {:.0} % seed {seed}, {:.0} kHz (heats {:.0} K)", 100.0 * share, fs / 1e3, s.dt_max);
        // (unknowns, iteration) of the final fit's states.
        let mut finals: Vec<(usize, usize)> = Vec::new();
        let observe = |pr: &Progress| {
            if matches!(pr.stage, Stage::Final { .. }) {
                finals.push((pr.state.theta.len(), pr.state.iteration));
            }
        };
        match identify(
            &u,
            &i,
            fs,
            &label,
            &IdentifyOptions { mms: p.mms, effects: EffectsChoice::Fixed(Effects::NONE), ..Default::default() },
            observe,
        ) {
            Ok(fit) => {
                // The heating test is made on the first Jacobian's
                // linearised step, and the fit with the heating terms starts from there
                // (no step is taken without them).
                let most = finals.iter().map(|f| f.0).max().unwrap_or(0);
                let unheated_steps = finals.iter().filter(|f| f.0 < most && f.1 > 0).count();
                if !fit.layout.heat_taus.is_empty() && unheated_steps > 0 {
                    failures.push(format!(
                        "{label}: {unheated_steps} steps without the heating terms before they were tried"
                    ));
                }
                let e = Errors::of(&fit.params, &p, [s.x_min, s.x_max]);
                let r: Vec<f64> = fit.i_model.iter().zip(&i).skip(fit.settle).map(|(a, b)| a - b).collect();
                let floor = coilscope_ident::checks::noise_floor(&r, fs).ratio;
                let line = format!(
                    "{label}: order {}, residual {:.2e} ({floor:.2}x its floor), heating terms {:?}, {e}",
                    fit.order, fit.residual_rel, fit.layout.heat_taus
                );
                println!("{line}");
                if !(e.bl <= 1e-3 && e.kms <= 1e-3 && e.le <= 2e-3 && e.re <= 1e-3) {
                    failures.push(format!("{line}: beyond the test's bounds"));
                }
                if !(floor <= 2.0) {
                    failures.push(format!("{line}: residual above 2x its floor"));
                }
            }
            Err(e) => failures.push(format!("{label}: {e}")),
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

//! Large-signal identification of a driver in its box (`IdentifyOptions::enclosure`) against
//! the truth, on fresh drivers and boxes of the population, simulated by our own model (the
//! independent simulator's box records, with their own truth).
//!
//! Release sweeps (`--ignored`; `.ci/run` runs them). Recordings: 6 s at 48 kHz of pink noise (10 Hz - 8 kHz, crest factor 3) at the level that
//! takes the cone to 70 % of its range, 70 dB sensor noise, the LR-2 world (no creep, LR-3,
//! Le(i) or Rms(v): those are the free-air tests' matter). The bounds are the published ones:
//! Bl, Kms within 1 % and Le within 3 % over the reached range, Re within 0.3 %; Vb within 2
//! %, fb within 1 %, QL within 25 %, the port's loss within 20 % (when the port's air moved
//! fast enough for it to show), the radiator's mass and stiffness within 3 %, and the truth
//! within 4.5 sd of each box value (its sd with [`coilscope_ident::large::BOX_SYSTEMATIC_REL`]).

use coilscope_core::enclosure::{BoxKind, Enclosure};
use coilscope_core::population::draw_box;
use coilscope_core::result::Sd;
use coilscope_core::Parameters;
use coilscope_ident::box_fit::BoxChoice;
use coilscope_ident::large::{identify, IdentifyOptions, InBox, LargeFit};
use coilscope_ident::linear::{Effects, EffectsChoice};
use coilscope_testkit::population::keep_failure;

mod common;
use common::world::pink_record;
use common::Errors;

fn bound(key: &str) -> f64 {
    match key {
        "enclosure.Vb" => 0.02,
        "enclosure.fb" => 0.01,
        "enclosure.Mmp" | "enclosure.Kmp" => 0.03,
        "enclosure.port_loss" | "enclosure.knl" => 0.20,
        _ => 0.25,
    }
}

/// The box's values against the truth: (key, relative error, z).
fn box_errors(fit: &LargeFit, truth: &Enclosure) -> Vec<(&'static str, f64, f64)> {
    let got = fit.params.enclosure.as_ref().expect("a box fit has a box");
    let mut out = Vec::new();
    for key in [
        "enclosure.Vb",
        "enclosure.QL",
        "enclosure.fb",
        "enclosure.Qp",
        "enclosure.port_loss",
        "enclosure.Mmp",
        "enclosure.Kmp",
        "enclosure.Rmp",
    ] {
        let (Some(g), Some(t)) = (got.get(key), truth.get(key)) else { continue };
        let fitted = fit.layout.enclosure.as_ref().is_some_and(|b| {
            b.keys.contains(&key) || (key == "enclosure.port_loss" && b.keys.contains(&"enclosure.knl"))
        });
        if !fitted {
            continue;
        }
        let sd = match (
            &fit.cov,
            fit.layout.sd_of(key, &fit.theta, &|a, b| fit.cov.as_ref().map_or(f64::NAN, |c| c[(a, b)])),
        ) {
            (Some(_), Some(Sd::Value(s))) => s,
            (Some(_), Some(Sd::Coefficients(c))) => c[0],
            _ => f64::NAN,
        };
        out.push((key, g / t - 1.0, (g - t) / sd));
    }
    out
}

/// The fit of `label` against its truth (`truth` in `b`, over the reached `x_range`): what is
/// out of its bound, and the residual's ratio to its noise floor. Prints the errors.
fn judge(label: &str, fit: &LargeFit, truth: &Parameters, b: &Enclosure, x_range: [f64; 2]) -> (Vec<String>, f64) {
    let e = Errors::of(&fit.params, truth, x_range);
    let mut bad = Vec::new();
    for (what, v, lim) in [("Bl", e.bl, 0.01), ("Kms", e.kms, 0.01), ("Le", e.le, 0.03), ("Re", e.re, 0.003)] {
        if !(v <= lim) {
            bad.push(format!("{what} {:.3} % (bound {:.1} %)", 100.0 * v, 100.0 * lim));
        }
    }
    let be = box_errors(fit, b);
    for (k, err, z) in &be {
        if !(err.abs() < bound(k)) {
            bad.push(format!("{k} {:+.2} % (bound {:.0} %)", 100.0 * err, 100.0 * bound(k)));
        }
        if !(z.abs() <= 4.5) {
            bad.push(format!("{k} {z:+.1} sd"));
        }
    }
    let r: Vec<f64> = fit.i_model.iter().zip(&fit.i_phys).skip(fit.settle).map(|(a, b)| a - b).collect();
    // The ratio the command line's verdict reads (the quiet quarter of the band as the floor
    // where the model's error fills the rest).
    let ratio = coilscope_ident::checks::residual_warnings(&r, fit.fs, "fit", 1.0, 0.0).0.ratio;
    eprintln!(
        "{label}: model {}, order {}, residual {:.2e} ({ratio:.1} x floor), {e}; box: {}",
        fit.layout.effects.model_name(),
        fit.order,
        fit.residual_rel,
        be.iter().map(|(k, e, z)| format!("{k} {:+.3} % ({z:+.1} sd)", 100.0 * e)).collect::<Vec<_>>().join(", ")
    );
    (bad, ratio)
}

/// What one fit of a drawn driver in a drawn box came to.
enum Outcome {
    /// Within every bound.
    Right,
    /// Refused with an error, or ended far above its noise floor (the workflow's
    /// `residual-above-noise` warning): wrong, but not silently.
    Loud(String),
    /// Out of a bound at the noise floor: a silent wrong answer.
    Silent(String),
}

/// Identify the driver of `seed` in a box of type `ty` drawn for it, and judge the result.
fn one(seed: u64, ty: &str) -> (String, Outcome) {
    let d = coilscope_core::population::draw(seed);
    let mut truth = d.plain.clone();
    let b = draw_box(d.seed, &truth, Some(ty));
    truth.enclosure = Some(b.clone());
    let (u, i, s) = pink_record(&truth, 48_000.0, 6.0, 0.7, d.seed);
    let sd = truth.sd.unwrap();
    let port_area = match &b.kind {
        BoxKind::Vented { port_area, .. } => *port_area,
        _ => None,
    };
    let sp = match &b.kind {
        BoxKind::PassiveRadiator { sp, .. } => Some(*sp),
        _ => None,
    };
    let opts = IdentifyOptions {
        mms: truth.mms,
        effects: EffectsChoice::Fixed(Effects::NONE),
        enclosure: Some(InBox {
            choice: BoxChoice::parse(ty).unwrap(),
            sd,
            vb: (ty == "closed").then_some(b.vb),
            port_area,
            sp,
        }),
        ..IdentifyOptions::default()
    };
    let name = format!("{} in a {ty} box", d.name());
    let fit = match identify(&u, &i, 48_000.0, &name, &opts, |_| {}) {
        Ok(f) => f,
        Err(e) => return (name, Outcome::Loud(format!("refused: {e}"))),
    };
    let (bad, ratio) = judge(&name, &fit, &truth, &b, [s.x_min, s.x_max]);
    let outcome = if bad.is_empty() {
        Outcome::Right
    } else if ratio > coilscope_ident::checks::RESIDUAL_RATIO_WARN {
        Outcome::Loud(format!("{} at {ratio:.1} x the noise floor", bad.join("; ")))
    } else {
        Outcome::Silent(format!("{} at {ratio:.1} x the noise floor", bad.join("; ")))
    };
    (name, outcome)
}

/// Fresh drivers of the population, each in a fresh box of each type in turn: none may be
/// silently wrong, and one at least must be right (about half are: 8 of 15 in the sweeps
/// that set this; the others refused or far above their noise floor). The others are printed
/// with their `population:` names, to be kept in [`KEPT`].
#[test]
#[ignore = "release sweep: .ci/run runs it"]
fn fresh_drivers_in_fresh_boxes_are_identified_with_their_boxes() {
    let seeds = coilscope_testkit::population::seeds("identify_in_a_box", FRESH);
    let (mut right, mut loud, mut silent) = (0, Vec::new(), Vec::new());
    for (n, seed) in seeds.into_iter().enumerate() {
        let ty = ["closed", "vented", "passive_radiator"][n % 3];
        let (name, outcome) = one(seed, ty);
        match outcome {
            Outcome::Right => right += 1,
            Outcome::Loud(m) => loud.push(format!("{name}: {m}")),
            Outcome::Silent(m) => {
                let kept = keep_failure(&name, &coilscope_core::population::draw(seed).plain);
                silent.push(format!("{name}: {m} (kept: {})", kept.display()))
            }
        }
    }
    eprintln!("right {right} of {FRESH}; wrong but loud: {}", loud.len());
    for l in &loud {
        eprintln!("  {l}");
    }
    assert!(silent.is_empty(), "silently wrong:\n{}", silent.join("\n"));
    assert!(right >= 1, "none of {FRESH} right:\n{}", loud.join("\n"));
}

/// Fresh draws per run: two of each box type.
const FRESH: usize = 6;

/// Draws a sweep failed on, by `population:` seed and box type, and whether the fit is now
/// right (`true`) or still wrong but loud (`false`: refused, or far above its floor).
const KEPT: [(&str, u64, &str, bool); 8] = [
    // A grid over the driver's resonance ended with the port tuned at 312 Hz; two peaks read
    // Thiele's way start it right.
    ("population:subwoofer:3958736020", 3958736020, "vented", true),
    // The joint small-signal fit stuck on a wall of its ranges, 13-17 % from the impedance
    // (the truth 3 %); with the ranges as penalty rows it comes right.
    ("population:woofer:2616793441", 2616793441, "vented", true),
    ("population:woofer:2758093175", 2758093175, "passive_radiator", true),
    // Right with the joint fit's ranges as walls alone, wrong (and loud) with the rows.
    ("population:midwoofer:1326074088", 1326074088, "vented", false),
    // The radiator vanishes into an open hole (its mass, stiffness and loss to zero).
    ("population:woofer:953014526", 953014526, "passive_radiator", false),
    ("population:woofer:3503997956", 3503997956, "passive_radiator", false),
    // The leak's Q runs away (closed box of given volume), at 29 times the floor.
    ("population:midwoofer:3448770891", 3448770891, "closed", false),
    // Order 2 taken, Kms 8.6 % off at 3 times the floor.
    ("population:microspeaker:243204631", 243204631, "vented", false),
];

/// Draws a sweep found silently wrong and that still are: run and printed with the kept ones,
/// not asserted, until they are right or loud (then they move to [`KEPT`]).
const OPEN_SILENT: [(&str, u64, &str); 1] = [
    // The radiator vanishes (Kmp -99 %, Rmp -100 %, Vb +21 %, Kms 6 % off) with the residual
    // 1.9 times its floor: the model's error sits at low frequencies, where a floor read from
    // the spectrum cannot see it.
    ("population:midwoofer:251209093", 251209093, "passive_radiator"),
];

#[test]
#[ignore = "release sweep: .ci/run runs it, a slice per run"]
fn kept_draws_in_boxes_stay_right_or_loud() {
    let mut bad = Vec::new();
    for (label, seed, ty, right) in coilscope_testkit::slice::in_slice("kept_draws_in_boxes", KEPT.to_vec()) {
        let (name, outcome) = one(seed, ty);
        match (outcome, right) {
            (Outcome::Right, _) => {}
            (Outcome::Loud(m), false) => eprintln!("{label} ({name}) still open: {m}"),
            (Outcome::Loud(m), true) => bad.push(format!("{label} ({name}) was right, now: {m}")),
            (Outcome::Silent(m), _) => bad.push(format!("{label} ({name}) silently wrong: {m}")),
        }
    }
    for (label, seed, ty) in coilscope_testkit::slice::in_slice("open_silent_draws_in_boxes", OPEN_SILENT.to_vec()) {
        match one(seed, ty) {
            (name, Outcome::Right) => eprintln!("{label} ({name}) is now right: move it to KEPT"),
            (name, Outcome::Loud(m)) => eprintln!("{label} ({name}) is now loud, move it to KEPT: {m}"),
            (name, Outcome::Silent(m)) => eprintln!("{label} ({name}) still open, silently wrong: {m}"),
        }
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

/// The independent simulator's box records (`shared/recordings/*-box-*`): SB17 in a closed
/// 12 l box (its volume given), SB17 in a vented 20 l box with port compression, PTT4 with a
/// passive radiator, and 18WU in a vented 40 l box with creep, LR-3 and a sound card's chain
/// (the chain and the effects found by the fit itself). The same bounds as our own records;
/// the truth is the driver file and the record's `world.enclosure`. One record per run
/// (18WU's takes two minutes).
///
/// Open: PTT4 with its radiator. The joint small-signal start lets the radiator's loss go to
/// zero and the time-domain fit does not come back (Kms 43 % off, the radiator's stiffness
/// to zero); it ends at 6 times its noise floor, and the command line says the result is
/// not trustworthy. It must stay that loud until it is right.
#[test]
#[cfg_attr(no_shared, ignore = "../shared is missing (COILSCOPE_NO_SHARED=1): skipped")]
#[ignore = "release sweep: .ci/run runs it, a slice per run"]
fn the_independent_box_records_are_identified_with_their_boxes() {
    // (record, driver, through a card with the effects of a real driver, still open)
    let records = [
        ("sb17cac35-4-box-closed", "sb17cac35-4", false, false),
        ("sb17cac35-4-box-vented", "sb17cac35-4", false, false),
        ("ptt4.0w04-01a-box-pr", "ptt4.0w04-01a", false, true),
        ("18wu-4741t-00-box-vented-real", "18wu-4741t-00", true, false),
    ];
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/recordings");
    let mut bad = Vec::new();
    for (file, driver, real, open) in coilscope_testkit::slice::in_slice("independent_box_records", records.to_vec()) {
        let info = dir.join(format!("{file}.info.json"));
        let b = coilscope_io::load_enclosure(&info).unwrap();
        let mut truth = coilscope_core::embedded_driver(driver).unwrap();
        truth.enclosure = Some(b.clone());
        let rec = coilscope_io::read_recording(&dir.join(format!("{file}.wav")), None).unwrap();
        let (port_area, sp) = match &b.kind {
            BoxKind::Vented { port_area, .. } => (*port_area, None),
            BoxKind::PassiveRadiator { sp, .. } => (None, Some(*sp)),
            BoxKind::Closed => (None, None),
        };
        let opts = IdentifyOptions {
            mms: truth.mms,
            chain: real,
            // As the command line does by default: the chain estimated where the record shows one.
            detect_chain: !real,
            enclosure: Some(InBox {
                choice: BoxChoice::parse(b.type_name()).unwrap(),
                sd: truth.sd.unwrap(),
                vb: matches!(b.kind, BoxKind::Closed).then_some(b.vb),
                port_area,
                sp,
            }),
            ..IdentifyOptions::default()
        };
        let fit =
            identify(&rec.u, &rec.i, rec.fs as f64, file, &opts, |_| {}).unwrap_or_else(|e| panic!("{file}: {e}"));
        let (wrong, ratio) = judge(file, &fit, &truth, &b, fit.x_range);
        let wrong: Vec<String> = wrong.into_iter().map(|w| format!("{file}: {w}")).collect();
        if open && !wrong.is_empty() {
            eprintln!("{file}: still open, at {ratio:.1} x its noise floor: {}", wrong.join("; "));
            if !(ratio > coilscope_ident::checks::RESIDUAL_RATIO_WARN) {
                bad.push(format!("{file}: wrong and no longer loud ({ratio:.1} x the floor): {}", wrong.join("; ")));
            }
        } else {
            bad.extend(wrong);
        }
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

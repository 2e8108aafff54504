//! `coilscope compensate` end to end: a 30 Hz tone in, the drive out; the drive,
//! played by `simulate --input`, moves the driver as the linear reference does (the check
//! the command prints), and bad inputs get one clear line.

use std::process::{Command, Output};

fn coilscope(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_coilscope")).args(args).output().unwrap()
}

#[test]
fn compensate_writes_a_drive_that_linearises_the_displacement() {
    let d = tempfile::tempdir().unwrap();
    let tone = d.path().join("tone.wav");
    let drive = d.path().join("drive.wav");
    let p = |p: &std::path::Path| p.to_str().unwrap().to_string();
    let o = coilscope(&[
        "simulate",
        "sb17cac35-4",
        "--excitation",
        "sine",
        "--freq",
        "30",
        "--volts",
        "3",
        "--seconds",
        "1",
        "--out",
        &p(&tone),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = coilscope(&["compensate", "sb17cac35-4", "--input", &p(&tone), "--out", &p(&drive)]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout).into_owned();
    // "... (largest): plain A m, compensated B m": B at least 1e4 below A.
    let line = text.lines().find(|l| l.contains("off the linear reference")).unwrap_or_else(|| panic!("{text}"));
    let nums: Vec<f64> = line.split_whitespace().filter_map(|w| w.parse::<f64>().ok()).collect();
    assert_eq!(nums.len(), 2, "{line}");
    assert!(nums[0] > 1e-4 && nums[1] < 1e-4 * nums[0], "{line}");
    let (fs, u) = coilscope_io::read_voltage(&drive, None).unwrap();
    assert_eq!((fs, u.len()), (48000, 48000));
    // Clipping is reported.
    let o = coilscope(&["compensate", "sb17cac35-4", "--input", &p(&tone), "--out", &p(&drive), "--max-volts", "2"]);
    assert!(o.status.success());
    assert!(String::from_utf8_lossy(&o.stdout).contains("warning: the drive was clipped at 2.000 V"));
    // Too loud for the range: one clear line, exit 2.
    let loud = d.path().join("loud.wav");
    let u: Vec<f64> =
        (0..14400).map(|k| 60.0 * (2.0 * std::f64::consts::PI * 20.0 * k as f64 / 48000.0).sin()).collect();
    coilscope_io::write_voltage(&loud, 48000, &u).unwrap();
    let o = coilscope(&["compensate", "sb17cac35-4", "--input", &p(&loud), "--out", &p(&drive)]);
    assert_eq!(o.status.code(), Some(2));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("leaves the driver's valid range") && e.trim_end().lines().count() == 1, "{e}");
    let o = coilscope(&["compensate", "sb17cac35-4", "--input", "/nonexistent.wav", "--out", &p(&drive)]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("/nonexistent.wav"));
}

/// `coilscope quasistatic`: the point-by-point measurement on a virtual driver writes a
/// quasi-static result with every working point and the curves' bands; with 5 points (4
/// static ones for a 4th-order series) it says that nothing checks the series between the
/// points (exit 3, the result written); it names a bad option.
#[test]
fn quasistatic_writes_the_points_and_the_fitted_curves() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("qs.json");
    let o =
        coilscope(&["quasistatic", "ptt4.0w04-01a", "--points", "5", "--hold", "1", "--out", out.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(3), "{}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("4 static points for a series of order 4"), "{text}");
    assert!(text.contains("stiffness at rest: dynamic") && text.contains("rest position"), "{text}");
    let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert_eq!(r["kind"], "quasi-static");
    assert_eq!(r["quasi_static"]["points"].as_array().unwrap().len(), 5);
    assert_eq!(r["fit"]["trustworthy"], false);
    for k in ["Bl_band", "Kms_band", "Le_band"] {
        assert_eq!(r["uncertainty"][k]["sd"].as_array().unwrap().len(), 21, "{k}");
    }
    // The fitted Bl at rest is the driver's within 0.5 %.
    let bl0 = r["parameters"]["Bl"][0].as_f64().unwrap();
    let truth = coilscope_core::embedded_driver("ptt4.0w04-01a").unwrap().bl.c[0];
    assert!((bl0 / truth - 1.0).abs() < 5e-3, "{bl0} vs {truth}");
    // By pressure (the set's Sd): no current at any point, the pressure recorded.
    let o = coilscope(&[
        "quasistatic",
        "ptt4.0w04-01a",
        "--offset",
        "pressure",
        "--hold",
        "1",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert_eq!(r["quasi_static"]["offset"], "pressure on the diaphragm");
    let pts = r["quasi_static"]["points"].as_array().unwrap();
    assert!(pts.iter().all(|w| w["I_dc"].as_f64().unwrap().abs() < 1e-3));
    assert!(pts.iter().any(|w| w["pressure_Pa"].as_f64().unwrap() > 100.0), "{pts:?}");
    let o = coilscope(&["quasistatic", "ptt4.0w04-01a", "--reach", "1.5", "--out", out.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("--reach 1.5"));
}

/// `report --compare`: the quasi-static result against the driver's dynamic parameters,
/// overlaid (dashed) on the curve charts, the differences tabulated (compare.csv), and the
/// paper's two caveats (static vs dynamic stiffness, rest drift) shown; another driver's
/// result is refused.
#[test]
fn report_compares_quasi_static_with_dynamic_curves() {
    let d = tempfile::tempdir().unwrap();
    let qs = d.path().join("qs.json");
    let p = |p: &std::path::Path| p.to_str().unwrap().to_string();
    let o = coilscope(&["quasistatic", "ptt4.0w04-01a", "--hold", "1", "--out", &p(&qs)]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let html = d.path().join("r.html");
    let o = coilscope(&["report", &p(&qs), "--compare", "ptt4.0w04-01a", "--out", &p(&html)]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = std::fs::read_to_string(&html).unwrap();
    assert!(
        text.contains("quasi-static and parameter set compared")
            && text.contains("quasi-static caveat")
            && text.contains("rest position 1.5 s after the largest offset"),
        "compare section missing"
    );
    let csv = std::fs::read_to_string(d.path().join("r_files/compare.csv")).unwrap();
    // Without creep the quasi-static curves are the set's: Bl and Kms within 1 % over the
    // common range (measured 0.06 % and 0.15 %).
    for row in csv.lines().skip(1) {
        let f: Vec<&str> = row.split(',').collect();
        let diff: f64 = f[1].parse().unwrap();
        if f[0] != "Le" {
            assert!(diff < 0.01, "{row}");
        }
    }
    assert_eq!(csv.lines().count(), 4, "{csv}");
    let o = coilscope(&["report", &p(&qs), "--compare", "sb17cac35-4", "--out", &p(&html)]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("same driver"));
}

fn text(o: &Output) -> String {
    format!("{}\n{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

/// `quasistatic --card`: what a sound card cannot do, and what a real driver must be told,
/// is named before any device is opened (the card path itself is tested headless in
/// coilscope-measure's `quasistatic_card.rs`).
#[test]
fn quasistatic_card_names_what_it_needs() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("q.json");
    let out = out.to_str().unwrap();
    for (args, want) in [
        (vec!["--xmax", "4mm", "--offset", "mass"], "needs --mms KG"),
        (vec!["--mms", "0.015", "--offset", "mass"], "needs --xmax LENGTH"),
        (vec!["--mms", "0.015", "--xmax", "4mm"], "cannot hold a DC current"),
        (vec!["--mms", "0.015", "--xmax", "4mm", "--offset", "pressure"], "needs --sd M2"),
        (vec!["--mms=-1", "--xmax", "4mm", "--offset", "mass"], "--mms -1 kg is not valid"),
    ] {
        let o = coilscope(&[&["quasistatic", "--card", "--out", out][..], &args[..]].concat());
        assert_eq!(o.status.code(), Some(2), "{args:?}: {}", text(&o));
        assert!(text(&o).contains(want), "{args:?}: {}", text(&o));
    }
    // A virtual driver and --card are one or the other.
    let o = coilscope(&["quasistatic", "sb17cac35-4", "--card", "--out", out]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
}

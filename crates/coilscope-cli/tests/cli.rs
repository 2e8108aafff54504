//! The `coilscope` binary end to end: main job, and one clear line for each bad input.

use std::process::{Command, Output};

fn coilscope(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_coilscope")).args(args).output().unwrap()
}

fn one_error_line(o: &Output) -> String {
    assert_eq!(o.status.code(), Some(2), "stdout: {}", String::from_utf8_lossy(&o.stdout));
    let e = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(!e.contains("panicked"), "{e}");
    assert_eq!(e.trim_end().lines().count(), 1, "not one line: {e}");
    assert!(e.starts_with("error: "), "{e}");
    e
}

#[test]
fn simulate_writes_a_recording_and_reports_excursion_temperature_and_power() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("rec.wav");
    let o = coilscope(&[
        "simulate",
        "ptt4.0w04-01a",
        "--volts",
        "2",
        "--seconds",
        "1",
        "--laser",
        "--snr-db",
        "70",
        "--seed",
        "3",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout);
    for want in ["peak excursion", "electrical power", "voice coil", "mm"] {
        assert!(text.contains(want), "{text}");
    }
    let rec = coilscope_io::read_recording(&out, None).unwrap();
    assert_eq!(rec.fs, 48000);
    assert_eq!(rec.u.len(), 48000);
    let x = rec.x.unwrap();
    let info: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.path().join("rec.info.json")).unwrap()).unwrap();
    let x_max = info["x_max"].as_f64().unwrap();
    let peak_rec = x.iter().cloned().fold(f64::MIN, f64::max);
    // The recorded displacement (with 70 dB noise) peaks where the summary says.
    assert!((peak_rec - x_max).abs() < 0.02 * x_max, "{peak_rec} vs {x_max}");
    assert!(info["dT_end"].as_f64().unwrap() > 0.0);
    // Deterministic: the same seed gives the same file.
    let again = d.path().join("again.wav");
    let o = coilscope(&[
        "simulate",
        "ptt4.0w04-01a",
        "--volts",
        "2",
        "--seconds",
        "1",
        "--laser",
        "--snr-db",
        "70",
        "--seed",
        "3",
        "--out",
        again.to_str().unwrap(),
    ]);
    assert!(o.status.success());
    assert_eq!(std::fs::read(&out).unwrap(), std::fs::read(&again).unwrap());
}

#[test]
fn simulate_runs_other_rates_and_excitations() {
    let d = tempfile::tempdir().unwrap();
    for (rate, exc) in [("44100", "sine"), ("96000", "multitone"), ("48000", "sweep"), ("48000", "pink")] {
        let out = d.path().join(format!("{rate}-{exc}.wav"));
        let o = coilscope(&[
            "simulate",
            "sb17cac35-4",
            "--excitation",
            exc,
            "--volts",
            "1",
            "--seconds",
            "0.5",
            "--rate",
            rate,
            "--out",
            out.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{rate} {exc}: {}", String::from_utf8_lossy(&o.stderr));
        assert_eq!(coilscope_io::read_recording(&out, None).unwrap().fs.to_string(), rate);
    }
}

#[test]
fn bad_inputs_get_one_clear_line() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("o.wav");
    let out = out.to_str().unwrap();
    // Unknown driver.
    let e = one_error_line(&coilscope(&["simulate", "nope", "--volts", "1", "--out", out]));
    assert!(e.contains("nope: neither an embedded driver"), "{e}");
    // Parameter file in wrong units.
    let p = d.path().join("bad.json");
    std::fs::write(&p, r#"{"Re": 3.3, "Le": 0.0001, "Bl": 5.0, "Kms": 600.0, "Mms": 15, "Rms": 0.5}"#).unwrap();
    let e = one_error_line(&coilscope(&["simulate", p.to_str().unwrap(), "--volts", "1", "--out", out]));
    assert!(e.contains("bad.json: key `Mms`") && e.contains("grams"), "{e}");
    // Broken JSON.
    std::fs::write(&p, "{ not json").unwrap();
    let e = one_error_line(&coilscope(&["check", p.to_str().unwrap()]));
    assert!(e.contains("bad.json: not valid JSON"), "{e}");
    // A WAV that is not one.
    let w = d.path().join("fake.wav");
    std::fs::write(&w, "RIFF????").unwrap();
    let e = one_error_line(&coilscope(&["simulate", "sb17cac35-4", "--input", w.to_str().unwrap(), "--out", out]));
    assert!(e.contains("fake.wav: not a readable WAV file"), "{e}");
    // Missing level.
    let e = one_error_line(&coilscope(&["simulate", "sb17cac35-4", "--out", out]));
    assert!(e.contains("--volts RMS is required"), "{e}");
    // Driven past its valid range: names time and state.
    let e = one_error_line(&coilscope(&[
        "simulate",
        "sb17cac35-4",
        "--excitation",
        "sine",
        "--freq",
        "20",
        "--volts",
        "20",
        "--seconds",
        "1",
        "--out",
        out,
    ]));
    assert!(e.contains("simulation stopped at t = ") && e.contains("outside x_range"), "{e}");
    // Output directory missing.
    let e = one_error_line(&coilscope(&[
        "simulate",
        "sb17cac35-4",
        "--volts",
        "1",
        "--seconds",
        "0.2",
        "--out",
        "/nonexistent-dir-xyz/o.wav",
    ]));
    assert!(e.contains("does not exist"), "{e}");
    // Bad band.
    let e = one_error_line(&coilscope(&[
        "simulate",
        "sb17cac35-4",
        "--excitation",
        "pink",
        "--band",
        "500",
        "100",
        "--volts",
        "1",
        "--out",
        out,
    ]));
    assert!(e.contains("--band 500 100: give LO HI (or LO,HI) in Hz with 0 <= LO < HI"), "{e}");
}

#[test]
fn drivers_and_check_list_the_embedded_sets() {
    let o = coilscope(&["drivers"]);
    let t = String::from_utf8_lossy(&o.stdout);
    for n in ["sb17cac35-4", "ptt4.0w04-01a", "18wu-4741t-00"] {
        assert!(t.contains(n), "{t}");
    }
    let o = coilscope(&["check", "18wu-4741t-00"]);
    assert!(o.status.success());
    assert!(String::from_utf8_lossy(&o.stdout).contains("Qts"));
}

/// The result file at `path` as JSON, after checking that the typed reader
/// (`coilscope_core::result::ResultFile`) knows every key in it and writes it back unchanged.
fn typed_result(path: &std::path::Path) -> serde_json::Value {
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    let r = coilscope_core::result::ResultFile::from_json_value(v.clone(), &path.display().to_string()).unwrap();
    assert!(r.other.is_empty(), "keys the typed result does not know: {:?}", r.other.keys().collect::<Vec<_>>());
    assert_eq!(r.to_json_value(), v, "the typed result does not write the file back unchanged");
    v
}

#[test]
fn linear_writes_a_result_zma_and_csv() {
    let d = tempfile::tempdir().unwrap();
    let rec = d.path().join("small.wav");
    let o = coilscope(&[
        "simulate",
        "18wu-4741t-00",
        "--volts",
        "0.12",
        "--seconds",
        "3",
        "--snr-db",
        "70",
        "--laser",
        "--out",
        rec.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = d.path().join("lin.json");
    // The displacement channel gives the scale; --sd gives Vas.
    let o = coilscope(&["linear", rec.to_str().unwrap(), "--sd", "0.0154", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout);
    for want in ["Re", "Qts", "Bl", "Kms", "Vas", "displacement channel"] {
        assert!(text.contains(want), "{text}");
    }
    let r = typed_result(&out);
    assert_eq!(r["format"], "coilscope.result/1");
    let truth = coilscope_core::embedded_driver("18wu-4741t-00").unwrap();
    let bl = r["parameters"]["Bl"].as_f64().unwrap();
    assert!((bl / truth.bl.c[0] - 1.0).abs() < 0.01, "Bl {bl}");
    let fs = r["small_signal"]["fs"].as_f64().unwrap();
    assert!((fs / 23.64 - 1.0).abs() < 0.01, "fs {fs}");
    assert!(r["fit"]["residual_rel"].as_f64().unwrap() < 0.01);
    let xr = r["fit"]["x_range"].as_array().unwrap();
    assert!(xr[0].as_f64().unwrap() < 0.0 && xr[1].as_f64().unwrap() > 0.0);
    assert!(r["uncertainty"]["Re"].as_f64().unwrap() > 0.0);
    // The .zma is what REW and VituixCAD read: frequency, magnitude, phase.
    let zma = std::fs::read_to_string(d.path().join("lin.zma")).unwrap();
    let line: Vec<f64> = zma.lines().nth(10).unwrap().split_whitespace().map(|v| v.parse().unwrap()).collect();
    assert_eq!(line.len(), 3);
    assert!(line[1] > 3.0 && line[1] < 100.0);
    assert!(std::fs::read_to_string(d.path().join("lin.csv")).unwrap().starts_with("frequency_hz,magnitude_ohm"));
    // Without a scale the command says which to give.
    let plain = d.path().join("plain.wav");
    assert!(coilscope(&[
        "simulate",
        "18wu-4741t-00",
        "--volts",
        "0.12",
        "--seconds",
        "2",
        "--out",
        plain.to_str().unwrap()
    ])
    .status
    .success());
    let e = one_error_line(&coilscope(&["linear", plain.to_str().unwrap(), "--out", out.to_str().unwrap()]));
    assert!(e.contains("no absolute scale: give --mms MASS"), "{e}");
}

#[test]
fn identify_writes_the_result_contract_and_a_summary() {
    // Simulate a large-signal record, identify it, read the result per formats.md.
    let d = tempfile::tempdir().unwrap();
    let rec = d.path().join("big.wav");
    let rec_s = rec.to_str().unwrap();
    let o = coilscope(&[
        "simulate",
        "sb17cac35-4",
        "--excitation",
        "pink",
        "--volts",
        "2.2",
        "--seconds",
        "4",
        "--snr-db",
        "70",
        "--laser",
        "--out",
        rec_s,
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = d.path().join("big.json");
    let o = coilscope(&[
        "identify",
        rec_s,
        "--mms",
        "0.015367",
        "--order",
        "4",
        "--sd",
        "0.0118",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout);
    for want in ["order 4", "Bl", "Kms", "Le", "XC", "cross-check", "voice coil"] {
        assert!(text.contains(want), "{want}: {text}");
    }
    let r = typed_result(&out);
    assert_eq!(r["format"], "coilscope.result/1");
    assert!(r["fit"]["residual_rel"].as_f64().unwrap() < 0.01);
    let xr = r["fit"]["x_range"].as_array().unwrap();
    assert!(xr[0].as_f64().unwrap() < -1e-3 && xr[1].as_f64().unwrap() > 1e-3);
    assert_eq!(r["parameters"]["x_range"], r["fit"]["x_range"]);
    assert_eq!(r["parameters"]["Bl"].as_array().unwrap().len(), 5);
    assert!(r["small_signal"]["Vas"].as_f64().unwrap() > 0.0);
    assert!(r["limits"]["XC"].as_f64().unwrap() > 0.0);
    assert!(r["uncertainty"]["Re"].as_f64().unwrap() > 0.0);
    assert_eq!(r["uncertainty"]["Bl_band"]["sd"].as_array().unwrap().len(), 41);
    // The parameter set it wrote is a valid parameter file for the simulator.
    let params = d.path().join("identified.json");
    std::fs::write(&params, serde_json::to_string(&r["parameters"]).unwrap()).unwrap();
    let o = coilscope(&["check", params.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

#[test]
fn identify_bad_inputs_get_one_clear_line() {
    let d = tempfile::tempdir().unwrap();
    let rec = d.path().join("r.wav");
    let rec_s = rec.to_str().unwrap();
    let o = coilscope(&["simulate", "sb17cac35-4", "--volts", "1", "--seconds", "2.5", "--out", rec_s]);
    assert!(o.status.success());
    let out = d.path().join("o.json");
    let out = out.to_str().unwrap();
    let e = one_error_line(&coilscope(&["identify", rec_s, "--out", out]));
    assert!(e.contains("r.wav") && e.contains("--mms"), "{e}");
    let e = one_error_line(&coilscope(&["identify", rec_s, "--mms", "0.015", "--order", "9", "--out", out]));
    assert!(e.contains("--order 9") && e.contains("2 to 8"), "{e}");
    let e = one_error_line(&coilscope(&["identify", rec_s, "--mms", "15", "--out", out]));
    assert!(e.contains("15") && e.contains("kg"), "{e}");
    let e = one_error_line(&coilscope(&["identify", "missing.wav", "--mms", "0.015", "--out", out]));
    assert!(e.contains("missing.wav"), "{e}");
}

/// Outputs are checked before the work: a result path whose directory is missing, or a new
/// file among the devices, is refused before the input is even read; a result sent to a
/// device (`/dev/null`) is written there with nothing created beside it.
#[test]
fn outputs_are_checked_before_the_work_and_nothing_lands_beside_a_device() {
    let d = tempfile::tempdir().unwrap();
    let missing = d.path().join("missing.wav");
    let missing = missing.to_str().unwrap();
    for cmd in [
        vec!["linear", missing, "--mms", "0.01", "--out", "/nonexistent-dir-xyz/lin.json"],
        vec!["identify", missing, "--mms", "0.01", "--out", "/nonexistent-dir-xyz/id.json"],
        vec!["simulate", "sb17cac35-4", "--volts", "1", "--input", missing, "--out", "/nonexistent-dir-xyz/s.wav"],
        vec!["calibrate", missing, "--resistor", "4", "--out", "/nonexistent-dir-xyz/chain.json"],
    ] {
        let e = one_error_line(&coilscope(&cmd));
        assert!(e.contains("/nonexistent-dir-xyz") && e.contains("does not exist"), "{cmd:?}: {e}");
    }
    let e = one_error_line(&coilscope(&["linear", missing, "--mms", "0.01", "--out", "/dev/coilscope-lin.json"]));
    assert!(e.contains("the devices' directory"), "{e}");

    let rec = d.path().join("small.wav");
    let o = coilscope(&["simulate", "sb17cac35-4", "--volts", "0.1", "--seconds", "2", "--out", rec.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = coilscope(&["linear", rec.to_str().unwrap(), "--mms", "0.0107", "--out", "/dev/null"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(matches!(o.status.code(), Some(0 | 3)), "{err}");
    assert!(err.contains("/dev/null is a device: no .zma or .csv is written beside it"), "{err}");
    let o = coilscope(&["simulate", "sb17cac35-4", "--volts", "0.1", "--seconds", "0.2", "--out", "/dev/null"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stdout).contains("a device: no description beside it"));
}

/// A quasi-static run whose points fall short of the reach asked for says so, and its curves
/// end at the last points (`fit.x_range`): the DC a point needs grows as the suspension
/// stiffens, so a drawn woofer's points end near three quarters of the way.
#[test]
fn a_quasistatic_run_short_of_its_reach_says_so_and_its_curves_end_at_the_last_points() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("qs.json");
    let o = coilscope(&["quasistatic", "population:woofer:5", "--reach", "0.9", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout);
    let note =
        text.lines().find(|l| l.contains("note: the points reached")).unwrap_or_else(|| panic!("no note: {text}"));
    assert!(note.contains("(--reach 0.9)") && note.contains("the curves end at the last points"), "{note}");
    let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    let span = r["fit"]["x_range"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap().abs()).fold(0.0, f64::max);
    let range =
        coilscope_core::population::parse_name("population:woofer:5").unwrap().unwrap().natural().x_range.unwrap()[1];
    assert!(span > 0.0 && span < 0.95 * 0.9 * range, "x_range to {span} m of an asked {} m", 0.9 * range);
}

/// `quasistatic` corrects a card's chain only on a card: on the virtual driver a `--chain`
/// would be ignored, so it is refused by name.
#[test]
fn quasistatic_refuses_a_chain_it_would_ignore() {
    let d = tempfile::tempdir().unwrap();
    let chain = d.path().join("chain.json");
    std::fs::write(&chain, r#"{"delay_i": 2e-5}"#).unwrap();
    let out = d.path().join("qs.json");
    let e = one_error_line(&coilscope(&[
        "quasistatic",
        "sb17cac35-4",
        "--chain",
        chain.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]));
    assert!(e.contains("--chain") && e.contains("with --card only"), "{e}");
}

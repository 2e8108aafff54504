//! `coilscope qc`: limits learned from golden units, a unit's verdict and exit code, a lot's
//! capability.
//!
//! The quick test takes the units' true sets (a virtual line around SB17,
//! `coilscope_core::production`). The release sweep (`--ignored`, run by `.ci/run`) takes a
//! short virtual record of each unit (3 s of pink noise to 70 % of the range, 70 dB sensor
//! noise), identifies it with `coilscope identify` as a station would, learns the limits from
//! the golden units' results and tests the others: each faulty unit must fail naming its
//! fault, and no good one fail by more than 3 sd past a limit.

use coilscope_core::production::{unit, Fault, Spread};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn coilscope(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_coilscope")).args(args).output().unwrap()
}

fn text(o: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

fn write_set(dir: &Path, name: &str, p: &coilscope_core::Parameters) -> String {
    let f = dir.join(format!("{name}.json"));
    std::fs::write(&f, p.to_json_value().to_string()).unwrap();
    f.to_str().unwrap().to_string()
}

#[test]
fn qc_learns_limits_passes_a_good_unit_and_fails_a_rubbing_one_with_exit_4() {
    let d = tempfile::tempdir().unwrap();
    let g = coilscope_core::embedded_driver("sb17cac35-4").unwrap();
    let s = Spread::default();
    let golden: Vec<String> =
        (0..30).map(|k| write_set(d.path(), &format!("golden{k}"), &unit(&g, &s, None, 500 + k))).collect();
    let limits = d.path().join("limits.json");
    let mut args = vec!["qc", "learn"];
    args.extend(golden.iter().map(String::as_str));
    args.extend(["--k", "4", "--out", limits.to_str().unwrap()]);
    let o = coilscope(&args);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("Xsym_Bl"), "{}", text(&o));

    let good = write_set(d.path(), "good", &unit(&g, &s, None, 900));
    let o = coilscope(&["qc", "test", &good, "--limits", limits.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(0), "{}", text(&o));
    assert!(text(&o).contains("PASS"), "{}", text(&o));

    let rubbing = write_set(d.path(), "rubbing", &unit(&g, &s, Some(Fault::RubbingCoil(2.0)), 901));
    let verdict = d.path().join("verdict.json");
    let o =
        coilscope(&["qc", "test", &rubbing, "--limits", limits.to_str().unwrap(), "--out", verdict.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(4), "{}", text(&o));
    assert!(text(&o).contains("FAIL: ") && text(&o).contains("rubbing coil"), "{}", text(&o));
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&verdict).unwrap()).unwrap();
    assert_eq!(v["pass"], false);
    assert!(v["checks"].as_array().unwrap().iter().any(|c| c["key"] == "Rms" && c["pass"] == false));

    let offset = write_set(d.path(), "offset", &unit(&g, &s, Some(Fault::CoilOffset(-0.5e-3)), 902));
    let o = coilscope(&["qc", "test", &offset, "--limits", limits.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(4), "{}", text(&o));
    assert!(text(&o).contains("advice: Bl(x) is symmetric about") && text(&o).contains("move it"), "{}", text(&o));

    let stats = d.path().join("stats.json");
    let mut args = vec!["qc", "stats"];
    args.extend(golden.iter().map(String::as_str));
    args.extend(["--limits", limits.to_str().unwrap(), "--out", stats.to_str().unwrap()]);
    let o = coilscope(&args);
    assert!(o.status.success(), "{}", text(&o));
    let st: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&stats).unwrap()).unwrap();
    // The golden units against their own 4-sd limits: Cpk 4/3 by construction.
    for f in st["figures"].as_array().unwrap() {
        assert!((f["Cpk"].as_f64().unwrap() - 4.0 / 3.0).abs() < 1e-9 || f["key"] == "Xmax", "{f}");
    }

    // Bad inputs: one clear line each.
    let o = coilscope(&["qc", "test", &good, "--limits", &good]);
    assert_eq!(o.status.code(), Some(2));
    assert!(text(&o).contains("good.json") && text(&o).contains("coilscope.qc-limits/1"), "{}", text(&o));
    let o = coilscope(&["qc", "learn", &golden[0], &golden[1], "--out", limits.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2));
    assert!(text(&o).contains("at least 5"), "{}", text(&o));
}

/// A short record of the unit `p`, as a station takes it: 3 s of pink noise at the level that
/// takes the cone to 70 % of its range, 70 dB sensor noise.
fn record(dir: &Path, name: &str, p: &coilscope_core::Parameters, seed: u64) -> PathBuf {
    use coilscope_core::excitation::{add_sensor_noise, generate, Excitation, SignalSpec};
    let fs = 48_000.0;
    let [lo, hi] = p.x_range.unwrap();
    let unit = generate(
        &Excitation::Pink { f_lo: 10.0, f_hi: 8000.0, crest: Some(3.0) },
        &SignalSpec { fs, seconds: 3.0, rms: 1.0, fade: 0.05, seed },
    )
    .unwrap();
    let opts = coilscope_core::SimOptions::default();
    let (_, tr) = coilscope_core::simulate::gain_for_peak(p, fs, &unit, 0.7 * hi.min(-lo), &opts).unwrap();
    let (mut u, mut i) = (tr.u, tr.i);
    add_sensor_noise(&mut u, 70.0, seed, "sensor-noise/voltage");
    add_sensor_noise(&mut i, 70.0, seed, "sensor-noise/current");
    let path = dir.join(format!("{name}.wav"));
    coilscope_io::write_recording(&path, &coilscope_io::Recording { fs: 48_000, u, i, x: None }).unwrap();
    path
}

#[test]
#[ignore = "release sweep: .ci/run runs it"]
fn a_virtual_line_tested_from_short_records_fails_each_faulty_unit_naming_its_fault() {
    let d = tempfile::tempdir().unwrap();
    let g = coilscope_core::embedded_driver("sb17cac35-4").unwrap();
    let s = Spread::default();
    let base = coilscope_testkit::population::seeds("qc_virtual_line", 1)[0] << 20;
    let identify = |name: &str, p: &coilscope_core::Parameters, seed: u64| -> String {
        let rec = record(d.path(), name, p, seed);
        let out = d.path().join(format!("{name}.result.json"));
        let mms = format!("{}", p.mms);
        let o = coilscope(&[
            "identify",
            rec.to_str().unwrap(),
            "--mms",
            &mms,
            "--effects",
            "none",
            "--chain",
            "none",
            "--out",
            out.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{name}: {}", text(&o));
        out.to_str().unwrap().to_string()
    };
    // The station weighs each cone (Mms given): the scale of every mechanical figure.
    let golden: Vec<String> =
        (0..10).map(|k| identify(&format!("golden{k}"), &unit(&g, &s, None, base + k), base + k)).collect();
    let limits = d.path().join("limits.json");
    let mut args = vec!["qc", "learn"];
    args.extend(golden.iter().map(String::as_str));
    args.extend(["--out", limits.to_str().unwrap()]);
    let o = coilscope(&args);
    assert!(o.status.success(), "{}", text(&o));
    println!("{}", text(&o));
    let mut bad = Vec::new();
    let cases = [
        (None, "good"),
        (Some(Fault::CoilOffset(0.5e-3)), "Xsym_Bl"),
        (Some(Fault::StiffSpider(1.3)), "Kms(0)"),
        (Some(Fault::RubbingCoil(2.0)), "Rms"),
        (None, "good"),
    ];
    for (n, (fault, figure)) in cases.into_iter().enumerate() {
        let seed = base + 100 + n as u64;
        let name = format!("unit{n}");
        let result = identify(&name, &unit(&g, &s, fault, seed), seed);
        let verdict = d.path().join(format!("{name}.verdict.json"));
        let o = coilscope(&[
            "qc",
            "test",
            &result,
            "--limits",
            limits.to_str().unwrap(),
            "--out",
            verdict.to_str().unwrap(),
        ]);
        let t = text(&o);
        println!("{fault:?}:\n{t}");
        let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&verdict).unwrap()).unwrap();
        let ok = match fault {
            // Limits from 10 units at 3 sd fail a good unit now and then (the sd of 10 is
            // rough): a good unit must not fail by more than 3 sd past a limit, 6 from the mean.
            None => v["checks"]
                .as_array()
                .unwrap()
                .iter()
                .all(|c| c["pass"] == true || c["by_sd"].as_f64().is_some_and(|b| b.abs() < 3.0)),
            Some(_) => o.status.code() == Some(4) && t.lines().any(|l| l.starts_with("FAIL") && l.contains(figure)),
        };
        if !ok {
            bad.push(format!("{fault:?} (exit {:?}): {t}", o.status.code()));
        }
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

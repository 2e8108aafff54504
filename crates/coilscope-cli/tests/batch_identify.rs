//! `coilscope identify A.wav B.wav ... --out DIR`, a production line's batch: each
//! recording identified by a worker on one core, `--jobs` at a time, each result in
//! `DIR/NAME.json` and the same as a single `identify` with the same options would write; a
//! bad recording fails alone (its report says why) and sets the exit code.
use std::process::{Command, Output};

fn coilscope(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_coilscope")).args(args).output().unwrap()
}

fn text(o: &Output) -> String {
    format!("{}\n{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

fn bl0(path: &std::path::Path) -> f64 {
    let j: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    j["parameters"]["Bl"][0].as_f64().unwrap()
}

#[test]
fn a_batch_identifies_each_recording_and_names_the_bad_one() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_str().unwrap().to_string();
    for seed in ["1", "2"] {
        let o = coilscope(&[
            "simulate",
            "ptt4.0w04-01a",
            "--excitation",
            "pink",
            "--volts",
            "2.5",
            "--seconds",
            "3",
            "--snr-db",
            "70",
            "--seed",
            seed,
            "--out",
            &p(&format!("rec{seed}.wav")),
        ]);
        assert!(o.status.success(), "{}", text(&o));
    }
    std::fs::write(p("broken.wav"), b"not a wav").unwrap();
    let fit = ["--mms", "0.012596", "--order", "4", "--effects", "none"];
    let o = coilscope(
        &[
            &["identify", &p("rec1.wav"), &p("broken.wav"), &p("rec2.wav"), "--jobs", "2", "--out", &p("batch")][..],
            &fit[..],
        ]
        .concat(),
    );
    let t = text(&o);
    // The broken recording fails, by name; the others are identified.
    assert_eq!(o.status.code(), Some(2), "{t}");
    assert!(t.contains("batch: 3 recordings") && t.contains("broken.wav") && t.contains("failed"), "{t}");
    let truth = coilscope_core::embedded_driver("ptt4.0w04-01a").unwrap().bl.c[0];
    for n in ["rec1", "rec2"] {
        let r = d.path().join("batch").join(format!("{n}.json"));
        assert!((bl0(&r) / truth - 1.0).abs() < 1e-3, "{n}: Bl {} vs {truth}", bl0(&r));
    }
    assert!(!d.path().join("batch/broken.json").exists());
    // The same as one identify with the same options (the worker is that command on one core).
    let o = coilscope(&[&["identify", &p("rec1.wav"), "--out", &p("single.json")][..], &fit[..]].concat());
    assert!(o.status.success(), "{}", text(&o));
    let (a, b) = (bl0(&d.path().join("batch/rec1.json")), bl0(&d.path().join("single.json")));
    assert!((a / b - 1.0).abs() < 1e-9, "batch {a} vs single {b}");
}

#[test]
fn batch_arguments_are_checked_before_any_work() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_str().unwrap().to_string();
    let other = d.path().join("other");
    std::fs::create_dir_all(&other).unwrap();
    let same = other.join("a.wav");
    for (args, want) in [
        (
            vec!["identify", &p("a.wav"), same.to_str().unwrap(), "--mms", "0.01", "--out", &p("o")],
            "would both write a.json",
        ),
        (vec!["identify", &p("a.wav"), &p("b.wav"), "--mms", "0.01", "--out", &p("o.json")], "--out is a directory"),
        (
            vec!["identify", &p("a.wav"), "--jobs", "2", "--mms", "0.01", "--out", &p("o.json")],
            "--jobs applies to several recordings",
        ),
        (vec!["identify", &p("a.wav"), &p("b.wav"), "--jobs", "0", "--mms", "0.01", "--out", &p("o")], "--jobs 0"),
    ] {
        let o = coilscope(&args);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {}", text(&o));
        assert!(text(&o).contains(want), "{args:?}: {}", text(&o));
    }
}

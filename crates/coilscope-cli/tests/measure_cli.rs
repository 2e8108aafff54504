//! `coilscope measure` and `coilscope runs`: the result and database, a kill during
//! a long-term run, bad input.
use std::process::{Command, Output};

fn coilscope(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_coilscope")).args(args).output().unwrap()
}

#[test]
fn virtual_measurement_writes_result_and_database() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("sb17");
    let o = coilscope(&["measure", "--virtual", "sb17cac35-4", "--target-x", "4.5mm", "--out", out.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{text}\n{}", String::from_utf8_lossy(&o.stderr));
    assert!(text.contains("converged"), "{text}");
    // The live lines before the small-signal fit show "-", never "Re NaN ohm  err NaN".
    let live = String::from_utf8_lossy(&o.stderr);
    assert!(live.contains("small-signal") && live.contains("Re   -    ohm"), "{live}");
    assert!(!text.contains("NaN") && !live.contains("NaN"), "{text}\n{live}");
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("result.json")).unwrap()).unwrap();
    assert_eq!(j["format"], "coilscope.result/1");
    // The typed reader knows every key and writes the file back unchanged.
    let r = coilscope_core::result::ResultFile::from_json_value(j.clone(), "result.json").unwrap();
    assert!(r.other.is_empty(), "keys the typed result does not know: {:?}", r.other.keys().collect::<Vec<_>>());
    assert_eq!(r.to_json_value(), j);
    let peak = j["measurement"]["x_peak_max"].as_f64().unwrap();
    assert!(peak > 0.003 && peak < 0.0048, "{peak}");
    let runs = coilscope(&["runs", out.to_str().unwrap()]);
    let listing = String::from_utf8_lossy(&runs.stdout);
    assert!(runs.status.success() && listing.contains("converged"), "{listing}");
}

#[test]
fn a_killed_long_term_run_keeps_its_data() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("long");
    let db = out.join("run.sqlite");
    let mut child = Command::new(env!("CARGO_BIN_EXE_coilscope"))
        .args([
            "measure",
            "--virtual",
            "ptt4.0w04-01a",
            "--target-x",
            "6mm",
            "--duration",
            "3600",
            "--out",
            out.to_str().unwrap(),
        ])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    // Wait until a few seconds of states are committed, then kill -9.
    let t0 = std::time::Instant::now();
    loop {
        std::thread::sleep(std::time::Duration::from_millis(200));
        if let Ok(r) = coilscope_db::list_runs(&coilscope_db::Target::Sqlite(db.clone())) {
            if r.first().is_some_and(|r| r.states >= 40) {
                break;
            }
        }
        assert!(t0.elapsed().as_secs() < 120, "no states were committed");
    }
    child.kill().unwrap();
    child.wait().unwrap();
    let runs = coilscope_db::list_runs(&coilscope_db::Target::Sqlite(db.clone())).unwrap();
    let r = &runs[0];
    assert!(r.states >= 40 && r.last.is_some(), "{r:?}");
    // The committed rows are whole: states arrive in whole seconds (10 blocks each).
    assert_eq!(r.states % 10, 0, "{r:?}");
    let o = coilscope(&["runs", db.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // A run whose process was killed is listed as killed at once (its process is gone).
    assert_eq!(r.status, "killed", "{r:?}");
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("killed"), "{text}");
}

#[test]
fn ctrl_c_writes_the_result_marked_interrupted_and_exits_130() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("int");
    let db = out.join("run.sqlite");
    let child = Command::new(env!("CARGO_BIN_EXE_coilscope"))
        .args([
            "measure",
            "--virtual",
            "ptt4.0w04-01a",
            "--duration",
            "3600",
            "--no-report",
            "--out",
            out.to_str().unwrap(),
        ])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let t0 = std::time::Instant::now();
    loop {
        std::thread::sleep(std::time::Duration::from_millis(200));
        if coilscope_db::list_runs(&coilscope_db::Target::Sqlite(db.clone()))
            .is_ok_and(|r| r.first().is_some_and(|r| r.estimates >= 2))
        {
            break;
        }
        assert!(t0.elapsed().as_secs() < 120, "no estimates were committed");
    }
    let k = Command::new("kill").args(["-INT", &child.id().to_string()]).status().unwrap();
    assert!(k.success());
    let o = child.wait_with_output().unwrap();
    assert_eq!(o.status.code(), Some(130), "{}", String::from_utf8_lossy(&o.stderr));
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("result.json")).unwrap()).unwrap();
    assert_eq!(j["measurement"]["stop_reason"], "interrupted");
    assert_eq!(j["fit"]["converged"], false);
    let listing = String::from_utf8_lossy(&coilscope(&["runs", out.to_str().unwrap()]).stdout).into_owned();
    assert!(listing.contains("interrupted"), "{listing}");
}

#[test]
fn bad_devices_files_and_limits_get_one_line_errors() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("x");
    let o = out.to_str().unwrap();
    for (args, want) in [
        (vec!["measure", "--out", o], "--virtual DRIVER"),
        (vec!["measure", "--virtual", "no-such-driver", "--out", o], "no-such-driver"),
        (vec!["measure", "--virtual", "sb17cac35-4", "--target-x=-2mm", "--out", o], "--target-x"),
        (vec!["measure", "--virtual", "sb17cac35-4", "--max-dt", "0", "--out", o], "--max-dt"),
        // A bare number is metres; 4 (meant as mm) is refused with the unit named.
        (vec!["measure", "--virtual", "sb17cac35-4", "--target-x", "4", "--out", o], "did you mean 4mm"),
        (vec!["measure", "--virtual", "sb17cac35-4", "--target-x", "4furlongs", "--out", o], "unknown length unit"),
        (vec!["measure", "--virtual", "sb17cac35-4", "--music", "/nonexistent/song.wav", "--out", o], "song.wav"),
        (vec!["measure", "--replay", "/nonexistent/rec.wav", "--out", o], "rec.wav: no such file"),
        (vec!["runs", "/nonexistent/run.sqlite"], "no such run database"),
        (vec!["measure", "--card", "--out", o], "--card needs --mms"),
        (
            vec!["measure", "--card", "--mms", "0.02", "--u-channel", "1", "--i-channel", "1", "--out", o],
            if cfg!(feature = "soundcard") { "--u-channel" } else { "--features soundcard" },
        ),
        (vec!["devices"], if cfg!(feature = "soundcard") { "" } else { "--features soundcard" }),
    ] {
        if want.is_empty() {
            continue;
        }
        let r = coilscope(&args);
        let err = String::from_utf8_lossy(&r.stderr);
        assert_eq!(r.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains(want), "{args:?}: {err}");
    }
    // A file that is not a database.
    let bogus = dir.path().join("bogus.sqlite");
    std::fs::write(&bogus, b"this is not sqlite at all, just text that is long enough to be a header").unwrap();
    let r = coilscope(&["runs", bogus.to_str().unwrap()]);
    assert_eq!(r.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&r.stderr).contains("bogus.sqlite"));
}

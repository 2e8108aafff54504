//! A report an engineer trusts: the tables carry the sds, engineering units and
//! the figures engineers look for (Vas, Cms, Res, Qtp, Xmax = min(XBl, XC, XL)); a
//! small-signal result gets no nonlinear sections; a run database of another measurement is
//! refused by name.

use std::process::{Command, Output};

fn coilscope(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_coilscope")).args(args).output().unwrap()
}

fn text(o: &Output) -> String {
    format!("{}\n{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

#[test]
fn report_tables_sds_and_what_the_result_supports() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_str().unwrap().to_string();
    // A large-signal result with bands and sds (identify on a recording).
    assert!(coilscope(&[
        "simulate",
        "ptt4.0w04-01a",
        "--excitation",
        "pink",
        "--volts",
        "2.5",
        "--seconds",
        "4",
        "--snr-db",
        "70",
        "--out",
        &p("rec.wav")
    ])
    .status
    .success());
    let o = coilscope(&[
        "identify",
        &p("rec.wav"),
        "--mms",
        "0.012596",
        "--order",
        "4",
        "--effects",
        "none",
        "--sd",
        "0.00567",
        "--out",
        &p("large.json"),
    ]);
    assert!(o.status.code() == Some(0) || o.status.code() == Some(3), "{}", text(&o));
    let o = coilscope(&["report", &p("large.json"), "--out", &p("large.html")]);
    assert!(o.status.success(), "{}", text(&o));
    let html = std::fs::read_to_string(p("large.html")).unwrap();
    for want in [
        "Xmax = min(XBl, XC, XL)",
        "<td>Vas</td>",
        "<td>Cms</td>",
        "Res (Bl²/Rms at fs)",
        "Rms at fs (with creep's loss)",
        "Qtp",
        "Dominant nonlinearity",
        "± ",
        "plot-bl-symmetry",
        "plot-kms-symmetry",
        "plot-ak",
    ] {
        assert!(html.contains(want), "the large-signal report lacks {want:?}");
    }
    // Engineering units: Mms in g, Le in mH.
    assert!(html.contains("<td>g</td>") && html.contains("<td>mH</td>"), "units");
    // Every small-signal figure with its sd (propagated from Kms, Rms, Bl, Re and Sd's).
    for row in [
        "fs",
        "Qms",
        "Qes",
        "Qts",
        "Qtp (with the eddy-current losses at fs)",
        "Cms",
        "Vas",
        "Rms at fs (with creep's loss)",
        "Res (Bl²/Rms at fs)",
    ] {
        let start = html.find(&format!("<td>{row}</td>")).unwrap_or_else(|| panic!("no row {row}"));
        let cells = &html[start..start + html[start..].find("</tr>").unwrap()];
        assert!(cells.contains("<td>± "), "the row {row} has no sd: {cells}");
    }
    // A small-signal result: no curves, limits or distortion.
    assert!(coilscope(&[
        "simulate",
        "ptt4.0w04-01a",
        "--excitation",
        "pink",
        "--volts",
        "0.3",
        "--seconds",
        "4",
        "--snr-db",
        "70",
        "--out",
        &p("small.wav")
    ])
    .status
    .success());
    let o = coilscope(&["linear", &p("small.wav"), "--mms", "0.012596", "--out", &p("lin.json")]);
    assert!(o.status.success(), "{}", text(&o));
    let o = coilscope(&["report", &p("lin.json"), "--out", &p("lin.html")]);
    assert!(o.status.success(), "{}", text(&o));
    let html = std::fs::read_to_string(p("lin.html")).unwrap();
    assert!(html.contains("This is a small-signal result"));
    for not in ["Dominant nonlinearity", "Harmonic distortion", "plot-bl\""] {
        assert!(!html.contains(not), "a small-signal report shows {not:?}");
    }
    assert!(!d.path().join("lin_files/hd.png").exists());
}

#[test]
fn a_run_database_of_another_measurement_is_refused() {
    let d = tempfile::tempdir().unwrap();
    let a = d.path().join("a");
    let b = d.path().join("b");
    for (dir, driver) in [(&a, "ptt4.0w04-01a"), (&b, "sb17cac35-4")] {
        let o = coilscope(&[
            "measure",
            "--virtual",
            driver,
            "--max-seconds",
            "6",
            "--no-report",
            "--out",
            dir.to_str().unwrap(),
        ]);
        assert!(dir.join("result.json").exists(), "{}", text(&o));
    }
    // Sd is the driver's geometry, not measured: a virtual driver's own is the result's, so
    // the report can give Vas.
    let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(b.join("result.json")).unwrap()).unwrap();
    assert_eq!(r["parameters"]["Sd"].as_f64(), coilscope_core::embedded_driver("sb17cac35-4").unwrap().sd);
    let out = d.path().join("r.html");
    let o = coilscope(&[
        "report",
        a.join("result.json").to_str().unwrap(),
        "--db",
        b.join("run.sqlite").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("run.sqlite") && e.contains("give the run database of this measurement"), "{e}");
    // Its own database is taken.
    let o = coilscope(&[
        "report",
        a.join("result.json").to_str().unwrap(),
        "--db",
        a.join("run.sqlite").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    // A parameter set (or an identify result) is no measurement: no run's states go with it.
    let o = coilscope(&[
        "report",
        "sb17cac35-4",
        "--db",
        a.join("run.sqlite").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("is not the result of a measurement") && e.contains("leave --db out"), "{e}");
}

//! `coilscope identify --method volterra` end to end on records of
//! `simulate --excitation readable` (90 dB sensor noise): the small-signal start from
//! `coilscope linear`, the kernels' fit, its bands, and the truncation warning at a level the
//! third-order series does not describe; wrong inputs get one clear line.

use std::process::{Command, Output};

fn coilscope(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_coilscope")).args(args).output().unwrap()
}

#[test]
fn volterra_identify_on_a_recorded_multitone() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_str().unwrap().to_string();
    let ok = |o: &Output| {
        assert!(o.status.success(), "{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
    };
    ok(&coilscope(&[
        "simulate",
        "sb17cac35-4",
        "--excitation",
        "noise",
        "--volts",
        "0.3",
        "--seconds",
        "8",
        "--snr-db",
        "90",
        "--out",
        &p("small.wav"),
    ]));
    ok(&coilscope(&["linear", &p("small.wav"), "--mms", "0.0154", "--out", &p("lin.json")]));
    let sim = |volts: &str, name: &str| {
        coilscope(&[
            "simulate",
            "sb17cac35-4",
            "--excitation",
            "readable",
            "--band",
            "20",
            "800",
            "--tones",
            "20",
            "--volts",
            volts,
            "--seconds",
            "16",
            "--snr-db",
            "90",
            "--seed",
            "4",
            "--out",
            &p(name),
        ])
    };
    ok(&sim("0.06", "quiet.wav"));
    ok(&sim("0.7", "loud.wav"));
    // Small level: trusted, the bands present, Kms(x) at the reach within 0.5 % (of the
    // value at rest) of the truth.
    let o = coilscope(&[
        "identify",
        &p("quiet.wav"),
        "--method",
        "volterra",
        "--start",
        &p("lin.json"),
        "--out",
        &p("v.json"),
    ]);
    ok(&o);
    let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(p("v.json")).unwrap()).unwrap();
    assert_eq!(r["fit"]["trustworthy"], true);
    assert_eq!(r["fit"]["order"], 2);
    assert!(r["fit"]["method"].as_str().unwrap().starts_with("Volterra"));
    for k in ["Bl_band", "Kms_band", "Le_band"] {
        assert_eq!(r["uncertainty"][k]["sd"].as_array().unwrap().len(), 21, "{k}");
    }
    let truth = coilscope_core::embedded_driver("sb17cac35-4").unwrap();
    let kms: Vec<f64> = r["parameters"]["Kms"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    let q = coilscope_core::Poly { c: kms };
    let reach: Vec<f64> = r["fit"]["x_range"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    assert!(reach[1] > 5e-5 && reach[1] < 5e-4, "{reach:?}");
    for x in reach {
        let rel = (q.eval(x) / q.c[0] - truth.kms.eval(x) / truth.kms.c[0]).abs();
        assert!(rel < 5e-3, "Kms at {x} m: {rel}");
    }
    // At 25 % of the range: written, not trusted, exit 3, the cause named.
    let o = coilscope(&[
        "identify",
        &p("loud.wav"),
        "--method",
        "volterra",
        "--start",
        &p("lin.json"),
        "--out",
        &p("v2.json"),
    ]);
    assert_eq!(o.status.code(), Some(3), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stderr).contains("volterra-truncation"));
    let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(p("v2.json")).unwrap()).unwrap();
    assert_eq!(r["fit"]["trustworthy"], false);
    // Noise is not a multitone; the start is required; --order is second.
    let o = coilscope(&[
        "identify",
        &p("small.wav"),
        "--method",
        "volterra",
        "--start",
        &p("lin.json"),
        "--out",
        &p("v3.json"),
    ]);
    assert_eq!(o.status.code(), Some(2));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("not a periodic multitone") && e.contains("small.wav"), "{e}");
    let o = coilscope(&["identify", &p("quiet.wav"), "--method", "volterra", "--out", &p("v3.json")]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("--start FILE"));
    let o = coilscope(&[
        "identify",
        &p("quiet.wav"),
        "--method",
        "volterra",
        "--start",
        &p("lin.json"),
        "--order",
        "4",
        "--out",
        &p("v3.json"),
    ]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("second order"));
}

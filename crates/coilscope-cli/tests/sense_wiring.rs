//! Sense-resistor wiring: the voltage channel across the driver alone (`terminals`)
//! or across driver and shunt in series (`driver+shunt`, `--sense-ohm`). A `driver+shunt`
//! record read as `terminals` puts the shunt into Re (3.6 % for 0.22 ohm on SB17); read with
//! its wiring, it gives the driver, through an ideal, an estimated or a calibrated chain.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn coilscope(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_coilscope")).args(args).output().unwrap()
}

fn text(o: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

const RS: &str = "0.22";

/// A 4 s small-signal pink-noise record of SB17 (80 dB sensor noise) with `extra` options of
/// `simulate` (wiring, chain).
fn record(dir: &Path, name: &str, extra: &[&str]) -> PathBuf {
    let out = dir.join(name);
    let mut args = vec![
        "simulate",
        "sb17cac35-4",
        "--excitation",
        "pink",
        "--band",
        "5",
        "20000",
        "--volts",
        "0.3",
        "--seconds",
        "4",
        "--snr-db",
        "80",
        "--seed",
        "31",
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    let o = coilscope(&args);
    assert!(o.status.success(), "{}", text(&o));
    out
}

fn linear(rec: &Path, out: &Path, extra: &[&str]) -> serde_json::Value {
    let mms = coilscope_core::embedded_driver("sb17cac35-4").unwrap().mms.to_string();
    let mut args = vec!["linear", rec.to_str().unwrap(), "--mms", &mms, "--out", out.to_str().unwrap()];
    args.extend_from_slice(extra);
    let o = coilscope(&args);
    assert!(o.status.code().is_some_and(|c| c == 0 || c == 3), "{args:?}: {}", text(&o));
    serde_json::from_str(&std::fs::read_to_string(out).unwrap()).unwrap()
}

/// Re within 0.5 %, Bl within 2 %, Kms within 3 %, Le within 5 % (the accuracy bounds).
fn check(r: &serde_json::Value, what: &str) {
    let p = coilscope_core::embedded_driver("sb17cac35-4").unwrap();
    for (k, t, tol) in
        [("Re", p.re, 0.005), ("Bl", p.bl.c[0], 0.02), ("Kms", p.kms.c[0], 0.03), ("Le", p.le.c[0], 0.05)]
    {
        let got = r["parameters"][k].as_f64().unwrap();
        assert!((got / t - 1.0).abs() < tol, "{what}: {k} {got} vs {t} (tolerance {tol})");
    }
}

#[test]
fn a_driver_plus_shunt_record_gives_the_driver_when_read_with_its_wiring() {
    let d = tempfile::tempdir().unwrap();
    let rec = record(d.path(), "series.wav", &["--sense-wiring", "driver+shunt", "--sense-ohm", RS]);
    let info: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.path().join("series.info.json")).unwrap()).unwrap();
    assert_eq!(info["chain"]["sense_wiring"], "driver+shunt");
    let with = linear(&rec, &d.path().join("with.json"), &["--sense-wiring", "driver+shunt", "--sense-ohm", RS]);
    check(&with, "driver+shunt, --chain none");
    assert_eq!(with["chain"]["sense_wiring"], "driver+shunt");
    assert_eq!(with["chain"]["sense_ohm"], 0.22);
    // Read as terminals, the shunt is in Re.
    let without = linear(&rec, &d.path().join("without.json"), &[]);
    let re = coilscope_core::embedded_driver("sb17cac35-4").unwrap().re;
    let re_without = without["parameters"]["Re"].as_f64().unwrap();
    assert!((re_without - re - 0.22).abs() < 0.005 * re, "Re read as terminals {re_without}, driver {re}");
}

#[test]
fn a_driver_plus_shunt_record_through_a_real_card_with_the_chain_estimated() {
    let d = tempfile::tempdir().unwrap();
    let card = d.path().join("card.json");
    std::fs::write(&card, r#"{"delay_i": 8.333e-6, "hp_u": 1.5, "hp_i": 3.5, "dc_u": 0.002, "dc_i": 0.0005}"#).unwrap();
    let rec = record(
        d.path(),
        "card.wav",
        &["--sense-wiring", "driver+shunt", "--sense-ohm", RS, "--chain", card.to_str().unwrap()],
    );
    let r = linear(
        &rec,
        &d.path().join("auto.json"),
        &["--chain", "auto", "--sense-wiring", "driver+shunt", "--sense-ohm", RS],
    );
    check(&r, "driver+shunt through a card, --chain auto");
    assert_eq!(r["chain"]["source"], "estimated");
    assert_eq!(r["chain"]["sense_wiring"], "driver+shunt");
    let delay = r["chain"]["delay_i"].as_f64().unwrap() * 48000.0;
    assert!((delay - 0.4).abs() < 0.02, "delay {delay} samples, true 0.4");
}

/// `calibrate` with the wiring keeps it in the chain file; `linear --chain FILE` then reads
/// records with it unless told otherwise.
#[test]
fn calibrate_keeps_the_wiring_for_the_records_that_follow() {
    use coilscope_core::chain::{Chain, SenseWiring};
    use coilscope_core::excitation::{add_sensor_noise, generate, Excitation, SignalSpec};
    use coilscope_io::{write_recording, Recording};
    let d = tempfile::tempdir().unwrap();
    let fs = 48000.0;
    let card = Chain {
        delay_i: 0.25 / fs,
        hp_u: 2.5,
        hp_i: 1.2,
        gain_i: Some(0.99),
        dc_u: 0.001,
        dc_i: -0.002,
        ..Default::default()
    };
    let wiring = SenseWiring::DriverPlusShunt { ohm: 0.22 };
    let noise = generate(
        &Excitation::Pink { f_lo: 0.3, f_hi: 20000.0, crest: None },
        &SignalSpec { fs, seconds: 40.0, rms: 1.0, fade: 0.0, seed: 41 },
    )
    .unwrap();
    let i: Vec<f64> = noise.iter().map(|v| v / 4.7).collect();
    let (mut ur, mut ir) = card.apply(&wiring.channel_voltage(&noise, &i), &i, fs);
    add_sensor_noise(&mut ur, 80.0, 41, "sensor-noise/voltage");
    add_sensor_noise(&mut ir, 80.0, 41, "sensor-noise/current");
    let r_rec = d.path().join("resistor.wav");
    write_recording(&r_rec, &Recording { fs: fs as u32, u: ur, i: ir, x: None }).unwrap();
    let chain_file = d.path().join("card.json");
    let o = coilscope(&[
        "calibrate",
        r_rec.to_str().unwrap(),
        "--resistor",
        "4.7",
        "--sense-wiring",
        "driver+shunt",
        "--sense-ohm",
        RS,
        "--out",
        chain_file.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let c: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&chain_file).unwrap()).unwrap();
    assert_eq!(c["sense_wiring"], "driver+shunt");
    assert!(
        (c["gain_i"].as_f64().unwrap() - 0.99).abs() < 1e-3
            && (c["delay_i"].as_f64().unwrap() * fs - 0.25).abs() < 0.01,
        "{c}"
    );

    std::fs::write(d.path().join("sim-card.json"), serde_json::to_string(&card).unwrap()).unwrap();
    let rec = record(
        d.path(),
        "driver.wav",
        &[
            "--sense-wiring",
            "driver+shunt",
            "--sense-ohm",
            RS,
            "--chain",
            d.path().join("sim-card.json").to_str().unwrap(),
        ],
    );
    let r = linear(&rec, &d.path().join("cal.json"), &["--chain", chain_file.to_str().unwrap()]);
    check(&r, "driver+shunt through a calibrated card");
    assert_eq!(r["chain"]["source"], "calibrated");
    assert_eq!(r["chain"]["sense_wiring"], "driver+shunt");
}

#[test]
fn wiring_refusals_name_the_option() {
    let d = tempfile::tempdir().unwrap();
    let rec = record(d.path(), "r.wav", &[]);
    let out = d.path().join("x.json");
    for (extra, want) in [
        (vec!["--sense-wiring", "driver+shunt"], "needs --sense-ohm"),
        (vec!["--sense-ohm", "0.1"], "--sense-ohm is for --sense-wiring driver+shunt"),
        (vec!["--sense-wiring", "across", "--sense-ohm", "0.1"], "`terminals`"),
        (vec!["--sense-wiring", "driver+shunt", "--sense-ohm=-0.1"], "--sense-ohm -0.1 is not valid"),
    ] {
        let mut args = vec!["linear", rec.to_str().unwrap(), "--mms", "0.0154", "--out", out.to_str().unwrap()];
        args.extend_from_slice(&extra);
        let o = coilscope(&args);
        assert_eq!(o.status.code(), Some(2), "{extra:?}: {}", text(&o));
        assert!(text(&o).contains(want), "{extra:?}: {}", text(&o));
    }
}

//! Exports: `coilscope export`. The speakersafetyd configuration of a measured
//! result (a long-term virtual run, so that it has thermal parameters) is read back with the
//! rules of speakersafetyd's own loader (`src/types.rs` `Globals::parse`, `Speaker::new`,
//! `src/main.rs` `get_speakers`, `src/helpers.rs` `parse_int`/`parse_float`/`parse_string`:
//! `configparser`'s case-sensitive INI, every key present and typed, the channel and
//! temperature asserts), and its thermal figures are the result's. The power-series table and
//! the impedance files read back too.

use configparser::ini::Ini;
use std::process::{Command, Output};

fn coilscope(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_coilscope")).args(args).output().unwrap()
}

fn parse_int(c: &Ini, s: &str, k: &str) -> i64 {
    c.getint(s, k)
        .unwrap_or_else(|e| panic!("{s}/{k}: Invalid value ({e})"))
        .unwrap_or_else(|| panic!("{s}/{k}: Missing key"))
}

fn parse_float(c: &Ini, s: &str, k: &str) -> f32 {
    let v = c
        .getfloat(s, k)
        .unwrap_or_else(|e| panic!("{s}/{k}: Invalid value ({e})"))
        .unwrap_or_else(|| panic!("{s}/{k}: Missing key")) as f32;
    assert!(v.is_finite(), "{s}/{k}");
    v
}

fn parse_string(c: &Ini, s: &str, k: &str) -> String {
    c.get(s, k).unwrap_or_else(|| panic!("{s}/{k}: Missing key"))
}

#[test]
fn speakersafetyd_export_of_a_measured_result_loads_as_the_daemon_loads_it() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_str().unwrap().to_string();
    let run = d.path().join("run");
    let o = coilscope(&[
        "measure",
        "--virtual",
        "sb17cac35-4",
        "--world",
        "published",
        "--duration",
        "200",
        "--volts",
        "4",
        "--no-report",
        "--out",
        run.to_str().unwrap(),
    ]);
    assert!(o.status.code() == Some(0) || o.status.code() == Some(3), "{}", String::from_utf8_lossy(&o.stderr));
    let result = run.join("result.json");
    let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&result).unwrap()).unwrap();
    let th = &r["parameters"]["thermal"];
    assert!(th["Rtv"].as_f64().is_some(), "the long-term run fitted no thermal model: {}", r["parameters"]);
    let conf = p("sb17.conf");
    let o = coilscope(&[
        "export",
        result.to_str().unwrap(),
        "--speakersafetyd",
        "--name",
        "Left Woofer",
        "--t-limit",
        "110",
        "--out",
        &conf,
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // speakersafetyd's loader.
    let mut cfg = Ini::new_cs();
    cfg.load(&conf).unwrap();
    let channels = parse_int(&cfg, "Globals", "channels");
    for k in ["visense_pcm", "period"] {
        parse_int(&cfg, "Globals", k);
    }
    let t_ambient = parse_float(&cfg, "Globals", "t_ambient");
    let t_window = parse_float(&cfg, "Globals", "t_window");
    parse_float(&cfg, "Globals", "t_hysteresis");
    for k in ["vsense", "isense", "amp_gain", "volume"] {
        parse_string(&cfg, "Controls", k);
    }
    let speakers: Vec<String> =
        cfg.sections().iter().filter_map(|a| a.strip_prefix("Speaker/")).map(|a| a.to_string()).collect();
    assert_eq!(speakers, vec!["Left Woofer".to_string()]);
    let s = "Speaker/Left Woofer";
    parse_int(&cfg, s, "group");
    let f: Vec<f32> = [
        "tau_coil",
        "tau_magnet",
        "tr_coil",
        "tr_magnet",
        "t_limit",
        "t_headroom",
        "z_nominal",
        "is_scale",
        "vs_scale",
    ]
    .iter()
    .map(|k| parse_float(&cfg, s, k))
    .collect();
    let (is_chan, vs_chan) = (parse_int(&cfg, s, "is_chan"), parse_int(&cfg, s, "vs_chan"));
    assert!(is_chan < channels && vs_chan < channels);
    assert!(f[4] - t_window > t_ambient);
    // The figures are the result's: the resistances, and the network's time constants.
    let (rtv, ctv, rtm, ctm) = (
        th["Rtv"].as_f64().unwrap(),
        th["Ctv"].as_f64().unwrap(),
        th["Rtm"].as_f64().unwrap(),
        th["Ctm"].as_f64().unwrap(),
    );
    assert!((f[2] as f64 / rtv - 1.0).abs() < 1e-3 && (f[3] as f64 / rtm - 1.0).abs() < 1e-3, "{f:?}");
    let (tc, tm) = coilscope_io::export::thermal_time_constants(rtv, ctv, rtm, ctm);
    assert!((f[0] as f64 / tc - 1.0).abs() < 1e-3 && (f[1] as f64 / tm - 1.0).abs() < 1e-3, "{f:?} vs {tc} {tm}");
    assert_eq!(f[4], 110.0);
    // A set without thermal parameters, and a limit below the daemon's window, are refused.
    let plain = d.path().join("plain.json");
    let mut v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&result).unwrap()).unwrap();
    v["parameters"].as_object_mut().unwrap().remove("thermal");
    std::fs::write(&plain, v.to_string()).unwrap();
    let o = coilscope(&["export", plain.to_str().unwrap(), "--speakersafetyd", "--out", &conf]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("no thermal parameters"));
    let o = coilscope(&["export", result.to_str().unwrap(), "--speakersafetyd", "--t-limit", "50", "--out", &conf]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("--t-limit 50"));
}

/// The power series in millimetres and the impedance files: read back, they give the set.
#[test]
fn power_series_and_impedance_exports_read_back() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_str().unwrap().to_string();
    let truth = coilscope_core::embedded_driver("sb17cac35-4").unwrap();
    let o = coilscope(&["export", "sb17cac35-4", "--power-series", "--out", &p("ps.csv")]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = std::fs::read_to_string(p("ps.csv")).unwrap();
    let le: Vec<f64> = text
        .lines()
        .find(|l| l.starts_with("Le,mH/mm^n"))
        .unwrap()
        .split(',')
        .skip(2)
        .filter(|v| !v.is_empty())
        .map(|v| v.parse().unwrap())
        .collect();
    let at = |x_mm: f64| le.iter().enumerate().map(|(j, c)| c * x_mm.powi(j as i32)).sum::<f64>();
    assert!((at(-2.0) / (1e3 * truth.le.eval(-2e-3)) - 1.0).abs() < 1e-5);
    for fmt in ["zma", "frd"] {
        let path = p(&format!("z.{fmt}"));
        let o = coilscope(&["export", "sb17cac35-4", &format!("--{fmt}"), "--out", &path]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let c = coilscope_io::impedance::read_impedance(std::path::Path::new(&path)).unwrap();
        assert_eq!(c.f.len(), 400);
        for (f, z) in c.f.iter().zip(&c.z) {
            let want = coilscope_core::small_signal::impedance(&truth, *f);
            assert!((z - want).norm() / want.norm() < 1e-4, "{fmt} at {f} Hz: {z} vs {want}");
        }
    }
    let o = coilscope(&["export", "sb17cac35-4", "--out", &p("x")]);
    assert_eq!(o.status.code(), Some(2));
}

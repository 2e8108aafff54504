//! `coilscope distortion`, `diagnose` and `report`; the report rendered in headless
//! Chromium (installed by `.ci/run`) without console messages, every plot drawn on the
//! screenshot.
use coilscope_report::chart::Rgb;
use std::path::Path;
use std::process::{Command, Output};

fn coilscope(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_coilscope")).args(args).output().unwrap()
}

fn text(o: &Output) -> String {
    format!("{}\n{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

#[test]
fn distortion_json_reports_harmonics_parts_and_volterra() {
    let o = coilscope(&["distortion", "ptt4.0w04-01a", "--freq", "40", "--volts", "2", "--json"]);
    assert!(o.status.success(), "{}", text(&o));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let hd2 = j["HD2"].as_f64().unwrap();
    assert!(hd2 > 1e-4 && hd2 < 0.3, "{hd2}");
    for part in ["Bl", "Kms", "Le"] {
        assert!(j["contributions"][part]["HD2"].as_f64().unwrap() > 0.0, "{part}");
    }
    // At 2 V the series and the model agree within a few dB (they are tested closely elsewhere).
    let v2 = j["volterra"]["HD2_dB"].as_f64().unwrap();
    assert!((v2 - j["HD2_dB"].as_f64().unwrap()).abs() < 3.0, "{v2}");
    assert!(j["x_dc"].as_f64().unwrap().abs() < 1e-3);
}

#[test]
fn intermodulation_of_bl_modulation_matches_the_closed_form() {
    // Only Bl(x) = b0 + b1 x, Le constant: far above resonance the force at f2 is modulated by
    // x(f1), so each first-order sideband of the pressure is |b1 X1| / (2 b0) of the f2 line and
    // d2 = |b1 X1| / b0, with X1 the f1 displacement amplitude from the linear model.
    let mut p = coilscope_core::embedded_driver("sb17cac35-4").unwrap();
    let b1 = -150.0;
    p.bl = coilscope_core::Poly { c: vec![p.bl.c[0], b1] };
    p.kms = coilscope_core::Poly::constant(p.kms.c[0]);
    p.le = coilscope_core::Poly::constant(p.le.c[0]);
    p.l2r2 = p.l2r2.map(|(l2, r2)| (coilscope_core::Poly::constant(l2.c[0]), coilscope_core::Poly::constant(r2.c[0])));
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("bl.json");
    std::fs::write(&file, serde_json::to_string(&p.to_json_value()).unwrap()).unwrap();
    let (f1, f2, volts) = (20.0, 3000.0, 2.0);
    let o =
        coilscope(&["distortion", file.to_str().unwrap(), "--freq", "20", "--freq2", "3000", "--volts", "2", "--json"]);
    assert!(o.status.success(), "{}", text(&o));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let a1 = volts; // each tone: total RMS 2 V with equal tones -> peak 2 V each
    let x1 = (coilscope_core::small_signal::displacement_per_current(&p, f1)
        / coilscope_core::small_signal::impedance(&p, f1))
    .norm()
        * a1;
    let expect = b1.abs() * x1 / p.bl.c[0];
    let d2 = j["d2"].as_f64().unwrap();
    assert!((d2 / expect - 1.0).abs() < 0.05, "d2 {d2} vs closed form {expect} (f2 {f2})");
}

#[test]
fn diagnose_reports_limits_with_changed_thresholds() {
    let o = coilscope(&["diagnose", "sb17cac35-4", "--json"]);
    assert!(o.status.success(), "{}", text(&o));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let xbl = j["limits"]["XBl"].as_f64().unwrap();
    assert!((xbl - 5.10e-3).abs() < 0.1e-3, "{xbl}");
    assert_eq!(j["polarity"]["verdict"], "consistent");
    assert!(j["thermal"]["P_max"].as_f64().unwrap() > 0.0);
    let o2 = coilscope(&["diagnose", "sb17cac35-4", "--xbl", "0.9", "--json"]);
    let j2: serde_json::Value = serde_json::from_slice(&o2.stdout).unwrap();
    assert!(j2["limits"]["XBl"].as_f64().unwrap() < xbl, "a stricter threshold is reached earlier");
    let bad = coilscope(&["diagnose", "sb17cac35-4", "--xc", "1.5"]);
    assert!(!bad.status.success() && text(&bad).contains("Cms threshold 1.5"), "{}", text(&bad));
}

#[test]
fn bad_distortion_input_gets_clear_errors() {
    for (args, needle) in [
        (vec!["distortion", "sb17cac35-4", "--freq", "40", "--volts=-1"], "--volts -1"),
        (vec!["distortion", "sb17cac35-4", "--freq", "0.1", "--volts", "1"], "--freq 0.1 Hz"),
        (vec!["distortion", "sb17cac35-4", "--freq", "30", "--freq2", "60", "--volts", "1"], "at least 3 times"),
        (vec!["distortion", "sb17cac35-4", "--freq", "20", "--volts", "40"], "outside x_range"),
        (vec!["distortion", "nonexistent.json", "--freq", "20", "--volts", "1"], "nonexistent.json"),
    ] {
        let o = coilscope(&args);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {}", text(&o));
        assert!(text(&o).contains(needle), "{args:?}: {}", text(&o));
    }
    // A report whose directory cannot be made: the error names the path.
    let dir = tempfile::tempdir().unwrap();
    let blocker = dir.path().join("file");
    std::fs::write(&blocker, "not a directory").unwrap();
    let out = blocker.join("report.html");
    let o = coilscope(&["report", "sb17cac35-4", "--out", out.to_str().unwrap(), "--volts", "1"]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    assert!(text(&o).contains(blocker.to_str().unwrap()), "{}", text(&o));
}

const CHROMIUM_FLAGS: [&str; 9] = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
];

fn chromium() -> String {
    let c = std::env::var("CHROMIUM").unwrap_or_else(|_| "/usr/bin/chromium".into());
    assert!(
        Path::new(&c).exists(),
        "headless Chromium not found at {c}: `.ci/run` installs Debian's chromium (or set CHROMIUM)"
    );
    c
}

/// Run Chromium on a page; return (stdout, console lines from its log).
fn run_chromium(page: &Path, extra: &[&str]) -> (String, Vec<String>) {
    let profile = tempfile::tempdir().unwrap();
    let o = Command::new(chromium())
        .args(CHROMIUM_FLAGS)
        .arg(format!("--user-data-dir={}", profile.path().display()))
        .args(["--enable-logging=stderr", "--v=0"])
        .args(extra)
        .arg(format!("file://{}", page.display()))
        .output()
        .unwrap();
    let log = String::from_utf8_lossy(&o.stderr).into_owned();
    let console = log.lines().filter(|l| l.contains("CONSOLE")).map(str::to_string).collect();
    (String::from_utf8_lossy(&o.stdout).into_owned(), console)
}

#[test]
fn the_console_check_catches_a_broken_page() {
    // The negative control: the console check below must be able to fail.
    let dir = tempfile::tempdir().unwrap();
    let page = dir.path().join("bad.html");
    std::fs::write(&page, "<html><body><script>console.error('boom'); notDefined();</script></body></html>").unwrap();
    let (_, console) = run_chromium(&page, &["--dump-dom"]);
    assert!(
        console.iter().any(|l| l.contains("boom")) && console.iter().any(|l| l.contains("notDefined")),
        "{console:?}"
    );
}

#[test]
fn report_of_a_measurement_renders_in_chromium_with_every_plot_drawn() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("sb17");
    let o = coilscope(&["measure", "--virtual", "sb17cac35-4", "--out", run.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let html = dir.path().join("report.html");
    let o = coilscope(&["report", run.join("result.json").to_str().unwrap(), "--out", html.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));

    // Self-contained: no external resources.
    let page = std::fs::read_to_string(&html).unwrap();
    for bad in ["http://", "https://", "<link", "src=\""] {
        let hits: Vec<_> =
            page.match_indices(bad).filter(|(i, _)| !page[i.saturating_sub(30)..*i].contains("xmlns")).collect();
        assert!(hits.is_empty(), "the report refers to an external resource ({bad})");
    }
    let ids: Vec<&str> = page
        .match_indices("<figure class=\"plot\" id=\"")
        .map(|(i, m)| page[i + m.len()..].split('"').next().unwrap())
        .collect();
    for want in [
        "plot-bl",
        "plot-kms",
        "plot-cms",
        "plot-le",
        "plot-impedance",
        "plot-hd",
        "plot-contrib-hd2",
        "plot-contrib-hd3",
        "plot-volterra",
        "plot-x-time",
        "plot-temperature-time",
        "plot-level-time",
        "plot-power-time",
        "plot-multitone",
    ] {
        assert!(ids.contains(&want), "{want} missing from {ids:?}");
    }
    // PNG and CSV copies.
    let files = dir.path().join("report_files");
    for id in &ids {
        let png = files.join(format!("{}.png", id.trim_start_matches("plot-")));
        let img = std::fs::read(&png)
            .map_err(|e| e.to_string())
            .and_then(|b| Rgb::from_png(&b))
            .unwrap_or_else(|e| panic!("{}: {e}", png.display()));
        assert!(img.width > 500, "{}", png.display());
    }
    let curves = std::fs::read_to_string(files.join("curves.csv")).unwrap();
    assert!(curves.lines().count() > 100 && curves.starts_with("x_mm,Bl_Tm"));

    // Layout and console: the page's script records each plot's box.
    let (dom, console) = run_chromium(&html, &["--window-size=1000,2000", "--dump-dom"]);
    assert!(console.is_empty(), "console messages: {console:?}");
    let layout = dom
        .split("<pre id=\"layout\" hidden=\"\">")
        .nth(1)
        .and_then(|s| s.split("</pre>").next())
        .expect("the layout record");
    let layout: serde_json::Value = serde_json::from_str(layout).unwrap();
    let height = layout["height"].as_u64().unwrap();
    let plots = layout["plots"].as_array().unwrap();
    assert_eq!(plots.len(), ids.len());

    // No legend box covers a data line, in any chart of this measured result's
    // report (the time charts and the live distortion among them), at both sizes.
    let mut input = coilscope_report::input_from(run.join("result.json").to_str().unwrap()).unwrap();
    let rows = coilscope_db::read_states(&coilscope_db::Target::Sqlite(run.join("run.sqlite")), None).unwrap();
    input.states = Some(coilscope_report::TimeSeries {
        t: rows.iter().map(|r| r.t).collect(),
        x_min: rows.iter().map(|r| r.x_min).collect(),
        x_max: rows.iter().map(|r| r.x_max).collect(),
        dtv: rows.iter().map(|r| r.dtv).collect(),
        volts: rows.iter().map(|r| r.u_rms).collect(),
        power: rows.iter().map(|r| r.re * r.i_rms * r.i_rms).collect(),
    });
    let rep = coilscope_report::build(&input, &coilscope_report::ReportOptions::default()).unwrap();
    let with_legend: Vec<&coilscope_report::chart::Chart> = rep.charts.iter().filter(|c| c.series.len() > 1).collect();
    assert!(
        with_legend.iter().any(|c| c.id == "x-time") && with_legend.iter().any(|c| c.id == "live-distortion-x"),
        "{:?}",
        with_legend.iter().map(|c| &c.id).collect::<Vec<_>>()
    );
    for c in with_legend {
        for size in [coilscope_report::ReportOptions::default().png_size, coilscope_report::SVG_SIZE] {
            let n = c.legend_covers_data(size).unwrap();
            assert_eq!(n, 0, "the legend of {} covers {n} pixels of its data lines at {size:?}", c.id);
        }
    }

    // Screenshot of the whole page; every plot's box must hold its data colours.
    let shot = dir.path().join("shot.png");
    let (_, console) =
        run_chromium(&html, &[&format!("--window-size=1000,{height}"), &format!("--screenshot={}", shot.display())]);
    assert!(console.is_empty(), "console messages: {console:?}");
    let img = Rgb::from_png(&std::fs::read(&shot).unwrap()).unwrap();
    let palette = coilscope_report::chart::PALETTE;
    for p in plots {
        let (x, y, w, h) =
            (p["x"].as_f64().unwrap(), p["y"].as_f64().unwrap(), p["w"].as_f64().unwrap(), p["h"].as_f64().unwrap());
        assert!(w > 300.0 && h > 200.0, "{p}");
        let mut data = 0usize;
        for py in y as u32..((y + h) as u32).min(img.height) {
            for px in x as u32..((x + w) as u32).min(img.width) {
                let c = img.get(px, py);
                if palette[..5].iter().any(|q| (0..3).all(|k| (c[k] as i32 - [q.0, q.1, q.2][k] as i32).abs() < 24)) {
                    data += 1;
                }
            }
        }
        assert!(data > 400, "plot {} shows only {data} pixels of data colour on the screenshot", p["id"]);
    }
}

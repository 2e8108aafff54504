//! `identify`: large-signal parameters from a recording: the full output-error fit, a batch of
//! recordings, or the Volterra method.

use crate::{parse_effects, print_values, print_warnings, untrusted_if_warned, Failure};
use coilscope_core::chain::SenseWiring;
use coilscope_core::result::ResultFile;
use coilscope_io::{read_recording, write_json, Recording};
use coilscope_workflow::chain::ChainMode;
use std::path::{Path, PathBuf};

#[allow(clippy::too_many_arguments)]
pub(crate) fn cmd_identify(
    path: &Path,
    mms: Option<coilscope_core::mass::Mass>,
    order: Option<usize>,
    effects: &str,
    chain: &ChainMode,
    wiring: SenseWiring,
    sd: Option<f64>,
    enclosure: Option<coilscope_ident::large::InBox>,
    scale: Option<&[f64]>,
    out: &Path,
) -> Result<(), Failure> {
    use coilscope_ident::large::Stage;
    use coilscope_workflow::identify::{identify_record, IdentifyRequest};
    coilscope_io::check_writable(out).map_err(|e| e.to_string())?;
    let origin = path.display().to_string();
    let mut rec = read_recording(path, scale).map_err(|e| e.to_string())?;
    let live = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let t0 = std::time::Instant::now();
    let progress = |p: &coilscope_ident::large::Progress| {
        if live {
            let stage = match p.stage {
                Stage::Estimate { order } => format!("order {order} on the estimation part"),
                Stage::Final { order } => format!("order {order} on the whole record"),
            };
            eprint!(
                "\r  {:5.1} s  fitting {stage}: iteration {:2}, current error {:.3e}        ",
                t0.elapsed().as_secs_f64(),
                p.state.iteration,
                p.residual_rel
            );
        }
    };
    // A batch's worker runs on one core (`cmd_identify_batch`).
    let threads = std::env::var(JOB_THREADS).ok().and_then(|v| v.parse().ok()).unwrap_or(0);
    let req = IdentifyRequest {
        origin: origin.clone(),
        mms: mms.map(|m| m.kg),
        mms_sd_rel: mms.map_or(0.0, |m| m.sd_rel()),
        order,
        effects: parse_effects(effects)?,
        chain: chain.clone(),
        wiring,
        sd,
        threads,
        enclosure,
    };
    let done = identify_record(&mut rec, &req, progress);
    if live {
        eprintln!();
    }
    let done = done?;
    for d in &done.detected {
        eprintln!("chain: estimated, as the record shows one: {d}");
    }
    print_warnings(&done.warnings);
    write_json(out, &done.result).map_err(|e| e.to_string())?;
    print_large_summary(path, &rec, &done.fit, &done.result, t0.elapsed().as_secs_f64());
    match &done.failure {
        Some(m) => Err(Failure::Untrusted(format!("{m}; written to {}", out.display()))),
        None => {
            println!("  result: {}", out.display());
            untrusted_if_warned(&done.warnings, out)
        }
    }
}

/// The environment variable that sets `identify`'s Jacobian threads (a batch's workers: 1).
const JOB_THREADS: &str = "COILSCOPE_THREADS";

/// `identify A.wav B.wav ... --out DIR`: each recording identified by a worker process of
/// this program with the same options (`OUT/NAME.json`), `jobs` at a time, each on one core:
/// on a production line whole records in parallel keep every core busy, where one record's
/// fit leaves a second core partly idle. A worker's failure is its recording's, not the
/// batch's; the exit code is the worst of the workers'.
pub(crate) fn cmd_identify_batch(recordings: &[PathBuf], jobs: Option<usize>, out: &Path) -> Result<(), Failure> {
    use coilscope_workflow::batch::{plan, run, verdict};
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let jobs = jobs.unwrap_or(cores);
    let planned = plan(recordings, out, jobs)?;
    std::fs::create_dir_all(out).map_err(|e| format!("{}: cannot create the output directory: {e}", out.display()))?;
    let exe = std::env::current_exe().map_err(|e| format!("cannot find this program to start the workers: {e}"))?;
    // The worker's arguments: this invocation's, less the recordings, --out and --jobs.
    let given: Vec<std::ffi::OsString> = std::env::args_os().skip(1).collect();
    let mut options = vec![];
    let mut k = 0;
    while k < given.len() {
        let a = given[k].to_string_lossy();
        if a == "--out" || a == "--jobs" {
            k += 2;
            continue;
        }
        if a.starts_with("--out=") || a.starts_with("--jobs=") || recordings.iter().any(|r| r.as_os_str() == given[k]) {
            k += 1;
            continue;
        }
        options.push(given[k].clone());
        k += 1;
    }
    let t0 = std::time::Instant::now();
    // Each record in a process of its own: a record that crashes takes no other with it.
    let work = |job: &coilscope_workflow::batch::Job| {
        let o = std::process::Command::new(&exe)
            .args(&options)
            .arg(&job.record)
            .arg("--out")
            .arg(&job.result)
            .env(JOB_THREADS, "1")
            .stdin(std::process::Stdio::null())
            .output();
        match o {
            Ok(o) => (
                o.status.code().unwrap_or(2),
                format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr)),
            ),
            Err(e) => (2, format!("cannot start a worker: {e}")),
        }
    };
    // Each recording's report whole, as it finishes.
    let finished = |d: &coilscope_workflow::batch::Done| {
        println!("== {} ({:.1} s, exit {})\n{}", d.job.record.display(), d.seconds, d.exit, d.text.trim_end());
    };
    let done = run(planned, jobs, work, finished);
    println!("batch: {} recordings in {:.1} s, {jobs} at a time", done.len(), t0.elapsed().as_secs_f64());
    for d in &done {
        let what = match d.exit {
            0 => format!("ok: {}", d.job.result.display()),
            3 => format!("written but not trustworthy (see its warnings): {}", d.job.result.display()),
            _ => "failed (see its report above)".to_string(),
        };
        println!("  {:<40} {what}", d.job.record.display().to_string());
    }
    verdict(&done).map_err(|(code, why)| if code == 3 { Failure::Untrusted(why) } else { Failure::Error(why) })
}

/// `identify --method volterra`: the seed paper's Volterra identification (3.2.2.1) on a
/// recorded readable multitone. Every number traces to `coilscope_ident::volterra`: the lines
/// (`record_lines`), the ratios and their noise (`RecordLines::harmonics`), the fit and its
/// covariance (`identify_volterra_weighted`), the truncation check (`truncation_check`).
#[allow(clippy::too_many_arguments)]
pub(crate) fn cmd_identify_volterra(
    path: &Path,
    start: Option<&str>,
    mms: Option<f64>,
    order: Option<usize>,
    effects: &str,
    chain_choice: &ChainMode,
    wiring: SenseWiring,
    sd: Option<f64>,
    scale: Option<&[f64]>,
    out: &Path,
) -> Result<(), Failure> {
    use coilscope_workflow::volterra::{identify_volterra, linear_start};
    coilscope_io::check_writable(out).map_err(|e| e.to_string())?;
    let origin = path.display().to_string();
    if let Some(o) = order.filter(|&o| o != 2) {
        return Err(Failure::from(format!("--order {o}: the Volterra method gives the series to second order (the kernels to third order depend on x^0 .. x^2 only); leave --order out")));
    }
    if effects != "auto" && effects != "none" {
        return Err(Failure::from(format!("--effects {effects}: the Volterra method fits Bl, Kms, Le to the kernels of the start's linear model; its effects (creep, LR-3) come from --start")));
    }
    if mms.is_some() {
        return Err(Failure::from(
            "--mms: the Volterra method takes the moving mass (and the rest of the linear part) from --start",
        ));
    }
    let start_spec = start.ok_or("--method volterra needs --start FILE: the small-signal parameters (run `coilscope linear` on a noise record of the driver, or give a parameter set)")?;
    let start = linear_start(coilscope_report::input_from(start_spec)?.params, sd);
    let mut rec = read_recording(path, scale).map_err(|e| e.to_string())?;
    let t0 = std::time::Instant::now();
    let v = identify_volterra(&mut rec, &origin, &start, start_spec, chain_choice, wiring)?;
    print_warnings(&v.warnings);
    write_json(out, &v.result).map_err(|e| e.to_string())?;
    let (q, reach, chi2, trunc) = (&v.params, v.reach, v.chi2_dof, v.truncation);
    let pct = |f: &coilscope_core::Poly, x: f64| 100.0 * (f.eval(x) / f.c[0] - 1.0);
    println!(
        "coilscope identify --method volterra: {origin}, {} tones {}-{} Hz, {} periods, {:.2} s",
        v.tones_hz.len(),
        v.tones_hz[0],
        v.tones_hz[v.tones_hz.len() - 1],
        v.periods,
        t0.elapsed().as_secs_f64()
    );
    println!("  reach {:+.3} .. {:+.3} mm; kernel chi^2/dof {chi2:.2}, truncation {trunc:.2} (both about 1 or less where the series holds)", 1e3 * reach[0], 1e3 * reach[1]);
    for (name, f) in [("Bl", &q.bl), ("Kms", &q.kms), ("Le", &q.le)] {
        println!(
            "  {name:>3}(x) at the reach: {:+.2} % / {:+.2} % of its value at rest",
            pct(f, reach[0]),
            pct(f, reach[1])
        );
    }
    println!("  result: {}", out.display());
    untrusted_if_warned(&v.warnings, out)
}

fn print_large_summary(
    path: &Path,
    rec: &Recording,
    fit: &coilscope_ident::large::LargeFit,
    result: &ResultFile,
    seconds: f64,
) {
    let p = &fit.params;
    let fs = rec.fs as f64;
    println!(
        "coilscope identify: {} ({:.2} s at {} Hz), fitted in {:.1} s",
        path.display(),
        rec.u.len() as f64 / fs,
        rec.fs,
        seconds
    );
    println!(
        "  order {} ({}), {} iterations, current error {:.3e} (relative RMS), x reached {:.3} .. {:.3} mm",
        fit.order,
        if fit.trials.is_empty() { "given".to_string() } else { "chosen on held-out data".to_string() },
        fit.iterations,
        fit.residual_rel,
        fit.x_range[0] * 1e3,
        fit.x_range[1] * 1e3
    );
    for t in &fit.trials {
        println!("    order {}: estimation {:.3e}, validation {:.3e}", t.order, t.estimation_rel, t.validation_rel);
    }
    let tried = fit.models_tried();
    let words = |t: &coilscope_core::result::ModelTrial| {
        match (t.validation_rel, t.screen_gain) {
        (Some(v), _) => match t.validation_rel_before {
            Some(b) => format!("{} validation {v:.3e} (went on alone from {b:.3e}: the next trial's gain was within what its fit had left)", t.model),
            None => format!("{} validation {v:.3e}", t.model),
        },
        (None, Some(g)) if t.outscored_by.is_some() => format!("{} not fitted: {} took its round (could gain {:.2e})", t.model, t.outscored_by.as_deref().unwrap_or_default(), g),
        (None, Some(g)) => format!("{} screened out (could gain {:.2e})", t.model, g),
        (None, None) => t.model.clone(),
    }
    };
    println!(
        "  model {} ({})",
        fit.layout.effects.model_name(),
        if tried.is_empty() { "given".to_string() } else { tried.iter().map(words).collect::<Vec<_>>().join(", ") }
    );
    if let Some(c) = &fit.chain {
        println!("  chain: {}", c.describe_fitted(fit.fs));
    }
    let u = &result.uncertainty;
    // Bl, Kms and Le are shown as curves below.
    print_values(p, u, &["Bl", "Kms", "Le"]);
    let [lo, hi] = fit.x_range;
    println!(
        "  {:<6} {:>14} {:>14} {:>14}",
        "",
        format!("x={:.2} mm", lo * 1e3),
        "x=0",
        format!("x={:.2} mm", hi * 1e3)
    );
    for (name, unit, scale) in [("Bl", "T m", 1.0), ("Kms", "N/m", 1.0), ("Le", "mH", 1e3)] {
        let b = fit.band(name, 3);
        let cell = |k: usize| format!("{:.4} +- {:.1e}", b.value[k] * scale, b.sd[k] * scale);
        let f = match name {
            "Bl" => &p.bl,
            "Kms" => &p.kms,
            _ => &p.le,
        };
        println!("  {:<6} {:>14} {:>14} {:>14}  {unit}", name, cell(0), format!("{:.4}", f.eval(0.0) * scale), cell(2));
    }
    if let Some(l) = &result.limits {
        let lim = |v: Option<f64>, beyond: Option<f64>| match v {
            Some(v) => format!("{:.2} mm", v * 1e3),
            None => format!("> {:.2} mm", beyond.unwrap_or(0.0) * 1e3),
        };
        println!(
            "  limits: XBl {}, XC {}, XL {}, Xsym {}, Ak {:.1} %",
            lim(l.xbl, l.xbl_beyond),
            lim(l.xc, l.xc_beyond),
            lim(l.xl, l.xl_beyond),
            l.xsym.map(|v| format!("{:+.2} mm", v * 1e3)).unwrap_or("-".into()),
            l.ak
        );
    }
    if let Some(d) = &result.cross_check {
        let pc = |k: &str| 100.0 * d.max_rel_difference.get(k).copied().unwrap_or(f64::NAN);
        println!(
            "  cross-check (post-inverse, measured x): Bl {:.2} %, Kms {:.2} %, Le {:.2} %, Mms {:.2} %",
            pc("Bl"),
            pc("Kms"),
            pc("Le"),
            pc("Mms")
        );
    }
    if let Some(dt) = result.thermal.as_ref().and_then(|t| t.dt_end) {
        println!(
            "  voice coil: Re {:.4} -> {:.4} ohm over the record (+{:.2} K)",
            fit.re_track[0].1,
            fit.re_track.last().unwrap().1,
            dt
        );
        if !fit.layout.heat_taus.is_empty() {
            println!("  Re(t): knots every {:.2} s plus heating terms (time constants {:?} s): the coil heated faster than the knots could follow", fit.layout.knot_dt, fit.layout.heat_taus);
        }
    }
}

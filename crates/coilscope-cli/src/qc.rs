//! `qc`: the end-of-line test of a production line (the workflow is
//! [`coilscope_workflow::qc`]): learning limits, testing a unit, a lot's capability.

use crate::args::QcAction;
use crate::Failure;
use coilscope_core::Parameters;
use coilscope_db::Target;
use coilscope_report::lot::{lot_report, FigureSeries, LotInput, LotStats};
use coilscope_workflow::identify::IdentifyRequest;
use coilscope_workflow::qc::{
    capability, drift, figures, history, learn, lot, test_unit, unit_from_record, Limit, Limits, Station, Verdict,
    FIGURES,
};
use std::path::Path;

/// A unit's set from a result or a parameter set, with the range its record reached as its
/// `x_range`; and whether its measurement is trustworthy.
fn unit(spec: &str) -> Result<(Parameters, bool), String> {
    let input = coilscope_report::input_from(spec)?;
    let trusted = input.result.as_ref().is_none_or(|r| r.fit.trustworthy != Some(false));
    Ok((Parameters { x_range: Some(input.range), ..input.params }, trusted))
}

/// Whether a unit is given as a record (a `.wav` file) rather than a result or a set.
fn is_record(spec: &str) -> bool {
    Path::new(spec).extension().is_some_and(|e| e.eq_ignore_ascii_case("wav"))
}

/// A unit's id from its file's name: the name without `.json` or `.wav`, or the embedded name.
fn default_unit_id(spec: &str) -> String {
    let p = Path::new(spec);
    match p.extension() {
        Some(e) if e == "json" || e.eq_ignore_ascii_case("wav") => {
            p.file_stem().map_or(spec.to_string(), |s| s.to_string_lossy().into_owned())
        }
        _ => p.file_name().map_or(spec.to_string(), |s| s.to_string_lossy().into_owned()),
    }
}

/// A verdict's checks, one line each, and its advice.
fn print_checks(v: &Verdict) {
    for c in &v.checks {
        let value = if c.value.is_finite() { shown(&c.key, c.value) } else { "-".into() };
        let hi = if c.hi.is_finite() { shown(&c.key, c.hi) } else { "-".into() };
        let mark = if c.pass { "ok  " } else { "FAIL" };
        let why = if c.pass {
            String::new()
        } else if c.by_sd.is_finite() {
            format!("  {:+.1} sd past the limit: {}", c.by_sd, c.cause)
        } else {
            format!("  {}", c.cause)
        };
        println!("{mark} {:<9} {:>16}   limits {} .. {}{why}", c.key, value, shown(&c.key, c.lo), hi);
    }
    for a in &v.advice {
        println!("advice: {a}");
    }
}

fn load_limits(path: &Path) -> Result<Limits, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: cannot read ({e})", path.display()))?;
    Limits::from_json(&text, &path.display().to_string())
}

fn write(path: &Path, v: &serde_json::Value) -> Result<(), String> {
    coilscope_io::write_json(path, v).map_err(|e| e.to_string())
}

/// A figure's display unit and the factor from SI to it (mm for lengths, mH for Le).
fn display_unit(key: &str) -> (String, f64) {
    match key {
        "Xsym_Bl" | "Xsym_Kms" | "Xmax" => ("mm".into(), 1e3),
        "Le(0)" => ("mH".into(), 1e3),
        _ => (FIGURES.iter().find(|f| f.key == key).map_or("", |f| f.unit).to_string(), 1.0),
    }
}

/// A limited figure's series for a page, in its display unit (`k` from SI).
fn series(
    l: &Limit,
    unit: String,
    k: f64,
    values: Vec<Option<f64>>,
    capability: Option<LotStats>,
    drift_sd: Option<f64>,
) -> FigureSeries {
    FigureSeries {
        key: l.key.clone(),
        unit,
        values,
        lo: l.lo * k,
        hi: l.hi * k,
        mean: l.mean * k,
        capability,
        drift_sd,
    }
}

/// Write a page and its files, and say where.
fn write_page(rep: &coilscope_report::Report, out: &Path) -> Result<(), String> {
    let written = coilscope_report::write(rep, out, coilscope_report::ReportOptions::default().png_size)?;
    for w in &rep.warnings {
        eprintln!("warning: the page could not draw {w}");
    }
    println!(
        "wrote {} and {} files in {}",
        out.display(),
        written.len() - 1,
        coilscope_report::files_dir(out).display()
    );
    Ok(())
}

/// A figure's value in its display unit (mm for lengths, mH for Le).
fn shown(key: &str, v: f64) -> String {
    let (unit, k) = display_unit(key);
    if unit == "mm" {
        format!("{:+.3} mm", v * k)
    } else {
        format!("{:.4} {unit}", v * k)
    }
}

pub(crate) fn cmd_qc(action: QcAction) -> Result<(), Failure> {
    match action {
        QcAction::Learn { results, k, out } => {
            coilscope_io::check_writable(&out).map_err(|e| e.to_string())?;
            let mut golden = Vec::new();
            for r in &results {
                let (p, trusted) = unit(r)?;
                if !trusted {
                    return Err(Failure::from(format!("{r}: its measurement is not trustworthy (fit.trustworthy false): measure the golden unit again")));
                }
                golden.push((r.clone(), p));
            }
            let l = learn(&golden, k)?;
            write(&out, &l.to_json())?;
            println!(
                "limits of {} golden units at +-{k} sd (symmetry points at +-{:.2} mm):",
                golden.len(),
                l.amplitude * 1e3
            );
            for x in &l.limits {
                let hi = if x.hi.is_finite() { shown(&x.key, x.hi) } else { "-".into() };
                println!(
                    "  {:<9} {:>16} .. {:<16} (mean {}, sd {})",
                    x.key,
                    shown(&x.key, x.lo),
                    hi,
                    shown(&x.key, x.mean),
                    shown(&x.key, x.sd)
                );
            }
            for (key, why) in &l.skipped {
                println!("  {key:<9} not limited: {why}");
            }
            println!("wrote {}", out.display());
            Ok(())
        }
        QcAction::Test { results, limits, out, db, station, unit_id, mms, effects, chain, threads } => {
            let request = |origin: &str| -> Result<IdentifyRequest, Failure> {
                let Some(m) = mms else {
                    return Err(Failure::from(format!("{origin}: a record is identified before it is judged: give the unit's moving mass with --mms KG")));
                };
                Ok(IdentifyRequest {
                    effects: crate::parse_effects(&effects)?,
                    chain: crate::parse_chain(&chain)?,
                    threads,
                    ..IdentifyRequest::new(origin, Some(m))
                })
            };
            if let Some(o) = &out {
                if results.len() > 1 {
                    return Err(Failure::from(format!("--out {}: one verdict file is for one unit; {} were given (with --db every verdict is in the database)", o.display(), results.len())));
                }
                coilscope_io::check_writable(o).map_err(|e| e.to_string())?;
            }
            if unit_id.is_some() && results.len() > 1 {
                return Err(Failure::from(format!(
                    "--unit-id names one unit; {} were given (each is named by its file)",
                    results.len()
                )));
            }
            let l = load_limits(&limits)?;
            let mut station = match &db {
                Some(spec) => {
                    Some(Station::open(&Target::parse(spec), &station, l.clone(), &limits.display().to_string())?)
                }
                None => None,
            };
            let one = results.len() == 1;
            let (mut failed, mut untrusted) = (Vec::new(), Vec::new());
            for result in &results {
                let (p, trusted) = if is_record(result) {
                    let mut rec = coilscope_io::read_recording(Path::new(result), None).map_err(|e| e.to_string())?;
                    unit_from_record(&mut rec, &request(result)?)?
                } else {
                    unit(result)?
                };
                let id = unit_id.clone().unwrap_or_else(|| default_unit_id(result));
                let v = match station.as_mut() {
                    Some(s) => s.test(&id, &p, trusted)?,
                    None => test_unit(&p, result, &l),
                };
                if let Some(o) = &out {
                    write(o, &v.to_json())?;
                }
                let names: Vec<String> = v.failed().map(|c| format!("{} ({})", c.key, c.cause)).collect();
                if one {
                    print_checks(&v);
                } else {
                    match (trusted, v.pass) {
                        (false, _) => println!("UNTRUSTED {id}: its measurement is not trustworthy; measure it again"),
                        (true, true) => println!("PASS {id}"),
                        (true, false) => println!("FAIL {id}: {}", names.join("; ")),
                    }
                    for a in v.advice.iter().filter(|_| trusted) {
                        println!("  advice: {a}");
                    }
                }
                if !trusted {
                    untrusted.push(result.clone());
                } else if !v.pass {
                    failed.push(format!("{result}: {}", names.join("; ")));
                } else if one {
                    println!("PASS: {result}");
                }
            }
            if let Some(s) = station {
                let (run, passed, n_failed) = (s.run(), s.passed, s.failed);
                s.finish()?;
                println!(
                    "{} units: {passed} passed, {n_failed} failed; station run {run} in {}",
                    results.len(),
                    Target::parse(db.as_deref().unwrap_or_default()).name()
                );
            }
            if !failed.is_empty() {
                return Err(Failure::Rejected(failed.join("\n")));
            }
            if !untrusted.is_empty() {
                return Err(Failure::Untrusted(format!("{}: the unit's measurement is not trustworthy (fit.trustworthy false): measure it again before judging it", untrusted.join(", "))));
            }
            Ok(())
        }
        QcAction::Stats { results, limits, out, db, run, report } => {
            for o in out.iter().chain(&report) {
                coilscope_io::check_writable(o).map_err(|e| e.to_string())?;
            }
            let l = load_limits(&limits)?;
            let mut units = Vec::new();
            let mut names = Vec::new();
            if let Some(spec) = &db {
                let target = Target::parse(spec);
                for (id, p) in lot(&target, run)? {
                    names.push(id);
                    units.push(p);
                }
                if units.is_empty() {
                    return Err(Failure::from(match run {
                        Some(r) => format!(
                            "{}: run {r} tested no units (`coilscope runs {spec}` lists the runs)",
                            target.name()
                        ),
                        None => format!("{}: no units tested yet (qc test --db writes them)", target.name()),
                    }));
                }
            }
            for r in &results {
                let (p, trusted) = unit(r)?;
                if !trusted {
                    eprintln!(
                        "warning: {r}: its measurement is not trustworthy (fit.trustworthy false); counted as it is"
                    );
                }
                names.push(r.clone());
                units.push(p);
            }
            let caps = capability(&units, &l);
            println!("{} units against {}:", units.len(), limits.display());
            println!(
                "  {:<9} {:>5} {:>16} {:>16} {:>7} {:>8} {:>8}",
                "figure", "n", "mean", "sd", "Cpk", "outside", "unknown"
            );
            for c in &caps {
                println!(
                    "  {:<9} {:>5} {:>16} {:>16} {:>7.2} {:>8} {:>8}",
                    c.key,
                    c.n,
                    shown(&c.key, c.mean),
                    shown(&c.key, c.sd),
                    c.cpk,
                    c.outside,
                    c.unknown
                );
            }
            if let Some(o) = &out {
                let rows: Vec<serde_json::Value> = caps
                    .iter()
                    .map(|c| serde_json::json!({"key": c.key, "n": c.n, "mean": c.mean, "sd": c.sd, "Cpk": if c.cpk.is_finite() { serde_json::json!(c.cpk) } else { serde_json::Value::Null }, "outside": c.outside, "unknown": c.unknown}))
                    .collect();
                write(o, &serde_json::json!({"format": "coilscope.qc-stats/1", "units": names, "figures": rows}))?;
            }
            if let Some(r) = &report {
                // Each unit's figures once (their symmetry points and limits are searched).
                let rows: Vec<Vec<Option<f64>>> = units.iter().map(|p| figures(p, l.amplitude)).collect();
                let figures = l
                    .limits
                    .iter()
                    .filter_map(|x| {
                        let j = FIGURES.iter().position(|f| f.key == x.key)?;
                        let c = caps.iter().find(|c| c.key == x.key)?;
                        let (unit, k) = display_unit(&x.key);
                        let values = rows.iter().map(|r| r[j].map(|v| v * k)).collect();
                        let capability =
                            LotStats { n: c.n, mean: c.mean * k, sd: c.sd * k, cpk: c.cpk, outside: c.outside };
                        Some(series(x, unit, k, values, Some(capability), None))
                    })
                    .collect();
                let source = match &db {
                    Some(spec) => format!(
                        "{} units from {}{}",
                        units.len(),
                        Target::parse(spec).name(),
                        run.map_or(String::new(), |r| format!(", run {r}"))
                    ),
                    None => format!("{} units from their result files", units.len()),
                };
                let input = LotInput {
                    title: format!("Lot of {} units against {}", units.len(), limits.display()),
                    source,
                    units: names.clone(),
                    tested: None,
                    figures,
                };
                write_page(&lot_report(&input)?, r)?;
            }
            Ok(())
        }
        QcAction::History { unit: id, db, limits, out, report } => {
            for o in out.iter().chain(&report) {
                coilscope_io::check_writable(o).map_err(|e| e.to_string())?;
            }
            let l = load_limits(&limits)?;
            let target = Target::parse(&db);
            let visits = history(&target, &id, l.amplitude)?;
            if visits.is_empty() {
                return Err(Failure::from(format!(
                    "{}: no tests of unit {id:?} (qc test --db --unit-id writes them)",
                    target.name()
                )));
            }
            println!("unit {id}: {} tests in {}", visits.len(), target.name());
            let limited: Vec<(usize, &coilscope_workflow::qc::Limit)> =
                l.limits.iter().filter_map(|x| FIGURES.iter().position(|f| f.key == x.key).map(|j| (j, x))).collect();
            for v in &visits {
                print!("  run {:>4} {}", v.run, if v.pass { "pass" } else { "FAIL" });
                for (j, x) in &limited {
                    print!("  {} {}", x.key, v.figures[*j].map_or("-".into(), |f| shown(&x.key, f)));
                }
                println!();
            }
            // Drift: the last known value against the first, in the limits' sds.
            let drifts = drift(&visits, &l);
            let drift_json: Vec<serde_json::Value> = drifts
                .iter()
                .map(|(key, d)| {
                    if d.is_finite() {
                        println!("  drift {key:<9} {d:+.2} sd of the line since its first test");
                    }
                    serde_json::json!({"key": key, "sd": if d.is_finite() { serde_json::json!(d) } else { serde_json::Value::Null }})
                })
                .collect();
            if let Some(r) = &report {
                let figures = limited
                    .iter()
                    .map(|(j, x)| {
                        let (unit, k) = display_unit(&x.key);
                        let d = drifts.iter().find(|(key, _)| *key == x.key).map(|(_, d)| *d);
                        series(x, unit, k, visits.iter().map(|v| v.figures[*j].map(|f| f * k)).collect(), None, d)
                    })
                    .collect();
                let input = LotInput {
                    title: format!("Unit {id}: {} tests", visits.len()),
                    source: format!("unit {id} in {}, against {}", target.name(), limits.display()),
                    units: visits.iter().map(|v| format!("run {}", v.run)).collect(),
                    tested: Some(visits.iter().map(|v| v.tested).collect()),
                    figures,
                };
                write_page(&lot_report(&input)?, r)?;
            }
            if let Some(o) = &out {
                let tests: Vec<serde_json::Value> = visits
                    .iter()
                    .map(|v| {
                        let f: serde_json::Map<String, serde_json::Value> = limited
                            .iter()
                            .map(|(j, x)| {
                                (x.key.clone(), v.figures[*j].map_or(serde_json::Value::Null, |f| serde_json::json!(f)))
                            })
                            .collect();
                        serde_json::json!({"tested": v.tested, "run": v.run, "pass": v.pass, "figures": f})
                    })
                    .collect();
                write(
                    o,
                    &serde_json::json!({"format": "coilscope.qc-history/1", "unit": id, "tests": tests, "drift": drift_json}),
                )?;
            }
            Ok(())
        }
    }
}

//! `qc`: the end-of-line test of a production line (the workflow is
//! [`coilscope_workflow::qc`]): learning limits, testing a unit, a lot's capability.

use crate::args::QcAction;
use crate::Failure;
use coilscope_core::Parameters;
use coilscope_workflow::qc::{capability, learn, test_unit, Limits, FIGURES};
use std::path::Path;

/// A unit's set from a result or a parameter set, with the range its record reached as its
/// `x_range`; and whether its measurement is trustworthy.
fn unit(spec: &str) -> Result<(Parameters, bool), String> {
    let input = coilscope_report::input_from(spec)?;
    let trusted = input.result.as_ref().is_none_or(|r| r.fit.trustworthy != Some(false));
    Ok((Parameters { x_range: Some(input.range), ..input.params }, trusted))
}

fn load_limits(path: &Path) -> Result<Limits, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: cannot read ({e})", path.display()))?;
    Limits::from_json(&text, &path.display().to_string())
}

fn write(path: &Path, v: &serde_json::Value) -> Result<(), String> {
    coilscope_io::write_json(path, v).map_err(|e| e.to_string())
}

/// A figure's value in its display unit (mm for lengths, mH for Le).
fn shown(key: &str, v: f64) -> String {
    match key {
        "Xsym_Bl" | "Xsym_Kms" | "Xmax" => format!("{:+.3} mm", v * 1e3),
        "Le(0)" => format!("{:.4} mH", v * 1e3),
        _ => {
            let unit = FIGURES.iter().find(|f| f.key == key).map_or("", |f| f.unit);
            format!("{v:.4} {unit}")
        }
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
        QcAction::Test { result, limits, out } => {
            if let Some(o) = &out {
                coilscope_io::check_writable(o).map_err(|e| e.to_string())?;
            }
            let l = load_limits(&limits)?;
            let (p, trusted) = unit(&result)?;
            let v = test_unit(&p, &result, &l);
            if let Some(o) = &out {
                write(o, &v.to_json())?;
            }
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
            if !trusted {
                return Err(Failure::Untrusted(format!("{result}: the unit's measurement is not trustworthy (fit.trustworthy false): measure it again before judging it")));
            }
            if v.pass {
                println!("PASS: {result}");
                Ok(())
            } else {
                let names: Vec<String> = v.failed().map(|c| format!("{} ({})", c.key, c.cause)).collect();
                Err(Failure::Rejected(format!("{result}: {}", names.join("; "))))
            }
        }
        QcAction::Stats { results, limits, out } => {
            if let Some(o) = &out {
                coilscope_io::check_writable(o).map_err(|e| e.to_string())?;
            }
            let l = load_limits(&limits)?;
            let mut units = Vec::new();
            for r in &results {
                let (p, trusted) = unit(r)?;
                if !trusted {
                    eprintln!(
                        "warning: {r}: its measurement is not trustworthy (fit.trustworthy false); counted as it is"
                    );
                }
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
                write(o, &serde_json::json!({"format": "coilscope.qc-stats/1", "units": results, "figures": rows}))?;
            }
            Ok(())
        }
    }
}

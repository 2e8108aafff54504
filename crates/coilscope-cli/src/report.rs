//! `report`, `diagnose`, `compensate` and `export`: what a result says, and what other tools read
//! of it.

use crate::args::LimitArgs;
use crate::print_json;
use coilscope_core::simulate::{simulate, SimOptions};
use coilscope_io::read_voltage;
use std::path::Path;

/// What `export` writes.
pub(crate) enum ExportFormat {
    /// The unit's protection model and calibration record.
    Protection {
        unit_id: Option<String>,
        measured_at: f64,
    },
    Speakersafetyd,
    PowerSeries,
    Zma,
    Frd,
}

/// `export`: one file for another tool, written atomically.
pub(crate) fn cmd_export(
    spec: &str,
    format: ExportFormat,
    out: &Path,
    o: &coilscope_io::export::SafetydOptions,
) -> Result<(), String> {
    use coilscope_io::export;
    coilscope_io::check_writable(out).map_err(|e| e.to_string())?;
    let input = coilscope_report::input_from(spec)?;
    let mut p = input.params;
    // A measured set has no name of its own: the result's device or recording names it.
    if p.name.is_none() {
        p.name = input.result.map(|r| r.recording).filter(|r| !r.is_empty());
    }
    let curve = || export::impedance_curve(&p, 5.0, 20_000.0, 400);
    let (text, what) = match format {
        ExportFormat::Protection { unit_id, measured_at } => {
            let po = coilscope_io::protection::ProtectionOptions {
                unit_id: unit_id.or_else(|| p.name.clone()).unwrap_or_default(),
                measured_at,
                t_limit: o.t_limit,
                thresholds: coilscope_core::limits::Thresholds::default(),
            };
            let v = coilscope_io::protection::protection(&p, &po).map_err(|e| format!("{spec}: {e}"))?;
            let text = serde_json::to_string_pretty(&v).map_err(|e| e.to_string())? + "\n";
            (text, "protection model and calibration")
        }
        ExportFormat::Speakersafetyd => {
            (export::speakersafetyd(&p, o).map_err(|e| format!("{spec}: {e}"))?, "speakersafetyd configuration")
        }
        ExportFormat::PowerSeries => (export::power_series_csv(&p), "power series (mm)"),
        ExportFormat::Zma => (coilscope_io::impedance::zma_text(&curve()), "impedance (.zma)"),
        ExportFormat::Frd => (export::frd_text(&curve()), "impedance (.frd)"),
    };
    coilscope_io::atomic_write(out, text.as_bytes()).map_err(|e| e.to_string())?;
    println!("wrote {} ({what})", out.display());
    Ok(())
}

/// `compensate`: the pre-inverse drive, and what the model predicts it does (the largest
/// deviation of the displacement from the linear reference, plain and compensated).
pub(crate) fn cmd_compensate(
    params: &str,
    input: &Path,
    out: &Path,
    max_volts: Option<f64>,
    min_force_factor: f64,
    scale: Option<f64>,
) -> Result<(), String> {
    use coilscope_core::inverse::{compensate, CompensateOptions};
    coilscope_io::check_writable(out).map_err(|e| e.to_string())?;
    let p = coilscope_report::input_from(params)?.params;
    let (fs, u) = read_voltage(input, scale.map(|s| vec![s]).as_deref()).map_err(|e| e.to_string())?;
    if u.is_empty() {
        return Err(format!("{}: the input has no samples", input.display()));
    }
    let c = compensate(&p, fs as f64, &u, &CompensateOptions { max_volts, min_force_factor })
        .map_err(|e| format!("{}: {e}", input.display()))?;
    coilscope_io::write_voltage(out, fs, &c.drive).map_err(|e| e.to_string())?;
    let dev = |x: &[f64]| x.iter().zip(&c.x_target).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    let peak = c.x_target.iter().fold(0.0f64, |a, v| a.max(v.abs()));
    let sim =
        |d: &[f64]| simulate(&p, fs as f64, d, &SimOptions::default()).map(|t| dev(&t.x)).map_err(|e| e.to_string());
    let name = p.name.clone().unwrap_or_else(|| params.to_string());
    println!("coilscope compensate: {name}, {:.2} s at {fs} Hz", u.len() as f64 / fs as f64);
    println!("  linear reference peak excursion {:.3} mm", peak * 1e3);
    println!("  drive peak {:.3} V (input {:.3} V)", c.peak_volts, u.iter().fold(0.0f64, |a, v| a.max(v.abs())));
    match (sim(&u), sim(&c.drive)) {
        (Ok(a), Ok(b)) => println!(
            "  the model's displacement off the linear reference (largest): plain {a:.3e} m, compensated {b:.3e} m"
        ),
        (Err(e), _) | (_, Err(e)) => println!("  (the model's check did not run: {e})"),
    }
    for w in &c.warnings {
        println!("  warning: {w}");
    }
    println!("  wrote {}", out.display());
    Ok(())
}

pub(crate) fn cmd_diagnose(spec: &str, l: &LimitArgs, json: bool) -> Result<(), String> {
    let th = l.thresholds()?;
    let input = coilscope_report::input_from(spec)?;
    let d = coilscope_analysis::diagnosis::diagnose(&input.params, input.range, th, l.max_dt);
    if json {
        print_json(&d.to_json());
        return Ok(());
    }
    let mm = |v: Option<f64>| {
        v.map(|x| format!("{:.2} mm", x * 1e3))
            .unwrap_or_else(|| format!("beyond the reach ({:.2} mm)", d.limits.reach * 1e3))
    };
    println!(
        "{}: over {:.2} .. {:.2} mm",
        input.params.name.clone().unwrap_or_else(|| spec.into()),
        input.range[0] * 1e3,
        input.range[1] * 1e3
    );
    println!("  XBl (Bl {:.0} %)   {}", th.bl * 100.0, mm(d.limits.xbl));
    println!("  XC  (Cms {:.0} %)  {}", th.cms * 100.0, mm(d.limits.xc));
    println!("  XL  (Le {:.0} %)   {}", th.le * 100.0, mm(d.limits.xl));
    println!("  Ak               {:.1} %", d.limits.ak);
    println!("  Bl               {}", d.bl_shift_advice());
    let pol = &d.polarity;
    println!(
        "  polarity         {} (Le(-{:.2} mm) / Le(+{:.2} mm) = {:.3})",
        pol.verdict,
        pol.at * 1e3,
        pol.at * 1e3,
        pol.le_minus / pol.le_plus
    );
    match &d.thermal {
        Some(t) => {
            println!("  thermal (+{:.0} K) {:.1} W continuous in Re; {:.2} V RMS worst sine ({:.0} Hz); {:.2} V RMS IEC noise ({:.1} W nominal)", t.dt_max, t.p_max, t.volts_sine, t.f_sine, t.volts_iec, t.p_nominal_iec);
        }
        None => println!("  thermal          no thermal parameters in the set"),
    }
    Ok(())
}

pub(crate) fn cmd_report(
    spec: &str,
    out: &Path,
    db: Option<&str>,
    volts: Option<f64>,
    compare: Option<&str>,
    l: &LimitArgs,
) -> Result<(), String> {
    coilscope_io::check_writable(out).map_err(|e| e.to_string())?;
    let th = l.thresholds()?;
    if let Some(v) = volts {
        if !(v.is_finite() && v > 0.0 && v <= 500.0) {
            return Err(format!("--volts {v} is not valid (0 .. 500 V RMS)"));
        }
    }
    let mut input = coilscope_report::input_from(spec)?;
    // A run database holds a measurement's states over time: it goes with a measurement's
    // result only (an identify result or a parameter set beside one is drawn without it).
    let measured = input.result.as_ref().is_some_and(|r| r.measurement.is_some());
    if let (Some(spec_db), false) = (db, measured) {
        return Err(format!(
            "--db {spec_db}: {spec} is not the result of a measurement (it has no `measurement`), so no run's states belong with it; leave --db out"
        ));
    }
    let target = db
        .map(coilscope_db::Target::parse)
        .or_else(|| {
            Path::new(spec)
                .parent()
                .map(|d| d.join("run.sqlite"))
                .filter(|p| p.exists())
                .map(coilscope_db::Target::Sqlite)
        })
        .filter(|_| measured);
    if let (Some(target), Some(m)) = (target, input.result.as_ref().and_then(|r| r.measurement.as_ref())) {
        // The database must hold this measurement: its states are those of the last run of
        // the result's device (a fleet's database holds many stations' runs).
        let runs = coilscope_db::list_runs(&target)?;
        let Some(run) = runs.iter().rev().find(|r| r.device == m.device) else {
            return Err(format!("{}: no run measured {:?}, the device of {spec}: give the run database of this measurement (--db), or none", target.name(), m.device));
        };
        let rows = coilscope_db::read_states(&target, Some(run.id))?;
        if !rows.is_empty() {
            input.states = Some(coilscope_report::TimeSeries {
                t: rows.iter().map(|r| r.t).collect(),
                x_min: rows.iter().map(|r| r.x_min).collect(),
                x_max: rows.iter().map(|r| r.x_max).collect(),
                dtv: rows.iter().map(|r| r.dtv).collect(),
                volts: rows.iter().map(|r| r.u_rms).collect(),
                power: rows.iter().map(|r| r.re * r.i_rms * r.i_rms).collect(),
            });
        }
    }
    if let Some(c) = compare {
        let other = coilscope_report::input_from(c)?;
        if let (Some(a), Some(b)) = (&input.params.name, &other.params.name) {
            if a != b {
                return Err(format!("--compare {c}: that result is of {b:?}, this one of {a:?}; compare two measurements of the same driver"));
            }
        }
        input.compare = Some(Box::new(other));
    }
    let opts = coilscope_report::ReportOptions { thresholds: th, dt_max: l.max_dt, volts, ..Default::default() };
    let rep = coilscope_report::build(&input, &opts)?;
    let written = coilscope_report::write(&rep, out, opts.png_size)?;
    for w in &rep.warnings {
        eprintln!("warning: the report could not draw {w}");
    }
    println!(
        "report: {} plots, distortion predicted for a sine of {:.2} V RMS ({}){}",
        rep.charts.len(),
        rep.volts,
        if opts.volts.is_some() { "--volts" } else { "the level that takes the cone to 70 % of the reached range" },
        rep.volterra_divergence
            .map(|v| format!(", the Volterra series off the full model by > 1 dB from {v:.2} V"))
            .unwrap_or_default()
    );
    println!(
        "wrote {} and {} files in {}",
        out.display(),
        written.len() - 1,
        coilscope_report::files_dir(out).display()
    );
    Ok(())
}

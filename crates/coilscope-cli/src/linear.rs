//! `linear`: small-signal (Thiele/Small) parameters from a recording or a measured impedance file.

use crate::args::LinearArgs;
use crate::{fit_wiring, parse_chain, parse_effects, print_values, print_warnings, untrusted_if_warned, Failure};
use coilscope_core::small_signal::thiele_small;
use coilscope_io::{read_recording, write_json};
use coilscope_workflow::chain::ChainMode;
use std::path::Path;

pub(crate) fn cmd_linear(a: LinearArgs) -> Result<(), Failure> {
    use coilscope_ident::linear::ScaleMethod;
    use coilscope_workflow::linear::{linear, LinearInput, LinearRequest, Scale};
    let (scale, out) = (a.fit.scale.as_deref(), a.fit.out.as_path());
    let chain = parse_chain(&a.fit.chain)?;
    let wiring = fit_wiring(&a.fit, &chain)?;
    let effects = parse_effects(&a.effects)?;
    let band = a.band.as_deref().map(crate::args::parse_band).transpose()?;
    // The outputs, before the work: the result, and beside it (unless it goes to a device
    // such as /dev/null) the measured impedance as .zma and .csv.
    let beside = coilscope_io::check_outputs(out, &[out.with_extension("zma"), out.with_extension("csv")])
        .map_err(|e| e.to_string())?;
    let (path, is_curve) = match (&a.recording, &a.impedance) {
        (Some(p), None) => (p.clone(), false),
        (None, Some(p)) => (p.clone(), true),
        _ => return Err("give a recording or --impedance FILE (one of them)".into()),
    };
    let origin = path.display().to_string();
    if is_curve && matches!(chain, ChainMode::Calibrated(_)) {
        return Err(Failure::from(format!("{origin}: an impedance curve has no measurement chain to invert (its tool calibrated it); --chain FILE applies to records")));
    }
    // A curve measured across driver and shunt: the shunt is a plain series resistance.
    let read_input = |p: &Path| -> Result<LinearInput, Failure> {
        if is_curve {
            let c = coilscope_io::impedance::read_impedance(p).map_err(|e| e.to_string())?;
            Ok(LinearInput::curve_across_driver(c, wiring, &p.display().to_string())?)
        } else {
            Ok(LinearInput::Record(read_recording(p, scale).map_err(|e| e.to_string())?))
        }
    };
    let mut input = read_input(&path)?;
    if let Some(kind) = &a.enclosure {
        // A record's chain: a calibrated one is undone before the box is fitted (and a
        // shunt's drop); the box fit does not estimate one.
        if let LinearInput::Record(r) = &mut input {
            if matches!(chain, ChainMode::Estimate) {
                return Err(Failure::from(format!("{origin}: --chain auto: the box fit does not estimate a measurement chain; calibrate the card (`coilscope calibrate`) and give --chain FILE, or --chain none")));
            }
            // A calibrated chain inverted, and the shunt's drop taken out with the wiring.
            chain.undo(r, &origin, wiring)?;
        }
        return linear_box(&a, kind, &input, &origin, band, out);
    }
    let has_x = matches!(&input, LinearInput::Record(r) if r.x.is_some());
    let with_mass = if is_curve { a.with_mass_impedance.as_ref() } else { a.with_mass.as_ref() };
    let with_name = if is_curve { "--with-mass-impedance Z2.zma" } else { "--with-mass REC2.wav" };
    // Refuse a missing or doubled scale before spending time on the fit.
    let scale = match (a.mms, a.added_mass, with_mass, has_x) {
        (Some(m), None, None, _) => Scale::Mms(m),
        (None, Some(m), Some(p2), _) => {
            Scale::AddedMass { mass: m, with: Box::new(read_input(p2)?), origin: p2.display().to_string() }
        }
        (None, None, None, true) => Scale::Displacement,
        (None, Some(_), None, _) | (None, None, Some(_), _) => {
            return Err(format!("--added-mass MASS and {with_name} go together").into())
        }
        (Some(_), _, _, _) => return Err(format!("give one scale: --mms, or --added-mass with {with_name}").into()),
        (None, None, None, false) => {
            let x = if is_curve { "" } else { ", or record a displacement channel (3)" };
            return Err(Failure::from(format!(
                "{origin}: no absolute scale: give --mms MASS (15.3g, or 15.3g±0.3g with its sd), or --added-mass MASS {with_name}{x}"
            )));
        }
    };
    let live = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let progress = |s: &coilscope_ident::lm::LmState| {
        if live && (s.iteration.is_multiple_of(5) || s.converged) {
            eprint!("\r  fitting impedance: iteration {:3}, residual {:.3e}   ", s.iteration, (2.0 * s.cost).sqrt());
        }
    };
    let req = LinearRequest { origin: origin.clone(), effects, chain, wiring, sd: a.fit.sd, band, volts: a.volts };
    let done = linear(input.clone(), scale, &req, progress)?;
    if live {
        eprintln!();
    }
    for d in &done.detected {
        eprintln!("chain: estimated, as the record shows one: {d}");
    }
    print_warnings(&done.warnings);
    let (fit, params, result, x_range) = (&done.fit, &done.params, &done.result, done.x_range);
    write_json(out, result).map_err(|e| e.to_string())?;
    let csv = out.with_extension("csv");
    let mut wrote = vec![out.display().to_string()];
    if !beside {
        eprintln!("note: {} is a device: no .zma or .csv is written beside it", out.display());
    }
    if !is_curve && beside {
        let zma = out.with_extension("zma");
        let (f, z) = fit.h1.coherent();
        let comments = vec![
            format!("coilscope linear: H1 impedance of {origin} (coherent bins)"),
            "Data: Impedance (ohms), Phase (degrees)".to_string(),
        ];
        coilscope_io::impedance::write_zma(
            &zma,
            &coilscope_io::impedance::ImpedanceCurve { f, z, comments, magnitude_only: false },
        )
        .map_err(|e| e.to_string())?;
        wrote.push(zma.display().to_string());
    }
    if beside {
        coilscope_io::atomic_write(&csv, coilscope_ident::linear::impedance_csv(&fit.h1, fit).as_bytes())
            .map_err(|e| e.to_string())?;
        wrote.push(csv.display().to_string());
    }
    let ts = thiele_small(params);
    let u = &result.uncertainty;
    let pm = |k: &str, scale: f64| u.value(k).map(|v| format!("+- {:.2e}", v * scale)).unwrap_or_default();
    match &input {
        LinearInput::Record(r) => {
            println!("coilscope linear: {} ({:.2} s at {} Hz)", path.display(), r.u.len() as f64 / r.fs as f64, r.fs);
            println!(
                "  fit {:.1} .. {:.0} Hz, {} bins, residual {:.3e} (current, relative RMS), {} iterations",
                fit.band[0], fit.band[1], fit.bins, fit.residual_rel, fit.iterations
            );
        }
        LinearInput::Curve(c) => {
            println!(
                "coilscope linear: {} (impedance file, {} points, {:.1} .. {:.0} Hz)",
                path.display(),
                c.f.len(),
                c.f[0],
                c.f[c.f.len() - 1]
            );
            println!(
                "  fit {:.1} .. {:.0} Hz, {} points, residual {:.3e} (impedance, relative RMS), {} iterations",
                fit.band[0], fit.band[1], fit.bins, fit.residual_rel, fit.iterations
            );
            if let Some(note) = &result.fit.band_note {
                println!("  band: {note}");
            }
            if let Some(note) = &result.fit.phase_note {
                println!("  phase: {note}");
            }
        }
    }
    let scale_text = match &done.method {
        ScaleMethod::Mms { sd_rel } if *sd_rel > 0.0 => format!("Mms given, +- {:.2} %", 100.0 * sd_rel),
        ScaleMethod::Mms { .. } => "Mms given".to_string(),
        ScaleMethod::AddedMass { added, fs_with, .. } => {
            format!("added mass {:.3} g, fs with mass {:.3} Hz", added * 1e3, fs_with)
        }
        ScaleMethod::Displacement { delay_samples, mms_sd_rel } if delay_samples.abs() >= 0.125 => format!(
            "displacement channel (Mms +- {:.2} %; the channel {} the current by {:.2} samples, the sensor's delay, taken out)",
            100.0 * mms_sd_rel,
            if *delay_samples > 0.0 { "lags" } else { "leads" },
            delay_samples.abs()
        ),
        ScaleMethod::Displacement { mms_sd_rel, .. } => {
            format!("displacement channel (Mms +- {:.2} %; no delay against the current)", 100.0 * mms_sd_rel)
        }
    };
    println!("  scale: {scale_text}");
    if let (Some(c), LinearInput::Record(r)) = (&fit.chain, &input) {
        println!("  chain: {}", c.to_chain().describe_fitted(r.fs as f64));
    }
    println!(
        "  model: {} (tried: {})",
        fit.effects.model_name(),
        fit.tried.iter().map(|(m, r)| format!("{m} {r:.2e}")).collect::<Vec<_>>().join(", ")
    );
    print_values(params, u, &[]);
    println!("  {:<6} {:>12} {:<5} {}", "fs", format!("{:.3}", ts.fs), "Hz", pm("fs", 1.0));
    println!(
        "  {:<6} {:>12}      (at fs, with creep's loss: Rms at fs {:.4} kg/s)",
        "Qms",
        format!("{:.4}", ts.qms),
        ts.rms_fs
    );
    println!("  {:<6} {:>12}", "Qes", format!("{:.4}", ts.qes));
    println!("  {:<6} {:>12}", "Qts", format!("{:.4}", ts.qts));
    if let Some(v) = ts.vas {
        println!("  {:<6} {:>12} {:<5}", "Vas", format!("{:.3}", v * 1e3), "l");
    }
    if !is_curve || a.volts.is_some() {
        println!("  x reached {:+.3} .. {:+.3} mm", x_range[0] * 1e3, x_range[1] * 1e3);
    } else {
        println!("  x reached: unknown (give --volts, the measurement's RMS voltage)");
    }
    println!("  wrote {}", wrote.join(", "));
    untrusted_if_warned(&done.warnings, out)
}

/// `linear --enclosure`: the box from the driver's impedance in it, the driver's set held.
fn linear_box(
    a: &LinearArgs,
    kind: &str,
    input: &coilscope_workflow::linear::LinearInput,
    origin: &str,
    band: Option<[f64; 2]>,
    out: &Path,
) -> Result<(), Failure> {
    use coilscope_workflow::enclosure::{fit_enclosure, BoxRequest};
    if a.mms.is_some() || a.added_mass.is_some() || a.with_mass.is_some() || a.with_mass_impedance.is_some() {
        return Err(Failure::from(
            "--enclosure holds the driver's own set (--driver), scale included: --mms and --added-mass do not apply",
        ));
    }
    let choice = coilscope_ident::box_fit::BoxChoice::parse(kind)?;
    let spec = a.driver.as_deref().ok_or("--enclosure needs --driver: the driver's own parameter set")?;
    let mut driver = load_driver(spec)?;
    if let Some(sd) = a.fit.sd {
        driver.sd = Some(sd);
    }
    let req = BoxRequest { origin: origin.to_string(), choice, sp: a.sp, band };
    let done = fit_enclosure(input, &driver, &req)?;
    print_warnings(&done.warnings);
    write_json(out, &done.result).map_err(|e| e.to_string())?;
    let e = &done.fit.enclosure;
    println!("coilscope linear: {origin}, the box of {}", driver.name.as_deref().unwrap_or(spec));
    println!(
        "  fit {:.1} .. {:.0} Hz, {} points, residual {:.3e} (impedance, relative RMS)",
        done.band[0], done.band[1], done.points, done.fit.residual
    );
    if done.fit.why.is_empty() {
        println!("  box: {} (as asked)", e.type_name());
    } else {
        println!("  box: {} (auto: {})", e.type_name(), done.fit.why);
    }
    print_values(&done.params, &done.result.uncertainty, &[]);
    let p = &done.params;
    println!(
        "  {:<6} {:>12} {:<5} (the box's tuning: {})",
        "f_t",
        format!("{:.3}", e.tuning_hz(p.kms.c[0], p.mms, p.sd.unwrap_or(f64::NAN))),
        "Hz",
        match e.kind {
            coilscope_core::enclosure::BoxKind::Closed => "the system's resonance",
            coilscope_core::enclosure::BoxKind::Vented { .. } => "the port's fb",
            coilscope_core::enclosure::BoxKind::PassiveRadiator { .. } => "the radiator on the box air",
        }
    );
    println!("  wrote {}", out.display());
    untrusted_if_warned(&done.warnings, out)
}

/// A driver's own set: an embedded driver, a parameter file, or a result file's `parameters`.
fn load_driver(spec: &str) -> Result<coilscope_core::Parameters, Failure> {
    let path = Path::new(spec);
    if path.is_file() {
        let text = std::fs::read_to_string(path).map_err(|e| format!("{spec}: cannot read ({e})"))?;
        if let Ok(v) = serde_json::from_str::<serde_json::Value>(&text) {
            if v.get("format").and_then(|f| f.as_str()) == Some(coilscope_core::result::RESULT_FORMAT) {
                let r = coilscope_core::result::ResultFile::from_json_value(v, spec).map_err(|e| e.to_string())?;
                return Ok(r.parameters);
            }
        }
    }
    coilscope_io::load_parameters(spec).map_err(|e| Failure::from(e.to_string()))
}

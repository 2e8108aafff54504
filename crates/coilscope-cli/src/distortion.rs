//! `distortion`: the predicted distortion of a parameter set, by simulation to the steady state.

use crate::args::DistortionArgs;
use crate::print_json;

pub(crate) fn cmd_distortion(a: DistortionArgs) -> Result<(), String> {
    use coilscope_analysis::db;
    use coilscope_analysis::distortion::{self as d, SteadyOptions};
    let input = coilscope_report::input_from(&a.params)?;
    let p = &input.params;
    if !(a.temp_rise.is_finite() && (0.0..=300.0).contains(&a.temp_rise)) {
        return Err(format!("--temp-rise {} K is not valid (0 .. 300 K)", a.temp_rise));
    }
    let opts = SteadyOptions { dt_coil: a.temp_rise, ..SteadyOptions::default() };
    let e = |e: coilscope_analysis::AnalysisError| e.to_string();
    let name = p.name.clone().unwrap_or_else(|| a.params.clone());
    let out = a.output.name();
    let volts = a.volts.unwrap_or(f64::NAN);
    if a.multitone {
        let band = a.band.as_deref().map(crate::args::parse_band).transpose()?.unwrap_or([20.0, 10_000.0]);
        let m = d::multitone(p, band[0], band[1], a.tones, volts, a.output, a.seed, &opts).map_err(e)?;
        if a.json {
            print_json(&m.to_json());
        } else {
            println!("{name}: {} tones {:.0} .. {:.0} Hz, {:.3} V RMS, {out}", m.tones.len(), band[0], band[1], volts);
            println!("  multitone total distortion {:.2} dB ({:.3} %)", db(m.mtd), 100.0 * m.mtd);
            println!(
                "  DC displacement {:+.4} mm, x {:+.3} .. {:+.3} mm",
                m.x_dc * 1e3,
                m.x_peak[0] * 1e3,
                m.x_peak[1] * 1e3
            );
        }
        return Ok(());
    }
    if let (Some(_), Some(_)) = (&a.sweep, a.freq) {
        return Err("--sweep F_LO F_HI sets the frequencies itself: drop --freq".into());
    }
    // A frequency sweep needs no --freq (it runs from F_LO to F_HI).
    let freq = a.freq.or(a.sweep.as_ref().map(|b| b[0])).ok_or(
        "--freq F is required (the sine, or the low tone of a two-tone); or use --multitone or --sweep F_LO F_HI",
    )?;
    if let Some(f2) = a.freq2 {
        let im = d::intermod(p, freq, f2, volts, a.ratio, a.output, &opts).map_err(e)?;
        if a.json {
            print_json(&im.to_json());
        } else {
            println!(
                "{name}: two-tone {:.2} Hz + {:.2} Hz (f2/f1 amplitude {}), {:.3} V RMS, {out}",
                im.f1, im.f2, im.amplitude_ratio, volts
            );
            println!("  d2 (f2 +- f1)   {:8.2} dB  {:8.4} %", db(im.d2), 100.0 * im.d2);
            println!("  d3 (f2 +- 2f1)  {:8.2} dB  {:8.4} %", db(im.d3), 100.0 * im.d3);
            for (l, f, r) in &im.lines {
                println!("    {l:<7} {f:9.2} Hz {:8.2} dB", db(*r));
            }
            println!(
                "  DC displacement {:+.4} mm, x {:+.3} .. {:+.3} mm",
                im.x_dc * 1e3,
                im.x_peak[0] * 1e3,
                im.x_peak[1] * 1e3
            );
        }
        return Ok(());
    }
    if let Some(levels) = &a.levels {
        let rows = d::level_sweep(p, freq, levels, a.output, &opts).map_err(e)?;
        let div = d::divergence_level(&rows, 1.0);
        if a.json {
            let v: Vec<_> = rows.iter().map(|r| serde_json::json!({"volts_rms": r.volts, "full": r.full.to_json(), "volterra": {"HD2": r.volterra.0, "HD3": r.volterra.1, "x_dc": r.volterra_x_dc}})).collect();
            print_json(&serde_json::json!({"freq": freq, "rows": v, "volterra_divergence_1dB_volts": div}));
        } else {
            println!("{name}: sine {freq} Hz, {out}; full model against the 3rd-order Volterra series");
            println!("  {:>9} {:>9} {:>9} {:>11} {:>11}", "V RMS", "HD2 dB", "HD3 dB", "HD2 Volt.", "HD3 Volt.");
            for r in &rows {
                println!(
                    "  {:9.3} {:9.2} {:9.2} {:11.2} {:11.2}",
                    r.volts,
                    db(r.full.hd(2)),
                    db(r.full.hd(3)),
                    db(r.volterra.0),
                    db(r.volterra.1)
                );
            }
            match div {
                Some(v) => println!("  the Volterra series is off by more than 1 dB from {v:.3} V"),
                None => println!("  the Volterra series stays within 1 dB over these levels"),
            }
        }
        return Ok(());
    }
    let freqs = match &a.sweep {
        Some(b) => d::log_frequencies(b[0], b[1], 3),
        None => vec![freq],
    };
    let sweep = coilscope_workflow::distortion::sine(p, &freqs, volts, a.output, a.temp_rise)?;
    if a.json {
        let v: Vec<_> = sweep.iter().map(|s| s.to_json()).collect();
        print_json(&if v.len() == 1 { v[0].clone() } else { serde_json::Value::Array(v) });
        return Ok(());
    }
    println!("{name}: sine, {:.3} V RMS, {out}", volts);
    for s in &sweep {
        let (an, t) = (&s.analysis, &s.analysis.total);
        let (v2, v3) = s.volterra_hd();
        println!(
            "  {:.2} Hz: x {:+.3} .. {:+.3} mm, DC displacement {:+.4} mm",
            t.freq,
            t.x_peak[0] * 1e3,
            t.x_peak[1] * 1e3,
            t.x_dc * 1e3
        );
        println!("    {:<10} {:>9} {:>9} {:>9}", "", "HD2 dB", "HD3 dB", "THD dB");
        println!("    {:<10} {:9.2} {:9.2} {:9.2}", "total", db(t.hd(2)), db(t.hd(3)), db(t.thd()));
        for (nl, h) in &an.parts {
            println!(
                "    {:<10} {:9.2} {:9.2} {:9.2}",
                format!("{} only", nl.key()),
                db(h.hd(2)),
                db(h.hd(3)),
                db(h.thd())
            );
        }
        println!("    {:<10} {:9.2} {:9.2}", "Volterra", db(v2), db(v3));
        println!(
            "    dominant: {}; the parts' HD2 lines add up to the total within {:.1} %",
            an.dominant().name(),
            100.0 * an.sum_mismatch(2)
        );
    }
    Ok(())
}

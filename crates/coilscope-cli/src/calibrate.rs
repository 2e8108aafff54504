//! `calibrate`: the measurement chain from a record of a known resistor or of a loopback.

use crate::Failure;
use coilscope_core::chain::SenseWiring;
use coilscope_io::{read_recording, write_json};
use std::path::Path;

pub(crate) fn cmd_calibrate(
    path: &Path,
    resistor: Option<f64>,
    loopback: bool,
    wiring: SenseWiring,
    scale: Option<&[f64]>,
    out: &Path,
) -> Result<(), Failure> {
    coilscope_io::check_writable(out).map_err(|e| e.to_string())?;
    let origin = path.display().to_string();
    let r = match (resistor, loopback) {
        (Some(r), false) if r.is_finite() && r > 0.0 && r < 1e6 => r,
        (Some(r), false) => {
            return Err(Failure::from(format!("--resistor {r}: give the resistor's measured value in ohm (> 0)")))
        }
        _ => 1.0,
    };
    let rec = read_recording(path, scale).map_err(|e| e.to_string())?;
    let fs = rec.fs as f64;
    // Across resistor and shunt, the voltage channel sees both.
    let cal = coilscope_ident::calibrate::calibrate(&rec.u, &rec.i, fs, r + wiring.series_ohm(), &origin)?;
    let mut chain = cal.chain.clone();
    if !loopback {
        wiring.mark(&mut chain);
    }
    let info = serde_json::json!({
        "format": "coilscope.chain/1",
        "record": origin,
        "fs_hz": fs,
        "load": if loopback { "loopback".to_string() } else { format!("resistor {r} ohm") },
        "band_hz": cal.band,
        "bins": cal.bins,
        "residual_in_noise": cal.residual_in_noise,
        "residual_rel": cal.residual_rel,
    });
    for (k, v) in info.as_object().expect("an object") {
        chain.other.insert(k.clone(), v.clone());
    }
    write_json(out, &chain).map_err(|e| e.to_string())?;
    let sd = |k: &str| chain.sd.get(k).copied().unwrap_or(f64::NAN);
    println!(
        "coilscope calibrate: {} ({:.1} s at {} Hz, {})",
        origin,
        rec.u.len() as f64 / fs,
        rec.fs,
        if loopback { "loopback".to_string() } else { format!("resistor {r} ohm") }
    );
    println!(
        "  fit {:.2} .. {:.0} Hz, {} bins, residual {:.2}x the noise ({:.2e} relative)",
        cal.band[0], cal.band[1], cal.bins, cal.residual_in_noise, cal.residual_rel
    );
    println!(
        "  current channel {:+.4} +- {:.4} samples late ({:+.3} us), gain {:.5} +- {:.1e} against the voltage's",
        chain.delay_i * fs,
        sd("delay_i") * fs,
        chain.delay_i * 1e6,
        chain.gain_i.unwrap_or(1.0),
        sd("gain_i")
    );
    if chain.fitted.iter().any(|k| k == "hp_u") {
        println!(
            "  AC coupling: voltage {:.3} +- {:.3} Hz, current {:.3} +- {:.3} Hz",
            chain.hp_u,
            sd("hp_u"),
            chain.hp_i,
            sd("hp_i")
        );
    } else if let Some(n) = chain.other.get("note").and_then(|v| v.as_str()) {
        println!("  AC coupling: {n}");
    }
    println!("  wrote {} (use it as --chain {})", out.display(), out.display());
    Ok(())
}

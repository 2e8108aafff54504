//! `simulate`: a virtual transducer driven by a generated or given signal, written as a recording.

use crate::args::{ExcitationKind, SimulateArgs};
use crate::iec_noise;
use coilscope_core::excitation::{crest_factor, generate, Excitation, SignalSpec};
use coilscope_io::{load_parameters, read_voltage, write_json, write_recording};
use coilscope_workflow::chain::load_chain;
use coilscope_workflow::simulate::{record, RecordRequest};
use serde_json::json;
use std::path::{Path, PathBuf};

/// Where the summary of a recording goes: `NAME.info.json` beside `NAME.wav`.
fn info_path(out: &Path) -> PathBuf {
    let stem = out.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "recording".into());
    out.with_file_name(format!("{stem}.info.json"))
}

pub(crate) fn cmd_simulate(a: SimulateArgs) -> Result<(), String> {
    // The outputs, before the work: the recording and, unless it goes to a device such as
    // /dev/null, its description beside it.
    let info_beside = coilscope_io::check_outputs(&a.out, &[info_path(&a.out)]).map_err(|e| e.to_string())?;
    let mut params = a.world.apply(load_parameters(&a.driver).map_err(|e| e.to_string())?);
    if let Some(path) = &a.enclosure {
        params.enclosure = Some(coilscope_io::load_enclosure(path).map_err(|e| e.to_string())?);
        params.validate(&format!("{} in the box of {}", a.driver, path.display())).map_err(|e| e.to_string())?;
    }
    let (fs, u, what) = match &a.input {
        Some(path) => {
            let (fs, mut u) = read_voltage(path, a.scale.map(|s| vec![s]).as_deref()).map_err(|e| e.to_string())?;
            if let Some(v) = a.volts {
                let r = coilscope_core::simulate::rms(&u);
                if r == 0.0 {
                    return Err(format!(
                        "{}: the voltage channel is silent; cannot scale it to {v} V RMS",
                        path.display()
                    ));
                }
                u.iter_mut().for_each(|x| *x *= v / r);
            }
            (fs as f64, u, json!({"input": path.display().to_string()}))
        }
        None => {
            let volts = a.volts.ok_or("--volts RMS is required with a generated excitation (e.g. --volts 2)")?;
            let band = match &a.band {
                Some(b) => crate::args::parse_band(b).map(|[lo, hi]| (lo, hi))?,
                None => (10.0, (8000.0f64).min(0.45 * a.rate as f64)),
            };
            let exc = match a.excitation {
                ExcitationKind::Noise => iec_noise(a.crest),
                ExcitationKind::Pink => Excitation::Pink { f_lo: band.0, f_hi: band.1, crest: a.crest },
                ExcitationKind::Sine => Excitation::Sine { freq: a.freq },
                ExcitationKind::Multitone => {
                    Excitation::Multitone { f_lo: band.0, f_hi: band.1, count: a.tones, crest: a.crest }
                }
                ExcitationKind::Sweep => Excitation::Sweep { f_lo: band.0, f_hi: band.1 },
                ExcitationKind::Readable => {
                    Excitation::Readable { f_lo: band.0, f_hi: band.1, count: a.tones, crest: a.crest }
                }
            };
            let spec = SignalSpec { fs: a.rate as f64, seconds: a.seconds, rms: volts, fade: a.fade, seed: a.seed };
            let u = generate(&exc, &spec)?;
            let cf = crest_factor(&u);
            (
                a.rate as f64,
                u,
                json!({"excitation": format!("{exc:?}"), "rms": volts, "seconds": a.seconds, "crest_factor": cf, "seed": a.seed}),
            )
        }
    };
    // The channels: the wiring, then the chain (the sensor noise after both).
    let req = RecordRequest {
        wiring: a.wiring,
        chain: a.chain.as_deref().map(load_chain).transpose()?,
        snr_db: a.snr_db,
        laser: a.laser,
        seed: a.seed,
    };
    let sim = record(&params, fs, &u, &req)?;
    write_recording(&a.out, &sim.recording).map_err(|e| e.to_string())?;
    let info = sim.info(&params, &a.driver, what, &req);
    let (trace, box_peaks) = (&sim.trace, &sim.box_peaks);
    let s = trace.summary();
    let info_file = info_path(&a.out);
    if info_beside {
        write_json(&info_file, &info).map_err(|e| e.to_string())?;
    }

    let name = params.name.as_deref().unwrap_or(&a.driver);
    println!(
        "coilscope simulate: {name}, {:.2} s at {} Hz ({} scheme, {} step{} per sample)",
        u.len() as f64 / fs,
        fs,
        trace.scheme.name(),
        trace.substeps,
        if trace.substeps == 1 { "" } else { "s" }
    );
    let range = params
        .x_range
        .map(|[lo, hi]| format!(" ({:.0} % / {:.0} % of x_range)", 100.0 * s.x_min / lo, 100.0 * s.x_max / hi))
        .unwrap_or_default();
    println!("  peak excursion   {:+.3} mm .. {:+.3} mm{range}", s.x_min * 1e3, s.x_max * 1e3);
    println!("  voltage, current {:.3} V RMS, {:.3} A RMS", s.u_rms, s.i_rms);
    println!("  electrical power {:.3} W (mean u i)", s.p_mean);
    println!("  voice coil       +{:.3} K at the end (max +{:.3} K), magnet +{:.4} K", s.dt_end, s.dt_max, s.dtm_end);
    if let (Some(e), Some(peaks)) = (&params.enclosure, box_peaks) {
        let shown: Vec<String> = peaks
            .iter()
            .map(|(k, v)| match *k {
                "p_box_peak_Pa" => format!("box pressure {v:.0} Pa"),
                "port_air_velocity_peak_m_s" => format!("port air {v:.2} m/s"),
                _ => format!("radiator {:.3} mm", v * 1e3),
            })
            .collect();
        println!("  {:<16} {} ({}: peaks)", "box", shown.join(", "), e.type_name());
    }
    if trace.range_excess > 0.0 {
        println!("  warning: x exceeded x_range by {:.3} mm (parameters extrapolated)", trace.range_excess * 1e3);
    }
    if info_beside {
        println!("  wrote {} and {}", a.out.display(), info_file.display());
    } else {
        println!("  wrote {} (a device: no description beside it)", a.out.display());
    }
    Ok(())
}

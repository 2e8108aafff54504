//! `drivers` and `check`: the embedded drivers, and a parameter set's small-signal figures.

use coilscope_core::small_signal::thiele_small;
use coilscope_core::{embedded_driver, embedded_driver_names, Parameters};

fn resonance(p: &Parameters) -> f64 {
    thiele_small(p).fs
}

pub(crate) fn print_params(p: &Parameters) {
    let ts = thiele_small(p);
    println!("{}", p.name.as_deref().unwrap_or("(unnamed)"));
    println!(
        "  Re {:.3} ohm, Le(0) {:.4} mH, Bl(0) {:.3} T m, Kms(0) {:.1} N/m, Mms {:.3} g, Rms {:.3} kg/s",
        p.re,
        p.le.c[0] * 1e3,
        p.bl.c[0],
        p.kms.c[0],
        p.mms * 1e3,
        p.rms
    );
    if let Some((l2, r2)) = &p.l2r2 {
        println!("  L2 {:.4} mH, R2 {:.3} ohm", l2.c[0] * 1e3, r2.c[0]);
    }
    if let Some((l3, r3)) = p.l3r3 {
        println!("  L3 {:.4} mH, R3 {:.3} ohm", l3 * 1e3, r3);
    }
    if let Some(c) = &p.creep {
        println!("  creep lambda {:.4} (LOG, reference {:.2} Hz)", c.lambda, p.creep_f_ref().unwrap_or(0.0));
    }
    println!(
        "  fs {:.2} Hz, Qms {:.3}, Qes {:.3}, Qts {:.3}, Rms at fs {:.3} kg/s (with creep's loss)",
        ts.fs, ts.qms, ts.qes, ts.qts, ts.rms_fs
    );
    match p.x_range {
        Some([lo, hi]) => println!("  x_range {:.2} .. {:.2} mm", lo * 1e3, hi * 1e3),
        None => println!("  x_range not given"),
    }
    println!("  electrical time constant Le/(Re+R2) >= {:.2} us", p.min_electrical_time_constant() * 1e6);
}

pub(crate) fn cmd_drivers() -> Result<(), String> {
    for name in embedded_driver_names() {
        let p = embedded_driver(name).ok_or("embedded driver missing")?;
        let [lo, hi] = p.x_range.unwrap_or([0.0, 0.0]);
        println!(
            "{name:<15} {:<40} fs {:6.2} Hz  x_range {:+.1} .. {:+.1} mm",
            p.name.as_deref().unwrap_or(""),
            resonance(&p),
            lo * 1e3,
            hi * 1e3
        );
    }
    Ok(())
}

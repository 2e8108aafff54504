//! Where `identify`'s time goes, stage by stage: the benchmark's record (8 s at 48 kHz, pink
//! noise to 85 % of x_range, heating, 70 dB) identified with an observer that prints every LM
//! iteration's wall time, stage, current error, number of unknowns, cost decrease, gain ratio
//! and damping.
//!
//! ```text
//! cargo run --release -p coilscope-ident --example stages -- [DRIVER] [auto] [chain] [slow-lr3] [clean]
//! ```
//!
//! `DRIVER`: an embedded driver (default `sb17cac35-4`) or one of `testdata/drivers`
//! (`microspeaker-0g1`, ...), or a recording (`.wav`, e.g. one of `../shared/recordings`;
//! `--mms` is taken from the embedded driver whose name begins the file's name); `auto`: choose the effects (creep,
//! LR-3, Le(i), Rms(v)) on held-out data as `identify` does by default, instead of LR-2;
//! `chain`: record through a sound card (current 0.3 sample late, AC coupling at 2 Hz on the
//! voltage and 4 Hz on the current, offsets of 0.5 % of each channel's peak, 50 Hz hum at
//! -60 dB) and estimate the chain with the driver (`--chain auto`); `slow-lr3`: give the
//! driver a second branch of half its L2 at twice its time constant (the
//! `branch_order` test's record; implies `auto`); `clean`: no sensor noise.
//! The profile by function is `perf record -g` on the `identify` benchmark.

use coilscope_core::chain::{Chain, Hum};
use coilscope_core::excitation::{add_sensor_noise, generate, Excitation, SignalSpec};
use coilscope_core::simulate::{gain_for_peak, SimOptions};
use coilscope_core::{embedded_driver, Parameters};
use coilscope_ident::large::{identify, IdentifyOptions};
use coilscope_ident::linear::{Effects, EffectsChoice};
use std::time::Instant;

fn main() {
    let name = std::env::args().nth(1).unwrap_or_else(|| "sb17cac35-4".into());
    let args: Vec<String> = std::env::args().skip(2).collect();
    let slow_lr3 = args.iter().any(|a| a == "slow-lr3");
    let auto = slow_lr3 || args.iter().any(|a| a == "auto");
    let chain = args.iter().any(|a| a == "chain");
    let clean = args.iter().any(|a| a == "clean");
    if name.ends_with(".wav") {
        return recording(&name, chain);
    }
    let fs = 48000.0;
    // An embedded driver, or one of testdata/drivers (microspeaker-0g1, microspeaker-2g7,
    // large-coil).
    let path = format!("{}/../../testdata/drivers/{name}.json", env!("CARGO_MANIFEST_DIR"));
    let Some(p) =
        embedded_driver(&name).or_else(|| Parameters::from_json_str(&std::fs::read_to_string(&path).ok()?, &path).ok())
    else {
        eprintln!("{name}: not an embedded driver (see `coilscope drivers`) nor one of testdata/drivers");
        std::process::exit(2);
    };
    let p = match (slow_lr3, p.l2r2.as_ref().map(|(l, r)| (l.eval(0.0), r.eval(0.0)))) {
        (true, Some((l2, r2))) => Parameters { l3r3: Some((0.5 * l2, 0.5 * l2 / (2.0 * l2 / r2))), ..p },
        _ => p,
    };
    let [lo, hi] = p.x_range.expect("embedded drivers have an x_range");
    let unit = generate(
        &Excitation::Pink { f_lo: 10.0, f_hi: 8000.0, crest: Some(3.0) },
        &SignalSpec { fs, seconds: 8.0, rms: 1.0, fade: 0.05, seed: 1 },
    )
    .expect("valid signal");
    let (_, tr) =
        gain_for_peak(&p, fs, &unit, 0.85 * hi.min(-lo), &SimOptions::default()).expect("the driver simulates");
    let (mut u, mut i) = (tr.u, tr.i);
    if chain {
        let peak = |v: &[f64]| v.iter().fold(0.0f64, |a, x| a.max(x.abs()));
        let (pu, pi) = (peak(&u), peak(&i));
        let card = Chain {
            delay_i: 0.3 / fs,
            hp_u: 2.0,
            hp_i: 4.0,
            dc_u: 5e-3 * pu,
            dc_i: 5e-3 * pi,
            hum: Some(Hum { f: 50.0, u: vec![[1e-3 * pu, 0.3]], i: vec![[1e-3 * pi, 1.1]] }),
            ..Default::default()
        };
        (u, i) = card.apply(&u, &i, fs);
    }
    if !clean {
        add_sensor_noise(&mut u, 70.0, 1, "sensor-noise/voltage");
        add_sensor_noise(&mut i, 70.0, 1, "sensor-noise/current");
    }
    let effects = if auto { EffectsChoice::Auto } else { EffectsChoice::Fixed(Effects::NONE) };
    run(&u, &i, fs, &name, &IdentifyOptions { mms: p.mms, effects, chain, ..Default::default() });
}

/// `identify` of the recording at `path` (the effects chosen; `chain`: `--chain auto`), with
/// the mass of the embedded driver whose name begins the file's name.
fn recording(path: &str, chain: bool) {
    let rec = coilscope_io::read_recording(std::path::Path::new(path), None).unwrap_or_else(|e| panic!("{e}"));
    let file = std::path::Path::new(path).file_name().map(|f| f.to_string_lossy().to_string()).unwrap_or_default();
    let mms = coilscope_core::embedded_driver_names()
        .into_iter()
        .find(|d| file.starts_with(d))
        .and_then(embedded_driver)
        .map(|p| p.mms)
        .unwrap_or_else(|| panic!("{file}: no embedded driver names it"));
    run(&rec.u, &rec.i, rec.fs as f64, &file, &IdentifyOptions { mms, chain, ..Default::default() });
}

/// `identify` with an observer that prints every iteration.
fn run(u: &[f64], i: &[f64], fs: f64, name: &str, opts: &IdentifyOptions) {
    let t0 = Instant::now();
    let (mut last, mut last_cpu) = (0.0, cpu_seconds());
    let fit = identify(u, i, fs, name, opts, |pr| {
        let (t, cpu) = (t0.elapsed().as_secs_f64(), cpu_seconds());
        let s = pr.state;
        // The cores' use since the last line: CPU time over wall time (200 % = both busy).
        let used = cpu
            .zip(last_cpu)
            .map_or(String::new(), |(c, l)| format!(" cpu {:3.0} %", 100.0 * (c - l) / (t - last).max(1e-9)));
        println!(
            "{t:7.3} s (+{:.3}{used}) {:?} it {} error {:.3e} unknowns {} decrease {:.2e} gain ratio {:.3} damping {:.1e} gn_left {:.2e}",
            t - last,
            pr.stage,
            s.iteration,
            pr.residual_rel,
            s.theta.len(),
            s.last_decrease,
            s.gain_ratio,
            s.step_lambda,
            s.gn_left
        );
        (last, last_cpu) = (t, cpu);
    });
    match fit {
        Ok(f) => {
            println!(
                "total {:.3} s: order {}, model {}, sub-steps per sample {:?} (residual, Jacobian)",
                t0.elapsed().as_secs_f64(),
                f.order,
                f.layout.effects.model_name(),
                f.substeps
            );
            for t in f.models_tried() {
                let before =
                    t.validation_rel_before.map_or(String::new(), |b| format!(" (went on alone from {b:.4e})"));
                println!("  {}: validation {:?}{before}, screen gain {:?}", t.model, t.validation_rel, t.screen_gain);
            }
        }
        Err(e) => println!("total {:.3} s: {e}", t0.elapsed().as_secs_f64()),
    }
}

/// The process's CPU time so far (user + system, s), from `/proc/self/stat` (Linux; `None`
/// elsewhere). Its resolution is the clock tick (10 ms).
fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the command name (which is in parentheses): utime and stime are the
    // 14th and 15th fields of the line, the 12th and 13th after ") ".
    let rest = &stat[stat.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0)
}

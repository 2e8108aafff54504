//! Where `identify`'s time goes, stage by stage: the benchmark's record (8 s at 48 kHz, pink
//! noise to 85 % of x_range, heating, 70 dB) identified with an observer that prints every LM
//! iteration's wall time, stage, current error, number of unknowns, cost decrease, gain ratio
//! and damping.
//!
//! ```text
//! cargo run --release -p coilscope-ident --example stages -- [DRIVER] [auto]
//! ```
//!
//! `DRIVER`: an embedded driver (default `sb17cac35-4`); `auto`: choose the effects (creep,
//! LR-3, Le(i), Rms(v)) on held-out data as `identify` does by default, instead of LR-2.
//! The profile by function is `perf record -g` on the `identify` benchmark.

use coilscope_core::embedded_driver;
use coilscope_core::excitation::{add_sensor_noise, generate, Excitation, SignalSpec};
use coilscope_core::simulate::{gain_for_peak, SimOptions};
use coilscope_ident::large::{identify, IdentifyOptions};
use coilscope_ident::linear::{Effects, EffectsChoice};
use std::time::Instant;

fn main() {
    let name = std::env::args().nth(1).unwrap_or_else(|| "sb17cac35-4".into());
    let auto = std::env::args().nth(2).is_some_and(|a| a == "auto");
    let fs = 48000.0;
    let Some(p) = embedded_driver(&name) else {
        eprintln!("{name}: not an embedded driver (see `coilscope drivers`)");
        std::process::exit(2);
    };
    let [lo, hi] = p.x_range.expect("embedded drivers have an x_range");
    let unit = generate(&Excitation::Pink { f_lo: 10.0, f_hi: 8000.0, crest: Some(3.0) }, &SignalSpec { fs, seconds: 8.0, rms: 1.0, fade: 0.05, seed: 1 }).expect("valid signal");
    let (_, tr) = gain_for_peak(&p, fs, &unit, 0.85 * hi.min(-lo), &SimOptions::default()).expect("the driver simulates");
    let (mut u, mut i) = (tr.u, tr.i);
    add_sensor_noise(&mut u, 70.0, 1, "sensor-noise/voltage");
    add_sensor_noise(&mut i, 70.0, 1, "sensor-noise/current");
    let effects = if auto { EffectsChoice::Auto } else { EffectsChoice::Fixed(Effects::NONE) };
    let t0 = Instant::now();
    let mut last = 0.0;
    let fit = identify(&u, &i, fs, &name, &IdentifyOptions { mms: p.mms, effects, ..Default::default() }, |pr| {
        let t = t0.elapsed().as_secs_f64();
        let s = pr.state;
        println!(
            "{t:7.3} s (+{:.3}) {:?} it {} error {:.3e} unknowns {} decrease {:.2e} gain ratio {:.3} damping {:.1e}",
            t - last,
            pr.stage,
            s.iteration,
            pr.residual_rel,
            s.theta.len(),
            s.last_decrease,
            s.gain_ratio,
            s.step_lambda
        );
        last = t;
    });
    match fit {
        Ok(f) => println!("total {:.3} s: order {}, model {}", t0.elapsed().as_secs_f64(), f.order, f.layout.effects.model_name()),
        Err(e) => println!("total {:.3} s: {e}", t0.elapsed().as_secs_f64()),
    }
}

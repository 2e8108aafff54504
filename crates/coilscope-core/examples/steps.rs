//! Accuracy of the integration schemes (RK4 at 1-3 sub-steps and the one chosen, the
//! exponential scheme at 1-6 steps, the current's exponential method at 1-2) against a tiny-step
//! reference (classical RK4 with
//! 256 sub-steps) per driver and steps per sample: `cargo run --release -p coilscope-core
//! --example steps -- [DRIVER.json ...]` (bundled drivers without arguments). IEC noise
//! driving the driver to 90 % of its x_range; relative RMS errors of current and
//! displacement.

use coilscope_core::excitation::{generate, Excitation, SignalSpec};
use coilscope_core::integrate::Scheme;
use coilscope_core::simulate::{rms, simulate, SimOptions};
use coilscope_core::{embedded_driver, embedded_driver_names, Parameters};

const FS: f64 = 48000.0;

fn rel_rms(a: &[f64], b: &[f64]) -> f64 {
    let e: Vec<f64> = a.iter().zip(b).map(|(x, y)| x - y).collect();
    rms(&e) / rms(b)
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let sets: Vec<(String, Parameters)> = if args.is_empty() {
        embedded_driver_names().into_iter().map(|n| (n.to_string(), embedded_driver(n).unwrap())).collect()
    } else {
        args.iter()
            .map(|f| (f.clone(), Parameters::from_json_str(&std::fs::read_to_string(f).unwrap(), f).unwrap()))
            .collect()
    };
    for (name, p) in sets {
        let spec = SignalSpec { fs: FS, seconds: 0.4, rms: 1.0, fade: 0.05, seed: 11 };
        let u1 = generate(&Excitation::Iec, &spec).unwrap();
        let [lo, hi] = p.x_range.unwrap();
        let (_, tr) =
            coilscope_core::simulate::gain_for_peak(&p, FS, &u1, 0.9 * hi.min(-lo), &SimOptions::default()).unwrap();
        let u = tr.u.clone();
        let tiny =
            simulate(&p, FS, &u, &SimOptions { substeps: Some(256), scheme: Some(Scheme::Rk4), ..Default::default() })
                .unwrap();
        let rk = simulate(&p, FS, &u, &SimOptions { scheme: Some(Scheme::Rk4), ..Default::default() }).unwrap();
        let r = p.rates();
        println!("{name}: stiff/fs {:.3}, LR-3/fs {:.3}", r.stiff / FS, r.lr3 / FS);
        println!(
            "{name}: RK4 {} sub-steps: current {:.2e}, displacement {:.2e}",
            rk.substeps,
            rel_rms(&rk.i, &tiny.i),
            rel_rms(&rk.x, &tiny.x)
        );
        for n in 1..=3 {
            match simulate(
                &p,
                FS,
                &u,
                &SimOptions { substeps: Some(n), scheme: Some(Scheme::Rk4), ..Default::default() },
            ) {
                Ok(e) => println!(
                    "  RK4 {n}: current {:.2e}, displacement {:.2e}",
                    rel_rms(&e.i, &tiny.i),
                    rel_rms(&e.x, &tiny.x)
                ),
                Err(_) => println!("  RK4 {n}: unstable (the stiff mode outside RK4's region)"),
            }
        }
        for n in 1..=6 {
            let e = simulate(
                &p,
                FS,
                &u,
                &SimOptions { substeps: Some(n), scheme: Some(Scheme::Exponential), ..Default::default() },
            )
            .unwrap();
            println!(
                "  exponential {n}: current {:.2e}, displacement {:.2e}",
                rel_rms(&e.i, &tiny.i),
                rel_rms(&e.x, &tiny.x)
            );
        }
        for n in 1..=2 {
            match simulate(
                &p,
                FS,
                &u,
                &SimOptions { substeps: Some(n), scheme: Some(Scheme::ExpCurrent), ..Default::default() },
            ) {
                Ok(e) => println!(
                    "  exponential-current {n}: current {:.2e}, displacement {:.2e}",
                    rel_rms(&e.i, &tiny.i),
                    rel_rms(&e.x, &tiny.x)
                ),
                Err(_) => {
                    println!("  exponential-current {n}: unstable (the LR-2 branch's coupling outside RK4's region)")
                }
            }
        }
    }
}

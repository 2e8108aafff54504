use coilscope_core::excitation::*;
use coilscope_core::params::embedded_driver;
use coilscope_core::simulate::{simulate, SimOptions};
use coilscope_ident::large::*;
use std::time::Instant;
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let name = args.get(1).map(|s| s.as_str()).unwrap_or("sb17cac35-4");
    let fs: f64 = args.get(2).map(|s| s.parse().unwrap()).unwrap_or(48000.0);
    let snr: f64 = args.get(3).map(|s| s.parse().unwrap()).unwrap_or(70.0);
    let p = embedded_driver(name).unwrap();
    let [lo, hi] = p.x_range.unwrap();
    let target = 0.85 * hi.min(-lo);
    let mut volts = 1.0;
    let mut u = vec![];
    let mut tr = None;
    for _ in 0..4 {
        let spec = SignalSpec { fs, seconds: 8.0, rms: volts, fade: 0.05, seed: 1 };
        u = generate(&Excitation::Pink { f_lo: 10.0, f_hi: 8000.0, crest: Some(3.0) }, &spec).unwrap();
        let t = simulate(&p, fs, &u, &SimOptions::default()).unwrap();
        let peak = t.x.iter().fold(0.0f64, |a, v| a.max(v.abs()));
        println!("volts {volts:.3} peak {:.3} mm", peak * 1e3);
        if (peak / target - 1.0).abs() < 0.02 { tr = Some(t); break; }
        volts *= target / peak;
        tr = Some(t);
    }
    let tr = tr.unwrap();
    let mut um = u.clone();
    let mut im = tr.i.clone();
    add_sensor_noise(&mut um, snr, 1, "u-noise");
    add_sensor_noise(&mut im, snr, 1, "i-noise");
    println!("dT_end {:.2} K", tr.tv.last().unwrap());
    let t = Instant::now();
    let opts = IdentifyOptions { mms: p.mms, ..Default::default() };
    let t0 = Instant::now();
    let res = identify(&um, &im, fs, "probe", &opts, |pr| {
        print!("{:6.2} ", t0.elapsed().as_secs_f64());
        println!("  {:?} it {} rel {:.4e} lambda {:.1e} dec {:.2e}", pr.stage, pr.state.iteration, pr.residual_rel, pr.state.lambda, pr.state.last_decrease);
    });
    println!("identify {:.2} s", t.elapsed().as_secs_f64());
    let f = match res { Ok(f) => f, Err(IdentifyError::NotConverged{best, message}) => { println!("{message}"); *best }, Err(e) => { println!("{e}"); return; } };
    println!("order {} trials {:?}", f.order, f.trials);
    println!("substeps {:?} residual_rel {:.3e} x_range {:?}", f.substeps, f.residual_rel, f.x_range);
    let q = &f.params;
    println!("Re {:.4} vs {:.4}  Rms {:.4} vs {:.4}", q.re, p.re, q.rms, p.rms);
    let (l2, r2) = q.l2r2.clone().unwrap();
    let (l2t, r2t) = p.l2r2.clone().unwrap();
    println!("L2 {:.4e} vs {:.4e} R2 {:.4} vs {:.4}", l2.c[0], l2t.c[0], r2.c[0], r2t.c[0]);
    let [a, b] = f.x_range;
    for (nm, fi, ti) in [("Bl", &q.bl, &p.bl), ("Kms", &q.kms, &p.kms), ("Le", &q.le, &p.le)] {
        let mut worst: f64 = 0.0;
        for k in 0..=200 { let x = a + (b - a) * k as f64 / 200.0; worst = worst.max((fi.eval(x) - ti.eval(x)).abs()); }
        println!("{nm}: worst err {:.3} % of rest value", 100.0 * worst / ti.eval(0.0));
    }
    println!("re track {:?}", f.re_track);
}

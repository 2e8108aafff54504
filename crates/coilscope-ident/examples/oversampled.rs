//! Whose is the delay offset? The independent simulator's `sb17cac35-4-large.wav` (no chain
//! delay) gives `identify --chain auto` a current delay 2.2e-4 sample short and Le 0.03 %
//! high. This drives *our* model with the same record's voltage at `OS` times the rate
//! (FFT interpolation, default 16, as the reference integrates), brings the current back to
//! 48 kHz (FFT brickwall) and identifies it the same way (order 4, LR-2, chain estimated, no
//! noise). Measured: OS 16: delay +1.6e-5 sample, Le 0.0075 % high; OS 1: -4e-8
//! sample, 0.0088 %. Our 48 kHz discretisation agrees with our continuous model to 1.6e-5
//! sample: the reference's offset is its own (`LE_DELAY_SYSTEMATIC_REL`).
//!
//! ```text
//! cargo run --release -p coilscope-ident --example oversampled -- [OS]
//! ```
use coilscope_core::embedded_driver;
use coilscope_core::fft::{irfft, rfft};
use coilscope_core::simulate::{simulate, SimOptions};
use coilscope_ident::large::{identify, IdentifyOptions};
use coilscope_ident::linear::EffectsChoice;
use realfft::num_complex::Complex64;

fn resample(x: &[f64], n_out: usize) -> Vec<f64> {
    let s = rfft(x);
    let mut t = vec![Complex64::new(0.0, 0.0); n_out / 2 + 1];
    let k = t.len().min(s.len());
    t[..k].copy_from_slice(&s[..k]);
    let scale = 1.0 / x.len() as f64;
    irfft(&t, n_out).into_iter().map(|v| v * scale).collect()
}

fn main() {
    let os: usize = std::env::args().nth(1).and_then(|a| a.parse().ok()).unwrap_or(16);
    let p = embedded_driver("sb17cac35-4").unwrap();
    let path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/recordings/sb17cac35-4-large.wav");
    let rec = coilscope_io::read_recording(&path, None).unwrap_or_else(|e| {
        eprintln!("{}: {e:?} (the shared recordings sit beside the repository)", path.display());
        std::process::exit(2);
    });
    let fs = rec.fs as f64;
    let n = rec.u.len();
    let u_hi = resample(&rec.u, n * os);
    let tr = simulate(&p, fs * os as f64, &u_hi, &SimOptions::default()).unwrap();
    let i = resample(&tr.i, n);
    let u = resample(&tr.u, n);
    println!(
        "simulated at {} Hz, {} substeps; u diff {:.2e}",
        fs * os as f64,
        tr.substeps,
        u.iter().zip(&rec.u).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max)
    );
    let fit = identify(
        &u,
        &i,
        fs,
        "oversampled",
        &IdentifyOptions {
            mms: p.mms,
            chain: true,
            order: Some(4),
            effects: EffectsChoice::Fixed(Default::default()),
            ..Default::default()
        },
        |_| {},
    )
    .unwrap();
    let c = fit.chain.unwrap();
    println!(
        "delay {:.3e} samples, Le0 {:.6e} (true {:.6e}), rel {:.2e}",
        c.delay_i * fs,
        fit.params.le.c[0],
        p.le.c[0],
        fit.params.le.c[0] / p.le.c[0] - 1.0
    );
}

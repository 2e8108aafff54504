//! Compensation with identified parameters: `identify` on the independent
//! simulator's `sb17cac35-4-large.wav` (6 s of pink noise to -3.9 .. +4.5 mm), then the
//! pre-inverse built from the identified set drives the true driver (the driver file) with a
//! 30 Hz tone whose linear reference reaches 80 % of the identified range. The worst of the
//! displacement's HD2 and HD3 must fall by at least 20 dB (with the true set it falls by
//! 90-126 dB: `coilscope-core/tests/independent_oracle.rs`).

use coilscope_core::embedded_driver;
use coilscope_core::inverse::{compensate, linear_reference, CompensateOptions};
use coilscope_core::simulate::{simulate, SimOptions};
use coilscope_ident::large::{identify, IdentifyOptions};
use std::path::Path;

/// `|X(order f0)| / |X(f0)|` over a whole number of periods.
fn hd(x: &[f64], fs: f64, f0: f64, order: usize) -> f64 {
    // A whole number of periods: the lines fall on the DFT's bins.
    let bin = f0 * x.len() as f64 / fs;
    assert!((bin - bin.round()).abs() < 1e-9, "{} periods of {f0} Hz", bin);
    let s = coilscope_core::fft::rfft(x);
    s[order * bin.round() as usize].norm() / s[bin.round() as usize].norm()
}

#[test]
#[cfg_attr(no_shared, ignore = "../shared is missing (COILSCOPE_NO_SHARED=1): skipped")]
fn compensation_with_identified_parameters_lowers_hd2_hd3_by_20_db() {
    let truth = embedded_driver("sb17cac35-4").unwrap();
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/recordings");
    let rec = coilscope_io::read_recording(&dir.join("sb17cac35-4-large.wav"), None).unwrap();
    let fs = rec.fs as f64;
    let fit = identify(
        &rec.u,
        &rec.i,
        fs,
        "sb17cac35-4-large.wav",
        &IdentifyOptions { mms: truth.mms, ..Default::default() },
        |_| {},
    )
    .unwrap();
    let q = fit.params.clone();
    let [lo, hi] = q.x_range.expect("the identified range");
    let (f0, seconds, fade) = (30.0, 1.2, 0.1);
    let n = (seconds * fs) as usize;
    let unit: Vec<f64> = (0..n)
        .map(|k| {
            let t = k as f64 / fs;
            let env = if t < fade { 0.5 - 0.5 * (std::f64::consts::PI * t / fade).cos() } else { 1.0 };
            env * (2.0 * std::f64::consts::PI * f0 * t).sin()
        })
        .collect();
    let s = simulate(&linear_reference(&q), fs, &unit, &SimOptions::default()).unwrap().summary();
    let volts = 0.8 * hi.min(-lo) / s.x_max.max(-s.x_min);
    let u_in: Vec<f64> = unit.iter().map(|v| v * volts).collect();
    let c = compensate(&q, fs, &u_in, &CompensateOptions::default()).unwrap();
    assert!(c.warnings.is_empty(), "{:?}", c.warnings);
    let tail = |x: &[f64]| x[n - fs as usize..].to_vec();
    let plain = tail(&simulate(&truth, fs, &u_in, &SimOptions::default()).unwrap().x);
    let comp = tail(&simulate(&truth, fs, &c.drive, &SimOptions::default()).unwrap().x);
    let db = |v: f64| 20.0 * v.log10();
    let worst = |x: &[f64]| hd(x, fs, f0, 2).max(hd(x, fs, f0, 3));
    println!(
        "identified {} ({}), {volts:.2} V: HD2/HD3 plain {:.1}/{:.1} dB, compensated {:.1}/{:.1} dB: worst down by {:.1} dB",
        fit.layout.effects.model_name(),
        fit.order,
        db(hd(&plain, fs, f0, 2)),
        db(hd(&plain, fs, f0, 3)),
        db(hd(&comp, fs, f0, 2)),
        db(hd(&comp, fs, f0, 3)),
        db(worst(&plain) / worst(&comp))
    );
    // Required: 20 dB; the README gives 78.7 dB: fails below 60.
    assert!(
        worst(&comp) < 1e-3 * worst(&plain),
        "the worst of HD2/HD3 fell by only {:.1} dB",
        db(worst(&plain) / worst(&comp))
    );
}

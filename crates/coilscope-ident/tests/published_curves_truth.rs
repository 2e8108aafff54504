//! Truth outside the model class.
//!
//! The other truth tests simulate drivers whose Bl(x), Kms(x), Le(x) are the parameter sets'
//! power series, of order 2-6, inside the order range `identify` fits, so a shared mistake
//! or a truncation error cannot show there. Here the truth is each bundled driver's
//! `published_curves` (the Klippel LSI curves as digitised) through an order-10 least-squares
//! series over the valid range: it follows the digitised points (within their scatter) and
//! has terms the fit does not. The record reaches 85 % of the range; measured over the
//! reached range: Bl <= 0.45 %, Kms <= 0.24 %, Le <= 0.71 %, Re <= 0.006 %, the residual at
//! the noise floor (the fit picks order 6-8).

use coilscope_core::excitation::{add_sensor_noise, generate, Excitation, SignalSpec};
use coilscope_core::simulate::{gain_for_peak, SimOptions};
use coilscope_core::{embedded_driver, Parameters, Poly};
use coilscope_ident::large::{identify, IdentifyOptions};
use nalgebra::{DMatrix, DVector};

mod common;
use common::Errors;

const ORDER: usize = 10;

/// Least-squares power series of `ORDER` through the points inside `[lo, hi]` (SI).
fn series_through(points: &[(f64, f64)], [lo, hi]: [f64; 2]) -> Poly {
    let pts: Vec<(f64, f64)> = points.iter().copied().filter(|&(x, _)| x >= lo - 1e-9 && x <= hi + 1e-9).collect();
    let s = hi.max(-lo);
    let a = DMatrix::from_fn(pts.len(), ORDER + 1, |r, c| (pts[r].0 / s).powi(c as i32));
    let b = DVector::from_iterator(pts.len(), pts.iter().map(|p| p.1));
    let c = a.svd(true, true).solve(&b, 1e-12).unwrap();
    Poly { c: (0..=ORDER).map(|k| c[k] / s.powi(k as i32)).collect() }
}

fn curve(p: &Parameters, which: &str) -> Vec<(f64, f64)> {
    p.extra["published_curves"][which]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| (v[0].as_f64().unwrap(), v[1].as_f64().unwrap()))
        .collect()
}

/// One driver per test, so the test harness runs them side by side.
fn identify_recovers_published_curves_outside_its_model_class(name: &str) {
    let base = embedded_driver(name).unwrap();
    let range = base.x_range.unwrap();
    let mut truth = base.clone();
    truth.bl = series_through(&curve(&base, "Bl"), range);
    truth.kms = series_through(&curve(&base, "Kms"), range);
    truth.le = series_through(&curve(&base, "Le"), range);
    // The series follows the digitised points.
    for (which, f) in [("Bl", &truth.bl), ("Kms", &truth.kms), ("Le", &truth.le)] {
        let pts: Vec<_> = curve(&base, which).into_iter().filter(|&(x, _)| x >= range[0] && x <= range[1]).collect();
        let off = pts.iter().map(|&(x, v)| (f.eval(x) / v - 1.0).abs()).fold(0.0, coilscope_testkit::check::nan_max);
        assert!(off < 0.02, "{name} {which}: the order-{ORDER} series is {off:.3} off the published points");
    }
    let fs = 48000.0;
    let unit = generate(
        &Excitation::Pink { f_lo: 10.0, f_hi: 8000.0, crest: Some(3.0) },
        &SignalSpec { fs, seconds: 8.0, rms: 1.0, fade: 0.05, seed: 21 },
    )
    .unwrap();
    let (_, tr) = gain_for_peak(&truth, fs, &unit, 0.85 * range[1].min(-range[0]), &SimOptions::default()).unwrap();
    let s = tr.summary();
    let (mut u, mut i) = (tr.u, tr.i);
    add_sensor_noise(&mut u, 70.0, 21, "sensor-noise/voltage");
    add_sensor_noise(&mut i, 70.0, 21, "sensor-noise/current");
    let fit = identify(&u, &i, fs, name, &IdentifyOptions { mms: truth.mms, ..Default::default() }, |_| {})
        .unwrap_or_else(|e| panic!("{name}: {e}"));
    let r = [s.x_min, s.x_max];
    let e = Errors::of(&fit.params, &truth, r);
    println!(
        "{name} (published curves, order {ORDER}): fit order {}, residual {:.2e}, {e} over {:.2}..{:.2} mm",
        fit.order,
        fit.residual_rel,
        r[0] * 1e3,
        r[1] * 1e3
    );
    // Measured: Bl <= 0.45 %, Kms <= 0.24 %, Le <= 0.71 % (the README's figures); the test
    // fails at about 3.5x.
    assert!(e.bl <= 0.015 && e.kms <= 0.015 && e.le <= 0.025, "{name}: Bl {}, Kms {}, Le {}", e.bl, e.kms, e.le);
    assert!(e.re <= 0.01, "{name}: Re {}", e.re);
    assert!(fit.residual_rel <= 0.01, "{name}: residual {}", fit.residual_rel);
}

#[test]
fn identify_recovers_the_published_curves_of_sb17() {
    identify_recovers_published_curves_outside_its_model_class("sb17cac35-4");
}

#[test]
fn identify_recovers_the_published_curves_of_ptt4() {
    identify_recovers_published_curves_outside_its_model_class("ptt4.0w04-01a");
}

#[test]
fn identify_recovers_the_published_curves_of_18wu() {
    identify_recovers_published_curves_outside_its_model_class("18wu-4741t-00");
}

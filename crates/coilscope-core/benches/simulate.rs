//! Simulation throughput of the full model (LR-2 branch and two-node thermal model on),
//! in samples per second on one core: `cargo bench -p coilscope-core --bench simulate`.

use coilscope_core::excitation::{generate, Excitation, SignalSpec};
use coilscope_core::simulate::{simulate, SimOptions};
use coilscope_core::{embedded_driver, embedded_driver_names};
use divan::counter::ItemsCount;
use divan::Bencher;

fn main() {
    divan::main();
}

const FS: f64 = 48000.0;

/// One second of IEC noise at a level that drives each driver to a large excursion.
fn voltage(volts: f64) -> Vec<f64> {
    generate(&Excitation::Iec, &SignalSpec { fs: FS, seconds: 1.0, rms: volts, fade: 0.05, seed: 1 }).unwrap()
}

#[divan::bench(args = embedded_driver_names())]
fn full_model(bencher: Bencher, name: &str) {
    let p = embedded_driver(name).unwrap();
    assert!(p.l2r2.is_some() && p.thermal.is_some());
    let u = voltage(3.0);
    bencher
        .counter(ItemsCount::new(u.len()))
        .bench(|| simulate(&p, FS, divan::black_box(&u), &SimOptions::default()).unwrap());
}

/// The three-state model of the seed (no LR-2, no thermal), for comparison.
#[divan::bench(args = embedded_driver_names())]
fn three_state(bencher: Bencher, name: &str) {
    let p = embedded_driver(name).unwrap().three_state();
    let u = voltage(3.0);
    bencher
        .counter(ItemsCount::new(u.len()))
        .bench(|| simulate(&p, FS, divan::black_box(&u), &SimOptions::default()).unwrap());
}

/// The extended model (creep bank lambda 0.07 and LR-3: 17 states), against
/// `full_model` on the same driver and drive.
#[divan::bench(args = embedded_driver_names())]
fn creep_and_lr3(bencher: Bencher, name: &str) {
    let mut p = embedded_driver(name).unwrap();
    let (l2, r2) = p.l2r2.as_ref().map(|(l, r)| (l.c[0], r.c[0])).unwrap();
    p.creep = Some(coilscope_core::params::Creep { lambda: 0.07, f_ref: None });
    p.l3r3 = Some((0.6 * l2, 2.5 * r2));
    let u = voltage(3.0);
    bencher
        .counter(ItemsCount::new(u.len()))
        .bench(|| simulate(&p, FS, divan::black_box(&u), &SimOptions::default()).unwrap());
}

/// The full model with classical RK4 and its sub-steps (the scheme before the exponential
/// one), against `full_model`.
#[divan::bench(args = embedded_driver_names())]
fn full_model_rk4(bencher: Bencher, name: &str) {
    let p = embedded_driver(name).unwrap();
    let u = voltage(3.0);
    let opts = SimOptions { scheme: Some(coilscope_core::integrate::Scheme::Rk4), ..Default::default() };
    bencher.counter(ItemsCount::new(u.len())).bench(|| simulate(&p, FS, divan::black_box(&u), &opts).unwrap());
}

/// The full model in the current's exponential method (one step per
/// sample: the current's decay and the drive exactly, RK4's weights for the rest), against
/// `full_model` (RK4 at two sub-steps).
#[divan::bench(args = embedded_driver_names())]
fn full_model_exp_current(bencher: Bencher, name: &str) {
    let p = embedded_driver(name).unwrap();
    let u = voltage(3.0);
    let opts = SimOptions { scheme: Some(coilscope_core::integrate::Scheme::ExpCurrent), ..Default::default() };
    bencher.counter(ItemsCount::new(u.len())).bench(|| simulate(&p, FS, divan::black_box(&u), &opts).unwrap());
}

/// The full model in the exponential method at one step per sample
/// (each step's drive the quartic through its own five points), against `full_model`.
#[divan::bench(args = embedded_driver_names())]
fn full_model_exponential_1(bencher: Bencher, name: &str) {
    let p = embedded_driver(name).unwrap();
    let u = voltage(3.0);
    let opts = SimOptions {
        scheme: Some(coilscope_core::integrate::Scheme::Exponential),
        substeps: Some(1),
        ..Default::default()
    };
    bencher.counter(ItemsCount::new(u.len())).bench(|| simulate(&p, FS, divan::black_box(&u), &opts).unwrap());
}

/// The stiff microspeaker of `testdata/drivers` (Le 30 uH), in the scheme it takes
/// (exponential, 3 steps per sample) and in RK4 (21 sub-steps).
#[divan::bench(args = ["exponential", "rk4"])]
fn microspeaker(bencher: Bencher, scheme: &str) {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../testdata/drivers/microspeaker-0g1.json");
    let p = coilscope_core::Parameters::from_json_str(&std::fs::read_to_string(path).unwrap(), "microspeaker").unwrap();
    let u = voltage(0.5);
    let scheme = match scheme {
        "rk4" => coilscope_core::integrate::Scheme::Rk4,
        _ => coilscope_core::integrate::Scheme::Exponential,
    };
    let opts = SimOptions { scheme: Some(scheme), ..Default::default() };
    bencher.counter(ItemsCount::new(u.len())).bench(|| simulate(&p, FS, divan::black_box(&u), &opts).unwrap());
}

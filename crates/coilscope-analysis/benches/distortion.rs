//! Speed of the distortion analysis (release): one sine's steady state with its three
//! single-nonlinearity runs, a multitone, and a Volterra probe.

use coilscope_analysis::distortion::{analyse, multitone, Output, SteadyOptions};
use coilscope_analysis::volterra::probe;
use coilscope_core::embedded_driver;

fn main() {
    divan::main();
}

#[divan::bench(args = ["sb17cac35-4", "18wu-4741t-00"], sample_count = 3)]
fn sine_analysis_50hz(name: &str) {
    let p = embedded_driver(name).unwrap();
    divan::black_box(analyse(&p, 50.0, 4.0, Output::Pressure, &SteadyOptions::default()).unwrap());
}

#[divan::bench(sample_count = 3)]
fn multitone_30_tones() {
    let p = embedded_driver("sb17cac35-4").unwrap();
    divan::black_box(multitone(&p, 20.0, 10_000.0, 30, 4.0, Output::Pressure, 1, &SteadyOptions::default()).unwrap());
}

#[divan::bench]
fn volterra_probe() {
    let p = embedded_driver("sb17cac35-4").unwrap();
    divan::black_box(probe(&p, 50.0));
}

//! The bands of `identify` hold the truth off the tested level and rate.
//!
//! Found on PTT4 at 44.1 kHz and 4 V of the IEC signal (x +-2.6 mm, 30 % of its range): the
//! order search kept order 2 (order 4 lowered the held-out error by 0.7 %, under its 2 %
//! threshold), the curves came out 0.11 % (Bl) and 0.36 % (Kms) off, and the bands, which held
//! only the noise, missed the truth by 9.7 and 11.6 sd with the fit marked trustworthy. The
//! truncation of the power series is a bias that no covariance of the residual sees. The
//! bands now carry it: the difference between the chosen order's curves and the next order's,
//! both fitted on the same data by the order search (`LargeFit::truncation`), added in
//! quadrature. Measured on that record: the truth within 1.0 sd, the band 0.12 % (Bl) and
//! 0.38 % (Kms) wide at its widest.
//!
//! The sweep: every bundled driver and the large semi-inductive coil, at 30-50 % of the range,
//! at 44.1, 48 and 96 kHz, IEC and pink noise, 70 dB sensor noise. The truth must lie within
//! 3 sd of the Bl, Kms and Le bands, and the curves within the accuracy bounds.
//!
//! Slow in a debug build: `cargo test --release -p coilscope-ident --test
//! order_truncation_bands -- --ignored` (`.ci/run` runs one slice of four).

use coilscope_core::excitation::{add_sensor_noise, generate, Excitation, SignalSpec};
use coilscope_core::simulate::{gain_for_peak, SimOptions};
use coilscope_core::{embedded_driver, Parameters};
use coilscope_ident::large::{identify, IdentifyOptions};
use coilscope_ident::linear::{Effects, EffectsChoice};

mod common;
use common::Errors;

fn driver(name: &str) -> Parameters {
    embedded_driver(name).unwrap_or_else(|| {
        let path = format!("{}/../../testdata/drivers/{name}.json", env!("CARGO_MANIFEST_DIR"));
        Parameters::from_json_str(&std::fs::read_to_string(&path).unwrap(), &path).unwrap()
    })
}

#[test]
#[ignore = "release-profile sweep: cargo test --release -p coilscope-ident --test order_truncation_bands -- --ignored"]
fn order_truncation_is_in_the_bands() {
    let iec = Excitation::Iec;
    let pink = Excitation::Pink { f_lo: 10.0, f_hi: 8000.0, crest: Some(3.0) };
    let mut cases = vec![];
    for name in ["ptt4.0w04-01a", "sb17cac35-4", "18wu-4741t-00", "large-coil"] {
        cases.push((name, 0.3, 44100.0, iec.clone(), 11u64));
        cases.push((name, 0.4, 48000.0, pink.clone(), 12));
        cases.push((name, 0.5, 96000.0, iec.clone(), 13));
    }
    let mut failures = vec![];
    for (name, share, fs, exc, seed) in common::slice::in_slice("order_truncation_bands", cases) {
        let p = driver(name);
        let [lo, hi] = p.x_range.unwrap();
        let unit = generate(&exc, &SignalSpec { fs, seconds: 6.0, rms: 1.0, fade: 0.05, seed }).unwrap();
        let (_, tr) = gain_for_peak(&p, fs, &unit, share * hi.min(-lo), &SimOptions::default()).unwrap();
        let s = tr.summary();
        let (mut u, mut i) = (tr.u, tr.i);
        add_sensor_noise(&mut u, 70.0, seed, "sensor-noise/voltage");
        add_sensor_noise(&mut i, 70.0, seed, "sensor-noise/current");
        let label = format!("{name} at {:.0} % of its range, {:.1} kHz, {exc:?}, seed {seed}", 100.0 * share, fs / 1e3);
        let opts = IdentifyOptions { mms: p.mms, effects: EffectsChoice::Fixed(Effects::NONE), ..Default::default() };
        match identify(&u, &i, fs, &label, &opts, |_| {}) {
            Ok(fit) => {
                let e = Errors::of(&fit.params, &p, [s.x_min, s.x_max]);
                let z = common::band_z(&fit, &p, &["Bl", "Kms", "Le"]);
                let line = format!("{label}: order {} (next tried {:?}), x {:.2} .. {:.2} mm, {e}, the truth within {z:.2} sd of the bands", fit.order, fit.truncation.as_ref().map(|t| t.next_order), 1e3 * s.x_min, 1e3 * s.x_max);
                println!("{line}");
                if !(e.bl <= 0.02 && e.kms <= 0.03 && e.le <= 0.05 && e.re <= 0.005) {
                    failures.push(format!("{line}: beyond the accuracy bounds"));
                }
                if !(z <= 3.0) {
                    failures.push(format!("{line}: the bands miss the truth"));
                }
            }
            Err(e) => failures.push(format!("{label}: {e}")),
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

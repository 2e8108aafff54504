//! A record is refused for what it lacks, not for its length. `identify` once refused
//! anything under 2 s ("record at least 2 s"); a 0.5 s record at 96 kHz that takes the
//! driver to +-2 mm holds what the fit needs (measured: Bl, Kms within 0.1 % over the
//! reached range, the truth within 1.5 sd of the bands, about 1 s each).
//!
//! Tolerances: Bl, Kms within 0.4 % (the README publishes <= 0.1 %; required: 1 %),
//! Le within 0.5 %, the truth within 3 sd of the bands, the residual at the noise floor.

use coilscope_core::excitation::{add_sensor_noise, generate, Excitation, SignalSpec};
use coilscope_core::simulate::{gain_for_peak, SimOptions};
use coilscope_core::{embedded_driver, Parameters};
use coilscope_ident::large::{identify, IdentifyError, IdentifyOptions, MIN_RESONANCE_PERIODS};
use coilscope_ident::linear::{Effects, EffectsChoice};

mod common;
use common::{band_z, Errors};

/// `seconds` of pink noise at `fs` taking `p` to a peak of `peak` (m), 70 dB sensor noise.
fn record(p: &Parameters, fs: f64, seconds: f64, peak: f64, seed: u64) -> (Vec<f64>, Vec<f64>, [f64; 2]) {
    let unit = generate(
        &Excitation::Pink { f_lo: 10.0, f_hi: 8000.0, crest: Some(3.0) },
        &SignalSpec { fs, seconds, rms: 1.0, fade: 0.02, seed },
    )
    .unwrap();
    let (_, tr) = gain_for_peak(p, fs, &unit, peak, &SimOptions::default()).unwrap();
    let s = tr.summary();
    let (mut u, mut i) = (tr.u, tr.i);
    add_sensor_noise(&mut u, 70.0, seed, "sensor-noise/voltage");
    add_sensor_noise(&mut i, 70.0, seed, "sensor-noise/current");
    (u, i, [s.x_min, s.x_max])
}

#[test]
fn half_a_second_at_96_khz_reaching_2_mm_is_identified() {
    for (name, seed) in [("sb17cac35-4", 1), ("ptt4.0w04-01a", 2), ("18wu-4741t-00", 1)] {
        let p = embedded_driver(name).unwrap();
        let (u, i, range) = record(&p, 96000.0, 0.5, 2e-3, seed);
        let opts = IdentifyOptions { mms: p.mms, effects: EffectsChoice::Fixed(Effects::NONE), ..Default::default() };
        let fit = identify(&u, &i, 96000.0, "0.5 s", &opts, |_| {}).unwrap_or_else(|e| panic!("{name}: {e}"));
        let e = Errors::of(&fit.params, &p, range);
        let z = band_z(&fit, &p, &["Bl", "Kms", "Le"]);
        println!(
            "{name} seed {seed}: order {}, {e}, truth within {z:.2} sd, residual {:.2e}",
            fit.order, fit.residual_rel
        );
        assert!(e.bl <= 4e-3 && e.kms <= 4e-3 && e.le <= 5e-3, "{name}: {e}");
        assert!(z <= 3.0, "{name}: the truth is {z:.2} sd outside the bands");
        assert!(fit.residual_rel < 5e-4, "{name}: residual {}", fit.residual_rel);
    }
}

/// A record too short to show the resonance is refused with that reason: 18WU with three
/// times its mass (resonance 13.6 Hz) in 0.5 s holds 3.4 periods after settling; fitted, it
/// gave Bl 6.7 % and Re 9 % off.
#[test]
fn a_record_without_enough_resonance_periods_is_refused_for_that() {
    let mut p = embedded_driver("18wu-4741t-00").unwrap();
    p.mms *= 3.0;
    let (u, i, _) = record(&p, 96000.0, 0.5, 2e-3, 1);
    let opts = IdentifyOptions { mms: p.mms, effects: EffectsChoice::Fixed(Effects::NONE), ..Default::default() };
    match identify(&u, &i, 96000.0, "0.5 s", &opts, |_| {}) {
        Err(IdentifyError::Input(m)) => {
            println!("{m}");
            assert!(
                m.contains("periods of the resonance")
                    && m.contains(&format!("at least {MIN_RESONANCE_PERIODS}"))
                    && m.contains("record at least"),
                "{m}"
            );
        }
        Err(e) => panic!("refused for another reason: {e}"),
        Ok(f) => panic!("fitted (order {}, residual {:.2e})", f.order, f.residual_rel),
    }
}

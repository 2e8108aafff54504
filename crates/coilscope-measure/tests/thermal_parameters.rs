//! Thermal parameters: a 10-minute virtual measurement at a fixed level
//! (`measure --virtual DRIVER --duration 600 --volts V`) fits the two-node thermal model to
//! the rise it tracked from Re and the powers it measured. The driver's thermal set is not
//! the bundled "typical" one, so that no default or start value can stand in for it. Rtv,
//! Ctv and Rtm are required within 15 %; measured within 0.1 % (Ctm too, though the
//! magnet's time constant, 13 min, is longer than the run), so this fails at 1 %; and every
//! value with the truth within 3 of its sds (measured within 0.15 sd: the sds carry the
//! cold Re's uncertainty, an offset of the whole tracked rise).
//!
//! Release profile (about a minute): `cargo test --release -p coilscope-measure --test thermal_parameters`.

use coilscope_core::excitation::Excitation;
use coilscope_core::{embedded_driver, params::Thermal};
use coilscope_ident::thermal::ThermalFit;
use coilscope_measure::device::VirtualDevice;
use coilscope_measure::signal::Source;
use coilscope_measure::{measure, MeasureOptions};

#[test]
fn a_ten_minute_run_at_a_fixed_level_gives_the_thermal_parameters() {
    let mut p = embedded_driver("sb17cac35-4").unwrap();
    p.thermal = Some(Thermal { alpha: 0.00393, rtv: 3.2, ctv: 9.0, rtm: 1.1, ctm: 700.0, rv: 0.0 });
    let truth = [3.2, 9.0, 1.1, 700.0];
    let mut dev = VirtualDevice::new(&p, 48000.0, (1e-4, 1e-4), 5).unwrap();
    let mut src = Source::noise(&Excitation::Iec, 48000.0, 5).unwrap();
    let opts = MeasureOptions { mms: p.mms, duration: Some(600.0), hold_volts: Some(4.0), ..Default::default() };
    let m = measure(&mut dev, &mut src, &opts, None, |_| {}).unwrap();
    let t = m.truth.as_ref().unwrap();
    let tr = &m.thermal_track;
    for k in (0..tr.t.len()).step_by(tr.t.len() / 20) {
        println!("t {:6.1} s  dT {:6.2} K  Pv {:6.3} W  Pm {:6.3} W", tr.t[k], tr.dtv[k], tr.pv[k], tr.pm[k]);
    }
    println!("{} (seconds {:.0})", m.stop_reason, m.seconds);
    let fit = match &m.thermal_fit {
        Some(Ok(f)) => f.clone(),
        other => panic!("no thermal fit: {other:?}"),
    };
    println!(
        "true dT max {:.1} K (estimated {:.1}), residual {:.3} K, tracking lag {:.3} +- {:.3} s",
        t.dtv_max, fit.peak_k, fit.residual_k, fit.lag_s, fit.lag_sd
    );
    let mut bad = vec![];
    for k in 0..4 {
        let (v, sd, want) = (fit.values[k], fit.sd[k], truth[k]);
        let z = (v - want).abs() / sd;
        println!(
            "{}: {v:.4} +- {sd:.4} (true {want}): {:.1} %, {z:.2} sd",
            ThermalFit::NAMES[k],
            100.0 * (v / want - 1.0)
        );
        if (v / want - 1.0).abs() > 0.01 {
            bad.push(format!("{} {v:.4} is more than 1 % off {want}", ThermalFit::NAMES[k]));
        }
        if !(z <= 3.0) {
            bad.push(format!("{} {v:.4} +- {sd:.4}: the truth {want} is {z:.1} sd away", ThermalFit::NAMES[k]));
        }
    }
    let th = m.params.thermal.as_ref().expect("params.thermal set");
    assert_eq!([th.rtv, th.ctv, th.rtm, th.ctm], fit.values);
    // No convection in this driver: the test for it runs (the speed changes from the
    // small-signal stage to the held level) and leaves it out.
    println!("{}", fit.convection_note);
    assert!(
        fit.rv.is_none() && th.rv == 0.0 && fit.convection_note.contains("not supported"),
        "{}",
        fit.convection_note
    );
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

/// The required level schedule (heating, then cooling at a quarter of the level:
/// `measure --duration 600 --volts 4 --cool-after 300 --cool-volts 1`) on a driver whose coil
/// is cooled by convection (`thermal.rv` 1.5 s/m: Rtv(v) = Rtv / (1 + rv |v|)): the fit
/// finds the convection (the speed changes with the level, and a fixed Rtv cannot follow
/// both phases) and keeps it; rv, Rtv, Ctv, Rtm within 15 % (the required figure), each with
/// the truth within 3 sd.
#[test]
fn heating_and_cooling_phases_give_the_convection_cooling() {
    let mut p = embedded_driver("sb17cac35-4").unwrap();
    p.thermal = Some(Thermal { alpha: 0.00393, rtv: 3.2, ctv: 9.0, rtm: 1.1, ctm: 700.0, rv: 1.5 });
    let truth = [3.2, 9.0, 1.1, 700.0];
    let mut dev = VirtualDevice::new(&p, 48000.0, (1e-4, 1e-4), 6).unwrap();
    let mut src = Source::noise(&Excitation::Iec, 48000.0, 6).unwrap();
    let opts = MeasureOptions {
        mms: p.mms,
        duration: Some(600.0),
        hold_volts: Some(4.0),
        cool: Some((300.0, 1.0)),
        ..Default::default()
    };
    let m = measure(&mut dev, &mut src, &opts, None, |_| {}).unwrap();
    let tr = &m.thermal_track;
    for k in (0..tr.t.len()).step_by(tr.t.len() / 12) {
        println!("t {:6.1} s  dT {:6.2} K  Pv {:6.3} W  |v| {:.3} m/s", tr.t[k], tr.dtv[k], tr.pv[k], tr.speed[k]);
    }
    let fit = match &m.thermal_fit {
        Some(Ok(f)) => f.clone(),
        other => panic!("no thermal fit: {other:?}"),
    };
    println!("{}", fit.convection_note);
    let mut bad = vec![];
    let (rv, rv_sd) = fit.rv.unwrap_or((0.0, f64::NAN));
    if fit.rv.is_none() || (rv / 1.5 - 1.0).abs() > 0.15 || (rv - 1.5).abs() > 3.0 * rv_sd {
        bad.push(format!("rv {rv:.3} +- {rv_sd:.3} (true 1.5): {}", fit.convection_note));
    }
    for k in 0..4 {
        let (v, sd, want) = (fit.values[k], fit.sd[k], truth[k]);
        let z = (v - want).abs() / sd;
        println!(
            "{}: {v:.4} +- {sd:.4} (true {want}): {:.1} %, {z:.2} sd",
            ThermalFit::NAMES[k],
            100.0 * (v / want - 1.0)
        );
        if k < 3 && (v / want - 1.0).abs() > 0.15 {
            bad.push(format!("{} {v:.4} is more than 15 % off {want}", ThermalFit::NAMES[k]));
        }
        if !(z <= 3.0) {
            bad.push(format!("{} {v:.4} +- {sd:.4}: the truth {want} is {z:.1} sd away", ThermalFit::NAMES[k]));
        }
    }
    assert_eq!(m.params.thermal.as_ref().unwrap().rv, rv);
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

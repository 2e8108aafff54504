//! Quasi-static (seed paper 3.2.1; IEC 62458 10.2/10.3): the point-by-point
//! measurement on the virtual driver (a DC offset per working point, a laser for the static
//! displacement, a small noise for the impedance at the point).
//!
//! - Without creep: Bl(x) and Kms(x) within 2 % over 80 % of the range (the accuracy bound;
//!   measured 0.25 % on SB17, 0.04 % on PTT4: asserted at 1 %).
//! - With creep (LOG, lambda 0.05): the static stiffness at rest is below the dynamic one by
//!   what the creep model says, `Kc = lambda Kms(0) Re b(w_fs)` (`coilscope_core::creep`),
//!   within 5 % (measured 1.4 %); and after the largest offset the rest position has drifted (creep memory),
//!   where without creep it has not.

use coilscope_core::excitation::{generate, Excitation, SignalSpec};
use coilscope_core::params::Creep;
use coilscope_core::simulate::{simulate, SimOptions};
use coilscope_core::{embedded_driver, Parameters, Poly};
use coilscope_ident::quasi_static::{quasi_static, Offset, Played, Push, QuasiStatic, QuasiStaticOptions};

const FS: f64 = 48000.0;

fn run(p: &Parameters, hold_s: f64) -> QuasiStatic {
    let ac = generate(
        &Excitation::Pink { f_lo: 5.0, f_hi: 16000.0, crest: None },
        &SignalSpec { fs: FS, seconds: 2.0, rms: 1.0, fade: 0.0, seed: 7 },
    )
    .unwrap();
    let opts = QuasiStaticOptions {
        mms: p.mms,
        points: 9,
        reach: 0.8,
        range: p.x_range.unwrap(),
        hold_s,
        record_s: 2.0,
        ac_volts: 0.1,
        order: 4,
        fs: FS,
        offset: Offset::Current,
    };
    let play = |d: &[f64], _: Push| {
        simulate(p, FS, d, &SimOptions::default()).map(|t| Played::from((t.u, t.i, t.x))).map_err(|e| e.to_string())
    };
    quasi_static(play, &ac, &opts).unwrap()
}

/// Largest `|f / g - 1|` over `[lo, hi]`.
fn worst(f: &Poly, g: &Poly, lo: f64, hi: f64) -> f64 {
    (0..=100)
        .map(|k| lo + (hi - lo) * k as f64 / 100.0)
        .map(|x| (f.eval(x) / g.eval(x) - 1.0).abs())
        .fold(0.0, coilscope_testkit::check::nan_max)
}

#[test]
fn quasi_static_curves_without_creep_are_within_2_percent() {
    for name in ["sb17cac35-4", "ptt4.0w04-01a"] {
        let p = embedded_driver(name).unwrap();
        let q = run(&p, 2.0);
        for w in &q.points {
            println!(
                "{name}: {:+.3} V  x {:+.3} mm  I {:+.4} A  Re {:.4}  Bl {:.4} (eff {:.4}, true {:.4})  Kms {:.1} (true {:.1})  k_t {:.1}  Le {:.4} mH (true {:.4})",
                w.u_dc,
                w.x_dc * 1e3,
                w.i_dc,
                w.re_dc,
                w.bl,
                w.bl_eff,
                p.bl.eval(w.x_dc),
                w.kms_static,
                p.kms.eval(w.x_dc),
                w.k_tangent,
                w.le * 1e3,
                p.le.eval(w.x_dc) * 1e3
            );
        }
        let [lo, hi] = p.x_range.unwrap();
        let (eb, ek, el) = (
            worst(&q.params.bl, &p.bl, 0.8 * lo, 0.8 * hi),
            worst(&q.params.kms, &p.kms, 0.8 * lo, 0.8 * hi),
            worst(&q.params.le, &p.le, 0.8 * lo, 0.8 * hi),
        );
        println!(
            "{name}: over 80 % of the range Bl {:.3} %, Kms {:.3} %, Le {:.3} %; rest drift {:.4} mm",
            100.0 * eb,
            100.0 * ek,
            100.0 * el,
            q.rest_drift * 1e3
        );
        assert!(eb < 0.01 && ek < 0.01, "{name}: Bl {eb:.4}, Kms {ek:.4}");
        // The bands: the truth within 3 sd on the points' span.
        for (which, band, t) in [("Bl", &q.bands[0], &p.bl), ("Kms", &q.bands[1], &p.kms), ("Le", &q.bands[2], &p.le)] {
            let z = band
                .x
                .iter()
                .zip(&band.value)
                .zip(&band.sd)
                .map(|((x, v), s)| (v - t.eval(*x)).abs() / s)
                .fold(0.0, coilscope_testkit::check::nan_max);
            let rel = band
                .x
                .iter()
                .zip(&band.sd)
                .zip(&band.value)
                .map(|((_, s), v)| s / v)
                .fold(0.0, coilscope_testkit::check::nan_max);
            println!("{name}: {which} band: the truth within {z:.2} sd (largest sd {:.3} %)", 100.0 * rel);
            assert!(z <= 3.0, "{name}: {which}: the truth {z:.2} sd outside the band");
        }
        assert!(
            q.rest_drift.abs() < 1e-3 * hi,
            "{name}: the rest position moved by {} mm without creep",
            q.rest_drift * 1e3
        );
        assert!(q.warnings.is_empty(), "{name}: {:?}", q.warnings);
    }
}

#[test]
fn with_creep_the_static_stiffness_is_below_the_dynamic_by_the_creep_model() {
    let mut p = embedded_driver("sb17cac35-4").unwrap();
    let lambda = 0.05;
    p.creep = Some(Creep { lambda, f_ref: None });
    let q = run(&p, 15.0);
    let k0 = p.kms.c[0];
    let kc = lambda * k0 * coilscope_core::creep::bank_re(2.0 * std::f64::consts::PI * p.resonance_hz());
    let measured = q.k_dynamic_rest - q.params.kms.eval(0.0);
    let [_, hi] = p.x_range.unwrap();
    println!("dynamic {:.1} N/m, static {:.1} N/m: difference {measured:.2} N/m, the creep model {kc:.2} N/m; rest drift {:.4} mm", q.k_dynamic_rest, q.params.kms.eval(0.0), q.rest_drift * 1e3);
    assert!((measured / kc - 1.0).abs() < 0.05, "static-dynamic difference {measured} N/m, the creep model {kc} N/m");
    assert!(
        q.rest_drift > 1e-3 * hi,
        "after the largest offset the rest position should lag (creep): {} mm",
        q.rest_drift * 1e3
    );
}

/// Off the woofers: the 0.1 g microspeaker (2 s thermal time constant) held at its range by
/// DC heats hundreds of kelvin, its reach collapses and its curves come out 70-125 % off; the
/// result must say so (`warnings`), not look like a measurement.
#[test]
fn a_coil_the_dc_heats_far_is_named() {
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../../testdata/drivers");
    let p = Parameters::from_json_str(
        &std::fs::read_to_string(format!("{dir}/microspeaker-0g1.json")).unwrap(),
        "microspeaker",
    )
    .unwrap();
    let ac = generate(
        &Excitation::Pink { f_lo: 5.0, f_hi: 16000.0, crest: None },
        &SignalSpec { fs: FS, seconds: 2.0, rms: 1.0, fade: 0.0, seed: 7 },
    )
    .unwrap();
    let opts = QuasiStaticOptions {
        mms: p.mms,
        points: 9,
        reach: 0.8,
        range: p.x_range.unwrap(),
        hold_s: 5.0,
        record_s: 2.0,
        ac_volts: 0.1,
        order: 4,
        fs: FS,
        offset: Offset::Current,
    };
    let play = |d: &[f64], _: Push| {
        simulate(&p, FS, d, &SimOptions::default()).map(|t| Played::from((t.u, t.i, t.x))).map_err(|e| e.to_string())
    };
    let q = quasi_static(play, &ac, &opts).unwrap();
    println!("{:?}", q.warnings);
    assert!(q.warnings.iter().any(|w| w.contains("the DC heated the coil")), "{:?}", q.warnings);
}

fn run_with(p: &Parameters, offset: Offset, ac_volts: f64) -> QuasiStatic {
    let ac = generate(
        &Excitation::Pink { f_lo: 5.0, f_hi: 16000.0, crest: None },
        &SignalSpec { fs: FS, seconds: 2.0, rms: 1.0, fade: 0.0, seed: 7 },
    )
    .unwrap();
    let opts = QuasiStaticOptions {
        mms: p.mms,
        points: 9,
        reach: 0.8,
        range: p.x_range.unwrap(),
        hold_s: 2.0,
        record_s: 2.0,
        ac_volts,
        order: 4,
        fs: FS,
        offset,
    };
    let play = |d: &[f64], push: Push| {
        let q = Parameters { mms: p.mms + push.added_mass, ..p.clone() };
        simulate(&q, FS, d, &SimOptions { force: push.force, ..Default::default() })
            .map(|t| Played::from((t.u, t.i, t.x)))
            .map_err(|e| e.to_string())
    };
    quasi_static(play, &ac, &opts).unwrap()
}

/// The offsets without current (IEC 62458 10.2/10.3): an added mass under gravity, and a
/// pressure on the diaphragm. The static balance is the force alone (`Kms(x) x = F`), the
/// small signal is fitted with the added mass in the moving mass. On SB17 and PTT4 Bl(x) and
/// Kms(x) within 1 % over 80 % of the range (as by current), the truth within 3 sd of the
/// bands, and no heat. And where the DC current fails, on the 0.1 g microspeaker whose coil
/// it heats hundreds of kelvin (above), a pressure measures it: Bl and Kms within 2 %.
#[test]
fn mass_and_pressure_offsets_need_no_current() {
    for name in ["sb17cac35-4", "ptt4.0w04-01a"] {
        let p = embedded_driver(name).unwrap();
        for offset in [Offset::Mass, Offset::Pressure { sd: p.sd.unwrap() }] {
            let q = run_with(&p, offset, 0.1);
            let [lo, hi] = p.x_range.unwrap();
            let (eb, ek) =
                (worst(&q.params.bl, &p.bl, 0.8 * lo, 0.8 * hi), worst(&q.params.kms, &p.kms, 0.8 * lo, 0.8 * hi));
            let top = q.points.iter().map(|w| w.push.added_mass).fold(0.0, coilscope_testkit::check::nan_max);
            println!(
                "{name} by {offset:?}: Bl {:.3} %, Kms {:.3} %; largest force {:.2} N (mass {:.1} g); warnings {:?}",
                100.0 * eb,
                100.0 * ek,
                q.points.iter().map(|w| w.force.abs()).fold(0.0, coilscope_testkit::check::nan_max),
                1e3 * top,
                q.warnings
            );
            assert!(eb < 0.01 && ek < 0.01, "{name} {offset:?}: Bl {eb:.4}, Kms {ek:.4}");
            assert!(q.points.iter().all(|w| w.i_dc.abs() < 1e-3), "{name} {offset:?}: a DC current");
            for (which, band, t) in [("Bl", &q.bands[0], &p.bl), ("Kms", &q.bands[1], &p.kms)] {
                let z = band
                    .x
                    .iter()
                    .zip(&band.value)
                    .zip(&band.sd)
                    .map(|((x, v), s)| (v - t.eval(*x)).abs() / s)
                    .fold(0.0, coilscope_testkit::check::nan_max);
                assert!(z <= 3.0, "{name} {offset:?}: {which}: the truth {z:.2} sd outside the band");
            }
            assert!(q.warnings.is_empty(), "{name} {offset:?}: {:?}", q.warnings);
        }
    }
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../../testdata/drivers");
    let p = Parameters::from_json_str(
        &std::fs::read_to_string(format!("{dir}/microspeaker-0g1.json")).unwrap(),
        "microspeaker",
    )
    .unwrap();
    let q = run_with(&p, Offset::Pressure { sd: p.sd.unwrap_or(1e-4) }, 0.01);
    let [lo, hi] = p.x_range.unwrap();
    let (eb, ek) = (worst(&q.params.bl, &p.bl, 0.8 * lo, 0.8 * hi), worst(&q.params.kms, &p.kms, 0.8 * lo, 0.8 * hi));
    println!("microspeaker by pressure: Bl {:.3} %, Kms {:.3} %; warnings {:?}", 100.0 * eb, 100.0 * ek, q.warnings);
    assert!(eb < 0.02 && ek < 0.02 && q.warnings.is_empty(), "microspeaker: Bl {eb:.4}, Kms {ek:.4}, {:?}", q.warnings);
}

/// Seen with `coilscope quasistatic 18wu-4741t-00 --offset mass`: at 2.3 N the
/// working point's small-signal fit once stopped after one iteration at 25 % current error (Bl
/// 1.74 T m where the driver has 6.0), the series took the point in, and the command exited 0;
/// and with every point at 0 V the "dynamic stiffness at rest" was read at the outermost
/// point (1124 N/m against 453). Now the point is left out by name (a warning: exit 3) and
/// the rest point is the one without a push. Same settings as the command: seed-1 noise at
/// its level, 5 s hold.
#[test]
fn a_failed_point_fit_is_left_out_by_name() {
    let p = embedded_driver("18wu-4741t-00").unwrap();
    let ac = generate(
        &Excitation::Pink { f_lo: 5.0, f_hi: 16000.0, crest: None },
        &SignalSpec { fs: FS, seconds: 2.0, rms: 1.0, fade: 0.0, seed: 1 },
    )
    .unwrap();
    let ts = coilscope_core::small_signal::thiele_small(&p);
    let range = p.x_range.unwrap();
    let ac_volts =
        (0.02 * range[1].min(-range[0]) / (p.bl.c[0] / (p.re * p.kms.c[0]) * ts.qts.max(0.3))).clamp(0.01, 1.0);
    let opts = QuasiStaticOptions {
        mms: p.mms,
        points: 9,
        reach: 0.8,
        range,
        hold_s: 5.0,
        record_s: 2.0,
        ac_volts,
        order: 4,
        fs: FS,
        offset: Offset::Mass,
    };
    let play = |d: &[f64], push: Push| {
        let q = Parameters { mms: p.mms + push.added_mass, ..p.clone() };
        simulate(&q, FS, d, &SimOptions { force: push.force, ..Default::default() })
            .map(|t| Played::from((t.u, t.i, t.x)))
            .map_err(|e| e.to_string())
    };
    let q = quasi_static(play, &ac, &opts).unwrap();
    println!("{:?}", q.warnings);
    let [lo, hi] = q.params.x_range.unwrap();
    let (eb, ek) = (worst(&q.params.bl, &p.bl, lo, hi), worst(&q.params.kms, &p.kms, lo, hi));
    println!(
        "18WU by mass: Bl {:.3} %, Kms {:.3} % over {:.2}..{:.2} mm; {} points; k at rest {:.1} (true {:.1})",
        100.0 * eb,
        100.0 * ek,
        lo * 1e3,
        hi * 1e3,
        q.points.len(),
        q.k_dynamic_rest,
        p.kms.c[0]
    );
    // The failed point is named; every point kept has a working fit.
    assert!(q.warnings.iter().any(|w| w.contains("is left out: its small-signal fit failed")), "{:?}", q.warnings);
    assert!(
        q.points.iter().all(|w| w.residual < 0.02 && (w.bl_eff / p.bl.eval(w.x_dc) - 1.0).abs() < 0.05),
        "a failed point kept"
    );
    // The curves from the other points, and the rest point's stiffness at rest.
    assert!(eb < 0.02 && ek < 0.02, "Bl {eb}, Kms {ek}");
    assert!((q.k_dynamic_rest / p.kms.c[0] - 1.0).abs() < 0.02, "k at rest {} vs {}", q.k_dynamic_rest, p.kms.c[0]);
}

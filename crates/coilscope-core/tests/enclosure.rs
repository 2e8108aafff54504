//! The box as an element of the model (`enclosure`): its time-domain equations against the
//! textbook small-signal network, its energy balance, and its file keys.

use coilscope_core::enclosure::{BoxKind, Enclosure, P0};
use coilscope_core::integrate::{Dynamics, Electrical, Stepper};
use coilscope_core::model::{ext_idx, idx, ExtModel, NBOX};
use coilscope_core::simulate::{simulate, SimOptions};
use coilscope_core::small_signal::impedance;
use coilscope_core::{embedded_driver, Parameters, Poly};
use realfft::num_complex::Complex64;
use std::f64::consts::PI;

const FS: f64 = 48000.0;

/// The boxes of the independent simulator's `*-box-*` records, and a microspeaker in a back
/// volume of one cubic centimetre, where the air spring is stiffer than the suspension and
/// the volume changes by percent at full excursion.
fn boxed(name: &str) -> Parameters {
    let (mut p, e) = match name {
        "closed" => (
            embedded_driver("sb17cac35-4").unwrap(),
            Enclosure { vb: 0.012, ql: Some(10.0), adiabatic: true, kind: BoxKind::Closed },
        ),
        "vented" => (
            embedded_driver("sb17cac35-4").unwrap(),
            Enclosure {
                vb: 0.020,
                ql: Some(8.0),
                adiabatic: true,
                kind: BoxKind::Vented {
                    fb: 38.0,
                    qp: Some(40.0),
                    port_area: Some(0.002),
                    port_loss: Some(1.5),
                    knl: None,
                },
            },
        ),
        "passive_radiator" => (
            embedded_driver("ptt4.0w04-01a").unwrap(),
            Enclosure {
                vb: 0.005,
                ql: Some(10.0),
                adiabatic: true,
                kind: BoxKind::PassiveRadiator {
                    sp: 0.0095,
                    mmp: 0.050,
                    kmp: Poly { c: vec![900.0, 0.0, 1.5e7] },
                    rmp: 0.8,
                },
            },
        ),
        "back_volume" => {
            let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../../testdata/drivers");
            let mut p = Parameters::from_json_str(
                &std::fs::read_to_string(format!("{dir}/microspeaker-0g1.json")).unwrap(),
                "microspeaker",
            )
            .unwrap();
            p.sd = Some(1.0e-4);
            (p, Enclosure { vb: 1.0e-6, ql: Some(5.0), adiabatic: true, kind: BoxKind::Closed })
        }
        other => panic!("no box {other}"),
    };
    p.enclosure = Some(e);
    p.validate("test box").unwrap();
    p
}

const BOXES: [&str; 4] = ["closed", "vented", "passive_radiator", "back_volume"];

/// Tones (Hz, whole cycles in one second) around a box's resonances, log-spaced.
fn tones(p: &Parameters) -> Vec<f64> {
    let f0 = p.resonance_hz();
    let (lo, hi) = ((f0 / 6.0).max(5.0), f0 * 6.0);
    let mut f: Vec<f64> = (0..40).map(|k| (lo * (hi / lo).powf(k as f64 / 39.0)).round()).collect();
    f.dedup();
    f
}

/// The complex amplitude of `s` at `f` (Hz) over the last second.
fn phasor(s: &[f64], f: f64) -> Complex64 {
    let n = FS as usize;
    let tail = &s[s.len() - n..];
    tail.iter()
        .enumerate()
        .map(|(k, v)| v * Complex64::from_polar(1.0, -2.0 * PI * f * k as f64 / FS))
        .sum::<Complex64>()
        * (2.0 / n as f64)
}

/// The textbook small-signal network is the time-domain model at a whisper: a multitone
/// of small amplitude through the nonlinear model, box air, port and radiator included
/// (adiabatic law, quadratic port loss, Kmp(xp)), gives at every tone the impedance that
/// `small_signal::impedance` computes from the network (box compliance, leak, port or
/// radiator in parallel, times Sd^2 on the cone).
#[test]
fn a_whisper_through_the_box_has_the_small_signal_impedance() {
    for name in BOXES {
        // No heating and no para-inductance drift: the linear network is the model at rest.
        let mut p = boxed(name);
        p.thermal = None;
        let f = tones(&p);
        let seconds = 4.0;
        let n = (seconds * FS) as usize;
        let mut u: Vec<f64> = (0..n)
            .map(|k| {
                let t = k as f64 / FS;
                f.iter()
                    .enumerate()
                    .map(|(j, fj)| (2.0 * PI * fj * t - PI * (j * j) as f64 / f.len() as f64).sin())
                    .sum::<f64>()
                    * 1e-3
            })
            .collect();
        // Scale to a peak excursion of 0.1 % of the range. The port's quadratic loss is the
        // first to show: at 1 % its `knl |U|` is 15 % of the port's linear loss.
        let tr = simulate(&p, FS, &u, &SimOptions::default()).unwrap();
        let peak = tr.x.iter().fold(0.0f64, |a, x| a.max(x.abs()));
        let gain = 0.001 * p.x_range.unwrap()[1] / peak;
        u.iter_mut().for_each(|v| *v *= gain);
        let tr = simulate(&p, FS, &u, &SimOptions::default()).unwrap();
        let mut worst = (0.0, 0.0);
        for &fj in &f {
            let z = phasor(&u, fj) / phasor(&tr.i, fj);
            let want = impedance(&p, fj);
            let e = (z - want).norm() / want.norm();
            if e > worst.0 {
                worst = (e, fj);
            }
        }
        eprintln!("{name}: worst tone {:.1} Hz, |Z - Z_network| / |Z| = {:.2e}", worst.1, worst.0);
        assert!(
            worst.0 < 2e-3,
            "{name}: at {} Hz the simulated impedance is {:.3e} off the network's",
            worst.1,
            worst.0
        );
    }
}

/// A vented box's impedance has two peaks and the dip between them at the port's tuning;
/// a closed box's one peak moves up to `sqrt((Kms + Sd^2 / Cab) / Mms) / 2 pi`.
#[test]
fn a_vented_box_has_two_peaks_and_its_dip_at_fb() {
    let p = boxed("vented");
    let grid: Vec<f64> = (0..4000).map(|k| 10.0 * (200.0f64 / 10.0).powf(k as f64 / 3999.0)).collect();
    let mag: Vec<f64> = grid.iter().map(|&f| impedance(&p, f).norm()).collect();
    let peaks: Vec<f64> =
        (1..grid.len() - 1).filter(|&k| mag[k] > mag[k - 1] && mag[k] > mag[k + 1]).map(|k| grid[k]).collect();
    let dips: Vec<f64> =
        (1..grid.len() - 1).filter(|&k| mag[k] < mag[k - 1] && mag[k] < mag[k + 1]).map(|k| grid[k]).collect();
    assert_eq!(peaks.len(), 2, "peaks at {peaks:?}");
    assert_eq!(dips.len(), 1, "dips at {dips:?}");
    assert!(peaks[0] < 38.0 && 38.0 < peaks[1], "peaks {peaks:?} around fb 38 Hz");
    assert!((dips[0] / 38.0 - 1.0).abs() < 0.02, "the dip at {} Hz, fb 38 Hz", dips[0]);

    // Without a leak the load is a pure compliance.
    let mut c = boxed("closed");
    c.enclosure.as_mut().unwrap().ql = None;
    let sd = c.sd.unwrap();
    let e = c.enclosure.as_ref().unwrap();
    let fc = ((c.kms.c[0] + sd * sd / e.cab()) / c.mms).sqrt() / (2.0 * PI);
    // The peak of the motional impedance: where its reactance crosses zero.
    let (mut lo, mut hi) = (c.resonance_hz(), 4.0 * c.resonance_hz());
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        let zm = impedance(&c, mid) - impedance(&Parameters { bl: Poly::constant(1e-9), ..c.clone() }, mid);
        if zm.im > 0.0 {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    assert!((lo / fc - 1.0).abs() < 1e-3, "closed box: resonance {lo} Hz, sqrt((Kms + Sd^2/Cab)/Mms)/2pi = {fc} Hz");
    assert!((fc - 61.33).abs() < 0.05, "the independent simulator's fc for SB17 in 12 l: 61.33 Hz, ours {fc}");
}

/// The model with two accumulators: the electrical input and every loss (Re, R2, R3, Rms,
/// creep, the box's).
struct WithEnergy<'a>(&'a ExtModel<f64>);

impl Dynamics<f64, { NBOX + 2 }> for WithEnergy<'_> {
    fn deriv(&self, y: &[f64; NBOX + 2], u: f64) -> [f64; NBOX + 2] {
        let s: [f64; NBOX] = std::array::from_fn(|k| y[k]);
        let d = self.0.deriv_n(&s, u);
        let p = self.0.powers(&s, u);
        let loss = p.re_loss + p.r2_loss + p.r3_loss + p.rms_loss + p.creep_loss + p.box_loss;
        std::array::from_fn(|k| match k {
            k if k < NBOX => d[k],
            k if k == NBOX => p.input,
            _ => loss,
        })
    }
}

impl Electrical<f64, { NBOX + 2 }> for WithEnergy<'_> {
    fn electrical(&self, y: &[f64; NBOX + 2]) -> [[f64; 2]; 2] {
        Electrical::<f64, NBOX>::electrical(self.0, &std::array::from_fn(|k| y[k]))
    }
    fn input(&self, y: &[f64; NBOX + 2]) -> f64 {
        Electrical::<f64, NBOX>::input(self.0, &std::array::from_fn(|k| y[k]))
    }
    fn current_rate_and_input(&self, y: &[f64; NBOX + 2]) -> (f64, f64) {
        Electrical::<f64, NBOX>::current_rate_and_input(self.0, &std::array::from_fn(|k| y[k]))
    }
    fn network3(&self, y: &[f64; NBOX + 2]) -> Option<[[f64; 3]; 3]> {
        Electrical::<f64, NBOX>::network3(self.0, &std::array::from_fn(|k| y[k]))
    }
}

/// Pink-ish noise scaled so the cone reaches `frac` of its range.
fn loud(p: &Parameters, seconds: f64, frac: f64) -> Vec<f64> {
    use coilscope_core::excitation::{generate, Excitation, SignalSpec};
    let u1 = generate(&Excitation::Iec, &SignalSpec { fs: FS, seconds, rms: 1.0, fade: 0.05, seed: 5 }).unwrap();
    let target = frac * p.x_range.unwrap()[1];
    let mut gain = 0.5;
    for _ in 0..6 {
        let u: Vec<f64> = u1.iter().map(|v| v * gain).collect();
        let s = simulate(p, FS, &u, &SimOptions::default()).unwrap().summary();
        gain *= (target / s.x_max.max(-s.x_min)).powf(0.8);
    }
    u1.iter().map(|v| v * gain).collect()
}

/// Input, imbalance (input less losses less stored energy) and the peak box pressure over
/// `u` with `stepper`.
fn balance(p: &Parameters, u: &[f64], stepper: &Stepper) -> (f64, f64, f64) {
    let m = ExtModel::new(p);
    let mut pts = vec![0.0; stepper.points()];
    let sys = WithEnergy(&m);
    let mut y = [0.0; NBOX + 2];
    let mut p_peak = 0.0f64;
    for k in 0..u.len() * 3 / 5 {
        stepper.fill(u, k, &mut pts);
        y = stepper.sample(&sys, &y, 1.0 / FS, &pts);
        p_peak = p_peak.max(y[ext_idx::BOX].abs());
    }
    let s: [f64; NBOX] = std::array::from_fn(|k| y[k]);
    let stored = m.stored_energy(&s);
    assert!(stored.is_finite() && y[NBOX + 1] > 0.0);
    (y[NBOX], y[NBOX] - y[NBOX + 1] - stored, p_peak)
}

/// The energy put in at the terminals is the energy lost plus the energy stored, box air,
/// port air and radiator included, at full excursion with the driver's thermal model, creep
/// and LR-3. With tiny RK4 steps (the oracle) it closes to rounding under the linear law and
/// for a box no air leaves under the adiabatic law; with air leaving under the adiabatic law
/// it closes within a small part of `p / p0` (the contract's port and leak are driven by the
/// gauge pressure, not by the air's enthalpy). The production steps add their own error,
/// within 5e-5 of the input.
#[test]
fn box_energy_balance_closes() {
    for name in BOXES {
        for (adiabatic, leak) in [(false, true), (true, false), (true, true)] {
            let mut p = boxed(name);
            if let Some(e) = p.enclosure.as_mut() {
                e.adiabatic = adiabatic;
                if !leak {
                    e.ql = None;
                }
            }
            let lr3 = p.l2r2.as_ref().map(|(l, r)| (0.6 * l.c[0], 2.5 * r.c[0]));
            p.l3r3 = lr3;
            p.creep = Some(coilscope_core::params::Creep { lambda: 0.07, f_ref: None });
            let u = loud(&p, 0.6, 0.9);
            let sealed = matches!(p.enclosure.as_ref().unwrap().kind, BoxKind::Closed) && !leak;
            let tiny = Stepper::new(coilscope_core::integrate::Scheme::Rk4, 64);
            let production = Stepper::for_rates(p.rates(), FS);
            for (what, stepper, tol) in [("tiny steps", &tiny, 1e-9), ("production steps", &production, 5e-5)] {
                let (input, imbalance, p_peak) = balance(&p, &u, stepper);
                let bound = if !adiabatic || sealed { tol } else { tol + 0.01 * p_peak / P0 };
                eprintln!(
                    "{name}, adiabatic {adiabatic}, leak {leak}, {what}: imbalance {:.2e} of the input, p peak {p_peak:.0} Pa (bound {bound:.1e})",
                    imbalance / input
                );
                assert!(
                    imbalance.abs() < bound * input,
                    "{name}, adiabatic {adiabatic}, leak {leak}, {what}: imbalance {:.3e} of the input",
                    imbalance / input
                );
            }
        }
    }
}

/// Under the adiabatic law a sealed box keeps `(p0 + p) V^gamma` (no air leaves): the air
/// spring stiffens on compression and softens on expansion, as a microspeaker's back volume
/// does at full excursion.
#[test]
fn a_sealed_box_keeps_its_adiabatic_invariant() {
    let mut p = boxed("back_volume");
    p.enclosure.as_mut().unwrap().ql = None;
    let u = loud(&p, 0.3, 0.9);
    let m = ExtModel::new(&p);
    let stepper = Stepper::for_rates(p.rates(), FS);
    let mut pts = vec![0.0; stepper.points()];
    let mut y = [0.0; NBOX];
    let (sd, vb) = (p.sd.unwrap(), 1.0e-6);
    let mut worst = 0.0f64;
    let mut p_max = 0.0f64;
    for k in 0..u.len() {
        stepper.fill(&u, k, &mut pts);
        y = stepper.sample(&m, &y, 1.0 / FS, &pts);
        let v = vb + sd * y[idx::X];
        let inv = (P0 + y[ext_idx::BOX]) * v.powf(1.4) / (P0 * vb.powf(1.4));
        worst = worst.max((inv - 1.0).abs());
        p_max = p_max.max(y[ext_idx::BOX].abs());
    }
    eprintln!("back volume: p peak {p_max:.0} Pa, invariant kept to {worst:.1e}");
    assert!(p_max > 0.03 * P0, "the back volume's pressure reached {p_max} Pa: not a large-signal test");
    assert!(worst < 1e-7, "(p0 + p) V^gamma moved by {worst:.2e}");
}

/// The box is read and written in the contract's keys; a mistake names the key, the value
/// and what would be valid.
#[test]
fn a_box_round_trips_and_its_mistakes_are_named() {
    for name in BOXES {
        let p = boxed(name);
        let back = Parameters::from_json_value(&p.to_json_value(), "round trip").unwrap();
        assert_eq!(back.enclosure, p.enclosure, "{name}");
    }
    let base = embedded_driver("sb17cac35-4").unwrap().to_json_value();
    let with = |e: serde_json::Value| {
        let mut v = base.clone();
        v["enclosure"] = e;
        Parameters::from_json_value(&v, "box.json").map(|_| ()).unwrap_err().to_string()
    };
    let e = with(serde_json::json!({"type": "sealed", "Vb": 0.01}));
    assert!(e.contains("enclosure.type") && e.contains("\"sealed\"") && e.contains("closed"), "{e}");
    let e = with(serde_json::json!({"type": "closed", "Vb": 12.0e3}));
    assert!(e.contains("enclosure.Vb") && e.contains("litres"), "{e}");
    let e = with(serde_json::json!({"type": "closed", "Vb": 0.01, "fb": 40}));
    assert!(e.contains("enclosure.fb") && e.contains("not a key of a closed box"), "{e}");
    let e = with(serde_json::json!({"type": "vented", "Vb": 0.01}));
    assert!(e.contains("enclosure.fb") && e.contains("missing"), "{e}");
    let e = with(serde_json::json!({"type": "vented", "Vb": 0.01, "fb": 40, "port_loss": 1.5}));
    assert!(e.contains("enclosure.port_area"), "{e}");
    let e = with(serde_json::json!({"type": "passive_radiator", "Vb": 0.01, "Sp": 0.01, "Mmp": 0.05}));
    assert!(e.contains("enclosure.Kmp") && e.contains("missing"), "{e}");
    let mut no_sd = base.clone();
    no_sd.as_object_mut().unwrap().remove("Sd");
    no_sd["enclosure"] = serde_json::json!({"type": "closed", "Vb": 0.01});
    let e = Parameters::from_json_value(&no_sd, "box.json").unwrap_err().to_string();
    assert!(e.contains("key `Sd`") && e.contains("closed"), "{e}");
}

//! `measure --virtual` on real drivers. The virtual transducer has every effect of a
//! real driver at once (LOG creep lambda 0.05; LR-3 with L3 = 0.5 L2, R3 = 3 R2; flux
//! modulation with Le 3 % down at 4 A; Rms 35 % up at 0.5 m/s), coil heating and 0.1 mV /
//! 0.1 mA sensor noise, IEC noise to 85 % of the range. The small stage chooses creep and
//! LR-3 on the data, the online estimator carries them and estimates Le(i) and Rms(v) too.
//!
//! Asserted (the accuracy bounds): converged; the model with all four effects reported;
//! Bl(x) within 2 %, Kms(x) within 3 %, Le(x) within 5 % over the reached range; Re (cold)
//! within 0.5 %; lambda, g2 and c2 within 20 %; the truth within 3 sd of the bands. And on
//! the plain driver, Le(i) and Rms(v) are estimated at none and not reported.

use coilscope_core::excitation::Excitation;
use coilscope_core::params::Creep;
use coilscope_core::{embedded_driver, Parameters, Poly};
use coilscope_ident::linear::Effects;
use coilscope_measure::device::VirtualDevice;
use coilscope_measure::signal::Source;
use coilscope_measure::{measure, MeasureOptions, Measurement};

fn worst(f: &Poly, g: &Poly, [lo, hi]: [f64; 2]) -> f64 {
    (0..=400)
        .map(|k| lo + (hi - lo) * k as f64 / 400.0)
        .map(|x| (f.eval(x) / g.eval(x) - 1.0).abs())
        .fold(0.0, coilscope_testkit::check::nan_max)
}

/// The driver with every effect (Le(i) and Rms(v) scaled to 4 A and 0.5 m/s, about the peaks
/// of SB17 and PTT4 at 85 % of their range).
fn real(p: &Parameters) -> Parameters {
    let (l2, r2) = p.l2r2.as_ref().map(|(l, r)| (l.c[0], r.c[0])).unwrap();
    Parameters {
        creep: Some(Creep { lambda: 0.05, f_ref: None }),
        l3r3: Some((0.5 * l2, 3.0 * r2)),
        le_i: Some(Poly { c: vec![1.0, 0.0, -0.03 / 16.0] }),
        rms_v: Some(Poly { c: vec![p.rms, 0.0, 0.35 * p.rms / 0.25] }),
        ..p.clone()
    }
}

fn run(p: &Parameters, seed: u64) -> Measurement {
    let [lo, hi] = p.x_range.unwrap();
    let mut dev = VirtualDevice::new(p, 48000.0, (1e-4, 1e-4), seed).unwrap();
    let mut src = Source::noise(&Excitation::Iec, 48000.0, seed).unwrap();
    let opts = MeasureOptions { mms: p.mms, target_x: Some(0.85 * hi.min(-lo)), ..Default::default() };
    measure(&mut dev, &mut src, &opts, None, |_| {}).unwrap_or_else(|e| panic!("{e}"))
}

/// Checks one measurement against its truth; returns the problems.
fn check(label: &str, m: &Measurement, truth: &Parameters) -> Vec<String> {
    let q = &m.params;
    let r = m.x_range;
    let (e_bl, e_k, e_le, e_re) = (
        worst(&q.bl, &truth.bl, r),
        worst(&q.kms, &truth.kms, r),
        worst(&q.le, &truth.le, r),
        (m.re_cold / truth.re - 1.0).abs(),
    );
    let j = m.result().to_json_value();
    let mut zmax: f64 = 0.0;
    for (which, f) in [("Bl", &truth.bl), ("Kms", &truth.kms), ("Le", &truth.le)] {
        let b = &j["uncertainty"][format!("{which}_band")];
        let xs = b["x"].as_array().unwrap();
        for k in 0..xs.len() {
            let (x, v, sd) = (xs[k].as_f64().unwrap(), b["value"][k].as_f64().unwrap(), b["sd"][k].as_f64().unwrap());
            zmax = coilscope_testkit::check::nan_max(zmax, (v - f.eval(x)).abs() / sd);
        }
    }
    let lambda = q.creep.as_ref().map_or(0.0, |c| c.lambda);
    let g2 = q.le_i.as_ref().map_or(0.0, |g| g.c[2]);
    let c2 = q.rms_v.as_ref().map_or(0.0, |r| r.c[2]);
    println!(
        "{label}: {} in {:.1} s, model {}, Bl {:.3} %, Kms {:.3} %, Le {:.3} %, Re(cold) {:.4} %, lambda {lambda:.4}, L3/R3 {:?}, g2 {g2:.4e}, c2 {c2:.4}, truth within {zmax:.2} sd, x {:.2}..{:.2} mm",
        m.stop_reason,
        m.seconds,
        m.effects.model_name(),
        100.0 * e_bl,
        100.0 * e_k,
        100.0 * e_le,
        100.0 * e_re,
        q.l3r3,
        r[0] * 1e3,
        r[1] * 1e3
    );
    let mut bad = vec![];
    if !m.converged {
        bad.push(format!("{label}: {}", m.stop_reason));
    }
    if !(e_bl <= 0.02 && e_k <= 0.03 && e_le <= 0.05 && e_re <= 0.005) {
        bad.push(format!("{label}: Bl {e_bl:.4}, Kms {e_k:.4}, Le {e_le:.4}, Re {e_re:.5}"));
    }
    if zmax > 3.0 {
        bad.push(format!("{label}: the truth lies {zmax:.1} sd outside the bands"));
    }
    let want = Effects {
        creep: truth.creep.is_some(),
        lr3: truth.l3r3.is_some(),
        le_i: truth.le_i.is_some(),
        rms_v: truth.rms_v.is_some(),
    };
    if m.effects != want {
        bad.push(format!("{label}: model {} (want {})", m.effects.model_name(), want.model_name()));
    }
    if let (Some(t), Some(c)) = (&truth.creep, &q.creep) {
        if (c.lambda / t.lambda - 1.0).abs() > 0.2 {
            bad.push(format!("{label}: lambda {} vs {}", c.lambda, t.lambda));
        }
    }
    if let (Some(t), Some(g)) = (&truth.le_i, &q.le_i) {
        if (g.c[2] / t.c[2] - 1.0).abs() > 0.2 {
            bad.push(format!("{label}: g2 {} vs {}", g.c[2], t.c[2]));
        }
    }
    if let (Some(t), Some(rv)) = (&truth.rms_v, &q.rms_v) {
        if (rv.c[2] / t.c[2] - 1.0).abs() > 0.2 {
            bad.push(format!("{label}: c2 {} vs {}", rv.c[2], t.c[2]));
        }
    }
    bad
}

#[test]
fn measure_finds_every_effect_of_a_real_sb17_and_ptt4() {
    let bad: Vec<String> = std::thread::scope(|sc| {
        let hs: Vec<_> = [("sb17cac35-4", 1u64), ("ptt4.0w04-01a", 2)]
            .into_iter()
            .map(|(name, seed)| {
                sc.spawn(move || {
                    let truth = real(&embedded_driver(name).unwrap());
                    let m = run(&truth, seed);
                    check(name, &m, &truth)
                })
            })
            .collect();
        hs.into_iter().flat_map(|h| h.join().unwrap()).collect()
    });
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

#[test]
fn measure_of_a_plain_driver_reports_no_large_signal_effect() {
    let p = embedded_driver("sb17cac35-4").unwrap();
    let m = run(&p, 3);
    let bad = check("sb17cac35-4 plain", &m, &p);
    assert!(bad.is_empty(), "{}", bad.join("\n"));
    assert!(m.dropped.le_i && m.dropped.rms_v && m.params.le_i.is_none() && m.params.rms_v.is_none());
    let j = m.result().to_json_value();
    assert_eq!(j["fit"]["model"], "LR-2");
    assert!(j["fit"]["models_note"].as_str().unwrap().contains("Le(i) and Rms(v)"), "{}", j["fit"]["models_note"]);
}

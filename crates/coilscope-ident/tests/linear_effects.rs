//! The linear fit identifies LOG creep and a second para-inductance branch, and the
//! data decide which of them a record supports.
//!
//! Records: periodic IEC noise (the whole record is one period, so `I = U / Z` holds bin by
//! bin exactly) through the core's small-signal impedance (`small_signal::impedance`, the
//! mechanical form with the creep bank; the fit uses its own electrical-analogue code), with
//! 70 dB sensor noise on both channels. Drivers: the three bundled ones and the large
//! semi-inductive coil (Le 2.9 mH, L2 6.7 mH); effects: none, creep with lambda 0.02, 0.05 and
//! 0.1, LR-3 with L3 = 0.5 L2 and R3 = 3 R2, and both.
//!
//! Asserted (the accuracy bounds): the chosen model is the true one; lambda within 20 %; Re
//! within 0.5 %; Bl (Mms given) within 2 %, Kms (the dynamic stiffness at the resonance)
//! within 3 %; the residual within 2x the noise floor; and the reported sds cover the
//! truth: over every identified quantity of every record, at least 90 % within 2 sd and 97 %
//! within 3 sd (a Gaussian: 95.4 and 99.7 %), none beyond 4.5 sd. Measured over the sweep
//! (48 records, 414 values): 92.8 % within 2 sd, 98.6 % within 3, the largest 3.6 sd (one
//! noise record's Lces, +0.003 %).

use coilscope_core::excitation::{add_sensor_noise, generate, named_rng, Excitation, SignalSpec};
use coilscope_core::fft::{irfft, rfft};
use coilscope_core::params::Creep;
use coilscope_core::small_signal::{displacement_per_current, impedance};
use coilscope_core::{embedded_driver, Parameters};
use coilscope_ident::linear::{
    fit_linear, fit_linear_record, fit_linear_record_from, scale_by_mms, Effects, EffectsChoice, LinearOptions,
};
use rand::Rng;

fn driver(name: &str) -> Parameters {
    embedded_driver(name).unwrap_or_else(|| {
        let path = format!("{}/../../testdata/drivers/{name}.json", env!("CARGO_MANIFEST_DIR"));
        Parameters::from_json_str(&std::fs::read_to_string(&path).unwrap(), &path).unwrap()
    })
}

/// A periodic small-signal record of `p` (peak excursion about 0.1 mm), 4 s at 48 kHz.
fn record(p: &Parameters, seed: u64) -> (Vec<f64>, Vec<f64>) {
    let fs = 48000.0;
    let u0 = generate(&Excitation::Iec, &SignalSpec { fs, seconds: 4.0, rms: 1.0, fade: 0.0, seed }).unwrap();
    let n = u0.len();
    let filter = |x: &[f64], h: &dyn Fn(f64) -> realfft::num_complex::Complex64| {
        let mut s = rfft(x);
        for (k, c) in s.iter_mut().enumerate() {
            *c = if k == 0 { realfft::num_complex::Complex64::new(0.0, 0.0) } else { *c * h(k as f64 * fs / n as f64) };
        }
        irfft(&s, n).iter().map(|v| v / n as f64).collect::<Vec<f64>>()
    };
    let x = filter(&u0, &|f| displacement_per_current(p, f) / impedance(p, f));
    let g = 1e-4 / x.iter().fold(0.0f64, |a, v| a.max(v.abs()));
    let mut u: Vec<f64> = u0.iter().map(|v| v * g).collect();
    let mut i = filter(&u, &|f| 1.0 / impedance(p, f));
    add_sensor_noise(&mut u, 70.0, seed, "sensor-noise/voltage");
    add_sensor_noise(&mut i, 70.0, seed, "sensor-noise/current");
    (u, i)
}

fn with(p: &Parameters, lambda: Option<f64>, lr3: bool) -> Parameters {
    let (l2, r2) = p.l2r2.as_ref().map(|(l, r)| (l.c[0], r.c[0])).unwrap();
    Parameters {
        creep: lambda.map(|lambda| Creep { lambda, f_ref: None }),
        l3r3: lr3.then_some((0.5 * l2, 3.0 * r2)),
        ..p.clone()
    }
}

fn rel(a: f64, b: f64) -> f64 {
    a / b - 1.0
}

/// Fit one record and check it against the truth; returns a line for the log.
fn check(name: &str, truth: &Parameters, seed: u64, bad: &mut Vec<String>, zs: &mut Vec<f64>) -> String {
    let (u, i) = record(truth, seed);
    let fit = fit_linear(&u, &i, 48000.0, name, |_| {}).unwrap();
    let got = scale_by_mms(&fit, truth.mms).unwrap();
    let want = Effects { creep: truth.creep.is_some(), lr3: truth.l3r3.is_some(), ..Effects::NONE };
    let label = format!("{name} {} seed {seed}", want.model_name());
    let mut line = format!(
        "{label}: chose {} (tried {}), residual {:.2e}",
        fit.effects.model_name(),
        fit.tried.iter().map(|(m, r)| format!("{m} {r:.2e}")).collect::<Vec<_>>().join(", "),
        fit.residual_rel
    );
    if fit.effects != want {
        bad.push(format!("{label}: chose {}", fit.effects.model_name()));
        return line;
    }
    // The noise floor: 70 dB on each channel, the current's own and the voltage's through Z.
    let floor = 2.0f64.sqrt() * 10f64.powf(-70.0 / 20.0);
    if fit.residual_rel > 2.0 * floor {
        bad.push(format!("{label}: residual {:.2e} above 2x the noise floor {floor:.2e}", fit.residual_rel));
    }
    let (l2, r2) = truth.l2r2.as_ref().map(|(l, r)| (l.c[0], r.c[0])).unwrap();
    let bl2 = truth.bl.c[0].powi(2);
    let tv = [truth.re, truth.le.c[0], l2, r2, bl2 / truth.rms, truth.mms / bl2, bl2 / truth.kms.c[0]];
    let names = ["Re", "Le", "L2", "R2", "Res", "Cmes", "Lces"];
    for k in 0..7 {
        let e = rel(fit.p[k], tv[k]);
        let z = e.abs() / (fit.sigma_rel[k].powi(2)).sqrt();
        line += &format!(", {} {:+.3} % ({z:.1} sd)", names[k], 100.0 * e);
        zs.push(z);
    }
    if rel(got.re, truth.re).abs() > 0.005 {
        bad.push(format!("{label}: Re {:+.3} %", 100.0 * rel(got.re, truth.re)));
    }
    if rel(got.bl.c[0], truth.bl.c[0]).abs() > 0.02 || rel(got.kms.c[0], truth.kms.c[0]).abs() > 0.03 {
        bad.push(format!(
            "{label}: Bl {:+.3} %, Kms {:+.3} %",
            100.0 * rel(got.bl.c[0], truth.bl.c[0]),
            100.0 * rel(got.kms.c[0], truth.kms.c[0])
        ));
    }
    if let (Some(c), Some((lambda, sd))) = (&truth.creep, fit.creep) {
        let z = (lambda - c.lambda).abs() / sd;
        line += &format!(", lambda {lambda:.4} (true {}, {z:.1} sd)", c.lambda);
        zs.push(z);
        if rel(lambda, c.lambda).abs() > 0.2 {
            bad.push(format!("{label}: lambda {lambda:.4} +- {sd:.4} vs {}", c.lambda));
        }
    }
    if let (Some((l3, r3)), Some((v, sd))) = (truth.l3r3, fit.lr3) {
        for (n, got, want, s) in [("L3", v[0], l3, sd[0]), ("R3", v[1], r3, sd[1])] {
            let e = rel(got, want);
            let z = e.abs() / (s * s).sqrt();
            line += &format!(", {n} {:+.3} % ({z:.1} sd)", 100.0 * e);
            zs.push(z);
        }
    }
    line
}

/// `sweep` over `names` and `seeds`. The share within 2 sd is asserted only over more than
/// one seed per driver: the values of one seed share one noise realisation (its four creep
/// records put lambda and Res at 2.0-2.1 sd together), so one seed's share says little.
fn sweep(names: &[&str], seeds: std::ops::Range<u64>) {
    let several = seeds.end - seeds.start > 1;
    // One thread per driver (the records are independent); the lines print in order.
    let per_driver: Vec<(Vec<String>, Vec<String>, Vec<f64>)> = std::thread::scope(|sc| {
        let handles: Vec<_> = names
            .iter()
            .enumerate()
            .map(|(d, &name)| {
                let seeds = seeds.clone();
                sc.spawn(move || {
                    let (mut lines, mut bad, mut zs) = (vec![], vec![], vec![]);
                    let p = driver(name);
                    for seed in seeds.map(|s| s + 10 * d as u64) {
                        let mut rng = named_rng(seed, "linear_effects/lambda");
                        for (lambda, lr3) in [
                            (None, false),
                            (Some(0.02), false),
                            (Some(0.05), false),
                            (Some(0.1), false),
                            (None, true),
                            (Some(0.02 + 0.08 * rng.random::<f64>()), true),
                        ] {
                            lines.push(check(name, &with(&p, lambda, lr3), seed, &mut bad, &mut zs));
                        }
                    }
                    (lines, bad, zs)
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let (mut bad, mut zs, mut n) = (vec![], vec![], 0);
    for (lines, b, z) in per_driver {
        for l in &lines {
            println!("{l}");
        }
        n += lines.len();
        bad.extend(b);
        zs.extend(z);
    }
    println!("{} of {n} records within the figures", n - bad.len());
    let share = |k: f64| zs.iter().filter(|&&z| z <= k).count() as f64 / zs.len() as f64;
    let worst = zs.iter().cloned().fold(0.0, coilscope_testkit::check::nan_max);
    let coverage = format!(
        "{} values: {:.1} % within 2 sd, {:.1} % within 3 sd, the largest {worst:.1} sd",
        zs.len(),
        100.0 * share(2.0),
        100.0 * share(3.0)
    );
    println!("{coverage}");
    if (several && share(2.0) < 0.9) || share(3.0) < 0.97 || worst > 4.5 {
        bad.push(format!("the sds do not cover the truth: {coverage}"));
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

/// Debug-profile sample: SB17, one seed.
#[test]
fn creep_and_lr3_are_identified_and_chosen_on_sb17() {
    sweep(&["sb17cac35-4"], 1..2);
}

/// The sweep: the three bundled drivers and the large coil, two seeds each (one seed per
/// driver differs from the others: 10 d + 1, 10 d + 2).
#[test]
#[ignore = "release-profile sweep: cargo test --release -p coilscope-ident --test linear_effects -- --ignored"]
fn creep_and_lr3_over_drivers_and_seeds() {
    sweep(&["sb17cac35-4", "ptt4.0w04-01a", "18wu-4741t-00", "large-coil"], 2..4);
}

/// A fit with fixed effects that takes the LR-2 model from an earlier fit of the
/// same record (`identify`'s effects search, from its start fit) is the fit that makes it
/// again, bit for bit: creep and LR-3, alone and together, on a record with both.
#[test]
fn lr2_fit_reused_is_the_fit() {
    let truth = with(&driver("sb17cac35-4"), Some(0.05), true);
    let (u, i) = record(&truth, 3);
    let start = fit_linear_record(
        &u,
        &i,
        48000.0,
        "sb17",
        &LinearOptions { effects: EffectsChoice::Auto, ..LinearOptions::LARGE_SIGNAL_START },
        |_| {},
    )
    .unwrap();
    for e in [
        Effects { creep: true, ..Effects::NONE },
        Effects { lr3: true, ..Effects::NONE },
        Effects { creep: true, lr3: true, ..Effects::NONE },
    ] {
        let opts = LinearOptions { effects: EffectsChoice::Fixed(e), ..LinearOptions::LARGE_SIGNAL_START };
        let (mut fresh_states, mut reused_states) = (0, 0);
        let fresh = fit_linear_record(&u, &i, 48000.0, "sb17", &opts, |_| fresh_states += 1).unwrap();
        let reused =
            fit_linear_record_from(&u, &i, 48000.0, "sb17", &opts, Some(&start.lr2), |_| reused_states += 1).unwrap();
        let m = e.model_name();
        assert_eq!(
            (fresh.p, fresh.sigma_rel, fresh.residual_rel),
            (reused.p, reused.sigma_rel, reused.residual_rel),
            "{m}"
        );
        assert_eq!((fresh.creep, fresh.lr3, fresh.effects), (reused.creep, reused.lr3, reused.effects), "{m}");
        assert_eq!(fresh.tried, reused.tried, "{m}");
        // The LR-2 model's LM states are not run again.
        assert!(
            reused_states < fresh_states,
            "{m}: {reused_states} LM states with the LR-2 fit given, {fresh_states} without"
        );
    }
}

/// Forcing creep on a record without it gives lambda near zero, inside its band.
#[test]
fn forced_creep_on_a_record_without_it_finds_none() {
    let p = driver("ptt4.0w04-01a");
    let (u, i) = record(&p, 5);
    let opts =
        LinearOptions { effects: EffectsChoice::Fixed(Effects { creep: true, ..Effects::NONE }), ..Default::default() };
    let fit = fit_linear_record(&u, &i, 48000.0, "ptt4", &opts, |_| {}).unwrap();
    let (lambda, sd) = fit.creep.unwrap();
    println!("lambda {lambda:.5} +- {sd:.5}");
    assert!(lambda.abs() < 3.0 * sd && lambda.abs() < 0.005, "lambda {lambda} +- {sd}");
}

/// The same identification on records of coilscope's time-domain simulator (the extended
/// model: the creep bank's and LR-3's own states, integrated with the rest), 4 s of IEC
/// noise from rest with 50 ms fades at 0.1 mm peak, 70 dB: the effects are chosen and
/// lambda is within 20 %. Release-profile (it simulates 6 x 4 s per driver to set the level).
#[test]
#[ignore = "release-profile sweep: cargo test --release -p coilscope-ident --test linear_effects -- --ignored"]
fn time_domain_records_give_the_same_answer() {
    use coilscope_core::simulate::{gain_for_peak, SimOptions};
    let mut bad = vec![];
    for (name, lambda, lr3) in
        [("sb17cac35-4", Some(0.05), false), ("ptt4.0w04-01a", None, true), ("18wu-4741t-00", Some(0.07), true)]
    {
        let truth = with(&driver(name), lambda, lr3);
        let unit = generate(&Excitation::Iec, &SignalSpec { fs: 48000.0, seconds: 4.0, rms: 1.0, fade: 0.05, seed: 3 })
            .unwrap();
        let (_, tr) = gain_for_peak(&truth, 48000.0, &unit, 1e-4, &SimOptions::default()).unwrap();
        let (mut u, mut i) = (tr.u, tr.i);
        add_sensor_noise(&mut u, 70.0, 3, "sensor-noise/voltage");
        add_sensor_noise(&mut i, 70.0, 3, "sensor-noise/current");
        let fit = fit_linear(&u, &i, 48000.0, name, |_| {}).unwrap();
        let want = Effects { creep: lambda.is_some(), lr3, ..Effects::NONE };
        let got = scale_by_mms(&fit, truth.mms).unwrap();
        println!(
            "{name} {}: chose {}, residual {:.2e}, lambda {:?}, Re {:+.3} %, Bl {:+.3} %, Kms {:+.3} %",
            want.model_name(),
            fit.effects.model_name(),
            fit.residual_rel,
            fit.creep,
            100.0 * rel(got.re, truth.re),
            100.0 * rel(got.bl.c[0], truth.bl.c[0]),
            100.0 * rel(got.kms.c[0], truth.kms.c[0])
        );
        if fit.effects != want {
            bad.push(format!("{name}: chose {}", fit.effects.model_name()));
        }
        if let (Some(l), Some((g, _))) = (lambda, fit.creep) {
            if rel(g, l).abs() > 0.2 {
                bad.push(format!("{name}: lambda {g} vs {l}"));
            }
        }
        if rel(got.re, truth.re).abs() > 0.005
            || rel(got.bl.c[0], truth.bl.c[0]).abs() > 0.02
            || rel(got.kms.c[0], truth.kms.c[0]).abs() > 0.03
        {
            bad.push(format!("{name}: Re, Bl or Kms off"));
        }
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

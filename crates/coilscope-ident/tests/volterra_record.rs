//! `identify --method volterra` on a record: the Volterra identification from a
//! recorded readable multitone (`Excitation::Readable`, periodic in 1 s), with sensor noise
//! on both channels: the steady periods are averaged, the harmonic ratios' noise comes from
//! the scatter between periods, and the fit's bands come from it. At small level the
//! second-order series are within 5 % and the truth (to second order) lies within the bands;
//! at large level the fit's chi^2 names the truncation (the feed-back of the distortion).

use coilscope_core::excitation::{add_sensor_noise, generate, Excitation, SignalSpec};
use coilscope_core::simulate::{simulate, SimOptions};
use coilscope_core::{embedded_driver, Parameters, Poly};
use coilscope_ident::volterra::{identify_volterra_weighted, record_lines, truncation_check};

use coilscope_ident::volterra::series_error as err;

struct Case {
    name: &'static str,
    frac: f64,
    seed: u64,
    tones: usize,
    seconds: f64,
    snr: f64,
}

fn run(c: &Case) -> ([f64; 3], [f64; 3], f64, f64) {
    let truth = embedded_driver(c.name).unwrap();
    let [lo, hi] = truth.x_range.unwrap();
    let range = hi.min(-lo);
    let f0 = truth.resonance_hz();
    let fs = 48000.0;
    let exc = Excitation::Readable { f_lo: (0.5 * f0).round(), f_hi: (20.0 * f0).round(), count: c.tones, crest: None };
    let mut volts = 0.2;
    let mut rec = None;
    for _ in 0..4 {
        let u = generate(&exc, &SignalSpec { fs, seconds: c.seconds, rms: volts, fade: 0.05, seed: c.seed }).unwrap();
        let t = simulate(&truth, fs, &u, &SimOptions::default()).unwrap();
        let peak = t.x[fs as usize..].iter().fold(0.0f64, |a, v| a.max(v.abs()));
        let ok = (peak / (c.frac * range) - 1.0).abs() < 0.05;
        rec = Some((u, t.i));
        if ok {
            break;
        }
        volts *= c.frac * range / peak;
    }
    let (mut u, mut i) = rec.unwrap();
    add_sensor_noise(&mut u, c.snr, c.seed, "noise-u");
    add_sensor_noise(&mut i, c.snr, c.seed, "noise-i");
    let lines = record_lines(&u, &i, fs, c.name).unwrap();
    let mut start: Parameters = truth.clone();
    start.bl = Poly::constant(truth.bl.c[0]);
    start.kms = Poly::constant(truth.kms.c[0]);
    start.le = Poly::constant(truth.le.c[0]);
    let (h, noise) = lines.harmonics(&start);
    let fit = identify_volterra_weighted(&start, &h, Some(&noise)).unwrap();
    let trunc = truncation_check(&fit, &lines, &h, &noise).unwrap();
    let xs = 0.5 * range;
    let q = &fit.params;
    let e = [err(&q.bl, &truth.bl, xs), err(&q.kms, &truth.kms, xs), err(&q.le, &truth.le, xs)];
    let z = ["Bl", "Kms", "Le"].map(|w| {
        let b = fit.band(w, [-xs, xs], 21);
        let t = match w {
            "Bl" => &truth.bl,
            "Kms" => &truth.kms,
            _ => &truth.le,
        };
        let t2 = Poly { c: t.c.iter().take(3).copied().collect() };
        b.x.iter()
            .zip(&b.value)
            .zip(&b.sd)
            .filter(|(_, s)| **s > 0.0)
            .map(|((x, v), s)| (v - t2.eval(*x)).abs() / s)
            .fold(0.0, coilscope_testkit::check::nan_max)
    });
    println!(
        "{} seed {} at {:.1} % of the range ({volts:.3} V, {} tones, {} periods): Bl {:.2} %, Kms {:.2} %, Le {:.2} %; z {:.2} {:.2} {:.2}; chi2/dof {:.2}, truncation {trunc:.2}, misfit {:.2e}",
        c.name,
        c.seed,
        100.0 * c.frac,
        lines.bins.len(),
        lines.starts.len(),
        100.0 * e[0],
        100.0 * e[1],
        100.0 * e[2],
        z[0],
        z[1],
        z[2],
        fit.chi2_dof.unwrap(),
        fit.misfit
    );
    (e, z, fit.chi2_dof.unwrap(), fit.misfit)
}

/// At 2.5 % of the range (16 s, 90 dB sensor noise on both channels, two seeds, three
/// drivers): no warning (the kernels explain the lines to their noise, and the truncation is
/// below it), Kms within 5 % of the truth's second-order series over half the range, and the
/// truth within 3 sd of each band (Bl and Le are often not resolved at this level: Bl 1-7 %,
/// Le 40-640 % off, with bands as wide; measured z <= 2). At 30 % of the range the warning
/// fires on every driver (chi^2/dof 280-1180). Not caught (printed, README): 18WU at 10 % of
/// its range, where the true curves' terms beyond x^2 (order-4 and -5 lines on the 2nd and
/// 3rd harmonic) bias Bl and Kms by 3-8 % at z 5-10 with chi^2/dof 1.2-2.3.
#[test]
fn volterra_from_a_recorded_multitone_is_honest_at_small_level_and_warns_at_large() {
    let mut bad = vec![];
    for name in ["sb17cac35-4", "ptt4.0w04-01a", "18wu-4741t-00"] {
        for seed in [1, 2] {
            let (e, z, chi2, trunc) = run(&Case { name, frac: 0.025, seed, tones: 20, seconds: 16.0, snr: 90.0 });
            if chi2 > 2.0 || trunc > 1.0 {
                bad.push(format!("{name} seed {seed} at 2.5 %: a truncation warning at small level (chi2/dof {chi2:.2}, truncation {trunc:.2})"));
            }
            if e[1] > 0.05 {
                bad.push(format!("{name} seed {seed} at 2.5 %: Kms {:.2} % off", 100.0 * e[1]));
            }
            if z.iter().any(|v| *v > 3.0) {
                bad.push(format!("{name} seed {seed} at 2.5 %: the truth outside 3 sd (z {z:?})"));
            }
        }
        let (_, _, chi2, trunc) = run(&Case { name, frac: 0.3, seed: 3, tones: 20, seconds: 16.0, snr: 90.0 });
        if !(chi2 > 2.0 || trunc > 1.0) {
            bad.push(format!("{name} at 30 %: no truncation warning (chi2/dof {chi2:.2}, truncation {trunc:.2})"));
        }
        run(&Case { name, frac: 0.1, seed: 3, tones: 20, seconds: 16.0, snr: 90.0 });
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

//! Volterra identification (seed paper 3.2.2.1): the current's 2nd and 3rd
//! harmonics of steady sines at nine frequencies (0.5-20 times the resonance), measured on
//! the full model, give Bl, Kms, Le to second order through the Volterra kernels. At small
//! level the series come out within 5 % (of the size of each curve's second-order
//! nonlinearity over half the range); over level the error grows, because the feed-back of
//! the distortion that the truncated series leaves out grows: the table is printed (and is in
//! the README). Sines one at a time (a stepped sine), not a multitone: a multitone's
//! intermodulation lines need the off-diagonal kernels, which `probe` does not give yet.

use coilscope_analysis::distortion::{harmonics, Output, SteadyOptions};
use coilscope_core::{embedded_driver, Parameters, Poly};
use coilscope_ident::volterra::identify_volterra;

use coilscope_ident::volterra::series_error as err;

fn run(name: &str, fracs: &[f64]) -> Vec<(f64, f64, [f64; 3], f64)> {
    let truth = embedded_driver(name).unwrap();
    let [lo, hi] = truth.x_range.unwrap();
    let range = hi.min(-lo);
    let xs = 0.5 * range;
    let mut start = truth.clone();
    start.bl = Poly::constant(truth.bl.c[0]);
    start.kms = Poly::constant(truth.kms.c[0]);
    start.le = Poly::constant(truth.le.c[0]);
    let f0 = truth.resonance_hz();
    let freqs: Vec<f64> = [0.5, 0.7, 1.0, 1.4, 2.0, 3.0, 5.0, 10.0, 20.0].iter().map(|k| k * f0).collect();
    let opts = SteadyOptions::default();
    let mut rows = vec![];
    for &frac in fracs {
        // The level whose largest peak over the tones is `frac` of the range.
        let probe_v = 1.0;
        let peak1 = freqs
            .iter()
            .map(|&f| harmonics(&truth, f, probe_v, Output::Current, &opts).unwrap().x_peak)
            .map(|[a, b]| b.max(-a))
            .fold(0.0, coilscope_testkit::check::nan_max);
        let mut volts = probe_v * frac * range / peak1;
        let mut measured = vec![];
        for _ in 0..3 {
            measured =
                freqs.iter().map(|&f| harmonics(&truth, f, volts, Output::Current, &opts).unwrap()).collect::<Vec<_>>();
            let peak =
                measured.iter().map(|h| h.x_peak[1].max(-h.x_peak[0])).fold(0.0, coilscope_testkit::check::nan_max);
            if (peak / (frac * range) - 1.0).abs() < 0.03 {
                break;
            }
            volts *= frac * range / peak;
        }
        let fit = identify_volterra(&start, &measured).unwrap();
        let q: &Parameters = &fit.params;
        let e = [err(&q.bl, &truth.bl, xs), err(&q.kms, &truth.kms, xs), err(&q.le, &truth.le, xs)];
        println!(
            "{name} at {:.1} % of the range ({volts:.2} V): Bl {:.2} %, Kms {:.2} %, Le {:.2} % of their 2nd-order nonlinearity over +-{:.1} mm; kernel misfit {:.2e}",
            100.0 * frac,
            100.0 * e[0],
            100.0 * e[1],
            100.0 * e[2],
            xs * 1e3,
            fit.misfit
        );
        rows.push((frac, volts, e, fit.misfit));
    }
    rows
}

/// Required: within 5 % at small level. Measured (README): at 2.5 % of the range the worst
/// curve is within 2.9 % (18WU's Le; SB17 and PTT4 within 0.3 %); the truncation error grows
/// as the square of the level (18WU's Le 11 % at 5 %, 43 % at 10 %). Asserted: within 5 % at
/// 2.5 % of the range. And the paper's point, that it fails at large level: at 90 % of the
/// range one of the curves is more than 20 % off (SB17: Kms 81 %).
#[test]
fn volterra_kernels_give_the_series_at_small_level_and_fail_at_large() {
    let mut bad = vec![];
    for name in ["sb17cac35-4", "ptt4.0w04-01a", "18wu-4741t-00"] {
        let rows = run(name, &[0.025, 0.05, 0.1, 0.3, 0.6, 0.9]);
        for (frac, _, e, _) in &rows {
            let worst = e.iter().cloned().fold(0.0, coilscope_testkit::check::nan_max);
            if *frac <= 0.025 && worst > 0.05 {
                bad.push(format!("{name} at {frac}: {e:?}"));
            }
            if *frac >= 0.9 && worst < 0.2 {
                bad.push(format!("{name} at {frac}: the Volterra fit no longer fails ({e:?}): the comparison does not show the feed-back"));
            }
        }
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

/// The required case: from a multitone. `level_study`: a readable multitone (no product of
/// order 2-4 of other tones on any tone's 2nd or 3rd harmonic, none on a mains line) of eight
/// tones between 0.5 and 20 times the resonance, in its steady state on the full model; the
/// same fit. Within 5 % at 2.5 % of the range (by the peak of the sum), on the three drivers
/// (measured: within 3.7 %, PTT4's Le); the report tabulates the same study for a result.
#[test]
fn volterra_kernels_from_a_multitone_give_the_series_at_small_level() {
    use coilscope_ident::volterra::level_study;
    let mut bad = vec![];
    for name in ["sb17cac35-4", "ptt4.0w04-01a", "18wu-4741t-00"] {
        let truth = embedded_driver(name).unwrap();
        for r in level_study(&truth, &[0.025, 0.1, 0.3]).unwrap() {
            println!("{name} multitone at {:.1} % of the range ({:.3} V): Bl {:.2} %, Kms {:.2} %, Le {:.2} %; misfit {:.2e}", 100.0 * r.frac, r.volts, 100.0 * r.err[0], 100.0 * r.err[1], 100.0 * r.err[2], r.misfit);
            if r.frac <= 0.025 && r.err.iter().any(|v| *v > 0.05) {
                bad.push(format!("{name} at {}: {:?}", r.frac, r.err));
            }
        }
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

//! Unit tests of the small-signal fit.

use super::*;

/// The linear fit names the larger branch LR-2, as `identify` does, its sds moving with
/// it; one already in that order is left alone.
#[test]
fn the_larger_branch_is_named_lr2() {
    let mut p = [3.4, 1.1e-4, 2.7e-4, 0.0725, 72.0, 3.8e-4, 6.3e-2];
    let mut sd = [1e-4, 2e-3, 3e-3, 4e-3, 1e-3, 1e-3, 1e-3];
    let mut lr3 = Some(([5.4e-4, 0.29], [5e-3, 6e-3]));
    assert!(lr3_named_first(&mut p, &mut sd, &mut lr3));
    assert_eq!((p[2], p[3], sd[2], sd[3]), (5.4e-4, 0.29, 5e-3, 6e-3));
    assert_eq!(lr3, Some(([2.7e-4, 0.0725], [3e-3, 4e-3])));
    assert!(!lr3_named_first(&mut p, &mut sd, &mut lr3));
    assert!(!lr3_named_first(&mut p, &mut sd, &mut None));
}

/// The model choice's share of each sd is the largest move to a model that fits as well,
/// in either direction; the branch's partition is not one; with no such model there is none.
#[test]
fn the_model_choices_spread_is_the_largest_move_to_an_equal_model() {
    let chosen = [1.0f64, -9.0, -8.0, 0.5, 3.0, -7.0, -2.0];
    let mut up = chosen;
    up[0] += 0.05f64.ln_1p();
    up[1] -= 0.3;
    up[2] += 1.0;
    let mut down = chosen;
    down[0] -= 0.02f64.ln_1p();
    down[5] += 0.04f64.ln_1p();
    let m = fit::model_spread(&chosen, &[up, down]);
    assert!((m[0] - 0.05).abs() < 1e-12, "Re's spread {}", m[0]);
    assert!((m[1] - (0.3f64.exp() - 1.0)).abs() < 1e-12, "Le's spread {}", m[1]);
    assert!((m[5] - 0.04).abs() < 1e-12, "Cmes's spread {}", m[5]);
    assert_eq!((m[2], m[3], m[4], m[6]), (0.0, 0.0, 0.0, 0.0));
    let mut far = chosen;
    far[4] += 5.0;
    assert_eq!(fit::model_spread(&chosen, &[far])[4], 1.0);
    assert_eq!(fit::model_spread(&chosen, &[]), [0.0; 7]);
}

/// `ChainFactor::at` (the corners' filter coefficients once per theta) gives what the
/// chain factor was per bin, each corner through `hp_response`, to the last bit: its
/// value and its derivatives, every combination of terms on, over random delays, corners
/// and frequencies.
#[test]
fn the_chain_factor_is_hp_response_s() {
    use coilscope_core::chain::hp_response;
    use rand::Rng;
    let mut rng = coilscope_core::excitation::named_rng(3, "linear-test/chain-factor");
    for case in 0..64 {
        let fs = [44100.0, 48000.0, 96000.0][case % 3];
        let terms = ChainTerms { fs, delay: case & 4 == 0, hp_u: case & 8 == 0, hp_i: case & 16 == 0 };
        let th: Vec<f64> = [rng.random_range(-0.6..0.6), rng.random_range(0.0..6.0), rng.random_range(0.0..6.0)]
            .into_iter()
            .zip(terms.on())
            .filter(|(_, on)| *on)
            .map(|(v, _)| v)
            .collect();
        let [tau, fu, fi] = terms.values(&th);
        let c = |tau: f64, fu: f64, fi: f64, f: f64| {
            Complex64::from_polar(1.0, -2.0 * PI * f * tau / fs) * hp_response(fi, f, fs) / hp_response(fu, f, fs)
        };
        let prepared = terms.factor_at(&th);
        for _ in 0..50 {
            let f = rng.random_range(1.0..0.45 * fs);
            let (c0, d) = prepared.at(f, true);
            let h = CHAIN_CORNER_STEP;
            let mut want = vec![];
            if terms.delay {
                want.push(c(tau, fu, fi, f) * Complex64::new(0.0, -2.0 * PI * f / fs));
            }
            if terms.hp_u {
                want.push((c(tau, fu + h, fi, f) - c(tau, fu - h, fi, f)) / (2.0 * h));
            }
            if terms.hp_i {
                want.push((c(tau, fu, fi + h, f) - c(tau, fu, fi - h, f)) / (2.0 * h));
            }
            assert_eq!(c0, c(tau, fu, fi, f), "case {case} at {f} Hz");
            assert_eq!(d, want, "case {case} at {f} Hz");
            assert_eq!(prepared.at(f, false), (c0, vec![]));
        }
    }
}

#[test]
fn analytic_gradient_matches_finite_differences() {
    let p = [3.4, 1.1e-4, 5.4e-4, 0.29, 72.0, 3.8e-4, 6.3e-2];
    for f in [15.0, 32.0, 300.0, 5000.0] {
        let (z, g) = model_impedance_and_gradient(&p, f);
        for k in 0..7 {
            let h = 1e-6_f64;
            let mut a = p;
            let mut b = p;
            a[k] *= h.exp();
            b[k] *= (-h).exp();
            let fd = (model_impedance(&a, f) - model_impedance(&b, f)) / (2.0 * h);
            // Central differences: truncation ~h^2 |g|, round-off ~eps |Z| / h.
            let tol = 1e-6 * g[k].norm() + 1e-9 * z.norm();
            assert!((fd - g[k]).norm() < tol, "{} at {f}: {fd} vs {}", NAMES[k], g[k]);
        }
    }
}

#[test]
fn the_current_error_jacobian_matches_finite_differences_with_transient_and_delay() {
    // Every column of the LM problem (bounded LR-2 corner, the extra effects' unknowns,
    // transient coefficients, the skew check's delay) against central differences of the
    // residual, for each set of effects.
    let p = [3.4, 1.1e-4, 5.4e-4, 0.29, 72.0, 3.8e-4, 6.3e-2];
    let freqs: Vec<f64> = (1..60).map(|k| 3.0 * 1.12f64.powi(k)).collect();
    let u: Vec<Complex64> =
        freqs.iter().enumerate().map(|(k, _)| Complex64::from_polar(1.0 + 0.1 * k as f64, 0.7 * k as f64)).collect();
    let i: Vec<Complex64> = freqs.iter().zip(&u).map(|(&f, u)| u / model_impedance(&p, f) * 1.01).collect();
    let w: Vec<f64> = freqs.iter().map(|f| 1.0 / (1.0 + f / 1000.0)).collect();
    let (mut lo, mut hi) = ([f64::NEG_INFINITY; 7], [f64::INFINITY; 7]);
    lo[2] = (1.0 / (2.0 * PI * 20000.0)).ln();
    hi[2] = (1.0 / (2.0 * PI * 3.0)).ln();
    let map = ParamMap { lo, hi };
    // A curve without phase is a curve's problem: unit current and weights, no transient
    // term, no chain.
    for (creep, lr3, magnitude_only) in [
        (false, false, false),
        (true, false, false),
        (false, true, false),
        (true, true, false),
        (false, false, true),
        (true, true, true),
    ] {
        let effects = Effects { creep, lr3, ..Effects::NONE };
        let prob = if magnitude_only {
            CurrentError {
                f: freqs.clone(),
                u: u.clone(),
                i: vec![Complex64::new(1.0, 0.0); freqs.len()],
                w: vec![1.0; freqs.len()],
                norm: 3.0,
                map: map.clone(),
                omega0: 2.0 * PI * 250.0,
                n_transient: 0,
                effects,
                chain: None,
                magnitude_only,
            }
        } else {
            CurrentError {
                f: freqs.clone(),
                u: u.iter().zip(&w).map(|(u, w)| u * w).collect(),
                i: i.iter().zip(&w).map(|(i, w)| i * w).collect(),
                w: w.clone(),
                norm: 3.0,
                map: map.clone(),
                omega0: 2.0 * PI * 250.0,
                n_transient: N_TRANSIENT,
                effects,
                chain: Some(ChainTerms { fs: 48000.0, delay: true, hp_u: true, hp_i: true }),
                magnitude_only,
            }
        };
        let mut th = map.theta(&ParamMap::q_of(&p));
        if creep {
            th.push(0.06);
        }
        if lr3 {
            th.extend([0.7, (0.8f64).ln()]);
        }
        if !magnitude_only {
            th.extend([0.02, -0.01, 0.005, 0.003, 0.4, 2.0, 3.5]);
        }
        let (_, jac) = prob.residual_jacobian(&th);
        for c in 0..th.len() {
            let h = 1e-6;
            let (mut a, mut b) = (th.clone(), th.clone());
            a[c] += h;
            b[c] -= h;
            let fd = (prob.residual(&a) - prob.residual(&b)) / (2.0 * h);
            let err = (&fd - jac.column(c)).amax();
            assert!(
                err <= 1e-6 * fd.amax().max(1e-9),
                "{effects:?}, magnitude only {magnitude_only}: column {c}: {err} of {}",
                fd.amax()
            );
        }
    }
}

/// The fit's impedance with creep and LR-3 is the core's small-signal impedance of the
/// same parameter set (two codes: the fit's electrical-analogue form and the core's
/// mechanical form).
#[test]
fn impedance_with_effects_equals_the_core_small_signal_impedance() {
    let mut d = coilscope_core::embedded_driver("sb17cac35-4").unwrap();
    let (l2, r2) = (d.l2r2.as_ref().unwrap().0.c[0], d.l2r2.as_ref().unwrap().1.c[0]);
    d.creep = Some(coilscope_core::params::Creep { lambda: 0.07, f_ref: None });
    d.l3r3 = Some((0.6 * l2, 2.5 * r2));
    let bl2 = d.bl.c[0].powi(2);
    let p = [d.re, d.le.c[0], l2, r2, bl2 / d.rms, d.mms / bl2, bl2 / d.kms.c[0]];
    let e = Ext::new(&p, Some(0.07), d.l3r3);
    for f in [2.0, 10.0, 45.0, 100.0, 3000.0, 15000.0] {
        let a = impedance_ext(&p, &e, f).0;
        let b = coilscope_core::small_signal::impedance(&d, f);
        assert!((a - b).norm() < 1e-12 * b.norm(), "{f} Hz: {a} vs {b}");
    }
}

#[test]
fn model_impedance_equals_the_core_small_signal_impedance() {
    let d = coilscope_core::embedded_driver("18wu-4741t-00").unwrap();
    let (l2, r2) = (d.l2r2.as_ref().unwrap().0.c[0], d.l2r2.as_ref().unwrap().1.c[0]);
    let bl2 = d.bl.c[0].powi(2);
    let p = [d.re, d.le.c[0], l2, r2, bl2 / d.rms, d.mms / bl2, bl2 / d.kms.c[0]];
    for f in [10.0, 23.6, 100.0, 3000.0] {
        let a = model_impedance(&p, f);
        let b = coilscope_core::small_signal::impedance(&d, f);
        assert!((a - b).norm() < 1e-12 * b.norm());
    }
}

/// The start's sixth-octave smoothing equals the plain mean over each bin's window.
#[test]
fn sixth_octave_mean_equals_the_mean_over_each_window() {
    let n = 400;
    let f: Vec<f64> = (0..n).map(|k| 2.0 + 3.0 * k as f64).collect();
    let z: Vec<Complex64> = (0..n).map(|k| Complex64::new((k as f64 * 0.37).sin(), (k as f64 * 1.3).cos())).collect();
    let h1 = ImpedanceEstimate { f, z, coherence: vec![1.0; n], suu: vec![1.0; n], suu_max: 1.0 };
    // Every third bin, as where some are not usable.
    let at: Vec<usize> = (0..n).filter(|k| k % 3 != 1).collect();
    let fast = super::problem::sixth_octave_mean(&h1, &at, |z| z.im);
    let side = 2f64.powf(1.0 / 12.0);
    for (j, &k) in at.iter().enumerate() {
        let inside: Vec<f64> = at
            .iter()
            .filter(|&&m| h1.f[m] >= h1.f[k] / side && h1.f[m] <= h1.f[k] * side)
            .map(|&m| h1.z[m].im)
            .collect();
        let slow = inside.iter().sum::<f64>() / inside.len() as f64;
        assert!((fast[j] - slow).abs() < 1e-12, "bin {k} at {} Hz: {} against {slow}", h1.f[k], fast[j]);
    }
}

/// A curve's noise floor read from the roughness of its error: on 600 log-spaced points of
/// a driver's impedance with 0.3 % complex noise it is the noise's RMS (0.3 %; with |Z| alone
/// the noise's in-phase part, 0.3 % / sqrt 2) within 10 %, whether the model fits or misses
/// smoothly (Re 2 % off: a residual five times the noise); on the same curve without noise it
/// is a small part of the misfit.
#[test]
fn a_curves_noise_floor_is_the_roughness_of_its_error() {
    use rand::{Rng, SeedableRng};
    let p = [3.4, 1.1e-4, 5.4e-4, 0.29, 72.0, 3.8e-4, 6.3e-2];
    let n = 600;
    let freqs: Vec<f64> = (0..n).map(|k| 10.0 * 2000f64.powf(k as f64 / (n - 1) as f64)).collect();
    let (mut lo, mut hi) = ([f64::NEG_INFINITY; 7], [f64::INFINITY; 7]);
    lo[2] = (1.0 / (2.0 * PI * 20000.0)).ln();
    hi[2] = (1.0 / (2.0 * PI * 3.0)).ln();
    let map = ParamMap { lo, hi };
    let mut rng = rand::rngs::StdRng::seed_from_u64(7);
    let sigma = 0.003;
    let mut gauss = move || -> f64 {
        (-2.0 * rng.random::<f64>().max(1e-300).ln()).sqrt() * (2.0 * PI * rng.random::<f64>()).cos()
    };
    let noise: Vec<Complex64> =
        (0..n).map(|_| Complex64::new(1.0 + sigma / 2f64.sqrt() * gauss(), sigma / 2f64.sqrt() * gauss())).collect();
    let th_true = map.theta(&ParamMap::q_of(&p));
    let mut th_off = th_true.clone();
    th_off[0] += 0.02f64.ln_1p();
    for magnitude_only in [false, true] {
        let prob = |noisy: bool| {
            let z: Vec<Complex64> = freqs
                .iter()
                .enumerate()
                .map(|(k, &f)| model_impedance(&p, f) * if noisy { noise[k] } else { Complex64::new(1.0, 0.0) })
                .collect();
            CurrentError {
                f: freqs.clone(),
                u: if magnitude_only { z.iter().map(|z| Complex64::new(z.norm(), 0.0)).collect() } else { z },
                i: vec![Complex64::new(1.0, 0.0); n],
                w: vec![1.0; n],
                norm: 1.0,
                map: map.clone(),
                omega0: 2.0 * PI * 250.0,
                n_transient: 0,
                effects: Effects::NONE,
                chain: None,
                magnitude_only,
            }
        };
        let expected = if magnitude_only { sigma / 2f64.sqrt() } else { sigma };
        let noisy = prob(true);
        for (what, th) in [("the truth", &th_true), ("Re 2 % off", &th_off)] {
            let floor = noisy.roughness_floor(th);
            let r = noisy.residual_rel(th);
            assert!(
                (floor / expected - 1.0).abs() < 0.1,
                "|Z| alone {magnitude_only}, {what}: floor {floor:.3e} for noise {expected:.3e} (residual {r:.3e})"
            );
        }
        assert!(noisy.residual_rel(&th_off) > 3.0 * expected, "the misfit is well above the noise");
        let clean = prob(false);
        let (floor, r) = (clean.roughness_floor(&th_off), clean.residual_rel(&th_off));
        assert!(floor < 0.05 * r, "|Z| alone {magnitude_only}, no noise: floor {floor:.3e} of a misfit of {r:.3e}");
    }
}

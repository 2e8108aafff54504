//! A moving mass given with its sd (`--mms 15.3g±0.3g`): the sds of what it scales grow as a
//! Monte Carlo run over the mass says, and not more.

use coilscope_core::mass::Mass;
use coilscope_core::small_signal::impedance;
use coilscope_io::impedance::ImpedanceCurve;
use coilscope_workflow::linear::{linear, LinearInput, LinearRequest, Scale};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

/// A bundled driver's impedance, 10 Hz - 2 kHz, with 0.2 % of noise on each point.
fn curve() -> (coilscope_core::Parameters, ImpedanceCurve) {
    let p = coilscope_core::embedded_driver("sb17cac35-4").unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let noise = Normal::new(0.0, 2e-3).unwrap();
    let f: Vec<f64> = (0..200).map(|k| 10.0 * 200f64.powf(k as f64 / 199.0)).collect();
    let z = f.iter().map(|&f| impedance(&p, f) * (1.0 + noise.sample(&mut rng))).collect();
    (p, ImpedanceCurve { f, z, comments: vec![], magnitude_only: false })
}

fn fit(c: &ImpedanceCurve, m: Mass) -> coilscope_core::result::ResultFile {
    let req = LinearRequest { band: Some([10.0, 2000.0]), ..LinearRequest::new("mass-sd") };
    linear(LinearInput::Curve(c.clone()), Scale::Mms(m), &req, |_| {}).expect("the curve fits").result
}

/// The scale's share of the sds of Bl, Kms, Rms and Mms is the spread a Monte Carlo run over
/// the mass gives (each fit of the same curve with a mass drawn from `N(Mms, sd)`), within
/// the run's own sampling error; the sd with the mass is the statistical one and that share
/// in quadrature; a mass given without an sd leaves the sds as they were.
#[test]
fn a_mass_sd_grows_the_scaled_sds_as_a_monte_carlo_run_over_the_mass() {
    let (p, c) = curve();
    let sd_rel = 0.02;
    let exact = fit(&c, Mass::exact(p.mms));
    let given = fit(&c, Mass { kg: p.mms, sd_kg: sd_rel * p.mms });
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let mass = Normal::new(p.mms, sd_rel * p.mms).unwrap();
    let draws = 60;
    let runs: Vec<[f64; 4]> = (0..draws)
        .map(|_| {
            let r = fit(&c, Mass::exact(mass.sample(&mut rng)));
            let q = &r.parameters;
            [q.bl.c[0], q.kms.c[0], q.rms, q.mms]
        })
        .collect();
    for (k, key) in ["Bl", "Kms", "Rms", "Mms"].iter().enumerate() {
        let mean = runs.iter().map(|r| r[k]).sum::<f64>() / draws as f64;
        let spread = (runs.iter().map(|r| (r[k] - mean).powi(2)).sum::<f64>() / (draws - 1) as f64).sqrt();
        let share = given.uncertainty.value(&format!("scale.{key}")).unwrap_or(f64::NAN);
        // 60 draws: the sample sd is within about 3 x 9 % of the true one.
        let ratio = share / spread;
        assert!(
            (0.75..1.33).contains(&ratio),
            "{key}: the scale's share {share:.4e}, the Monte Carlo spread {spread:.4e}"
        );
        let stat = exact.uncertainty.value(key).unwrap_or(0.0);
        let total = given.uncertainty.value(key).unwrap_or(f64::NAN);
        assert!(
            (total - stat.hypot(share)).abs() <= 1e-9 * total,
            "{key}: sd {total:.4e} with the mass's, {stat:.4e} without, share {share:.4e}"
        );
        assert!(exact.uncertainty.value(&format!("scale.{key}")).is_none(), "{key}: an exact mass has no share");
    }
    // What the mass does not scale keeps its sd.
    for key in ["Re", "Le", "fs"] {
        assert_eq!(exact.uncertainty.value(key), given.uncertainty.value(key), "{key}");
    }
    assert_eq!(given.fit.scale.as_ref().and_then(|s| s.mass_sd), Some(sd_rel * p.mms));
}

//! Truth comparisons shared by the identification tests (`mod common;` in each).
#![allow(dead_code)]

#[allow(unused_imports)]
pub use coilscope_testkit::slice;
pub mod world;

use coilscope_core::{Parameters, Poly};
use coilscope_ident::large::{LargeFit, EFFECT_SCREEN_GAIN};
use coilscope_ident::linear::Effects;

/// The effects screen's problems on a fit of a record that holds `want`: an
/// effect the record holds must score at least ten times the screen's bar in the round that
/// takes it (its best screen), so the screen never stands between it and its trial. In the
/// rounds before, a dominant effect not yet in (LR-3) can mask it below the bar (creep 5.7e-4
/// on 18WU with every effect); it is screened again in every round, and the tests assert
/// the model chosen.
pub fn screen_problems(label: &str, fit: &LargeFit, want: Effects) -> Vec<String> {
    println!(
        "{label}: screens {:?}",
        fit.effect_screens.iter().map(|s| format!("{} {:.2e}", s.model.model_name(), s.gain)).collect::<Vec<_>>()
    );
    let mut bad = vec![];
    for added in [
        Effects { creep: true, ..Effects::NONE },
        Effects { lr3: true, ..Effects::NONE },
        Effects { le_i: true, ..Effects::NONE },
        Effects { rms_v: true, ..Effects::NONE },
    ]
    .into_iter()
    .filter(|&e| want.union(e) == want)
    {
        let best = fit.effect_screens.iter().filter(|s| s.added == added).map(|s| s.gain).fold(f64::NAN, f64::max);
        println!("{label}: {} in the record, best screen {best:.2e}", added.model_name());
        if best < 10.0 * EFFECT_SCREEN_GAIN {
            bad.push(format!(
                "{label}: {} is in the record and scored at best {best:.2e} in the screen",
                added.model_name()
            ));
        }
    }
    bad
}

/// Largest distance of the truth from the fit's bands, in sds, over 41 points of the reached
/// range, for the curves named in `which` (`Bl`, `Kms`, `Le`).
pub fn band_z(fit: &LargeFit, truth: &Parameters, which: &[&str]) -> f64 {
    let mut z: f64 = 0.0;
    for &name in which {
        let f = match name {
            "Bl" => &truth.bl,
            "Kms" => &truth.kms,
            _ => &truth.le,
        };
        let b = fit.band(name, 41);
        let zs: Vec<f64> = (0..b.x.len()).map(|k| (b.value[k] - f.eval(b.x[k])) / b.sd[k]).collect();
        if std::env::var("COILSCOPE_BAND_TRACE").is_ok() {
            println!(
                "{name}: z {:?} x {:?} sd {:?}",
                zs.iter().map(|v| format!("{v:.2}")).collect::<Vec<_>>(),
                b.x.iter().step_by(8).map(|v| format!("{:.2}", v * 1e3)).collect::<Vec<_>>(),
                b.sd.iter().map(|v| format!("{:.2e}", v)).collect::<Vec<_>>()
            );
        }
        z = coilscope_testkit::check::nan_max(
            z,
            zs.iter().map(|v| v.abs()).fold(0.0, coilscope_testkit::check::nan_max),
        );
    }
    z
}

/// Largest |f - g| over [lo, hi], relative to g(0).
pub fn worst(f: &Poly, g: &Poly, [lo, hi]: [f64; 2]) -> f64 {
    (0..=400)
        .map(|k| lo + (hi - lo) * k as f64 / 400.0)
        .map(|x| (f.eval(x) - g.eval(x)).abs())
        .fold(0.0, coilscope_testkit::check::nan_max)
        / g.eval(0.0).abs()
}

/// Errors of an identified set against the truth: Bl(x), Kms(x), Le(x) as the largest error
/// over `range` relative to the true value at rest; Re and Rms relative.
pub struct Errors {
    pub bl: f64,
    pub kms: f64,
    pub le: f64,
    pub re: f64,
    pub rms: f64,
}

impl Errors {
    pub fn of(q: &Parameters, truth: &Parameters, range: [f64; 2]) -> Self {
        Errors {
            bl: worst(&q.bl, &truth.bl, range),
            kms: worst(&q.kms, &truth.kms, range),
            le: worst(&q.le, &truth.le, range),
            re: (q.re / truth.re - 1.0).abs(),
            rms: (q.rms / truth.rms - 1.0).abs(),
        }
    }
}

impl std::fmt::Display for Errors {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "Bl {:.3} %, Kms {:.3} %, Le {:.3} %, Re {:.4} %, Rms {:.3} %",
            100.0 * self.bl,
            100.0 * self.kms,
            100.0 * self.le,
            100.0 * self.re,
            100.0 * self.rms
        )
    }
}

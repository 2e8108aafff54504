//! A production line's units: copies of a golden driver with the spread of production, and
//! the faults an end-of-line test must catch (a virtual line for `coilscope qc`).
//!
//! A unit's values are the golden driver's, each times its own factor `1 + rel_sd N(0, 1)`
//! (`Re`, `Le(x)` and the LR-2 branch, `Bl(x)`, `Kms(x)`, `Mms`, `Rms`), and its coil and
//! suspension rest a little off the golden centre: the coil by `coil_sd N(0, 1)` (its `Bl(x)`
//! and `Le(x)` are the golden curves seen from the moved rest position), the suspension by
//! `spider_sd N(0, 1)` (its secant `Kms(x)` likewise: a model of a spider glued off its centre,
//! not the golden force curve moved). A fault is applied on top.

use crate::excitation::named_rng;
use crate::params::Parameters;
use rand_distr::{Distribution, StandardNormal};

/// The spread of a production line.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Spread {
    /// The sd of each value's factor (0.01: +-3 % at 3 sd).
    pub rel_sd: f64,
    /// The sd of the coil's rest position in the gap (m).
    pub coil_sd: f64,
    /// The sd of the suspension's rest position (m).
    pub spider_sd: f64,
}

impl Default for Spread {
    fn default() -> Self {
        Spread { rel_sd: 0.01, coil_sd: 0.05e-3, spider_sd: 0.05e-3 }
    }
}

/// A fault of one unit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Fault {
    /// The coil rests this far (m, + out) from where it should.
    CoilOffset(f64),
    /// The suspension is this many times as stiff.
    StiffSpider(f64),
    /// The coil rubs: the mechanical loss is this many times as large.
    RubbingCoil(f64),
}

impl Fault {
    /// What the fault is, in a few words.
    pub fn name(&self) -> &'static str {
        match self {
            Fault::CoilOffset(_) => "coil offset",
            Fault::StiffSpider(_) => "stiff spider",
            Fault::RubbingCoil(_) => "rubbing coil",
        }
    }

    /// The end-of-line figure that shows the fault first (`coilscope qc`'s keys).
    pub fn figure(&self) -> &'static str {
        match self {
            Fault::CoilOffset(_) => "Xsym_Bl",
            Fault::StiffSpider(_) => "Kms(0)",
            Fault::RubbingCoil(_) => "Rms",
        }
    }
}

/// The unit of `seed` on a line making `golden` with `spread`, with `fault` where it has one.
pub fn unit(golden: &Parameters, spread: &Spread, fault: Option<Fault>, seed: u64) -> Parameters {
    let mut rng = named_rng(seed, "production unit");
    let mut n = || -> f64 { StandardNormal.sample(&mut rng) };
    let mut factor = || 1.0 + spread.rel_sd * n();
    let mut p = golden.clone();
    p.re *= factor();
    let fl = factor();
    p.le = p.le.scaled(fl);
    if let Some((l2, r2)) = p.l2r2.as_mut() {
        *l2 = l2.scaled(fl);
        *r2 = r2.scaled(factor());
    }
    p.bl = p.bl.scaled(factor());
    p.kms = p.kms.scaled(factor());
    p.mms *= factor();
    let fr = factor();
    p.rms *= fr;
    p.rms_v = p.rms_v.map(|r| r.scaled(fr));
    let mut coil = spread.coil_sd * n();
    let spider = spread.spider_sd * n();
    match fault {
        Some(Fault::CoilOffset(d)) => coil += d,
        Some(Fault::StiffSpider(k)) => p.kms = p.kms.scaled(k),
        Some(Fault::RubbingCoil(k)) => {
            p.rms *= k;
            p.rms_v = p.rms_v.map(|r| r.scaled(k));
        }
        None => {}
    }
    // A coil resting `coil` out sees at displacement x the field the centred one sees at
    // x + coil.
    p.bl = p.bl.shifted(coil);
    p.le = p.le.shifted(coil);
    if let Some((l2, r2)) = p.l2r2.as_mut() {
        *l2 = l2.shifted(coil);
        *r2 = r2.shifted(coil);
    }
    p.kms = p.kms.shifted(spider);
    // The curves are the golden ones seen from moved origins: valid where the golden ones
    // were, less the larger move on each side.
    let moved = coil.abs().max(spider.abs());
    p.x_range = p.x_range.map(|[lo, hi]| [lo + moved, hi - moved]);
    // The golden driver's published curves are not this unit's.
    p.extra.remove("published_curves");
    p.name = Some(format!(
        "unit {seed} of {}{}",
        golden.name.as_deref().unwrap_or("the line"),
        fault.map_or(String::new(), |f| format!(" ({})", f.name()))
    ));
    p
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn units_spread_as_the_line_says_and_faults_move_their_figure() {
        let g = crate::params::embedded_driver("sb17cac35-4").unwrap();
        let s = Spread::default();
        let units: Vec<Parameters> = (0..2000).map(|k| unit(&g, &s, None, k)).collect();
        let rel: Vec<f64> = units.iter().map(|u| u.rms / g.rms - 1.0).collect();
        let mean = rel.iter().sum::<f64>() / rel.len() as f64;
        let sd = (rel.iter().map(|r| (r - mean).powi(2)).sum::<f64>() / (rel.len() - 1) as f64).sqrt();
        assert!(mean.abs() < 0.001 && (sd / s.rel_sd - 1.0).abs() < 0.05, "mean {mean} sd {sd}");
        // The same seed draws the same unit; a fault changes only its own part.
        assert_eq!(unit(&g, &s, None, 7), unit(&g, &s, None, 7));
        let rub = unit(&g, &s, Some(Fault::RubbingCoil(3.0)), 7);
        assert!((rub.rms / unit(&g, &s, None, 7).rms - 3.0).abs() < 1e-12);
        // A coil resting 0.5 mm out sees at -0.5 mm what the centred coil sees at rest.
        let still = Spread { rel_sd: 0.0, coil_sd: 0.0, spider_sd: 0.0 };
        let off = unit(&g, &still, Some(Fault::CoilOffset(0.5e-3)), 1);
        assert!((off.bl.eval(-0.5e-3) / g.bl.eval(0.0) - 1.0).abs() < 1e-12);
    }
}

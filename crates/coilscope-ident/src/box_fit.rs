//! The box a known driver works into, from its impedance in the box: the volume `Vb`, the
//! leak's `QL`, and the port's `fb` and `Qp` or the passive radiator's `Mmp`, `Kmp(0)` and
//! `Rmp` ([`fit_box`]).
//!
//! The model is the small-signal network of the one model
//! ([`coilscope_core::small_signal::impedance`] with the set's `enclosure`): the driver's
//! values are held (from a free-air measurement), the box's are the unknowns, in logarithms
//! (positive, and relative steps). The fit starts from the best point of a grid over the
//! volume (and the tuning), then Levenberg-Marquardt. The standard deviations are the larger
//! of the classical covariance `s^2 (J'J)^-1` of the relative residual and its sandwich over
//! runs of neighbouring points.
//!
//! A passive radiator's admittance on the box air is `Sp^2 / (jw Mmp + Rmp + Kmp / jw)`: the
//! impedance gives `Mmp`, `Rmp` and `Kmp` over `Sp^2`, so `Sp` must be known; without it the
//! fit takes `Sp = Sd` and says so. A port's quadratic loss and area do not show at small
//! signal and are left out.

use crate::lm::{lm_step, LmState, Problem};
use coilscope_core::enclosure::{BoxKind, Enclosure};
use coilscope_core::small_signal::{impedance, thiele_small};
use coilscope_core::{Complex64, Parameters, Poly};
use nalgebra::{DMatrix, DVector};
use std::f64::consts::PI;

/// Which box to fit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BoxChoice {
    Closed,
    Vented,
    PassiveRadiator,
    /// Each of the three, and the simplest that explains the data ([`fit_box`]).
    Auto,
}

impl BoxChoice {
    /// `closed`, `vented`, `passive_radiator` or `auto`.
    pub fn parse(s: &str) -> Result<BoxChoice, String> {
        match s {
            "closed" => Ok(BoxChoice::Closed),
            "vented" => Ok(BoxChoice::Vented),
            "passive_radiator" => Ok(BoxChoice::PassiveRadiator),
            "auto" => Ok(BoxChoice::Auto),
            other => Err(format!("--enclosure {other:?}: expected closed, vented, passive_radiator or auto")),
        }
    }
}

/// A fitted box.
#[derive(Clone, Debug)]
pub struct BoxFit {
    pub enclosure: Enclosure,
    /// Standard deviations under the parameter schema's keys (`enclosure.Vb`, ...).
    pub sd: Vec<(&'static str, f64)>,
    /// RMS of the relative residual `|Z_model - Z| / |Z|` (or of `ln |Z_model| - ln |Z|`
    /// for a magnitude alone).
    pub residual: f64,
    /// With `auto`: each type tried and its residual.
    pub trials: Vec<(&'static str, f64)>,
    /// Why `auto` chose this type; empty otherwise.
    pub why: String,
    /// The radiator's area was not given and `Sd` was taken for it.
    pub sp_assumed: bool,
    /// Unknowns that ended on a bound of the search, by key.
    pub on_bound: Vec<&'static str>,
}

/// The residual `auto` allows a simpler box above the best fit's before it takes a more
/// complex one: a port needs 25 % less residual than a closed box, a radiator's stiffness
/// 25 % less than a port.
pub const AUTO_MARGIN: f64 = 0.75;

/// A relative residual below which a box explains the data as far as any measurement can
/// tell (a measured impedance's noise and the driver's own model are at 1e-3 and above):
/// `auto` takes no more complex box to lower it further.
pub const AUTO_FLOOR: f64 = 1e-4;

/// The box of the driver `driver` (a parameter set with `Sd`; its own `enclosure` ignored)
/// from its impedance `z` at `f` (Hz); `magnitude_only`: only `|z|` is data. `sp`: a passive
/// radiator's area (m^2).
pub fn fit_box(
    f: &[f64],
    z: &[Complex64],
    magnitude_only: bool,
    driver: &Parameters,
    choice: BoxChoice,
    sp: Option<f64>,
) -> Result<BoxFit, String> {
    let sd = driver.sd.ok_or(
        "the driver's radiating area Sd is needed for the box's volume (give it in the driver's set, or --sd)",
    )?;
    if f.len() != z.len() || f.len() < 10 {
        return Err(format!("{} impedance points: at least 10 are needed to fit a box", f.len()));
    }
    if let Some(k) = (0..f.len()).find(|&k| !(f[k] > 0.0 && z[k].norm() > 0.0 && z[k].norm().is_finite())) {
        return Err(format!("impedance point {k} ({} Hz, {} ohm) is not usable", f[k], z[k]));
    }
    let driver = Parameters { enclosure: None, ..driver.clone() };
    let data = Data { f: f.to_vec(), z: z.to_vec(), magnitude_only, driver, sp: sp.unwrap_or(sd) };
    let kinds: Vec<Kind> = match choice {
        BoxChoice::Closed => vec![Kind::Closed],
        BoxChoice::Vented => vec![Kind::Vented],
        BoxChoice::PassiveRadiator => vec![Kind::Radiator],
        BoxChoice::Auto => vec![Kind::Closed, Kind::Vented, Kind::Radiator],
    };
    let fits: Vec<(Kind, Solved)> = kinds.iter().map(|&k| (k, solve(&data, k))).collect();
    let trials: Vec<(&'static str, f64)> = fits.iter().map(|(k, s)| (k.name(), s.residual)).collect();
    // The simplest box within the margin of the next more complex one.
    let mut pick = 0;
    let mut why = String::new();
    if choice == BoxChoice::Auto {
        for next in 1..fits.len() {
            if fits[pick].1.residual > AUTO_FLOOR && fits[next].1.residual < AUTO_MARGIN * fits[pick].1.residual {
                why = format!(
                    "{} lowers the residual from {:.2e} ({}) to {:.2e}",
                    fits[next].0.name(),
                    fits[pick].1.residual,
                    fits[pick].0.name(),
                    fits[next].1.residual
                );
                pick = next;
            }
        }
        if why.is_empty() {
            why = format!(
                "no other type lowers its residual {:.2e} by {:.0} %",
                fits[0].1.residual,
                100.0 * (1.0 - AUTO_MARGIN)
            );
        }
    }
    let (kind, s) = fits.into_iter().nth(pick).expect("one fit at least");
    let enclosure = data.enclosure(kind, &s.theta);
    let keys = kind.keys();
    let sd_out = keys.iter().zip(&s.sd_ln).map(|(k, sl)| (*k, sl * value_of(&enclosure, k))).collect();
    let on_bound = keys.iter().zip(&s.theta).filter(|(k, t)| at_bound(k, **t)).map(|(k, _)| *k).collect();
    Ok(BoxFit {
        enclosure,
        sd: sd_out,
        residual: s.residual,
        trials,
        why,
        sp_assumed: kind == Kind::Radiator && sp.is_none(),
        on_bound,
    })
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Closed,
    Vented,
    Radiator,
}

impl Kind {
    fn name(self) -> &'static str {
        match self {
            Kind::Closed => "closed",
            Kind::Vented => "vented",
            Kind::Radiator => "passive_radiator",
        }
    }

    /// The unknowns (ln of each), in theta's order, by schema key.
    fn keys(self) -> &'static [&'static str] {
        match self {
            Kind::Closed => &["enclosure.Vb", "enclosure.QL"],
            Kind::Vented => &["enclosure.Vb", "enclosure.QL", "enclosure.fb", "enclosure.Qp"],
            Kind::Radiator => &["enclosure.Vb", "enclosure.QL", "enclosure.Mmp", "enclosure.Kmp", "enclosure.Rmp"],
        }
    }
}

/// Neighbouring points whose errors the covariance takes as one cluster
/// ([`crate::lm::sandwich_covariance`]).
const CLUSTER_POINTS: usize = 8;

/// The search's bounds on the quality factors: a leak or a port loss beyond Q = 1000 does not
/// show in an impedance, and below 0.3 the box is open.
const Q_BOUNDS: (f64, f64) = (0.3, 1000.0);

fn at_bound(key: &str, ln: f64) -> bool {
    matches!(key, "enclosure.QL" | "enclosure.Qp") && (ln <= Q_BOUNDS.0.ln() + 1e-3 || ln >= Q_BOUNDS.1.ln() - 1e-3)
}

fn value_of(e: &Enclosure, key: &str) -> f64 {
    match (key, &e.kind) {
        ("enclosure.Vb", _) => e.vb,
        ("enclosure.QL", _) => e.ql.unwrap_or(f64::NAN),
        ("enclosure.fb", BoxKind::Vented { fb, .. }) => *fb,
        ("enclosure.Qp", BoxKind::Vented { qp, .. }) => qp.unwrap_or(f64::NAN),
        ("enclosure.Mmp", BoxKind::PassiveRadiator { mmp, .. }) => *mmp,
        ("enclosure.Kmp", BoxKind::PassiveRadiator { kmp, .. }) => kmp.c[0],
        ("enclosure.Rmp", BoxKind::PassiveRadiator { rmp, .. }) => *rmp,
        _ => f64::NAN,
    }
}

struct Data {
    f: Vec<f64>,
    z: Vec<Complex64>,
    magnitude_only: bool,
    driver: Parameters,
    sp: f64,
}

impl Data {
    /// The box of `theta` (ln of [`Kind::keys`]); the quality factors clamped to
    /// [`Q_BOUNDS`].
    fn enclosure(&self, kind: Kind, th: &[f64]) -> Enclosure {
        let q = |t: f64| t.exp().clamp(Q_BOUNDS.0, Q_BOUNDS.1);
        let kind_of = match kind {
            Kind::Closed => BoxKind::Closed,
            Kind::Vented => {
                BoxKind::Vented { fb: th[2].exp(), qp: Some(q(th[3])), port_area: None, port_loss: None, knl: None }
            }
            Kind::Radiator => BoxKind::PassiveRadiator {
                sp: self.sp,
                mmp: th[2].exp(),
                kmp: Poly::constant(th[3].exp()),
                rmp: th[4].exp(),
            },
        };
        Enclosure { vb: th[0].exp(), ql: Some(q(th[1])), adiabatic: true, kind: kind_of }
    }

    fn residual(&self, kind: Kind, th: &[f64]) -> DVector<f64> {
        let p = Parameters { enclosure: Some(self.enclosure(kind, th)), ..self.driver.clone() };
        let n = self.f.len();
        if self.magnitude_only {
            DVector::from_iterator(n, (0..n).map(|k| impedance(&p, self.f[k]).norm().ln() - self.z[k].norm().ln()))
        } else {
            let mut r = DVector::zeros(2 * n);
            for k in 0..n {
                let e = (impedance(&p, self.f[k]) - self.z[k]) / self.z[k].norm();
                r[2 * k] = e.re;
                r[2 * k + 1] = e.im;
            }
            r
        }
    }
}

struct BoxProblem<'a> {
    data: &'a Data,
    kind: Kind,
}

impl Problem for BoxProblem<'_> {
    fn residual_jacobian(&self, theta: &[f64]) -> (DVector<f64>, DMatrix<f64>) {
        let r = self.data.residual(self.kind, theta);
        let mut j = DMatrix::zeros(r.len(), theta.len());
        let h = 1e-6;
        for c in 0..theta.len() {
            let mut a = theta.to_vec();
            let mut b = theta.to_vec();
            a[c] += h;
            b[c] -= h;
            let d = (self.data.residual(self.kind, &a) - self.data.residual(self.kind, &b)) / (2.0 * h);
            j.set_column(c, &d);
        }
        (r, j)
    }

    fn residual(&self, theta: &[f64]) -> DVector<f64> {
        self.data.residual(self.kind, theta)
    }
}

struct Solved {
    theta: Vec<f64>,
    sd_ln: Vec<f64>,
    residual: f64,
}

fn rms(r: &DVector<f64>) -> f64 {
    (r.norm_squared() / r.len().max(1) as f64).sqrt()
}

/// The grid's start and Levenberg-Marquardt from it.
fn solve(d: &Data, kind: Kind) -> Solved {
    let ts = thiele_small(&d.driver);
    let vas = ts.vas.unwrap_or(0.01);
    let cost = |th: &[f64]| d.residual(kind, th).norm_squared();
    // The volume from Vas / 100 to 100 Vas, the tuning from fs / 5 to 5 fs.
    let vols: Vec<f64> = (0..41).map(|k| (vas * 0.01 * 1e4f64.powf(k as f64 / 40.0)).ln()).collect();
    let tunes: Vec<f64> = (0..31).map(|k| ts.fs * 0.2 * 25f64.powf(k as f64 / 30.0)).collect();
    let gamma_p0 = coilscope_core::enclosure::GAMMA * coilscope_core::enclosure::P0;
    let candidates: Vec<Vec<f64>> = match kind {
        Kind::Closed => vols.iter().map(|&v| vec![v, 10f64.ln()]).collect(),
        Kind::Vented => {
            vols.iter().flat_map(|&v| tunes.iter().map(move |&fb| vec![v, 10f64.ln(), fb.ln(), 20f64.ln()])).collect()
        }
        Kind::Radiator => vols
            .iter()
            .flat_map(|&v| {
                tunes.iter().map(move |&ft| {
                    // Half the radiator's tuning from its own suspension, half from the air.
                    let air = d.sp * d.sp * gamma_p0 / v.exp();
                    let mmp = 2.0 * air / (2.0 * PI * ft).powi(2);
                    let rmp = 2.0 * PI * ft * mmp / 10.0;
                    vec![v, 10f64.ln(), mmp.ln(), air.ln(), rmp.ln()]
                })
            })
            .collect(),
    };
    let start = candidates
        .into_iter()
        .map(|th| (cost(&th), th))
        .filter(|(c, _)| c.is_finite())
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, th)| th)
        .unwrap_or_else(|| vec![vas.ln(); kind.keys().len()]);
    let problem = BoxProblem { data: d, kind };
    let mut s = LmState::new(&problem, start);
    while !s.converged && s.iteration < 300 {
        s = lm_step(&problem, &s);
    }
    let (r, j) = problem.residual_jacobian(&s.theta);
    // The classical covariance, or the sandwich over runs of neighbouring points where that
    // is larger: a measured impedance's errors are correlated over neighbouring frequencies
    // (a window's leakage, a smoothed curve), which the classical one takes for independent
    // information.
    let rows_per_point = if d.magnitude_only { 1 } else { 2 };
    let classical = crate::lm::covariance(&problem, &s.theta);
    let sandwich = crate::lm::sandwich_covariance(&j, &r, CLUSTER_POINTS * rows_per_point);
    let sd_ln = (0..s.theta.len())
        .map(|k| match (&classical, &sandwich) {
            (Some(c), Some(w)) => crate::lm::sd_from_variance(c[(k, k)].max(w[(k, k)])),
            (Some(c), None) => crate::lm::sd_from_variance(c[(k, k)]),
            _ => f64::NAN,
        })
        .collect();
    Solved { residual: rms(&r), theta: s.theta, sd_ln }
}

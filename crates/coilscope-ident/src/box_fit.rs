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
    /// A joint fit's ([`fit_driver_in_box`]) other ends, from the grid's next best points,
    /// lowest residual first: each a driver with its box. A large-signal record's impedance
    /// is not the small-signal network's near the resonances, and the lowest residual there
    /// need not be the driver; `identify` runs each and takes the one that misses least of
    /// the current in the time domain.
    pub alternatives: Vec<Parameters>,
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
    let data = Data { f: f.to_vec(), z: z.to_vec(), magnitude_only, driver, sp: sp.unwrap_or(sd), walls: false };
    let kinds = Kind::of(choice);
    let fits: Vec<(Kind, Solved)> = kinds.iter().map(|&k| (k, solve(&data, k))).collect();
    let trials: Vec<(&'static str, f64)> = fits.iter().map(|(k, s)| (k.name(), s.residual)).collect();
    let (pick, why) = auto_pick(choice, &fits.iter().map(|(k, s)| (*k, s.residual)).collect::<Vec<_>>());
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
        alternatives: Vec::new(),
    })
}

/// Which of the fits `auto` takes (the simplest box within [`AUTO_MARGIN`] of the next more
/// complex one, and not below [`AUTO_FLOOR`]) and why; the only one otherwise.
fn auto_pick(choice: BoxChoice, fits: &[(Kind, f64)]) -> (usize, String) {
    let mut pick = 0;
    let mut why = String::new();
    if choice == BoxChoice::Auto {
        for next in 1..fits.len() {
            if fits[pick].1 > AUTO_FLOOR && fits[next].1 < AUTO_MARGIN * fits[pick].1 {
                why = format!(
                    "{} lowers the residual from {:.2e} ({}) to {:.2e}",
                    fits[next].0.name(),
                    fits[pick].1,
                    fits[pick].0.name(),
                    fits[next].1
                );
                pick = next;
            }
        }
        if why.is_empty() {
            why =
                format!("no other type lowers its residual {:.2e} by {:.0} %", fits[0].1, 100.0 * (1.0 - AUTO_MARGIN));
        }
    }
    (pick, why)
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Closed,
    Vented,
    Radiator,
}

impl Kind {
    /// The kinds of box a choice tries, simplest first.
    fn of(choice: BoxChoice) -> &'static [Kind] {
        match choice {
            BoxChoice::Closed => &[Kind::Closed],
            BoxChoice::Vented => &[Kind::Vented],
            BoxChoice::PassiveRadiator => &[Kind::Radiator],
            BoxChoice::Auto => &[Kind::Closed, Kind::Vented, Kind::Radiator],
        }
    }

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
    e.get(key).unwrap_or(f64::NAN)
}

#[derive(Clone)]
struct Data {
    f: Vec<f64>,
    z: Vec<Complex64>,
    magnitude_only: bool,
    driver: Parameters,
    sp: f64,
    /// A joint fit's ranges ([`Data::outside`]) as walls (no residual outside: a trial step
    /// there is refused) instead of penalty rows.
    walls: bool,
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

    /// The driver at theta: the held driver, or, in a joint fit, scaled by the factors
    /// `exp(th[nk..])` of [`DRIVER_KEYS`] after the box's `nk` unknowns.
    fn driver_at(&self, kind: Kind, th: &[f64]) -> Parameters {
        let mut p = self.driver.clone();
        let f = &th[kind.keys().len()..];
        if !f.is_empty() {
            let e = |k: usize| f[k].exp();
            p.re *= e(0);
            p.le = p.le.scaled(e(1));
            p.bl = p.bl.scaled(e(2));
            p.kms = p.kms.scaled(e(3));
            p.rms *= e(4);
            if let (Some((l2, r2)), true) = (p.l2r2.as_mut(), f.len() == DRIVER_KEYS.len()) {
                *l2 = l2.scaled(e(5));
                *r2 = r2.scaled(e(6));
            }
        }
        p
    }

    /// How far a joint fit's driver `p` (its factors `f` on the start's) and box are outside
    /// what drivers and boxes are, each as a logarithmic distance (0 inside): the driver's
    /// Qms within [`QMS_RANGE`], `Re` below the least `|Z|` (every branch of the network adds
    /// a positive real part), its electrical values within [`ELECTRICAL_RANGE`] of the
    /// start's (the data above its resonance fix them), the box's tuning (a port's or a
    /// radiator's) within the data's frequencies, and a radiator at least a tenth as heavy
    /// per area squared as the cone. Where the data say little, the driver's losses and the
    /// box's trade, and a radiator can vanish into an open hole (its mass, stiffness and
    /// loss to zero together). The distances enter the residual as [`PENALTY`] rows: a wall
    /// that refused every trial across it left the fit stuck on it, 17 % from the data.
    fn outside(&self, p: &Parameters, f: &[f64]) -> [f64; N_PENALTY] {
        let below = |v: f64, lo: f64| (lo / v).ln().max(0.0);
        let above = |v: f64, hi: f64| (v / hi).ln().max(0.0);
        let qms = (p.kms.c[0] * p.mms).sqrt() / p.rms;
        let zmin = self.z.iter().map(|z| z.norm()).fold(f64::INFINITY, f64::min);
        let mut out = [0.0; N_PENALTY];
        out[0] = below(qms, QMS_RANGE.0) + above(qms, QMS_RANGE.1);
        out[1] = above(p.re, RE_ABOVE_ZMIN * zmin);
        for (j, &k) in [0, 1, 5, 6].iter().enumerate() {
            out[2 + j] = f.get(k).map_or(0.0, |v| (v.abs() - ELECTRICAL_RANGE.ln()).max(0.0));
        }
        if let Some(e) = &p.enclosure {
            let sd = p.sd.unwrap_or(self.sp);
            let (lo, hi) = (self.f[0], self.f[self.f.len() - 1]);
            let tuning = e.tuning_hz(p.kms.c[0], p.mms, sd);
            if !matches!(e.kind, BoxKind::Closed) {
                out[6] = below(tuning, 0.5 * lo) + above(tuning, hi);
            }
            if let BoxKind::PassiveRadiator { sp, mmp, .. } = &e.kind {
                out[7] = below(mmp / (sp * sp), 0.1 * p.mms / (sd * sd));
            }
        }
        out.map(|v| if v.is_finite() { v } else { 1e3 })
    }

    fn residual(&self, kind: Kind, th: &[f64]) -> DVector<f64> {
        let p = Parameters { enclosure: Some(self.enclosure(kind, th)), ..self.driver_at(kind, th) };
        let n = self.f.len();
        let joint = th.len() > kind.keys().len();
        let extra = if joint { N_PENALTY } else { 0 };
        let mut r = DVector::zeros(if self.magnitude_only { n } else { 2 * n } + extra);
        if self.magnitude_only {
            for k in 0..n {
                r[k] = impedance(&p, self.f[k]).norm().ln() - self.z[k].norm().ln();
            }
        } else {
            for k in 0..n {
                let e = (impedance(&p, self.f[k]) - self.z[k]) / self.z[k].norm();
                r[2 * k] = e.re;
                r[2 * k + 1] = e.im;
            }
        }
        if joint {
            let m = r.len() - extra;
            let out = self.outside(&p, &th[kind.keys().len()..]);
            if self.walls && out.iter().any(|v| *v > 0.0) {
                r.fill(f64::NAN);
            }
            for (j, v) in out.into_iter().enumerate() {
                r[m + j] = PENALTY * v;
            }
        }
        r
    }
}

/// The rows of [`Data::outside`] in a joint fit's residual, and their weight (a residual of
/// relative impedance error): a factor of e outside a range costs as much as the whole
/// impedance missed. A joint fit runs from each start twice, with the ranges as these rows
/// and as walls ([`Data::walls`]): of the independent simulator's records, SB17 in a vented
/// box came right only with the rows (with walls the fit stuck on one, 12 % from the data),
/// PTT4 with a passive radiator only with walls (with the rows its radiator's loss went to
/// zero); `identify` takes the end that misses least of the current in the time domain.
const N_PENALTY: usize = 8;
const PENALTY: f64 = 10.0;

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

/// The driver's values a joint fit ([`fit_driver_in_box`]) scales, in theta's order after the
/// box's (`L2`, `R2` when the start has them).
pub const DRIVER_KEYS: [&str; 7] = ["Re", "Le", "Bl", "Kms", "Rms", "L2", "R2"];

/// [`BoxProblem`] over the unknowns not held: `full` with `free` entries from theta.
struct Held<'a> {
    inner: BoxProblem<'a>,
    full: Vec<f64>,
    free: Vec<usize>,
}

impl Held<'_> {
    fn expand(&self, th: &[f64]) -> Vec<f64> {
        let mut full = self.full.clone();
        for (k, &c) in self.free.iter().enumerate() {
            full[c] = th[k];
        }
        full
    }
}

impl Problem for Held<'_> {
    fn residual_jacobian(&self, theta: &[f64]) -> (DVector<f64>, DMatrix<f64>) {
        let (r, j) = self.inner.residual_jacobian(&self.expand(theta));
        let cols: Vec<_> = self.free.iter().map(|&c| j.column(c).into_owned()).collect();
        (r, DMatrix::from_columns(&cols))
    }

    fn residual(&self, theta: &[f64]) -> DVector<f64> {
        self.inner.residual(&self.expand(theta))
    }
}

/// A driver and its box together, from the impedance `z` at `f` (Hz) in the box: the start of
/// a large-signal identification in a box.
///
/// `start` is the driver as a free-air fit of the same record reads it, its `Mms` and `Sd`
/// given. Its stiffness then holds the box air's, and with a port or a radiator it is a
/// compromise between the two peaks. The driver's [`DRIVER_KEYS`] are fitted as factors on a
/// reference, `Mms` held, together with the box's values. A closed box's volume `vb` (m^3)
/// is held: its air and the suspension are springs in parallel, and an impedance sees only
/// their sum; without it a closed box is an error.
///
/// The search starts from:
/// - two electrical starts, one made from the data (`Re` under the least `|Z|`, `Le` and an
///   LR-2 branch from the highest point's reactance) and `start`'s own where physical;
/// - for each, a grid of the driver's resonance over the data (its stiffness from `Mms`, `Rms`
///   at `Qms = 4`, `Bl` from the highest peak), and `start`'s mechanical values where physical,
///   each with the box as [`fit_box`] starts it; the best few of the grid are kept;
/// - with a port or a radiator, Thiele's reading of the two peaks (the driver's resonance at
///   `fL fH / fM`, the outlet's tuning at the dip `fM` between them, the compliance ratio from
///   the three).
///
/// Each start is solved by Levenberg-Marquardt twice, with the physical ranges (Qms, `Re`
/// under the least `|Z|`, the electrical values within a factor of the data's, the tuning
/// within the data, a radiator's mass per area) as penalty rows and as walls. The least
/// residual wins; the others are returned in [`BoxFit::alternatives`], best first.
pub fn fit_driver_in_box(
    f: &[f64],
    z: &[Complex64],
    magnitude_only: bool,
    start: &Parameters,
    choice: BoxChoice,
    sp: Option<f64>,
    vb: Option<f64>,
) -> Result<(Parameters, BoxFit), String> {
    let sd = start.sd.ok_or("the driver's radiating area Sd is needed in a box (--sd)")?;
    if f.len() != z.len() || f.len() < 10 {
        return Err(format!("{} impedance points: at least 10 are needed to fit a driver in a box", f.len()));
    }
    let driver = Parameters { enclosure: None, ..start.clone() };
    let data = Data { f: f.to_vec(), z: z.to_vec(), magnitude_only, driver, sp: sp.unwrap_or(sd), walls: false };
    let kinds = Kind::of(choice);
    if choice == BoxChoice::Closed && vb.is_none() {
        return Err("a closed box's volume must be given (--vb M3): its air and the driver's suspension are two springs on the same cone, and the terminals see only their sum".into());
    }
    let lumped = data.driver.clone();
    let electrical = electrical_starts(&data.driver, f, z);
    let n_driver = DRIVER_KEYS.len();
    let data = Data { driver: electrical[0].clone(), ..data };
    let gamma_p0 = coilscope_core::enclosure::GAMMA * coilscope_core::enclosure::P0;
    // Every 4th point for the grid.
    let coarse = Data {
        f: data.f.iter().step_by(4).copied().collect(),
        z: data.z.iter().step_by(4).copied().collect(),
        ..data.clone()
    };
    type Joint = (Kind, Solved, Parameters, Vec<Parameters>);
    let fits: Vec<Joint> = kinds
        .iter()
        .map(|&kind| {
            let nk = kind.keys().len();
            // The grid: each electrical start, with the driver's own resonance from the
            // lowest frequency to a quarter of the highest (its stiffness from Mms; Rms at Qms
            // = 4; Bl from the highest peak over Re) and the free-air fit's own mechanical
            // values where physical (less the air's stiffness in a closed box of known
            // volume), and for each the box as fit_box's; the best few go on below.
            let mut candidates = Vec::new();
            for el in &electrical {
                candidates.extend(driver_grid(el, f, z));

                let mut own = Parameters { re: el.re, le: el.le.clone(), l2r2: el.l2r2.clone(), ..lumped.clone() };
                if let (Kind::Closed, Some(v)) = (kind, vb) {
                    own.kms = Poly::constant(own.kms.c[0] - sd * sd * gamma_p0 / v);
                }
                let qms = (own.kms.c[0] * own.mms).sqrt() / own.rms;
                if own.kms.c[0] > 0.0 && own.bl.c[0].abs() > 0.0 && (QMS_RANGE.0..=QMS_RANGE.1).contains(&qms) {
                    candidates.push(own);
                }
            }
            let mut best: Vec<(f64, Vec<f64>)> = Vec::new();
            for d in &candidates {
                let mut th = match (kind, vb) {
                    (Kind::Closed, Some(v)) => vec![v.ln(), 10f64.ln()],
                    _ => grid_start(&Data { driver: d.clone(), ..coarse.clone() }, kind),
                };
                th.extend(factors(d, &data.driver));
                let c = coarse.residual(kind, &th).norm_squared();
                if c.is_finite()
                    && data
                        .outside(
                            &Parameters { enclosure: Some(data.enclosure(kind, &th)), ..data.driver_at(kind, &th) },
                            &th[nk..],
                        )
                        .iter()
                        .all(|v| *v == 0.0)
                {
                    best.push((c, th));
                }
            }
            best.sort_by(|a, b| a.0.total_cmp(&b.0));
            best.truncate(GRID_KEPT);
            // Thiele's reading of two peaks, whatever the grid's cost says of it.
            if kind != Kind::Closed {
                for el in &electrical {
                    let Some((d, fb, vas_over_vb)) = two_peak_driver(el, f, z) else { continue };
                    let vb = gamma_p0 * sd * sd / d.kms.c[0] / vas_over_vb;
                    let mut th = match kind {
                        Kind::Vented => vec![vb.ln(), 10f64.ln(), fb.ln(), 20f64.ln()],
                        _ => grid_start(&Data { driver: d.clone(), ..coarse.clone() }, kind),
                    };
                    th.extend(factors(&d, &data.driver));
                    if data.residual(kind, &th).iter().all(|v| v.is_finite()) {
                        best.push((0.0, th));
                    }
                }
            }
            let mut solved: Vec<(Solved, Parameters)> = Vec::new();
            let walled = Data { walls: true, ..data.clone() };
            for (full, data) in best.iter().flat_map(|(_, th)| [(th.clone(), &data), (th.clone(), &walled)]) {
                // A closed box's volume held.
                let free: Vec<usize> = (0..full.len()).filter(|&c| !(kind == Kind::Closed && c == 0)).collect();
                let problem = Held { inner: BoxProblem { data, kind }, full: full.clone(), free: free.clone() };
                let th0: Vec<f64> = free.iter().map(|&c| full[c]).collect();
                let mut st = LmState::new(&problem, th0);
                while !st.converged && st.iteration < 300 {
                    st = lm_step(&problem, &st);
                }
                let (r, j) = problem.residual_jacobian(&st.theta);
                let rows_per_point = if magnitude_only { 1 } else { 2 };
                let classical = crate::lm::covariance(&problem, &st.theta);
                let sandwich = crate::lm::sandwich_covariance(&j, &r, CLUSTER_POINTS * rows_per_point);
                let full_theta = problem.expand(&st.theta);
                let sd_ln = (0..full_theta.len())
                    .map(|c| match free.iter().position(|&f| f == c) {
                        None => 0.0,
                        Some(k) => match (&classical, &sandwich) {
                            (Some(a), Some(w)) => crate::lm::sd_from_variance(a[(k, k)].max(w[(k, k)])),
                            (Some(a), None) => crate::lm::sd_from_variance(a[(k, k)]),
                            _ => f64::NAN,
                        },
                    })
                    .collect();
                let driver = Parameters { enclosure: None, ..data.driver_at(kind, &full_theta) };
                let res = rms(&r.rows(0, r.len() - N_PENALTY).into_owned());
                let enclosure = data.enclosure(kind, &full_theta);
                solved.push((
                    Solved { residual: res, theta: full_theta, sd_ln },
                    Parameters { enclosure: Some(enclosure), sd: Some(sd), ..driver },
                ));
            }
            solved.sort_by(|a, b| a.0.residual.total_cmp(&b.0.residual));
            if solved.is_empty() {
                let s = Solved {
                    residual: f64::INFINITY,
                    theta: vec![0.0; nk + n_driver],
                    sd_ln: vec![f64::NAN; nk + n_driver],
                };
                let enclosure = data.enclosure(kind, &s.theta);
                solved.push((s, Parameters { enclosure: Some(enclosure), sd: Some(sd), ..data.driver.clone() }));
            }
            let mut all = solved.into_iter();
            let (s, driver) = all.next().expect("one at least");
            (kind, s, driver, all.map(|(_, p)| p).collect::<Vec<_>>())
        })
        .collect();
    let (pick, why) = auto_pick(choice, &fits.iter().map(|(k, s, ..)| (*k, s.residual)).collect::<Vec<_>>());
    let trials: Vec<(&'static str, f64)> = fits.iter().map(|(k, s, ..)| (k.name(), s.residual)).collect();
    let (kind, s, driver, alternatives) = fits.into_iter().nth(pick).expect("one fit at least");
    if kind == Kind::Closed && vb.is_none() {
        return Err(format!("the impedance is of a closed box ({why}); its volume must be given (--vb M3): its air and the driver's suspension are two springs on the same cone, and the terminals see only their sum"));
    }
    let enclosure = data.enclosure(kind, &s.theta);
    let keys = kind.keys();
    let sd_out = keys
        .iter()
        .zip(&s.sd_ln)
        .filter(|(k, _)| !(kind == Kind::Closed && **k == "enclosure.Vb"))
        .map(|(k, sl)| (*k, sl * value_of(&enclosure, k)))
        .collect();
    let on_bound = keys.iter().zip(&s.theta).filter(|(k, t)| at_bound(k, **t)).map(|(k, _)| *k).collect();
    let fit = BoxFit {
        enclosure: enclosure.clone(),
        sd: sd_out,
        residual: s.residual,
        trials,
        why,
        sp_assumed: kind == Kind::Radiator && sp.is_none(),
        on_bound,
        alternatives,
    };
    Ok((Parameters { enclosure: Some(enclosure), ..driver }, fit))
}

/// An impedance estimate's bins `(f, z)` as `n` points evenly spaced in log frequency
/// between `lo` and `hi` (Hz), each the mean of the bins in its cell (cells without a bin are
/// left out): a record's DFT has most of its bins far above where a box and the driver's
/// mechanics show, and a fit over them all would weigh those.
pub fn log_spaced(f: &[f64], z: &[Complex64], n: usize, lo: f64, hi: f64) -> (Vec<f64>, Vec<Complex64>) {
    let (mut fo, mut zo) = (Vec::new(), Vec::new());
    if !(lo > 0.0 && hi > lo) || n == 0 {
        return (fo, zo);
    }
    let step = (hi / lo).ln() / n as f64;
    let mut cells = vec![(0.0, Complex64::new(0.0, 0.0), 0usize); n];
    for (&fk, &zk) in f.iter().zip(z) {
        if fk < lo || fk >= hi {
            continue;
        }
        let c = (((fk / lo).ln() / step) as usize).min(n - 1);
        cells[c].0 += fk;
        cells[c].1 += zk;
        cells[c].2 += 1;
    }
    for (sf, sz, m) in cells.into_iter().filter(|c| c.2 > 0) {
        fo.push(sf / m as f64);
        zo.push(sz / m as f64);
    }
    (fo, zo)
}

/// The driver's Qms a joint fit ([`fit_driver_in_box`]) may reach.
const QMS_RANGE: (f64, f64) = (0.2, 200.0);

/// How far above the least `|Z|` a joint fit's `Re` may go (the data's noise).
const RE_ABOVE_ZMIN: f64 = 1.05;

/// How far a joint fit's electrical values (Re, Le, L2, R2) may move from the start's, as a
/// factor either way.
const ELECTRICAL_RANGE: f64 = 3.0;

/// How many of the grid's best points a joint fit goes on from.
const GRID_KEPT: usize = 6;

/// The electrical starts of a joint fit: `Re` just under the least `|Z|` with `Le` and an
/// LR-2 branch of the same inductance at three times `Re` from the highest point's reactance
/// (the reference the fit's factors are relative to, first), and `start`'s own where they
/// are physical (a free-air fit of a record in a box can end anywhere: on a vented box it
/// gave Re 61 % low, and from there the joint fit ended 44 % low). A coil's eddy currents
/// make its impedance rise slower than a plain inductance's: without a branch Re takes up the
/// difference.
fn electrical_starts(start: &Parameters, f: &[f64], z: &[Complex64]) -> Vec<Parameters> {
    let zmin = z.iter().map(|z| z.norm()).fold(f64::INFINITY, f64::min);
    let ok = |v: f64| v.is_finite() && v > 0.0;
    let k = f.len() - 1;
    let l = (z[k].im / (2.0 * PI * f[k])).max(1e-6) / 2.0;
    let re = 0.95 * zmin;
    let made = Parameters {
        re,
        le: Poly::constant(l),
        l2r2: Some((Poly::constant(l), Poly::constant(3.0 * re))),
        ..start.clone()
    };
    // The mechanical values the factors are relative to: the grid's middle.
    let mid = driver_grid(&made, f, z).swap_remove(DRIVER_GRID / 2);
    let made = Parameters { kms: mid.kms, bl: mid.bl, rms: mid.rms, ..made };
    let mut out = vec![made.clone()];
    let own_ok = ok(start.re)
        && start.re < 1.2 * zmin
        && start.re > re / ELECTRICAL_RANGE
        && ok(start.le.c[0])
        && start.le.c[0] < l * ELECTRICAL_RANGE
        && start.l2r2.as_ref().is_some_and(|(a, b)| ok(a.c[0]) && ok(b.c[0]) && b.c[0] < 1e3 * start.re);
    if own_ok {
        out.push(Parameters { re: start.re, le: start.le.clone(), l2r2: start.l2r2.clone(), ..made });
    }
    out
}

/// The driver's mechanical trials of a joint fit's grid: its resonance from the lowest
/// frequency to a quarter of the highest, `Kms` from it and `Mms`, `Rms` at `Qms = 4`, `Bl`
/// from the highest peak of `|Z|` over `Re` (`Bl^2 = (|Z|max - Re) Rms`).
fn driver_grid(p: &Parameters, f: &[f64], z: &[Complex64]) -> Vec<Parameters> {
    let zmax = z.iter().map(|z| z.norm()).fold(0.0, f64::max);
    let (lo, hi) = (f[0].max(1.0), f[f.len() - 1] / 4.0);
    (0..DRIVER_GRID)
        .map(|k| {
            let fd = lo * (hi / lo).powf(k as f64 / (DRIVER_GRID - 1) as f64);
            let w = 2.0 * PI * fd;
            let rms = w * p.mms / 4.0;
            let bl = ((zmax - p.re).max(0.1 * p.re) * rms).sqrt();
            Parameters { kms: Poly::constant(p.mms * w * w), rms, bl: Poly::constant(bl), ..p.clone() }
        })
        .collect()
}

/// The driver's resonance read from an impedance with two peaks (a port or a radiator),
/// Thiele's way: with the peaks at `fL` and `fH` and the least `|Z|` between them at `fM`
/// (about the outlet's tuning), the driver alone resonates at `fL fH / fM`; its stiffness
/// from `Mms`, `Rms` at `Qms = 4`, `Bl` from the higher peak over `Re`; and the outlet's
/// tuning `fM` and the compliance ratio `alpha = Vas / Vb = (fH^2 - fM^2)(fM^2 - fL^2) /
/// (fH^2 fL^2)`. `None` without two peaks. A grid over the driver's own resonance alone can miss the right pair of peaks
/// and end with the port tuned near the upper one.
fn two_peak_driver(p: &Parameters, f: &[f64], z: &[Complex64]) -> Option<(Parameters, f64, f64)> {
    let m: Vec<f64> = z.iter().map(|z| z.norm()).collect();
    let w = 2;
    let mut peaks: Vec<usize> =
        (w..m.len().saturating_sub(w)).filter(|&k| (k - w..=k + w).all(|j| m[j] <= m[k])).collect();
    peaks.sort_by(|a, b| m[*b].total_cmp(&m[*a]));
    let (a, b) = (*peaks.first()?, *peaks.get(1)?);
    let (lo, hi) = (a.min(b), a.max(b));
    let dip = (lo..=hi).min_by(|x, y| m[*x].total_cmp(&m[*y]))?;
    let fd = f[lo] * f[hi] / f[dip];
    let w = 2.0 * PI * fd;
    let rms = w * p.mms / 4.0;
    let bl = ((m[a] - p.re).max(0.1 * p.re) * rms).sqrt();
    let (fl, fh, fm) = (f[lo], f[hi], f[dip]);
    let alpha = (fh * fh - fm * fm) * (fm * fm - fl * fl) / (fh * fh * fl * fl);
    (alpha > 0.0).then(|| {
        (Parameters { kms: Poly::constant(p.mms * w * w), rms, bl: Poly::constant(bl), ..p.clone() }, fm, alpha)
    })
}

/// `d` as the factors of [`DRIVER_KEYS`] on `r`: the ln of each ratio (the branch's 0 when
/// either lacks it).
fn factors(d: &Parameters, r: &Parameters) -> [f64; 7] {
    let (l2, r2) = match (&d.l2r2, &r.l2r2) {
        (Some((l, rr)), Some((lr, rrr))) => ((l.c[0] / lr.c[0]).ln(), (rr.c[0] / rrr.c[0]).ln()),
        _ => (0.0, 0.0),
    };
    [
        (d.re / r.re).ln(),
        (d.le.c[0] / r.le.c[0]).ln(),
        (d.bl.c[0] / r.bl.c[0]).ln(),
        (d.kms.c[0] / r.kms.c[0]).ln(),
        (d.rms / r.rms).ln(),
        l2,
        r2,
    ]
}

/// Points of [`driver_grid`].
const DRIVER_GRID: usize = 16;

fn rms(r: &DVector<f64>) -> f64 {
    (r.norm_squared() / r.len().max(1) as f64).sqrt()
}

/// The grid's start and Levenberg-Marquardt from it.
fn solve(d: &Data, kind: Kind) -> Solved {
    let start = grid_start(d, kind);
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

/// The best point of a grid over the box's volume (Vas / 100 to 100 Vas) and tuning (fs / 5
/// to 5 fs), the driver held.
fn grid_start(d: &Data, kind: Kind) -> Vec<f64> {
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
    candidates
        .into_iter()
        .map(|th| (cost(&th), th))
        .filter(|(c, _)| c.is_finite())
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, th)| th)
        .unwrap_or_else(|| vec![vas.ln(); kind.keys().len()])
}

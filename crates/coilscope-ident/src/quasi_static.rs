//! Static and quasi-static point-by-point measurement (seed paper 3.2.1; IEC 62458 10.2 and
//! 10.3): the coil is held at a series of working points `x_dc` by a DC current, and at
//! each one
//!
//! - the **static displacement** (a laser) gives the secant stiffness from the force
//!   balance: `Kms(x_dc) x_dc = Bl(x_dc) I_dc + 1/2 Le'(x_dc) I_dc^2` (3.2.1.1, 3.2.1.2);
//! - the **small-signal impedance** of a small noise on top of the DC (3.2.1.3), fitted like
//!   any record ([`crate::linear::fit_linear_record`], Mms given), gives at the working point
//!   `Le(x_dc)`, L2/R2, the effective force factor `Bl(x_dc) + Le'(x_dc) I_dc` (the DC
//!   current's reluctance force adds to Bl in both directions of the coupling) and the
//!   effective stiffness `k_t(x_dc) - Bl'(x_dc) I_dc - 1/2 Le''(x_dc) I_dc^2` (`k_t` the
//!   tangent stiffness). The DC terms are taken off with the derivatives of the series fitted
//!   to the points (two passes);
//! - the **coil's resistance** `U_dc / I_dc`: the extra heat the DC current makes is tracked.
//!
//! The power series are fitted to the points: Bl and Le from the impedances, Kms from the
//! static balances. The paper's caveats are measured, not assumed: a suspension that creeps
//! gives a static stiffness below the dynamic one (its creep bank relaxes under a held
//! offset), and after a large offset the rest position does not come straight back
//! ([`QuasiStatic::rest_drift`]).
//!
//! The transducer is `play`: a drive in volts in, `(u, i, x)` out from rest (a virtual driver
//! or, later, a card with a laser); so the method is the same on both.

use crate::linear::{fit_linear_record, scale_by_mms, LinearOptions};
use coilscope_core::{Parameters, Poly};
use nalgebra::{DMatrix, DVector};

/// Options of [`quasi_static`].
#[derive(Clone, Debug)]
pub struct QuasiStaticOptions {
    /// Moving mass (kg): the absolute scale of the small-signal fits.
    pub mms: f64,
    /// Working points (odd: one at rest).
    pub points: usize,
    /// The outermost working points, as a share of the range on each side.
    pub reach: f64,
    /// The range (m): where the outermost points go (`[x_min, x_max]`).
    pub range: [f64; 2],
    /// Seconds the DC is held before the small signal is recorded (a creeping suspension
    /// relaxes for seconds: the slowest element of a two-per-decade bank from 0.05 Hz is 3 s).
    pub hold_s: f64,
    /// Seconds of small signal recorded at each point.
    pub record_s: f64,
    /// The small signal's RMS voltage.
    pub ac_volts: f64,
    /// Power-series order of the fitted curves.
    pub order: usize,
    pub fs: f64,
    /// How the coil is held off rest.
    pub offset: Offset,
}

impl QuasiStaticOptions {
    /// How the points are held, in words.
    pub fn offset_name(&self) -> &'static str {
        self.offset.name()
    }
}

/// How the quasi-static method holds the coil at a working point (IEC 62458 10.2/10.3).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Offset {
    /// A DC current through the coil: it heats the coil, and its reluctance force and the
    /// DC terms of the small signal are taken off with the fitted series' derivatives.
    Current,
    /// An added mass under gravity (the driver facing up for x < 0, down for x > 0): no
    /// current, but the moving mass grows by the mass (the small-signal fit is scaled by it).
    Mass,
    /// A pressure on the diaphragm of area `sd` (m^2) (a sealed box pumped up or down): no
    /// current and no added mass.
    Pressure { sd: f64 },
}

/// What [`quasi_static`]'s `play` is asked to hold besides the drive: a constant external
/// force on the cone (N, + pushes the coil out) and the mass added to the cone (kg).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Push {
    pub force: f64,
    pub added_mass: f64,
}

/// One play of a working point: `u` (V), `i` (A) and `x` (m) from the start of the drive,
/// and the push actually applied where it differs from the one asked for (an operator who
/// placed 12.5 g where 12.3 g was asked; `None`: as asked).
#[derive(Clone, Debug, Default)]
pub struct Played {
    pub u: Vec<f64>,
    pub i: Vec<f64>,
    pub x: Vec<f64>,
    pub applied: Option<Push>,
}

impl From<(Vec<f64>, Vec<f64>, Vec<f64>)> for Played {
    fn from((u, i, x): (Vec<f64>, Vec<f64>, Vec<f64>)) -> Self {
        Played { u, i, x, applied: None }
    }
}

/// Gravity (m/s^2) of the added-mass offsets.
pub const GRAVITY: f64 = 9.80665;

impl Offset {
    fn push(self, force: f64) -> Push {
        match self {
            Offset::Current => Push::default(),
            Offset::Mass => Push { force, added_mass: force.abs() / GRAVITY },
            Offset::Pressure { .. } => Push { force, added_mass: 0.0 },
        }
    }
    fn name(self) -> &'static str {
        match self {
            Offset::Current => "DC current",
            Offset::Mass => "added mass under gravity",
            Offset::Pressure { .. } => "pressure on the diaphragm",
        }
    }
}

/// One working point.
#[derive(Clone, Debug)]
pub struct WorkingPoint {
    pub u_dc: f64,
    pub i_dc: f64,
    /// The external force holding the point (N; 0 with a DC current offset), and the
    /// pressure (Pa) or added mass (kg) that makes it.
    pub force: f64,
    pub push: Push,
    /// Static displacement (m).
    pub x_dc: f64,
    /// Coil resistance from the DC (ohm): heated by the DC current.
    pub re_dc: f64,
    /// The small-signal fit's effective force factor and stiffness, and Le, at the point.
    pub bl_eff: f64,
    pub k_eff: f64,
    pub le: f64,
    /// Bl(x_dc) with the reluctance term taken off.
    pub bl: f64,
    /// Secant stiffness from the static balance (NaN at rest).
    pub kms_static: f64,
    /// Tangent stiffness from the small signal, the DC terms taken off.
    pub k_tangent: f64,
    /// sds of `bl_eff` and `le` (the point's small-signal fit: Bl = sqrt(Mms / Cmes) with
    /// Mms given) and of `kms_static` (through Bl; x and I are means over seconds).
    pub bl_sd: f64,
    pub le_sd: f64,
    pub kms_sd: f64,
    /// The point's small-signal fit's relative current error.
    pub residual: f64,
}

/// The measurement: the points, and the series fitted to them.
#[derive(Clone, Debug)]
pub struct QuasiStatic {
    pub points: Vec<WorkingPoint>,
    /// The start set with Bl(x), Kms(x) (static secant), Le(x) fitted to the points, Re the
    /// cold value (the point at rest), `x_range` the points' span.
    pub params: Parameters,
    /// Displacement (m) 1.5 s after the largest positive offset is released to 0 V.
    pub rest_drift: f64,
    /// The small signal's stiffness at rest (N/m): the dynamic one, at the resonance. The
    /// static `params.kms(0)` of a creeping suspension is below it.
    pub k_dynamic_rest: f64,
    /// What makes the curves doubtful, named: a coil the DC heated far (its Re rose by more
    /// than [`MAX_RE_RISE`]). (Points short of the reach asked for are not: `params.x_range`
    /// is the span they reached.)
    pub warnings: Vec<String>,
    /// Bands (value and sd on 21 displacements over the points' span) of Bl, Kms, Le: the
    /// series' covariance from the points' sds, scaled up by the series fit's chi^2 per
    /// degree of freedom where above 1 (what the series' order leaves between the points).
    pub bands: [coilscope_core::result::Band; 3],
}

/// Largest rise of the coil's resistance under a working point's DC before the result is
/// called doubtful (20 %: about 50 K of copper). A microspeaker with a 2 s thermal time
/// constant held at its excursion limit by DC heats hundreds of kelvin (0.1 g: Re 7.5 -> 27
/// ohm), its current and so its reach collapse, and its curves came out 70-125 % off.
pub const MAX_RE_RISE: f64 = 0.2;

/// The smallest relative sd of a working point's Bl and Le (0.1 %): the small signal moves
/// the coil by about 2 % of the range, over which Bl(x), Kms(x), Le(x) change, and its linear
/// fit reads that as about 0.1 % on the values at the point, beyond its own sds (SB17 and
/// PTT4 with the fits' sds alone: the truth at 2.5-4.6 sd of the bands).
pub const POINT_SD_FLOOR: f64 = 1e-3;

/// A working point's small-signal fit has failed when its current error is above
/// `POINT_RESIDUAL_LIMIT` times the rest point's and above [`POINT_RESIDUAL_FLOOR`]: off rest
/// the small signal sees the curves change across its own excursion (18WU at 8.6 mm: 8 times
/// the rest point's error), a failed fit is hundreds of times off (25 % against 0.07 %).
pub const POINT_RESIDUAL_LIMIT: f64 = 30.0;
/// See [`POINT_RESIDUAL_LIMIT`] (2 % of the current).
pub const POINT_RESIDUAL_FLOOR: f64 = 0.02;

/// Least-squares power series of `order` through `(x, y)` (fewer points: lower order).
pub fn fit_series(x: &[f64], y: &[f64], order: usize) -> Poly {
    if x.is_empty() {
        return Poly::constant(f64::NAN);
    }
    let n = order.min(x.len().saturating_sub(1));
    let scale = x.iter().fold(0.0f64, |a, v| a.max(v.abs())).max(1e-9);
    let a = DMatrix::from_fn(x.len(), n + 1, |r, c| (x[r] / scale).powi(c as i32));
    let b = DVector::from_column_slice(y);
    let c = a.clone().svd(true, true).solve(&b, 1e-12).unwrap_or_else(|_| DVector::zeros(n + 1));
    Poly { c: (0..=n).map(|j| c[j] / scale.powi(j as i32)).collect() }
}

/// [`fit_series`] with its band on `grid`: the reported series itself (the band's values
/// are the curve the result carries) and the sd of that least-squares estimator from the
/// points' sds, `B A' diag(sd^2) A B` with `B = (A'A)^-1`, scaled up by the points' chi^2
/// per degree of freedom about the series where above 1 (what the order leaves between
/// them). A point without a usable sd takes the smallest of the others.
pub fn fit_series_band(
    x: &[f64],
    y: &[f64],
    sd: &[f64],
    order: usize,
    grid: &[f64],
) -> (Poly, coilscope_core::result::Band) {
    let poly = fit_series(x, y, order);
    let n = poly.c.len() - 1;
    let scale = x.iter().fold(0.0f64, |a, v| a.max(v.abs())).max(1e-9);
    let floor = sd.iter().cloned().filter(|v| v.is_finite() && *v > 0.0).fold(f64::INFINITY, f64::min);
    let sd: Vec<f64> = sd
        .iter()
        .map(|&s| {
            if s.is_finite() && s > 0.0 {
                s
            } else if floor.is_finite() {
                floor
            } else {
                1.0
            }
        })
        .collect();
    let a = DMatrix::from_fn(x.len(), n + 1, |r, c| (x[r] / scale).powi(c as i32));
    let chi2: f64 = x.iter().zip(y).zip(&sd).map(|((&xv, &yv), s)| ((yv - poly.eval(xv)) / s).powi(2)).sum();
    let s2 = (chi2 / (x.len() as f64 - (n + 1) as f64).max(1.0)).max(1.0);
    let meat = a.transpose() * DMatrix::from_diagonal(&DVector::from_iterator(sd.len(), sd.iter().map(|s| s * s))) * &a;
    let cov = (a.transpose() * &a)
        .try_inverse()
        .map(|b| &b * meat * &b * s2)
        .unwrap_or_else(|| DMatrix::from_element(n + 1, n + 1, f64::NAN));
    let value = grid.iter().map(|&v| poly.eval(v)).collect();
    let sdv = grid
        .iter()
        .map(|&v| {
            let g = DVector::from_iterator(n + 1, (0..=n).map(|j| (v / scale).powi(j as i32)));
            (g.transpose() * &cov * &g)[(0, 0)].max(0.0).sqrt()
        })
        .collect();
    (poly, coilscope_core::result::Band { x: grid.to_vec(), value, sd: sdv })
}

/// The drive of a working point: a raised-cosine ramp to `u_dc` over 1 s, `hold` s of DC,
/// then `ac` added.
fn drive(u_dc: f64, hold: f64, ac: &[f64], fs: f64) -> Vec<f64> {
    let ramp = fs as usize;
    let held = (hold * fs) as usize;
    (0..ramp + held + ac.len())
        .map(|k| {
            let dc = if k < ramp {
                u_dc * 0.5 * (1.0 - (std::f64::consts::PI * k as f64 / ramp as f64).cos())
            } else {
                u_dc
            };
            dc + if k >= ramp + held { ac[k - ramp - held] } else { 0.0 }
        })
        .collect()
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

/// Run the point-by-point measurement on `play` (`(drive, push) -> (u, i, x)`, from rest
/// each time, the push's force and added mass held from the start), with `ac` the small
/// signal (unit RMS noise of at least `record_s`).
pub fn quasi_static(
    mut play: impl FnMut(&[f64], Push) -> Result<Played, String>,
    ac: &[f64],
    opts: &QuasiStaticOptions,
) -> Result<QuasiStatic, String> {
    point_by_point(&mut play, ac, opts)
}

/// [`quasi_static`]'s work, compiled once (not for each caller's `play`).
fn point_by_point(
    play: &mut dyn FnMut(&[f64], Push) -> Result<Played, String>,
    ac: &[f64],
    opts: &QuasiStaticOptions,
) -> Result<QuasiStatic, String> {
    if opts.points < 3 || opts.points.is_multiple_of(2) {
        return Err(format!("{} working points: give an odd number, at least 3", opts.points));
    }
    let fs = opts.fs;
    let nrec = (opts.record_s * fs) as usize;
    if ac.len() < nrec {
        return Err(format!("the small signal has {} samples, {nrec} needed", ac.len()));
    }
    let ac: Vec<f64> = ac[..nrec].iter().map(|v| v * opts.ac_volts).collect();
    let settle = (0.25 * fs) as usize;
    if let Offset::Pressure { sd } = opts.offset {
        if !(sd.is_finite() && sd > 0.0 && sd < 2.0) {
            return Err(format!(
                "the pressure offset needs the diaphragm's area Sd (m^2, e.g. 0.0133); {sd} is not valid"
            ));
        }
    }
    let point = |play: &mut dyn FnMut(&[f64], Push) -> Result<Played, String>,
                 u_dc: f64,
                 push: Push|
     -> Result<(WorkingPoint, Parameters), String> {
        let d = drive(u_dc, opts.hold_s, &ac, fs);
        let Played { u, i, x, applied } = play(&d, push)?;
        let push = applied.unwrap_or(push);
        if u.len() < d.len() || i.len() < d.len() || x.len() < d.len() {
            return Err(format!(
                "working point {u_dc:.3} V, {:.3} N: {} / {} / {} samples of u / i / x for a drive of {}",
                push.force,
                u.len(),
                i.len(),
                x.len(),
                d.len()
            ));
        }
        let from = d.len() - nrec + settle;
        let (u, i, x) = (&u[from..], &i[from..], &x[from..]);
        let (um, im, xm) = (mean(u), mean(i), mean(x));
        let uac: Vec<f64> = u.iter().map(|v| v - um).collect();
        let iac: Vec<f64> = i.iter().map(|v| v - im).collect();
        let fit = fit_linear_record(
            &uac,
            &iac,
            fs,
            &format!("working point {:.3} V, {:.3} N", u_dc, push.force),
            &LinearOptions::default(),
            |_| {},
        )?;
        // An added mass moves with the cone: the small-signal fit's absolute scale.
        let mut p = scale_by_mms(&fit, opts.mms + push.added_mass)?;
        p.mms = opts.mms;
        // At rest the DC is only the drift of the noise: Re is the small-signal fit's there.
        let re_dc = if u_dc != 0.0 { um / im } else { p.re };
        // The fit's own sds, with a floor of POINT_SD_FLOOR for what a linear fit of a small
        // signal on a nonlinear driver leaves (see the constant).
        let (bl_sd, le_sd) = (
            (0.5 * fit.sigma_rel[5]).max(POINT_SD_FLOOR) * p.bl.c[0],
            fit.sigma_rel[1].max(POINT_SD_FLOOR) * p.le.c[0],
        );
        let wp = WorkingPoint {
            u_dc,
            i_dc: im,
            force: push.force,
            push,
            x_dc: xm,
            re_dc,
            bl_eff: p.bl.c[0],
            k_eff: p.kms.c[0],
            le: p.le.c[0],
            bl: f64::NAN,
            kms_static: f64::NAN,
            k_tangent: f64::NAN,
            bl_sd,
            le_sd,
            kms_sd: f64::NAN,
            residual: fit.residual_rel,
        };
        Ok((wp, p))
    };
    // At rest: the small-signal set, and the linear map from volts to displacement.
    let (rest, p0) = point(play, 0.0, Push::default())?;
    let per_volt = rest.bl_eff / (p0.re * rest.k_eff);
    let per_newton = 1.0 / rest.k_eff;
    let half = opts.points / 2;
    let mut pts = vec![rest];
    for side in [1.0f64, -1.0] {
        let edge = if side > 0.0 { opts.range[1] } else { -opts.range[0] };
        // Outward from rest: each point's volts from the last one's volts per metre (the
        // suspension stiffens, so the linear map undershoots more and more).
        let mut volts_per_m = 1.0 / per_volt;
        let mut newtons_per_m = 1.0 / per_newton;
        for k in 1..=half {
            let target = side * opts.reach * edge * k as f64 / half as f64;
            let (wp, _) = match opts.offset {
                Offset::Current => point(play, target * volts_per_m, Push::default())?,
                o => point(play, 0.0, o.push(target * newtons_per_m))?,
            };
            if wp.x_dc.abs() > 1e-9 {
                volts_per_m = wp.u_dc / wp.x_dc;
                newtons_per_m = wp.force / wp.x_dc;
            }
            pts.push(wp);
        }
    }
    // A point whose small-signal fit failed (stuck far from the data, or a value that is not
    // a number) is left out of the series, by name: 18WU by mass, at 2.3 N the fit stopped
    // after one iteration at 25 % current error, Bl 1.74 T m (true 6.0), and the series took
    // it in without a word.
    let r0 = pts[0].residual;
    let mut warnings = vec![];
    // Over every point, those left out below too (the heat is what made them fail).
    let hot = pts.iter().map(|p| p.re_dc / p0.re - 1.0).fold(0.0, f64::max);
    if hot > MAX_RE_RISE {
        warnings.push(format!(
            "the DC heated the coil: its resistance rose by {:.0} % (about {:.0} K) at the outermost points; the current, the reach and the curves there are not trustworthy (shorten --hold, fewer points, or measure with a displacement offset that needs no current: an added mass or pressure)",
            100.0 * hot,
            hot / coilscope_core::params::ALPHA_COPPER
        ));
    }

    pts.retain(|p| {
        let ok = p.bl_eff.is_finite() && p.k_eff.is_finite() && p.le.is_finite() && p.x_dc.is_finite() && p.residual <= (POINT_RESIDUAL_LIMIT * r0).max(POINT_RESIDUAL_FLOOR);
        if !ok {
            warnings.push(format!(
                "the working point at {:.3} V, {:.3} N (x {:.3} mm) is left out: its small-signal fit failed (current error {:.2} % against {:.3} % at rest, from a fit stuck far from the data or a coil heating during the record; Bl {:.4} T m, Le {:.4} mH); the series are fitted to the other points",
                p.u_dc,
                p.force,
                p.x_dc * 1e3,
                100.0 * p.residual,
                100.0 * r0,
                p.bl_eff,
                p.le * 1e3
            ));
        }
        ok
    });
    pts.sort_by(|a, b| a.x_dc.total_cmp(&b.x_dc));
    // Two passes: series from the points, then the DC terms taken off with their derivatives.
    let xs: Vec<f64> = pts.iter().map(|p| p.x_dc).collect();
    // Each series with its band over the points' span (the band's values are the series).
    let span: Vec<f64> = (0..21).map(|k| xs[0] + (xs[xs.len() - 1] - xs[0]) * k as f64 / 20.0).collect();
    let col = |pts: &[WorkingPoint], f: &dyn Fn(&WorkingPoint) -> f64| pts.iter().map(f).collect::<Vec<f64>>();
    let (le, le_band) = fit_series_band(&xs, &col(&pts, &|p| p.le), &col(&pts, &|p| p.le_sd), opts.order, &span);
    let dle = le.derivative();
    let ddle = dle.derivative();
    let mut bl = fit_series(&xs, &col(&pts, &|p| p.bl_eff), opts.order);
    let mut bl_band = Default::default();
    for _ in 0..2 {
        for p in pts.iter_mut() {
            p.bl = p.bl_eff - dle.eval(p.x_dc) * p.i_dc;
        }
        (bl, bl_band) = fit_series_band(&xs, &col(&pts, &|p| p.bl), &col(&pts, &|p| p.bl_sd), opts.order, &span);
    }
    let dbl = bl.derivative();
    for p in pts.iter_mut() {
        let (x, i) = (p.x_dc, p.i_dc);
        p.k_tangent = p.k_eff + dbl.eval(x) * i + 0.5 * ddle.eval(x) * i * i;
        if x.abs() > 1e-3 * opts.range[1].max(-opts.range[0]) {
            p.kms_static = (p.force + bl.eval(x) * i + 0.5 * dle.eval(x) * i * i) / x;
            // Through Bl when the current holds the point; a force is known (a mass, a
            // pressure): its own share, taken as the floor.
            p.kms_sd = if p.force != 0.0 {
                (p.kms_static * POINT_SD_FLOOR).abs()
            } else {
                (p.kms_static * p.bl_sd / p.bl_eff).abs()
            };
        }
    }
    // Kms: the static secants only (at rest the secant is 0/0; the small signal's stiffness
    // there is the dynamic one, which a creeping suspension holds above the static).
    let (kx, ky): (Vec<f64>, Vec<f64>) =
        pts.iter().filter(|p| p.kms_static.is_finite()).map(|p| (p.x_dc, p.kms_static)).unzip();
    if kx.len() < 2 {
        let seen: Vec<String> =
            pts.iter().map(|p| format!("{:.3} V: x {:.4} mm, Bl_eff {:.4}", p.u_dc, p.x_dc * 1e3, p.bl_eff)).collect();
        return Err(format!("only {} working point(s) gave a static stiffness, at least 2 are needed: the coil did not move off rest, or the small-signal fits at the points failed (raise the small signal's level) ({})", kx.len(), seen.join(", ")));
    }
    let ks: Vec<f64> = pts.iter().filter(|p| p.kms_static.is_finite()).map(|p| p.kms_sd).collect();
    let (kms, kms_band) = fit_series_band(&kx, &ky, &ks, opts.order, &span);
    // The point at rest: no DC and no push (with a mass or a pressure every point has no DC).
    let k_dynamic_rest = pts.iter().find(|p| p.u_dc == 0.0 && p.force == 0.0).map_or(f64::NAN, |p| p.k_tangent);
    // The rest position after the largest positive offset: release it, wait a second. (A
    // held force is constant over a play: its release is not simulated.)
    let rest_drift = if opts.offset == Offset::Current {
        let top = pts.iter().map(|p| p.u_dc).fold(0.0, f64::max);
        let mut d = drive(top, opts.hold_s, &[], fs);
        let n = (fs as usize) * 2;
        d.extend((0..n).map(|k| top * 0.5 * (1.0 + (std::f64::consts::PI * (k as f64 / (fs * 0.5)).min(1.0)).cos())));
        *play(&d, Push::default())?.x.last().unwrap_or(&0.0)
    } else {
        f64::NAN
    };
    let [lo, hi] = [xs[0], xs[xs.len() - 1]];
    if kx.len() < opts.order + 3 {
        warnings.push(format!(
            "{} static points for a series of order {}: the stiffness between the points is interpolated with fewer than 2 points to spare, nothing checks it (with 5 points PTT4's Kms came out 3 % off near rest); give --points {} or more, or a lower --order",
            kx.len(),
            opts.order,
            opts.order + 4 + (opts.order % 2)
        ));
    }
    let params = Parameters {
        re: p0.re,
        bl,
        kms,
        le,
        x_range: Some([lo, hi]),
        source: Some(format!("coilscope quasistatic (point by point, offset by {})", opts.offset.name())),
        ..p0
    };
    Ok(QuasiStatic { points: pts, params, rest_drift, k_dynamic_rest, warnings, bands: [bl_band, kms_band, le_band] })
}

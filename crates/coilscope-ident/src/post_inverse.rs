//! Equation-error (post-inverse) estimate from voltage, current *and* displacement (seed
//! section 3.2.2): with x measured, both model equations are linear in the parameters, so
//! two direct least-squares solves give the whole set, Mms included (the displacement fixes
//! the scale). A fast start for [`crate::large::identify`] and a cross-check of it.
//!
//! 1. Electrical: `u - u_L2R2 = Re i + sum_j le_j (x^j di/dt + j x^(j-1) v i) + sum_j b_j x^j v`
//!    (L2, R2 from the linear fit; `i2` from `L2 di2/dt = R2 (i - i2)`).
//! 2. Mechanical, with Bl(x) and Le(x) from 1:
//!    `Mms a + Rms v + sum_j k_j x^(j+1) = Bl(x) i + 1/2 Le'(x) i^2`.
//!
//! Derivatives are spectral. Each equation holds at every instant, so applying one linear
//! low-pass to every column and to the left side leaves it exact while it removes the noise
//! that differentiation lifts; the electrical solve is low-passed at 0.4 fs (at most 10 kHz),
//! the mechanical one at 1 kHz.

use coilscope_core::fft::{irfft, rfft};
use coilscope_core::params::Parameters;
use coilscope_core::poly::Poly;
use nalgebra::{DMatrix, DVector};
use realfft::num_complex::Complex64;
use std::f64::consts::PI;

/// `d^order/dt^order` of `x`, low-passed (raised-cosine roll-off from 0.7 fc to fc).
fn filtered(x: &[f64], fs: f64, fc: f64, order: u32) -> Vec<f64> {
    let n = x.len();
    let mut s = rfft(x);
    for (k, c) in s.iter_mut().enumerate() {
        let f = k as f64 * fs / n as f64;
        let w = if f <= 0.7 * fc {
            1.0
        } else if f >= fc {
            0.0
        } else {
            0.5 * (1.0 + (PI * (f - 0.7 * fc) / (0.3 * fc)).cos())
        };
        let jw = Complex64::new(0.0, 2.0 * PI * f);
        *c *= w * jw.powu(order) / n as f64;
    }
    irfft(&s, n)
}

fn solve(cols: Vec<Vec<f64>>, rhs: Vec<f64>) -> Result<Vec<f64>, String> {
    let (m, n) = (rhs.len(), cols.len());
    let mut a = DMatrix::zeros(m, n);
    for (c, col) in cols.iter().enumerate() {
        a.column_mut(c).copy_from_slice(col);
    }
    // Column scaling for conditioning.
    let norms: Vec<f64> = (0..n).map(|c| a.column(c).norm().max(1e-300)).collect();
    for (c, s) in norms.iter().enumerate() {
        a.column_mut(c).scale_mut(1.0 / s);
    }
    let b = DVector::from_vec(rhs);
    let sol =
        a.tr_mul(&a).cholesky().ok_or("the equation-error system is singular (does x move?)")?.solve(&a.tr_mul(&b));
    Ok(sol.iter().zip(&norms).map(|(v, s)| v / s).collect())
}

/// Equation-error estimate of order `order` from `u` (V), `i` (A), `x` (m) at `fs`, with the
/// LR-2 branch `(L2, R2)` (H, ohm) from the linear fit. The result's `x_range` is the measured
/// range of x.
pub fn post_inverse(
    u: &[f64],
    i: &[f64],
    x: &[f64],
    fs: f64,
    order: usize,
    l2r2: Option<(f64, f64)>,
    origin: &str,
) -> Result<Parameters, String> {
    equation_error(u, i, x, fs, order, l2r2, None, origin)
}

/// [`post_inverse`] with the moving mass either estimated (`mms = None`) or given (kg): with
/// Mms given, `Mms a` moves to the right side of the mechanical equation. With `x` taken
/// from the model itself this is the pseudo-linear regression step of the online estimator.
#[allow(clippy::too_many_arguments)]
pub fn equation_error(
    u: &[f64],
    i: &[f64],
    x: &[f64],
    fs: f64,
    order: usize,
    l2r2: Option<(f64, f64)>,
    mms: Option<f64>,
    origin: &str,
) -> Result<Parameters, String> {
    let n = u.len();
    if i.len() != n || x.len() != n {
        return Err(format!("{origin}: channels have different lengths"));
    }
    let fe = (0.4 * fs).min(10000.0);
    let lp = |s: &[f64], fc: f64| filtered(s, fs, fc, 0);
    let v = filtered(x, fs, 0.45 * fs, 1);
    let di = filtered(i, fs, 0.45 * fs, 1);
    // Electrical.
    let u_l2r2: Vec<f64> = match l2r2 {
        Some((l2, r2)) => {
            // Exact discretisation of the first-order branch, current held over a sample.
            let a = (-r2 / l2 / fs).exp();
            let mut i2 = 0.0;
            i.iter()
                .map(|&ik| {
                    let ur = r2 * (ik - i2);
                    i2 = a * i2 + (1.0 - a) * ik;
                    ur
                })
                .collect()
        }
        None => vec![0.0; n],
    };
    let mut cols = vec![lp(i, fe)];
    for j in 0..=order {
        let c: Vec<f64> = (0..n)
            .map(|m| {
                x[m].powi(j as i32) * di[m] + if j > 0 { j as f64 * x[m].powi(j as i32 - 1) * v[m] * i[m] } else { 0.0 }
            })
            .collect();
        cols.push(lp(&c, fe));
    }
    for j in 0..=order {
        let c: Vec<f64> = (0..n).map(|m| x[m].powi(j as i32) * v[m]).collect();
        cols.push(lp(&c, fe));
    }
    let rhs: Vec<f64> = lp(&(0..n).map(|m| u[m] - u_l2r2[m]).collect::<Vec<_>>(), fe);
    let e = solve(cols, rhs)?;
    let re = e[0];
    let le = Poly { c: e[1..order + 2].to_vec() };
    let bl = Poly { c: e[order + 2..].to_vec() };
    // Mechanical.
    let fm = 1000.0f64.min(0.4 * fs);
    let a = filtered(x, fs, fm, 2);
    let vm = filtered(x, fs, fm, 1);
    let mut cols = if mms.is_some() { vec![vm] } else { vec![a.clone(), vm] };
    for j in 0..=order {
        let c: Vec<f64> = x.iter().map(|&xm| xm.powi(j as i32 + 1)).collect();
        cols.push(lp(&c, fm));
    }
    let force: Vec<f64> = (0..n)
        .map(|m| {
            let (_, dle) = le.eval_d(x[m]);
            bl.eval(x[m]) * i[m] + 0.5 * dle * i[m] * i[m] - mms.map_or(0.0, |mm| mm * a[m])
        })
        .collect();
    let mut k = solve(cols, lp(&force, fm))?;
    if let Some(mm) = mms {
        k.insert(0, mm);
    }
    let (mms, rms) = (k[0], k[1]);
    if bl.eval(0.0) < 0.0 {
        return Err(format!("{origin}: the displacement channel (3) has inverted polarity: Bl(0) comes out {:.3} T m; x > 0 must be coil out for positive current", bl.eval(0.0)));
    }
    if !(mms > 0.0 && rms > 0.0 && re > 0.0 && bl.eval(0.0) > 0.0) {
        return Err(format!("{origin}: the equation-error estimate is not physical (Mms {mms:.4e} kg, Rms {rms:.4e} kg/s, Re {re:.4e} ohm); check the displacement channel's scale and polarity"));
    }
    let x_range =
        [x.iter().cloned().fold(f64::INFINITY, f64::min), x.iter().cloned().fold(f64::NEG_INFINITY, f64::max)];
    Ok(Parameters {
        name: None,
        source: Some("coilscope post-inverse (equation error with measured displacement)".into()),
        re,
        le,
        l2r2: l2r2.map(|(l2, r2)| (Poly::constant(l2), Poly::constant(r2))),
        bl,
        kms: Poly { c: k[2..].to_vec() },
        mms,
        rms,
        sd: None,
        creep: None,
        l3r3: None,
        le_i: None,
        rms_v: None,
        thermal: None,
        enclosure: None,
        x_range: Some(x_range),
        extra: Default::default(),
    })
}

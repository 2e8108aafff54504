//! The minimum phase of a magnitude-only impedance curve (Bode's gain-phase relation).
//!
//! A passive one-port's impedance is a positive-real function, so it has no zeros or poles in
//! the right half plane: its phase follows from its magnitude,
//!
//! ```text
//! phi(u0) = (1/pi) integral dA/du ln coth(|u - u0| / 2) du,   A = ln |Z|,  u = ln w
//! ```
//!
//! A measured curve covers a band only. Below it, |Z| is taken to settle as a driver's does
//! below its resonance, where `Z = Re + jw Bl^2 / Kms` and `ln |Z|` flattens as `w^2`: its
//! slope `s` at the band's bottom decays as `s (w / w_lo)^2` (a falling slope, as at the
//! bottom of a curve that starts above its resonance, is taken flat). Above the band, |Z|
//! goes on as `|R + jwL|` through the top point with the slope of the band's top tenth (in
//! log frequency): a voice coil whose semi-inductance gives way to its inductance, the slope
//! rising to 1. The phase this gives is a
//! start for the fit, which then fits the magnitude alone
//! ([`crate::linear::fit_impedance_magnitude`]): the lumped model's own phase is minimum
//! phase, so a magnitude fit takes nothing from this reconstruction's guesses at the band's
//! ends.
//!
//! The integral is exact for a magnitude that is piecewise linear in `(ln f, ln |Z|)` between
//! the points: each segment contributes its slope times the kernel's integral over it,
//! [`kernel_integral`], in closed form.

use std::f64::consts::PI;

/// `F(x) = integral_0^x ln coth(t / 2) dt` for `x >= 0`, `F(inf) = pi^2 / 4`.
///
/// Below 0.1 its series at 0 (`ln coth(t/2) = -ln(t/2) + t^2/12 - 7 t^4/1440 + ...`), above
/// it `pi^2/4 - 2 sum_{k odd} e^{-k x} / k^2` (`ln coth(t/2) = 2 sum_{k odd} e^{-k t} / k`);
/// both to better than 1e-9.
pub fn kernel_integral(x: f64) -> f64 {
    if x.is_nan() {
        return f64::NAN;
    }
    if x <= 0.0 {
        return 0.0;
    }
    if x < 0.1 {
        return x - x * (x / 2.0).ln() + x.powi(3) / 36.0 - 7.0 * x.powi(5) / 7200.0;
    }
    let mut tail = 0.0;
    let mut k = 1.0;
    loop {
        let term = (-k * x).exp() / (k * k);
        tail += term;
        if term < 1e-13 {
            break;
        }
        k += 2.0;
    }
    PI * PI / 4.0 - 2.0 * tail
}

/// The odd extension of [`kernel_integral`]: `integral_0^x ln coth(|t| / 2) dt` for any `x`.
fn g(x: f64) -> f64 {
    x.signum() * kernel_integral(x.abs())
}

/// Most points the integral runs over: a longer curve is taken on this many log-spaced
/// points (the integral is O(n^2)).
const MAX_POINTS: usize = 1000;

/// The minimum phase (rad) at each of the frequencies `f` (Hz, increasing, positive) of a
/// curve with magnitudes `mag` (positive); the caller checks both (a NaN in, NaN out).
pub fn min_phase(f: &[f64], mag: &[f64]) -> Vec<f64> {
    let n = f.len().min(mag.len());
    if n < 2 {
        return vec![0.0; n];
    }
    let (u_all, a_all): (Vec<f64>, Vec<f64>) =
        (f[..n].iter().map(|f| f.ln()).collect(), mag[..n].iter().map(|m| m.ln()).collect());
    // The grid the integral runs on: the points, or log-spaced points interpolated.
    let (u, a) = if n <= MAX_POINTS {
        (u_all.clone(), a_all.clone())
    } else {
        let (lo, hi) = (u_all[0], u_all[n - 1]);
        let u: Vec<f64> = (0..MAX_POINTS).map(|k| lo + (hi - lo) * k as f64 / (MAX_POINTS - 1) as f64).collect();
        let a = u.iter().map(|&x| interpolate(&u_all, &a_all, x)).collect();
        (u, a)
    };
    // Below the band: points on the settling tail, 0.1 apart in ln f over 6 (the slope down
    // to e^-12 of the bottom's).
    // The bottom's slope over the band's first tenth in ln f (one segment's would carry its
    // points' noise).
    let u_first = u[0] + 0.1 * (u[u.len() - 1] - u[0]);
    let j_lo = (1..u.len()).find(|&j| u[j] >= u_first).unwrap_or(u.len() - 1);
    let s_below = ((a[j_lo] - a[0]) / (u[j_lo] - u[0])).max(0.0);
    let (u, a): (Vec<f64>, Vec<f64>) = (1..=60)
        .rev()
        .map(|k| (u[0] - 0.1 * k as f64, a[0] + s_below / 2.0 * ((-0.2 * k as f64).exp() - 1.0)))
        .chain(u.iter().copied().zip(a.iter().copied()))
        .unzip();
    // Above the band: `|R + jwL|` through the top point with the slope of the band's top
    // tenth (in ln f), `w^2 L^2 = s |Z|^2`, `R^2 = (1 - s) |Z|^2`, on points 0.1 apart in ln f
    // over 8; from there the slope is 1 for ever.
    let m = u.len();
    let u_tenth = u[m - 1] - 0.1 * (u[m - 1] - u[60]);
    let j_top = (0..m).find(|&j| u[j] >= u_tenth).unwrap_or(0).min(m - 2);
    let s_top = ((a[m - 1] - a[j_top]) / (u[m - 1] - u[j_top])).clamp(0.0, 1.0);
    let (u_end, a_end) = (u[m - 1], a[m - 1]);
    let (u, a): (Vec<f64>, Vec<f64>) = u
        .into_iter()
        .zip(a)
        .chain((1..=80).map(|k| {
            let du = 0.1 * k as f64;
            // |Z|^2 / |Z_top|^2 = (1 - s) + s e^{2 du}.
            (u_end + du, a_end + 0.5 * ((1.0 - s_top) + s_top * (2.0 * du).exp()).ln())
        }))
        .unzip();
    let m = u.len();
    let slope: Vec<f64> = (0..m - 1).map(|j| (a[j + 1] - a[j]) / (u[j + 1] - u[j])).collect();
    let s_above = 1.0;
    let phase_at = |u0: f64| -> f64 {
        let inside: f64 = (0..m - 1).map(|j| slope[j] * (g(u[j + 1] - u0) - g(u[j] - u0))).sum();
        // Above the band: slope s_above from u[m-1] to infinity.
        let above = s_above * (PI * PI / 4.0 - g(u[m - 1] - u0));
        (inside + above) / PI
    };
    if n <= MAX_POINTS {
        u_all.iter().map(|&u0| phase_at(u0)).collect()
    } else {
        let ph: Vec<f64> = u.iter().map(|&u0| phase_at(u0)).collect();
        u_all.iter().map(|&x| interpolate(&u, &ph, x)).collect()
    }
}

/// `y` at `x` by linear interpolation in the increasing `xs` (clamped at the ends).
fn interpolate(xs: &[f64], ys: &[f64], x: f64) -> f64 {
    let k = xs.partition_point(|&v| v < x).clamp(1, xs.len() - 1);
    let t = ((x - xs[k - 1]) / (xs[k] - xs[k - 1])).clamp(0.0, 1.0);
    ys[k - 1] + t * (ys[k] - ys[k - 1])
}

#[cfg(test)]
mod tests {
    use super::*;
    use coilscope_core::small_signal::impedance;

    /// The closed form against a fine midpoint sum: of `ln coth(t/2) + ln(t/2)`, smooth at 0,
    /// plus the exact `integral_0^x -ln(t/2) dt = x - x ln(x/2)`.
    #[test]
    fn kernel_integral_matches_a_fine_sum() {
        for x in [1e-4, 0.01, 0.3, 0.49, 0.5, 0.51, 1.0, 3.0, 10.0] {
            let n = 200_000;
            let h = x / n as f64;
            let smooth: f64 = (0..n)
                .map(|k| {
                    let t = (k as f64 + 0.5) * h;
                    ((t / 2.0).tanh().recip().ln() + (t / 2.0).ln()) * h
                })
                .sum();
            let sum = smooth + x - x * (x / 2.0).ln();
            assert!((kernel_integral(x) - sum).abs() < 1e-8 * sum.max(1e-3), "x {x}: {} vs {sum}", kernel_integral(x));
        }
        assert!((kernel_integral(60.0) - PI * PI / 4.0).abs() < 1e-12);
    }

    /// A series R-L (`R + jwL`): its phase `atan(wL/R)` from its magnitude alone, on a band
    /// wide enough that the ends' guesses hold (flat below, +1 slope above).
    #[test]
    fn min_phase_of_an_rl_is_its_phase() {
        let (r, l) = (6.0, 1e-3);
        let f: Vec<f64> = (0..400).map(|k| 0.1 * 10f64.powf(7.0 * k as f64 / 399.0)).collect();
        let mag: Vec<f64> = f.iter().map(|&f| (r * r + (2.0 * PI * f * l).powi(2)).sqrt()).collect();
        let ph = min_phase(&f, &mag);
        for (k, &fk) in f.iter().enumerate() {
            let truth = (2.0 * PI * fk * l / r).atan();
            assert!((ph[k] - truth).abs() < 2e-3, "{fk} Hz: {} vs {truth}", ph[k]);
        }
    }

    /// A driver's impedance (SB17 with creep and LR-3) on 10 Hz - 20 kHz, the band of a real
    /// file: within a few degrees of its phase inside the band (the ends' guesses cost most
    /// at the band's bottom), as a start for the fit.
    #[test]
    fn min_phase_of_a_driver_is_near_its_phase() {
        let mut p = coilscope_core::embedded_driver("sb17cac35-4").unwrap();
        p.creep = Some(coilscope_core::params::Creep { lambda: 0.1, f_ref: None });
        p.l3r3 = Some((0.5 * p.l2r2.as_ref().unwrap().0.c[0], 3.0 * p.l2r2.as_ref().unwrap().1.c[0]));
        let f: Vec<f64> = (0..400).map(|k| 10.0 * 2000f64.powf(k as f64 / 399.0)).collect();
        let z: Vec<_> = f.iter().map(|&f| impedance(&p, f)).collect();
        let ph = min_phase(&f, &z.iter().map(|z| z.norm()).collect::<Vec<_>>());
        let (worst, at) = f
            .iter()
            .zip(&ph)
            .zip(&z)
            .filter(|((f, _), _)| **f >= 20.0 && **f <= 10000.0)
            .map(|((f, p), z)| ((p - z.arg()).abs().to_degrees(), *f))
            .fold((0.0, 0.0), |a, b| if b.0 > a.0 { b } else { a });
        assert!(worst < 5.0, "worst {worst:.2} deg over 20 Hz - 10 kHz, at {at:.0} Hz");
    }
}

//! Calibration of a measurement chain from a record of a known resistor (or a loopback).
//!
//! Wire a resistor `R` where the driver goes (or feed one signal into both channels: a
//! loopback, `R = 1`), play broadband noise that reaches well below the card's coupling
//! corners (down to 0.3 Hz), and record it as for a driver. Through the chain of
//! [`coilscope_core::chain`] the recorded impedance is
//!
//! ```text
//! Z_rec(f) = U_rec / I_rec = (R / g) H_u(f) / H_i(f) e^{j 2 pi f tau}
//! ```
//!
//! with `H_u`, `H_i` the channels' first-order AC couplings (corners `hp_u`, `hp_i`), `tau`
//! the current channel's delay against the voltage and `g` its gain against the voltage
//! channel. A resistor's own impedance is `R` at every frequency, so whatever `Z_rec` does is
//! the chain's. [`calibrate`] fits these four quantities to the H1 estimate of `Z_rec` over
//! long segments (resolution 0.1 Hz or finer, so the corners are resolved), each bin
//! weighted by its coherence (the H1's variance is `(1 - C) / (2 K C)` of `|Z|^2` with `K`
//! averages), the bins next to mains lines left out. A constant offset is invisible in
//! every bin but the DC one, which is not fitted.
//!
//! The corners are `hp = s^2` of the solver's unknowns `s`, so a DC-coupled channel (0 Hz)
//! is reachable without a bound; the delay is in samples, the gain a logarithm.

use crate::linear::{h1_impedance, near_hum, ImpedanceEstimate};
use crate::lm::{lm_step, sandwich_covariance, LmState, Problem};
use coilscope_core::chain::{hp_coefficients, hp_response_at, Chain};
use coilscope_core::Complex64;
use nalgebra::{DMatrix, DVector};
use std::f64::consts::PI;

/// A calibrated chain with how well the resistor model fitted.
#[derive(Clone, Debug)]
pub struct Calibration {
    /// `source` "calibrated", `delay_i`, `hp_u`, `hp_i`, `gain_i`, with their sds.
    pub chain: Chain,
    /// The resistor (ohm; 1 for a loopback).
    pub resistor: f64,
    /// Fitted band (Hz) and bins.
    pub band: [f64; 2],
    pub bins: usize,
    /// RMS of the weighted residual in units of the H1's own noise (about 1 when the record
    /// is a resistor through this chain).
    pub residual_in_noise: f64,
    /// RMS relative error of the fitted `Z_rec`.
    pub residual_rel: f64,
}

/// Coherence below which a bin is not used.
const MIN_COHERENCE: f64 = 0.9;
/// Weighted residual (in noise sds, RMS) above which the record is refused as not a
/// resistor through a first-order chain.
pub const MAX_RESIDUAL_IN_NOISE: f64 = 5.0;

/// Segment length of the calibration's H1: a power of two, at most a quarter of the record
/// (four averages or more), as long as gives 0.1 Hz or finer.
fn segment(n: usize, fs: f64) -> usize {
    let want = (fs / 0.1) as usize;
    let mut seg = 1024usize;
    while seg * 2 <= n / 4 && seg < want {
        seg *= 2;
    }
    seg
}

struct ResistorProblem {
    f: Vec<f64>,
    z: Vec<Complex64>,
    /// Per-bin weight: 1 / the H1's relative sd.
    w: Vec<f64>,
    fs: f64,
    /// `e^{-j 2 pi f / fs}` per bin ([`hp_response_at`]'s `zi`), taken once.
    zi: Vec<Complex64>,
}

/// A corner's bilinear high-pass at one parameter point, with what the derivative of
/// `ln H` by the fitted `s` (`fc = s^2`) needs: `H = g (1 - zi) / (1 - a zi)` with
/// `k = tan(pi fc / fs)`, `g = 1 / (1 + k)`, `a = (1 - k) / (1 + k)`, so
/// `d ln H / dk = -1 / (1 + k) - 2 zi / ((1 + k)^2 (1 - a zi))` and
/// `dk / ds = 2 s (pi / fs) (1 + k^2)`.
#[derive(Clone, Copy)]
struct Corner {
    /// `(g, a)` ([`hp_coefficients`]); `g` is also `1 / (1 + k)`.
    ga: (f64, f64),
    dk_ds: f64,
}

impl Corner {
    fn new(s: f64, fs: f64) -> Corner {
        let fc = s * s;
        let ga = hp_coefficients(fc, fs);
        let k = (PI * fc / fs).tan();
        Corner { ga, dk_ds: 2.0 * s * PI / fs * (1.0 + k * k) }
    }

    /// `H` at `zi` and `d ln H / ds`.
    fn at(&self, zi: Complex64) -> (Complex64, Complex64) {
        let den = 1.0 - self.ga.1 * zi;
        let h = hp_response_at(self.ga, zi);
        let g = self.ga.0;
        let dln_dk = -g - 2.0 * g * g * zi / den;
        (h, dln_dk * self.dk_ds)
    }
}

impl ResistorProblem {
    fn new(f: Vec<f64>, z: Vec<Complex64>, w: Vec<f64>, fs: f64) -> ResistorProblem {
        let zi = f.iter().map(|&f| Complex64::from_polar(1.0, -2.0 * PI * f / fs)).collect();
        ResistorProblem { f, z, w, fs, zi }
    }

    /// Model `Z_rec` at bin `k` and its derivatives by `[ln(R/g), tau, s_u, s_i]`, with the
    /// corners `cu`, `ci` of theta's `s_u`, `s_i` ([`Corner`]: the derivatives analytic).
    fn model(&self, th: &[f64], cu: &Corner, ci: &Corner, k: usize) -> (Complex64, [Complex64; 4]) {
        let (a, tau) = (th[0], th[1]);
        let f = self.f[k];
        let ((hu, dlu), (hi, dli)) = (cu.at(self.zi[k]), ci.at(self.zi[k]));
        let ph = Complex64::from_polar(a.exp(), 2.0 * PI * f * tau / self.fs);
        let z = hu / hi * ph;
        let j = Complex64::new(0.0, 2.0 * PI * f / self.fs);
        (z, [z, z * j, z * dlu, -z * dli])
    }
}

impl Problem for ResistorProblem {
    fn residual_jacobian(&self, th: &[f64]) -> (DVector<f64>, DMatrix<f64>) {
        let m = self.f.len();
        let mut r = DVector::zeros(2 * m);
        let mut jm = DMatrix::zeros(2 * m, 4);
        let (cu, ci) = (Corner::new(th[2], self.fs), Corner::new(th[3], self.fs));
        for k in 0..m {
            let (z, d) = self.model(th, &cu, &ci, k);
            // Relative error, weighted: (Z_h1 - Z) / |Z| w.
            let scale = self.w[k] / z.norm();
            let e = (self.z[k] - z) * scale;
            r[2 * k] = e.re;
            r[2 * k + 1] = e.im;
            for c in 0..4 {
                let dd = -d[c] * scale;
                jm[(2 * k, c)] = dd.re;
                jm[(2 * k + 1, c)] = dd.im;
            }
        }
        (r, jm)
    }
}

/// The fit with equal corners (the model is then independent of their common value: both
/// 0), from the free fit `th`: its sum of squared residuals, and the sd of a corner
/// difference (Hz) there, `sigma / |J_d|` with `J_d` the residuals' derivative by the
/// difference (finite, 1e-3 Hz), less what gain and delay absorb, and `sigma` the free fit's
/// residual scale.
fn tied_corners(prob: &ResistorProblem, th: &[f64], sigma: f64) -> (f64, f64) {
    struct Tied<'a>(&'a ResistorProblem);
    impl Problem for Tied<'_> {
        fn residual_jacobian(&self, th: &[f64]) -> (DVector<f64>, DMatrix<f64>) {
            let (r, j) = self.0.residual_jacobian(&[th[0], th[1], 0.0, 0.0]);
            (r, j.columns(0, 2).into_owned())
        }
    }
    let tied = Tied(prob);
    let mut s = LmState::new(&tied, vec![th[0], th[1]]);
    while !s.converged && s.iteration < 100 {
        s = lm_step(&tied, &s);
    }
    let (r0, j) = tied.residual_jacobian(&s.theta);
    let step: f64 = 1e-3;
    let (r1, _) = prob.residual_jacobian(&[s.theta[0], s.theta[1], step.sqrt(), 0.0]);
    let jd = (r1 - &r0) / step;
    // Project out the gain and delay columns.
    let jd_perp = match (j.transpose() * &j).cholesky() {
        Some(c) => &jd - &j * c.solve(&(j.transpose() * &jd)),
        None => jd,
    };
    (r0.norm_squared(), sigma / jd_perp.norm().max(1e-300))
}

/// Calibrate the chain from a record of voltage `u` and current `i` (channel units: V and A,
/// or anything proportional for a loopback) at `fs` through a resistor of `resistor` ohm
/// (1 for a loopback). `origin` names the record in errors.
pub fn calibrate(u: &[f64], i: &[f64], fs: f64, resistor: f64, origin: &str) -> Result<Calibration, String> {
    if !(resistor.is_finite() && resistor > 0.0) {
        return Err(format!("resistor {resistor} ohm: give its measured value (> 0), or a loopback"));
    }
    if u.len() != i.len() {
        return Err(format!("{origin}: the channels differ in length ({} and {})", u.len(), i.len()));
    }
    let seconds = u.len() as f64 / fs;
    if seconds < 20.0 {
        return Err(format!("{origin}: {seconds:.1} s is too short for a calibration: record 40 s or more (the coupling corners need 0.1 Hz resolution and several averages)"));
    }
    let seg = segment(u.len(), fs);
    let h1: ImpedanceEstimate = h1_impedance(u, i, fs, seg);
    let averages = (2 * u.len() / seg).saturating_sub(1).max(1) as f64;
    let df = fs / seg as f64;
    let f_hi = 0.45 * fs;
    let keep: Vec<usize> = (1..h1.f.len())
        .filter(|&k| h1.f[k] >= 2.0 * df && h1.f[k] <= f_hi && h1.usable(k, MIN_COHERENCE) && !near_hum(h1.f[k]))
        .collect();
    if keep.len() < 100 {
        return Err(format!("{origin}: only {} coherent, excited bins; play broadband noise (0.3 Hz .. 20 kHz) at a level well above the noise", keep.len()));
    }
    let z: Vec<Complex64> = keep.iter().map(|&k| h1.z[k]).collect();
    let f: Vec<f64> = keep.iter().map(|&k| h1.f[k]).collect();
    let w: Vec<f64> = keep
        .iter()
        .map(|&k| {
            let c = h1.coherence[k].min(1.0 - 1e-12);
            1.0 / ((1.0 - c) / (2.0 * averages * c)).sqrt().max(1e-7)
        })
        .collect();
    let zmed = crate::checks::median(z.iter().map(|z| z.norm()).collect());
    let low_re = crate::checks::median(
        keep.iter().filter(|&&k| h1.f[k] > 20.0 && h1.f[k] < 2000.0).map(|&k| h1.z[k].re).collect(),
    );
    if low_re < 0.0 {
        return Err(format!("{origin}: U/I is negative ({low_re:.3} ohm median, 20 Hz .. 2 kHz): one channel is inverted, the current or the voltage (U/I alone cannot tell which); swap the leads of the one wired backwards (the sense resistor's on channel 2, the voltage probe's on channel 1) or negate its scale"));
    }
    // Start: the level from the mid band, the delay from the phase's slope above 1 kHz
    // (unwrapped), both corners near 1 Hz (apart, so neither is favoured).
    let mid: Vec<usize> = (0..f.len()).filter(|&k| f[k] > 100.0 && f[k] < 2000.0).collect();
    let a0 = crate::checks::median(mid.iter().map(|&k| z[k].norm()).collect()).max(1e-12).ln();
    let hi: Vec<usize> = (0..f.len()).filter(|&k| f[k] > 1000.0).collect();
    let mut tau0 = 0.0;
    if hi.len() > 10 {
        let (mut prev, mut off) = (z[hi[0]].arg(), 0.0);
        let (mut sff, mut sfp) = (0.0, 0.0);
        for &k in &hi {
            let mut ph = z[k].arg();
            if ph + off - prev > PI {
                off -= 2.0 * PI;
            } else if ph + off - prev < -PI {
                off += 2.0 * PI;
            }
            ph += off;
            prev = ph;
            sff += f[k] * f[k];
            sfp += f[k] * ph;
        }
        tau0 = sfp / sff * fs / (2.0 * PI);
    }
    let prob = ResistorProblem::new(f, z, w, fs);
    let mut s = LmState::new(&prob, vec![a0, tau0, 1.0, 1.2]);
    while !s.converged && s.iteration < 200 {
        s = lm_step(&prob, &s);
    }
    if !s.converged {
        return Err(format!("{origin}: the calibration fit did not converge in {} iterations", s.iteration));
    }
    let th = s.theta.clone();
    let (r, j) = prob.residual_jacobian(&th);
    let m = prob.f.len();
    let residual_in_noise = (r.norm_squared() / (2 * m) as f64).sqrt();
    let (cu, ci) = (Corner::new(th[2], fs), Corner::new(th[3], fs));
    let residual_rel =
        ((0..m).map(|k| ((prob.z[k] - prob.model(&th, &cu, &ci, k).0) / prob.z[k].norm()).norm_sqr()).sum::<f64>()
            / m as f64)
            .sqrt();
    if residual_in_noise > MAX_RESIDUAL_IN_NOISE {
        return Err(format!(
            "{origin}: this does not look like a resistor through a first-order chain: the fit misses by {residual_in_noise:.1}x the noise (|U/I| median {zmed:.3}, {:.2} % RMS). A driver or a reactive load on the channels, a second-order coupling, or a gain that drifts",
            100.0 * residual_rel
        ));
    }
    let cov = sandwich_covariance(&j, &r, 32).ok_or_else(|| {
        format!("{origin}: the calibration is not identifiable (singular Jacobian): excite below the coupling corners")
    })?;
    let sd = |c: usize| crate::lm::sd_from_variance(cov[(c, c)]);
    let (hp_u, hp_i) = (th[2] * th[2], th[3] * th[3]);
    let gain = resistor * (-th[0]).exp();
    // A resistor shows only H_u / H_i: a zero at hp_i over a pole at hp_u. Equal corners
    // cancel, and then any common value fits: the two are resolved only when the fit with
    // them equal (both 0: no coupling) misses the data by more than a 3 sd difference would
    // explain. A likelihood-ratio test, not the difference's sd from the covariance: along
    // the common corner (not identifiable) that covariance is singular, and its round-off
    // once reported a difference of 2e-6 Hz as resolved (sd 0, with a faster-falling LM damping
    // tried).
    let sigma2 = r.norm_squared() / (2 * m).saturating_sub(4).max(1) as f64;
    let (tied, diff_sd) = tied_corners(&prob, &th, sigma2.sqrt());
    let resolved = tied - r.norm_squared() > 9.0 * sigma2;
    let mut chain =
        Chain { source: Some("calibrated".into()), delay_i: th[1] / fs, gain_i: Some(gain), ..Default::default() };
    chain.sd.insert("delay_i".into(), sd(1) / fs);
    chain.sd.insert("gain_i".into(), gain * sd(0));
    chain.fitted = vec!["delay_i".into(), "gain_i".into()];
    if resolved {
        (chain.hp_u, chain.hp_i) = (hp_u, hp_i);
        chain.sd.insert("hp_u".into(), 2.0 * th[2].abs() * sd(2));
        chain.sd.insert("hp_i".into(), 2.0 * th[3].abs() * sd(3));
        chain.fitted.extend(["hp_u".into(), "hp_i".into()]);
    } else {
        chain.other.insert(
            "note".into(),
            serde_json::Value::String(format!(
                "the channels' AC-coupling corners are equal to within {:.3} Hz (3 sd): a resistor record measures only their difference, so the common corner is unknown and both are written as 0 (the same impedance); `identify --chain auto` estimates it from a driver record",
                3.0 * diff_sd
            )),
        );
    }
    let band = [prob.f[0], prob.f[m - 1]];
    Ok(Calibration { chain, resistor, band, bins: m, residual_in_noise, residual_rel })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The resistor model's derivatives (the corners' analytic, [`Corner`]) against central
    /// differences of the model, and its `H` against
    /// [`coilscope_core::chain::hp_response`], at corners from DC-coupled (0.05 Hz) to 8 Hz
    /// and bins from 0.2 Hz to 20 kHz, at 44.1 and 96 kHz: to 1e-6 of each column's largest
    /// entry (what the differences' own error allows).
    #[test]
    fn the_resistor_models_jacobian_is_its_finite_differences() {
        for fs in [44100.0, 96000.0] {
            let f: Vec<f64> = (0..400).map(|k| 0.2 * 1.025f64.powi(k)).filter(|&f| f < 0.45 * fs).collect();
            let n = f.len();
            let prob = ResistorProblem::new(f.clone(), vec![Complex64::new(4.0, 0.1); n], vec![1.0; n], fs);
            for th in [[1.3, 0.4, 0.05f64.sqrt(), 8.0f64.sqrt()], [1.3, -2.5, 2.0, 0.7], [0.2, 0.0, 1.1, 1.1]] {
                for (corner, s) in [(Corner::new(th[2], fs), th[2]), (Corner::new(th[3], fs), th[3])] {
                    for k in (0..n).step_by(37) {
                        let (h, _) = corner.at(prob.zi[k]);
                        let want = coilscope_core::chain::hp_response(s * s, f[k], fs);
                        assert!((h - want).norm() < 1e-13, "H {h} vs hp_response's {want} at {} Hz", f[k]);
                    }
                }
                // The model's derivatives (the residual's Jacobian is them times the bin's
                // fixed weight).
                let (cu, ci) = (Corner::new(th[2], fs), Corner::new(th[3], fs));
                let at = |t: &[f64; 4], k: usize| prob.model(t, &Corner::new(t[2], fs), &Corner::new(t[3], fs), k).0;
                for c in 0..4 {
                    let h = 1e-4;
                    let (mut tp, mut tm) = (th, th);
                    tp[c] += h;
                    tm[c] -= h;
                    let (mut err, mut scale) = (0.0f64, 0.0f64);
                    for k in 0..n {
                        let d = prob.model(&th, &cu, &ci, k).1[c];
                        let fd = (at(&tp, k) - at(&tm, k)) / (2.0 * h);
                        err = err.max((d - fd).norm());
                        scale = scale.max(d.norm());
                    }
                    assert!(
                        scale > 0.0 && err < 1e-6 * scale,
                        "fs {fs}, theta {th:?}, column {c}: {err:e} of {scale:e}"
                    );
                }
            }
        }
    }
}

//! Volterra-based identification (seed paper 3.2.2.1, Fig. 3): the distortion a transducer
//! produces is read as its second- and third-order Volterra kernels, and the nonlinear
//! parameters are fitted to those kernels.
//!
//! The measurement: sines at several frequencies, each in its steady state; of the current
//! (what the terminals give), the complex ratios of the 2nd and 3rd harmonic to the
//! fundamental. The model: the diagonal kernels of the model by harmonic probing
//! ([`coilscope_analysis::volterra::probe`]), `H2(f,f) a / H1(f)` and `H3(f,f,f) a^2 / H1(f)`
//! for a cosine of complex amplitude `a`. The kernels to the third order depend on the power
//! series only up to `x^2`: the fit gives `Bl`, `Kms`, `Le` to second order (`b1, b2, k1,
//! k2, l1, l2`), with the linear parameters (the rest values, Re, Mms, Rms, L2/R2) from the
//! small-signal fit.
//!
//! It is exact where the Volterra series is: at small amplitude. The paper's point is where
//! it fails: at large amplitude the distortion the nonlinearities produce feeds back into
//! their own generation (Bl(x) and Kms(x) change by tens of percent, the displacement's
//! harmonics move x, which moves Bl and Kms again), the series truncated after the third
//! order no longer describes the response, and the fitted coefficients absorb what the
//! truncation leaves out. `issue18_volterra.rs` tabulates the error over level.

use crate::lm::{lm_step, LmState, Problem};
use coilscope_analysis::distortion::{Harmonics, Output};
use coilscope_analysis::volterra::probe;
use coilscope_core::{Parameters, Poly};
use nalgebra::{DMatrix, DVector};

/// The fitted second-order series and what the fit left.
#[derive(Clone, Debug)]
pub struct VolterraFit {
    /// `start` with Bl, Kms, Le replaced by the fitted second-order series.
    pub params: Parameters,
    /// RMS of the fitted ratios less the measured, relative to the RMS of the measured.
    pub misfit: f64,
}

struct Kernels<'a> {
    start: &'a Parameters,
    measured: &'a [Harmonics],
    /// Displacement scale (m) of the unknowns: theta = c_j x_s^j / c_0.
    xs: f64,
    /// Residual weights per tone: 1 / (|ratio2| + |ratio3|) of the measurement.
    weight: Vec<f64>,
}

impl Kernels<'_> {
    fn params(&self, th: &[f64]) -> Parameters {
        let s = self.start;
        let series = |c0: f64, a: f64, b: f64| Poly { c: vec![c0, c0 * a / self.xs, c0 * b / (self.xs * self.xs)] };
        Parameters { bl: series(s.bl.c[0], th[0], th[1]), kms: series(s.kms.c[0], th[2], th[3]), le: series(s.le.c[0], th[4], th[5]), ..s.clone() }
    }
}

impl Problem for Kernels<'_> {
    fn residual(&self, th: &[f64]) -> DVector<f64> {
        let q = self.params(th);
        let mut r = Vec::with_capacity(4 * self.measured.len());
        for (h, w) in self.measured.iter().zip(&self.weight) {
            let (r2, r3) = probe(&q, h.freq).ratios(Output::Current, h.volts);
            for d in [r2 - h.ratio(2), r3 - h.ratio(3)] {
                r.push(d.re * w);
                r.push(d.im * w);
            }
        }
        DVector::from_vec(r)
    }

    fn residual_jacobian(&self, th: &[f64]) -> (DVector<f64>, DMatrix<f64>) {
        let r = self.residual(th);
        let mut j = DMatrix::zeros(r.len(), th.len());
        for c in 0..th.len() {
            let h = 1e-6 * th[c].abs().max(1e-3);
            let mut tp = th.to_vec();
            tp[c] += h;
            let rp = self.residual(&tp);
            j.column_mut(c).copy_from(&((rp - &r) / h));
        }
        (r, j)
    }
}

/// A multitone whose diagonal lines can be read: `count` tone bins between `lo` and `hi`
/// (bins of the period), about log-spaced, chosen so that no product of order 2 or 3 of the
/// other tones (`+-f_a +- f_b`, `+-f_a +- f_b +- f_c`) lands on any tone's 2nd or 3rd
/// harmonic bin, or on a fundamental: there the lines are `H2(f,f) a^2` and `H3(f,f,f) a^3`
/// alone (to third order), as for a sine.
pub fn readable_multitone(lo: usize, hi: usize, count: usize) -> Vec<usize> {
    let ok = |set: &[usize]| {
        let f: Vec<i64> = set.iter().map(|&v| v as i64).collect();
        let n = f.len();
        let fundamental = |v: i64| f.contains(&v);
        let harmonic = |v: i64| f.iter().any(|&k| v == 2 * k || v == 3 * k);
        // Order 2: f_a + f_b and |f_a - f_b|; 2 f_a belongs on its own bin.
        for a in 0..n {
            for b in a..n {
                let sum = f[a] + f[b];
                if (a != b && (harmonic(sum) || fundamental(sum))) || (a == b && (fundamental(sum) || f.iter().any(|&k| sum == 3 * k))) {
                    return false;
                }
                let diff = (f[a] - f[b]).abs();
                if a != b && (harmonic(diff) || fundamental(diff)) {
                    return false;
                }
            }
        }
        // Order 3: +-f_a +- f_b +- f_c; 3 f_a belongs on its own bin, and products on a
        // fundamental (f_k + f_a - f_a) are not read as kernel lines.
        for a in 0..n {
            for b in a..n {
                for c in b..n {
                    for (sb, sc) in [(1i64, 1i64), (1, -1), (-1, 1), (-1, -1)] {
                        let v = (f[a] + sb * f[b] + sc * f[c]).abs();
                        if a == b && b == c && sb == 1 && sc == 1 {
                            continue;
                        }
                        if harmonic(v) {
                            return false;
                        }
                    }
                }
            }
        }
        // Order 4: f_a +- f_b +- f_c +- f_d on a 2nd or 3rd harmonic (their lines are a
        // level weaker than the third order's, but many, and Le's lines are the weakest).
        for a in 0..n {
            for b in 0..n {
                for c in 0..n {
                    for d in 0..n {
                        for (sb, sc, sd) in [(1i64, 1i64, 1i64), (1, 1, -1), (1, -1, -1), (-1, -1, -1)] {
                            let v = (f[a] + sb * f[b] + sc * f[c] + sd * f[d]).abs();
                            if !harmonic(v) {
                                continue;
                            }
                            // A tone's own harmonic through a pair that cancels (f_k + f_k +
                            // f_a - f_a) is in a sine's line too: allowed.
                            let mut net = vec![0i64; n];
                            for (i, sg) in [(a, 1i64), (b, sb), (c, sc), (d, sd)] {
                                net[i] += sg;
                            }
                            let own = net.iter().filter(|&&m| m != 0).count() == 1 && net.iter().any(|&m| m.abs() >= 2);
                            if !own {
                                return false;
                            }
                        }
                    }
                }
            }
        }
        true
    };
    let mut set: Vec<usize> = vec![];
    let ratio = (hi as f64 / lo as f64).powf(1.0 / count.max(2).saturating_sub(1) as f64);
    for k in 0..count {
        let want = (lo as f64 * ratio.powi(k as i32)).round() as usize;
        // The nearest candidate (above, then below) that keeps the set readable.
        for d in 0..want.max(1) {
            let mut found = false;
            for c in [want + d, want.saturating_sub(d)] {
                if c < lo || c > hi || set.contains(&c) {
                    continue;
                }
                let mut trial = set.clone();
                trial.push(c);
                if ok(&trial) {
                    set = trial;
                    found = true;
                    break;
                }
            }
            if found {
                break;
            }
        }
    }
    set.sort();
    set
}

/// The current's 2nd and 3rd harmonic ratios of each tone of a [`readable_multitone`] in a
/// steady-state response, as [`Harmonics`] for [`identify_volterra`]: the line at `2 f_k`
/// and `3 f_k` over the fundamental, each rotated back by the tone's phase (`a_k = A e^{j
/// phi}` turns `H2 a^2 / (H1 a)` by `phi` and `H3 a^3 / (H1 a)` by `2 phi`).
pub fn multitone_harmonics(r: &coilscope_analysis::distortion::Response, tones: &[coilscope_analysis::distortion::Tone]) -> Vec<Harmonics> {
    use realfft::num_complex::Complex64 as C;
    tones
        .iter()
        .map(|t| {
            let f1 = r.line(Output::Current, t.bin);
            let rot = |k: i32| C::from_polar(1.0, -(k as f64) * t.phase);
            let lines = vec![(2usize, r.line(Output::Current, 2 * t.bin) / f1 * rot(1)), (3usize, r.line(Output::Current, 3 * t.bin) / f1 * rot(2))];
            Harmonics { freq: r.freq(t.bin), volts: t.amplitude / std::f64::consts::SQRT_2, output: Output::Current, fundamental: f1, lines, x_dc: r.x_dc(), x_peak: r.x_peak }
        })
        .collect()
}

/// Fit Bl, Kms, Le to second order to the measured current harmonics `measured` (sines of
/// [`coilscope_analysis::distortion::harmonics`] with `Output::Current`, at least two
/// frequencies), the linear parameters and the start of the series from `start`.
pub fn identify_volterra(start: &Parameters, measured: &[Harmonics]) -> Result<VolterraFit, String> {
    if measured.len() < 2 {
        return Err(format!("{} tone(s): the Volterra fit needs the harmonics of at least two frequencies", measured.len()));
    }
    if let Some(h) = measured.iter().find(|h| h.output != Output::Current) {
        return Err(format!("the tone at {} Hz gives {:?}; the Volterra fit reads the current's harmonics", h.freq, h.output));
    }
    let xs = start.x_range.map_or(1e-3, |[lo, hi]| 0.5 * hi.min(-lo));
    let weight = measured.iter().map(|h| 1.0 / (h.hd(2) + h.hd(3)).max(1e-12)).collect();
    let prob = Kernels { start, measured, xs, weight };
    let c = |f: &Poly, j: usize| f.c.get(j).copied().unwrap_or(0.0) * xs.powi(j as i32) / f.c[0];
    let th0 = vec![c(&start.bl, 1), c(&start.bl, 2), c(&start.kms, 1), c(&start.kms, 2), c(&start.le, 1), c(&start.le, 2)];
    let mut s = LmState::new(&prob, th0);
    for _ in 0..200 {
        s = lm_step(&prob, &s);
        if s.converged || s.last_decrease < 1e-14 {
            break;
        }
    }
    let r = prob.residual(&s.theta);
    Ok(VolterraFit { params: prob.params(&s.theta), misfit: (r.norm_squared() / (r.len() as f64 / 2.0)).sqrt() / 2f64.sqrt() })
}

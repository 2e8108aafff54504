//! The band-limited interpolation of the sampled drive ([`Interpolator`]): a Kaiser-windowed
//! sinc, exact at the sample instants.

use super::*;

pub(super) fn bessel_i0(x: f64) -> f64 {
    let mut sum = 1.0;
    let mut term = 1.0;
    let q = x * x / 4.0;
    for k in 1..200 {
        term *= q / (k as f64 * k as f64);
        sum += term;
        if term < 1e-17 * sum {
            break;
        }
    }
    sum
}

/// The band-limited interpolation kernel at offset `t` (in samples).
pub fn kernel(t: f64) -> f64 {
    let half = HALF_TAPS as f64;
    if t.abs() >= half {
        return 0.0;
    }
    let sinc = if t == 0.0 { 1.0 } else { (std::f64::consts::PI * t).sin() / (std::f64::consts::PI * t) };
    let r = t / half;
    sinc * bessel_i0(KAISER_BETA * (1.0 - r * r).sqrt()) / bessel_i0(KAISER_BETA)
}

/// Dot product with independent partial sums (vectorisable: no chain of dependent adds).
/// Not inlined: inlined into [`Interpolator::fill`]'s loop, it was vectorised across the
/// rows of weights with a shuffle per tap (26 ns a sample of three points; out of line, 20).
#[inline(never)]
pub(super) fn dot(a: &[f64; 2 * HALF_TAPS], b: &[f64; 2 * HALF_TAPS]) -> f64 {
    let mut acc = [0.0; 8];
    for (ca, cb) in a.chunks_exact(8).zip(b.chunks_exact(8)) {
        for k in 0..8 {
            acc[k] += ca[k] * cb[k];
        }
    }
    acc.iter().sum()
}

/// Band-limited values of a sampled signal at `2 n` equally spaced points per sample period.
#[derive(Clone, Debug)]
pub struct Interpolator {
    /// Sub-steps per sample (the points are at multiples of `1 / (2 n)` sample).
    pub n: usize,
    /// `weights[j - 1][k]`: weight of sample `m + k + 1 - HALF_TAPS` for the point
    /// `m + j / (2 n)`, `j = 1 .. 2 n - 1`.
    pub(super) weights: Vec<[f64; 2 * HALF_TAPS]>,
}

impl Interpolator {
    pub fn new(n: usize) -> Self {
        let m = 2 * n;
        let weights = (1..m)
            .map(|j| {
                let tau = j as f64 / m as f64;
                let mut w = [0.0; 2 * HALF_TAPS];
                for (k, wk) in w.iter_mut().enumerate() {
                    let offset = k as f64 + 1.0 - HALF_TAPS as f64; // sample index relative to m
                    *wk = kernel(tau - offset);
                }
                // Exact for DC.
                let s: f64 = w.iter().sum();
                w.iter_mut().for_each(|x| *x /= s);
                w
            })
            .collect();
        Interpolator { n, weights }
    }

    /// Fill `out` (length `2 n + 1`) with the signal at `m + j / (2 n)`, `j = 0 ..= 2 n`.
    /// Samples outside `u` count as zero (the signal is silent before and after).
    pub fn fill(&self, u: &[f64], m: usize, out: &mut [f64]) {
        debug_assert_eq!(out.len(), 2 * self.n + 1);
        let at = |k: isize| if k >= 0 && (k as usize) < u.len() { u[k as usize] } else { 0.0 };
        out[0] = at(m as isize);
        out[2 * self.n] = at(m as isize + 1);
        let start = m as isize + 1 - HALF_TAPS as isize;
        // Inside the record the window is borrowed, not copied; at its ends it is built with
        // zeros.
        let edge: [f64; 2 * HALF_TAPS];
        let win: &[f64; 2 * HALF_TAPS] = match usize::try_from(start).ok().and_then(|s| u.get(s..s + 2 * HALF_TAPS)) {
            Some(w) => w.try_into().expect("window length"),
            None => {
                edge = std::array::from_fn(|k| at(start + k as isize));
                &edge
            }
        };
        for (o, w) in out[1..].iter_mut().zip(&self.weights) {
            *o = dot(w, win);
        }
    }
}

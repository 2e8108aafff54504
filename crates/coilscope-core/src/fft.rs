//! Whole-record real FFTs (realfft), unnormalised as realfft is: `irfft(rfft(x)) = n x`.
//!
//! The planner is kept per thread: a length planned once is not planned again (the chain's
//! delay runs an FFT pair of the record's length at every residual of a fit).

use realfft::num_complex::Complex64;
use realfft::RealFftPlanner;
use std::cell::RefCell;

thread_local! {
    static PLANNER: RefCell<RealFftPlanner<f64>> = RefCell::new(RealFftPlanner::new());
}

/// Spectrum of a real signal: `n / 2 + 1` bins, bin k at `k fs / n`.
pub fn rfft(x: &[f64]) -> Vec<Complex64> {
    let fft = PLANNER.with(|p| p.borrow_mut().plan_fft_forward(x.len()));
    let mut buf = x.to_vec();
    let mut out = fft.make_output_vec();
    fft.process(&mut buf, &mut out).expect("lengths are consistent");
    out
}

/// Real signal of `n` samples from its `n / 2 + 1` bins (the imaginary parts of DC and, for
/// even n, Nyquist are ignored). Not normalised: divide by n to invert [`rfft`].
pub fn irfft(spec: &[Complex64], n: usize) -> Vec<f64> {
    irfft_owned(spec.to_vec(), n)
}

/// [`irfft`] of a spectrum the caller gives up: the transform works in it (realfft's inverse
/// overwrites its input), so it is not copied first. The same values to the last bit.
pub fn irfft_owned(mut s: Vec<Complex64>, n: usize) -> Vec<f64> {
    let c2r = PLANNER.with(|p| p.borrow_mut().plan_fft_inverse(n));
    s[0].im = 0.0;
    if n.is_multiple_of(2) {
        let last = s.len() - 1;
        s[last].im = 0.0;
    }
    let mut out = vec![0.0; n];
    c2r.process(&mut s, &mut out).expect("lengths are consistent");
    out
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_planned_length_gives_the_same_spectrum_again() {
        // The cached plan against a fresh planner's, and across lengths in between.
        let x: Vec<f64> = (0..3000).map(|k| (k as f64 * 0.013).sin() + 0.1 * (k as f64 * 1.7).cos()).collect();
        let fresh = {
            let mut p = realfft::RealFftPlanner::<f64>::new();
            let f = p.plan_fft_forward(x.len());
            let (mut buf, mut out) = (x.clone(), f.make_output_vec());
            f.process(&mut buf, &mut out).unwrap();
            out
        };
        let a = super::rfft(&x);
        let _ = super::rfft(&x[..1000]);
        let b = super::rfft(&x);
        assert_eq!(a, fresh);
        assert_eq!(b, fresh);
    }

    #[test]
    fn round_trip_scales_by_n() {
        let x: Vec<f64> = (0..10).map(|k| (k as f64 * 0.7).sin()).collect();
        let y = super::irfft(&super::rfft(&x), 10);
        for (a, b) in x.iter().zip(&y) {
            assert!((a * 10.0 - b).abs() < 1e-12);
        }
    }
}

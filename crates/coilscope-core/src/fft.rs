//! Whole-record real FFTs (realfft), unnormalised as realfft is: `irfft(rfft(x)) = n x`.

use realfft::num_complex::Complex64;
use realfft::RealFftPlanner;

/// Spectrum of a real signal: `n / 2 + 1` bins, bin k at `k fs / n`.
pub fn rfft(x: &[f64]) -> Vec<Complex64> {
    let mut planner = RealFftPlanner::<f64>::new();
    let fft = planner.plan_fft_forward(x.len());
    let mut buf = x.to_vec();
    let mut out = fft.make_output_vec();
    fft.process(&mut buf, &mut out).expect("lengths are consistent");
    out
}

/// Real signal of `n` samples from its `n / 2 + 1` bins (the imaginary parts of DC and, for
/// even n, Nyquist are ignored). Not normalised: divide by n to invert [`rfft`].
pub fn irfft(spec: &[Complex64], n: usize) -> Vec<f64> {
    let mut planner = RealFftPlanner::<f64>::new();
    let c2r = planner.plan_fft_inverse(n);
    let mut s = spec.to_vec();
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
    fn round_trip_scales_by_n() {
        let x: Vec<f64> = (0..10).map(|k| (k as f64 * 0.7).sin()).collect();
        let y = super::irfft(&super::rfft(&x), 10);
        for (a, b) in x.iter().zip(&y) {
            assert!((a * 10.0 - b).abs() < 1e-12);
        }
    }
}

//! Excitation sources for the measurement: unit-rms signals delivered block by block, and the
//! variable high-pass the controller uses to keep the excursion in range.

use coilscope_core::excitation::{generate, Excitation, SignalSpec};
use std::f64::consts::PI;

/// A looping unit-rms signal.
pub struct Source {
    name: String,
    /// Whether it excites every band all the time (noise), unlike music.
    persistent: bool,
    x: Vec<f64>,
    pos: usize,
}

impl Source {
    /// Noise of `exc` (IEC 60268-1 programme simulation, pink, ...): an 8 s period, looped.
    pub fn noise(exc: &Excitation, fs: f64, seed: u64) -> Result<Self, String> {
        let x = generate(exc, &SignalSpec { fs, seconds: 8.0, rms: 1.0, fade: 0.0, seed })?;
        Ok(Source { name: format!("{exc:?}"), persistent: true, x, pos: 0 })
    }

    /// Music or any audio file: the first channel, scaled to unit rms, looped. Its sample
    /// rate must be the measurement's.
    pub fn music(path: &std::path::Path, fs: f64) -> Result<Self, String> {
        let mut reader = hound_reader(path)?;
        let spec = reader.spec();
        if spec.sample_rate as f64 != fs {
            return Err(format!(
                "{}: sample rate {} Hz; the measurement runs at {fs} Hz (resample the file, or pass --rate {})",
                path.display(),
                spec.sample_rate,
                spec.sample_rate
            ));
        }
        let ch = spec.channels as usize;
        let samples: Vec<f64> = match spec.sample_format {
            hound::SampleFormat::Float => {
                reader.samples::<f32>().step_by(ch).map(|s| s.map(|v| v as f64)).collect::<Result<_, _>>()
            }
            hound::SampleFormat::Int => {
                let full = (1u64 << (spec.bits_per_sample - 1)) as f64;
                reader.samples::<i32>().step_by(ch).map(|s| s.map(|v| v as f64 / full)).collect::<Result<_, _>>()
            }
        }
        .map_err(|e| format!("{}: cannot read the samples: {e}", path.display()))?;
        let rms = coilscope_core::simulate::rms(&samples);
        if !(samples.len() as f64 >= fs && rms > 1e-6) {
            return Err(format!(
                "{}: the music file must hold at least 1 s of sound ({} samples, rms {rms:.2e})",
                path.display(),
                samples.len()
            ));
        }
        Ok(Source {
            name: path.display().to_string(),
            persistent: false,
            x: samples.iter().map(|v| v / rms).collect(),
            pos: 0,
        })
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    /// Whether the signal excites every band all the time (generated noise), so that the
    /// small-signal impedance fit can rely on it. Music need not.
    pub fn persistent(&self) -> bool {
        self.persistent
    }

    /// The next `n` samples.
    pub fn next_block(&mut self, n: usize) -> Vec<f64> {
        (0..n)
            .map(|_| {
                let v = self.x[self.pos];
                self.pos = (self.pos + 1) % self.x.len();
                v
            })
            .collect()
    }
}

fn hound_reader(path: &std::path::Path) -> Result<hound::WavReader<std::io::BufReader<std::fs::File>>, String> {
    hound::WavReader::open(path).map_err(|e| format!("{}: cannot open as WAV: {e}", path.display()))
}

/// Second-order Butterworth high-pass whose cut-off may change between blocks (the state is
/// kept, so a change makes no click).
pub struct HighPass {
    fs: f64,
    pub fc: f64,
    b: [f64; 3],
    a: [f64; 2],
    z: [f64; 2],
}

impl HighPass {
    pub fn new(fs: f64, fc: f64) -> Self {
        let mut h = HighPass { fs, fc, b: [1.0, 0.0, 0.0], a: [0.0, 0.0], z: [0.0; 2] };
        h.set(fc);
        h
    }

    /// Set the cut-off (Hz); 0 passes everything.
    pub fn set(&mut self, fc: f64) {
        self.fc = fc;
        if fc <= 0.0 {
            self.b = [1.0, 0.0, 0.0];
            self.a = [0.0, 0.0];
            return;
        }
        // Bilinear transform (RBJ cookbook), Q = 1/sqrt(2).
        let w = 2.0 * PI * fc / self.fs;
        let alpha = w.sin() / (2.0 * std::f64::consts::FRAC_1_SQRT_2);
        let c = w.cos();
        let a0 = 1.0 + alpha;
        self.b = [(1.0 + c) / 2.0 / a0, -(1.0 + c) / a0, (1.0 + c) / 2.0 / a0];
        self.a = [-2.0 * c / a0, (1.0 - alpha) / a0];
    }

    pub fn process(&mut self, x: &mut [f64]) {
        for v in x.iter_mut() {
            // Transposed direct form II.
            let y = self.b[0] * *v + self.z[0];
            self.z[0] = self.b[1] * *v - self.a[0] * y + self.z[1];
            self.z[1] = self.b[2] * *v - self.a[1] * y;
            *v = y;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn high_pass_has_the_butterworth_response() {
        // |H| at fc is -3 dB, at fc/10 -40 dB, at 10 fc 0 dB: measured with sines.
        let fs = 48000.0;
        for (f, want_db) in [(100.0, -3.01), (10.0, -40.0), (1000.0, 0.0)] {
            let mut h = HighPass::new(fs, 100.0);
            let mut x: Vec<f64> = (0..(fs as usize)).map(|k| (2.0 * PI * f * k as f64 / fs).sin()).collect();
            h.process(&mut x);
            let tail = &x[x.len() / 2..];
            let amp = tail.iter().fold(0.0f64, |a, v| a.max(v.abs()));
            let db = 20.0 * amp.log10();
            assert!((db - want_db).abs() < 0.1, "{f} Hz: {db} dB, want {want_db}");
        }
    }
}

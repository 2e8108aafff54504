//! Devices under test: what turns a drive voltage block into measured voltage and current.
//!
//! * [`VirtualDevice`]: the core simulator driven by any parameter set, thermal model on,
//!   with Gaussian sensor noise on both channels (named, seeded RNGs). The default: it needs
//!   no hardware. It also keeps the truth (true x and voice-coil temperature) for tests.
//! * [`ReplayDevice`]: a recorded WAV played back block by block; the drive is ignored (the
//!   level was set when it was recorded).
//!
//! A device may delay its channels (a sound card does; the virtual device delays by the
//! interpolator's look-ahead): the blocks it returns are aligned with each other, not with
//! the drive.

use coilscope_core::excitation::named_rng;
use coilscope_core::integrate::{Stepper, HALF_TAPS};
use coilscope_core::model::{idx, State, NSTATE};
use coilscope_core::params::Parameters;
use coilscope_core::simulate::Plant;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

/// How far past its `x_range` the virtual driver survives (fraction of the half-width).
pub const BREAK_MARGIN: f64 = 0.10;

/// A measured block: voltage (V) and current (A) at the terminals.
#[derive(Clone, Debug, Default)]
pub struct Block {
    pub u: Vec<f64>,
    pub i: Vec<f64>,
}

/// What the measurement system talks to.
pub trait Device {
    /// Sample rate (Hz).
    fn fs(&self) -> f64;
    /// Play `drive` (V) and return the measured block (same length), or `Ok(None)` when the
    /// device has nothing more (end of a replayed file).
    fn play(&mut self, drive: &[f64]) -> Result<Option<Block>, String>;
    /// The true state, when the device knows it (virtual device): for tests.
    fn truth(&self) -> Option<Truth> {
        None
    }
    /// Whether the drive reaches the transducer (false for a replay).
    fn controllable(&self) -> bool {
        true
    }
    /// A name for messages and the database.
    fn describe(&self) -> String;
}

/// A boxed device is a device (so that adapters such as [`crate::card::Corrected`] take one).
impl<T: Device + ?Sized> Device for Box<T> {
    fn fs(&self) -> f64 {
        (**self).fs()
    }
    fn play(&mut self, drive: &[f64]) -> Result<Option<Block>, String> {
        (**self).play(drive)
    }
    fn truth(&self) -> Option<Truth> {
        (**self).truth()
    }
    fn controllable(&self) -> bool {
        (**self).controllable()
    }
    fn describe(&self) -> String {
        (**self).describe()
    }
}

/// Extremes of the true state so far.
#[derive(Clone, Copy, Debug, Default)]
pub struct Truth {
    /// Largest |x| (m).
    pub x_peak: f64,
    /// Smallest and largest x (m): the range the driver truly reached.
    pub x_min: f64,
    pub x_max: f64,
    /// Largest voice-coil temperature rise (K).
    pub dtv_max: f64,
    /// The present voice-coil temperature rise (K).
    pub dtv: f64,
}

/// The virtual transducer.
pub struct VirtualDevice {
    params: Parameters,
    plant: Plant,
    fs: f64,
    stepper: Stepper,
    state: State<f64>,
    /// Drive history with look-ahead: `hist[0]` is absolute sample `base`.
    hist: Vec<f64>,
    base: usize,
    /// Next sample to integrate (absolute).
    pos: usize,
    noise: (f64, f64),
    rng_u: ChaCha8Rng,
    rng_i: ChaCha8Rng,
    truth: Truth,
    /// The driver's valid range (m); beyond it plus [`BREAK_MARGIN`] the driver is destroyed.
    x_range: Option<[f64; 2]>,
}

impl VirtualDevice {
    /// `noise`: rms sensor noise of the voltage (V) and current (A) channels.
    pub fn new(params: &Parameters, fs: f64, noise: (f64, f64), seed: u64) -> Result<Self, String> {
        if !(fs.is_finite() && (8000.0..=384000.0).contains(&fs)) {
            return Err(format!("sample rate {fs} Hz is not valid (8 kHz .. 384 kHz)"));
        }
        if !(noise.0 >= 0.0 && noise.1 >= 0.0) {
            return Err(format!("sensor noise ({} V, {} A) is not valid (>= 0)", noise.0, noise.1));
        }
        Ok(VirtualDevice {
            params: params.clone(),
            plant: Plant::new(params),
            fs,
            // RK4 as the online estimator that measures it (`Stepper::rk4_for`).
            stepper: Stepper::rk4_for(params.rates(), fs).0,
            state: [0.0; NSTATE],
            hist: Vec::new(),
            base: 0,
            pos: 0,
            noise,
            rng_u: named_rng(seed, "virtual-device/voltage-noise"),
            rng_i: named_rng(seed, "virtual-device/current-noise"),
            truth: Truth::default(),
            x_range: params.x_range,
        })
    }

    pub fn params(&self) -> &Parameters {
        &self.params
    }

    /// Hold a constant external force on the cone (N, + pushes the coil out) with a mass
    /// added to it (kg) from the next sample on: the quasi-static method's added mass under
    /// gravity or pressure on the diaphragm, applied by hand.
    pub fn set_push(&mut self, force: f64, added_mass: f64) {
        let p = Parameters { mms: self.params.mms + added_mass, ..self.params.clone() };
        self.plant.set_force(&p, force);
    }

    /// The true displacement now (m): what a dial gauge on the cone reads.
    pub fn x_now(&self) -> f64 {
        self.state[idx::X]
    }
}

impl Device for VirtualDevice {
    fn fs(&self) -> f64 {
        self.fs
    }

    fn play(&mut self, drive: &[f64]) -> Result<Option<Block>, String> {
        if let Some(k) = drive.iter().position(|v| !v.is_finite()) {
            return Err(format!("drive sample {k} is not finite"));
        }
        self.hist.extend_from_slice(drive);
        let dt = 1.0 / self.fs;
        let mut pf = vec![0.0; self.stepper.points()];
        let mut out = Block { u: Vec::with_capacity(drive.len()), i: Vec::with_capacity(drive.len()) };
        // The interpolator looks HALF_TAPS samples ahead: the device lags by that much.
        while out.u.len() < drive.len() {
            let k = self.pos as isize - self.base as isize;
            let (u, i) = if self.pos < HALF_TAPS {
                (0.0, 0.0)
            } else {
                let m = (k - HALF_TAPS as isize) as usize;
                let s = self.state;
                let x = s[idx::X];
                if let Some([lo, hi]) = self.x_range {
                    if !(x >= (1.0 + BREAK_MARGIN) * lo && x <= (1.0 + BREAK_MARGIN) * hi) {
                        return Err(format!(
                            "the virtual driver was destroyed: x = {:.3} mm at t = {:.3} s, beyond its valid range [{:.3}, {:.3}] mm + {:.0} % (the protection failed)",
                            x * 1e3,
                            (self.pos - HALF_TAPS) as f64 / self.fs,
                            lo * 1e3,
                            hi * 1e3,
                            100.0 * BREAK_MARGIN
                        ));
                    }
                }
                if let Some(why) = self.plant.invalid_at(&s) {
                    return Err(format!(
                        "the virtual driver left its model at t = {:.3} s: {why} (the protection failed)",
                        (self.pos - HALF_TAPS) as f64 / self.fs
                    ));
                }
                self.truth.x_peak = self.truth.x_peak.max(x.abs());
                self.truth.x_min = self.truth.x_min.min(x);
                self.truth.x_max = self.truth.x_max.max(x);
                self.truth.dtv = s[idx::TV];
                self.truth.dtv_max = self.truth.dtv_max.max(s[idx::TV]);
                let u = self.hist[m];
                self.stepper.fill(&self.hist, m, &mut pf);
                self.plant.step(&self.stepper, &mut self.state, dt, &pf);
                (u, s[idx::I])
            };
            let eu: f64 = self.rng_u.sample(StandardNormal);
            let ei: f64 = self.rng_i.sample(StandardNormal);
            out.u.push(u + self.noise.0 * eu);
            out.i.push(i + self.noise.1 * ei);
            self.pos += 1;
        }
        // Keep what the interpolator still needs behind the integration point.
        let integrated = self.pos.saturating_sub(HALF_TAPS);
        let keep_from = integrated.saturating_sub(2 * HALF_TAPS + 1);
        if keep_from > self.base + (1 << 16) {
            self.hist.drain(..keep_from - self.base);
            self.base = keep_from;
        }
        Ok(Some(out))
    }

    fn truth(&self) -> Option<Truth> {
        Some(self.truth)
    }

    fn describe(&self) -> String {
        format!("virtual {}", self.params.name.clone().unwrap_or_else(|| "driver".into()))
    }
}

/// A recording played back.
pub struct ReplayDevice {
    name: String,
    fs: f64,
    u: Vec<f64>,
    i: Vec<f64>,
    pos: usize,
}

impl ReplayDevice {
    pub fn open(path: &std::path::Path, scale: Option<&[f64]>) -> Result<Self, String> {
        let rec = coilscope_io::read_recording(path, scale).map_err(|e| e.to_string())?;
        Ok(ReplayDevice { name: path.display().to_string(), fs: rec.fs as f64, u: rec.u, i: rec.i, pos: 0 })
    }

    pub fn from_samples(name: &str, fs: f64, u: Vec<f64>, i: Vec<f64>) -> Self {
        ReplayDevice { name: name.into(), fs, u, i, pos: 0 }
    }
}

impl Device for ReplayDevice {
    fn fs(&self) -> f64 {
        self.fs
    }
    fn play(&mut self, drive: &[f64]) -> Result<Option<Block>, String> {
        if self.pos >= self.u.len() {
            return Ok(None);
        }
        let end = (self.pos + drive.len()).min(self.u.len());
        let b = Block { u: self.u[self.pos..end].to_vec(), i: self.i[self.pos..end].to_vec() };
        self.pos = end;
        Ok(Some(b))
    }
    fn controllable(&self) -> bool {
        false
    }
    fn describe(&self) -> String {
        format!("replay of {}", self.name)
    }
}

//! A sound card as the device under test (feature `soundcard`, through cpal; ALSA on Linux).
//!
//! Wiring: one output channel drives the power amplifier; two input channels record the
//! voltage at the transducer's terminals (through a divider if needed) and the voltage across
//! a sense resistor in series with it. Calibration turns digital full scale into volts and
//! amperes:
//!
//! * drive: `out_volts_fs` volts at the terminals for a full-scale output sample (the
//!   amplifier's gain included). A drive that would need more is refused, never clipped.
//! * voltage: `u_volts_fs` volts at the terminals for a full-scale input sample.
//! * current: `i_volts_fs` volts across the sense resistor for a full-scale input sample, and
//!   the resistor `sense_ohm`; the current is that voltage over the resistance.
//!
//! Samples are `f32`, interleaved, at the measurement's rate. The output is primed with
//! [`PRIME_SECONDS`] of silence so that the measurement's block processing never starves it;
//! the recorded blocks are aligned with each other (both channels come from one input
//! stream), not with the drive, which is all the identification needs.

use crate::device::{Block, Device};
use cpal::traits::{DeviceTrait, HostTrait, StreamTrait};
use std::collections::VecDeque;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

/// Seconds of silence queued on the output before the first block.
pub const PRIME_SECONDS: f64 = 0.2;

/// Where and how the sound card is connected (SI units).
#[derive(Clone, Debug)]
pub struct SoundCardOptions {
    /// Output device name (as `coilscope devices` lists it); `None`: the default output.
    pub output: Option<String>,
    /// Input device name; `None`: the default input.
    pub input: Option<String>,
    pub fs: f64,
    /// Output channels opened, and the one that carries the drive (0-based).
    pub out_channels: u16,
    pub drive_channel: usize,
    /// Input channels opened, and the voltage and current-sense channels (0-based).
    pub in_channels: u16,
    pub u_channel: usize,
    pub i_channel: usize,
    /// Calibration (see the module documentation).
    pub out_volts_fs: f64,
    pub u_volts_fs: f64,
    pub i_volts_fs: f64,
    pub sense_ohm: f64,
    /// How long to wait for input before giving up.
    pub timeout: Duration,
}

impl Default for SoundCardOptions {
    fn default() -> Self {
        SoundCardOptions {
            output: None,
            input: None,
            fs: 48000.0,
            out_channels: 2,
            drive_channel: 0,
            in_channels: 2,
            u_channel: 0,
            i_channel: 1,
            out_volts_fs: 10.0,
            u_volts_fs: 10.0,
            i_volts_fs: 1.0,
            sense_ohm: 0.1,
            timeout: Duration::from_secs(2),
        }
    }
}

impl SoundCardOptions {
    /// Check the settings; the message names the option and what is valid.
    pub fn validate(&self) -> Result<(), String> {
        let pos = |v: f64, name: &str, unit: &str| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(format!("{name} {v} {unit} is not valid (> 0)"))
            }
        };
        if !(self.fs.is_finite() && (8000.0..=384000.0).contains(&self.fs) && self.fs.fract() == 0.0) {
            return Err(format!(
                "--fs {} Hz is not valid for a sound card (a whole number of Hz, 8000 .. 384000)",
                self.fs
            ));
        }
        pos(self.out_volts_fs, "--out-volts-fs", "V")?;
        pos(self.u_volts_fs, "--u-volts-fs", "V")?;
        pos(self.i_volts_fs, "--i-volts-fs", "V")?;
        pos(self.sense_ohm, "--sense-ohm", "ohm")?;
        if self.drive_channel >= self.out_channels as usize {
            return Err(format!(
                "--drive-channel {} is not valid: the output has {} channels (0 .. {})",
                self.drive_channel,
                self.out_channels,
                self.out_channels.saturating_sub(1)
            ));
        }
        for (name, ch) in [("--u-channel", self.u_channel), ("--i-channel", self.i_channel)] {
            if ch >= self.in_channels as usize {
                return Err(format!(
                    "{name} {ch} is not valid: the input has {} channels (0 .. {})",
                    self.in_channels,
                    self.in_channels.saturating_sub(1)
                ));
            }
        }
        if self.u_channel == self.i_channel {
            return Err(format!(
                "--u-channel and --i-channel are both {}: voltage and current need two input channels",
                self.u_channel
            ));
        }
        Ok(())
    }
}

/// Names of the sound devices cpal sees: (inputs, outputs).
pub fn list_devices() -> Result<(Vec<String>, Vec<String>), String> {
    let host = cpal::default_host();
    let names = |input| devices(&host, input).map(|d| d.into_iter().map(|(n, _)| n).collect());
    Ok((names(true)?, names(false)?))
}

/// The input (or output) devices with their names.
fn devices(host: &cpal::Host, input: bool) -> Result<Vec<(String, cpal::Device)>, String> {
    let what = if input { "input" } else { "output" };
    let list: Vec<cpal::Device> =
        if input { host.input_devices().map(|d| d.collect()) } else { host.output_devices().map(|d| d.collect()) }
            .map_err(|e| format!("cannot list the {what} sound devices ({:?} host): {e}", host.id()))?;
    Ok(list.into_iter().filter_map(|d| d.name().ok().map(|n| (n, d))).collect())
}

fn find(host: &cpal::Host, name: Option<&str>, input: bool) -> Result<cpal::Device, String> {
    let what = if input { "input" } else { "output" };
    match name {
        None => (if input { host.default_input_device() } else { host.default_output_device() })
            .ok_or_else(|| format!("there is no default {what} sound device; name one (coilscope devices lists them)")),
        Some(n) => {
            let list = devices(host, input)?;
            let names: Vec<&str> = list.iter().map(|(m, _)| m.as_str()).collect();
            let known = if names.is_empty() { "none".to_string() } else { names.join(", ") };
            match list.iter().position(|(m, _)| m == n) {
                Some(k) => Ok(list.into_iter().nth(k).expect("index from the same list").1),
                None => Err(format!("no {what} sound device named '{n}'; there are: {known}")),
            }
        }
    }
}

/// Digital input frames to volts and amperes.
#[derive(Clone, Copy, Debug)]
pub struct Calibration {
    u_channel: usize,
    i_channel: usize,
    /// Volts at the terminals per unit sample.
    ku: f64,
    /// Amperes per unit sample (`i_volts_fs / sense_ohm`).
    ki: f64,
}

impl Calibration {
    pub fn of(o: &SoundCardOptions) -> Self {
        Calibration { u_channel: o.u_channel, i_channel: o.i_channel, ku: o.u_volts_fs, ki: o.i_volts_fs / o.sense_ohm }
    }

    /// (u in V, i in A) of one interleaved input frame.
    pub fn ui(&self, frame: &[f32]) -> (f64, f64) {
        (frame[self.u_channel] as f64 * self.ku, frame[self.i_channel] as f64 * self.ki)
    }
}

/// What the audio threads share with the measurement.
#[derive(Default)]
struct Shared {
    /// Drive samples (digital, one channel) waiting for the output.
    out: VecDeque<f32>,
    /// Recorded (u, i) in volts and amperes.
    recorded: VecDeque<(f64, f64)>,
    /// Output callbacks that found the queue empty (after the start).
    underruns: usize,
    error: Option<String>,
}

/// The sound card.
pub struct SoundCardDevice {
    opts: SoundCardOptions,
    names: (String, String),
    shared: Arc<(Mutex<Shared>, Condvar)>,
    _streams: (cpal::Stream, cpal::Stream),
}

impl SoundCardDevice {
    /// Open both streams and start them (the output plays silence until the first block).
    pub fn open(opts: &SoundCardOptions) -> Result<Self, String> {
        opts.validate()?;
        let host = cpal::default_host();
        let out_dev = find(&host, opts.output.as_deref(), false)?;
        let in_dev = find(&host, opts.input.as_deref(), true)?;
        let names = (in_dev.name().unwrap_or_default(), out_dev.name().unwrap_or_default());
        let rate = cpal::SampleRate(opts.fs as u32);
        let shared: Arc<(Mutex<Shared>, Condvar)> = Arc::default();
        shared
            .0
            .lock()
            .map_err(|_| "sound card state poisoned".to_string())?
            .out
            .extend(std::iter::repeat_n(0.0f32, (PRIME_SECONDS * opts.fs) as usize));
        let err_cb = |which: &'static str, sh: Arc<(Mutex<Shared>, Condvar)>| {
            move |e: cpal::StreamError| {
                if let Ok(mut s) = sh.0.lock() {
                    s.error.get_or_insert(format!("the {which} stream failed: {e}"));
                }
                sh.1.notify_all();
            }
        };
        let out_cfg = cpal::StreamConfig {
            channels: opts.out_channels,
            sample_rate: rate,
            buffer_size: cpal::BufferSize::Default,
        };
        let (och, dch) = (opts.out_channels as usize, opts.drive_channel);
        let sh = shared.clone();
        let mut started = false;
        let out_stream = out_dev
            .build_output_stream(
                &out_cfg,
                move |data: &mut [f32], _: &cpal::OutputCallbackInfo| {
                    let Ok(mut s) = sh.0.lock() else { return data.fill(0.0) };
                    for frame in data.chunks_mut(och) {
                        frame.fill(0.0);
                        match s.out.pop_front() {
                            Some(v) => {
                                frame[dch] = v;
                                started = true;
                            }
                            None if started => {
                                s.underruns += 1;
                                started = false;
                            }
                            None => {}
                        }
                    }
                },
                err_cb("output", shared.clone()),
                None,
            )
            .map_err(|e| {
                format!(
                    "cannot open the output '{}' at {} Hz with {} channels of f32: {e}",
                    names.1, opts.fs, opts.out_channels
                )
            })?;
        let in_cfg = cpal::StreamConfig {
            channels: opts.in_channels,
            sample_rate: rate,
            buffer_size: cpal::BufferSize::Default,
        };
        let ich = opts.in_channels as usize;
        let cal = Calibration::of(opts);
        let sh = shared.clone();
        let in_stream = in_dev
            .build_input_stream(
                &in_cfg,
                move |data: &[f32], _: &cpal::InputCallbackInfo| {
                    if let Ok(mut s) = sh.0.lock() {
                        s.recorded.extend(data.chunks_exact(ich).map(|f| cal.ui(f)));
                    }
                    sh.1.notify_all();
                },
                err_cb("input", shared.clone()),
                None,
            )
            .map_err(|e| {
                format!(
                    "cannot open the input '{}' at {} Hz with {} channels of f32: {e}",
                    names.0, opts.fs, opts.in_channels
                )
            })?;
        out_stream.play().map_err(|e| format!("cannot start the output '{}': {e}", names.1))?;
        in_stream.play().map_err(|e| format!("cannot start the input '{}': {e}", names.0))?;
        Ok(SoundCardDevice { opts: opts.clone(), names, shared, _streams: (out_stream, in_stream) })
    }

    /// Output callbacks that ran out of drive after the start (gaps in the excitation).
    pub fn underruns(&self) -> usize {
        self.shared.0.lock().map(|s| s.underruns).unwrap_or(0)
    }
}

impl Device for SoundCardDevice {
    fn fs(&self) -> f64 {
        self.opts.fs
    }

    fn play(&mut self, drive: &[f64]) -> Result<Option<Block>, String> {
        let fs = self.opts.out_volts_fs;
        if let Some((k, v)) = drive.iter().enumerate().find(|(_, v)| !(v.abs() <= fs)) {
            return Err(format!("drive sample {k} is {v:.3} V, beyond what the output reaches ({fs} V at full scale, --out-volts-fs): lower --max-volts or raise the amplifier's gain and --out-volts-fs with it"));
        }
        let (lock, cv) = &*self.shared;
        let mut s = lock.lock().map_err(|_| "sound card state poisoned".to_string())?;
        s.out.extend(drive.iter().map(|v| (v / fs) as f32));
        let deadline = Instant::now() + self.opts.timeout;
        while s.recorded.len() < drive.len() {
            if let Some(e) = s.error.take() {
                return Err(format!("sound card ({} -> {}): {e}", self.names.1, self.names.0));
            }
            let now = Instant::now();
            if now >= deadline {
                return Err(format!(
                    "the input '{}' delivered {} of {} samples within {:.1} s: the device is not running at {} Hz, or another program holds it",
                    self.names.0,
                    s.recorded.len(),
                    drive.len(),
                    self.opts.timeout.as_secs_f64(),
                    self.opts.fs
                ));
            }
            s = cv.wait_timeout(s, deadline - now).map_err(|_| "sound card state poisoned".to_string())?.0;
        }
        let (u, i) = s.recorded.drain(..drive.len()).unzip();
        Ok(Some(Block { u, i }))
    }

    fn describe(&self) -> String {
        let o = &self.opts;
        format!(
            "sound card: output '{}' ch {} ({} V FS), input '{}' u ch {} ({} V FS), i ch {} ({} V FS over {} ohm), {} Hz",
            self.names.1, o.drive_channel, o.out_volts_fs, self.names.0, o.u_channel, o.u_volts_fs, o.i_channel, o.i_volts_fs, o.sense_ohm, o.fs
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn calibration_turns_full_scale_into_volts_and_amperes() {
        // 10 V full scale on the voltage channel (1), 1 V full scale across 0.1 ohm on the
        // current channel (0): a half-scale frame is 5 V and 5 A.
        let o = SoundCardOptions {
            u_channel: 1,
            i_channel: 0,
            u_volts_fs: 10.0,
            i_volts_fs: 1.0,
            sense_ohm: 0.1,
            ..Default::default()
        };
        let (u, i) = Calibration::of(&o).ui(&[0.5, -0.5]);
        assert!((u + 5.0).abs() < 1e-12 && (i - 5.0).abs() < 1e-12, "{u} V, {i} A");
    }
}

//! `coilscope simulate`: a virtual driver driven by a voltage, recorded as a bench would
//! record it: through the sense wiring, a sound card's chain, and sensor noise, in that order.

use crate::chain::mark_wiring;
use coilscope_core::chain::{Chain, SenseWiring};
use coilscope_core::enclosure::BoxKind;
use coilscope_core::excitation::add_sensor_noise;
use coilscope_core::simulate::{simulate, SimOptions};
use coilscope_core::{Parameters, Trace};
use coilscope_io::Recording;
use serde_json::{json, Value};

/// How the virtual driver is recorded.
#[derive(Clone, Debug, Default)]
pub struct RecordRequest {
    /// What the voltage channel reads (the terminals, or across driver and shunt).
    pub wiring: SenseWiring,
    /// A sound card's chain the channels pass through (AC coupling, skew, gain, offsets, hum).
    pub chain: Option<Chain>,
    /// Sensor noise on every channel, this many dB below the channel's RMS.
    pub snr_db: Option<f64>,
    /// Record the displacement as a third channel (a laser).
    pub laser: bool,
    /// The seed of the sensor noise.
    pub seed: u64,
}

/// A virtual record and what made it.
pub struct Simulated {
    /// The channels as recorded.
    pub recording: Recording,
    /// The driver's own run (the states at its terminals, before wiring, chain and noise).
    pub trace: Trace,
    /// The chain the record carries, the wiring marked in it (`None`: ideal channels at the
    /// terminals).
    pub chain: Option<Chain>,
    /// The box's peaks (`None` in free air): see [`box_peaks`].
    pub box_peaks: Option<Vec<(&'static str, f64)>>,
}

/// Simulate the set `p` on the voltage `u` (V, sampled at `fs` Hz) and record it as `req`
/// says.
pub fn record(p: &Parameters, fs: f64, u: &[f64], req: &RecordRequest) -> Result<Simulated, String> {
    if let Some(db) = req.snr_db {
        if !(db.is_finite() && db > 0.0) {
            return Err(format!("--snr-db {db}: give a positive number of dB (e.g. 70)"));
        }
    }
    let trace = simulate(p, fs, u, &SimOptions::default()).map_err(|e| e.to_string())?;
    let mut chain = req.chain.clone().map(|c| Chain { source: Some("simulated".into()), ..c });
    let u_channel = req.wiring.channel_voltage(&trace.u, &trace.i);
    let (u_rec, i_rec) = match &chain {
        Some(c) => c.apply(&u_channel, &trace.i, fs),
        None => (u_channel, trace.i.clone()),
    };
    let mut recording = Recording { fs: fs as u32, u: u_rec, i: i_rec, x: req.laser.then(|| trace.x.clone()) };
    mark_wiring(&mut chain, req.wiring);
    if let Some(db) = req.snr_db {
        add_sensor_noise(&mut recording.u, db, req.seed, "sensor-noise/voltage");
        add_sensor_noise(&mut recording.i, db, req.seed, "sensor-noise/current");
        if let Some(x) = &mut recording.x {
            add_sensor_noise(x, db, req.seed, "sensor-noise/displacement");
        }
    }
    let box_peaks = box_peaks(p, &trace);
    Ok(Simulated { recording, trace, chain, box_peaks })
}

impl Simulated {
    /// The record's description (`NAME.info.json`): the run's summary, the driver's name, the
    /// signal (`signal`, as the caller describes it), the chain, and in a box the box and its
    /// peaks under the keys the independent simulator's descriptions use.
    pub fn info(&self, p: &Parameters, driver: &str, signal: Value, req: &RecordRequest) -> Value {
        let s = self.trace.summary();
        let mut info = json!({
            "x_min": s.x_min, "x_max": s.x_max, "x_p01": s.x_p01, "x_p99": s.x_p99,
            "u_rms": s.u_rms, "i_rms": s.i_rms, "dT_end": s.dt_end, "dT_max": s.dt_max,
            "dTm_end": s.dtm_end, "p_mean": s.p_mean,
            "driver": p.name.clone().unwrap_or_else(|| driver.to_string()),
            "fs": self.recording.fs as f64, "samples": self.trace.u.len(), "substeps": self.trace.substeps,
            "scheme": self.trace.scheme.name(), "snr_db": req.snr_db, "laser": req.laser,
            "signal": signal,
            "chain": self.chain,
        });
        if let (Some(e), Some(peaks)) = (&p.enclosure, &self.box_peaks) {
            info["world"] = json!({"enclosure": e.to_json()});
            for (k, v) in peaks {
                info[*k] = json!(v);
            }
        }
        info
    }
}

/// The box's peaks over a run, under the keys the independent simulator's descriptions use:
/// the box pressure (Pa), and the port's air velocity (m/s, the port's flow over its area)
/// or the radiator's excursion (m). `None` in free air.
pub fn box_peaks(p: &Parameters, trace: &Trace) -> Option<Vec<(&'static str, f64)>> {
    let e = p.enclosure.as_ref()?;
    let peak = |k: usize| trace.boxed.iter().fold(0.0f64, |a, b| a.max(b[k].abs()));
    let mut out = vec![("p_box_peak_Pa", peak(0))];
    match &e.kind {
        BoxKind::Closed => {}
        BoxKind::Vented { port_area: Some(a), .. } => out.push(("port_air_velocity_peak_m_s", peak(1) / a)),
        BoxKind::Vented { .. } => {}
        BoxKind::PassiveRadiator { .. } => out.push(("radiator_x_peak_m", peak(1))),
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use coilscope_core::excitation::{generate, Excitation, SignalSpec};

    fn drive(fs: f64) -> Vec<f64> {
        generate(
            &Excitation::Pink { f_lo: 10.0, f_hi: 8000.0, crest: None },
            &SignalSpec { fs, seconds: 0.5, rms: 1.0, fade: 0.05, seed: 3 },
        )
        .expect("pink noise")
    }

    #[test]
    fn a_record_at_the_terminals_is_the_drivers_own_run() {
        let p = coilscope_core::params::embedded_driver("sb17cac35-4").expect("embedded");
        let u = drive(48000.0);
        let s = record(&p, 48000.0, &u, &RecordRequest { laser: true, ..Default::default() }).expect("runs");
        assert_eq!(s.recording.u, s.trace.u);
        assert_eq!(s.recording.i, s.trace.i);
        assert_eq!(s.recording.x.as_deref(), Some(&s.trace.x[..]));
        assert!(s.chain.is_none() && s.box_peaks.is_none());
    }

    #[test]
    fn sensor_noise_sits_at_its_stated_level_below_each_channel() {
        let p = coilscope_core::params::embedded_driver("sb17cac35-4").expect("embedded");
        let u = drive(48000.0);
        let s = record(&p, 48000.0, &u, &RecordRequest { snr_db: Some(40.0), seed: 9, ..Default::default() })
            .expect("runs");
        let rms = coilscope_core::simulate::rms;
        let noise: Vec<f64> = s.recording.i.iter().zip(&s.trace.i).map(|(a, b)| a - b).collect();
        let db = 20.0 * (rms(&s.trace.i) / rms(&noise)).log10();
        assert!((db - 40.0).abs() < 0.5, "current noise {db:.2} dB below the channel, asked 40 dB");
        let e = record(&p, 48000.0, &u, &RecordRequest { snr_db: Some(f64::NAN), ..Default::default() });
        assert!(e.is_err_and(|e| e.contains("--snr-db")));
    }
}

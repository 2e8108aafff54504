//! `distortion` of a sine: the full model to the steady state (every element of the set: creep,
//! LR-3, a box), each nonlinearity alone, and the third-order Volterra series of the same set
//! beside it. The command line and the Python package both call [`sine`], so that a sine's
//! figures and its Volterra comparison are the same from either.

use coilscope_analysis::db;
use coilscope_analysis::distortion::{analyse, with_only, Analysis, Nonlinearity, Output, SteadyOptions};
use coilscope_analysis::volterra::{probe, Probe};
use coilscope_core::Parameters;
use serde_json::{json, Value};

/// A sine's distortion at one frequency: the full model's analysis and the Volterra series'
/// kernels there.
pub struct SineDistortion {
    pub analysis: Analysis,
    pub volterra: Probe,
    pub volts: f64,
    pub output: Output,
}

impl SineDistortion {
    /// The Volterra series' HD2 and HD3 at the sine's level.
    pub fn volterra_hd(&self) -> (f64, f64) {
        self.volterra.hd(self.output, self.volts)
    }

    /// The analysis as JSON with the Volterra series under `volterra` (HD2, HD3, in dB, its
    /// DC displacement and kernels).
    pub fn to_json(&self) -> Value {
        let (h2, h3) = self.volterra_hd();
        let mut j = self.analysis.to_json();
        j["volterra"] = json!({"HD2": h2, "HD3": h3, "HD2_dB": db(h2), "HD3_dB": db(h3), "x_dc": self.volterra.x_dc(self.volts), "kernels": self.volterra.to_json()});
        j
    }
}

/// The distortion of a sine of `volts` RMS at each of `freqs`, on `output`, the coil
/// `temp_rise` K above ambient.
pub fn sine(
    p: &Parameters,
    freqs: &[f64],
    volts: f64,
    output: Output,
    temp_rise: f64,
) -> Result<Vec<SineDistortion>, String> {
    if !(temp_rise.is_finite() && (0.0..=300.0).contains(&temp_rise)) {
        return Err(format!("temperature rise {temp_rise} K is not valid (0 .. 300 K)"));
    }
    let opts = SteadyOptions { dt_coil: temp_rise, ..SteadyOptions::default() };
    // The Volterra series of the same set, its nonlinearities all in, at the same coil
    // temperature.
    let q = with_only(p, &Nonlinearity::ALL, temp_rise);
    freqs
        .iter()
        .map(|&f| {
            let analysis = analyse(p, f, volts, output, &opts).map_err(|e| e.to_string())?;
            let volterra = probe(&q, analysis.total.freq);
            Ok(SineDistortion { analysis, volterra, volts, output })
        })
        .collect()
}

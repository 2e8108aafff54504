//! # coilscope-analysis
//!
//! What an identified (or published) parameter set predicts, without hardware.
//!
//! * [`distortion`]: the periodic steady state of the full model under a sine, a two-tone or
//!   a multitone, found by simulation and analysed by FFT over whole periods: harmonic
//!   distortion (HD2, HD3, THD), intermodulation (IEC 60268-5 d2, d3), the multitone
//!   distortion spectrum, the DC displacement, and the **contribution of each nonlinearity**
//!   (Bl(x), Kms(x), Le(x) with L2(x), R2(x) and their reluctance forces) simulated alone.
//! * [`volterra`]: the first three Volterra kernels on the diagonal, `H1(f)`, `H2(f,f)`,
//!   `H3(f,f,f)`, from the power series by harmonic probing, and their HD2/HD3 prediction.
//! * [`diagnosis`]: limits with changeable thresholds, the rest-position shift that symmetrises
//!   Bl(x), the polarity check from the Le(x) asymmetry, the dominant nonlinearity, and the
//!   thermal power handling from the thermal parameters.
//!
//! ## Conventions
//!
//! * Levels in volts are **RMS of the whole input signal** (a sine of `V` volts has the peak
//!   `V sqrt 2`; a two-tone or multitone of `V` volts has that total RMS).
//! * Distortion is computed in the **far-field sound pressure**, which is proportional to the
//!   cone acceleration `dv/dt` (the ratio of two lines does not depend on Sd or distance).
//!   [`distortion::Output`] also offers displacement and current.
//! * Ratios are amplitude ratios to the fundamental (`HDn = |P(n f)| / |P(f)|`); `db()` is
//!   `20 log10` of a ratio.
//! * The thermal model is off: distortion is evaluated at a fixed voice-coil temperature
//!   (ambient unless a rise is given), since Re(T) only compresses, it does not distort.

pub mod diagnosis;
pub mod distortion;
pub mod live_distortion;
pub mod volterra;

/// `20 log10(r)`, with -400 dB for zero.
pub fn db(r: f64) -> f64 {
    if r > 0.0 {
        20.0 * r.log10()
    } else {
        -400.0
    }
}

/// Errors of the analysis, each naming the value and what would be valid.
#[derive(Debug, thiserror::Error)]
pub enum AnalysisError {
    #[error("{0}")]
    Input(String),
    #[error("the model left its valid range: {0}")]
    Range(String),
    #[error(
        "no periodic steady state after {seconds:.2} s of simulation (last change {change:.2e} of the fundamental)"
    )]
    NotSteady { seconds: f64, change: f64 },
}

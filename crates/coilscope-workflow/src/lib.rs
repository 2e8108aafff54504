//! # coilscope-workflow
//!
//! What coilscope's commands do, as functions: the command line (`coilscope linear`,
//! `coilscope identify`) and the Python package call the same ones, so that both give the
//! same numbers, the same warnings and the same verdict (`fit.trustworthy`).
//!
//! * [`batch`]: many records identified a few at a time, with one verdict over all.
//! * [`chain`]: the measurement chain of a record: detected and estimated by default,
//!   ideal, or a calibrated card's inverted ([`chain::ChainMode`]).
//! * [`identify`]: the large-signal identification of a record, with every check the result
//!   carries.
//! * [`enclosure`]: the box a known driver works into, from its impedance in the box.
//! * [`linear`]: the small-signal fit of a record or an impedance curve, scaled by a known
//!   moving mass, an added mass or a displacement channel.
//! * [`quasistatic`]: the point-by-point static and quasi-static measurement and its result.
//! * [`simulate`]: a virtual driver's record through the wiring, a chain and sensor noise.
//!
//! A workflow never prints: it returns the result file (warnings attached) and its parts;
//! printing is the caller's.

pub mod batch;
pub mod chain;
pub mod distortion;
pub mod enclosure;
pub mod identify;
pub mod linear;
pub mod measure;
pub mod qc;
pub mod quasistatic;
pub mod simulate;
pub mod volterra;

use coilscope_core::result::ResultFile;
use coilscope_ident::checks::{NoiseFloor, Warning};

/// Put the noise floor and the warnings into `fit` of a result (`fit.noise_floor`,
/// `fit.warnings`, `fit.trustworthy`): a result with a warning is not trustworthy.
pub fn attach_warnings(result: &mut ResultFile, floor: Option<&NoiseFloor>, warnings: &[Warning]) {
    result.fit.noise_floor = floor.copied();
    result.fit.warnings = Some(warnings.to_vec());
    result.fit.trustworthy = Some(result.fit.trustworthy.unwrap_or(true) && warnings.is_empty());
}

/// Whether a result says it can be trusted (`fit.trustworthy`; absent counts as not).
pub fn trustworthy(result: &ResultFile) -> bool {
    result.fit.trustworthy == Some(true)
}

//! # coilscope-measure
//!
//! The dynamic measurement system (seed section 4): the transducer plays noise or music, the
//! system starts quiet, raises the level, identifies the model as it goes (the online
//! estimator of [`coilscope_ident::online`]), watches excursion and voice-coil temperature,
//! protects the transducer and stops when the parameters have converged.
//!
//! * [`card`]: a sound card's measurement chain corrected block by block from a calibration
//!   (`coilscope calibrate`), and a simulated card to test that path without hardware.
//! * [`device`]: what is measured: the virtual transducer (default, no hardware) or a
//!   replayed recording.
//! * `soundcard` (feature `soundcard`): a sound card through cpal, with the voltage and
//!   current-sense channels calibrated to volts and amperes.
//! * [`signal`]: excitation sources (IEC 60268-1 noise, pink noise, music files) and the
//!   variable high-pass.
//! * [`engine`]: the block loop, controller and protection; observers see every block.
//! * The run database is [`coilscope_db`] (SQLite or PostgreSQL; one transaction per second
//!   of measurement): the engine writes to its [`coilscope_db::Store`].

pub mod card;
pub mod device;
pub mod engine;
pub mod quasi_static_card;
pub mod signal;
#[cfg(feature = "soundcard")]
pub mod soundcard;

pub use engine::{
    control, measure, ControlDecision, ControlInput, Engine, LimitedBy, Live, MeasureOptions, Measurement, Stage,
    StopReason, Trace,
};

//! # coilscope-ident
//!
//! The identification engine. Solvers are pure state transitions ([`lm::lm_step`]); progress
//! bars, logs and live views observe the states and never live inside the solver.
//!
//! * [`linear`]: small-signal parameters from the impedance (H1 estimate, LR-2 + motional
//!   fit, absolute scale by Mms, added mass or displacement).

//! * [`calibrate`]: a measurement chain's delay, corners and gain from a resistor record.
//! * [`checks`]: the residual against its noise floor, and what a doubtful fit is named.

pub mod box_fit;
pub mod calibrate;
pub mod checks;
pub mod large;
pub mod linear;
pub mod lm;
pub mod min_phase;
pub mod online;
pub mod post_inverse;
pub mod pre_inverse;
pub mod quasi_static;
mod sensitivity;
pub mod thermal;
pub mod volterra;

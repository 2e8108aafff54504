//! # coilscope-testkit
//!
//! What the truth tests of every crate share (a dev-dependency only):
//!
//! * [`population`]: fresh drivers on every run, seeded from `COILSCOPE_POPULATION_SEED`
//!   (CI sets it from the commit) or from the clock, and printed, so that any failure can be
//!   drawn again; a failing driver is written out as a parameter file.
//! * [`slice`](mod@slice): a release sweep spread over CI runs (`COILSCOPE_SWEEP_SLICE=k/n`).
//! * [`world`]: records of a driver as a test plays them: pink noise to 85 % of the range,
//!   coil heating, sensor noise, optionally through a sound card's chain.
//! * [`check`]: comparisons that a NaN fails (a missing covariance must never pass as
//!   "0.00 sd"), and the two-sided check of reported bands: they must hold the truth and
//!   must not be inflated.

pub mod check;
pub mod population;
pub mod slice;
pub mod world;

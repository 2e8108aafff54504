//! # coilscope-report
pub mod chart;

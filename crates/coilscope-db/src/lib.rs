//! coilscope's run database: every measurement run with its live states, estimates and
//! distortion, and every unit a production station tests with its parameters and verdict.
//!
//! Two backends, one schema:
//!
//! * **SQLite** (bundled), the embedded default: a file (`DIR/run.sqlite` for a measurement),
//!   WAL journal, one writer per file.
//! * **PostgreSQL** (feature `postgres`, on by default): a `postgres://user@host/db` URL, where a
//!   fleet of stations writes at once. Each row a station writes is its own transaction, and a
//!   unit's row has the key (run, seq): a station can neither lose a committed row nor write
//!   one twice.
//!
//! The schema is versioned by [refinery](https://docs.rs/refinery) migrations
//! (`migrations/sqlite`, `migrations/postgres`, the same tables in each dialect), applied when a
//! database is opened. A database written before the migrations were versioned is taken as it
//! is and brought up to date.
//!
//! A run whose writer died (killed, power lost) never closes its row. [`list_runs`] reports it
//! as `killed`: on PostgreSQL when the run's advisory lock (a `pg_advisory_lock` its writer
//! holds while it lives) is free; on SQLite when the writer's process is gone (same host) or,
//! from another host, when its heartbeat is older than 10 s. A run stopped by Ctrl-C is closed
//! as `interrupted`.
//!
//! Tables (SI units):
//! * `runs(id, started, device, options, status, seconds, heartbeat, result, host, pid)`
//! * `states(run, t, stage, u_rms, i_rms, gain, f_hp, x_min, x_max, dtv, re, residual)`
//! * `estimates(run, t, residual, parameters)` (parameters as the contract's JSON)
//! * `distortion(run, t, bl_x, kms_x, le_x, bl_i, kms_i, le_i, bl_p, kms_p, le_p, dominant_x,
//!   dominant_p)`: the live distortion of each block
//! * `units(run, seq, unit_id, tested, pass, parameters, verdict)`: a station's tested units,
//!   the unit's parameter set and its verdict as JSON (`coilscope qc test --db`)

mod conn;
mod runs;
mod units;

pub use conn::{Db, Target};
pub use runs::{list_runs, read_distortion, read_states, RunInfo, StateRow, Store};
pub use units::{read_units, UnitFilter, UnitRow};

/// Seconds since the Unix epoch.
pub(crate) fn now() -> f64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs_f64()).unwrap_or(0.0)
}

//! The run database (SQLite, bundled): decimated live states and parameter estimates of
//! every run, crash-safe.
//!
//! WAL journal; rows are written inside one transaction per second of measurement, so a kill
//! loses at most the last second, and what was committed is never damaged. A run whose
//! process died stays `running` in the table; [`list_runs`] reports it as `killed`
//! (no heartbeat for 10 s); one stopped by Ctrl-C is closed as `interrupted`.
//!
//! Tables (SI units):
//! * `runs(id, started, device, options, status, seconds, heartbeat, result)`
//! * `states(run, t, stage, u_rms, i_rms, gain, f_hp, x_min, x_max, dtv, re, residual)`
//! * `estimates(run, t, residual, parameters)` (parameters as the contract's JSON)
//! * `distortion(run, t, bl_x, kms_x, le_x, bl_i, kms_i, le_i, bl_p, kms_p, le_p, dominant_x,
//!   dominant_p)`: the live distortion of each block (`coilscope_analysis::live_distortion`)

use rusqlite::{params, Connection, OptionalExtension};
use std::path::Path;

/// One decimated live state.
#[derive(Clone, Debug, Default)]
pub struct StateRow {
    pub t: f64,
    pub stage: String,
    pub u_rms: f64,
    pub i_rms: f64,
    pub gain: f64,
    pub f_hp: f64,
    pub x_min: f64,
    pub x_max: f64,
    pub dtv: f64,
    pub re: f64,
    pub residual: f64,
}

/// An open run.
pub struct Store {
    conn: Connection,
    pub run: i64,
    path: String,
    pending: Vec<StateRow>,
    pending_est: Vec<(f64, f64, String)>,
    pending_dist: Vec<(f64, [f64; 9], String, String)>,
}

fn now() -> f64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs_f64()).unwrap_or(0.0)
}

fn open(path: &Path) -> Result<Connection, String> {
    let conn = Connection::open(path).map_err(|e| format!("{}: cannot open the run database: {e}", path.display()))?;
    conn.execute_batch(
        "PRAGMA journal_mode = WAL;
         PRAGMA synchronous = NORMAL;
         PRAGMA busy_timeout = 5000;
         CREATE TABLE IF NOT EXISTS runs(id INTEGER PRIMARY KEY, started REAL NOT NULL, device TEXT NOT NULL, options TEXT NOT NULL,
             status TEXT NOT NULL, seconds REAL NOT NULL DEFAULT 0, heartbeat REAL NOT NULL, result TEXT);
         CREATE TABLE IF NOT EXISTS states(run INTEGER NOT NULL REFERENCES runs(id), t REAL NOT NULL, stage TEXT NOT NULL, u_rms REAL, i_rms REAL,
             gain REAL, f_hp REAL, x_min REAL, x_max REAL, dtv REAL, re REAL, residual REAL);
         CREATE TABLE IF NOT EXISTS estimates(run INTEGER NOT NULL REFERENCES runs(id), t REAL NOT NULL, residual REAL, parameters TEXT NOT NULL);
         CREATE TABLE IF NOT EXISTS distortion(run INTEGER NOT NULL REFERENCES runs(id), t REAL NOT NULL, bl_x REAL, kms_x REAL, le_x REAL,
             bl_i REAL, kms_i REAL, le_i REAL, bl_p REAL, kms_p REAL, le_p REAL, dominant_x TEXT, dominant_p TEXT);
         CREATE INDEX IF NOT EXISTS states_run_t ON states(run, t);",
    )
    .map_err(|e| format!("{}: not a coilscope run database, or damaged: {e}", path.display()))?;
    Ok(conn)
}

impl Store {
    /// Open (or create) the database and start a run.
    pub fn create(path: &Path, device: &str, options: &serde_json::Value) -> Result<Self, String> {
        let conn = open(path)?;
        let t = now();
        conn.execute(
            "INSERT INTO runs(started, device, options, status, heartbeat) VALUES (?1, ?2, ?3, 'running', ?1)",
            params![t, device, options.to_string()],
        )
        .map_err(|e| format!("{}: cannot start a run: {e}", path.display()))?;
        let run = conn.last_insert_rowid();
        Ok(Store {
            conn,
            run,
            path: path.display().to_string(),
            pending: Vec::new(),
            pending_est: Vec::new(),
            pending_dist: Vec::new(),
        })
    }

    pub fn push_state(&mut self, row: StateRow) {
        self.pending.push(row);
    }

    pub fn push_estimate(&mut self, t: f64, residual: f64, params: &serde_json::Value) {
        self.pending_est.push((t, residual, params.to_string()));
    }

    /// One block's live distortion: `[Bl, Kms, Le]` in x, then i, then p, and the dominant
    /// ones in x and p.
    pub fn push_distortion(&mut self, t: f64, f: [f64; 9], dominant_x: &str, dominant_p: &str) {
        self.pending_dist.push((t, f, dominant_x.into(), dominant_p.into()));
    }

    /// Write everything pending in one transaction (call once per second of measurement).
    pub fn commit(&mut self, seconds: f64) -> Result<(), String> {
        let err = |e: rusqlite::Error| format!("{}: cannot write the run: {e}", self.path);
        let tx = self.conn.transaction().map_err(err)?;
        {
            let mut st = tx.prepare_cached("INSERT INTO states(run, t, stage, u_rms, i_rms, gain, f_hp, x_min, x_max, dtv, re, residual) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12)").map_err(err)?;
            for r in &self.pending {
                st.execute(params![
                    self.run, r.t, r.stage, r.u_rms, r.i_rms, r.gain, r.f_hp, r.x_min, r.x_max, r.dtv, r.re, r.residual
                ])
                .map_err(err)?;
            }
            let mut se = tx
                .prepare_cached("INSERT INTO estimates(run, t, residual, parameters) VALUES (?1, ?2, ?3, ?4)")
                .map_err(err)?;
            for (t, r, p) in &self.pending_est {
                se.execute(params![self.run, t, r, p]).map_err(err)?;
            }
            let mut sd = tx.prepare_cached("INSERT INTO distortion(run, t, bl_x, kms_x, le_x, bl_i, kms_i, le_i, bl_p, kms_p, le_p, dominant_x, dominant_p) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13)").map_err(err)?;
            for (t, f, dx, dp) in &self.pending_dist {
                sd.execute(params![self.run, t, f[0], f[1], f[2], f[3], f[4], f[5], f[6], f[7], f[8], dx, dp])
                    .map_err(err)?;
            }
            tx.execute("UPDATE runs SET seconds = ?1, heartbeat = ?2 WHERE id = ?3", params![seconds, now(), self.run])
                .map_err(err)?;
        }
        tx.commit().map_err(err)?;
        self.pending.clear();
        self.pending_est.clear();
        self.pending_dist.clear();
        Ok(())
    }

    /// Close the run with its status (`converged`, `stopped`, `failed: ...`) and result.
    pub fn finish<R: serde::Serialize>(
        &mut self,
        seconds: f64,
        status: &str,
        result: Option<&R>,
    ) -> Result<(), String> {
        self.commit(seconds)?;
        let text = result.map(|r| serde_json::to_string(r).expect("maps with string keys always serialise"));
        self.conn
            .execute(
                "UPDATE runs SET status = ?1, result = ?2, heartbeat = ?3 WHERE id = ?4",
                params![status, text, now(), self.run],
            )
            .map_err(|e| format!("{}: cannot close the run: {e}", self.path))?;
        Ok(())
    }
}

/// One run as listed.
#[derive(Clone, Debug)]
pub struct RunInfo {
    pub id: i64,
    pub started: f64,
    pub device: String,
    /// `running`, `interrupted` (no heartbeat for 10 s), or the final status.
    pub status: String,
    pub seconds: f64,
    pub states: i64,
    pub estimates: i64,
    /// The last stored state.
    pub last: Option<StateRow>,
}

const STATE_COLUMNS: &str = "t, stage, u_rms, i_rms, gain, f_hp, x_min, x_max, dtv, re, residual";

fn state_row(r: &rusqlite::Row) -> rusqlite::Result<StateRow> {
    // Numeric columns may be NULL (a value not known yet at that state): read as NaN.
    let num = |k: usize| r.get::<_, Option<f64>>(k).map(|v| v.unwrap_or(f64::NAN));
    Ok(StateRow {
        t: r.get(0)?,
        stage: r.get(1)?,
        u_rms: num(2)?,
        i_rms: num(3)?,
        gain: num(4)?,
        f_hp: num(5)?,
        x_min: num(6)?,
        x_max: num(7)?,
        dtv: num(8)?,
        re: num(9)?,
        residual: num(10)?,
    })
}

/// Every stored state of run `run` (the last run when `None`), in time order.
/// An existing database, opened, and the run `run` (the last run when `None`).
fn open_run(path: &Path, run: Option<i64>) -> Result<(Connection, i64), String> {
    if !path.exists() {
        return Err(format!("{}: no such run database (coilscope measure writes DIR/run.sqlite)", path.display()));
    }
    let conn = open(path)?;
    let run = match run {
        Some(r) => r,
        None => conn
            .query_row("SELECT MAX(id) FROM runs", [], |r| r.get::<_, Option<i64>>(0))
            .map_err(|e| format!("{}: cannot read the runs: {e}", path.display()))?
            .ok_or_else(|| format!("{}: the database has no runs", path.display()))?,
    };
    Ok((conn, run))
}

pub fn read_states(path: &Path, run: Option<i64>) -> Result<Vec<StateRow>, String> {
    let (conn, run) = open_run(path, run)?;
    let err = |e: rusqlite::Error| format!("{}: cannot read the states: {e}", path.display());
    let mut st = conn.prepare(&format!("SELECT {STATE_COLUMNS} FROM states WHERE run = ?1 ORDER BY t")).map_err(err)?;
    let rows = st.query_map([run], state_row).map_err(err)?.collect::<Result<Vec<_>, _>>().map_err(err)?;
    Ok(rows)
}

/// The live distortion rows of run `run` (the last run when `None`): `(t, [Bl, Kms, Le] in x,
/// i, p, dominant in x)`, in time order.
pub fn read_distortion(path: &Path, run: Option<i64>) -> Result<Vec<(f64, [f64; 9], String)>, String> {
    let (conn, run) = open_run(path, run)?;
    let err = |e: rusqlite::Error| format!("{}: cannot read the distortion: {e}", path.display());
    let mut st = conn.prepare("SELECT t, bl_x, kms_x, le_x, bl_i, kms_i, le_i, bl_p, kms_p, le_p, dominant_x FROM distortion WHERE run = ?1 ORDER BY t").map_err(err)?;
    let rows = st
        .query_map([run], |r| {
            let mut f = [0.0; 9];
            for (k, v) in f.iter_mut().enumerate() {
                *v = r.get::<_, Option<f64>>(k + 1)?.unwrap_or(f64::NAN);
            }
            Ok((r.get(0)?, f, r.get::<_, Option<String>>(10)?.unwrap_or_default()))
        })
        .map_err(err)?
        .collect::<Result<Vec<_>, _>>()
        .map_err(err)?;
    Ok(rows)
}

/// List the runs of a database (works on a database whose writer was killed).
pub fn list_runs(path: &Path) -> Result<Vec<RunInfo>, String> {
    if !path.exists() {
        return Err(format!("{}: no such run database (coilscope measure writes DIR/run.sqlite)", path.display()));
    }
    let conn = open(path)?;
    let err = |e: rusqlite::Error| format!("{}: cannot read the runs: {e}", path.display());
    let mut st =
        conn.prepare("SELECT id, started, device, status, seconds, heartbeat FROM runs ORDER BY id").map_err(err)?;
    let rows: Vec<(i64, f64, String, String, f64, f64)> = st
        .query_map([], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?, r.get(4)?, r.get(5)?)))
        .map_err(err)?
        .collect::<Result<_, _>>()
        .map_err(err)?;
    let t_now = now();
    let mut out = Vec::new();
    for (id, started, device, status, seconds, heartbeat) in rows {
        let states: i64 =
            conn.query_row("SELECT COUNT(*) FROM states WHERE run = ?1", [id], |r| r.get(0)).map_err(err)?;
        let estimates: i64 =
            conn.query_row("SELECT COUNT(*) FROM estimates WHERE run = ?1", [id], |r| r.get(0)).map_err(err)?;
        let last = conn
            .query_row(
                &format!("SELECT {STATE_COLUMNS} FROM states WHERE run = ?1 ORDER BY t DESC LIMIT 1"),
                [id],
                state_row,
            )
            .optional()
            .map_err(err)?;
        // A run whose process died (killed, power lost) never closed its row: no heartbeat
        // for 10 s. A run stopped by Ctrl-C closed it as `interrupted`.
        let status = if status == "running" && t_now - heartbeat > 10.0 { "killed".to_string() } else { status };
        out.push(RunInfo { id, started, device, status, seconds, states, estimates, last });
    }
    Ok(out)
}

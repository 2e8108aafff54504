//! Runs: one writer's work (a measurement, or a production station's lot), its live
//! states, estimates and distortion, and how it ended.

use crate::conn::{Arg, Cell, Db, Target};
use crate::now;

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

/// The key of the PostgreSQL advisory lock (held per connection) a run's writer holds while it lives.
const RUN_LOCK: i64 = 0x636f_696c_0100_0000;

/// Seconds without a heartbeat after which a run whose writer cannot be asked is taken for
/// killed (a SQLite file read from another host).
const HEARTBEAT_TIMEOUT: f64 = 10.0;

/// This host's name, to tell whether a run's writer process can be looked up here.
fn host() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|s| s.trim().to_string())
        .ok()
        .or_else(|| std::env::var("HOSTNAME").ok())
        .unwrap_or_default()
}

/// Whether process `pid` of this host lives; `None` where that cannot be told.
fn alive(pid: i64) -> Option<bool> {
    if cfg!(target_os = "linux") {
        Some(std::path::Path::new(&format!("/proc/{pid}")).exists())
    } else {
        None
    }
}

/// An open run, written by this process.
pub struct Store {
    db: Db,
    pub run: i64,
    pending: Vec<StateRow>,
    pending_est: Vec<(f64, f64, String)>,
    pending_dist: Vec<(f64, [f64; 9], String, String)>,
    /// The next unit's number in this run.
    seq: i64,
}

impl Store {
    /// Open (or create) the database and start a run of `device` with its `options`.
    pub fn create(target: &Target, device: &str, options: &serde_json::Value) -> Result<Self, String> {
        let mut db = Db::open(target)?;
        let t = now();
        let options = options.to_string();
        let host = host();
        let rows = db
            .query(
                "INSERT INTO runs(started, device, options, status, heartbeat, host, pid) VALUES ($1, $2, $3, 'running', $4, $5, $6) RETURNING id",
                &[Arg::F(t), Arg::T(device), Arg::T(&options), Arg::F(t), Arg::T(&host), Arg::I(std::process::id() as i64)],
            )
            .map_err(|e| format!("{}: cannot start a run: {e}", db.name()))?;
        let run = rows
            .first()
            .and_then(|r| r.first())
            .map(Cell::i)
            .ok_or_else(|| format!("{}: cannot start a run: no id returned", db.name()))?;
        if db.is_postgres() {
            // Held by this connection until it closes: a reader that can take it knows the writer
            // is gone.
            db.exec("SELECT pg_advisory_lock($1)", &[Arg::I(RUN_LOCK + run)])
                .map_err(|e| format!("{}: cannot start a run: {e}", db.name()))?;
        }
        Ok(Store { db, run, pending: Vec::new(), pending_est: Vec::new(), pending_dist: Vec::new(), seq: 0 })
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

    /// Write everything pending in one transaction (call once per second of measurement), with
    /// the run's length so far and a heartbeat.
    pub fn commit(&mut self, seconds: f64) -> Result<(), String> {
        let (run, states, est, dist) = (self.run, &self.pending, &self.pending_est, &self.pending_dist);
        self.db
            .transaction(|db| {
                for r in states {
                    let num = |v: f64| Arg::F(v);
                    db.exec(
                        "INSERT INTO states(run, t, stage, u_rms, i_rms, gain, f_hp, x_min, x_max, dtv, re, residual) VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12)",
                        &[Arg::I(run), num(r.t), Arg::T(&r.stage), num(r.u_rms), num(r.i_rms), num(r.gain), num(r.f_hp), num(r.x_min), num(r.x_max), num(r.dtv), num(r.re), num(r.residual)],
                    )?;
                }
                for (t, r, p) in est {
                    db.exec(
                        "INSERT INTO estimates(run, t, residual, parameters) VALUES ($1, $2, $3, $4)",
                        &[Arg::I(run), Arg::F(*t), Arg::F(*r), Arg::T(p)],
                    )?;
                }
                for (t, f, dx, dp) in dist {
                    let mut args = vec![Arg::I(run), Arg::F(*t)];
                    args.extend(f.iter().map(|v| Arg::F(*v)));
                    args.extend([Arg::T(dx), Arg::T(dp)]);
                    db.exec("INSERT INTO distortion(run, t, bl_x, kms_x, le_x, bl_i, kms_i, le_i, bl_p, kms_p, le_p, dominant_x, dominant_p) VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13)", &args)?;
                }
                db.exec(
                    "UPDATE runs SET seconds = $1, heartbeat = $2 WHERE id = $3",
                    &[Arg::F(seconds), Arg::F(now()), Arg::I(run)],
                )?;
                Ok(())
            })
            .map_err(|e| format!("{}: cannot write the run: {e}", self.db.name()))?;
        self.pending.clear();
        self.pending_est.clear();
        self.pending_dist.clear();
        Ok(())
    }

    /// A tested unit: its id, whether it passed, its parameter set and its verdict, in one
    /// transaction of its own (with the run's heartbeat). Returns the unit's number in the run.
    pub fn record_unit(
        &mut self,
        unit_id: &str,
        pass: bool,
        parameters: &serde_json::Value,
        verdict: &serde_json::Value,
    ) -> Result<i64, String> {
        let (run, seq) = (self.run, self.seq);
        let (p, v) = (parameters.to_string(), verdict.to_string());
        self.db
            .transaction(|db| {
                let t = now();
                db.exec(
                    "INSERT INTO units(run, seq, unit_id, tested, pass, parameters, verdict) VALUES ($1, $2, $3, $4, $5, $6, $7)",
                    &[Arg::I(run), Arg::I(seq), Arg::T(unit_id), Arg::F(t), Arg::B(pass), Arg::T(&p), Arg::T(&v)],
                )?;
                db.exec("UPDATE runs SET heartbeat = $1 WHERE id = $2", &[Arg::F(t), Arg::I(run)])?;
                Ok(())
            })
            .map_err(|e| format!("{}: cannot write unit {unit_id}: {e}", self.db.name()))?;
        self.seq += 1;
        Ok(seq)
    }

    /// Close the run with its status (`converged`, `stopped`, `failed: ...`, a station's
    /// `finished`) and result.
    pub fn finish<R: serde::Serialize>(
        &mut self,
        seconds: f64,
        status: &str,
        result: Option<&R>,
    ) -> Result<(), String> {
        self.commit(seconds)?;
        let text = result.map(|r| serde_json::to_string(r).expect("maps with string keys always serialise"));
        self.db
            .exec(
                "UPDATE runs SET status = $1, result = $2, heartbeat = $3 WHERE id = $4",
                &[Arg::T(status), Arg::OptT(text.as_deref()), Arg::F(now()), Arg::I(self.run)],
            )
            .map_err(|e| format!("{}: cannot close the run: {e}", self.db.name()))?;
        Ok(())
    }
}

/// One run as listed.
#[derive(Clone, Debug)]
pub struct RunInfo {
    pub id: i64,
    pub started: f64,
    pub device: String,
    /// `running`, `killed` (its writer is gone), `interrupted` (Ctrl-C), or the final status.
    pub status: String,
    pub seconds: f64,
    pub states: i64,
    pub estimates: i64,
    /// Units a station tested in the run.
    pub units: i64,
    /// The last stored state.
    pub last: Option<StateRow>,
}

const STATE_COLUMNS: &str = "t, stage, u_rms, i_rms, gain, f_hp, x_min, x_max, dtv, re, residual";

fn state_row(r: &[Cell]) -> StateRow {
    StateRow {
        t: r[0].f(),
        stage: r[1].t(),
        u_rms: r[2].f(),
        i_rms: r[3].f(),
        gain: r[4].f(),
        f_hp: r[5].f(),
        x_min: r[6].f(),
        x_max: r[7].f(),
        dtv: r[8].f(),
        re: r[9].f(),
        residual: r[10].f(),
    }
}

/// An existing database, opened, and the run `run` (the last run when `None`).
fn open_run(target: &Target, run: Option<i64>) -> Result<(Db, i64), String> {
    let mut db = Db::open_existing(target)?;
    let run = match run {
        Some(r) => r,
        None => {
            let rows = db
                .query("SELECT MAX(id) FROM runs", &[])
                .map_err(|e| format!("{}: cannot read the runs: {e}", db.name()))?;
            match rows.first().and_then(|r| r.first()) {
                Some(Cell::I(id)) => *id,
                _ => return Err(format!("{}: the database has no runs", db.name())),
            }
        }
    };
    Ok((db, run))
}

/// Every stored state of run `run` (the last run when `None`), in time order.
pub fn read_states(target: &Target, run: Option<i64>) -> Result<Vec<StateRow>, String> {
    let (mut db, run) = open_run(target, run)?;
    let rows = db
        .query(&format!("SELECT {STATE_COLUMNS} FROM states WHERE run = $1 ORDER BY t"), &[Arg::I(run)])
        .map_err(|e| format!("{}: cannot read the states: {e}", db.name()))?;
    Ok(rows.iter().map(|r| state_row(r)).collect())
}

/// The live distortion rows of run `run` (the last run when `None`): `(t, [Bl, Kms, Le] in x,
/// i, p, dominant in x)`, in time order.
pub fn read_distortion(target: &Target, run: Option<i64>) -> Result<Vec<(f64, [f64; 9], String)>, String> {
    let (mut db, run) = open_run(target, run)?;
    let rows = db
        .query("SELECT t, bl_x, kms_x, le_x, bl_i, kms_i, le_i, bl_p, kms_p, le_p, dominant_x FROM distortion WHERE run = $1 ORDER BY t", &[Arg::I(run)])
        .map_err(|e| format!("{}: cannot read the distortion: {e}", db.name()))?;
    Ok(rows
        .iter()
        .map(|r| {
            let mut f = [0.0; 9];
            for (k, v) in f.iter_mut().enumerate() {
                *v = r[k + 1].f();
            }
            (r[0].f(), f, r[10].t())
        })
        .collect())
}

/// List the runs of a database, each with its status: a run left `running` by a writer that
/// is gone is reported (and, where that is certain, marked) `killed`.
pub fn list_runs(target: &Target) -> Result<Vec<RunInfo>, String> {
    let mut db = Db::open_existing(target)?;
    let name = db.name().to_string();
    let err = |e: String| format!("{name}: cannot read the runs: {e}");
    let rows = db
        .query("SELECT id, started, device, status, seconds, heartbeat, host, pid FROM runs ORDER BY id", &[])
        .map_err(err)?;
    let count = |db: &mut Db, table: &str| -> Result<std::collections::HashMap<i64, i64>, String> {
        let rows = db.query(&format!("SELECT run, COUNT(*) FROM {table} GROUP BY run"), &[]).map_err(err)?;
        Ok(rows.iter().map(|r| (r[0].i(), r[1].i())).collect())
    };
    let (states, estimates, units) =
        (count(&mut db, "states")?, count(&mut db, "estimates")?, count(&mut db, "units")?);
    let (t_now, here) = (now(), host());
    let mut out = Vec::new();
    for r in rows {
        let id = r[0].i();
        let mut status = r[3].t();
        if status == "running" {
            // Whether the writer is gone for certain (the status is then written), or only
            // seems to be (no heartbeat for a while, from another host: reported only).
            let (gone, certain) = if db.is_postgres() {
                let free = db.query("SELECT pg_try_advisory_lock($1)", &[Arg::I(RUN_LOCK + id)]).map_err(err)?;
                let free = free.first().and_then(|r| r.first()).is_some_and(Cell::b);
                if free {
                    db.exec("SELECT pg_advisory_unlock($1)", &[Arg::I(RUN_LOCK + id)]).map_err(err)?;
                }
                (free, true)
            } else {
                match (r[6].opt_t(), r[7].i()) {
                    (Some(h), pid) if h == here && pid > 0 => match alive(pid) {
                        Some(a) => (!a, true),
                        None => (t_now - r[5].f() > HEARTBEAT_TIMEOUT, false),
                    },
                    _ => (t_now - r[5].f() > HEARTBEAT_TIMEOUT, false),
                }
            };
            if gone {
                status = "killed".into();
                if certain {
                    db.exec("UPDATE runs SET status = 'killed' WHERE id = $1 AND status = 'running'", &[Arg::I(id)])
                        .map_err(err)?;
                }
            }
        }
        let last = db
            .query(&format!("SELECT {STATE_COLUMNS} FROM states WHERE run = $1 ORDER BY t DESC LIMIT 1"), &[Arg::I(id)])
            .map_err(err)?
            .first()
            .map(|r| state_row(r));
        out.push(RunInfo {
            id,
            started: r[1].f(),
            device: r[2].t(),
            status,
            seconds: r[4].f(),
            states: states.get(&id).copied().unwrap_or(0),
            estimates: estimates.get(&id).copied().unwrap_or(0),
            units: units.get(&id).copied().unwrap_or(0),
            last,
        });
    }
    Ok(out)
}

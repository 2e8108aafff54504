//! Units: what a production station tested, read back for a lot's statistics and a unit's
//! history.

use crate::conn::{Arg, Db, Target};

/// One tested unit.
#[derive(Clone, Debug, PartialEq)]
pub struct UnitRow {
    /// The station's run, and the unit's number in it.
    pub run: i64,
    pub seq: i64,
    pub unit_id: String,
    /// When it was tested (seconds since the Unix epoch).
    pub tested: f64,
    pub pass: bool,
    /// Its parameter set (the contract's JSON, with the range its record reached).
    pub parameters: String,
    /// Its verdict (`coilscope.qc-verdict/1`).
    pub verdict: String,
}

/// Which units to read: all, one run's, one unit's (its history).
#[derive(Clone, Debug, Default)]
pub struct UnitFilter {
    pub run: Option<i64>,
    pub unit_id: Option<String>,
}

/// The units that pass `filter`, in the order they were tested.
pub fn read_units(target: &Target, filter: &UnitFilter) -> Result<Vec<UnitRow>, String> {
    let mut db = Db::open_existing(target)?;
    let mut sql = "SELECT run, seq, unit_id, tested, pass, parameters, verdict FROM units".to_string();
    let mut args = Vec::new();
    let mut conds = Vec::new();
    if let Some(r) = filter.run {
        args.push(Arg::I(r));
        conds.push(format!("run = ${}", args.len()));
    }
    if let Some(u) = &filter.unit_id {
        args.push(Arg::T(u));
        conds.push(format!("unit_id = ${}", args.len()));
    }
    if !conds.is_empty() {
        sql += &format!(" WHERE {}", conds.join(" AND "));
    }
    sql += " ORDER BY tested, run, seq";
    let rows = db.query(&sql, &args).map_err(|e| format!("{}: cannot read the units: {e}", db.name()))?;
    Ok(rows
        .iter()
        .map(|r| UnitRow {
            run: r[0].i(),
            seq: r[1].i(),
            unit_id: r[2].t(),
            tested: r[3].f(),
            pass: r[4].b(),
            parameters: r[5].t(),
            verdict: r[6].t(),
        })
        .collect())
}

//! `coilscope qc`: the end-of-line test of a production line.
//!
//! - **Learning limits** ([`learn`]): from the identified sets of N golden units, each figure's
//!   mean and sd, and its limits `mean +- k sd` (or as given, by editing the file). The
//!   figures: `Re`, `fs`, `Qts`, `Qms`, `Rms`, `Bl(0)`, `Kms(0)`, `Le(0)`, the symmetry points
//!   of Bl(x) and Kms(x) at a fixed amplitude (half the golden units' least reach), and `Xmax`
//!   (the smallest of IEC 62458's XBl, XC and XL; a lower limit only).
//! - **Testing a unit** ([`test_unit`]): pass, or fail naming each figure outside its limits,
//!   by how much, and what it likely means (a raised `Rms`: a rubbing coil); where Bl's
//!   symmetry point is off, how far to move the coil.
//! - **A lot's capability** ([`capability`]): per figure its mean, sd, `Cpk =
//!   min(hi - mean, mean - lo) / 3 sd` and how many units fell outside.
//!
//! - **A unit from its record** ([`unit_from_record`]): a station's short record identified as
//!   `identify` does, the set a verdict is taken on.
//! - **A station** ([`Station`]): a lot tested on one station, each unit's set and verdict
//!   written to the run database ([`coilscope_db`]: a SQLite file, or a PostgreSQL server that
//!   every station of a line writes to) as it is judged, in a transaction of its own.
//! - **From the database**: a lot ([`lot`]) for its capability, and a unit's history
//!   ([`history`]): its figures at every test, for drift over time.
//!
//! The limits file is `"format": "coilscope.qc-limits/1"` (docs/usage.md, "Production line").

use coilscope_core::limits::{limits_with, symmetry_point, Thresholds};
use coilscope_core::small_signal::thiele_small;
use coilscope_core::Parameters;
use serde_json::{json, Value};

/// The format tag of a limits file.
pub const LIMITS_FORMAT: &str = "coilscope.qc-limits/1";

/// One end-of-line figure: its key, unit, what a value above and below its limits likely means,
/// and whether only its lower limit is tested.
pub struct Figure {
    pub key: &'static str,
    pub unit: &'static str,
    pub high: &'static str,
    pub low: &'static str,
    pub lower_only: bool,
}

/// The figures [`figures`] gives, in its order.
pub const FIGURES: [Figure; 11] = [
    Figure {
        key: "Re",
        unit: "ohm",
        high: "a thinner or longer coil wire, or a bad joint or lead",
        low: "a shorted turn or another coil",
        lower_only: false,
    },
    Figure {
        key: "fs",
        unit: "Hz",
        high: "a stiffer suspension or a lighter moving mass",
        low: "a softer suspension or a heavier moving mass",
        lower_only: false,
    },
    Figure {
        key: "Qts",
        unit: "1",
        high: "a weaker motor or less damping",
        low: "a stronger motor or more damping",
        lower_only: false,
    },
    Figure {
        key: "Qms",
        unit: "1",
        high: "less mechanical loss than the golden units",
        low: "more mechanical loss (a rubbing coil, a damaged suspension)",
        lower_only: false,
    },
    Figure {
        key: "Rms",
        unit: "kg/s",
        high: "raised mechanical loss: a rubbing coil or a damaged suspension",
        low: "less mechanical loss than the golden units",
        lower_only: false,
    },
    Figure {
        key: "Bl(0)",
        unit: "T m",
        high: "a stronger magnet or a longer coil in the gap",
        low: "a weak magnet, or the coil out of the gap's centre",
        lower_only: false,
    },
    Figure {
        key: "Kms(0)",
        unit: "N/m",
        high: "a stiff suspension (spider or surround)",
        low: "a soft suspension (spider or surround)",
        lower_only: false,
    },
    Figure {
        key: "Le(0)",
        unit: "H",
        high: "a coil with more turns or a pole piece without its shorting ring",
        low: "a coil with fewer turns",
        lower_only: false,
    },
    Figure {
        key: "Xsym_Bl",
        unit: "m",
        high: "a coil offset in the gap",
        low: "a coil offset in the gap",
        lower_only: false,
    },
    Figure {
        key: "Xsym_Kms",
        unit: "m",
        high: "a suspension off its centre (spider glued off-centre)",
        low: "a suspension off its centre (spider glued off-centre)",
        lower_only: false,
    },
    Figure {
        key: "Xmax",
        unit: "m",
        high: "more usable excursion than the limit set by hand",
        low: "a short usable excursion",
        lower_only: true,
    },
];

/// The figures of a unit's set `p`, in [`FIGURES`]' order; the symmetry points at `amplitude`
/// (m). `None`: not known from this set (its range is too short for the amplitude, or no limit
/// of Xmax lies inside it).
pub fn figures(p: &Parameters, amplitude: f64) -> Vec<Option<f64>> {
    let ts = thiele_small(p);
    let range = p.x_range;
    let sym = |f: &coilscope_core::Poly| range.and_then(|r| symmetry_point(f, amplitude, r));
    let xmax = range.and_then(|r| {
        let l = limits_with(p, r, Thresholds::default());
        [l.xbl, l.xc, l.xl].into_iter().flatten().reduce(f64::min)
    });
    vec![
        Some(p.re),
        Some(ts.fs),
        Some(ts.qts),
        Some(ts.qms),
        Some(p.rms),
        Some(p.bl.eval(0.0)),
        Some(p.kms.eval(0.0)),
        Some(p.le.eval(0.0)),
        sym(&p.bl),
        sym(&p.kms),
        xmax,
    ]
}

/// A figure's limits, with the golden units' mean and sd they came from.
#[derive(Clone, Debug, PartialEq)]
pub struct Limit {
    pub key: String,
    pub lo: f64,
    /// Infinite for a figure whose lower limit alone is tested.
    pub hi: f64,
    pub mean: f64,
    pub sd: f64,
}

/// The limits of a line.
#[derive(Clone, Debug, PartialEq)]
pub struct Limits {
    /// The limits are `mean +- k sd` of the golden units.
    pub k: f64,
    /// The amplitude (m) the symmetry points are taken at.
    pub amplitude: f64,
    /// The golden units, by name.
    pub golden: Vec<String>,
    pub limits: Vec<Limit>,
    /// Figures left without a limit, and why.
    pub skipped: Vec<(String, String)>,
}

fn mean_sd(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
    (mean, var.sqrt())
}

/// The limits learned from the golden units' sets (`(name, set)`, each with its measured
/// `x_range`): per figure `mean +- k sd`. At least 5 units. A figure that is not known on every
/// golden unit (Xmax beyond their ranges) gets no limit.
pub fn learn(golden: &[(String, Parameters)], k: f64) -> Result<Limits, String> {
    if golden.len() < 5 {
        return Err(format!("{} golden units: give at least 5 (30 or more make limits that hold)", golden.len()));
    }
    if !(k.is_finite() && k > 0.0) {
        return Err(format!("--k {k}: give the limits' width in sds, a positive number (3 is usual)"));
    }
    let mut reach = f64::INFINITY;
    for (name, p) in golden {
        let r = p.x_range.ok_or_else(|| format!("{name}: no x_range (the range its curves were measured over): learn from results of `identify` or `measure`"))?;
        reach = reach.min((-r[0]).min(r[1]));
    }
    if let Some((name, p)) = golden.iter().find(|(_, p)| p.x_range.is_some_and(|r| !(r[0] < 0.0 && r[1] > 0.0))) {
        return Err(format!("{name}: x_range {:?} m does not reach both sides of rest", p.x_range.unwrap_or_default()));
    }
    let amplitude = 0.5 * reach;
    let all: Vec<Vec<Option<f64>>> = golden.iter().map(|(_, p)| figures(p, amplitude)).collect();
    let mut limits = Vec::new();
    let mut skipped = Vec::new();
    for (j, f) in FIGURES.iter().enumerate() {
        let Some(v) = all.iter().map(|row| row[j].filter(|x| x.is_finite())).collect::<Option<Vec<f64>>>() else {
            let missing = all
                .iter()
                .zip(golden)
                .filter(|(row, _)| row[j].is_none())
                .map(|(_, (n, _))| n.as_str())
                .collect::<Vec<_>>();
            let why = if f.key == "Xmax" {
                "no limit of XBl, XC or XL lies inside the measured range of"
            } else {
                "the measured range is too short for the symmetry amplitude on"
            };
            skipped.push((f.key.to_string(), format!("{why} {}", missing.join(", "))));
            continue;
        };
        let (mean, sd) = mean_sd(&v);
        if !(sd > 0.0) {
            return Err(format!(
                "every golden unit has the same {} ({mean}): are the files copies of one unit?",
                f.key
            ));
        }
        let hi = if f.lower_only { f64::INFINITY } else { mean + k * sd };
        limits.push(Limit { key: f.key.to_string(), lo: mean - k * sd, hi, mean, sd });
    }
    Ok(Limits { k, amplitude, golden: golden.iter().map(|(n, _)| n.clone()).collect(), limits, skipped })
}

impl Limits {
    /// The limits file.
    pub fn to_json(&self) -> Value {
        let figures: serde_json::Map<String, Value> = self
            .limits
            .iter()
            .map(|l| {
                let unit = FIGURES.iter().find(|f| f.key == l.key).map_or("", |f| f.unit);
                let hi = if l.hi.is_finite() { json!(l.hi) } else { Value::Null };
                (l.key.clone(), json!({"lo": l.lo, "hi": hi, "mean": l.mean, "sd": l.sd, "unit": unit}))
            })
            .collect();
        json!({
            "format": LIMITS_FORMAT,
            "k": self.k,
            "symmetry_amplitude": self.amplitude,
            "golden": self.golden,
            "limits": figures,
            "not_limited": self.skipped.iter().map(|(k, why)| json!({"key": k, "why": why})).collect::<Vec<_>>(),
        })
    }

    /// A limits file read back (`origin` names it in errors). `hi` null: no upper limit.
    pub fn from_json(text: &str, origin: &str) -> Result<Limits, String> {
        let v: Value = serde_json::from_str(text).map_err(|e| format!("{origin}: not valid JSON ({e})"))?;
        if v.get("format").and_then(Value::as_str) != Some(LIMITS_FORMAT) {
            return Err(format!(
                "{origin}: format {}: expected \"{LIMITS_FORMAT}\" (write one with `coilscope qc learn`)",
                v.get("format").unwrap_or(&Value::Null)
            ));
        }
        let num = |o: &Value, k: &str, at: &str| -> Result<f64, String> {
            o.get(k).and_then(Value::as_f64).ok_or_else(|| {
                format!(
                    "{origin}: `{at}` = {}: expected a number",
                    o.get(k).map_or("(missing)".to_string(), Value::to_string)
                )
            })
        };
        let k = num(&v, "k", "k")?;
        let amplitude = num(&v, "symmetry_amplitude", "symmetry_amplitude")?;
        if !(amplitude.is_finite() && amplitude > 0.0) {
            return Err(format!(
                "{origin}: `symmetry_amplitude` = {amplitude}: expected the amplitude in m, above 0 (e.g. 0.002)"
            ));
        }
        let golden = v
            .get("golden")
            .and_then(Value::as_array)
            .map_or(Vec::new(), |a| a.iter().filter_map(|g| g.as_str().map(str::to_string)).collect());
        let obj = v
            .get("limits")
            .and_then(Value::as_object)
            .ok_or_else(|| format!("{origin}: `limits` is missing or not an object"))?;
        let mut limits = Vec::new();
        for (key, l) in obj {
            if !FIGURES.iter().any(|f| f.key == key) {
                let known: Vec<&str> = FIGURES.iter().map(|f| f.key).collect();
                return Err(format!("{origin}: `limits.{key}` is not a figure qc knows ({})", known.join(", ")));
            }
            let lo = num(l, "lo", &format!("limits.{key}.lo"))?;
            let hi = match l.get("hi") {
                None | Some(Value::Null) => f64::INFINITY,
                Some(h) => {
                    h.as_f64().ok_or_else(|| format!("{origin}: `limits.{key}.hi` = {h}: expected a number or null"))?
                }
            };
            if !(lo < hi) {
                return Err(format!("{origin}: `limits.{key}`: lo {lo} must be below hi {hi}"));
            }
            let mean =
                l.get("mean").and_then(Value::as_f64).unwrap_or(if hi.is_finite() { 0.5 * (lo + hi) } else { lo });
            let sd = l.get("sd").and_then(Value::as_f64).unwrap_or(f64::NAN);
            limits.push(Limit { key: key.clone(), lo, hi, mean, sd });
        }
        if limits.is_empty() {
            return Err(format!("{origin}: `limits` holds no figure: a unit would pass whatever it is"));
        }
        // In the figures' order.
        limits.sort_by_key(|l| FIGURES.iter().position(|f| f.key == l.key));
        let skipped = v.get("not_limited").and_then(Value::as_array).map_or(Vec::new(), |a| {
            a.iter()
                .filter_map(|s| Some((s.get("key")?.as_str()?.to_string(), s.get("why")?.as_str()?.to_string())))
                .collect()
        });
        Ok(Limits { k, amplitude, golden, limits, skipped })
    }
}

/// One figure of a unit against its limits.
#[derive(Clone, Debug, PartialEq)]
pub struct Check {
    pub key: String,
    /// NaN: not known from the unit's set.
    pub value: f64,
    pub lo: f64,
    pub hi: f64,
    pub pass: bool,
    /// Outside: the distance past the nearer limit in the golden units' sds (signed: + above).
    pub by_sd: f64,
    /// Outside: what it likely means.
    pub cause: String,
}

/// A unit's verdict.
#[derive(Clone, Debug, PartialEq)]
pub struct Verdict {
    pub unit: String,
    pub pass: bool,
    pub checks: Vec<Check>,
    /// What to do about it (the coil's offset), where the figures say.
    pub advice: Vec<String>,
}

impl Verdict {
    /// The figures outside their limits.
    pub fn failed(&self) -> impl Iterator<Item = &Check> {
        self.checks.iter().filter(|c| !c.pass)
    }

    pub fn to_json(&self) -> Value {
        json!({
            "format": "coilscope.qc-verdict/1",
            "unit": self.unit,
            "pass": self.pass,
            "checks": self.checks.iter().map(|c| json!({
                "key": c.key,
                "value": if c.value.is_finite() { json!(c.value) } else { Value::Null },
                "lo": c.lo,
                "hi": if c.hi.is_finite() { json!(c.hi) } else { Value::Null },
                "pass": c.pass,
                "by_sd": if c.pass || !c.by_sd.is_finite() { Value::Null } else { json!(c.by_sd) },
                "cause": c.cause,
            })).collect::<Vec<_>>(),
            "advice": self.advice,
        })
    }
}

/// The verdict on the unit `name` whose identified set is `p`: every figure with a limit
/// within it, or the unit fails, each figure outside named with what it likely means. A figure
/// the set cannot give (its measured range shorter than the symmetry points' amplitude) fails:
/// the unit must be tested again at a higher level.
pub fn test_unit(p: &Parameters, name: &str, limits: &Limits) -> Verdict {
    let values = figures(p, limits.amplitude);
    let mut checks = Vec::new();
    let mut advice = Vec::new();
    for l in &limits.limits {
        let Some(j) = FIGURES.iter().position(|f| f.key == l.key) else { continue };
        let f = &FIGURES[j];
        let value = values[j].unwrap_or(f64::NAN);
        let (pass, by_sd, cause) = if value.is_nan() && f.key == "Xmax" {
            // No limit inside the measured range: Xmax lies beyond the reach.
            let reach = p.x_range.map_or(0.0, |r| (-r[0]).min(r[1]));
            let pass = reach >= l.lo;
            (
                pass,
                f64::NAN,
                if pass {
                    String::new()
                } else {
                    format!("the test did not reach the lower limit ({:.2} mm): test at a higher level", l.lo * 1e3)
                },
            )
        } else if value.is_nan() {
            let reach = p.x_range.map_or(0.0, |r| (-r[0]).min(r[1]));
            let why = if reach > limits.amplitude {
                format!("{} has no symmetry point within the range at +-{:.2} mm: far off its centre (a large coil or spider offset)", if f.key == "Xsym_Bl" { "Bl(x)" } else { "Kms(x)" }, limits.amplitude * 1e3)
            } else {
                format!(
                    "not known from this test: its range does not reach +-{:.2} mm (test at a higher level)",
                    limits.amplitude * 1e3
                )
            };
            (false, f64::NAN, why)
        } else if value > l.hi {
            (false, (value - l.hi) / l.sd, f.high.to_string())
        } else if value < l.lo {
            (false, (value - l.lo) / l.sd, f.low.to_string())
        } else {
            (true, 0.0, String::new())
        };
        if !pass && f.key == "Xsym_Bl" && value.is_finite() {
            // Bl(x) of a coil resting d out is the centred curve seen from -d: its symmetry
            // point moves by -d.
            let d = l.mean - value;
            advice.push(format!(
                "Bl(x) is symmetric about {:+.2} mm (the golden units about {:+.2} mm): the coil rests {:.2} mm {} of where theirs does; move it {:.2} mm {}",
                value * 1e3,
                l.mean * 1e3,
                d.abs() * 1e3,
                if d > 0.0 { "out" } else { "in" },
                d.abs() * 1e3,
                if d > 0.0 { "in (towards the back plate)" } else { "out (away from the back plate)" }
            ));
        }
        checks.push(Check { key: l.key.clone(), value, lo: l.lo, hi: l.hi, pass, by_sd, cause });
    }
    let pass = checks.iter().all(|c| c.pass);
    Verdict { unit: name.to_string(), pass, checks, advice }
}

/// A production station at work: a run in the database whose rows are the units it tests.
pub struct Station {
    store: coilscope_db::Store,
    limits: Limits,
    started: std::time::Instant,
    pub passed: usize,
    pub failed: usize,
}

impl Station {
    /// Start station `name`'s run in `target`, testing against `limits` (read from
    /// `limits_origin`, which the run's options name).
    pub fn open(
        target: &coilscope_db::Target,
        name: &str,
        limits: Limits,
        limits_origin: &str,
    ) -> Result<Station, String> {
        let options = json!({"limits": limits_origin, "amplitude": limits.amplitude, "k": limits.k});
        let store = coilscope_db::Store::create(target, &format!("qc station {name}"), &options)?;
        Ok(Station { store, limits, started: std::time::Instant::now(), passed: 0, failed: 0 })
    }

    /// The station's run in the database.
    pub fn run(&self) -> i64 {
        self.store.run
    }

    /// Judge unit `unit_id` (its set `p`, whose measurement is `trusted` or not) and write it
    /// to the database. A unit whose measurement is not trustworthy fails: it must be
    /// measured again.
    pub fn test(&mut self, unit_id: &str, p: &Parameters, trusted: bool) -> Result<Verdict, String> {
        let mut v = test_unit(p, unit_id, &self.limits);
        if !trusted {
            v.pass = false;
            v.advice.push(
                "its measurement is not trustworthy (fit.trustworthy false): measure it again before judging it".into(),
            );
        }
        self.store.record_unit(unit_id, v.pass, &p.to_json_value(), &v.to_json())?;
        if v.pass {
            self.passed += 1;
        } else {
            self.failed += 1;
        }
        Ok(v)
    }

    /// Close the station's run.
    pub fn finish(mut self) -> Result<(), String> {
        let seconds = self.started.elapsed().as_secs_f64();
        let summary = json!({"passed": self.passed, "failed": self.failed});
        self.store.finish(seconds, "finished", Some(&summary))
    }
}

/// A unit's set from its short record, as a station takes it (`qc test UNIT.wav --mms KG`):
/// identified as `identify` does with `req`, its reached range as the set's `x_range`; and
/// whether the fit is trustworthy.
pub fn unit_from_record(
    rec: &mut coilscope_io::Recording,
    req: &crate::identify::IdentifyRequest,
) -> Result<(Parameters, bool), String> {
    let done = crate::identify::identify_record(rec, req, |_| {})?;
    let trusted = done.trustworthy();
    Ok((Parameters { x_range: Some(done.fit.x_range), ..done.fit.params }, trusted))
}

/// The units tested into a database (of one station's run, or all), as `(unit id, set)` in
/// the order they were tested.
pub fn lot(target: &coilscope_db::Target, run: Option<i64>) -> Result<Vec<(String, Parameters)>, String> {
    let rows = coilscope_db::read_units(target, &coilscope_db::UnitFilter { run, unit_id: None })?;
    rows.into_iter().map(|r| unit_set(target, &r).map(|p| (r.unit_id, p))).collect()
}

fn unit_set(target: &coilscope_db::Target, r: &coilscope_db::UnitRow) -> Result<Parameters, String> {
    Parameters::from_json_str(&r.parameters, &format!("{} run {} unit {} ({})", target.name(), r.run, r.seq, r.unit_id))
        .map_err(|e| e.to_string())
}

/// One test of a unit in its history.
#[derive(Clone, Debug)]
pub struct Visit {
    /// When (seconds since the Unix epoch), on which run.
    pub tested: f64,
    pub run: i64,
    pub pass: bool,
    /// Its figures ([`FIGURES`]) at the limits' amplitude.
    pub figures: Vec<Option<f64>>,
}

/// Every test of unit `unit_id` in the database, in time order, with its figures at
/// `amplitude` (the limits'): how the unit drifts over its life.
pub fn history(target: &coilscope_db::Target, unit_id: &str, amplitude: f64) -> Result<Vec<Visit>, String> {
    let rows =
        coilscope_db::read_units(target, &coilscope_db::UnitFilter { run: None, unit_id: Some(unit_id.into()) })?;
    rows.iter()
        .map(|r| {
            let p = unit_set(target, r)?;
            Ok(Visit { tested: r.tested, run: r.run, pass: r.pass, figures: figures(&p, amplitude) })
        })
        .collect()
}

/// Each limited figure's drift over a unit's history: its last known value less its first,
/// in the limits' sds (NaN where it is not known at two tests).
pub fn drift(visits: &[Visit], limits: &Limits) -> Vec<(String, f64)> {
    limits
        .limits
        .iter()
        .filter_map(|l| {
            let j = FIGURES.iter().position(|f| f.key == l.key)?;
            let known: Vec<f64> = visits.iter().filter_map(|v| v.figures[j]).filter(|x| x.is_finite()).collect();
            let d = match (known.first(), known.last()) {
                (Some(a), Some(b)) if known.len() >= 2 && l.sd > 0.0 => (b - a) / l.sd,
                _ => f64::NAN,
            };
            Some((l.key.clone(), d))
        })
        .collect()
}

/// A figure's capability over a lot.
#[derive(Clone, Debug, PartialEq)]
pub struct Capability {
    pub key: String,
    /// Units with the figure known.
    pub n: usize,
    pub mean: f64,
    pub sd: f64,
    /// `min(hi - mean, mean - lo) / (3 sd)` (the lower side alone for a lower limit); NaN
    /// below 2 units.
    pub cpk: f64,
    /// Units outside the limits.
    pub outside: usize,
    /// Units whose figure their set cannot give (its range too short).
    pub unknown: usize,
}

/// Each limited figure's capability over the lot `units`.
pub fn capability(units: &[Parameters], limits: &Limits) -> Vec<Capability> {
    let rows: Vec<Vec<Option<f64>>> = units.iter().map(|p| figures(p, limits.amplitude)).collect();
    limits
        .limits
        .iter()
        .filter_map(|l| {
            let j = FIGURES.iter().position(|f| f.key == l.key)?;
            let v: Vec<f64> = rows.iter().filter_map(|r| r[j]).filter(|x| x.is_finite()).collect();
            let (mean, sd) = if v.is_empty() { (f64::NAN, f64::NAN) } else { mean_sd(&v) };
            let cpk = if v.len() >= 2 { (l.hi - mean).min(mean - l.lo) / (3.0 * sd) } else { f64::NAN };
            let outside = v.iter().filter(|x| !(**x >= l.lo && **x <= l.hi)).count();
            Some(Capability { key: l.key.clone(), n: v.len(), mean, sd, cpk, outside, unknown: rows.len() - v.len() })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use coilscope_core::production::{unit, Fault, Spread};

    fn line(n: usize, seed: u64) -> (Parameters, Vec<(String, Parameters)>) {
        let g = coilscope_core::embedded_driver("sb17cac35-4").unwrap();
        let units =
            (0..n as u64).map(|k| (format!("golden {k}"), unit(&g, &Spread::default(), None, seed + k))).collect();
        (g, units)
    }

    #[test]
    fn a_limits_file_round_trips_and_bad_ones_are_named() {
        let (_, golden) = line(8, 1);
        let l = learn(&golden, 3.0).unwrap();
        let back = Limits::from_json(&l.to_json().to_string(), "limits.json").unwrap();
        // Numbers come back within a unit in the last place (serde_json parses fast, not
        // exactly).
        let close = |a: f64, b: f64| a == b || (a - b).abs() <= 4.0 * f64::EPSILON * a.abs().max(b.abs());
        assert_eq!((back.k, &back.golden, &back.skipped), (l.k, &l.golden, &l.skipped));
        assert!(close(back.amplitude, l.amplitude));
        assert_eq!(back.limits.len(), l.limits.len());
        for (a, b) in back.limits.iter().zip(&l.limits) {
            assert!(
                a.key == b.key && close(a.lo, b.lo) && close(a.hi, b.hi) && close(a.mean, b.mean) && close(a.sd, b.sd),
                "{a:?} {b:?}"
            );
        }
        let mut v = l.to_json();
        v["symmetry_amplitude"] = json!(0.0);
        assert!(Limits::from_json(&v.to_string(), "limits.json").unwrap_err().contains("`symmetry_amplitude` = 0"));
        let mut v = l.to_json();
        v["limits"] = json!({});
        assert!(Limits::from_json(&v.to_string(), "limits.json").unwrap_err().contains("no figure"));
        let copies: Vec<(String, Parameters)> = (0..5).map(|k| (format!("copy {k}"), golden[0].1.clone())).collect();
        assert!(learn(&copies, 3.0).unwrap_err().contains("copies"));
        let mut v = l.to_json();
        v["limits"]["Kms"] = json!({"lo": 1.0, "hi": 2.0});
        let e = Limits::from_json(&v.to_string(), "limits.json").unwrap_err();
        assert!(e.contains("limits.json") && e.contains("`limits.Kms`") && e.contains("Kms(0)"), "{e}");
        let mut v = l.to_json();
        v["limits"]["Re"]["hi"] = json!(0.0);
        assert!(Limits::from_json(&v.to_string(), "limits.json").unwrap_err().contains("below hi"));
        assert!(learn(&golden[..3], 3.0).unwrap_err().contains("at least 5"));
    }

    #[test]
    fn each_fault_fails_its_unit_and_is_named_with_the_coils_way_back() {
        let (g, golden) = line(40, 100);
        let l = learn(&golden, 4.0).unwrap();
        let s = Spread::default();
        for (fault, cause) in [
            (Fault::CoilOffset(0.5e-3), "coil offset"),
            (Fault::StiffSpider(1.3), "stiff suspension"),
            (Fault::RubbingCoil(2.0), "rubbing coil"),
        ] {
            let p = unit(&g, &s, Some(fault), 7);
            let v = test_unit(&p, fault.name(), &l);
            assert!(!v.pass, "{}: passed", fault.name());
            let c = v.checks.iter().find(|c| c.key == fault.figure()).unwrap();
            assert!(!c.pass && c.cause.contains(cause), "{}: {c:?}", fault.name());
            if let Fault::CoilOffset(d) = fault {
                // The way back is the offset (within the line's own spread of the coil).
                let a = v.advice.join("; ");
                let mean = l.limits.iter().find(|l| l.key == "Xsym_Bl").unwrap().mean;
                assert!((mean - c.value - d).abs() < 3.0 * s.coil_sd + 0.02e-3, "{a}");
                assert!(
                    a.contains("mm out of where theirs does; move it") && a.contains("in (towards the back plate)"),
                    "{a}"
                );
            }
        }
        // A good unit of the same line passes (4 sd: about 1 in 16000 per figure fails).
        let good = unit(&g, &s, None, 7);
        let v = test_unit(&good, "good", &l);
        assert!(v.pass, "{:?}", v.failed().collect::<Vec<_>>());
    }
}

//! The production line's pages: a lot's statistics (per figure its histogram against the
//! limits and its control chart, unit by unit, with Cpk), and a unit's history (each figure
//! at every test, over time, against the limits).
//!
//! The figures and limits come from `coilscope_workflow::qc`; this module lays them out.

use crate::chart::Chart;
use crate::{page_with_source, sig, Builder, Report};
use std::fmt::Write as _;

/// One figure over a lot (or over a unit's tests), in its display unit.
#[derive(Clone, Debug)]
pub struct FigureSeries {
    /// The figure's key (`Re`, `Bl(0)`, `Xsym_Bl`, ...).
    pub key: String,
    /// Its display unit (`ohm`, `mm`, ...): values, limits and mean are in it.
    pub unit: String,
    /// One value per unit (or test), in test order; `None` where the set cannot give it.
    pub values: Vec<Option<f64>>,
    /// The limits (`hi` infinite: a lower limit only) and the golden units' mean.
    pub lo: f64,
    pub hi: f64,
    pub mean: f64,
    /// A lot's capability (`coilscope_workflow::qc::capability`), in the display unit.
    pub capability: Option<LotStats>,
    /// A unit's drift from its first test to its last, in the line's sds.
    pub drift_sd: Option<f64>,
}

/// A figure's capability over a lot, as `coilscope_workflow::qc::capability` gives it.
#[derive(Clone, Copy, Debug)]
pub struct LotStats {
    pub n: usize,
    pub mean: f64,
    pub sd: f64,
    pub cpk: f64,
    pub outside: usize,
}

/// What a lot's or a unit's page is made from.
#[derive(Clone, Debug)]
pub struct LotInput {
    pub title: String,
    /// Where the data came from (the database, the result files), for the page's header.
    pub source: String,
    /// The units' (or the tests') names, in order.
    pub units: Vec<String>,
    /// With a unit's history: when each test was (seconds since the Unix epoch); the control
    /// charts are then drawn over time, in days since the first test.
    pub tested: Option<Vec<f64>>,
    pub figures: Vec<FigureSeries>,
}

/// A chart's id from a figure's key (`Bl(0)` -> `bl-0`).
fn slug(key: &str) -> String {
    let s: String = key.chars().map(|c| if c.is_ascii_alphanumeric() { c.to_ascii_lowercase() } else { '-' }).collect();
    s.split('-').filter(|p| !p.is_empty()).collect::<Vec<_>>().join("-")
}

/// The histogram of `values` over `bins` equal bins spanning them and the limits, as the
/// outline of its bars: `(points, bin width)`.
pub fn histogram(values: &[f64], lo: f64, hi: f64, bins: usize) -> (Vec<(f64, f64)>, f64) {
    let mut a = values.iter().copied().fold(f64::INFINITY, f64::min);
    let mut b = values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    for l in [lo, hi] {
        if l.is_finite() {
            a = a.min(l);
            b = b.max(l);
        }
    }
    if !(b > a) {
        let w = if a.is_finite() && a != 0.0 { a.abs() * 1e-3 } else { 1.0 };
        (a, b) = (a - w, a + w);
    }
    let pad = 0.05 * (b - a);
    let (a, b) = (a - pad, b + pad);
    let w = (b - a) / bins as f64;
    let mut counts = vec![0usize; bins];
    for v in values {
        let k = (((v - a) / w).floor().max(0.0) as usize).min(bins - 1);
        counts[k] += 1;
    }
    let mut pts = vec![(a, 0.0)];
    for (k, c) in counts.iter().enumerate() {
        let x0 = a + k as f64 * w;
        pts.push((x0, *c as f64));
        pts.push((x0 + w, *c as f64));
    }
    pts.push((b, 0.0));
    (pts, w)
}

/// The page of a lot (or of a unit's history).
pub fn lot_report(input: &LotInput) -> Result<Report, String> {
    let mut b = Builder { html: String::new(), charts: vec![], warnings: vec![] };
    let history = input.tested.as_ref();
    let n_units = input.units.len();
    let x_of = |k: usize| -> f64 {
        match history {
            Some(t) => (t[k] - t[0]) / 86400.0,
            None => (k + 1) as f64,
        }
    };
    let x_label = if history.is_some() { "days since the first test" } else { "unit (in test order)" };
    let x_end = if n_units == 0 { 1.0 } else { x_of(n_units - 1).max(x_of(0) + 1e-9) };
    b.section(
        if history.is_some() { "Figures at each test" } else { "Capability" },
        if history.is_some() {
            "Each figure at every test of the unit, and how far it moved from its first test in the line's sds."
        } else {
            "Per figure: the units whose set gives it (n), their mean and sd, Cpk = min(hi - mean, mean - lo) / (3 sd) (the lower side alone for a lower limit), and the units outside the limits."
        },
    );
    let mut rows = Vec::new();
    let num = |v: f64| if v.is_finite() { sig(v) } else { "-".into() };
    for f in &input.figures {
        let hi = if f.hi.is_finite() { sig(f.hi) } else { "-".into() };
        if history.is_some() {
            let tests = f.values.iter().filter(|v| v.is_some_and(f64::is_finite)).count();
            let outside = f.values.iter().flatten().filter(|x| !(**x >= f.lo && **x <= f.hi)).count();
            let drift = f.drift_sd.filter(|d| d.is_finite()).map_or("-".into(), |d| format!("{d:+.2}"));
            rows.push(vec![
                f.key.clone(),
                f.unit.clone(),
                format!("{tests}"),
                sig(f.lo),
                hi,
                drift,
                format!("{outside}"),
            ]);
        } else if let Some(c) = f.capability {
            let cpk = if c.cpk.is_finite() { format!("{:.2}", c.cpk) } else { "-".into() };
            rows.push(vec![
                f.key.clone(),
                f.unit.clone(),
                format!("{}", c.n),
                num(c.mean),
                num(c.sd),
                sig(f.lo),
                hi,
                cpk,
                format!("{}", c.outside),
            ]);
        }
    }
    if history.is_some() {
        b.table(&["figure", "unit", "tests", "lo", "hi", "drift (line sds)", "tests outside"], &rows);
    } else {
        b.table(&["figure", "unit", "n", "mean", "sd", "lo", "hi", "Cpk", "outside"], &rows);
    }
    let mut csv = String::from(if history.is_some() { "test,tested_s" } else { "unit" });
    for f in &input.figures {
        let _ = write!(csv, ",{} ({})", f.key, f.unit);
    }
    csv.push('\n');
    for (k, u) in input.units.iter().enumerate() {
        csv.push_str(&u.replace(',', ";"));
        if let Some(t) = history {
            let _ = write!(csv, ",{:.3}", t[k]);
        }
        for f in &input.figures {
            match f.values.get(k).copied().flatten() {
                Some(v) => {
                    let _ = write!(csv, ",{v}");
                }
                None => csv.push(','),
            }
        }
        csv.push('\n');
    }
    for f in &input.figures {
        let id = slug(&f.key);
        let known: Vec<f64> = f.values.iter().flatten().copied().filter(|x| x.is_finite()).collect();
        let limits_text = if f.hi.is_finite() {
            format!("limits {} .. {} {}", sig(f.lo), sig(f.hi), f.unit)
        } else {
            format!("lower limit {} {}", sig(f.lo), f.unit)
        };
        b.section(&f.key, "");
        if history.is_none() {
            let (pts, _) = histogram(&known, f.lo, f.hi, 24);
            let top = pts.iter().map(|p| p.1).fold(0.0, f64::max).max(1.0);
            let mut c = Chart::new(
                &format!("qc-hist-{id}"),
                &format!("{} over the lot", f.key),
                &format!("{} ({})", f.key, f.unit),
                "units",
            )
            .line("units per bin", pts);
            c = c.dashed("lower limit", vec![(f.lo, 0.0), (f.lo, top)]);
            if f.hi.is_finite() {
                c = c.dashed("upper limit", vec![(f.hi, 0.0), (f.hi, top)]);
            }
            let caption = match f.capability {
                Some(c) => format!(
                    "{} units: mean {} {u}, sd {} {u}, Cpk {}; {} outside the {limits_text}.",
                    c.n,
                    num(c.mean),
                    num(c.sd),
                    if c.cpk.is_finite() { format!("{:.2}", c.cpk) } else { "-".into() },
                    c.outside,
                    u = f.unit
                ),
                None => format!("{} units against the {limits_text}.", known.len()),
            };
            b.chart(c, &caption)?;
        }
        let points: Vec<(f64, f64)> = f
            .values
            .iter()
            .enumerate()
            .filter_map(|(k, v)| v.filter(|x| x.is_finite()).map(|v| (x_of(k), v)))
            .collect();
        let span = |v: f64| vec![(x_of(0), v), (x_end, v)];
        let mut c = Chart::new(
            &format!("qc-{}-{id}", if history.is_some() { "history" } else { "control" }),
            &format!("{} {}", f.key, if history.is_some() { "at each test" } else { "unit by unit" }),
            x_label,
            &format!("{} ({})", f.key, f.unit),
        )
        .line(if history.is_some() { "at each test" } else { "each unit" }, points)
        .dashed("golden mean", span(f.mean))
        .dashed("lower limit", span(f.lo));
        if f.hi.is_finite() {
            c = c.dashed("upper limit", span(f.hi));
        }
        let unknown = f.values.iter().filter(|v| !v.is_some_and(f64::is_finite)).count();
        b.chart(
            c,
            &format!(
                "{} against the golden units' mean and the {limits_text}{}.",
                if history.is_some() { "Each test" } else { "Each unit in test order (a control chart)" },
                if unknown > 0 {
                    format!("; {unknown} not known from their sets (range too short)")
                } else {
                    String::new()
                }
            ),
        )?;
    }
    let csv_name = if history.is_some() { "history.csv" } else { "lot.csv" };
    let html = page_with_source(&input.title, &input.source, &b.html);
    Ok(Report {
        html,
        charts: b.charts,
        csv: vec![(csv_name.to_string(), csv)],
        volts: f64::NAN,
        volterra_divergence: None,
        warnings: b.warnings,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_histogram_counts_every_value_once_and_spans_the_limits() {
        let v: Vec<f64> = (0..200).map(|k| 3.0 + 0.01 * ((k * 37 % 101) as f64 - 50.0)).collect();
        let (pts, w) = histogram(&v, 2.0, 4.5, 20);
        // Each bar is two points at its count.
        let total: f64 = pts[1..pts.len() - 1].chunks(2).map(|c| c[0].1).sum();
        assert_eq!(total, 200.0);
        assert!(pts[0].0 < 2.0 && pts[pts.len() - 1].0 > 4.5);
        assert!((pts[pts.len() - 1].0 - pts[0].0 - 20.0 * w).abs() < 1e-9);
    }
}

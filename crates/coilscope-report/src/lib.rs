//! # coilscope-report
//!
//! One self-contained HTML page per result (no network, no script libraries): the nonlinear
//! curves Bl(x), Kms(x), Cms(x), Le(x) with their uncertainty bands (+-2 sd) and the reached
//! range marked, the small-signal impedance, the measurement's time series (excursion and
//! voice-coil temperature) when a run database is attached, the predicted distortion with
//! each nonlinearity's contribution and the Volterra comparison, and tables of parameters,
//! power-series coefficients, limits and diagnosis.
//!
//! A production line's pages ([`lot`]): a lot's histograms and control charts per figure
//! with Cpk, and a unit's history.
//!
//! Every plot is also written as PNG, and the curves as CSV, into `<stem>_files/` beside the
//! HTML file. Every number comes from one function of `coilscope-core` or
//! `coilscope-analysis`; this crate only lays them out.

pub mod chart;
pub mod lot;

use chart::Chart;
use coilscope_analysis::diagnosis::diagnose;
use coilscope_analysis::distortion::{
    self, analyse, divergence_level, intermod, level_for_excursion, level_sweep, log_frequencies, multitone, Analysis,
    Nonlinearity, Output, SteadyOptions,
};
use coilscope_analysis::{db, volterra};
use coilscope_core::limits::Thresholds;
use coilscope_core::result::ResultFile;
use coilscope_core::small_signal::{impedance, thiele_small};
use coilscope_core::Parameters;
use serde_json::Value;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// The measurement's time series, one row per stored state (from the run database).
#[derive(Clone, Debug, Default)]
pub struct TimeSeries {
    pub t: Vec<f64>,
    pub x_min: Vec<f64>,
    pub x_max: Vec<f64>,
    pub dtv: Vec<f64>,
    /// The drive level: the terminal voltage's RMS over each block (V).
    pub volts: Vec<f64>,
    /// The power into the voice coil's resistance over each block, `Re(t) i_rms^2` (W; NaN
    /// before the first estimate of Re).
    pub power: Vec<f64>,
}

/// What a report is made from.
#[derive(Clone, Debug)]
pub struct ReportInput {
    pub title: String,
    pub params: Parameters,
    /// The range the measurement reached (m); the curves are drawn and limits searched in it.
    pub range: [f64; 2],
    /// The result file (`coilscope.result/1`), when the report is of a result.
    pub result: Option<ResultFile>,
    pub states: Option<TimeSeries>,
    /// Another result of the same driver whose curves are drawn over this one's (dashed):
    /// the quasi-static and the dynamic measurement side by side (seed paper 3.2.1).
    pub compare: Option<Box<ReportInput>>,
}

/// Report options.
#[derive(Clone, Copy, Debug)]
pub struct ReportOptions {
    pub thresholds: Thresholds,
    /// Voice-coil rise limit for the thermal power handling (K).
    pub dt_max: f64,
    /// Level of the distortion analysis (V RMS); default: the linear model's peak excursion
    /// at 70 % of the reach over the analysed band.
    pub volts: Option<f64>,
    /// PNG size in pixels.
    pub png_size: (u32, u32),
}

impl Default for ReportOptions {
    fn default() -> Self {
        ReportOptions { thresholds: Thresholds::default(), dt_max: 50.0, volts: None, png_size: (960, 560) }
    }
}

/// A built report: the HTML text, its charts (for PNG) and CSV files `(name, text)`.
pub struct Report {
    pub html: String,
    pub charts: Vec<Chart>,
    pub csv: Vec<(String, String)>,
    /// The distortion analysis level (V RMS) and where Volterra diverged (V), for the caller.
    pub volts: f64,
    pub volterra_divergence: Option<f64>,
    /// What the report could not show, one sentence each (a chart without a finite value to
    /// draw: its figure says so instead); the caller prints them as warnings.
    pub warnings: Vec<String>,
}

pub const SVG_SIZE: (u32, u32) = (760, 440);

fn esc(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

/// Four significant digits, without an exponent between 1e-3 and 1e6.
fn sig(v: f64) -> String {
    let a = v.abs();
    if v == 0.0 || !v.is_finite() {
        return format!("{v}");
    }
    if !(1e-3..1e6).contains(&a) {
        return format!("{v:.3e}");
    }
    let digits = (3 - a.log10().floor() as i32).max(0) as usize;
    format!("{v:.digits$}")
}

fn fmt(v: f64) -> String {
    let a = v.abs();
    if v == 0.0 {
        "0".into()
    } else if !(1e-3..1e5).contains(&a) {
        format!("{v:.4e}")
    } else {
        format!("{v:.4}")
    }
}

fn mm(v: Option<f64>) -> String {
    v.map(|x| format!("{:.2} mm", x * 1e3)).unwrap_or_else(|| "beyond the reach".into())
}

/// `(x, value, sd)` of a band from the result's `uncertainty.<key>_band` (finite points only).
fn band_of(result: Option<&ResultFile>, key: &str) -> Option<Vec<(f64, f64, f64)>> {
    let b = result?.uncertainty.band(key)?;
    (b.x.len() == b.value.len() && b.value.len() == b.sd.len()).then(|| {
        b.x.iter()
            .zip(&b.value)
            .zip(&b.sd)
            .map(|((&x, &v), &s)| (x, v, s))
            .filter(|(x, v, s)| x.is_finite() && v.is_finite() && s.is_finite())
            .collect()
    })
}

/// dB for plots, floored at -160 dB (a linear set has no distortion at all: -inf).
fn dbp(r: f64) -> f64 {
    db(r).max(-160.0)
}

/// The lowest distortion level the charts show (dB re the fundamental): what a measurement
/// through a good 24-bit card can resolve; below it a prediction is drawn on the floor.
const DB_FLOOR: f64 = -100.0;

fn grid(range: [f64; 2], n: usize) -> Vec<f64> {
    (0..=n).map(|k| range[0] + (range[1] - range[0]) * k as f64 / n as f64).collect()
}

struct Builder {
    html: String,
    charts: Vec<Chart>,
    warnings: Vec<String>,
}

impl Builder {
    fn section(&mut self, title: &str, intro: &str) {
        let _ = write!(self.html, "<h2>{}</h2>", esc(title));
        if !intro.is_empty() {
            let _ = write!(self.html, "<p class=\"note\">{}</p>", esc(intro));
        }
    }
    /// The chart's figure; a chart without a finite value to draw (a degenerate result: a
    /// curve that is NaN, a ratio 0/0) gets a figure that says so, and a warning, so that the
    /// rest of the report is still written.
    fn chart(&mut self, c: Chart, caption: &str) -> Result<(), String> {
        if !c.has_finite_data() {
            let why =
                format!("chart {}: no finite value to draw (the result is degenerate there: see its warnings)", c.id);
            let _ = write!(self.html, "<figure class=\"plot\" id=\"plot-{id}\" data-series=\"0\"><p class=\"note\">{t}: {w}</p><figcaption>{cap}</figcaption></figure>", id = esc(&c.id), t = esc(&c.title), w = esc(&why), cap = esc(caption));
            self.warnings.push(why);
            return Ok(());
        }
        let svg = c.svg(SVG_SIZE)?;
        let svg = svg.trim_start_matches("<?xml version=\"1.0\" encoding=\"UTF-8\"?>").trim();
        let _ = write!(self.html, "<figure class=\"plot\" id=\"plot-{id}\" data-series=\"{n}\">{svg}<figcaption>{cap} <a href=\"#\" data-png=\"{id}.png\">PNG</a></figcaption></figure>", id = esc(&c.id), n = c.series.len(), cap = esc(caption));
        self.charts.push(c);
        Ok(())
    }
    fn table(&mut self, head: &[&str], rows: &[Vec<String>]) {
        self.html.push_str("<table><tr>");
        for h in head {
            let _ = write!(self.html, "<th>{}</th>", esc(h));
        }
        self.html.push_str("</tr>");
        for r in rows {
            self.html.push_str("<tr>");
            for c in r {
                let _ = write!(self.html, "<td>{}</td>", esc(c));
            }
            self.html.push_str("</tr>");
        }
        self.html.push_str("</table>");
    }
}

/// The curve chart of one x-dependent parameter: value over the range, with +-2 sd band.
fn curve_chart(
    id: &str,
    title: &str,
    unit: &str,
    f: &dyn Fn(f64) -> f64,
    band: Option<Vec<(f64, f64, f64)>>,
    range: [f64; 2],
    limit: Option<(f64, &str)>,
    overlay: Option<(&str, Vec<(f64, f64)>)>,
) -> Chart {
    let xs = grid(range, 120);
    let mut c =
        Chart::new(id, title, "x (mm), + = coil out", unit).line(title, xs.iter().map(|&x| (x * 1e3, f(x))).collect());
    if let Some(b) = band {
        c = c.band(
            b.iter().map(|(x, v, s)| (x * 1e3, v - 2.0 * s)).collect(),
            b.iter().map(|(x, v, s)| (x * 1e3, v + 2.0 * s)).collect(),
        );
    }
    if let Some((name, pts)) = overlay {
        c = c.dashed(name, pts);
    }
    c = c.marker(range[0] * 1e3, "x min reached").marker(range[1] * 1e3, "x max reached");
    if let Some((x, label)) = limit {
        c = c.marker(-x * 1e3, label).marker(x * 1e3, label);
    }
    c
}

/// The comparison of two results of one driver (`report --compare`): the largest
/// difference of each curve over the range both reached, and, where one of them is
/// quasi-static, what the seed paper (3.2.1) says to look for: a creeping suspension's
/// static stiffness below its dynamic one, and the rest position after a large offset.
fn compare_section(b: &mut Builder, csv: &mut Vec<(String, String)>, a: &ReportInput, c: &ReportInput) {
    let (la, lc) = (method_label(a), method_label(c));
    b.section(&format!("{la} and {lc} compared"), &format!("Solid: this report's {la} curves; dashed: the {lc} result's. Differences over the range both reached, relative to this result's value at rest."));
    let lo = a.range[0].max(c.range[0]);
    let hi = a.range[1].min(c.range[1]);
    let mut rows = vec![];
    let mut text = String::from("curve,max_difference_rel,at_x_mm,value_at_rest,other_at_rest\n");
    if hi > lo {
        for (name, f, g) in [
            ("Bl", &a.params.bl, &c.params.bl),
            ("Kms", &a.params.kms, &c.params.kms),
            ("Le", &a.params.le, &c.params.le),
        ] {
            let (worst, at) = grid([lo, hi], 200)
                .into_iter()
                .map(|x| ((f.eval(x) - g.eval(x)).abs() / f.eval(0.0).abs(), x))
                .fold((0.0, 0.0), |m, v| if v.0 > m.0 { v } else { m });
            rows.push(vec![
                name.to_string(),
                format!("{:.2} % at {:+.2} mm", 100.0 * worst, at * 1e3),
                format!("{:.4} / {:.4}", f.eval(0.0), g.eval(0.0)),
            ]);
            let _ = writeln!(text, "{name},{worst:.6},{:.4},{},{}", at * 1e3, f.eval(0.0), g.eval(0.0));
        }
    }
    b.table(&["curve", "largest difference (common range)", &format!("at rest: {la} / {lc}")], &rows);
    csv.push(("compare.csv".to_string(), text));
    // The quasi-static result's own record of the paper's two caveats.
    for (q, other) in [(a, c), (c, a)] {
        let Some(qs) = q.result.as_ref().filter(|r| r.kind == "quasi-static").and_then(|r| r.other.get("quasi_static"))
        else {
            continue;
        };
        let mut notes = vec![];
        let k_static = q.params.kms.eval(0.0);
        let k_other = other.params.kms.eval(0.0);
        if let Some(kd) = qs.get("k_dynamic_rest").and_then(|v| v.as_f64()) {
            notes.push(vec!["stiffness at rest: static (quasi-static fit)".into(), format!("{k_static:.1} N/m")]);
            notes.push(vec![
                "stiffness at rest: small signal at the rest point (dynamic, at the resonance)".into(),
                format!("{kd:.1} N/m ({:+.1} %)", 100.0 * (kd / k_static - 1.0)),
            ]);
        }
        notes.push(vec![
            format!("stiffness at rest: the {} result", method_label(other)),
            format!("{k_other:.1} N/m ({:+.1} %)", 100.0 * (k_other / k_static - 1.0)),
        ]);
        if let Some(d) = qs.get("rest_drift_m").and_then(|v| v.as_f64()).filter(|d| d.is_finite()) {
            notes.push(vec!["rest position 1.5 s after the largest offset".into(), format!("{:+.4} mm", d * 1e3)]);
        }
        if let Some(l) = other.params.creep.as_ref().map(|c| c.lambda) {
            notes.push(vec![
                format!("creep of the {} result", method_label(other)),
                format!("LOG lambda {l:.3}: the static stiffness is expected below the dynamic one"),
            ]);
        }
        b.html.push_str("<p>A suspension that creeps gives a static stiffness below the dynamic one (the stiffness relaxes under a held offset), and the rest position drifts after a large offset (seed paper 3.2.1): both measured here.</p>");
        b.table(&["quasi-static caveat", "value"], &notes);
    }
}

/// Build the report (runs the distortion analysis; about a second in release).
pub fn build(input: &ReportInput, opts: &ReportOptions) -> Result<Report, String> {
    opts.thresholds.validate()?;
    let p = &input.params;
    let range = input.range;
    if !(range[0] < 0.0 && range[1] > 0.0) {
        return Err(format!(
            "the reached range [{:.3}, {:.3}] mm must contain the rest position x = 0",
            range[0] * 1e3,
            range[1] * 1e3
        ));
    }
    let result = input.result.as_ref();
    let diag = diagnose(p, range, opts.thresholds, opts.dt_max);
    let ts = thiele_small(p);
    let mut b = Builder { html: String::new(), charts: vec![], warnings: vec![] };
    let mut csv = Vec::new();

    // --- Parameters ---------------------------------------------------------------------
    b.section("Parameters", "Values at rest (x = 0), in the units engineers read them in; ± one standard deviation where the result carries it. Small-signal figures from the linearised model at rest, their sds propagated from those of the values they come from (Re, Bl, Kms, Mms, Rms, creep's lambda, Sd, Le, R2), taken as independent.");
    // Every constant of the parameter schema the set has, and the functions of x at rest,
    // each in its display unit, with its sd: a number's own, a curve's band at rest.
    let sd_of = |key: &str| -> Option<f64> {
        let u = &result?.uncertainty;
        u.value(key).or_else(|| {
            let b = u.band(key)?;
            let k = (0..b.x.len()).min_by(|&i, &j| b.x[i].abs().total_cmp(&b.x[j].abs()))?;
            Some(b.sd[k]).filter(|s| s.is_finite())
        })
    };
    let pm = |sd: Option<f64>, factor: f64| {
        sd.filter(|s| *s > 0.0).map(|s| format!("± {}", sig(s * factor))).unwrap_or_default()
    };
    let mut rows: Vec<Vec<String>> = p
        .values_at_rest()
        .map(|(e, v)| vec![e.label(), sig(v * e.display.1), pm(sd_of(e.key), e.display.1), e.display.0.to_string()])
        .collect();
    // Thiele/Small and the derived figures (no sd of their own), at fs with creep's loss as
    // LPM and Speakerbench give them (`ThieleSmall`); the table's Rms above is the viscous one.
    let bl0 = p.bl.c[0];
    let qtp = total_q_with_eddy_losses(p);
    let d = derived_sds(p, &sd_of);
    for (k, v, sd, u) in [
        ("fs", ts.fs, d.fs, "Hz"),
        ("Qms", ts.qms, d.qms, ""),
        ("Qes", ts.qes, d.qes, ""),
        ("Qts", ts.qts, d.qts, ""),
        ("Qtp (with the eddy-current losses at fs)", qtp, d.qtp, ""),
        ("Cms", 1e3 * ts.cms, d.cms.map(|s| 1e3 * s), "mm/N"),
        ("Rms at fs (with creep's loss)", ts.rms_fs, d.rms_fs, "kg/s"),
        ("Res (Bl²/Rms at fs)", bl0 * bl0 / ts.rms_fs, d.res, "ohm"),
    ] {
        rows.push(vec![k.into(), sig(v), pm(sd, 1.0), u.into()]);
    }
    match ts.vas {
        Some(v) => rows.push(vec!["Vas".into(), sig(v * 1e3), pm(d.vas, 1e3), "l".into()]),
        None => rows.push(vec!["Vas".into(), "—".into(), String::new(), "(needs Sd)".into()]),
    }
    b.table(&["parameter", "value", "sd", "unit"], &rows);
    let mut series_rows = vec![];
    let funcs: Vec<(String, &coilscope_core::Poly)> = coilscope_core::schema::ENTRIES
        .iter()
        .filter_map(|e| match (p.get(e.key), e.variable()) {
            (Some(coilscope_core::schema::Value::Series(f)), Some((var, var_unit))) => {
                Some((format!("{} ({}/{var_unit}^j, {var})", e.key, e.unit), f))
            }
            _ => None,
        })
        .collect();
    let order = funcs.iter().map(|f| f.1.c.len()).max().unwrap_or(1);
    for (name, f) in &funcs {
        let mut r = vec![name.clone()];
        r.extend((0..order).map(|j| f.c.get(j).map(|&c| fmt(c)).unwrap_or_default()));
        series_rows.push(r);
    }
    let heads: Vec<String> =
        std::iter::once("power series".to_string()).chain((0..order).map(|j| format!("c{j}"))).collect();
    b.table(&heads.iter().map(|s| s.as_str()).collect::<Vec<_>>(), &series_rows);

    // A small-signal result (constant curves) gets no nonlinear sections: nothing in it
    // supports them.
    let nonlinear = [&p.bl, &p.kms, &p.le].iter().any(|f| f.c.iter().skip(1).any(|c| *c != 0.0));
    let th = opts.thresholds;
    let lim = &diag.limits;
    if nonlinear {
        // --- Curves ---------------------------------------------------------------------------
        b.section("Nonlinear parameters", "Solid: identified curve over the reached range; shaded: +-2 standard deviations (when the result carries them); dashed verticals: the reached range and the limits.");
        let bl_band = band_of(result, "Bl");
        let kms_band = band_of(result, "Kms");
        let le_band = band_of(result, "Le");
        let cms_band = kms_band.as_ref().map(|v| v.iter().map(|(x, k, s)| (*x, 1.0 / k, s / (k * k))).collect());
        let xbl_label = format!("XBl ({:.0} %)", th.bl * 100.0);
        let xc_label = format!("XC ({:.0} %)", th.cms * 100.0);
        let xl_label = format!("XL ({:.0} %)", th.le * 100.0);
        let cmp = input.compare.as_deref();
        let cmp_name = cmp.map(|c| {
            format!("{} ({})", method_label(c), c.result.as_ref().map_or(c.title.as_str(), |r| r.recording.as_str()))
        });
        let over = |g: &dyn Fn(&Parameters, f64) -> f64| -> Option<(&str, Vec<(f64, f64)>)> {
            cmp.map(|c| {
                (
                    cmp_name.as_deref().unwrap_or_default(),
                    grid(c.range, 120).into_iter().map(|x| (x * 1e3, g(&c.params, x))).collect(),
                )
            })
        };
        b.chart(
            curve_chart(
                "bl",
                "Bl(x)",
                "Bl (T m)",
                &|x| p.bl.eval(x),
                bl_band,
                range,
                lim.xbl.map(|v| (v, xbl_label.as_str())),
                over(&|q, x| q.bl.eval(x)),
            ),
            "Force factor.",
        )?;
        b.chart(
            curve_chart(
                "kms",
                "Kms(x)",
                "Kms (N/m)",
                &|x| p.kms.eval(x),
                kms_band,
                range,
                None,
                over(&|q, x| q.kms.eval(x)),
            ),
            "Secant stiffness of the suspension.",
        )?;
        b.chart(
            curve_chart(
                "cms",
                "Cms(x)",
                "Cms (mm/N)",
                &|x| 1e3 / p.kms.eval(x),
                cms_band.map(|v: Vec<(f64, f64, f64)>| v.into_iter().map(|(x, c, s)| (x, c * 1e3, s * 1e3)).collect()),
                range,
                lim.xc.map(|v| (v, xc_label.as_str())),
                over(&|q, x| 1e3 / q.kms.eval(x)),
            ),
            "Compliance 1/Kms(x).",
        )?;
        b.chart(
            curve_chart(
                "le",
                "Le(x)",
                "Le (mH)",
                &|x| 1e3 * p.le.eval(x),
                le_band.map(|v| v.into_iter().map(|(x, l, s)| (x, l * 1e3, s * 1e3)).collect()),
                range,
                lim.xl.map(|v| (v, xl_label.as_str())),
                over(&|q, x| 1e3 * q.le.eval(x)),
            ),
            "Voice-coil inductance; it should rise toward the back plate (x < 0).",
        )?;
        // Symmetry against amplitude (as LSI plots it): the offset that makes Bl(x) and Kms(x)
        // symmetric over +-x_peak, and the stiffness asymmetry Ak(x_peak).
        let a = (-range[0]).min(range[1]);
        let amps: Vec<f64> = (1..=19).map(|k| 0.05 * k as f64 * a).collect();
        let sym = |f: &coilscope_core::Poly| {
            amps.iter()
                .filter_map(|&amp| coilscope_core::limits::symmetry_point(f, amp, range).map(|s| (amp * 1e3, s * 1e3)))
                .collect::<Vec<_>>()
        };
        let ak: Vec<(f64, f64)> = amps
            .iter()
            .map(|&amp| {
                (amp * 1e3, 100.0 * (p.kms.eval(amp) - p.kms.eval(-amp)) / p.kms.eval(amp).max(p.kms.eval(-amp)))
            })
            .collect();
        let (bl_sym, kms_sym) = (sym(&p.bl), sym(&p.kms));
        if !bl_sym.is_empty() {
            b.chart(
            Chart::new("bl-symmetry", "Bl symmetry point against amplitude", "amplitude x_peak (mm)", "Xsym (mm), + = coil out").line("Xsym of Bl", bl_sym.clone()),
            "The rest-position offset that would make Bl(x) symmetric over +-x_peak (Bl(Xsym - x_peak) = Bl(Xsym + x_peak)). A coil off the gap's centre shows as an offset that stays the same over amplitude; an asymmetric field, as one that changes.",
        )?;
        }
        if !kms_sym.is_empty() {
            b.chart(
                Chart::new("kms-symmetry", "Kms symmetry point against amplitude", "amplitude x_peak (mm)", "offset (mm), + = coil out").line("Kms symmetry point", kms_sym.clone()),
                "The offset that would make Kms(x) symmetric over +-x_peak: where the suspension is centred at each amplitude.",
            )?;
        }
        b.chart(
            Chart::new("ak", "Stiffness asymmetry Ak against amplitude", "amplitude x_peak (mm)", "Ak (%)").line("Ak", ak.clone()),
            "Ak(x_peak) = (Kms(x_peak) - Kms(-x_peak)) / the larger of the two (IEC 62458): the suspension's asymmetry at each amplitude; it drives a DC displacement.",
        )?;
        let mut sc = String::from("x_peak_mm,Xsym_Bl_mm,Xsym_Kms_mm,Ak_percent\n");
        for (k, &amp) in amps.iter().enumerate() {
            let find = |v: &[(f64, f64)]| {
                v.iter().find(|(x, _)| (x - amp * 1e3).abs() < 1e-12).map_or(String::new(), |(_, s)| format!("{s:.5}"))
            };
            let _ = writeln!(sc, "{:.5},{},{},{:.4}", amp * 1e3, find(&bl_sym), find(&kms_sym), ak[k].1);
        }
        csv.push(("symmetry.csv".to_string(), sc));
        if let Some(c) = cmp {
            compare_section(&mut b, &mut csv, input, c);
        }
        let mut c = String::from("x_mm,Bl_Tm,Kms_N_per_m,Cms_mm_per_N,Le_mH\n");
        for x in grid(range, 100) {
            let _ = writeln!(
                c,
                "{:.5},{:.6},{:.4},{:.6},{:.6}",
                x * 1e3,
                p.bl.eval(x),
                p.kms.eval(x),
                1e3 / p.kms.eval(x),
                1e3 * p.le.eval(x)
            );
        }
        csv.push(("curves.csv".to_string(), c));
    } else {
        b.html.push_str("<p>This is a small-signal result: its Bl, Kms and Le are constants, so it has no nonlinear curves, displacement limits or distortion to show. Measure the large-signal parameters with <code>coilscope measure</code> or <code>coilscope identify</code>.</p>");
    }

    // --- Limits and diagnosis -------------------------------------------------------------
    b.section("Limits and diagnosis", "IEC 62458 / Klippel displacement limits over the reached range (thresholds as given), the Bl symmetry point, the polarity check and the thermal power handling.");
    let xmax = [(lim.xbl, "XBl"), (lim.xc, "XC"), (lim.xl, "XL")]
        .into_iter()
        .filter_map(|(v, n)| v.map(|v| (v, n)))
        .min_by(|a, b| a.0.total_cmp(&b.0));
    let mut rows = vec![
        vec![
            "Xmax = min(XBl, XC, XL)".into(),
            match xmax {
                Some((v, n)) => format!("{:.2} mm (limited by {n})", v * 1e3),
                None => {
                    format!("beyond the reached range (+-{:.2} mm): no limit reached", (-range[0]).min(range[1]) * 1e3)
                }
            },
        ],
        vec![format!("XBl (Bl {:.0} %)", th.bl * 100.0), mm(lim.xbl)],
        vec![format!("XC (Cms {:.0} %)", th.cms * 100.0), mm(lim.xc)],
        vec![format!("XL (Le {:.0} %)", th.le * 100.0), mm(lim.xl)],
        vec![
            "Xsym (Bl symmetry point)".into(),
            format!("{} at amplitude {:.2} mm", mm(lim.xsym), lim.xsym_amplitude * 1e3),
        ],
        vec!["Ak (stiffness asymmetry)".into(), format!("{:.1} %", lim.ak)],
        vec!["Bl rest-position shift".into(), diag.bl_shift_advice()],
        vec![
            "Polarity (Le asymmetry)".into(),
            format!(
                "{}: Le(-{:.2} mm) = {:.4} mH, Le(+{:.2} mm) = {:.4} mH",
                diag.polarity.verdict,
                diag.polarity.at * 1e3,
                diag.polarity.le_minus * 1e3,
                diag.polarity.at * 1e3,
                diag.polarity.le_plus * 1e3
            ),
        ],
    ];
    if !nonlinear {
        rows.clear();
    }
    if let (Some(th), Some(unc)) = (p.thermal.as_ref(), result.map(|r| &r.uncertainty)) {
        // A measured thermal model (a long `measure` run fits it): its values with their sds.
        let sd = |k: &str| unc.value(&format!("thermal.{k}"));
        if let (Some(a), Some(b), Some(c), Some(d)) = (sd("Rtv"), sd("Ctv"), sd("Rtm"), sd("Ctm")) {
            rows.push(vec![
                "Thermal model (fitted to this run's rise)".into(),
                format!(
                    "Rtv {:.3} ± {a:.3} K/W, Ctv {:.2} ± {b:.2} J/K, Rtm {:.3} ± {c:.3} K/W, Ctm {:.0} ± {d:.0} J/K",
                    th.rtv, th.ctv, th.rtm, th.ctm
                ),
            ]);
        }
    }
    if let Some(t) = &diag.thermal {
        rows.push(vec![
            format!("Continuous power in Re for +{:.0} K", t.dt_max),
            format!("{:.1} W (tau_v {:.1} s, tau_m {:.0} s)", t.p_max, t.tau_v, t.tau_m),
        ]);
        rows.push(vec![
            "Voltage at that limit, worst sine".into(),
            format!("{:.2} V RMS at {:.0} Hz", t.volts_sine, t.f_sine),
        ]);
        rows.push(vec![
            "Voltage at that limit, IEC 60268-1 noise".into(),
            format!("{:.2} V RMS ({:.1} W nominal U^2/Re)", t.volts_iec, t.p_nominal_iec),
        ]);
    }

    // --- Distortion -----------------------------------------------------------------------
    let f_lo = (ts.fs / 3.0).max(10.0);
    let f_hi = (ts.fs * 60.0).min(5000.0);
    let freqs = log_frequencies(f_lo, f_hi, 3);
    let sopts = SteadyOptions::default();
    let mut volts = opts.volts.unwrap_or_else(|| level_for_excursion(p, &freqs, 0.7 * (-range[0]).min(range[1])));
    let mut sweep: Vec<Analysis> = Vec::new();
    for attempt in 0..4 {
        match distortion::frequency_sweep(p, &freqs, volts, Output::Pressure, &sopts) {
            Ok(s) => {
                sweep = s;
                break;
            }
            Err(e) if attempt < 3 && opts.volts.is_none() => {
                let _ = e;
                volts *= 0.7;
            }
            Err(e) => return Err(format!("distortion analysis at {volts:.3} V: {e}")),
        }
    }
    let dominant = {
        let mut score = [0.0f64; 3];
        for a in &sweep {
            for (k, (_, h)) in a.parts.iter().enumerate() {
                score[k] += h.thd().powi(2);
            }
        }
        let k = (0..3).max_by(|&i, &j| score[i].total_cmp(&score[j])).unwrap_or(0);
        Nonlinearity::ALL[k]
    };
    if nonlinear {
        rows.push(vec![
            "Dominant nonlinearity".into(),
            format!(
                "{} (largest harmonic distortion alone, summed over {:.0} .. {:.0} Hz at {:.2} V)",
                dominant.name(),
                f_lo,
                f_hi,
                volts
            ),
        ]);
    }
    if !rows.is_empty() {
        b.table(&["limit", "value"], &rows);
    }

    let mut divergence = None;
    if nonlinear {
        b.section(
        "Distortion",
        &format!("Predicted by simulating the identified model to its periodic steady state (sine of {volts:.2} V RMS; sound pressure in the far field, proportional to cone acceleration). Each nonlinearity's contribution is the model with only that nonlinearity left."),
    );
        let line = |f: &dyn Fn(&Analysis) -> f64| sweep.iter().map(|a| (a.total.freq, dbp(f(a)))).collect::<Vec<_>>();
        b.chart(
            Chart::new("hd", "Harmonic distortion", "frequency (Hz)", "dB re fundamental")
                .log_x()
                .floor(DB_FLOOR)
                .line("HD2", line(&|a| a.total.hd(2)))
                .line("HD3", line(&|a| a.total.hd(3)))
                .line("THD", line(&|a| a.total.thd()))
                .marker(ts.fs, "fs"),
            "HD2, HD3 and THD of the sound pressure over frequency.",
        )?;
        for order in [2usize, 3] {
            let mut c = Chart::new(
                &format!("contrib-hd{order}"),
                &format!("HD{order}: each nonlinearity alone"),
                "frequency (Hz)",
                "dB re fundamental",
            )
            .log_x()
            .floor(DB_FLOOR)
            .line("total", line(&|a| a.total.hd(order)));
            for (k, nl) in Nonlinearity::ALL.iter().enumerate() {
                c = c.dashed(nl.name(), sweep.iter().map(|a| (a.total.freq, dbp(a.parts[k].1.hd(order)))).collect());
            }
            b.chart(c, &format!("HD{order} of the full model (solid) and of each nonlinearity alone (dashed)."))?;
        }
        let mut c = String::from("f_Hz,HD2_dB,HD3_dB,THD_dB,HD2_Bl_dB,HD2_Kms_dB,HD2_Le_dB,HD3_Bl_dB,HD3_Kms_dB,HD3_Le_dB,x_dc_mm,dominant\n");
        for a in &sweep {
            let _ = write!(
                c,
                "{:.3},{:.3},{:.3},{:.3}",
                a.total.freq,
                db(a.total.hd(2)),
                db(a.total.hd(3)),
                db(a.total.thd())
            );
            for order in [2, 3] {
                for (_, h) in &a.parts {
                    let _ = write!(c, ",{:.3}", db(h.hd(order)));
                }
            }
            let _ = writeln!(c, ",{:.5},{}", a.total.x_dc * 1e3, a.dominant().key());
        }
        csv.push(("distortion.csv".to_string(), c));

        // Volterra against the full model over level, at resonance.
        let f_v = ts.fs;
        let v_top = level_for_excursion(p, &[f_v], 0.9 * (-range[0]).min(range[1]));
        let levels: Vec<f64> = (0..=12).map(|k| v_top * 10f64.powf((k as f64 - 12.0) / 10.0)).collect();
        let mut rows_v = Vec::new();
        for &v in &levels {
            if let Ok(r) = level_sweep(p, f_v, &[v], Output::Pressure, &sopts) {
                rows_v.extend(r);
            }
        }
        divergence = divergence_level(&rows_v, 1.0);
        let mut c = Chart::new(
            "volterra",
            &format!("Volterra series vs full model at {:.1} Hz", f_v),
            "level (V RMS)",
            "dB re fundamental",
        )
        .floor(DB_FLOOR)
        .log_x()
        .line("HD2 full", rows_v.iter().map(|r| (r.volts, dbp(r.full.hd(2)))).collect())
        .line("HD3 full", rows_v.iter().map(|r| (r.volts, dbp(r.full.hd(3)))).collect())
        .dashed("HD2 Volterra", rows_v.iter().map(|r| (r.volts, dbp(r.volterra.0))).collect())
        .dashed("HD3 Volterra", rows_v.iter().map(|r| (r.volts, dbp(r.volterra.1))).collect());
        if let Some(v) = divergence {
            c = c.marker(v, "Volterra off by 1 dB");
        }
        b.chart(
            c,
            &match divergence {
                Some(v) => format!("The third-order Volterra series follows the model at small level and fails from {v:.2} V (off by more than 1 dB): the distortion feeds back into its own generation."),
                None => "The third-order Volterra series stays within 1 dB of the model over the levels shown.".to_string(),
            },
        )?;
        let mut c = String::from("volts_rms,HD2_full_dB,HD3_full_dB,HD2_volterra_dB,HD3_volterra_dB\n");
        for r in &rows_v {
            let _ = writeln!(
                c,
                "{:.5},{:.3},{:.3},{:.3},{:.3}",
                r.volts,
                db(r.full.hd(2)),
                db(r.full.hd(3)),
                db(r.volterra.0),
                db(r.volterra.1)
            );
        }
        csv.push(("volterra.csv".to_string(), c));
        // The Volterra identification (seed paper 3.2.2.1) against level, on this model. Its
        // error is relative to the size of the nonlinearity: a model whose curves vary by
        // less than a millionth over the range (a degenerate fit's 1e-14 coefficients) has
        // none to identify, and 0/0 to draw.
        let varies = |f: &coilscope_core::poly::Poly| {
            grid(range, 40).iter().any(|&x| (f.eval(x) - f.eval(0.0)).abs() > 1e-6 * f.eval(0.0).abs())
        };
        let nonlinear = [&p.bl, &p.kms, &p.le].iter().any(|f| varies(f));
        if nonlinear {
            let model = Parameters { x_range: Some(range), ..p.clone() };
            let fracs = [0.025, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 0.9];
            if let Ok(rows) = coilscope_ident::volterra::level_study(&model, &fracs) {
                let pct = |k: usize| rows.iter().map(|r| (100.0 * r.frac, db(r.err[k]))).collect::<Vec<_>>();
                b.chart(
                Chart::new("volterra-identification", "Volterra identification against level (this model)", "peak displacement (% of the range)", "error (dB re the 2nd-order nonlinearity)")
                    .log_x()
                    .line("Bl", pct(0))
                    .line("Kms", pct(1))
                    .line("Le", pct(2)),
                "Bl, Kms and Le fitted to the Volterra kernels (H2, H3) of a readable multitone run on this model, against the peak displacement: the method is exact where the third-order series is (small level) and fails as the distortion feeds back into the nonlinearities (seed paper 3.2.2.1). The error is the largest difference from the model's own second-order series over half the range, over the size of that series' nonlinearity (0 dB: an error as large as the nonlinearity; -20 dB: 10 %). `identify --method volterra` warns on a record where this happens; the full identification has no such limit.",
            )?;
                let mut c = String::from("x_peak_over_range,volts_rms,Bl_error,Kms_error,Le_error,kernel_misfit\n");
                for r in &rows {
                    let _ = writeln!(
                        c,
                        "{:.4},{:.5},{:.5},{:.5},{:.5},{:.4e}",
                        r.frac, r.volts, r.err[0], r.err[1], r.err[2], r.misfit
                    );
                }
                csv.push(("volterra_identification.csv".to_string(), c));
            }
        }
        let kern: Vec<(f64, [realfft::num_complex::Complex64; 3])> = freqs
            .iter()
            .map(|&f| (f, volterra::probe(&distortion::with_only(p, &Nonlinearity::ALL, 0.0), f).kernels()))
            .collect();
        b.chart(
            Chart::new("kernels", "Volterra kernels on the diagonal (displacement)", "frequency (Hz)", "dB re 1 m/V^n")
                .log_x()
                .line("|H1(f)|", kern.iter().map(|(f, k)| (*f, db(k[0].norm()))).collect())
                .line("|H2(f,f)|", kern.iter().map(|(f, k)| (*f, db(k[1].norm()))).collect())
                .line("|H3(f,f,f)|", kern.iter().map(|(f, k)| (*f, db(k[2].norm()))).collect()),
            "First three kernels' transfer functions, from the power series by harmonic probing.",
        )?;

        // Two-tone IMD and multitone.
        let mut drows = Vec::new();
        for f in [ts.fs / 2.0, ts.fs, 3.0 * ts.fs] {
            if let Ok(a) = sweep_point(p, f, volts, &sopts) {
                drows.push(vec![
                    format!("sine {f:.1} Hz"),
                    format!("{:.1} dB", db(a.total.hd(2))),
                    format!("{:.1} dB", db(a.total.hd(3))),
                    format!("{:.1} dB", db(a.total.thd())),
                    format!("{:+.3} mm", a.total.x_dc * 1e3),
                    a.dominant().name().into(),
                ]);
            }
        }
        let (f1, f2) = (ts.fs.max(10.0), (ts.fs * 20.0).clamp(700.0, 4000.0) + 0.37 * ts.fs);
        if let Ok(im) = intermod(p, f1, f2, volts, 1.0, Output::Pressure, &sopts) {
            drows.push(vec![
                format!("two-tone {:.1} + {:.1} Hz", im.f1, im.f2),
                format!("d2 {:.1} dB", db(im.d2)),
                format!("d3 {:.1} dB", db(im.d3)),
                String::new(),
                format!("{:+.3} mm", im.x_dc * 1e3),
                String::new(),
            ]);
        }
        b.table(&["excitation", "HD2 / d2", "HD3 / d3", "THD", "DC displacement", "dominant"], &drows);
        if let Ok(mt) = multitone(p, f_lo, 10_000.0, 30, volts, Output::Pressure, 1, &sopts) {
            let ref_level = (mt.tones.iter().map(|t| t.1 * t.1).sum::<f64>() / mt.tones.len() as f64).sqrt();
            let bands = log_frequencies(f_lo, 20_000.0, 3);
            let dist: Vec<(f64, f64)> = bands
                .windows(2)
                .filter_map(|w| {
                    let pw: f64 =
                        mt.distortion.iter().filter(|(f, _)| *f >= w[0] && *f < w[1]).map(|(_, a)| a * a).sum();
                    (pw > 0.0).then(|| ((w[0] * w[1]).sqrt(), db(pw.sqrt() / ref_level)))
                })
                .collect();
            b.chart(
                Chart::new(
                    "multitone",
                    &format!("Multitone distortion (30 tones, MTD {:.1} dB)", db(mt.mtd)),
                    "frequency (Hz)",
                    "dB re mean tone",
                )
                .floor(DB_FLOOR)
                .log_x()
                .line("tones", mt.tones.iter().map(|(f, a)| (*f, dbp(a / ref_level))).collect())
                .line("distortion per 1/3 octave", dist),
                "Sound-pressure spectrum of a 30-tone multitone: the tones and the distortion that falls between them.",
            )?;
        }
    }

    // --- Impedance --------------------------------------------------------------------------
    b.section("Impedance", "Small-signal electrical impedance of the linearised model at rest.");
    let fz = log_frequencies(5.0, 20_000.0, 12);
    let small: Option<Parameters> = result.and_then(|r| Some(r.measurement.as_ref()?.small_signal.parameters.clone()));
    let mut cz = Chart::new("impedance", "Impedance magnitude", "frequency (Hz)", "|Z| (ohm)")
        .log_x()
        .line("large-signal set at x = 0", fz.iter().map(|&f| (f, impedance(p, f).norm())).collect());
    let mut cp = Chart::new("impedance-phase", "Impedance phase", "frequency (Hz)", "phase (deg)")
        .log_x()
        .line("large-signal set at x = 0", fz.iter().map(|&f| (f, impedance(p, f).arg().to_degrees())).collect());
    if let Some(s) = &small {
        cz = cz.dashed(
            "small-signal set (start of measurement)",
            fz.iter().map(|&f| (f, impedance(s, f).norm())).collect(),
        );
        cp = cp.dashed(
            "small-signal set (start of measurement)",
            fz.iter().map(|&f| (f, impedance(s, f).arg().to_degrees())).collect(),
        );
    }
    b.chart(cz, "Magnitude.")?;
    b.chart(cp, "Phase.")?;
    let mut c = String::from("f_Hz,Z_abs_ohm,Z_phase_deg\n");
    for &f in &fz {
        let z = impedance(p, f);
        let _ = writeln!(c, "{f:.3},{:.5},{:.4}", z.norm(), z.arg().to_degrees());
    }
    csv.push(("impedance.csv".to_string(), c));

    // --- Measurement --------------------------------------------------------------------
    if let Some(r) = result {
        if let Some(m) = &r.measurement {
            b.section("Measurement", "The dynamic measurement that produced this result.");
            let fit = &r.fit;
            let mut rows = vec![
                vec!["measurement time".into(), format!("{:.1} s", m.seconds)],
                vec!["converged".into(), fit.converged.map(|c| c.to_string()).unwrap_or_default()],
                vec!["stop reason".into(), fit.stop_reason.clone().unwrap_or_default()],
                vec!["residual".into(), format!("{:.2e}", fit.residual_rel)],
                vec!["peak excursion".into(), format!("{:.2} mm", m.x_peak_max * 1e3)],
                vec!["largest voice-coil rise".into(), format!("{:.1} K", m.dtv_max)],
            ];
            for (t, what) in &m.protection_events {
                rows.push(vec![format!("event at {t} s"), what.clone()]);
            }
            b.table(&["quantity", "value"], &rows);
        }
    }
    let dt_track: Option<Vec<(f64, f64)>> =
        result.and_then(|r| Some(r.thermal.as_ref()?.dt_track.clone())).filter(|t| !t.is_empty());
    if let Some(s) = &input.states {
        let measured = result.and_then(|r| r.measurement.as_ref());
        let span = |v: f64| vec![(s.t[0], v), (s.t[s.t.len() - 1], v)];
        let mut c = Chart::new("x-time", "Excursion during the measurement", "time (s)", "x (mm)")
            .line("largest x per block", s.t.iter().zip(&s.x_max).map(|(t, x)| (*t, x * 1e3)).collect())
            .line("smallest x per block", s.t.iter().zip(&s.x_min).map(|(t, x)| (*t, x * 1e3)).collect());
        let x_limit = measured.and_then(|m| m.x_limit).filter(|x| x.is_finite() && *x > 0.0);
        if let Some(xl) = x_limit {
            c = c.dashed("excursion limit", span(xl * 1e3)).dashed("excursion limit (in)", span(-xl * 1e3));
        }
        b.chart(
            c,
            &match x_limit {
                Some(xl) => format!("Live displacement from the model (no sensor): extremes of each block, and the excursion limit in force at the end (± {:.2} mm).", xl * 1e3),
                None => "Live displacement from the model (no sensor): extremes of each block.".to_string(),
            },
        )?;
        let mut c = Chart::new("temperature-time", "Voice-coil temperature rise", "time (s)", "dT (K)")
            .line("from the tracked Re", s.t.iter().zip(&s.dtv).map(|(t, v)| (*t, *v)).collect());
        if let Some(track) = &dt_track {
            c = c.dashed("at the parameter updates", track.clone());
        }
        let max_dt = measured.and_then(|m| m.max_dt).filter(|d| d.is_finite() && *d > 0.0);
        if let Some(d) = max_dt {
            c = c.dashed("temperature limit (--max-dt)", span(d));
        }
        b.chart(c, "Voice-coil temperature rise estimated from Re(t) = Re (1 + alpha dT), and the run's limit.")?;
        let finite = |v: &[f64]| -> Vec<(f64, f64)> {
            s.t.iter().zip(v).filter(|(_, y)| y.is_finite()).map(|(t, y)| (*t, *y)).collect()
        };
        b.chart(
            Chart::new("level-time", "Drive level during the measurement", "time (s)", "voltage (V rms)")
                .line("terminal voltage per block", finite(&s.volts)),
            "The RMS voltage at the terminals over each block: the quiet start, the ramp and the held level.",
        )?;
        b.chart(
            Chart::new("power-time", "Power into the voice coil", "time (s)", "power (W)")
                .line("Re(t) i_rms^2 per block", finite(&s.power)),
            "The power dissipated in the voice coil's resistance over each block, from the tracked Re(t) and the current's RMS: what heats the coil.",
        )?;
        let mut c = String::from("t_s,x_min_mm,x_max_mm,dTv_K,u_rms_V,power_W\n");
        for k in 0..s.t.len() {
            let _ = writeln!(
                c,
                "{:.3},{:.5},{:.5},{:.4},{:.5},{:.5}",
                s.t[k],
                s.x_min[k] * 1e3,
                s.x_max[k] * 1e3,
                s.dtv[k],
                s.volts[k],
                s.power[k]
            );
        }
        csv.push(("time_series.csv".to_string(), c));
    } else if let Some(track) = dt_track.filter(|t| t.len() >= 2) {
        b.chart(
            Chart::new("temperature-time", "Voice-coil temperature rise", "time (s)", "dT (K)")
                .line("from the tracked Re", track),
            "Voice-coil temperature rise from the fitted Re(t).",
        )?;
    }

    // Live distortion (seed paper 4.2): each nonlinearity's contribution over the run.
    if let Some(d) = result.and_then(|r| r.measurement.as_ref()).map(|m| &m.distortion).filter(|d| d.len() >= 2) {
        let names = ["Bl(x)", "Kms(x)", "Le(x)"];
        for (key, title, pick) in [("x", "displacement", 0usize), ("p", "sound pressure (cone acceleration)", 2)] {
            let mut c = Chart::new(
                &format!("live-distortion-{key}"),
                &format!("Live distortion in {title}"),
                "time (s)",
                "contribution (% of the signal)",
            );
            for (k, name) in names.iter().enumerate() {
                c = c.line(name, d.iter().map(|q| (q.t, 100.0 * [q.x, q.i, q.p][pick][k])).collect());
            }
            // The dominant nonlinearity over the run: its share of the seconds, and when it changed.
            let dom: Vec<&str> =
                d.iter().map(|q| if pick == 0 { q.dominant_x.as_str() } else { q.dominant_p.as_str() }).collect();
            let mut counts: Vec<(&str, usize)> =
                ["Bl", "Kms", "Le"].iter().map(|n| (*n, dom.iter().filter(|d| *d == n).count())).collect();
            counts.sort_by_key(|c| std::cmp::Reverse(c.1));
            let changes: Vec<String> = dom
                .windows(2)
                .zip(d.iter().skip(1))
                .filter(|(w, _)| w[0] != w[1])
                .map(|(w, q)| format!("{} from {:.0} s", w[1], q.t))
                .collect();
            let text = format!(
                "Each nonlinearity's contribution to the {title}, from the live model (RMS over each second, relative to the signal's RMS). Dominant: {} in {} of {} s{}.",
                counts[0].0,
                counts[0].1,
                dom.len(),
                if changes.is_empty() { String::new() } else { format!("; it changed: {}", changes.join(", ")) }
            );
            b.chart(c, &text)?;
        }
        let mut c = String::from("t_s,Bl_x,Kms_x,Le_x,Bl_i,Kms_i,Le_i,Bl_p,Kms_p,Le_p,dominant_x,dominant_p\n");
        for q in d {
            let _ = writeln!(
                c,
                "{:.2},{:.6},{:.6},{:.6},{:.6},{:.6},{:.6},{:.6},{:.6},{:.6},{},{}",
                q.t, q.x[0], q.x[1], q.x[2], q.i[0], q.i[1], q.i[2], q.p[0], q.p[1], q.p[2], q.dominant_x, q.dominant_p
            );
        }
        csv.push(("live_distortion.csv".to_string(), c));
    }

    let html = page(&input.title, p, &b.html);
    Ok(Report { html, charts: b.charts, csv, volts, volterra_divergence: divergence, warnings: b.warnings })
}

fn sweep_point(p: &Parameters, f: f64, volts: f64, o: &SteadyOptions) -> Result<Analysis, String> {
    analyse(p, f, volts, Output::Pressure, o).map_err(|e| e.to_string())
}

fn page(title: &str, p: &Parameters, body: &str) -> String {
    page_with_source(title, p.source.as_deref().unwrap_or_default(), body)
}

/// The page around `body`, its header naming `source`.
fn page_with_source(title: &str, source: &str, body: &str) -> String {
    format!(
        r#"<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{t}</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>
body {{ font-family: "DejaVu Sans", Arial, sans-serif; margin: 24px auto; max-width: 820px; color: #222; }}
h1 {{ font-size: 1.5em; }} h2 {{ font-size: 1.2em; margin-top: 2em; border-bottom: 1px solid #ccc; }}
table {{ border-collapse: collapse; margin: 0.8em 0; font-size: 0.9em; }}
th, td {{ border: 1px solid #ddd; padding: 3px 8px; text-align: left; }} th {{ background: #f3f3f3; }}
figure.plot {{ margin: 1em 0; }} figure.plot svg {{ display: block; max-width: 100%; height: auto; }}
figcaption {{ font-size: 0.85em; color: #555; }} .note {{ font-size: 0.9em; color: #555; }}
</style></head><body>
<h1>{t}</h1>
<p class="note">{s}. Written by coilscope {v}. All units SI unless shown; x &gt; 0 is coil out (away from the back plate).</p>
{body}
<pre id="layout" hidden></pre>
<script>
(function () {{
  var out = [];
  document.querySelectorAll("figure.plot").forEach(function (f) {{
    var r = f.querySelector("svg").getBoundingClientRect();
    var marks = f.querySelectorAll("polyline, path, polygon").length;
    f.setAttribute("data-drawn", marks > 0 && r.width > 0 && r.height > 0 ? "yes" : "no");
    out.push({{ id: f.id, x: r.left + window.scrollX, y: r.top + window.scrollY, w: r.width, h: r.height, marks: marks }});
  }});
  var height = Math.ceil(document.documentElement.scrollHeight);
  document.getElementById("layout").textContent = JSON.stringify({{ height: height, plots: out }});
}})();
</script>
</body></html>
"#,
        t = esc(title),
        s = esc(source),
        v = env!("CARGO_PKG_VERSION"),
    )
}

/// The directory beside `out` that holds the PNG and CSV files: `<stem>_files`.
pub fn files_dir(out: &Path) -> PathBuf {
    let stem = out.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "report".into());
    out.with_file_name(format!("{stem}_files"))
}

/// Write the HTML (atomically), the PNGs and the CSVs; return every path written.
pub fn write(report: &Report, out: &Path, png_size: (u32, u32)) -> Result<Vec<PathBuf>, String> {
    let dir = files_dir(out);
    std::fs::create_dir_all(&dir).map_err(|e| format!("{}: cannot create the directory ({e})", dir.display()))?;
    let mut written = vec![];
    for c in &report.charts {
        let path = dir.join(format!("{}.png", c.id));
        coilscope_io::atomic_write(&path, &c.png(png_size)?).map_err(|e| e.to_string())?;
        written.push(path);
    }
    for (name, text) in &report.csv {
        let path = dir.join(name);
        coilscope_io::atomic_write(&path, text.as_bytes()).map_err(|e| e.to_string())?;
        written.push(path);
    }
    let rel = dir.file_name().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    let html = report.html.replace("href=\"#\" data-png=\"", &format!("href=\"{rel}/"));
    coilscope_io::atomic_write(out, html.as_bytes()).map_err(|e| e.to_string())?;
    written.push(out.to_path_buf());
    Ok(written)
}

/// Read a result file or a parameter set (embedded name or JSON path) into a report input.
pub fn input_from(spec: &str) -> Result<ReportInput, String> {
    let path = Path::new(spec);
    if path.exists() {
        let text = std::fs::read_to_string(path).map_err(|e| format!("{spec}: cannot read ({e})"))?;
        input_from_text(&text, spec)
    } else {
        input_of(coilscope_io::load_parameters(spec).map_err(|e| e.to_string())?, None, spec)
    }
}

/// Read the text of a result file or of a parameter set (JSON) into a report input; `spec`
/// names it in messages. Never panics, whatever the text (a fuzz target).
pub fn input_from_text(text: &str, spec: &str) -> Result<ReportInput, String> {
    let v: Value = serde_json::from_str(text).map_err(|e| format!("{spec}: not JSON ({e})"))?;
    if v.get("format").and_then(|f| f.as_str()).is_some_and(|f| f.starts_with("coilscope.result")) {
        let r = ResultFile::from_json_value(v, spec).map_err(|e| e.to_string())?;
        input_of(r.parameters.clone(), Some(r), spec)
    } else {
        input_of(Parameters::from_json_value(&v, spec).map_err(|e| e.to_string())?, None, spec)
    }
}

fn input_of(params: Parameters, result: Option<ResultFile>, spec: &str) -> Result<ReportInput, String> {
    // A result without `fit` reads as the range [0, 0]: not a range.
    let fit_range = result.as_ref().map(|r| r.fit.x_range).filter(|[lo, hi]| hi > lo);
    let range = fit_range.or(params.x_range).ok_or_else(|| {
        format!("{spec}: neither fit.x_range nor the parameters' x_range says where the curves are valid")
    })?;
    let recording = result.as_ref().map(|r| r.recording.clone()).filter(|r| !r.is_empty());
    let title = format!("coilscope report: {}", params.name.clone().or(recording).unwrap_or_else(|| spec.to_string()));
    Ok(ReportInput { title, params, range, result, states: None, compare: None })
}

/// What a result's method is, for labels: `quasi-static`, `dynamic` (a large-signal result)
/// or the result's kind.
fn method_label(input: &ReportInput) -> String {
    match input.result.as_ref().map(|r| r.kind.as_str()) {
        Some("quasi-static") => "quasi-static".into(),
        Some("large-signal") => "dynamic".into(),
        Some(k) => k.to_string(),
        None => "parameter set".into(),
    }
}

#[cfg(test)]
mod legend_overlap {
    use super::*;

    /// No legend box covers a data line, in any chart of the reports of the bundled
    /// drivers, at the PNG size and at the inline SVG's size.
    #[test]
    fn no_legend_covers_a_data_line() {
        let mut checked = 0;
        for driver in ["sb17cac35-4", "ptt4.0w04-01a", "18wu-4741t-00"] {
            let input = input_from(driver).unwrap();
            let report = build(&input, &ReportOptions::default()).unwrap();
            for c in report.charts.iter().filter(|c| c.series.len() > 1) {
                for size in [ReportOptions::default().png_size, SVG_SIZE] {
                    let n = c.legend_covers_data(size).unwrap();
                    assert_eq!(
                        n, 0,
                        "{driver}: the legend of chart {} covers {n} pixels of its data lines at {size:?}",
                        c.id
                    );
                    checked += 1;
                }
            }
        }
        assert!(checked >= 12, "only {checked} charts with a legend were checked");
    }
}

/// The sds of the small-signal figures ([`coilscope_core::small_signal::ThieleSmall`]), of
/// `Res` and of [`total_q_with_eddy_losses`], propagated from the sds `sd_of` gives for the
/// values they are computed from: `Re`, `Bl(0)`, `Kms(0)`, `Mms`, `Rms`, creep's `lambda`, `Sd`,
/// `Le(0)` and `R2(0)`. Each figure's derivative by a central difference, the inputs taken
/// as independent (the result files carry sds, not covariances); `None` for a figure none of
/// whose inputs has an sd.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct DerivedSds {
    pub fs: Option<f64>,
    pub qms: Option<f64>,
    pub qes: Option<f64>,
    pub qts: Option<f64>,
    pub cms: Option<f64>,
    pub vas: Option<f64>,
    pub rms_fs: Option<f64>,
    pub res: Option<f64>,
    pub qtp: Option<f64>,
}

/// Total Q with the electrical losses the para-inductance adds at the resonance: the real part
/// of the blocked electrical impedance at fs in place of Re.
pub fn total_q_with_eddy_losses(p: &Parameters) -> f64 {
    let ts = thiele_small(p);
    let bl0 = p.bl.c[0];
    let w = 2.0 * std::f64::consts::PI * ts.fs;
    let jw = realfft::num_complex::Complex64::new(0.0, w);
    let mut ze = p.re + jw * p.le.c[0];
    if let Some((l2, r2)) = &p.l2r2 {
        ze += jw * l2.c[0] * r2.c[0] / (jw * l2.c[0] + r2.c[0]);
    }
    let qes_p = w * p.mms * ze.re / (bl0 * bl0);
    ts.qms * qes_p / (ts.qms + qes_p)
}

/// See [`DerivedSds`].
pub fn derived_sds(p: &Parameters, sd_of: &dyn Fn(&str) -> Option<f64>) -> DerivedSds {
    let figures = |q: &Parameters| {
        let t = thiele_small(q);
        let bl = q.bl.c[0];
        [
            t.fs,
            t.qms,
            t.qes,
            t.qts,
            t.cms,
            t.vas.unwrap_or(f64::NAN),
            t.rms_fs,
            bl * bl / t.rms_fs,
            total_q_with_eddy_losses(q),
        ]
    };
    type Set = fn(&mut Parameters, f64);
    let inputs: [(&str, Set, f64); 9] = [
        ("Re", |q, d| q.re += d, p.re),
        ("Bl", |q, d| q.bl.c[0] += d, p.bl.c[0]),
        ("Kms", |q, d| q.kms.c[0] += d, p.kms.c[0]),
        ("Mms", |q, d| q.mms += d, p.mms),
        ("Rms", |q, d| q.rms += d, p.rms),
        (
            "creep.lambda",
            |q, d| {
                if let Some(c) = q.creep.as_mut() {
                    c.lambda += d
                }
            },
            p.creep.as_ref().map_or(0.0, |c| c.lambda),
        ),
        (
            "Sd",
            |q, d| {
                if let Some(s) = q.sd.as_mut() {
                    *s += d
                }
            },
            p.sd.unwrap_or(0.0),
        ),
        ("Le", |q, d| q.le.c[0] += d, p.le.c[0]),
        (
            "R2",
            |q, d| {
                if let Some((_, r2)) = q.l2r2.as_mut() {
                    r2.c[0] += d
                }
            },
            p.l2r2.as_ref().map_or(0.0, |(_, r2)| r2.c[0]),
        ),
    ];
    let mut var = [0.0f64; 9];
    let mut any = false;
    for (key, set, value) in inputs {
        let Some(sd) = sd_of(key).filter(|s| s.is_finite() && *s > 0.0) else { continue };
        let h = 1e-6 * value.abs().max(sd);
        let (mut up, mut down) = (p.clone(), p.clone());
        set(&mut up, h);
        set(&mut down, -h);
        let (a, b) = (figures(&up), figures(&down));
        for k in 0..9 {
            let slope = (a[k] - b[k]) / (2.0 * h);
            if slope.is_finite() {
                var[k] += (slope * sd).powi(2);
            }
        }
        any = true;
    }
    let sd = |k: usize| any.then(|| var[k].sqrt()).filter(|s| *s > 0.0);
    DerivedSds {
        fs: sd(0),
        qms: sd(1),
        qes: sd(2),
        qts: sd(3),
        cms: sd(4),
        vas: p.sd.and(sd(5)),
        rms_fs: sd(6),
        res: sd(7),
        qtp: sd(8),
    }
}

#[cfg(test)]
mod degenerate {
    use super::*;

    /// `measure --replay` of SB17's `-real-chain` record without its
    /// calibration ended on curves that vary by 1e-16 of their value over the range; the
    /// Volterra identification's error (over the size of the nonlinearity) was 0/0 and the
    /// whole report failed on its chart. The report is written, without that chart.
    #[test]
    fn a_model_with_vanishing_nonlinearity_still_gets_its_report() {
        let mut input = input_from("sb17cac35-4").unwrap();
        for f in [&mut input.params.bl, &mut input.params.kms, &mut input.params.le] {
            let c0 = f.c[0];
            for (k, c) in f.c.iter_mut().enumerate().skip(1) {
                *c = 1e-14 * c0 * 1e3f64.powi(k as i32);
            }
        }
        let report = build(&input, &ReportOptions::default()).unwrap();
        assert!(report.warnings.is_empty(), "{:?}", report.warnings);
        assert!(!report.charts.iter().any(|c| c.id == "volterra-identification"), "no nonlinearity to identify");
        assert!(report.charts.iter().all(|c| c.has_finite_data()));
    }

    /// A chart without a finite value gets a figure that says so and a warning; the report
    /// goes on.
    #[test]
    fn a_chart_without_finite_data_is_a_note_and_a_warning() {
        let mut b = Builder { html: String::new(), charts: vec![], warnings: vec![] };
        b.chart(Chart::new("empty", "Empty", "x", "y").line("nan", vec![(0.0, f64::NAN), (1.0, f64::NAN)]), "caption")
            .unwrap();
        b.chart(Chart::new("fine", "Fine", "x", "y").line("one", vec![(0.0, 1.0), (1.0, 2.0)]), "caption").unwrap();
        assert_eq!(b.warnings.len(), 1, "{:?}", b.warnings);
        assert!(b.warnings[0].contains("chart empty") && b.warnings[0].contains("no finite value"));
        assert!(b.html.contains("id=\"plot-empty\"") && b.html.contains("no finite value to draw"));
        assert_eq!(b.charts.len(), 1, "only the drawable chart gets a PNG");
        assert_eq!(b.charts[0].id, "fine");
    }

    /// The figures' sds are the first-order propagation of the inputs' sds: with Kms and Mms
    /// alone uncertain, `sd(fs) / fs = 1/2 sqrt((sK / K)^2 + (sM / M)^2)`; with none, none.
    #[test]
    fn the_small_signal_figures_carry_the_sds_of_their_inputs() {
        let p = coilscope_core::embedded_driver("sb17cac35-4").unwrap();
        let (sk, sm) = (0.01 * p.kms.c[0], 0.02 * p.mms);
        let sds = |k: &str| match k {
            "Kms" => Some(sk),
            "Mms" => Some(sm),
            _ => None,
        };
        let d = derived_sds(&p, &sds);
        let fs = thiele_small(&p).fs;
        let want = 0.5 * fs * (0.01f64.powi(2) + 0.02f64.powi(2)).sqrt();
        let got = d.fs.unwrap();
        assert!((got / want - 1.0).abs() < 1e-4, "sd(fs) {got}, first order {want}");
        let cms = thiele_small(&p).cms;
        assert!((d.cms.unwrap() / (0.01 * cms) - 1.0).abs() < 1e-4);
        assert!(d.vas.is_some() && d.qms.is_some() && d.qes.is_some() && d.qts.is_some());
        // Qes = w_s Mms Re / Bl^2 with w_s = sqrt(K / M): d ln Qes = 1/2 d ln K + 1/2 d ln M.
        let qes = thiele_small(&p).qes;
        assert!((d.qes.unwrap() / (0.5 * qes * (0.01f64.powi(2) + 0.02f64.powi(2)).sqrt()) - 1.0).abs() < 1e-4);
        assert_eq!(derived_sds(&p, &|_| None), DerivedSds::default());
        // A NaN sd is no sd, never a figure's.
        assert_eq!(derived_sds(&p, &|_| Some(f64::NAN)), DerivedSds::default());
    }
}

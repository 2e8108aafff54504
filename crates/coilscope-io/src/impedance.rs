//! Impedance curves in files: what REW, ARTA, LIMP, DATS, Klippel and Speakerbench exchange.
//!
//! * **`.zma`** (and `.frd`/`.txt` laid out alike): one point per line, `frequency (Hz)
//!   magnitude (ohm) phase (degrees)`, separated by spaces, tabs, commas or semicolons.
//!   Lines starting with `*` are comments (the ZMA/FRD convention), as are those starting
//!   with `#`, `;` or `//`, and empty lines. Further columns are ignored.
//! * **CSV with named columns**: a first non-comment line of names, e.g.
//!   `Freq (Hz),Magnitude (Ohm),Phase (deg)` or `frequency_hz,real_ohm,imag_ohm`. A column is
//!   recognised by its name's first word: `freq`/`frequency`/`f`/`hz` (frequency, Hz),
//!   `mag`/`magnitude`/`impedance`/`z`/`|z|`/`abs` (ohm), `phase`/`angle`/`arg`/`phi` (degrees,
//!   or radians when the name says `rad`), `re`/`real`/`resistance` and `im`/`imag`/
//!   `imaginary`/`reactance` (ohm). Real and imaginary parts win over magnitude and phase
//!   when a file has both. Other columns (coherence, a model) are ignored.
//!
//! The decimal separator is the point. Frequencies must be positive and strictly
//! increasing, magnitudes positive and finite: a file that breaks this is refused with its
//! line and value named, never read half.
//!
//! **Magnitude only.** Many tools export |Z| alone (REW, KLIPPEL LPM's export with its
//! quoted header lines and a measured and a fitted column: the first magnitude column, the
//! measured one, is read). A `.zma` line of two numbers, or named columns with a magnitude
//! and no phase, give a curve with [`ImpedanceCurve::magnitude_only`] set; its `z` holds the
//! magnitudes as real numbers, and the fit takes the magnitude alone. Lines of names before
//! the data that name no frequency column (a title, a quoted header line) are kept as
//! comments.

use crate::{atomic_write, IoError};
use coilscope_core::Complex64;
use std::path::Path;

/// A measured impedance `z[k]` (ohm, complex) at frequency `f[k]` (Hz, increasing).
#[derive(Clone, Debug, PartialEq)]
pub struct ImpedanceCurve {
    pub f: Vec<f64>,
    pub z: Vec<Complex64>,
    /// The file's comment lines, without their leading markers (the measurement's notes).
    pub comments: Vec<String>,
    /// The file has no phase: `z` holds the magnitudes (real, phase 0), and only `|z|` is
    /// data.
    pub magnitude_only: bool,
}

/// Where a file's impedance is: magnitude and phase columns (phase in radians when `true`),
/// real and imaginary parts, or a magnitude alone.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Parts {
    MagPhase(usize, usize, bool),
    ReIm(usize, usize),
    Mag(usize),
}

/// Fewest points of a curve worth fitting (the linear model has 7 to 10 unknowns).
pub const MIN_POINTS: usize = 20;

#[derive(Clone, Copy, Debug, PartialEq)]
enum Column {
    Freq,
    Mag,
    /// Phase, in radians when `true`.
    Phase(bool),
    Re,
    Im,
    Other,
}

/// A column's role from its name (see the module docs).
fn column_of(name: &str) -> Column {
    let n = name.trim().trim_matches(|c| c == '"' || c == '\'').trim().to_ascii_lowercase();
    let rad = n.contains("rad");
    // The first word: up to a space, '(', '[', '_' or '/'.
    let word: String = n.chars().take_while(|c| !matches!(c, ' ' | '(' | '[' | '_' | '/' | '-')).collect();
    match word.as_str() {
        "freq" | "frequency" | "f" | "hz" => Column::Freq,
        "mag" | "magnitude" | "impedance" | "z" | "|z|" | "abs" | "ohm" | "ohms" => Column::Mag,
        "phase" | "angle" | "arg" | "phi" => Column::Phase(rad),
        "re" | "real" | "resistance" | "r" => Column::Re,
        "im" | "imag" | "imaginary" | "reactance" | "x" => Column::Im,
        _ => Column::Other,
    }
}

/// The fields of a line: split on the first of tab, comma or semicolon it contains, else
/// on whitespace.
fn fields(line: &str) -> Vec<&str> {
    for sep in ['\t', ',', ';'] {
        if line.contains(sep) {
            return line.split(sep).map(str::trim).filter(|s| !s.is_empty()).collect();
        }
    }
    line.split_whitespace().collect()
}

fn is_comment(line: &str) -> Option<&str> {
    for m in ["*", "#", ";", "//"] {
        if let Some(rest) = line.strip_prefix(m) {
            return Some(rest.trim_start_matches(m).trim());
        }
    }
    None
}

/// Read an impedance curve from `text`; `name` (the file) is named in every error.
pub fn parse_impedance(text: &str, name: &str) -> Result<ImpedanceCurve, IoError> {
    let mut comments = vec![];
    // Column indices: the frequency's, then the impedance's.
    let mut layout: Option<(usize, Parts)> = None;
    let (mut f, mut z) = (Vec::<f64>::new(), Vec::<Complex64>::new());
    for (ln, raw) in text.lines().enumerate() {
        let line_no = ln + 1;
        let line = raw.trim().trim_start_matches('\u{feff}');
        if line.is_empty() {
            continue;
        }
        if let Some(c) = is_comment(line) {
            if !c.chars().all(|ch| ch == '*') {
                comments.push(c.to_string());
            }
            continue;
        }
        let cols = fields(line);
        let nums: Vec<Option<f64>> = cols.iter().map(|c| c.trim_start_matches('+').parse::<f64>().ok()).collect();
        if nums.iter().any(Option::is_none) {
            // A line of names: only before the data, and only once.
            if layout.is_some() || !f.is_empty() {
                let bad = cols.iter().zip(&nums).find(|(_, n)| n.is_none()).map(|(c, _)| *c).unwrap_or("");
                return Err(IoError(format!("{name}, line {line_no}: `{bad}` is not a number (expected frequency Hz, magnitude ohm, phase deg; comment lines start with `*`)")));
            }
            let roles: Vec<Column> = cols.iter().map(|c| column_of(c)).collect();
            let find = |want: fn(Column) -> bool| roles.iter().position(|&r| want(r));
            let Some(fc) = find(|r| r == Column::Freq) else {
                // A title or a quoted header line before the column names: a comment. A line
                // that names impedance columns but no frequency is a header that would be
                // misread by position: refused.
                if roles.iter().any(|r| !matches!(r, Column::Other)) {
                    return Err(IoError(format!("{name}, line {line_no}: no frequency column among {cols:?} (name one `freq`, `frequency` or `Hz`)")));
                }
                comments.push(line.replace('"', "").trim().to_string());
                continue;
            };
            let parts = match (find(|r| r == Column::Re), find(|r| r == Column::Im), find(|r| r == Column::Mag), find(|r| matches!(r, Column::Phase(_)))) {
                (Some(a), Some(b), _, _) => Parts::ReIm(a, b),
                (_, _, Some(m), Some(p)) => Parts::MagPhase(m, p, matches!(roles[p], Column::Phase(true))),
                (_, _, Some(m), None) => Parts::Mag(m),
                _ => return Err(IoError(format!("{name}, line {line_no}: no impedance columns among {cols:?} (name them magnitude and phase, or real and imaginary)"))),
            };
            layout = Some((fc, parts));
            continue;
        }
        // Without names, a .zma line: `frequency magnitude phase`, or `frequency magnitude`.
        let (fc, parts) =
            *layout.get_or_insert((0, if nums.len() == 2 { Parts::Mag(1) } else { Parts::MagPhase(1, 2, false) }));
        let need = match parts {
            Parts::MagPhase(m, p, _) => fc.max(m).max(p),
            Parts::ReIm(a, b) => fc.max(a).max(b),
            Parts::Mag(m) => fc.max(m),
        };
        if nums.len() <= need {
            return Err(IoError(format!(
                "{name}, line {line_no}: {} columns, expected at least {} (frequency Hz, magnitude ohm{})",
                nums.len(),
                need + 1,
                if matches!(parts, Parts::Mag(_)) { "" } else { ", phase deg" }
            )));
        }
        let v = |k: usize| nums[k].expect("checked numeric");
        let fk = v(fc);
        if !(fk.is_finite() && fk > 0.0) {
            return Err(IoError(format!("{name}, line {line_no}: frequency {fk} Hz is not positive and finite")));
        }
        if let Some(&prev) = f.last() {
            if fk <= prev {
                return Err(IoError(format!("{name}, line {line_no}: frequency {fk} Hz does not increase (previous point {prev} Hz); one curve per file, sorted by frequency")));
            }
        }
        let zk = match parts {
            Parts::Mag(m) => {
                let mag = v(m);
                if !(mag.is_finite() && mag > 0.0) {
                    return Err(IoError(format!(
                        "{name}, line {line_no}: magnitude {mag} ohm at {fk} Hz is not positive and finite"
                    )));
                }
                Complex64::new(mag, 0.0)
            }
            Parts::MagPhase(m, p, rad) => {
                let (mag, ph) = (v(m), v(p));
                if !(mag.is_finite() && mag > 0.0) {
                    return Err(IoError(format!(
                        "{name}, line {line_no}: magnitude {mag} ohm at {fk} Hz is not positive and finite"
                    )));
                }
                let limit = if rad { std::f64::consts::PI * 1.001 } else { 180.5 };
                if !(ph.is_finite() && ph.abs() <= limit) {
                    return Err(IoError(format!(
                        "{name}, line {line_no}: phase {ph} {} at {fk} Hz is outside +-{}",
                        if rad { "rad" } else { "deg" },
                        if rad { "pi" } else { "180 (a .zma phase is in degrees)" }
                    )));
                }
                Complex64::from_polar(mag, if rad { ph } else { ph.to_radians() })
            }
            Parts::ReIm(a, b) => {
                let c = Complex64::new(v(a), v(b));
                if !(c.re.is_finite() && c.im.is_finite() && c.norm() > 0.0) {
                    return Err(IoError(format!(
                        "{name}, line {line_no}: impedance {} {:+}j ohm at {fk} Hz is not finite and non-zero",
                        c.re, c.im
                    )));
                }
                c
            }
        };
        f.push(fk);
        z.push(zk);
    }
    if f.len() < MIN_POINTS {
        return Err(IoError(format!("{name}: {} impedance points; at least {MIN_POINTS} are needed (frequency Hz, magnitude ohm, phase deg per line)", f.len())));
    }
    let magnitude_only = matches!(layout, Some((_, Parts::Mag(_))));
    Ok(ImpedanceCurve { f, z, comments, magnitude_only })
}

/// Read an impedance curve file (see the module docs).
pub fn read_impedance(path: &Path) -> Result<ImpedanceCurve, IoError> {
    let name = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|e| IoError(format!("{name}: cannot read the impedance file ({e})")))?;
    let text = String::from_utf8(bytes).map_err(|_| {
        IoError(format!(
            "{name}: not a text file (an impedance file is text: frequency Hz, magnitude ohm, phase deg per line)"
        ))
    })?;
    parse_impedance(&text, &name)
}

/// `.zma` text: the `comments` as `*` lines, then `frequency magnitude phase` per point
/// (Hz, ohm, degrees) with 9 significant digits, so that reading it back gives the curve to
/// 1e-8 relative.
pub fn zma_text(curve: &ImpedanceCurve) -> String {
    curve_text(curve, "Magnitude")
}

/// The text of [`zma_text`] with `magnitude` naming the second column (`.frd` files of an
/// impedance call it `Impedance`; the layout is the same).
pub fn curve_text(curve: &ImpedanceCurve, magnitude: &str) -> String {
    let mut out = String::new();
    for c in &curve.comments {
        out.push_str(&format!("* {c}\n"));
    }
    if curve.magnitude_only {
        // No phase to write: the file's own two columns.
        out.push_str(&format!("* Freq(Hz) {magnitude}(Ohm)\n"));
        for (f, z) in curve.f.iter().zip(&curve.z) {
            out.push_str(&format!("{:.9e} {:.9e}\n", f, z.norm()));
        }
        return out;
    }
    out.push_str(&format!("* Freq(Hz) {magnitude}(Ohm) Phase(Deg)\n"));
    for (f, z) in curve.f.iter().zip(&curve.z) {
        out.push_str(&format!("{:.9e} {:.9e} {:+.9e}\n", f, z.norm(), z.arg().to_degrees()));
    }
    out
}

/// Write `curve` as a `.zma` file, atomically.
pub fn write_zma(path: &Path, curve: &ImpedanceCurve) -> Result<(), IoError> {
    atomic_write(path, zma_text(curve).as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn curve_text(n: usize, line: impl Fn(f64, Complex64) -> String) -> String {
        (0..n)
            .map(|k| {
                let f = 10.0 * 1.1f64.powi(k as i32);
                let z = Complex64::new(6.0 + f * 1e-3, f * 2e-3);
                line(f, z) + "\n"
            })
            .collect()
    }

    #[test]
    fn reads_zma_with_comments_and_signs() {
        let text = format!(
            "****\n* FILE: x.zma\n* Data: Impedance (ohms), Phase (degrees)\n****\n{}",
            curve_text(30, |f, z| format!("   {f:.3}    +{:.4}   {:+.4}", z.norm(), z.arg().to_degrees()))
        );
        let c = parse_impedance(&text, "x.zma").unwrap();
        assert_eq!(c.f.len(), 30);
        assert_eq!(c.comments, vec!["FILE: x.zma", "Data: Impedance (ohms), Phase (degrees)"]);
        assert!((c.z[0] - Complex64::new(6.01, 0.02)).norm() < 1e-3);
    }

    #[test]
    fn reads_named_csv_columns_in_any_order_and_real_imag() {
        let text = format!(
            "Phase (deg);Freq (Hz);Impedance (Ohm);Coherence\n{}",
            curve_text(25, |f, z| format!("{};{f};{};0.99", z.arg().to_degrees(), z.norm()))
        );
        let c = parse_impedance(&text, "a.csv").unwrap();
        assert!((c.z[3].re - (6.0 + c.f[3] * 1e-3)).abs() < 1e-9 && (c.z[3].im - c.f[3] * 2e-3).abs() < 1e-9);
        let text =
            format!("frequency_hz,real_ohm,imag_ohm\n{}", curve_text(25, |f, z| format!("{f},{},{}", z.re, z.im)));
        let c = parse_impedance(&text, "b.csv").unwrap();
        assert!((c.z[24].im - c.f[24] * 2e-3).abs() < 1e-12);
        let text = format!("f\tmag\tphase (rad)\n{}", curve_text(25, |f, z| format!("{f}\t{}\t{}", z.norm(), z.arg())));
        let c = parse_impedance(&text, "c.txt").unwrap();
        assert!((c.z[5].im - c.f[5] * 2e-3).abs() < 1e-12);
    }

    /// |Z| alone, as REW writes it (two columns) and as KLIPPEL LPM exports it (tab
    /// separated, quoted header lines, a measured and a fitted magnitude: the measured one).
    #[test]
    fn reads_magnitude_only_files() {
        let c = parse_impedance(&curve_text(25, |f, z| format!("{f} {}", z.norm())), "rew.txt").unwrap();
        assert!(
            c.magnitude_only
                && (c.z[4].re - (6.0 + c.f[4] * 1e-3).hypot(c.f[4] * 2e-3)).abs() < 1e-9
                && c.z[4].im == 0.0
        );
        let text = format!("\"LPM Linear Parameter Measurement\"\n\"Driver: woofer 5.25\"\n\"Frequency [Hz]\"\t\"Impedance measured [Ohm]\"\t\"Impedance fitted [Ohm]\"\n{}", curve_text(25, |f, z| format!("{f}\t{}\t{}", z.norm(), z.norm() * 1.05)));
        let c = parse_impedance(&text, "lpm.txt").unwrap();
        assert!(c.magnitude_only);
        assert_eq!(c.comments, vec!["LPM Linear Parameter Measurement", "Driver: woofer 5.25"]);
        assert!(
            (c.z[7].re - (6.0 + c.f[7] * 1e-3).hypot(c.f[7] * 2e-3)).abs() < 1e-9,
            "the measured column, not the fitted one"
        );
        let c =
            parse_impedance(&curve_text(25, |f, z| format!("{f} {} {}", z.norm(), z.arg().to_degrees())), "full.zma")
                .unwrap();
        assert!(!c.magnitude_only);
    }

    #[test]
    fn zma_round_trip_is_exact_to_1e8() {
        let c =
            parse_impedance(&curve_text(40, |f, z| format!("{f} {} {}", z.norm(), z.arg().to_degrees())), "x").unwrap();
        let back = parse_impedance(
            &zma_text(&ImpedanceCurve { comments: vec!["written by a test".into()], ..c.clone() }),
            "y",
        )
        .unwrap();
        assert_eq!(back.comments, vec!["written by a test", "Freq(Hz) Magnitude(Ohm) Phase(Deg)"]);
        for k in 0..c.f.len() {
            assert!((back.f[k] / c.f[k] - 1.0).abs() < 1e-8 && (back.z[k] - c.z[k]).norm() < 1e-8 * c.z[k].norm());
        }
    }

    #[test]
    fn bad_files_are_named_with_line_and_value() {
        let good = curve_text(25, |f, z| format!("{f} {} {}", z.norm(), z.arg().to_degrees()));
        let cases = [
            (good.replacen("\n", "\n10 6\n", 3), "expected at least 3"),
            (good.replacen("\n", "\n10 6 2\n", 3), "does not increase"),
            (good.clone() + "5000 -1 0\n", "not positive"),
            (good.clone() + "6000 7 400\n", "outside +-180"),
            (good.clone() + "7000 7,5 3\n", "is not a number"),
            ("10 6 1\n11 6 1\n".to_string(), "at least 20"),
            (format!("Hz,Coherence\n{good}"), "no impedance columns"),
            (format!("Frequenz,Real,Imag\n{good}"), "no frequency column"),
        ];
        for (text, want) in cases {
            let e = parse_impedance(&text, "bad.zma").unwrap_err().0;
            assert!(e.contains("bad.zma") && e.contains(want), "{e} (wanted `{want}`)");
        }
    }
}

//! A mass as a user gives it: a value and, where known, its standard deviation (`15.3g±0.3g`).
//!
//! The moving mass (`--mms`) or an added mass (`--added-mass`) is the absolute scale of every
//! fit from voltage and current alone: with the mass `c` times larger, Bl comes out `sqrt(c)`
//! times larger and Kms, Rms and Mms `c` times (the electrical impedance does not change).
//! A weighed cone or a data sheet's Mms is known to a few percent, and that share belongs in
//! the sds of what it scales ([`Mass::sd_rel`]).

use std::fmt;

/// A mass (kg) and its standard deviation (kg; 0 when given as exact).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Mass {
    pub kg: f64,
    pub sd_kg: f64,
}

impl Mass {
    /// A mass taken as exact.
    pub fn exact(kg: f64) -> Self {
        Mass { kg, sd_kg: 0.0 }
    }

    /// The relative standard deviation `sd / value`.
    pub fn sd_rel(&self) -> f64 {
        self.sd_kg / self.kg
    }

    /// A mass as written on a command line: a number with an optional unit (`kg`, `g`, `mg`;
    /// a bare number is kilograms, as every input is SI), optionally followed by `±` (or `+-`)
    /// and its standard deviation, with its own unit or the value's: `0.0153`, `15.3g`,
    /// `15.3g±0.3g`, `15.3±0.3g`, `15.3 g +- 300 mg`. The message names the text and what
    /// would be valid.
    pub fn parse(text: &str) -> Result<Mass, String> {
        let t = text.trim();
        let (value, sd) = match t.split_once('±').or_else(|| t.split_once("+-")) {
            Some((v, s)) => (v.trim(), Some(s.trim())),
            None => (t, None),
        };
        let not_a_mass = || {
            format!("'{text}' is not a mass: write a number with its unit, e.g. 15.3g or 0.0153 (kg), and its sd after ± if known: 15.3g±0.3g")
        };
        let quantity = |part: &str| -> Result<(f64, Option<f64>), String> {
            let part = part.trim();
            // The unit is a suffix (a number may hold an exponent's `e`: 1.5e-2).
            let (num, scale) = [("kg", 1.0), ("mg", 1e-6), ("g", 1e-3)]
                .into_iter()
                .find_map(|(u, k)| part.strip_suffix(u).map(|n| (n.trim(), Some(k))))
                .unwrap_or((part, None));
            match num.parse::<f64>() {
                Ok(v) => Ok((v, scale)),
                Err(_) => {
                    let letters = part.len() - part.trim_end_matches(|c: char| c.is_alphabetic()).len();
                    let (n, unit) = part.split_at(part.len() - letters);
                    if letters > 0 && n.trim().parse::<f64>().is_ok() {
                        Err(format!("unknown mass unit '{unit}' in '{text}': use kg, g or mg"))
                    } else {
                        Err(not_a_mass())
                    }
                }
            }
        };
        let (v, v_unit) = quantity(value)?;
        let (s, s_unit) = match sd {
            Some(sd) => quantity(sd)?,
            None => (0.0, None),
        };
        // "15.3±0.3g": the sd's unit is the value's too.
        let v_scale = v_unit.or(s_unit).unwrap_or(1.0);
        let m = Mass { kg: v * v_scale, sd_kg: s * s_unit.unwrap_or(v_scale) };
        if !(m.kg.is_finite() && m.kg > 0.0 && m.kg < 10.0) {
            return Err(format!("'{text}' = {} kg is not a moving or added mass (0 .. 10 kg)", m.kg));
        }
        if !(m.sd_kg.is_finite() && m.sd_kg >= 0.0 && m.sd_kg < 0.5 * m.kg) {
            return Err(format!(
                "'{text}': the sd {} kg is not valid: it must be at least 0 and less than half the mass ({} kg)",
                m.sd_kg, m.kg
            ));
        }
        Ok(m)
    }
}

/// The power of the moving mass a figure scales with, in a fit from voltage and current whose
/// absolute scale is the mass: Bl 1/2; Kms, Rms and Mms 1; every electrical figure (Re, Le,
/// the branches), creep's lambda and the thermal figures 0.
pub fn mass_power(key: &str) -> f64 {
    match key {
        "Bl" => 0.5,
        "Kms" | "Rms" | "Mms" => 1.0,
        _ => 0.0,
    }
}

/// How a curve of the large-signal model moves with the mass at the displacement `x`:
/// `d ln F(x) / d ln Mms`. With the mass `s` times larger the same current needs
/// `Bl'(x) = sqrt(s) Bl(x sqrt(s))`, `Kms'(x) = s Kms(x sqrt(s))` and `Le'(x) = Le(x sqrt(s))`
/// (the displacement shrinks by `sqrt(s)`), so a curve of power `p` ([`mass_power`]: Bl,
/// Kms, and 0 for Le) moves by `p + x F'(x) / (2 F(x))`.
pub fn curve_mass_sensitivity(which: &str, curve: &crate::Poly, x: f64) -> f64 {
    let (f, df) = curve.eval_d(x);
    mass_power(which) + 0.5 * x * df / f
}

/// The scale's share of each figure's sd at rest (its units), for a mass known to `sd_rel`:
/// `power * sd_rel * value` of Bl, Kms, Rms and Mms ([`mass_power`]).
pub fn scale_share(p: &crate::Parameters, sd_rel: f64) -> Vec<(&'static str, f64)> {
    [("Bl", p.bl.c[0]), ("Kms", p.kms.c[0]), ("Rms", p.rms), ("Mms", p.mms)]
        .into_iter()
        .map(|(k, v)| (k, mass_power(k) * sd_rel * v.abs()))
        .collect()
}

impl fmt::Display for Mass {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.sd_kg > 0.0 {
            write!(f, "{:.4} g ± {:.4} g", self.kg * 1e3, self.sd_kg * 1e3)
        } else {
            write!(f, "{:.4} g", self.kg * 1e3)
        }
    }
}

impl std::str::FromStr for Mass {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Mass::parse(s)
    }
}

#[cfg(test)]
mod tests {
    use super::Mass;

    #[test]
    fn a_mass_reads_with_its_unit_and_its_sd() {
        let close = |a: Mass, kg: f64, sd: f64| (a.kg - kg).abs() < 1e-15 && (a.sd_kg - sd).abs() < 1e-15;
        assert!(close(Mass::parse("0.0153").unwrap(), 0.0153, 0.0));
        assert!(close(Mass::parse("15.3g").unwrap(), 0.0153, 0.0));
        assert!(close(Mass::parse("15.3g±0.3g").unwrap(), 0.0153, 0.0003));
        assert!(close(Mass::parse("15.3±0.3g").unwrap(), 0.0153, 0.0003));
        assert!(close(Mass::parse("15.3 g +- 300 mg").unwrap(), 0.0153, 0.0003));
        assert!(close(Mass::parse("0.0153±0.0003").unwrap(), 0.0153, 0.0003));
        assert!(close(Mass::parse("230mg").unwrap(), 0.00023, 0.0));
        assert!(close(Mass::parse("1.53e-2±3e-4").unwrap(), 0.0153, 0.0003));
        assert!((Mass::parse("15g±0.3g").unwrap().sd_rel() - 0.02).abs() < 1e-12);
    }

    #[test]
    fn a_mass_that_is_not_one_is_refused_by_name() {
        for (text, says) in [
            ("15.3 lb", "unknown mass unit 'lb'"),
            ("heavy", "is not a mass"),
            ("-3g", "not a moving or added mass"),
            ("15g±9g", "less than half the mass"),
            ("15g±-1g", "at least 0"),
            ("NaN", "not a moving or added mass"),
            ("1e400", "not a moving or added mass"),
        ] {
            let e = Mass::parse(text).unwrap_err();
            assert!(e.contains(says) && e.contains(text), "{text}: {e}");
        }
    }
}

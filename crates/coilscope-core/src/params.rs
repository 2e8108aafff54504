//! Parameter sets (`"format": "coilscope.parameters/1"`, see `docs/formats.md`).
//!
//! A value is a number (a constant) or an ascending SI power series in x (metres). Parsing
//! is strict about what the contract defines and lenient about what it does not: unknown keys
//! (such as `published_curves`) are kept and written back, so files round-trip unchanged.
//! Every error names the origin (file or embedded driver), the key, the value, and what
//! would be valid.

use crate::poly::Poly;
pub use crate::schema::Value as SchemaValue;
use serde_json::{Map, Value};
use std::fmt;

/// The format tag of a parameter set.
pub const PARAMETERS_FORMAT: &str = "coilscope.parameters/1";

/// Copper's temperature coefficient of resistance (1/K), used when `thermal.alpha` is absent.
pub const ALPHA_COPPER: f64 = 0.00393;

/// Two-node thermal model (voice coil and magnet), temperatures as rises above ambient.
#[derive(Clone, Debug, PartialEq)]
pub struct Thermal {
    /// Temperature coefficient of Re (1/K).
    pub alpha: f64,
    /// Voice coil to magnet thermal resistance (K/W).
    pub rtv: f64,
    /// Voice-coil heat capacity (J/K).
    pub ctv: f64,
    /// Magnet to ambient thermal resistance (K/W).
    pub rtm: f64,
    /// Magnet heat capacity (J/K).
    pub ctm: f64,
    /// Convection cooling of the coil (s/m): the coil-to-magnet resistance falls with the
    /// coil's speed, `Rtv(v) = Rtv / (1 + rv |v|)` (the form of Klippel's heat-transfer
    /// model, AES 2003; instantaneous |v|, which the thermal time constants average). 0: none
    /// (the key `thermal.rv` is then absent from the file).
    pub rv: f64,
}

/// LOG creep of the suspension (`creep`, see [`crate::creep`] for its realisation).
#[derive(Clone, Debug, PartialEq)]
pub struct Creep {
    /// Klippel's LOG creep factor: `Cms(f) = Cms(f_ref) (1 - lambda log10(f / f_ref))`.
    pub lambda: f64,
    /// Reference frequency (Hz) where `Kms` is the dynamic stiffness; `None`: the
    /// resonance `sqrt(Kms(0) / Mms) / 2 pi`.
    pub f_ref: Option<f64>,
}

/// A validated parameter set in SI units.
#[derive(Clone, Debug, PartialEq)]
pub struct Parameters {
    pub name: Option<String>,
    pub source: Option<String>,
    /// DC resistance of the voice coil at ambient temperature (ohm).
    pub re: f64,
    /// Voice-coil inductance Le(x) (H).
    pub le: Poly,
    /// LR-2 para-inductance L2(x) (H) and its resistance R2(x) (ohm); both or neither.
    pub l2r2: Option<(Poly, Poly)>,
    /// Force factor Bl(x) (T m).
    pub bl: Poly,
    /// Secant stiffness Kms(x) (N/m): restoring force Kms(x) x.
    pub kms: Poly,
    /// Moving mass (kg).
    pub mms: f64,
    /// Mechanical resistance (kg/s).
    pub rms: f64,
    /// Effective radiating area (m^2).
    pub sd: Option<f64>,
    /// Viscoelastic creep of the suspension (absent: not modelled).
    pub creep: Option<Creep>,
    /// A second para-inductance branch L3 (H) || R3 (ohm), in series with LR-2, independent
    /// of x (absent: not modelled).
    pub l3r3: Option<(f64, f64)>,
    /// Flux modulation (`Le_i`): ascending power series in the current (A) of the factor
    /// `g(i)` in the flux `psi = Le(x) g(i) i`, with `g(0) = 1` (absent: not modelled).
    pub le_i: Option<Poly>,
    /// Velocity-dependent mechanical loss (`Rms_v`): ascending power series in `|v|` (m/s)
    /// of `Rms(|v|)` (kg/s), replacing `Rms` in the model; `Rms_v(0) = Rms` (absent: not
    /// modelled).
    pub rms_v: Option<Poly>,
    pub thermal: Option<Thermal>,
    /// The box the driver works into (absent: free air; see [`crate::enclosure`]).
    pub enclosure: Option<crate::enclosure::Enclosure>,
    /// Where the x-dependent functions are valid (m).
    pub x_range: Option<[f64; 2]>,
    /// Keys this version does not interpret, kept verbatim (e.g. `published_curves`).
    pub extra: Map<String, Value>,
}

/// Figures other tools write beside a parameter set (the Thiele/Small figures derived from
/// it): unknown to the contract, kept as every unknown key is, and never taken for a
/// misspelling of a key they resemble (`Qms` is one edit from `Rms`).
const DERIVED_FIGURES: &[&str] =
    &["fs", "Fs", "Qms", "Qes", "Qts", "Vas", "Cms", "Res", "Xmax", "Xlim", "EBP", "Vd", "SPL", "Sens", "Znom"];

impl Parameters {
    /// The keys of the set that the contract does not define but that lie within one edit of
    /// one it does (two for keys of five letters or more), each with the known key it likely
    /// meant: `Bll` beside `Bl`. They are kept, as every unknown key is, but a misspelt key
    /// leaves the parameter meant absent, so readers warn about each (case-only differences
    /// are refused outright when the file is read).
    pub fn near_miss_keys(&self) -> Vec<(String, &'static str)> {
        let known = crate::schema::file_keys();
        self.extra
            .keys()
            .filter(|k| !DERIVED_FIGURES.contains(&k.as_str()))
            .filter_map(|k| {
                let (d, nearest) =
                    known.iter().map(|kk| (strsim::damerau_levenshtein(k, kk), *kk)).min_by_key(|(d, _)| *d)?;
                let allowed = if k.chars().count() >= 5 { 2 } else { 1 };
                (d <= allowed).then(|| (k.clone(), nearest))
            })
            .collect()
    }
}

/// A parameter-file problem, with where it is and what would be valid.
#[derive(Clone, Debug, PartialEq)]
pub struct ParamError {
    /// File path or `embedded driver NAME`.
    pub origin: String,
    /// The key at fault (empty for whole-file problems).
    pub key: String,
    pub message: String,
}

impl fmt::Display for ParamError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.key.is_empty() {
            write!(f, "{}: {}", self.origin, self.message)
        } else {
            write!(f, "{}: key `{}`: {}", self.origin, self.key, self.message)
        }
    }
}

impl std::error::Error for ParamError {}

/// LOG creep factor assumed for a real driver whose creep was not published (the middle of
/// the 0.03-0.08 Klippel LPM reports for woofer suspensions); see
/// [`Parameters::with_typical_creep`].
pub const TYPICAL_CREEP_LAMBDA: f64 = 0.05;

struct Ctx<'a> {
    origin: &'a str,
}

impl Ctx<'_> {
    fn err(&self, key: &str, message: impl Into<String>) -> ParamError {
        ParamError { origin: self.origin.to_string(), key: key.to_string(), message: message.into() }
    }

    fn number(&self, key: &str, v: &Value) -> Result<f64, ParamError> {
        match v {
            Value::Number(n) => {
                let f = n.as_f64().ok_or_else(|| self.err(key, format!("{n} is not a finite number")))?;
                if f.is_finite() {
                    Ok(f)
                } else {
                    Err(self.err(key, format!("{n} is not finite; give a finite number in SI units")))
                }
            }
            other => Err(self.err(key, format!("expected a number (SI units), found {}", describe(other)))),
        }
    }

    fn series(&self, key: &str, v: &Value) -> Result<Poly, ParamError> {
        match v {
            Value::Number(_) => Ok(Poly::constant(self.number(key, v)?)),
            Value::Array(items) if items.is_empty() => Err(self.err(
                key,
                "empty power series; give a number or ascending coefficients [c0, c1, ...] in SI (x in metres)",
            )),
            Value::Array(items) => {
                let mut c = Vec::with_capacity(items.len());
                for (j, item) in items.iter().enumerate() {
                    match item {
                        Value::Number(_) => c.push(
                            self.number(key, item)
                                .map_err(|e| self.err(key, format!("coefficient c{j}: {}", e.message)))?,
                        ),
                        other => {
                            return Err(
                                self.err(key, format!("coefficient c{j} must be a number, found {}", describe(other)))
                            )
                        }
                    }
                }
                if c.len() > 16 {
                    return Err(self.err(key, format!("{} coefficients; at most 16 (order 15) are supported", c.len())));
                }
                Ok(Poly { c })
            }
            other => Err(self.err(
                key,
                format!("expected a number or an array of power-series coefficients, found {}", describe(other)),
            )),
        }
    }
}

fn describe(v: &Value) -> String {
    match v {
        Value::Null => "null".into(),
        Value::Bool(b) => format!("the boolean {b}"),
        Value::Number(n) => format!("the number {n}"),
        Value::String(s) => format!("the string {s:?}"),
        Value::Array(_) => "an array".into(),
        Value::Object(_) => "an object".into(),
    }
}

impl Parameters {
    /// Parse and validate a parameter set from JSON text. `origin` names it in errors.
    pub fn from_json_str(text: &str, origin: &str) -> Result<Self, ParamError> {
        let value: Value = serde_json::from_str(text).map_err(|e| ParamError {
            origin: origin.to_string(),
            key: String::new(),
            message: format!(
                "not valid JSON ({e}); a parameter set is a JSON object, see docs/formats.md in coilscope's repository"
            ),
        })?;
        Self::from_json_value(&value, origin)
    }

    /// Parse and validate a parameter set from a JSON value.
    pub fn from_json_value(value: &Value, origin: &str) -> Result<Self, ParamError> {
        let ctx = Ctx { origin };
        let obj = value.as_object().ok_or_else(|| {
            ctx.err(
                "",
                format!(
                    "expected a JSON object with keys {}; found {}",
                    crate::schema::required_keys(),
                    describe(value)
                ),
            )
        })?;
        if let Some(f) = obj.get("format") {
            if f.as_str() != Some(PARAMETERS_FORMAT) {
                return Err(ctx.err("format", format!("{} is not {PARAMETERS_FORMAT:?}", describe(f))));
            }
        }
        // A misspelt key would silently drop a parameter: refuse near-misses of known keys.
        let known_keys = crate::schema::file_keys();
        for k in obj.keys() {
            if !known_keys.contains(&k.as_str()) {
                if let Some(known) = known_keys.iter().find(|kk| kk.eq_ignore_ascii_case(k.trim())) {
                    return Err(ctx.err(k, format!("unknown key; did you mean `{known}`? (keys are case-sensitive)")));
                }
            }
        }
        let required = |key: &str| -> Result<&Value, ParamError> {
            obj.get(key).ok_or_else(|| ctx.err(key, format!("missing (required: {})", crate::schema::required_keys())))
        };
        let text = |key: &str| -> Result<Option<String>, ParamError> {
            match obj.get(key) {
                None | Some(Value::Null) => Ok(None),
                Some(Value::String(s)) => Ok(Some(s.clone())),
                Some(other) => Err(ctx.err(key, format!("expected a string, found {}", describe(other)))),
            }
        };

        let re = ctx.number("Re", required("Re")?)?;
        let le = ctx.series("Le", required("Le")?)?;
        let bl = ctx.series("Bl", required("Bl")?)?;
        let kms = ctx.series("Kms", required("Kms")?)?;
        let mms = ctx.number("Mms", required("Mms")?)?;
        let rms = ctx.number("Rms", required("Rms")?)?;
        let l2r2 = match (obj.get("L2"), obj.get("R2")) {
            (None, None) => None,
            (Some(l2), Some(r2)) => Some((ctx.series("L2", l2)?, ctx.series("R2", r2)?)),
            (Some(_), None) => {
                return Err(ctx.err("R2", "missing: L2 is given, and the LR-2 branch needs both L2 and R2"))
            }
            (None, Some(_)) => {
                return Err(ctx.err("L2", "missing: R2 is given, and the LR-2 branch needs both L2 and R2"))
            }
        };
        let sd = obj.get("Sd").map(|v| ctx.number("Sd", v)).transpose()?;
        let x_range = match obj.get("x_range") {
            None => None,
            Some(Value::Array(a)) if a.len() == 2 => {
                Some([ctx.number("x_range", &a[0])?, ctx.number("x_range", &a[1])?])
            }
            Some(other) => {
                return Err(ctx.err("x_range", format!("expected [x_min, x_max] in metres, found {}", describe(other))))
            }
        };
        let thermal = match obj.get("thermal") {
            None | Some(Value::Null) => None,
            Some(Value::Object(t)) => {
                let get = |k: &str| -> Result<f64, ParamError> {
                    let key = format!("thermal.{k}");
                    ctx.number(
                        &key,
                        t.get(k).ok_or_else(|| {
                            ctx.err(&key, "missing (thermal needs Rtv, Ctv, Rtm, Ctm; alpha is optional)")
                        })?,
                    )
                };
                let alpha = match t.get("alpha") {
                    None => ALPHA_COPPER,
                    Some(v) => ctx.number("thermal.alpha", v)?,
                };
                let rv = match t.get("rv") {
                    None => 0.0,
                    Some(v) => ctx.number("thermal.rv", v)?,
                };
                Some(Thermal { alpha, rtv: get("Rtv")?, ctv: get("Ctv")?, rtm: get("Rtm")?, ctm: get("Ctm")?, rv })
            }
            Some(other) => {
                return Err(ctx.err(
                    "thermal",
                    format!("expected an object {{alpha, Rtv, Ctv, Rtm, Ctm}}, found {}", describe(other)),
                ))
            }
        };
        let creep = match obj.get("creep") {
            None | Some(Value::Null) => None,
            Some(Value::Object(c)) => {
                let lambda = ctx.number(
                    "creep.lambda",
                    c.get("lambda").ok_or_else(|| {
                        ctx.err("creep.lambda", "missing (creep needs lambda, Klippel's LOG creep factor, e.g. 0.05)")
                    })?,
                )?;
                let f_ref = c.get("f_ref").map(|v| ctx.number("creep.f_ref", v)).transpose()?;
                for (k, want) in [
                    ("per_decade", crate::creep::PER_DECADE as f64),
                    ("f_min", crate::creep::F_MIN),
                    ("f_max", crate::creep::F_MAX),
                ] {
                    if let Some(v) = c.get(k) {
                        let got = ctx.number(&format!("creep.{k}"), v)?;
                        if (got - want).abs() > 1e-9 * want {
                            return Err(ctx.err(
                                &format!("creep.{k}"),
                                format!("{got}: coilscope realises creep with {} Maxwell elements per decade from {} to {} Hz; {k} must be {want} (or absent)", crate::creep::PER_DECADE, crate::creep::F_MIN, crate::creep::F_MAX),
                            ));
                        }
                    }
                }
                Some(Creep { lambda, f_ref })
            }
            Some(other) => {
                return Err(
                    ctx.err("creep", format!("expected an object {{\"lambda\": 0.05}}, found {}", describe(other)))
                )
            }
        };
        let constant = |key: &str, v: &Value| -> Result<f64, ParamError> {
            match v {
                Value::Array(_) => Err(ctx.err(
                    key,
                    format!("{key} is a constant here (the LR-3 branch does not depend on x); give a number"),
                )),
                _ => ctx.number(key, v),
            }
        };
        let l3r3 = match (obj.get("L3"), obj.get("R3")) {
            (None, None) => None,
            (Some(l3), Some(r3)) => Some((constant("L3", l3)?, constant("R3", r3)?)),
            (Some(_), None) => {
                return Err(ctx.err("R3", "missing: L3 is given, and the LR-3 branch needs both L3 and R3"))
            }
            (None, Some(_)) => {
                return Err(ctx.err("L3", "missing: R3 is given, and the LR-3 branch needs both L3 and R3"))
            }
        };
        let enclosure = match obj.get("enclosure") {
            None | Some(Value::Null) => None,
            Some(v) => Some(crate::enclosure::Enclosure::from_json(v, &|k, m| ctx.err(k, m))?),
        };
        let le_i = obj.get("Le_i").map(|v| ctx.series("Le_i", v)).transpose()?;
        let rms_v = obj.get("Rms_v").map(|v| ctx.series("Rms_v", v)).transpose()?;
        let extra: Map<String, Value> = obj
            .iter()
            .filter(|(k, _)| !known_keys.contains(&k.as_str()))
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect();
        let p = Parameters {
            name: text("name")?,
            source: text("source")?,
            re,
            le,
            l2r2,
            bl,
            kms,
            mms,
            rms,
            sd,
            creep,
            l3r3,
            le_i,
            rms_v,
            thermal,
            enclosure,
            x_range,
            extra,
        };
        p.validate(origin)?;
        Ok(p)
    }

    /// Check physical sense and likely unit mistakes. Called by the parsers; call it again
    /// after editing a set by hand.
    pub fn validate(&self, origin: &str) -> Result<(), ParamError> {
        let ctx = Ctx { origin };
        let positive = |key: &str, v: f64, unit: &str| -> Result<(), ParamError> {
            if v > 0.0 {
                Ok(())
            } else {
                Err(ctx.err(key, format!("{v} {unit} must be > 0")))
            }
        };
        positive("Re", self.re, "ohm")?;
        positive("Mms", self.mms, "kg")?;
        if self.rms < 0.0 {
            return Err(ctx.err("Rms", format!("{} kg/s must be >= 0", self.rms)));
        }
        // Plausibility: a loudspeaker, headphone, microspeaker or shaker, in SI units.
        if self.mms > 2.0 {
            return Err(ctx.err(
                "Mms",
                format!(
                    "{} kg is not a plausible moving mass (expected 1e-6 .. 2 kg); it looks like grams: {} g = {} kg",
                    self.mms,
                    self.mms,
                    self.mms / 1000.0
                ),
            ));
        }
        if self.mms < 1e-7 {
            return Err(ctx.err("Mms", format!("{} kg is implausibly small (expected 1e-6 .. 2 kg)", self.mms)));
        }
        if self.re > 5000.0 || self.re < 0.01 {
            return Err(ctx.err(
                "Re",
                format!("{} ohm is not a plausible voice-coil resistance (expected 0.01 .. 5000 ohm)", self.re),
            ));
        }
        let le0 = self.le.c[0];
        if le0 > 0.1 {
            return Err(ctx.err("Le", format!("Le(0) = {le0} H is not a plausible voice-coil inductance (expected < 0.1 H); it looks like millihenry: {le0} mH = {} H", le0 / 1000.0)));
        }
        let bl0 = self.bl.c[0];
        if bl0 > 200.0 {
            return Err(ctx.err("Bl", format!("Bl(0) = {bl0} T m is not plausible (expected < 200 T m)")));
        }
        let kms0 = self.kms.c[0];
        if kms0 > 0.0 && kms0 < 0.5 {
            return Err(ctx.err("Kms", format!("Kms(0) = {kms0} N/m is implausibly soft; it looks like a compliance Cms in m/N: Kms = 1/Cms = {:.4} N/m", 1.0 / kms0)));
        }
        if let Some(sd) = self.sd {
            if !(sd > 0.0) {
                return Err(ctx.err("Sd", format!("{sd} m^2 must be > 0")));
            }
            if sd > 2.0 {
                return Err(ctx.err(
                    "Sd",
                    format!(
                        "{sd} m^2 is not plausible (expected < 2 m^2); it looks like cm^2: {sd} cm^2 = {} m^2",
                        sd * 1e-4
                    ),
                ));
            }
        }
        if let Some(e) = &self.enclosure {
            if self.sd.is_none() {
                return Err(ctx.err(
                    "Sd",
                    format!("missing: a driver in a box ({} enclosure) needs its radiating area Sd in m^2, the area the box air pushes on", e.type_name()),
                ));
            }
            e.check(&|k, m| ctx.err(k, m))?;
        }
        if let Some(c) = &self.creep {
            if !(c.lambda >= 0.0 && c.lambda < 0.5) {
                return Err(ctx.err(
                    "creep.lambda",
                    format!(
                        "{} is not a plausible LOG creep factor (expected 0 .. 0.5; typical 0.03 .. 0.1)",
                        c.lambda
                    ),
                ));
            }
            if let Some(f) = c.f_ref {
                if !(f > 0.0 && f < 1e5) {
                    return Err(ctx
                        .err("creep.f_ref", format!("{f} Hz must be > 0 (and below 100 kHz); absent: the resonance")));
                }
            }
        }
        if let Some((l3, r3)) = self.l3r3 {
            if !(l3 > 0.0 && l3 < 0.1) {
                return Err(ctx.err(
                    "L3",
                    format!("{l3} H is not a plausible para-inductance (expected 0 .. 0.1 H; give H, not mH)"),
                ));
            }
            if !(r3 > 0.0 && r3 < 1e4) {
                return Err(ctx.err("R3", format!("{r3} ohm must be > 0 (and below 10 kohm)")));
            }
        }
        if let Some(g) = &self.le_i {
            if (g.c[0] - 1.0).abs() > 1e-9 {
                return Err(ctx.err("Le_i", format!("the factor g(i) must be 1 at i = 0 (Le(x) is the inductance at rest), but its c0 is {}; divide the series by c0 and fold c0 into Le", g.c[0])));
            }
        }
        if let Some(r) = &self.rms_v {
            if !(r.c[0] >= 0.0) || (r.c[0] - self.rms).abs() > 1e-6 * self.rms.max(1e-12) {
                return Err(ctx.err(
                    "Rms_v",
                    format!("Rms_v(0) = {} kg/s must equal Rms = {} kg/s (Rms is the value at rest)", r.c[0], self.rms),
                ));
            }
            let (mn, _) = r.min_max_on(0.0, 10.0);
            if !(mn >= 0.0) {
                return Err(ctx.err("Rms_v", format!("Rms(|v|) must stay >= 0 for |v| up to 10 m/s, but it reaches {mn:.4e} kg/s; check the coefficients (SI: |v| in m/s)")));
            }
        }
        if let Some([lo, hi]) = self.x_range {
            if !(lo < 0.0 && hi > 0.0) {
                return Err(
                    ctx.err("x_range", format!("[{lo}, {hi}] must contain the rest position: x_min < 0 < x_max (m)"))
                );
            }
            if hi - lo > 0.2 {
                return Err(ctx.err(
                    "x_range",
                    format!(
                        "[{lo}, {hi}] m spans more than 0.2 m; it looks like millimetres: [{lo}, {hi}] mm = [{}, {}] m",
                        lo / 1000.0,
                        hi / 1000.0
                    ),
                ));
            }
        }
        if let Some(t) = &self.thermal {
            for (k, v) in
                [("thermal.Rtv", t.rtv), ("thermal.Ctv", t.ctv), ("thermal.Rtm", t.rtm), ("thermal.Ctm", t.ctm)]
            {
                if !(v > 0.0) {
                    return Err(ctx.err(k, format!("{v} must be > 0")));
                }
            }
            if !(t.rv >= 0.0 && t.rv < 1000.0) {
                return Err(ctx.err(
                    "thermal.rv",
                    format!("{} s/m is not valid (0 .. 1000 s/m: Rtv(v) = Rtv / (1 + rv |v|), v in m/s)", t.rv),
                ));
            }
            if !(t.alpha >= 0.0 && t.alpha < 0.02) {
                return Err(ctx.err(
                    "thermal.alpha",
                    format!("{} 1/K is not plausible (copper: 0.00393, aluminium: 0.0040)", t.alpha),
                ));
            }
        }
        // x-dependent functions must stay positive where they are valid.
        let (lo, hi) = match self.x_range {
            Some([lo, hi]) => (lo, hi),
            None => (0.0, 0.0),
        };
        let where_ =
            if self.x_range.is_some() { format!("inside x_range [{lo}, {hi}] m") } else { "at x = 0".to_string() };
        let funcs =
            crate::schema::ENTRIES.iter().filter(|e| e.kind == crate::schema::Kind::SeriesX).filter_map(|e| match self
                .get(e.key)
            {
                Some(SchemaValue::Series(p)) => Some((e.key, p, e.unit)),
                _ => None,
            });
        for (key, p, unit) in funcs {
            let (mn, _) = p.min_max_on(lo, hi);
            if !(mn > 0.0) {
                let xm = argmin_on(p, lo, hi);
                return Err(ctx.err(key, format!("{key}(x) must be > 0 {where_}, but {key}({xm:.6} m) = {mn:.6e} {unit}; check the coefficients (SI: x in metres) or narrow x_range")));
            }
        }
        Ok(())
    }

    /// The range where the x-dependent parameters may be evaluated. Without `x_range`, the
    /// polynomials are trusted as far as they stay positive (checked while simulating).
    pub fn valid_range(&self) -> Option<[f64; 2]> {
        self.x_range
    }

    /// The value of a [`crate::schema`] key (`"Re"`, `"Le"`, `"thermal.Rtv"`, ...), or `None`
    /// when the set does not have it (or the key is not in the schema).
    pub fn get(&self, key: &str) -> Option<SchemaValue<'_>> {
        use SchemaValue as V;
        let creep = |f: &dyn Fn(&Creep) -> Option<f64>| self.creep.as_ref().and_then(f).map(V::Number);
        let thermal = |f: &dyn Fn(&Thermal) -> f64| self.thermal.as_ref().map(|t| V::Number(f(t)));
        match key {
            "name" => self.name.as_deref().map(V::Text),
            "source" => self.source.as_deref().map(V::Text),
            "Re" => Some(V::Number(self.re)),
            "Le" => Some(V::Series(&self.le)),
            "Le_i" => self.le_i.as_ref().map(V::Series),
            "L2" => self.l2r2.as_ref().map(|(l, _)| V::Series(l)),
            "R2" => self.l2r2.as_ref().map(|(_, r)| V::Series(r)),
            "L3" => self.l3r3.map(|(l, _)| V::Number(l)),
            "R3" => self.l3r3.map(|(_, r)| V::Number(r)),
            "Bl" => Some(V::Series(&self.bl)),
            "Kms" => Some(V::Series(&self.kms)),
            "creep.lambda" => creep(&|c| Some(c.lambda)),
            "creep.f_ref" => creep(&|c| c.f_ref),
            "creep.per_decade" => creep(&|_| Some(crate::creep::PER_DECADE as f64)),
            "creep.f_min" => creep(&|_| Some(crate::creep::F_MIN)),
            "creep.f_max" => creep(&|_| Some(crate::creep::F_MAX)),
            "Mms" => Some(V::Number(self.mms)),
            "Rms" => Some(V::Number(self.rms)),
            "Rms_v" => self.rms_v.as_ref().map(V::Series),
            "Sd" => self.sd.map(V::Number),
            "thermal.alpha" => thermal(&|t| t.alpha),
            "thermal.Rtv" => thermal(&|t| t.rtv),
            "thermal.Ctv" => thermal(&|t| t.ctv),
            "thermal.Rtm" => thermal(&|t| t.rtm),
            "thermal.Ctm" => thermal(&|t| t.ctm),
            "thermal.rv" => self.thermal.as_ref().filter(|t| t.rv > 0.0).map(|t| V::Number(t.rv)),
            "x_range" => self.x_range.map(V::Range),
            k if k.starts_with("enclosure.") => self.enclosure_value(&k["enclosure.".len()..]),
            _ => None,
        }
    }

    /// A value of the box (`Vb`, `fb`, ...; [`Parameters::get`] with `enclosure.` taken off).
    fn enclosure_value(&self, key: &str) -> Option<SchemaValue<'_>> {
        self.enclosure.as_ref()?.value(key)
    }

    /// The constants and the functions of x at rest (their `c0`) the set has, in the schema's
    /// order, without the creep bank's realisation keys: what a table of values shows.
    pub fn values_at_rest(&self) -> impl Iterator<Item = (&'static crate::schema::Entry, f64)> + '_ {
        use crate::schema::{Kind, ENTRIES};
        ENTRIES
            .iter()
            .filter(|e| !e.realisation && matches!(e.kind, Kind::Number | Kind::SeriesX | Kind::SeriesXp))
            .filter_map(|e| self.get(e.key).and_then(|v| v.at_rest()).map(|v| (e, v)))
    }

    /// Write the set as contract JSON (constants as numbers, series in x as a number when
    /// constant, else arrays), every [`crate::schema`] entry the set has, and the unknown keys
    /// kept.
    pub fn to_json_value(&self) -> Value {
        let mut m = Map::new();
        m.insert("format".into(), PARAMETERS_FORMAT.into());
        for e in crate::schema::ENTRIES {
            let Some(v) = self.get(e.key) else { continue };
            let json = v.to_json(e.kind);
            match e.key.split_once('.') {
                Some((object, k)) => {
                    if let Value::Object(o) = m.entry(object).or_insert_with(|| Value::Object(Map::new())) {
                        o.insert(k.into(), json);
                    }
                }
                None => {
                    m.insert(e.key.into(), json);
                }
            }
        }
        for (k, v) in &self.extra {
            m.insert(k.clone(), v.clone());
        }
        Value::Object(m)
    }

    /// The same driver without the LR-2 branch and the thermal model: the three-state model
    /// of the seed paper (x, v, i).
    pub fn three_state(&self) -> Parameters {
        Parameters { l2r2: None, l3r3: None, creep: None, le_i: None, rms_v: None, thermal: None, ..self.clone() }
    }

    /// The set in the world of a real driver, as far as the published data leave it open:
    /// LOG creep with [`TYPICAL_CREEP_LAMBDA`] where the set has none (an assumption: the
    /// bundled drivers' reviews published no creep factor, and Klippel LPM reports 0.03-0.08
    /// for woofer suspensions). LR-3, Le(i) and Rms(v) are added only where published: none
    /// of the bundled drivers has them.
    pub fn with_typical_creep(&self) -> Parameters {
        let mut p = self.clone();
        if p.creep.is_none() {
            p.creep = Some(Creep { lambda: TYPICAL_CREEP_LAMBDA, f_ref: None });
        }
        p
    }

    /// The reference frequency of the creep (Hz): `creep.f_ref`, or the resonance.
    pub fn creep_f_ref(&self) -> Option<f64> {
        self.creep.as_ref().map(|c| c.f_ref.unwrap_or_else(|| self.resonance_hz()))
    }

    /// The mechanical resonance at rest, `sqrt(Kms(0) / Mms) / 2 pi` (Hz).
    pub fn resonance_hz(&self) -> f64 {
        (self.kms.c[0] / self.mms).sqrt() / (2.0 * std::f64::consts::PI)
    }

    /// Whether the set has an effect with states of its own (creep, LR-3, a box), which needs
    /// [`crate::model::ExtModel`]; without one, [`crate::model::Model`] is the same model,
    /// faster (it has Le(i) and Rms(v)).
    pub fn needs_ext_states(&self) -> bool {
        self.creep.is_some() || self.l3r3.is_some() || self.enclosure.is_some()
    }

    /// Electrical time constant of the fast mode, min over the valid range of
    /// `Le(x) / (Re + R2(x) + R3)` (s): what makes the current equation stiff.
    pub fn min_electrical_time_constant(&self) -> f64 {
        let (lo, hi) = self.x_range.map(|r| (r[0], r[1])).unwrap_or((0.0, 0.0));
        let (le_min, _) = self.le.min_max_on(lo, hi);
        let r2_max = self.l2r2.as_ref().map(|(_, r2)| r2.min_max_on(lo, hi).1).unwrap_or(0.0);
        let r3 = self.l3r3.map_or(0.0, |(_, r3)| r3);
        le_min / (self.re + r2_max + r3)
    }

    /// The electrical rates that set the integration steps
    /// ([`crate::integrate::exp_steps_for`]): the LR-2 network's (Re and R2 over the
    /// smallest Le in the range, plus R2 / L2) and the LR-3 branch's (`R3 / Le + R3 / L3`).
    pub fn rates(&self) -> crate::integrate::Rates {
        let (lo, hi) = self.x_range.map(|r| (r[0], r[1])).unwrap_or((0.0, 0.0));
        let le_min = self.le.min_max_on(lo, hi).0;
        let mut stiff = self.re / le_min;
        if let Some((l2, r2)) = &self.l2r2 {
            let r2_max = r2.min_max_on(lo, hi).1;
            stiff += r2_max / le_min + r2_max / l2.min_max_on(lo, hi).0;
        }
        let lr3 = self.l3r3.map_or(0.0, |(l3, r3)| r3 / le_min + r3 / l3);
        crate::integrate::Rates { stiff, lr3 }
    }

    /// Largest magnitude of the system's fast eigenvalues, an upper bound (1/s): the
    /// Le-branch rate plus the L2-branch rate, at the valid range's worst point.
    /// (The sum of [`Parameters::rates`]: one computation of the rates.)
    pub fn stiffness_rate(&self) -> f64 {
        self.rates().total()
    }
}

fn argmin_on(p: &Poly, lo: f64, hi: f64) -> f64 {
    let n = 2000;
    (0..=n)
        .map(|k| lo + (hi - lo) * k as f64 / n as f64)
        .min_by(|a, b| p.eval(*a).total_cmp(&p.eval(*b)))
        .unwrap_or(0.0)
}

/// The real drivers bundled with coilscope (Klippel LSI measurements, see `drivers/README`).
pub const EMBEDDED_DRIVERS: &[(&str, &str)] = &[
    ("sb17cac35-4", include_str!("../drivers/sb17cac35-4.json")),
    ("ptt4.0w04-01a", include_str!("../drivers/ptt4.0w04-01a.json")),
    ("18wu-4741t-00", include_str!("../drivers/18wu-4741t-00.json")),
];

/// The names of the embedded drivers.
pub fn embedded_driver_names() -> Vec<&'static str> {
    EMBEDDED_DRIVERS.iter().map(|(n, _)| *n).collect()
}

/// An embedded driver by name (case-insensitive), or None.
pub fn embedded_driver(name: &str) -> Option<Parameters> {
    EMBEDDED_DRIVERS.iter().find(|(n, _)| n.eq_ignore_ascii_case(name)).map(|(n, text)| {
        Parameters::from_json_str(text, &format!("embedded driver {n}"))
            .expect("embedded drivers are validated by the test suite")
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sb17() -> Value {
        serde_json::from_str(EMBEDDED_DRIVERS[0].1).unwrap()
    }

    fn err_of(v: Value) -> String {
        Parameters::from_json_value(&v, "test.json").unwrap_err().to_string()
    }

    #[test]
    fn embedded_drivers_parse_and_round_trip() {
        for name in embedded_driver_names() {
            let p = embedded_driver(name).unwrap();
            let again = Parameters::from_json_value(&p.to_json_value(), "again").unwrap();
            assert_eq!(p, again, "{name}");
            assert!(p.extra.contains_key("published_curves"));
        }
        assert!(embedded_driver("SB17CAC35-4").is_some());
        assert!(embedded_driver("nope").is_none());
    }

    #[test]
    fn a_misspelt_key_is_named_with_the_key_it_likely_meant() {
        let mut v = embedded_driver("sb17cac35-4").unwrap().to_json_value();
        let o = v.as_object_mut().unwrap();
        o.insert("Bll".into(), serde_json::json!([5.0]));
        o.insert("thermall".into(), serde_json::json!({}));
        // Figures other tools write, and keys far from any known one, are not misspellings.
        o.insert("Qms".into(), serde_json::json!(3.1));
        o.insert("Vas".into(), serde_json::json!(0.02));
        o.insert("manufacturer".into(), serde_json::json!("SB Acoustics"));
        let p = Parameters::from_json_value(&v, "t.json").unwrap();
        let mut got = p.near_miss_keys();
        got.sort();
        assert_eq!(got, vec![("Bll".to_string(), "Bl"), ("thermall".to_string(), "thermal")]);
        for name in embedded_driver_names() {
            assert!(embedded_driver(name).unwrap().near_miss_keys().is_empty(), "{name}");
        }
    }

    #[test]
    #[cfg_attr(no_shared, ignore = "../shared is missing (COILSCOPE_NO_SHARED=1): skipped")]
    fn embedded_copies_match_shared_drivers() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/drivers");
        assert!(dir.exists(), "{} missing (set COILSCOPE_NO_SHARED=1 to skip, reported as ignored)", dir.display());
        for (name, text) in EMBEDDED_DRIVERS {
            let shared = std::fs::read_to_string(dir.join(format!("{name}.json"))).unwrap();
            let a: Value = serde_json::from_str(text).unwrap();
            let b: Value = serde_json::from_str(&shared).unwrap();
            assert_eq!(a, b, "embedded copy of {name} differs from shared/drivers");
        }
    }

    #[test]
    fn every_schema_entry_is_read_written_and_read_back() {
        // A set with every entry: each is reachable by its key, written, and read back equal.
        let mut p = embedded_driver("sb17cac35-4").unwrap();
        p.name = Some("all".into());
        p.l3r3 = Some((0.4e-3, 6.0));
        p.creep = Some(Creep { lambda: 0.05, f_ref: Some(30.0) });
        p.le_i = Some(Poly { c: vec![1.0, -0.01, -0.002] });
        p.rms_v = Some(Poly { c: vec![p.rms, 0.0, 0.3] });
        p.sd = Some(0.0133);
        p.thermal.as_mut().unwrap().rv = 1.5;
        // The box's keys depend on its type (and a port's quadratic loss is given one of two
        // ways): three boxes between them have every one.
        use crate::enclosure::{BoxKind, Enclosure};
        let port = |port_loss: Option<f64>, knl: Option<f64>| BoxKind::Vented {
            fb: 38.0,
            qp: Some(40.0),
            port_area: Some(0.002),
            port_loss,
            knl,
        };
        let boxes = [
            port(Some(1.5), None),
            port(None, Some(2.0e5)),
            BoxKind::PassiveRadiator { sp: 0.0095, mmp: 0.05, kmp: Poly { c: vec![900.0, 0.0, 1.5e7] }, rmp: 0.8 },
        ];
        let sets: Vec<Parameters> = boxes
            .into_iter()
            .map(|kind| Parameters {
                enclosure: Some(Enclosure { vb: 0.02, ql: Some(8.0), adiabatic: false, kind }),
                ..p.clone()
            })
            .collect();
        for e in crate::schema::ENTRIES {
            assert!(sets.iter().any(|p| p.get(e.key).is_some()), "{} unreachable", e.key);
        }
        for p in &sets {
            p.validate("all").unwrap();
            assert!(p.get("nope").is_none());
            let json = p.to_json_value();
            for key in crate::schema::file_keys() {
                assert!(json.get(key).is_some(), "{key} not written");
            }
            assert_eq!(&Parameters::from_json_value(&json, "again").unwrap(), p);
        }
        // Absent entries are absent.
        let bare = p.three_state();
        assert!(bare.get("L2").is_none() && bare.get("thermal.Rtv").is_none() && bare.get("Le_i").is_none());
        // No convection: the key is absent from the file, and a negative one is named.
        let plain = embedded_driver("sb17cac35-4").unwrap();
        assert!(plain.to_json_value()["thermal"].get("rv").is_none());
        let mut v = plain.to_json_value();
        v["thermal"]["rv"] = (-1.0).into();
        let e =
            Parameters::from_json_value(&v, "neg").and_then(|p| p.validate("neg").map(|_| p)).unwrap_err().to_string();
        assert!(e.contains("thermal.rv"), "{e}");
    }

    #[test]
    fn missing_key_is_named() {
        let mut v = sb17();
        v.as_object_mut().unwrap().remove("Bl");
        assert_eq!(err_of(v), "test.json: key `Bl`: missing (required: Re, Le, Bl, Kms, Mms, Rms)");
    }

    #[test]
    fn non_finite_and_wrong_types_are_named() {
        let mut v = sb17();
        v["Re"] = Value::String("3.3".into());
        assert!(err_of(v).contains("key `Re`: expected a number (SI units), found the string \"3.3\""));
        let mut v = sb17();
        v["Kms"] = serde_json::json!([600.0, "x"]);
        assert!(err_of(v).contains("key `Kms`: coefficient c1 must be a number"));
        // JSON has no NaN literal; serde_json rejects it as invalid JSON, with the reason.
        let e = Parameters::from_json_str(r#"{"Re": NaN}"#, "t.json").unwrap_err().to_string();
        assert!(e.starts_with("t.json: not valid JSON"), "{e}");
        let e = Parameters::from_json_str(r#"{"Re": 1e999}"#, "t.json").unwrap_err().to_string();
        assert!(e.contains("t.json"), "{e}");
    }

    #[test]
    fn non_positive_values_are_refused() {
        for (key, val) in [("Mms", 0.0), ("Re", -1.0), ("Le", 0.0)] {
            let mut v = sb17();
            v[key] = val.into();
            let e = err_of(v);
            assert!(e.contains(&format!("key `{key}`")) && e.contains("> 0"), "{e}");
        }
    }

    #[test]
    fn stiffness_or_force_factor_crossing_zero_inside_range_is_refused() {
        let mut v = sb17();
        v["Bl"] = serde_json::json!([5.0, 0.0, -300000.0]); // zero at |x| = 4.1 mm
        let e = err_of(v);
        assert!(e.contains("key `Bl`: Bl(x) must be > 0 inside x_range"), "{e}");
        let mut v = sb17();
        v["Kms"] = serde_json::json!([600.0, 200000.0]); // zero at x = -3 mm
        assert!(err_of(v).contains("key `Kms`: Kms(x) must be > 0"));
    }

    #[test]
    fn unit_mistakes_are_flagged_with_the_likely_cause() {
        let mut v = sb17();
        v["Mms"] = 15.0.into();
        let e = err_of(v);
        assert!(e.contains("looks like grams: 15 g = 0.015 kg"), "{e}");
        let mut v = sb17();
        v["Le"] = 0.5.into();
        let e = err_of(v);
        assert!(e.contains("looks like millihenry: 0.5 mH = 0.0005 H"), "{e}");
        let mut v = sb17();
        v["x_range"] = serde_json::json!([-5.5, 5.5]);
        assert!(err_of(v).contains("looks like millimetres"));
        let mut v = sb17();
        v["Kms"] = 0.0015.into();
        assert!(err_of(v).contains("looks like a compliance Cms"));
    }

    #[test]
    fn misspelt_keys_and_half_lr2_are_refused() {
        let mut v = sb17();
        let bl = v["Bl"].clone();
        v.as_object_mut().unwrap().insert("bl".into(), bl);
        assert!(err_of(v).contains("did you mean `Bl`"));
        let mut v = sb17();
        v.as_object_mut().unwrap().remove("R2");
        assert!(err_of(v).contains("key `R2`: missing: L2 is given"));
        let mut v = sb17();
        v["format"] = "coilscope.parameters/9".into();
        assert!(err_of(v).contains("key `format`"));
    }

    #[test]
    fn stiffness_rate_reflects_the_electrical_time_constant() {
        let p = embedded_driver("sb17cac35-4").unwrap();
        let tau = p.min_electrical_time_constant();
        assert!(tau > 20e-6 && tau < 40e-6, "{tau}");
    }
}

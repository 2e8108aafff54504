//! The parameter schema: every key of a parameter set (`docs/formats.md`), with its SI
//! unit, its kind (a constant, a power series in x, in the current, in |v|, …), the component
//! of the model it belongs to and what it means.
//!
//! It is the one list the consumers iterate: the parameter reader's known keys and required
//! keys, the writer ([`crate::Parameters::to_json_value`]), the report's parameter tables and
//! the command line's. [`crate::Parameters::get`] reads any entry by its key. A new parameter
//! is an entry here, its field and component in the model, and its tests; the tables and files
//! follow.
//!
//! Keys of sub-objects are dotted (`thermal.Rtv`, `creep.lambda`): in the file they are keys of
//! the object `thermal` or `creep`.

use crate::poly::Poly;

/// What a value is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// A number (SI).
    Number,
    /// A number or an ascending power series in the displacement x (m).
    SeriesX,
    /// An ascending power series in the current i (A).
    SeriesI,
    /// An ascending power series in the speed |v| (m/s).
    SeriesV,
    /// An ascending power series in a passive radiator's excursion xp (m).
    SeriesXp,
    /// `[min, max]` (m).
    Range,
    /// `true` or `false`.
    Flag,
    /// Text.
    Text,
}

/// The part of the model an entry belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Component {
    /// Voice coil: Re, Le(x), flux modulation.
    VoiceCoil,
    /// Para-inductance branches (eddy currents): LR-2, LR-3.
    Eddy,
    /// Motor: Bl(x).
    Motor,
    /// Suspension: Kms(x), creep.
    Suspension,
    /// Moving mass, losses, radiating area.
    Mechanics,
    /// Two-node thermal model.
    Thermal,
    /// The box the driver works into ([`crate::enclosure`]).
    Enclosure,
    /// Where the curves hold, what the set is.
    About,
}

/// One key of the parameter set.
#[derive(Clone, Copy, Debug)]
pub struct Entry {
    /// The key in the file (dotted for a key of a sub-object).
    pub key: &'static str,
    /// SI unit of the value (of the function's value, for a series).
    pub unit: &'static str,
    pub kind: Kind,
    pub component: Component,
    /// Required in every parameter set.
    pub required: bool,
    /// The unit and factor tables show it in (`("mH", 1e3)` for an inductance).
    pub display: (&'static str, f64),
    /// An entry that describes how coilscope realises an effect (fixed values, written for
    /// outside tools), not a parameter of the driver.
    pub realisation: bool,
    /// A key coilscope adds to the file contract (a new optional key, as the contract
    /// allows; older files without it stay valid).
    pub extension: bool,
    pub meaning: &'static str,
}

const fn e(
    key: &'static str,
    unit: &'static str,
    kind: Kind,
    component: Component,
    required: bool,
    display: (&'static str, f64),
    meaning: &'static str,
) -> Entry {
    Entry { key, unit, kind, component, required, display, realisation: false, extension: false, meaning }
}

/// An optional key beyond the file contract's (see [`Entry::extension`]).
const fn extension(key: &'static str, unit: &'static str, component: Component, meaning: &'static str) -> Entry {
    Entry {
        key,
        unit,
        kind: Kind::Number,
        component,
        required: false,
        display: (unit, 1.0),
        realisation: false,
        extension: true,
        meaning,
    }
}

const fn realisation(key: &'static str, unit: &'static str, meaning: &'static str) -> Entry {
    Entry {
        key,
        unit,
        kind: Kind::Number,
        component: Component::Suspension,
        required: false,
        display: (unit, 1.0),
        realisation: true,
        extension: false,
        meaning,
    }
}

use Component as C;
use Kind as K;

/// Every entry, in the order tables show them.
pub const ENTRIES: &[Entry] = &[
    e("name", "", K::Text, C::About, false, ("", 1.0), "what the driver is"),
    e("source", "", K::Text, C::About, false, ("", 1.0), "where the numbers come from"),
    e(
        "Re",
        "ohm",
        K::Number,
        C::VoiceCoil,
        true,
        ("ohm", 1.0),
        "DC resistance of the voice coil at ambient temperature",
    ),
    e("Le", "H", K::SeriesX, C::VoiceCoil, true, ("mH", 1e3), "voice-coil inductance Le(x)"),
    e(
        "Le_i",
        "1",
        K::SeriesI,
        C::VoiceCoil,
        false,
        ("", 1.0),
        "flux modulation: the factor g(i) in the flux Le(x) g(i) i, g(0) = 1",
    ),
    e("L2", "H", K::SeriesX, C::Eddy, false, ("mH", 1e3), "LR-2 para-inductance L2(x)"),
    e("R2", "ohm", K::SeriesX, C::Eddy, false, ("ohm", 1.0), "LR-2 eddy-current resistance R2(x)"),
    e("L3", "H", K::Number, C::Eddy, false, ("mH", 1e3), "LR-3 para-inductance (a second branch, in series with LR-2)"),
    e("R3", "ohm", K::Number, C::Eddy, false, ("ohm", 1.0), "LR-3 eddy-current resistance"),
    e("Bl", "T m", K::SeriesX, C::Motor, true, ("T m", 1.0), "force factor Bl(x)"),
    e(
        "Kms",
        "N/m",
        K::SeriesX,
        C::Suspension,
        true,
        ("N/m", 1.0),
        "secant stiffness Kms(x) (with creep: the dynamic stiffness at f_ref)",
    ),
    e(
        "creep.lambda",
        "1",
        K::Number,
        C::Suspension,
        false,
        ("", 1.0),
        "LOG creep factor: Cms(f) = Cms(f_ref) (1 - lambda log10(f / f_ref))",
    ),
    e(
        "creep.f_ref",
        "Hz",
        K::Number,
        C::Suspension,
        false,
        ("Hz", 1.0),
        "creep's reference frequency (absent: the resonance)",
    ),
    realisation("creep.per_decade", "1", "Maxwell elements per decade of the creep bank"),
    realisation("creep.f_min", "Hz", "lowest relaxation frequency of the creep bank"),
    realisation("creep.f_max", "Hz", "highest relaxation frequency of the creep bank"),
    e("Mms", "kg", K::Number, C::Mechanics, true, ("g", 1e3), "moving mass including air load"),
    e("Rms", "kg/s", K::Number, C::Mechanics, true, ("kg/s", 1.0), "mechanical resistance (at rest)"),
    e(
        "Rms_v",
        "kg/s",
        K::SeriesV,
        C::Mechanics,
        false,
        ("kg/s", 1.0),
        "velocity-dependent loss Rms(|v|), replacing Rms in the model",
    ),
    e("Sd", "m^2", K::Number, C::Mechanics, false, ("cm^2", 1e4), "effective radiating area"),
    e("thermal.alpha", "1/K", K::Number, C::Thermal, false, ("1/K", 1.0), "temperature coefficient of Re"),
    e("thermal.Rtv", "K/W", K::Number, C::Thermal, false, ("K/W", 1.0), "voice coil to magnet thermal resistance"),
    e("thermal.Ctv", "J/K", K::Number, C::Thermal, false, ("J/K", 1.0), "voice-coil heat capacity"),
    e("thermal.Rtm", "K/W", K::Number, C::Thermal, false, ("K/W", 1.0), "magnet to ambient thermal resistance"),
    e("thermal.Ctm", "J/K", K::Number, C::Thermal, false, ("J/K", 1.0), "magnet heat capacity"),
    extension("thermal.rv", "s/m", C::Thermal, "convection cooling: Rtv(v) = Rtv / (1 + rv |v|)"),
    e("enclosure.type", "", K::Text, C::Enclosure, false, ("", 1.0), "the box: closed, vented or passive_radiator"),
    e("enclosure.Vb", "m^3", K::Number, C::Enclosure, false, ("l", 1e3), "net box volume with the cone at rest"),
    e(
        "enclosure.adiabatic",
        "",
        K::Flag,
        C::Enclosure,
        false,
        ("", 1.0),
        "the box air's law: adiabatic (p0 + p) V^gamma = const, or the linear gamma p0 / Vb",
    ),
    e("enclosure.QL", "1", K::Number, C::Enclosure, false, ("", 1.0), "the leak's Q at the box's tuning"),
    e("enclosure.fb", "Hz", K::Number, C::Enclosure, false, ("Hz", 1.0), "the port's Helmholtz tuning on the box air"),
    e("enclosure.Qp", "1", K::Number, C::Enclosure, false, ("", 1.0), "the port's linear loss as a Q at fb"),
    e("enclosure.port_area", "m^2", K::Number, C::Enclosure, false, ("cm^2", 1e4), "the port's cross-section"),
    e(
        "enclosure.port_loss",
        "1",
        K::Number,
        C::Enclosure,
        false,
        ("", 1.0),
        "the port's quadratic loss k: a pressure drop k rho/2 (U/port_area)^2 (port compression)",
    ),
    e(
        "enclosure.knl",
        "Pa s^2/m^6",
        K::Number,
        C::Enclosure,
        false,
        ("Pa s^2/m^6", 1.0),
        "the port's quadratic loss coefficient where its area is unknown: knl U |U|",
    ),
    e("enclosure.Sp", "m^2", K::Number, C::Enclosure, false, ("cm^2", 1e4), "the passive radiator's area"),
    e("enclosure.Mmp", "kg", K::Number, C::Enclosure, false, ("g", 1e3), "the passive radiator's moving mass"),
    e(
        "enclosure.Kmp",
        "N/m",
        K::SeriesXp,
        C::Enclosure,
        false,
        ("N/m", 1.0),
        "the passive radiator's secant stiffness Kmp(xp)",
    ),
    e("enclosure.Rmp", "N s/m", K::Number, C::Enclosure, false, ("N s/m", 1.0), "the passive radiator's loss"),
    e(
        "x_range",
        "m",
        K::Range,
        C::About,
        false,
        ("mm", 1e3),
        "[x_min, x_max]: where the x-dependent functions are valid",
    ),
];

/// The entry of a key.
pub fn entry(key: &str) -> Option<&'static Entry> {
    ENTRIES.iter().find(|e| e.key == key)
}

/// The top-level keys of a parameter file (`format`, and the first part of each dotted key).
pub fn file_keys() -> Vec<&'static str> {
    let mut keys = vec!["format"];
    for e in ENTRIES {
        let top = e.key.split('.').next().unwrap_or(e.key);
        if !keys.contains(&top) {
            keys.push(top);
        }
    }
    keys
}

/// The required keys, as the reader's errors list them (`Re, Le, Bl, Kms, Mms, Rms`).
pub fn required_keys() -> String {
    ENTRIES.iter().filter(|e| e.required).map(|e| e.key).collect::<Vec<_>>().join(", ")
}

/// A value of a parameter set, borrowed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Value<'a> {
    Number(f64),
    Series(&'a Poly),
    Range([f64; 2]),
    Text(&'a str),
    Flag(bool),
}

impl Value<'_> {
    /// The value as the contract writes an entry of `kind`: a number; a series in x (or
    /// xp) as a number when constant, else an array; other series and ranges as arrays.
    pub fn to_json(&self, kind: Kind) -> serde_json::Value {
        use serde_json::Value as J;
        let array = |c: &[f64]| J::Array(c.iter().map(|&c| c.into()).collect());
        match self {
            Value::Number(x) => (*x).into(),
            Value::Series(p) if matches!(kind, Kind::SeriesX | Kind::SeriesXp) && p.c.len() == 1 => p.c[0].into(),
            Value::Series(p) => array(&p.c),
            Value::Range(r) => array(r),
            Value::Text(t) => (*t).into(),
            Value::Flag(b) => (*b).into(),
        }
    }

    /// The number, or the series' value at 0 (its c0), or `None` for a range or text.
    pub fn at_rest(&self) -> Option<f64> {
        match self {
            Value::Number(v) => Some(*v),
            Value::Series(p) => p.c.first().copied(),
            _ => None,
        }
    }
}

impl Entry {
    /// The name a table gives it: the key, with `(0)` for a function (`Le(0)`), or the last
    /// part of a dotted key (`lambda`, `Rtv`).
    pub fn label(&self) -> String {
        let short = self.short();
        match self.kind {
            Kind::SeriesX | Kind::SeriesI | Kind::SeriesV | Kind::SeriesXp => format!("{short}(0)"),
            _ => short.to_string(),
        }
    }

    /// The last part of the key (`Rtv` for `thermal.Rtv`).
    pub fn short(&self) -> &'static str {
        self.key.rsplit('.').next().unwrap_or(self.key)
    }

    /// The SI unit as a table shows it (empty for a pure number).
    pub fn unit_text(&self) -> &'static str {
        if self.unit == "1" {
            ""
        } else {
            self.unit
        }
    }

    /// The variable of a series (`x` in m, `i` in A, `|v|` in m/s).
    pub fn variable(&self) -> Option<(&'static str, &'static str)> {
        match self.kind {
            Kind::SeriesX => Some(("x", "m")),
            Kind::SeriesI => Some(("i", "A")),
            Kind::SeriesV => Some(("|v|", "m/s")),
            Kind::SeriesXp => Some(("xp", "m")),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_are_unique_and_dotted_only_under_the_contract_objects() {
        for (k, a) in ENTRIES.iter().enumerate() {
            assert!(ENTRIES[..k].iter().all(|b| b.key != a.key), "{} twice", a.key);
            if let Some((top, _)) = a.key.split_once('.') {
                assert!(["thermal", "creep", "enclosure"].contains(&top), "{}", a.key);
            }
        }
        assert_eq!(required_keys(), "Re, Le, Bl, Kms, Mms, Rms");
    }

    #[test]
    #[cfg_attr(no_shared, ignore = "../shared is missing (COILSCOPE_NO_SHARED=1): skipped")]
    fn every_key_is_in_the_file_contract() {
        // The contract names each key (dotted ones by their last part, in their object's row);
        // the creep bank's realisation keys are its "further keys"; coilscope's extensions
        // (new optional keys) are not in it.
        let spec = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../../../shared/spec/formats.md"))
            .expect("shared/spec/formats.md (set COILSCOPE_NO_SHARED=1 to skip, reported as ignored)");
        for e in ENTRIES.iter().filter(|e| !e.realisation && !e.extension) {
            let last = e.key.rsplit('.').next().unwrap();
            assert!(
                spec.contains(&format!("`{last}`")) || spec.contains(&format!("`{}`", e.key)),
                "formats.md does not name {}",
                e.key
            );
        }
        // The repository carries the contract for its users (`docs/formats.md`): the same text.
        let copy = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../../docs/formats.md"))
            .expect("docs/formats.md");
        assert!(copy == spec, "docs/formats.md differs from shared/spec/formats.md: copy the contract again");
    }
}

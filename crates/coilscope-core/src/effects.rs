//! Which of a real driver's effects a parameter set, a fit or a test world has.

/// The effects of a real driver beyond the seed paper's model (and its LR-2 branch and
/// thermal nodes), each an optional part of a parameter set: which a set has, a fit
/// estimates or a test's world holds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Effects {
    /// LOG creep of the suspension ([`crate::creep`]).
    pub creep: bool,
    /// A second para-inductance branch L3 || R3 in series with LR-2.
    pub lr3: bool,
    /// Flux modulation `Le_i` (large signal only).
    pub le_i: bool,
    /// Velocity-dependent loss `Rms_v` (large signal only).
    pub rms_v: bool,
}

impl Effects {
    pub const NONE: Effects = Effects { creep: false, lr3: false, le_i: false, rms_v: false };
    /// Every effect.
    pub const ALL: Effects = Effects { creep: true, lr3: true, le_i: true, rms_v: true };
    /// The effects a parameter set carries.
    pub fn of(p: &crate::params::Parameters) -> Effects {
        Effects { creep: p.creep.is_some(), lr3: p.l3r3.is_some(), le_i: p.le_i.is_some(), rms_v: p.rms_v.is_some() }
    }
    /// Whether a large-signal-only effect (Le(i), Rms(v)) is included: no small-signal
    /// record can show it.
    pub fn has_large_signal(self) -> bool {
        self.le_i || self.rms_v
    }
    /// Whether an effect with states of its own (creep, LR-3) is in: the time-domain model
    /// is then [`crate::model::ExtModel`].
    pub fn needs_ext_states(self) -> bool {
        self.creep || self.lr3
    }
    /// The effects in either set.
    pub fn union(self, other: Effects) -> Effects {
        Effects {
            creep: self.creep || other.creep,
            lr3: self.lr3 || other.lr3,
            le_i: self.le_i || other.le_i,
            rms_v: self.rms_v || other.rms_v,
        }
    }
    /// The effects in `self` and not in `other`.
    pub fn without(self, other: Effects) -> Effects {
        Effects {
            creep: self.creep && !other.creep,
            lr3: self.lr3 && !other.lr3,
            le_i: self.le_i && !other.le_i,
            rms_v: self.rms_v && !other.rms_v,
        }
    }
    /// The effects a small-signal fit can see (creep, LR-3).
    pub fn small_signal(self) -> Effects {
        Effects { le_i: false, rms_v: false, ..self }
    }
    /// The names as in `fit.model` (`LR-2`, `LR-2+creep`, `LR-2+LR-3+creep+Le(i)+Rms(v)`).
    pub fn model_name(self) -> String {
        let mut s = String::from("LR-2");
        if self.lr3 {
            s.push_str("+LR-3");
        }
        if self.creep {
            s.push_str("+creep");
        }
        if self.le_i {
            s.push_str("+Le(i)");
        }
        if self.rms_v {
            s.push_str("+Rms(v)");
        }
        s
    }
    /// The parameter-schema keys the effects add (`creep.lambda`, `L3`, `R3`, `Le_i`, `Rms_v`).
    pub fn keys(self) -> Vec<&'static str> {
        let on = [
            (self.creep, &["creep.lambda"][..]),
            (self.lr3, &["L3", "R3"][..]),
            (self.le_i, &["Le_i"][..]),
            (self.rms_v, &["Rms_v"][..]),
        ];
        on.iter().filter(|(b, _)| *b).flat_map(|(_, k)| k.iter().copied()).collect()
    }
    /// The effects in words, without the LR-2 base (`Le(i) and Rms(v)`; empty for none).
    pub fn in_words(self) -> String {
        let model = self.model_name();
        let names: Vec<&str> = model.trim_start_matches("LR-2").split('+').filter(|n| !n.is_empty()).collect();
        match names.as_slice() {
            [] => String::new(),
            [one] => one.to_string(),
            [rest @ .., last] => format!("{} and {last}", rest.join(", ")),
        }
    }
    /// Parse `none`, or a comma-separated list of `creep`, `lr3`, `lei`, `rmsv` (the CLI's
    /// `--effects`).
    pub fn parse(text: &str) -> Result<Effects, String> {
        let mut e = Effects::NONE;
        for part in text.split(',').map(str::trim).filter(|t| !t.is_empty()) {
            match part {
                "none" => {}
                "creep" => e.creep = true,
                "lr3" | "LR-3" => e.lr3 = true,
                "lei" | "Le_i" | "Le(i)" => e.le_i = true,
                "rmsv" | "Rms_v" | "Rms(v)" => e.rms_v = true,
                other => {
                    return Err(format!(
                        "unknown effect {other:?}; valid: none, creep, lr3, lei, rmsv (comma-separated), or auto"
                    ))
                }
            }
        }
        Ok(e)
    }
}

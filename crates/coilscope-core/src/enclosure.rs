//! The box the driver works into (formats.md `enclosure`): a closed box, a vented box or a
//! passive radiator, with the box air, its leak, the port's air mass and losses, or the
//! radiator's moving system. The one place the box's equations are written.
//!
//! The box air's gauge pressure `p` (Pa) pushes on the cone with the force `Sd p`
//! (+ = coil out). Air leaves the box by the cone's motion (`Sd v`: the cone moving out
//! enlarges the box), by the port or the radiator (`U`, m^3/s) and by the leak (`p / Ral`):
//!
//! ```text
//! dp/dt = -gamma (p0 + p) / V (Sd v + U + p / Ral),   V = Vb + Sd x (+ Sp xp)     (adiabatic)
//! dp/dt = -(gamma p0 / Vb) (Sd v + U + p / Ral)                                 (linear law)
//! Map dU/dt = p - Rap U - knl U |U|                                            (vented: the port)
//! Mmp d2xp/dt2 = Sp p - Rmp dxp/dt - Kmp(xp) xp,   U = Sp dxp/dt                (passive radiator)
//! ```
//!
//! with `Cab = Vb / (gamma p0)`, the port's mass `Map = 1 / ((2 pi fb)^2 Cab)` and loss
//! `Rap = 2 pi fb Map / Qp`, the leak `Ral = QL / (2 pi f_t Cab)` at the box's tuning `f_t`,
//! and the port's quadratic loss `knl = port_loss rho / 2 / port_area^2` (port compression).
//! The sound radiated is the net volume velocity into the room, `Sd v + U`.
//!
//! Energy: the box air stores `Cab p^2 / 2` under the linear law, and under the adiabatic law
//! the work that compresses the air in it isentropically from ambient pressure
//! ([`BoxModel::stored_energy`]). The port's air stores `Map U^2 / 2`, the radiator its
//! kinetic and spring energy; the leak, `Rap`, `knl` and `Rmp` dissipate. The balance closes
//! exactly under the linear law and for a sealed box under the adiabatic law; with air
//! leaving through the port or the leak under the adiabatic law, the contract's port is driven
//! by the gauge pressure rather than by the air's enthalpy, which leaves a residual of the
//! order of `p / p0` of the port's throughput (`box_energy_balance_closes`).

use crate::poly::Poly;
use num_dual::DualNum;
use realfft::num_complex::Complex64;
use serde_json::{Map, Value};
use std::f64::consts::PI;

/// Ambient pressure (Pa), the contract's.
pub const P0: f64 = 101_325.0;
/// Ratio of specific heats of air (adiabatic exponent), the contract's.
pub const GAMMA: f64 = 1.4;
/// Density of air (kg/m^3), the contract's for the port's quadratic loss.
pub const RHO: f64 = 1.18;

/// What works on the box air besides the cone.
#[derive(Clone, Debug, PartialEq)]
pub enum BoxKind {
    /// A sealed box (with its leak, if `QL` is given).
    Closed,
    /// A port tuned to `fb` (Hz) on the box air, with its linear loss `Qp` and its quadratic
    /// loss: `port_loss` (dimensionless) with `port_area` (m^2), or `knl` (Pa s^2/m^6) when
    /// the port's area is unknown.
    Vented { fb: f64, qp: Option<f64>, port_area: Option<f64>, port_loss: Option<f64>, knl: Option<f64> },
    /// A passive radiator of area `sp` (m^2), moving mass `mmp` (kg), secant stiffness
    /// `kmp(xp)` (N/m, ascending power series in its excursion xp, outward positive) and
    /// loss `rmp` (N s/m).
    PassiveRadiator { sp: f64, mmp: f64, kmp: Poly, rmp: f64 },
}

/// A box (formats.md `enclosure`).
#[derive(Clone, Debug, PartialEq)]
pub struct Enclosure {
    /// Net air volume with the cone at rest (m^3).
    pub vb: f64,
    /// The leak's Q at the box's tuning ([`Enclosure::tuning_hz`]); `None`: no leak.
    pub ql: Option<f64>,
    /// The adiabatic law `(p0 + p) V^gamma = const` (`true`, the default) or the linear
    /// `gamma p0 / Vb`.
    pub adiabatic: bool,
    pub kind: BoxKind,
}

/// The box's acoustic elements (SI acoustic units), derived from an [`Enclosure`] and the
/// driver it holds ([`Enclosure::elements`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Elements<D = f64> {
    /// The driver's radiating area (m^2).
    pub sd: D,
    /// Net volume (m^3).
    pub vb: D,
    /// Acoustic compliance of the box air `Vb / (gamma p0)` (m^5/N).
    pub cab: D,
    /// The leak's resistance (Pa s/m^3); `None` without a leak.
    pub ral: Option<D>,
    /// The port's air mass (kg/m^4), linear loss (Pa s/m^3) and quadratic loss
    /// (Pa s^2/m^6); `None` without a port.
    pub port: Option<(D, D, D)>,
    /// The box's tuning `f_t` (Hz) the leak's Q refers to.
    pub tuning_hz: D,
}

/// The type names a file may give, in the contract's spelling.
pub const TYPES: [&str; 3] = ["closed", "vented", "passive_radiator"];

impl Enclosure {
    /// The contract's type name.
    pub fn type_name(&self) -> &'static str {
        match self.kind {
            BoxKind::Closed => "closed",
            BoxKind::Vented { .. } => "vented",
            BoxKind::PassiveRadiator { .. } => "passive_radiator",
        }
    }

    /// Acoustic compliance of the box air, `Vb / (gamma p0)` (m^5/N).
    pub fn cab(&self) -> f64 {
        self.vb / (GAMMA * P0)
    }

    /// The port's quadratic loss coefficient `knl` (Pa s^2/m^6): as given, or
    /// `port_loss rho / 2 / port_area^2`; 0 without one.
    pub fn knl(&self) -> f64 {
        match &self.kind {
            BoxKind::Vented { knl: Some(k), .. } => *k,
            BoxKind::Vented { port_area: Some(a), port_loss: Some(k), .. } => k * RHO / 2.0 / (a * a),
            _ => 0.0,
        }
    }

    /// The box's tuning `f_t` (Hz) for a driver of stiffness `kms0` (N/m), moving mass `mms`
    /// (kg) and area `sd` (m^2): the port's `fb`, the radiator's resonance on the box air
    /// `sqrt((Kmp(0) + Sp^2 / Cab) / Mmp) / 2 pi`, or the closed box's system resonance
    /// `sqrt((Kms(0) + Sd^2 / Cab) / Mms) / 2 pi`.
    pub fn tuning_hz(&self, kms0: f64, mms: f64, sd: f64) -> f64 {
        self.elements(kms0, mms, sd).tuning_hz
    }

    /// The acoustic elements for the driver of stiffness `kms0` (N/m), mass `mms` (kg) and
    /// area `sd` (m^2).
    pub fn elements(&self, kms0: f64, mms: f64, sd: f64) -> Elements {
        self.elements_lifted(kms0, mms, sd, &|_, v| v)
    }

    /// [`Enclosure::elements`] in the scalar type `D`, each of the box's values taken through
    /// `lift(key, value)` (schema keys: `enclosure.Vb`, `enclosure.QL`, `enclosure.fb`,
    /// `enclosure.Qp`, `enclosure.knl`, `enclosure.Sp`, `enclosure.Mmp`, `enclosure.Kmp` for
    /// Kmp(0), `enclosure.Rmp`): the one derivation of the elements, for the simulator
    /// (`lift` the identity) and for a fit whose unknowns the box's values are (`lift` puts
    /// them on dual numbers).
    pub fn elements_lifted<D: DualNum<Primitive = f64> + Copy>(
        &self,
        kms0: D,
        mms: D,
        sd: D,
        lift: &dyn Fn(&'static str, f64) -> D,
    ) -> Elements<D> {
        let vb = lift("enclosure.Vb", self.vb);
        let cab = vb * (1.0 / (GAMMA * P0));
        let two_pi = 2.0 * PI;
        let tuning_hz = match &self.kind {
            BoxKind::Closed => ((kms0 + sd * sd / cab) / mms).sqrt() * (1.0 / two_pi),
            BoxKind::Vented { fb, .. } => lift("enclosure.fb", *fb),
            BoxKind::PassiveRadiator { sp, mmp, kmp, .. } => {
                let sp = lift("enclosure.Sp", *sp);
                ((lift("enclosure.Kmp", kmp.c[0]) + sp * sp / cab) / lift("enclosure.Mmp", *mmp)).sqrt()
                    * (1.0 / two_pi)
            }
        };
        let ral = self.ql.map(|ql| lift("enclosure.QL", ql) / (tuning_hz * two_pi * cab));
        let port = match &self.kind {
            BoxKind::Vented { qp, .. } => {
                let wb = tuning_hz * two_pi;
                let map = (wb * wb * cab).recip();
                let rap = qp.map_or(D::zero(), |q| wb * map / lift("enclosure.Qp", q));
                Some((map, rap, lift("enclosure.knl", self.knl())))
            }
            _ => None,
        };
        Elements { sd, vb, cab, ral, port, tuning_hz }
    }

    /// The acoustic impedance the box presents to the cone's volume velocity at rest,
    /// `p / (-Sd v)` (Pa s/m^3): the box air's compliance, the leak, and the port's mass and
    /// loss or the radiator's moving system, in parallel (the textbook small-signal network).
    pub fn acoustic_impedance(&self, e: &Elements, w: f64) -> Complex64 {
        let jw = Complex64::new(0.0, w);
        let mut y = jw * e.cab + e.ral.map_or(0.0, |r| 1.0 / r);
        match &self.kind {
            BoxKind::Closed => {}
            BoxKind::Vented { .. } => {
                let (map, rap, _) = e.port.expect("a vented box has a port");
                y += 1.0 / (jw * map + rap);
            }
            BoxKind::PassiveRadiator { sp, mmp, kmp, rmp } => {
                y += sp * sp / (jw * mmp + rmp + kmp.c[0] / jw);
            }
        }
        1.0 / y
    }

    /// The box's mechanical load on the cone at rest, `Sd^2` times
    /// [`Enclosure::acoustic_impedance`] (N s/m): what adds to the driver's `Rms + jw Mms +
    /// K / jw` in the small-signal network.
    pub fn mechanical_load(&self, e: &Elements, w: f64) -> Complex64 {
        e.sd * e.sd * self.acoustic_impedance(e, w)
    }

    /// The net volume velocity radiated into the room per cone volume velocity at rest,
    /// `(Sd v + U) / (Sd v)`: 1 for a closed box without a leak, 0 at a vented box's tuning
    /// far below it (the port cancels the cone).
    pub fn radiated_ratio(&self, e: &Elements, w: f64) -> Complex64 {
        let jw = Complex64::new(0.0, w);
        // The box pressure per cone volume velocity, then what leaves by the port or the
        // radiator and by the leak (both radiate: the leak's flow is added, as the contract
        // says).
        let p = -self.acoustic_impedance(e, w);
        let out = match &self.kind {
            BoxKind::Closed => Complex64::new(0.0, 0.0),
            BoxKind::Vented { .. } => {
                let (map, rap, _) = e.port.expect("a vented box has a port");
                p / (jw * map + rap)
            }
            BoxKind::PassiveRadiator { sp, mmp, kmp, rmp } => p * sp * sp / (jw * mmp + rmp + kmp.c[0] / jw),
        };
        1.0 + out + e.ral.map_or(Complex64::new(0.0, 0.0), |r| p / r)
    }

    /// Parse `enclosure` from a parameter file's JSON. `err(key, message)` builds the reader's
    /// error (the key is dotted: `enclosure.Vb`).
    pub fn from_json<E>(v: &Value, err: &dyn Fn(&str, String) -> E) -> Result<Enclosure, E> {
        let obj = match v {
            Value::Object(o) => o,
            other => {
                return Err(err(
                    "enclosure",
                    format!("expected an object such as {{\"type\": \"closed\", \"Vb\": 0.012}}, found {other}"),
                ))
            }
        };
        let ty = match obj.get("type") {
            Some(Value::String(s)) => s.as_str(),
            Some(other) => return Err(err("enclosure.type", format!("expected one of {TYPES:?}, found {other}"))),
            None => return Err(err("enclosure.type", format!("missing: one of {TYPES:?}"))),
        };
        let allowed: &[&str] = match ty {
            "closed" => &["type", "Vb", "QL", "adiabatic"],
            "vented" => &["type", "Vb", "QL", "adiabatic", "fb", "Qp", "port_area", "port_loss", "knl"],
            "passive_radiator" => &["type", "Vb", "QL", "adiabatic", "Sp", "Mmp", "Kmp", "Rmp"],
            other => {
                return Err(err("enclosure.type", format!("{other:?} is not a box type; expected one of {TYPES:?}")))
            }
        };
        for k in obj.keys() {
            if !allowed.contains(&k.as_str()) {
                return Err(err(
                    &format!("enclosure.{k}"),
                    format!("not a key of a {ty} box; its keys are {}", allowed.join(", ")),
                ));
            }
        }
        let number = |k: &str| -> Result<Option<f64>, E> {
            match obj.get(k) {
                None => Ok(None),
                Some(Value::Number(n)) => match n.as_f64().filter(|f| f.is_finite()) {
                    Some(f) => Ok(Some(f)),
                    None => Err(err(&format!("enclosure.{k}"), format!("{n} is not a finite number"))),
                },
                Some(other) => {
                    Err(err(&format!("enclosure.{k}"), format!("expected a number (SI units), found {other}")))
                }
            }
        };
        let required = |k: &str, what: &str| -> Result<f64, E> {
            number(k)?.ok_or_else(|| err(&format!("enclosure.{k}"), format!("missing: a {ty} box needs {k} ({what})")))
        };
        let vb = required("Vb", "the net box volume in m^3")?;
        let adiabatic = match obj.get("adiabatic") {
            None => true,
            Some(Value::Bool(b)) => *b,
            Some(other) => return Err(err("enclosure.adiabatic", format!("expected true or false, found {other}"))),
        };
        let kind = match ty {
            "closed" => BoxKind::Closed,
            "vented" => BoxKind::Vented {
                fb: required("fb", "the port's tuning in Hz")?,
                qp: number("Qp")?,
                port_area: number("port_area")?,
                port_loss: number("port_loss")?,
                knl: number("knl")?,
            },
            _ => {
                let kmp = match obj.get("Kmp") {
                    None => return Err(err("enclosure.Kmp", "missing: a passive radiator needs Kmp (N/m, a number or an ascending power series in its excursion in metres)".into())),
                    Some(Value::Number(_)) => Poly::constant(number("Kmp")?.unwrap_or(0.0)),
                    Some(Value::Array(a)) if !a.is_empty() && a.len() <= 16 => {
                        let c: Option<Vec<f64>> = a.iter().map(|x| x.as_f64().filter(|f| f.is_finite())).collect();
                        Poly { c: c.ok_or_else(|| err("enclosure.Kmp", "every coefficient must be a finite number (SI, xp in metres)".into()))? }
                    }
                    Some(other) => return Err(err("enclosure.Kmp", format!("expected a number or 1 to 16 ascending power-series coefficients (N/m, xp in metres), found {other}"))),
                };
                BoxKind::PassiveRadiator {
                    sp: required("Sp", "the radiator's area in m^2")?,
                    mmp: required("Mmp", "the radiator's moving mass in kg")?,
                    kmp,
                    rmp: number("Rmp")?.unwrap_or(0.0),
                }
            }
        };
        let e = Enclosure { vb, ql: number("QL")?, adiabatic, kind };
        e.check(err)?;
        Ok(e)
    }

    /// Physical sense and likely unit mistakes, each error naming the key.
    pub fn check<E>(&self, err: &dyn Fn(&str, String) -> E) -> Result<(), E> {
        let positive = |k: &str, v: f64, unit: &str| -> Result<(), E> {
            if v > 0.0 {
                Ok(())
            } else {
                Err(err(&format!("enclosure.{k}"), format!("{v} {unit} must be > 0")))
            }
        };
        positive("Vb", self.vb, "m^3")?;
        if self.vb > 2.0 {
            return Err(err(
                "enclosure.Vb",
                format!(
                    "{} m^3 is not a plausible box (expected < 2 m^3); it looks like litres: {} l = {} m^3",
                    self.vb,
                    self.vb,
                    self.vb * 1e-3
                ),
            ));
        }
        if let Some(ql) = self.ql {
            positive("QL", ql, "")?;
        }
        match &self.kind {
            BoxKind::Closed => {}
            BoxKind::Vented { fb, qp, port_area, port_loss, knl } => {
                positive("fb", *fb, "Hz")?;
                if *fb > 2000.0 {
                    return Err(err(
                        "enclosure.fb",
                        format!("{fb} Hz is not a plausible port tuning (expected < 2 kHz)"),
                    ));
                }
                if let Some(q) = qp {
                    positive("Qp", *q, "")?;
                }
                if let Some(a) = port_area {
                    positive("port_area", *a, "m^2")?;
                }
                if let Some(k) = port_loss {
                    if !(*k >= 0.0) {
                        return Err(err("enclosure.port_loss", format!("{k} must be >= 0")));
                    }
                    if port_area.is_none() {
                        return Err(err(
                            "enclosure.port_area",
                            "missing: port_loss needs the port's area in m^2 (or give the loss as knl in Pa s^2/m^6)"
                                .into(),
                        ));
                    }
                }
                if let Some(k) = knl {
                    if !(*k >= 0.0) {
                        return Err(err("enclosure.knl", format!("{k} Pa s^2/m^6 must be >= 0")));
                    }
                    if port_loss.is_some() {
                        return Err(err(
                            "enclosure.knl",
                            "give the port's quadratic loss once: port_loss with port_area, or knl".into(),
                        ));
                    }
                }
            }
            BoxKind::PassiveRadiator { sp, mmp, kmp, rmp } => {
                positive("Sp", *sp, "m^2")?;
                positive("Mmp", *mmp, "kg")?;
                positive("Kmp", kmp.c[0], "N/m (at rest)")?;
                if !(*rmp >= 0.0) {
                    return Err(err("enclosure.Rmp", format!("{rmp} N s/m must be >= 0")));
                }
            }
        }
        Ok(())
    }

    /// The value of a key of the box (`Vb`, `fb`, ...: a schema key with `enclosure.` taken
    /// off), as [`crate::params::Parameters::get`] gives it; `None` where this box has none.
    pub fn value(&self, key: &str) -> Option<crate::params::SchemaValue<'_>> {
        use crate::params::SchemaValue as V;
        let num = |v: Option<f64>| v.map(V::Number);
        match (key, &self.kind) {
            ("type", _) => Some(V::Text(self.type_name())),
            ("Vb", _) => Some(V::Number(self.vb)),
            ("adiabatic", _) => Some(V::Flag(self.adiabatic)),
            ("QL", _) => num(self.ql),
            ("fb", BoxKind::Vented { fb, .. }) => Some(V::Number(*fb)),
            ("Qp", BoxKind::Vented { qp, .. }) => num(*qp),
            ("port_area", BoxKind::Vented { port_area, .. }) => num(*port_area),
            ("port_loss", BoxKind::Vented { port_loss, .. }) => num(*port_loss),
            ("knl", BoxKind::Vented { knl, .. }) => num(*knl),
            ("Sp", BoxKind::PassiveRadiator { sp, .. }) => Some(V::Number(*sp)),
            ("Mmp", BoxKind::PassiveRadiator { mmp, .. }) => Some(V::Number(*mmp)),
            ("Kmp", BoxKind::PassiveRadiator { kmp, .. }) => Some(V::Series(kmp)),
            ("Rmp", BoxKind::PassiveRadiator { rmp, .. }) => Some(V::Number(*rmp)),
            _ => None,
        }
    }

    /// The number under a schema key (`enclosure.Vb`, ...; `Kmp` at rest), `None` where this
    /// box has none.
    pub fn get(&self, key: &str) -> Option<f64> {
        self.value(key.strip_prefix("enclosure.")?)?.at_rest()
    }

    /// The box as the contract's JSON object: every `enclosure.` entry of the schema it has.
    pub fn to_json(&self) -> Value {
        let mut m = Map::new();
        for e in crate::schema::ENTRIES {
            let Some(key) = e.key.strip_prefix("enclosure.") else { continue };
            if let Some(v) = self.value(key) {
                m.insert(key.into(), v.to_json(e.kind));
            }
        }
        Value::Object(m)
    }
}

/// The keys under which [`BoxModel::lifted`] lifts the radiator's `Kmp(xp)` coefficients
/// (`c0`, `c1`, `c2`; `enclosure.Kmp` is the schema's, at rest); higher ones are held.
pub const KMP_TERMS: [&str; 3] = ["enclosure.Kmp", "enclosure.Kmp.1", "enclosure.Kmp.2"];

/// The box's states beside the driver's: the gauge pressure `p` (Pa), then the port's volume
/// velocity `U` (m^3/s, out of the box) or the radiator's excursion `xp` (m) and velocity
/// `vp` (m/s). Unused states stay at zero.
pub const NBOXSTATE: usize = 3;

/// A box in the model's scalar type (what [`crate::model::ExtModel`] integrates).
#[derive(Clone, Debug)]
pub struct BoxModel<D> {
    pub sd: D,
    pub vb: D,
    /// `gamma p0 / Vb` (Pa/m^3), the linear law's stiffness of the box air.
    pub stiffness: D,
    pub adiabatic: bool,
    /// `1 / Ral` (m^3/(Pa s)); zero without a leak.
    pub leak: D,
    pub outlet: Outlet<D>,
}

/// What works on the box air besides the cone and the leak, in the model's scalar type.
#[derive(Clone, Debug)]
pub enum Outlet<D> {
    Sealed,
    /// `Map` (kg/m^4), `Rap` (Pa s/m^3), `knl` (Pa s^2/m^6).
    Port {
        map: D,
        rap: D,
        knl: D,
    },
    /// `Sp` (m^2), `Mmp` (kg), `Kmp(xp)` (N/m), `Rmp` (N s/m).
    Radiator {
        sp: D,
        mmp: D,
        kmp: Poly<D>,
        rmp: D,
    },
}

/// The box's contribution to the rates at one state ([`BoxModel::rates`]).
#[derive(Clone, Copy, Debug)]
pub struct BoxRates<D> {
    /// The force on the cone `Sd p` (N, + = coil out).
    pub force: D,
    /// The rates of the box's states.
    pub d: [D; NBOXSTATE],
}

impl<D: DualNum<Primitive = f64> + Copy> BoxModel<D> {
    /// The box of `e` holding a driver of stiffness `kms0`, mass `mms` and area `sd`.
    pub fn new(e: &Enclosure, kms0: f64, mms: f64, sd: f64) -> Self {
        Self::lifted(e, D::from(kms0), D::from(mms), sd, &|_, v| D::from(v))
    }

    /// [`BoxModel::new`] with the driver's `kms0` and `mms` in `D` and each of the box's values
    /// taken through `lift(key, value)` ([`Enclosure::elements_lifted`]): a fit's model, whose
    /// unknowns the box's values are.
    pub fn lifted(e: &Enclosure, kms0: D, mms: D, sd: f64, lift: &dyn Fn(&'static str, f64) -> D) -> Self {
        let el = e.elements_lifted(kms0, mms, D::from(sd), lift);
        let outlet = match &e.kind {
            BoxKind::Closed => Outlet::Sealed,
            BoxKind::Vented { .. } => {
                let (map, rap, knl) = el.port.expect("a vented box has a port");
                Outlet::Port { map, rap, knl }
            }
            BoxKind::PassiveRadiator { sp, mmp, kmp, rmp } => {
                let kmp = Poly {
                    c: kmp
                        .c
                        .iter()
                        .enumerate()
                        .map(|(j, &c)| lift(KMP_TERMS.get(j).copied().unwrap_or(""), c))
                        .collect(),
                };
                Outlet::Radiator {
                    sp: lift("enclosure.Sp", *sp),
                    mmp: lift("enclosure.Mmp", *mmp),
                    kmp,
                    rmp: lift("enclosure.Rmp", *rmp),
                }
            }
        };
        BoxModel {
            sd: D::from(sd),
            vb: el.vb,
            stiffness: el.cab.recip(),
            adiabatic: e.adiabatic,
            leak: el.ral.map_or(D::zero(), |r| r.recip()),
            outlet,
        }
    }

    /// The force on the cone and the rates of the box's states `b` at cone displacement `x`
    /// and velocity `v`.
    #[inline]
    pub fn rates(&self, x: D, v: D, b: [D; NBOXSTATE]) -> BoxRates<D> {
        let [p, q1, q2] = b;
        let (outflow, volume, dq) = match &self.outlet {
            Outlet::Sealed => (D::zero(), self.vb + self.sd * x, [D::zero(), D::zero()]),
            Outlet::Port { map, rap, knl } => {
                let u = q1;
                (u, self.vb + self.sd * x, [(p - *rap * u - *knl * u * u.abs()) / *map, D::zero()])
            }
            Outlet::Radiator { sp, mmp, kmp, rmp } => {
                let (xp, vp) = (q1, q2);
                (*sp * vp, self.vb + self.sd * x + *sp * xp, [vp, (*sp * p - *rmp * vp - kmp.eval(xp) * xp) / *mmp])
            }
        };
        let flow = self.sd * v + outflow + p * self.leak;
        let k = if self.adiabatic { (p + P0) * GAMMA / volume } else { self.stiffness };
        BoxRates { force: self.sd * p, d: [-k * flow, dq[0], dq[1]] }
    }

    /// The energy stored in the box (J) at cone displacement `x`: the box air's (`Cab p^2 / 2`
    /// under the linear law; under the adiabatic law, the work that compressed the air now in
    /// the box isentropically from ambient pressure to `p0 + p`), the port air's `Map U^2 /
    /// 2`, and the radiator's kinetic and spring energy.
    pub fn stored_energy(&self, x: D, b: [D; NBOXSTATE]) -> D {
        let [p, q1, q2] = b;
        let mut volume = self.vb + self.sd * x;
        let mut e = match &self.outlet {
            Outlet::Sealed => D::zero(),
            Outlet::Port { map, .. } => *map * q1 * q1 * 0.5,
            Outlet::Radiator { sp, mmp, kmp, .. } => {
                volume += *sp * q1;
                *mmp * q2 * q2 * 0.5 + kmp.moment_integral(q1)
            }
        };
        e += if self.adiabatic {
            // The air's volume at ambient pressure, V0 = V ((p0 + p) / p0)^(1/gamma); the work
            // -int_V0^V p dV' along (p0 + p) V'^gamma = p0 V0^gamma.
            let v0 = volume * ((p + P0) * (1.0 / P0)).powf(1.0 / GAMMA);
            let g1 = GAMMA - 1.0;
            v0 * P0 * ((v0 / volume).powf(g1) - 1.0) * (1.0 / g1) + (volume - v0) * P0
        } else {
            p * p * 0.5 / self.stiffness
        };
        e
    }

    /// The power the box dissipates (W): the leak's `p^2 / Ral`, the port's `Rap U^2 + knl
    /// |U|^3`, the radiator's `Rmp vp^2`.
    pub fn loss(&self, b: [D; NBOXSTATE]) -> D {
        let [p, q1, q2] = b;
        p * p * self.leak
            + match &self.outlet {
                Outlet::Sealed => D::zero(),
                Outlet::Port { rap, knl, .. } => *rap * q1 * q1 + *knl * q1 * q1 * q1.abs(),
                Outlet::Radiator { rmp, .. } => *rmp * q2 * q2,
            }
    }

    /// The net volume velocity radiated into the room (m^3/s): `Sd v`, plus the port's flow
    /// or the radiator's `Sp vp`, plus the leak's.
    pub fn radiated(&self, v: D, b: [D; NBOXSTATE]) -> D {
        let [p, q1, q2] = b;
        let out = match &self.outlet {
            Outlet::Sealed => D::zero(),
            Outlet::Port { .. } => q1,
            Outlet::Radiator { sp, .. } => *sp * q2,
        };
        self.sd * v + out + p * self.leak
    }
}

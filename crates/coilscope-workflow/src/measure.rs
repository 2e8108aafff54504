//! `coilscope measure`'s setup and its result, as the command line and Python both do it: the
//! device a run measures (a virtual driver in its world, or a replayed record), where its
//! absolute scale (`Mms`) comes from, and the result file the run gives.

use coilscope_core::chain::Chain;
use coilscope_core::mass::Mass;
use coilscope_core::result::ResultFile;
use coilscope_core::Parameters;
use coilscope_io::Recording;
use coilscope_measure::device::{Device, ReplayDevice, VirtualDevice};
use coilscope_measure::{Measurement, StopReason};

/// The virtual driver's world.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum World {
    /// The parameter set as given.
    Published,
    /// Plus typical LOG creep where the set has none
    /// ([`coilscope_core::params::TYPICAL_CREEP_LAMBDA`] at the resonance), as a real
    /// suspension has: the default of `measure --virtual`.
    Real,
}

impl World {
    /// `published` or `real`.
    pub fn parse(s: &str) -> Result<World, String> {
        match s {
            "published" => Ok(World::Published),
            "real" => Ok(World::Real),
            o => Err(format!("world {o:?}: give real (typical creep added, as real suspensions creep) or published (the set as given)")),
        }
    }

    /// The driver in this world.
    pub fn apply(self, p: Parameters) -> Parameters {
        match self {
            World::Published => p,
            World::Real => p.with_typical_creep(),
        }
    }
}

/// A device ready to be measured, with the run's absolute scale.
pub struct Prepared {
    /// The device (`None` once taken by [`Prepared::split`]).
    pub device: Option<Box<dyn Device + Send>>,
    /// Moving mass (kg): the scale of every mechanical value.
    pub mms: f64,
    /// Where `mms` came from, as the result's `fit.mms_source` says.
    pub mms_source: String,
    /// The relative sd of `mms` as given (0: taken as exact), carried into the result.
    pub mms_sd_rel: f64,
    /// The driver's radiating area (m^2): given, or a virtual driver's own.
    pub sd: Option<f64>,
    /// What the user should be told of the setup (the world assumed).
    pub notes: Vec<String>,
}

impl Prepared {
    /// The setup of a device opened elsewhere (a sound card), `mms` given.
    pub fn given(mms: Mass, sd: Option<f64>) -> Prepared {
        Prepared {
            device: None,
            mms: mms.kg,
            mms_source: format!("given (--mms {mms})"),
            mms_sd_rel: mms.sd_rel(),
            sd,
            notes: Vec::new(),
        }
    }

    /// The device taken out, and the rest of the setup.
    pub fn split(mut self) -> (Box<dyn Device + Send>, Prepared) {
        let d = self.device.take().expect("a prepared device is split once");
        (d, self)
    }
}

/// `sd` as given (`--sd`): a radiating area in m^2.
pub fn check_sd(sd: Option<f64>) -> Result<(), String> {
    match sd {
        Some(sd) if !(sd.is_finite() && sd > 0.0 && sd < 10.0) => {
            Err(format!("--sd {sd}: give the effective radiating area in m^2 (e.g. 0.0133 for a 6.5\" cone)"))
        }
        _ => Ok(()),
    }
}

/// The virtual device of the set `given` (named `name` in messages) in `world`, sampled at
/// `fs` with sensor noise `noise` (V, A rms) and `seed`. `mms` given, or the set's own.
/// A set with a box is refused: the dynamic measurement models a driver in free air.
#[allow(clippy::too_many_arguments)]
pub fn virtual_driver(
    given: &Parameters,
    name: &str,
    world: World,
    mms: Option<Mass>,
    sd: Option<f64>,
    fs: f64,
    noise: (f64, f64),
    seed: u64,
) -> Result<Prepared, String> {
    check_sd(sd)?;
    if let Some(e) = &given.enclosure {
        return Err(format!("{name}: the set puts the driver in a {} box (`enclosure`); the dynamic measurement identifies a driver in free air and does not model a box yet, so it would read the box's air as the suspension. Remove `enclosure` to measure the driver in free air; `coilscope simulate --enclosure` and `coilscope linear --enclosure` handle the box", e.type_name()));
    }
    let p = world.apply(given.clone());
    let mut notes = Vec::new();
    if p != *given {
        notes.push(format!("virtual world: real (LOG creep lambda {} assumed, as real suspensions creep; --world published for the set as given)", coilscope_core::params::TYPICAL_CREEP_LAMBDA));
    }
    let device = VirtualDevice::new(&p, fs, noise, seed)?;
    let (mms, mms_source, mms_sd_rel) = match mms {
        Some(m) => (m.kg, format!("given (--mms {m})"), m.sd_rel()),
        None => (p.mms, format!("the virtual driver's own Mms ({name})"), 0.0),
    };
    Ok(Prepared { device: Some(Box::new(device)), mms, mms_source, mms_sd_rel, sd: sd.or(given.sd), notes })
}

/// A replay of the record `rec` (named `name`). `mms` given, or from the record's
/// displacement channel (a laser) by the post-inverse equation-error fit of the whole record;
/// a record without either is refused.
pub fn replay(rec: Recording, name: &str, mms: Option<Mass>, sd: Option<f64>) -> Result<Prepared, String> {
    check_sd(sd)?;
    let mut notes = Vec::new();
    let mms_sd_rel = mms.map_or(0.0, |m| m.sd_rel());
    let (mms, mms_source) = match (mms, &rec.x) {
        (Some(m), _) => (m.kg, format!("given (--mms {m})")),
        (None, Some(x)) => {
            let pi = crate::identify::post_inverse_of(&rec.u, &rec.i, x, rec.fs as f64, 4, name)?;
            notes.push(format!("Mms {:.3} g from the displacement channel (post-inverse equation error)", pi.mms * 1e3));
            (pi.mms, "displacement channel (post-inverse equation error)".to_string())
        }
        (None, None) => return Err(format!("{name}: --replay needs an absolute scale: give --mms KG (moving mass), or a recording with a displacement channel (3, m)")),
    };
    let device = ReplayDevice::from_samples(name, rec.fs as f64, rec.u, rec.i);
    Ok(Prepared { device: Some(Box::new(device)), mms, mms_source, mms_sd_rel, sd, notes })
}

/// The result file of a finished run `m`: with the scale's source, the relative sd of the
/// mass given (carried into what it scales, [`coilscope_core::result::Uncertainty::carry_mass_sd`])
/// and `sd` of its setup, and the chain it was corrected for (`None`: none).
pub fn result_of(
    m: &mut Measurement,
    mms_source: &str,
    mms_sd_rel: f64,
    sd: Option<f64>,
    chain: Option<Chain>,
) -> ResultFile {
    m.mms_source = mms_source.to_string();
    let mut j = m.result();
    j.uncertainty.carry_mass_sd(&j.parameters, mms_sd_rel);
    j.parameters.sd = sd;
    if chain.is_some() {
        j.chain = chain;
    }
    j
}

/// The run's status in one word or two, as the run database stores it.
pub fn status(m: &Measurement) -> &'static str {
    match m.stop_reason {
        _ if m.converged => "converged",
        StopReason::Interrupted { .. } => "interrupted",
        StopReason::Failed { .. } => "failed",
        StopReason::DurationOver { .. } => "finished",
        _ => "not converged",
    }
}

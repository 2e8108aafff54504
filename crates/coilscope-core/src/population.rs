//! A population of physically plausible drivers, drawn from a seed.
//!
//! A measurement tool is judged on the next driver, not on the few it was developed on. This
//! module draws parameter sets (the file contract's [`Parameters`]) over the classes of
//! electrodynamic transducers coilscope measures, from phone receivers to long-stroke
//! subwoofers, with the large-signal shapes real units show. The same seed always gives the
//! same driver ([`draw`]); `population:SEED` (or `population:CLASS:SEED`) names one wherever
//! a driver is read ([`parse_name`]).
//!
//! ## How a driver is drawn
//!
//! Within a class, one size variable `s` in [0, 1] sets the moving mass, the radiating area,
//! the coil's inductance and the excursion range together (each with its own spread around
//! the trend), as they go together in real drivers. The small-signal set follows the way a
//! designer reads a datasheet: the resonance `fs`, the mechanical and electrical Q and the
//! coil resistance are drawn, and `Kms = Mms (2 pi fs)^2`, `Rms = 2 pi fs Mms / Qms`,
//! `Bl = sqrt(2 pi fs Mms Re / Qes)` follow, so that every driver is consistent with itself.
//!
//! The curves are drawn over the normalised excursion `u = x / X` (X: the half-width of the
//! valid range) and written as power series in x (metres):
//!
//! * **Bl(x)**: a peak at a rest-position offset `d` (the coil sits off the gap's centre: LSI's
//!   Xsym), falling to 45-85 % of the peak at the range's edges. The fall mixes `w^2` (a short
//!   overhang, or an underhung coil leaving the gap early) and `w^4` (a long overhang: a plateau,
//!   then a steep fall) with `w = u - d`, and a `w^3` term makes one side fall faster.
//! * **Kms(x)**: rising to 2-4.5 times its rest value at the stiffer edge (a progressive
//!   spider and surround; a measured range ends about where the suspension has doubled its
//!   stiffness), one side stiffer than the other, and sometimes soft at rest (a small
//!   negative `u^2` term under the `u^4` hardening: a flat region before it stiffens).
//!   The restoring force `Kms(x) x` rises monotonically over the range and 10 % beyond it.
//! * **Le(x)**: rising as the coil moves in towards the back plate (x < 0: 10-100 % above its
//!   rest value at the inner edge) and falling as it moves out (5-40 % at the outer edge).
//! * **L2, R2**: the LR-2 para-inductance (Wright's empirical motor model) as a multiple of Le
//!   with its corner `R2 / (2 pi L2)`.
//! * **Thermal**: the coil's and the magnet's resistances and time constants by class.
//!
//! Each drawn unit may also carry the effects of real drivers ([`Effects`]): LOG creep of the
//! suspension (lambda 0.02-0.15), a second para-inductance branch LR-3, flux modulation Le(i),
//! and a velocity-dependent loss Rms(v). [`Draw::natural`] is the unit with the effects it was
//! drawn with; [`Draw::with_effects`] chooses them, for the tests of one world.
//!
//! ## Sources of the ranges
//!
//! * Small-signal sets (Mms, fs, Qms, Qes, Re, Le, Sd, Xmax) by class: manufacturers'
//!   datasheets (SB Acoustics, Scan-Speak, SEAS, Purifi, Dayton Audio, Tymphany, and the
//!   microspeaker and receiver datasheets of AAC, Knowles and PUI Audio) and the T/S collection
//!   of loudspeakerdatabase.com.
//! * Large-signal shapes and the edges of the valid range: KLIPPEL LSI reports published in
//!   Erin's Audio Corner driver reviews (the three bundled drivers among them), and W. Klippel,
//!   "Loudspeaker Nonlinearities - Causes, Parameters, Symptoms", J. Audio Eng. Soc. 54 (2006),
//!   with the IEC 62458 limits (Bl 82 %, Cms 75 %, Le 10 %) that a valid range reaches.
//! * LR-2: J. R. Wright, "An Empirical Model for Loudspeaker Motor Impedance", J. Audio Eng.
//!   Soc. 38 (1990); LSI reports give L2 of 0.3-3 times Le.
//! * Creep: M. H. Knudsen and J. G. Jensen, "Low-Frequency Loudspeaker Models That Include
//!   Suspension Creep", J. Audio Eng. Soc. 41 (1993); KLIPPEL LPM reports LOG creep factors of
//!   0.03-0.1 for woofer suspensions and up to about 0.15 for soft rubber surrounds.
//! * Thermal: W. Klippel, "Nonlinear Modeling of the Heat Transfer in Loudspeakers", J. Audio
//!   Eng. Soc. 52 (2004) (woofers: coil time constants of 10-60 s, magnets of many minutes);
//!   speaker-protection application notes for microspeakers (coil time constants of 1-5 s).
//!
//! The classes' ranges are deliberately a little wider than the typical: the population is a
//! test of the tool, and a driver at the edge of its class is a driver a user will bring.

pub use crate::effects::Effects;
use crate::excitation::named_rng;
use crate::params::{Creep, Parameters, Thermal, ALPHA_COPPER};
use crate::poly::Poly;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use std::f64::consts::PI;

/// The classes of drivers the population covers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Class {
    /// Phone receivers, earbud and laptop speakers, headphone drivers: Mms 0.05-3 g.
    Microspeaker,
    /// Small full-range drivers, 2-3.5": Mms 1.5-6 g.
    Fullrange,
    /// Midwoofers, 4-6.5": Mms 5-25 g.
    Midwoofer,
    /// Woofers, 8-12": Mms 25-110 g.
    Woofer,
    /// Long-stroke subwoofers, 12-18": Mms 100-300 g, Le to 4 mH, L2 to 8 mH.
    Subwoofer,
}

impl Class {
    /// Every class, smallest first.
    pub const ALL: [Class; 5] =
        [Class::Microspeaker, Class::Fullrange, Class::Midwoofer, Class::Woofer, Class::Subwoofer];

    /// The name used in `population:CLASS:SEED` and in messages.
    pub fn name(self) -> &'static str {
        match self {
            Class::Microspeaker => "microspeaker",
            Class::Fullrange => "fullrange",
            Class::Midwoofer => "midwoofer",
            Class::Woofer => "woofer",
            Class::Subwoofer => "subwoofer",
        }
    }

    /// The class of a name (as [`Class::name`] gives it), case-insensitive.
    pub fn from_name(name: &str) -> Option<Class> {
        Class::ALL.into_iter().find(|c| c.name().eq_ignore_ascii_case(name))
    }

    fn ranges(self) -> &'static Ranges {
        match self {
            Class::Microspeaker => &MICROSPEAKER,
            Class::Fullrange => &FULLRANGE,
            Class::Midwoofer => &MIDWOOFER,
            Class::Woofer => &WOOFER,
            Class::Subwoofer => &SUBWOOFER,
        }
    }
}

impl std::fmt::Display for Class {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A class's ranges. `(a, b)` pairs that follow the size variable go from `a` at the smallest
/// unit of the class to `b` at the largest (geometrically); the others are drawn within them.
struct Ranges {
    /// Moving mass (kg), with the size.
    mms: (f64, f64),
    /// Resonance (Hz) at the smallest and the largest unit.
    fs: (f64, f64),
    /// Radiating area (m^2), with the size.
    sd: (f64, f64),
    /// Half-width of the valid range (m), with the size.
    x: (f64, f64),
    /// Le(0) (H), with the size.
    le: (f64, f64),
    /// L2 as a multiple of Le(0).
    l2_over_le: (f64, f64),
    /// The LR-2 corner R2 / (2 pi L2) (Hz).
    f2: (f64, f64),
    /// Mechanical and electrical Q.
    qms: (f64, f64),
    qes: (f64, f64),
    /// Coil resistances (ohm) of the nominal impedances the class is built with.
    re: &'static [(f64, f64)],
    /// Coil-to-magnet thermal resistance (K/W) and the coil's time constant Rtv Ctv (s).
    rtv: (f64, f64),
    tau_v: (f64, f64),
    /// Magnet-to-ambient resistance (K/W) and the magnet's time constant (s).
    rtm: (f64, f64),
    tau_m: (f64, f64),
}

const MICROSPEAKER: Ranges = Ranges {
    mms: (0.05e-3, 3e-3),
    fs: (1000.0, 180.0),
    sd: (0.8e-4, 20e-4),
    x: (0.3e-3, 2.5e-3),
    le: (15e-6, 100e-6),
    l2_over_le: (0.3, 1.5),
    f2: (2000.0, 20000.0),
    qms: (1.0, 6.0),
    qes: (0.8, 4.0),
    re: &[(3.0, 4.4), (5.8, 7.5), (7.0, 8.5)],
    rtv: (25.0, 100.0),
    tau_v: (1.5, 5.0),
    rtm: (15.0, 100.0),
    tau_m: (40.0, 300.0),
};

const FULLRANGE: Ranges = Ranges {
    mms: (1.5e-3, 6e-3),
    fs: (170.0, 80.0),
    sd: (20e-4, 56e-4),
    x: (1.5e-3, 5e-3),
    le: (30e-6, 400e-6),
    l2_over_le: (0.5, 6.0),
    f2: (300.0, 3000.0),
    qms: (1.3, 8.0),
    qes: (0.5, 1.7),
    re: &[(3.0, 3.6), (5.6, 7.2)],
    rtv: (5.0, 15.0),
    tau_v: (4.0, 20.0),
    rtm: (3.0, 10.0),
    tau_m: (200.0, 1200.0),
};

const MIDWOOFER: Ranges = Ranges {
    mms: (5e-3, 30e-3),
    fs: (90.0, 30.0),
    sd: (50e-4, 155e-4),
    x: (3e-3, 12e-3),
    le: (0.04e-3, 1.0e-3),
    l2_over_le: (0.5, 10.0),
    f2: (80.0, 2000.0),
    qms: (2.0, 12.0),
    qes: (0.3, 0.8),
    re: &[(3.0, 3.6), (5.4, 7.2)],
    rtv: (2.0, 6.0),
    tau_v: (8.0, 30.0),
    rtm: (0.8, 3.0),
    tau_m: (600.0, 3600.0),
};

const WOOFER: Ranges = Ranges {
    mms: (25e-3, 130e-3),
    fs: (45.0, 20.0),
    sd: (200e-4, 530e-4),
    x: (5e-3, 14e-3),
    le: (0.1e-3, 3.0e-3),
    l2_over_le: (0.5, 4.0),
    f2: (80.0, 1500.0),
    qms: (2.0, 10.0),
    qes: (0.25, 0.75),
    re: &[(3.0, 3.6), (5.4, 7.2)],
    rtv: (1.0, 3.0),
    tau_v: (15.0, 60.0),
    rtm: (0.5, 1.5),
    tau_m: (1200.0, 5400.0),
};

const SUBWOOFER: Ranges = Ranges {
    mms: (100e-3, 300e-3),
    fs: (35.0, 16.0),
    sd: (500e-4, 1200e-4),
    x: (10e-3, 25e-3),
    le: (1.0e-3, 4.0e-3),
    l2_over_le: (0.5, 2.0),
    f2: (80.0, 1000.0),
    qms: (2.5, 12.0),
    qes: (0.25, 0.6),
    re: &[(1.5, 1.9), (3.0, 3.6), (5.4, 7.2)],
    rtv: (0.5, 2.0),
    tau_v: (30.0, 120.0),
    rtm: (0.3, 1.0),
    tau_m: (1800.0, 7200.0),
};

/// One drawn driver: the plain parameter set and the values of every effect, whether or not
/// this unit carries it.
#[derive(Clone, Debug)]
pub struct Draw {
    pub seed: u64,
    pub class: Class,
    /// The driver without creep, LR-3, Le(i) and Rms(v).
    pub plain: Parameters,
    /// The effects this unit was drawn with.
    pub effects: Effects,
    creep: Creep,
    l3r3: (f64, f64),
    le_i: Poly,
    rms_v: Poly,
}

impl Draw {
    /// The driver with the effects it was drawn with.
    pub fn natural(&self) -> Parameters {
        self.with_effects(self.effects)
    }

    /// The driver with the chosen effects (each with this unit's own values).
    pub fn with_effects(&self, e: Effects) -> Parameters {
        let mut p = self.plain.clone();
        p.creep = e.creep.then(|| self.creep.clone());
        p.l3r3 = e.lr3.then_some(self.l3r3);
        p.le_i = e.le_i.then(|| self.le_i.clone());
        p.rms_v = e.rms_v.then(|| self.rms_v.clone());
        p
    }

    /// The name that draws this unit again (`population:CLASS:SEED`).
    pub fn name(&self) -> String {
        format!("population:{}:{}", self.class.name(), self.seed)
    }
}

/// The share of the population in each class, in [`Class::ALL`]'s order: woofers of every
/// size are what most users measure; microspeakers are a fifth.
const CLASS_WEIGHTS: [f64; 5] = [0.2, 0.15, 0.25, 0.25, 0.15];

/// The driver of `seed`, its class drawn with the population's shares.
pub fn draw(seed: u64) -> Draw {
    let mut rng = named_rng(seed, "population class");
    let mut r: f64 = rng.random();
    let mut class = Class::Subwoofer;
    for (c, w) in Class::ALL.into_iter().zip(CLASS_WEIGHTS) {
        if r < w {
            class = c;
            break;
        }
        r -= w;
    }
    draw_in(class, seed)
}

/// The driver of `seed` within one class.
pub fn draw_in(class: Class, seed: u64) -> Draw {
    let mut rng = named_rng(seed, &format!("population {}", class.name()));
    // A drawn shape is kept when its curves are physical over the range and 10 % beyond it
    // (where a protection that overshoots still takes the driver); a handful of tries does.
    loop {
        if let Some(d) = try_draw(class, seed, &mut rng) {
            return d;
        }
    }
}

/// `population:SEED` or `population:CLASS:SEED`: the driver it names, or `None` when `spec`
/// is not a population name. `Some(Err)` says what is wrong with one that is.
pub fn parse_name(spec: &str) -> Option<Result<Draw, String>> {
    let rest = spec.strip_prefix("population:")?;
    let valid = "population:SEED or population:CLASS:SEED, with SEED a whole number and CLASS one of microspeaker, fullrange, midwoofer, woofer, subwoofer";
    let (class, seed) = match rest.split_once(':') {
        Some((c, s)) => match Class::from_name(c) {
            Some(c) => (Some(c), s),
            None => return Some(Err(format!("{spec}: unknown class `{c}`; give {valid}"))),
        },
        None => (None, rest),
    };
    let Ok(seed) = seed.parse::<u64>() else {
        return Some(Err(format!("{spec}: `{seed}` is not a seed; give {valid}")));
    };
    Some(Ok(match class {
        Some(c) => draw_in(c, seed),
        None => draw(seed),
    }))
}

fn lerp_log((a, b): (f64, f64), s: f64) -> f64 {
    (a.ln() + (b.ln() - a.ln()) * s).exp()
}

/// A box for the driver `p` (which has `Sd`), drawn from `seed`: `kind` (`closed`, `vented`
/// or `passive_radiator`), or one of the three at random. Sizes follow the driver's `Vas` and
/// `fs` as boxes are designed: a closed box of 0.3-3 Vas (a microspeaker's back volume among
/// them), a vented box of 0.5-3 Vas tuned to 0.6-1.4 fs with a port of 10-30 % of Sd, a
/// passive radiator of 1-2.5 Sd tuned to 0.6-1.2 fs, its own suspension 10-60 % of its
/// stiffness on the box air, stiffening by up to 2x at the driver's excursion. Leaks QL 5-20,
/// port losses Qp 10-80 and `port_loss` 0.5-3, radiator Q 5-20.
pub fn draw_box(seed: u64, p: &Parameters, kind: Option<&str>) -> crate::enclosure::Enclosure {
    use crate::enclosure::{BoxKind, Enclosure, GAMMA, P0};
    let mut rng = named_rng(seed, "population box");
    let sd = p.sd.expect("a driver in a box has Sd");
    let ts = crate::small_signal::thiele_small(p);
    let vas = ts.vas.expect("Sd is known");
    let kind = kind.unwrap_or(["closed", "vented", "passive_radiator"][rng.random_range(0..3)]);
    let ql = Some(log_uniform(&mut rng, (5.0, 20.0)));
    match kind {
        "closed" => {
            Enclosure { vb: vas * log_uniform(&mut rng, (0.3, 3.0)), ql, adiabatic: true, kind: BoxKind::Closed }
        }
        "vented" => {
            let vb = vas * log_uniform(&mut rng, (0.5, 3.0));
            let kind = BoxKind::Vented {
                fb: ts.fs * uniform(&mut rng, (0.6, 1.4)),
                qp: Some(log_uniform(&mut rng, (10.0, 80.0))),
                port_area: Some(sd * uniform(&mut rng, (0.1, 0.3))),
                port_loss: Some(uniform(&mut rng, (0.5, 3.0))),
                knl: None,
            };
            Enclosure { vb, ql, adiabatic: true, kind }
        }
        _ => {
            let vb = vas * log_uniform(&mut rng, (0.5, 3.0));
            let sp = sd * uniform(&mut rng, (1.0, 2.5));
            let ft = ts.fs * uniform(&mut rng, (0.6, 1.2));
            let air = sp * sp * GAMMA * P0 / vb;
            let share = uniform(&mut rng, (0.1, 0.6));
            let kmp0 = share / (1.0 - share) * air;
            let mmp = (kmp0 + air) / (2.0 * std::f64::consts::PI * ft).powi(2);
            let rmp = 2.0 * std::f64::consts::PI * ft * mmp / log_uniform(&mut rng, (5.0, 20.0));
            // Up to twice as stiff where the radiator moves as far as the cone's range.
            let xp = p.x_range.map_or(0.005, |r| r[1]);
            let c2 = kmp0 * uniform(&mut rng, (0.0, 1.0)) / (xp * xp);
            Enclosure {
                vb,
                ql,
                adiabatic: true,
                kind: BoxKind::PassiveRadiator { sp, mmp, kmp: Poly { c: vec![kmp0, 0.0, c2] }, rmp },
            }
        }
    }
}

fn uniform(rng: &mut ChaCha8Rng, (a, b): (f64, f64)) -> f64 {
    a + (b - a) * rng.random::<f64>()
}

fn log_uniform(rng: &mut ChaCha8Rng, (a, b): (f64, f64)) -> f64 {
    lerp_log((a, b), rng.random())
}

/// A value that follows the size `s` with a spread of `spread` (a factor, geometric) around
/// the trend, kept within the class's range.
fn with_size(rng: &mut ChaCha8Rng, range: (f64, f64), s: f64, spread: f64) -> f64 {
    let (lo, hi) = (range.0.min(range.1), range.0.max(range.1));
    (lerp_log(range, s) * log_uniform(rng, (1.0 / spread, spread))).clamp(lo, hi)
}

/// The coefficients of `sum_k a_k (u - d)^k` as a power series in u.
fn shift(a: &[f64], d: f64) -> Vec<f64> {
    let mut c = vec![0.0; a.len()];
    for (k, &ak) in a.iter().enumerate() {
        // (u - d)^k = sum_j binom(k, j) u^j (-d)^(k - j)
        let mut binom = 1.0;
        for j in 0..=k {
            c[j] += ak * binom * (-d).powi((k - j) as i32);
            binom = binom * (k - j) as f64 / (j + 1) as f64;
        }
    }
    c
}

/// A series in u = x / X as a power series in x (metres), scaled by `v0`.
fn in_metres(u: &[f64], x: f64, v0: f64) -> Poly {
    Poly { c: u.iter().enumerate().map(|(j, &c)| v0 * c / x.powi(j as i32)).collect() }
}

fn eval(c: &[f64], u: f64) -> f64 {
    c.iter().rev().fold(0.0, |acc, &cj| acc * u + cj)
}

/// Points over the range and 10 % beyond it, where a drawn curve must be physical.
fn grid() -> impl Iterator<Item = f64> {
    (0..=220).map(|k| -1.1 + 2.2 * k as f64 / 220.0)
}

fn try_draw(class: Class, seed: u64, rng: &mut ChaCha8Rng) -> Option<Draw> {
    let r = class.ranges();
    let s: f64 = rng.random();
    let mms = with_size(rng, r.mms, s, 1.15);
    let fs = with_size(rng, r.fs, s, 1.3);
    let sd = with_size(rng, r.sd, s, 1.2);
    let x = with_size(rng, r.x, s, 1.3);
    let le0 = with_size(rng, r.le, s, 1.6);
    let re_band = r.re[rng.random_range(0..r.re.len())];
    let re = uniform(rng, re_band);
    let qms = log_uniform(rng, r.qms);
    let qes = log_uniform(rng, r.qes);
    let w0 = 2.0 * PI * fs;
    let kms0 = mms * w0 * w0;
    let rms = w0 * mms / qms;
    let bl0 = (w0 * mms * re / qes).sqrt();
    let l2 = le0 * log_uniform(rng, r.l2_over_le);
    let r2 = 2.0 * PI * l2 * log_uniform(rng, r.f2);

    // Bl: a peak at the offset d, falling to `edge` of it at the range's edges.
    let d = uniform(rng, (-0.25, 0.25));
    let edge = uniform(rng, (0.45, 0.85));
    let plateau = uniform(rng, (0.0, 0.85)); // the share of the w^4 term
    let skew = uniform(rng, (-0.25, 0.25));
    // The fall's shape in w = u - d, scaled so that the lower edge is at `edge` of the peak.
    let shape = [0.0, 0.0, 1.0 - plateau, -skew, plateau];
    let deepest = [-1.0, 1.0].map(|u| eval(&shape, u - d)).into_iter().fold(f64::MIN, f64::max);
    let fall = (1.0 - edge) / deepest;
    let g = [1.0, 0.0, -fall * shape[2], -fall * shape[3], -fall * shape[4]];
    let bl_u = shift(&g, d);
    let bl_at_rest = eval(&bl_u, 0.0);
    let bl_u: Vec<f64> = bl_u.iter().map(|c| c / bl_at_rest).collect();
    // Bl stays positive and falls away from its peak (no second hump inside the range).
    let peak = d;
    for u in grid() {
        let b = eval(&bl_u, u);
        let slope = eval(&deriv(&bl_u), u);
        if !(b > 0.2) || (u > peak + 0.05 && slope > 0.0) || (u < peak - 0.05 && slope < 0.0) {
            return None;
        }
    }

    // Kms: hardening towards the edges, one side stiffer, sometimes soft at rest. The valid
    // range is the range a measurement reached, and a measurement stops where the suspension
    // has stiffened to about twice its rest stiffness (LSI's reports; `measure --kms-limit`):
    // the stiffer edge is drawn at 2-4.5 times Kms(0), the softer one follows the asymmetry.
    let stiff = log_uniform(rng, (2.0, 4.5));
    let soft = uniform(rng, (-0.08, 0.6)); // the share of the u^2 term (negative: soft at rest)
    let asym = uniform(rng, (-0.35, 0.35));
    let cubic = uniform(rng, (0.0, 0.6)); // the share of the odd part in u^3
    let hard = (stiff - 1.0) / (1.0 + asym.abs());
    let k_u = vec![1.0, asym * hard * (1.0 - cubic), hard * soft, asym * hard * cubic, hard * (1.0 - soft)];
    for u in grid() {
        let k = eval(&k_u, u);
        // The restoring force rises with x: d(Kms(x) x)/dx = Kms + x Kms' > 0.
        let tangent = k + u * eval(&deriv(&k_u), u);
        if !(k > 0.5 && tangent > 0.3) {
            return None;
        }
    }

    // Le: rising towards the back plate (u < 0), falling outwards.
    let inner = uniform(rng, (0.1, 1.0));
    let outer = uniform(rng, (0.05, 0.4));
    let l3c = uniform(rng, (-0.1, 0.1)) * (inner + outer);
    let le_u = vec![1.0, -(inner + outer) / 2.0 - l3c, (inner - outer) / 2.0, l3c];
    for u in grid() {
        if !(eval(&le_u, u) > 0.3 && eval(&deriv(&le_u), u) < 0.0) {
            return None;
        }
    }

    let rtv = uniform(rng, r.rtv);
    let ctv = log_uniform(rng, r.tau_v) / rtv;
    let rtm = uniform(rng, r.rtm);
    let ctm = log_uniform(rng, r.tau_m) / rtm;

    let plain = Parameters {
        name: Some(format!("population {} {seed}", class.name())),
        source: Some(format!(
            "coilscope driver population (synthetic, not a measured unit): population:{}:{seed}",
            class.name()
        )),
        re,
        le: in_metres(&le_u, x, le0),
        l2r2: Some((Poly::constant(l2), Poly::constant(r2))),
        bl: in_metres(&bl_u, x, bl0),
        kms: in_metres(&k_u, x, kms0),
        mms,
        rms,
        sd: Some(sd),
        creep: None,
        l3r3: None,
        le_i: None,
        rms_v: None,
        thermal: Some(Thermal { alpha: ALPHA_COPPER, rtv, ctv, rtm, ctm, rv: 0.0 }),
        enclosure: None,
        x_range: Some([-x, x]),
        extra: Default::default(),
    };

    // The effects' values. The current and velocity that set Le(i)'s and Rms(v)'s scales:
    // three times the static current that holds the cone at the range's edge (the crests of a
    // drive that reaches the edge below the resonance), and the peak velocity of that
    // excursion at the resonance. The flux falls by 0.2-2.5 % at that current, so that the
    // incremental inductance `Le (1 + 3 f2 i^2)` stays above 70 % of Le at twice it.
    let i_ref = 3.0 * kms0 * x / bl0;
    let v_ref = w0 * x;
    let creep = Creep { lambda: uniform(rng, (0.01, 0.15)), f_ref: None };
    // LR-3: a second branch whose corner lies a factor 2-5 from LR-2's, on either side, and
    // inside the band a 44.1-48 kHz record resolves (below 6 kHz): above it the branch is
    // an inductance in series with Le that no record can tell from Le.
    let r3 = r2 * uniform(rng, (1.5, 4.0));
    let f2c = r2 / (2.0 * PI * l2);
    let apart = log_uniform(rng, (2.0, 5.0));
    let f3c = if f2c * apart < 6000.0 && rng.random::<f64>() < 0.5 { f2c * apart } else { f2c / apart };
    let l3r3 = (r3 / (2.0 * PI * f3c), r3);
    let le_i = Poly { c: vec![1.0, 0.0, -uniform(rng, (0.002, 0.025)) / (i_ref * i_ref)] };
    let rms_v = Poly { c: vec![rms, 0.0, rms * uniform(rng, (0.1, 1.0)) / (v_ref * v_ref)] };
    let effects = Effects {
        creep: rng.random::<f64>() < 0.9,
        lr3: rng.random::<f64>() < 0.4,
        le_i: rng.random::<f64>() < 0.3,
        rms_v: rng.random::<f64>() < 0.3,
    };
    let draw = Draw { seed, class, plain, effects, creep, l3r3, le_i, rms_v };
    draw.with_effects(Effects::ALL).validate("population").ok()?;
    Some(draw)
}

fn deriv(c: &[f64]) -> Vec<f64> {
    c.iter().enumerate().skip(1).map(|(j, &cj)| j as f64 * cj).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::small_signal::thiele_small;

    #[test]
    fn a_seed_draws_the_same_driver_every_time() {
        for seed in [0, 1, 17, 123456789] {
            assert_eq!(draw(seed).natural(), draw(seed).natural());
        }
        assert_ne!(draw(1).plain, draw(2).plain);
    }

    #[test]
    fn every_class_is_drawn_and_named() {
        let mut seen = std::collections::HashSet::new();
        for seed in 0..200 {
            let d = draw(seed);
            seen.insert(d.class);
            let again = parse_name(&d.name()).unwrap().unwrap();
            assert_eq!(again.natural(), d.natural());
        }
        assert_eq!(seen.len(), Class::ALL.len());
        assert_eq!(parse_name("population:7").unwrap().unwrap().natural(), draw(7).natural());
        assert!(parse_name("sb17cac35-4").is_none());
        assert!(parse_name("population:tweeter:3").unwrap().unwrap_err().contains("unknown class `tweeter`"));
        assert!(parse_name("population:woofer:x").unwrap().unwrap_err().contains("`x` is not a seed"));
    }

    /// The drawn small-signal set is the one its class's datasheets describe.
    #[test]
    fn drawn_drivers_have_their_class_small_signal_figures() {
        for class in Class::ALL {
            let r = class.ranges();
            for seed in 0..100 {
                let p = draw_in(class, seed).natural();
                p.validate("population").unwrap();
                let ts = thiele_small(&p);
                let fs_lo = r.fs.0.min(r.fs.1);
                let fs_hi = r.fs.0.max(r.fs.1);
                assert!(ts.fs >= fs_lo * 0.999 && ts.fs <= fs_hi * 1.001, "{class} {seed}: fs {}", ts.fs);
                // The class's Qms range is drawn as the viscous Q (creep's loss, drawn apart,
                // lowers the Qms at fs below it).
                let q_viscous = 2.0 * std::f64::consts::PI * ts.fs * p.mms / p.rms;
                assert!(
                    q_viscous >= r.qms.0 * 0.999 && q_viscous <= r.qms.1 * 1.001,
                    "{class} {seed}: viscous Qms {q_viscous}"
                );
                assert!(
                    ts.qms <= q_viscous * (1.0 + 1e-12),
                    "{class} {seed}: Qms at fs {} above the viscous {q_viscous}",
                    ts.qms
                );
                assert!(p.mms >= r.mms.0 * 0.999 && p.mms <= r.mms.1 * 1.001);
                let le_lo = r.le.0.min(r.le.1);
                assert!(p.le.c[0] >= le_lo * 0.999 && p.le.c[0] <= r.le.1 * 1.001, "{class} {seed}: Le {}", p.le.c[0]);
            }
        }
    }

    /// Bl falls to 45-85 % of its peak at the range's edges, Kms rises 1.4-4 times, Le rises
    /// towards the back plate: the shapes LSI reports show, within the valid range.
    #[test]
    fn drawn_curves_have_the_shapes_of_measured_drivers() {
        for seed in 0..300 {
            let d = draw(seed);
            let p = &d.plain;
            let [lo, hi] = p.x_range.unwrap();
            let (bmin, bmax) = p.bl.min_max_on(lo, hi);
            assert!(bmin / bmax > 0.4 && bmin / bmax < 0.9, "{}: Bl min/max {}", d.name(), bmin / bmax);
            let k0 = p.kms.eval(0.0);
            let k_edge = p.kms.eval(lo).max(p.kms.eval(hi)) / k0;
            assert!((2.0..4.6).contains(&k_edge), "{}: Kms stiffer edge/rest {k_edge}", d.name());
            assert!(
                p.le.eval(lo) > p.le.eval(0.0) && p.le.eval(0.0) > p.le.eval(hi),
                "{}: Le(x) must fall outwards",
                d.name()
            );
            // The restoring force rises over the range and 10 % beyond it.
            let f = |x: f64| p.kms.eval(x) * x;
            for k in 0..200 {
                let (a, b) = (
                    1.1 * lo + 1.1 * (hi - lo) * k as f64 / 200.0,
                    1.1 * lo + 1.1 * (hi - lo) * (k + 1) as f64 / 200.0,
                );
                assert!(f(b) > f(a), "{}: Kms(x) x falls at {a}", d.name());
            }
        }
    }

    #[test]
    fn effects_are_switched_one_by_one() {
        let d = draw(5);
        let all = d.with_effects(Effects::ALL);
        assert!(all.creep.is_some() && all.l3r3.is_some() && all.le_i.is_some() && all.rms_v.is_some());
        let none = d.with_effects(Effects::NONE);
        assert_eq!(none, d.plain);
        let lam = all.creep.unwrap().lambda;
        assert!((0.01..=0.15).contains(&lam));
        // Rms(v) starts at Rms; Le(i) at 1.
        assert_eq!(all.rms_v.unwrap().c[0], d.plain.rms);
        assert_eq!(all.le_i.unwrap().c[0], 1.0);
    }
}

//! Small-signal (linear) parameters from the electrical impedance (seed section 3.1).
//!
//! * [`check_channels`]: refuses recordings that would give a silently wrong answer
//!   (silent, clipped, DC-offset or swapped channels).
//! * [`h1_impedance`]: `Z(f) = U/I` by cross-spectral (H1) estimation: Hann windows, 50 %
//!   overlap, averaged; with the coherence. For display (`.zma`, CSV) and to reject bins.
//! * [`fit_linear`]: the LR-2 + motional model fitted by Levenberg-Marquardt as an *output
//!   error on the current* over the whole record's DFT: `min sum_k |I_k - U_k / Z(f_k)|^2`.
//!   No window: the leakage of a record that does not start and end at rest is a rational
//!   term with the system's own poles, fitted with the rest ([`Ends`]); bins without
//!   excitation carry no weight, so noise, sweeps, multitones and music all work. Parameters are
//!   fitted as logarithms (positive, well scaled), with the
//!   exact analytic Jacobian.
//! * [`scale_by_mms`], [`added_mass_mms`], [`scale_by_displacement`]: absolute scale.
//!
//! The motional branch is fitted as the parallel circuit `Res || Cmes || Lces` with
//! `Res = Bl^2/Rms`, `Cmes = Mms/Bl^2`, `Lces = Bl^2/Kms`; the voltage alone determines these
//! three, and one more number (Mms, an added mass, or the displacement) gives Bl.
//!
//! The parts, each in its file: `problem` (the output error on the current and its Jacobian),
//! `fit` (the model candidates grown and chosen over the bins, and the covariance), `band`
//! (measured impedance curves and the band where the lumped model holds), `chain` (what a
//! sound card adds, and the checks it calls for), `scale` (the absolute scale) and `warnings`
//! (the checks of a fit); here, the options, the fit's result and the record's workflow.

use crate::lm::{lambda_after_gain, lm_step, sandwich_covariance, sd_from_variance, LmState, Problem};
use coilscope_core::fft::{irfft, rfft};
use coilscope_core::params::Parameters;
use coilscope_core::poly::Poly;
use coilscope_core::result::{Fit, ModelTrial, ResultFile, Scale, Uncertainty};
use coilscope_core::simulate::rms;
use nalgebra::{DMatrix, DVector};
use realfft::num_complex::Complex64;
use realfft::RealFftPlanner;
use std::f64::consts::PI;

mod band;
mod chain;
mod fit;
mod problem;
mod scale;
#[cfg(test)]
mod tests;
mod warnings;

pub use band::*;
pub use chain::*;
use fit::*;
pub use problem::*;
pub use scale::*;
pub use warnings::*;

/// Names of the fitted electrical quantities, in `LinearFit::theta` order.
pub const NAMES: [&str; 7] = ["Re", "Le", "L2", "R2", "Res", "Cmes", "Lces"];

/// The linear fit's plateau: converged when the cost fell by less than `PLATEAU_REL` of
/// itself over the last `PLATEAU_ITERATIONS` iterations (a parameter move of about 1e-3 of
/// its sd; a fit that converges properly stops earlier, on LM's own test).
const PLATEAU_ITERATIONS: usize = 10;
/// Most LM iterations of one linear fit.
const MAX_ITERATIONS: usize = 200;
/// Most LM iterations of a candidate effect's scout (it starts from the fitted model with the
/// effect at a typical value). An effect the record has takes most of its gain within a few
/// iterations; one it lacks crept on (PTT4's 2 s small stage in `measure`: creep and LR-3
/// scouts ran to 200 iterations, 0.6 s of a 0.4 s fit). A scout that passes the gate is
/// polished on all bins to convergence.
const CANDIDATE_SCOUT_ITERATIONS: usize = 40;
const PLATEAU_REL: f64 = 1e-6;

/// Bins the starts of the impedance fit are compared on (the best is then fitted on all).
const SCOUT_BINS: usize = 4000;

/// How far above the fitted band the LR-2 corner may lie.
const CORNER_ABOVE_BAND: f64 = 4.0;

/// Lowest coherence for a bin to enter the fit.
pub const MIN_COHERENCE: f64 = 0.8;

/// Check the two channels for what would make a fit silently wrong. `origin` names the file.
/// `offsets_estimated`: the fit estimates the measurement chain, offsets included, so an
/// offset is not refused.
pub fn check_channels(u: &[f64], i: &[f64], fs: f64, offsets_estimated: bool, origin: &str) -> Result<(), String> {
    // Too short first: a few milliseconds of a signal have any mean at all.
    let seconds = u.len() as f64 / fs;
    if seconds < 0.5 {
        return Err(format!("{origin}: {seconds:.3} s is too short; record at least 1 s (better 3 s or more)"));
    }
    for (name, x, unit) in [("voltage (channel 1)", u, "V"), ("current (channel 2)", i, "A")] {
        let r = rms(x);
        if r < 1e-9 {
            return Err(format!(
                "{origin}: {name} is silent (RMS {r:.3e} {unit}); check the wiring and the input gain"
            ));
        }
        let mean = x.iter().sum::<f64>() / x.len() as f64;
        if !offsets_estimated && mean.abs() > 0.05 * r {
            return Err(format!(
                "{origin}: {name} has a DC offset of {mean:.4} {unit} ({:.0} % of its RMS); re-zero the interface, or let the fit take the offset with --chain auto (or --chain FILE from `coilscope calibrate`)",
                100.0 * mean.abs() / r
            ));
        }
        // Clipping shows as flat runs at the extremes: three or more consecutive samples
        // equal (to 1e-6 of the peak) at 99.9 % of the peak or more.
        let peak = x.iter().fold(0.0f64, |a, v| a.max(v.abs()));
        let flat = x
            .windows(3)
            .filter(|w| {
                w[1].abs() >= 0.999 * peak && (w[0] - w[1]).abs() <= 1e-6 * peak && (w[2] - w[1]).abs() <= 1e-6 * peak
            })
            .count();
        if flat > 8 {
            return Err(format!("{origin}: {name} is clipped: {flat} samples sit flat at its peak {peak:.4} {unit}; lower the level or the input gain"));
        }
    }
    Ok(())
}

/// An impedance estimate.
#[derive(Clone, Debug)]
pub struct ImpedanceEstimate {
    pub f: Vec<f64>,
    pub z: Vec<Complex64>,
    /// Magnitude-squared coherence between voltage and current.
    pub coherence: Vec<f64>,
    /// Voltage power per bin (V^2, Welch average).
    pub suu: Vec<f64>,
    /// The largest `suu`: the reference of the excitation threshold.
    pub suu_max: f64,
}

impl ImpedanceEstimate {
    /// Bins with excitation (within 60 dB of the strongest) and coherence >= `min_coh`.
    pub fn usable(&self, k: usize, min_coh: f64) -> bool {
        self.suu[k] > 1e-6 * self.suu_max && self.coherence[k] >= min_coh
    }

    /// Nearest bin to frequency `f` (any increasing grid: a record's or a file's); halfway
    /// between two, the upper one.
    pub fn bin(&self, f: f64) -> usize {
        let k = self.f.partition_point(|&g| g < f);
        if k == 0 {
            0
        } else if k == self.f.len() || f - self.f[k - 1] < self.f[k] - f {
            k - 1
        } else {
            k
        }
    }

    /// The coherent bins (coherence >= the fit's minimum) as frequencies and impedances: what
    /// `linear` writes as `.zma`.
    pub fn coherent(&self) -> (Vec<f64>, Vec<Complex64>) {
        (0..self.f.len())
            .filter(|&k| self.f[k] > 0.0 && self.usable(k, MIN_COHERENCE))
            .map(|k| (self.f[k], self.z[k]))
            .unzip()
    }

    /// A measured impedance curve (a file's) as an estimate: every point coherent and
    /// excited.
    pub fn from_curve(f: &[f64], z: &[Complex64]) -> ImpedanceEstimate {
        ImpedanceEstimate {
            f: f.to_vec(),
            z: z.to_vec(),
            coherence: vec![1.0; f.len()],
            suu: vec![1.0; f.len()],
            suu_max: 1.0,
        }
    }
}

/// Segment length of the H1 estimate: about 1 Hz resolution, at least 4 segments when the
/// record allows, a power of two.
pub fn segment_length(n: usize, fs: f64) -> usize {
    let target = (fs.min(n as f64 / 2.5)).max(256.0);
    let mut seg = 256usize;
    while (seg * 2) as f64 <= target {
        seg *= 2;
    }
    seg
}

/// `Z = U/I` by H1 estimation (`S_ui / S_ii` with `U` as output), Hann windows, 50 % overlap.
pub fn h1_impedance(u: &[f64], i: &[f64], fs: f64, seg: usize) -> ImpedanceEstimate {
    let mut planner = RealFftPlanner::<f64>::new();
    let fft = planner.plan_fft_forward(seg);
    let win: Vec<f64> = (0..seg).map(|k| 0.5 - 0.5 * (2.0 * PI * k as f64 / seg as f64).cos()).collect();
    let nb = seg / 2 + 1;
    let (mut suu, mut sii) = (vec![0.0; nb], vec![0.0; nb]);
    let mut siu = vec![Complex64::new(0.0, 0.0); nb];
    let (mut bu, mut bi) = (vec![0.0; seg], vec![0.0; seg]);
    let (mut fu, mut fi) = (fft.make_output_vec(), fft.make_output_vec());
    let mut start = 0;
    let mut count = 0;
    while start + seg <= u.len() {
        for k in 0..seg {
            bu[k] = u[start + k] * win[k];
            bi[k] = i[start + k] * win[k];
        }
        fft.process(&mut bu, &mut fu).expect("lengths are consistent");
        fft.process(&mut bi, &mut fi).expect("lengths are consistent");
        for k in 0..nb {
            suu[k] += fu[k].norm_sqr();
            sii[k] += fi[k].norm_sqr();
            siu[k] += fi[k].conj() * fu[k];
        }
        start += seg / 2;
        count += 1;
    }
    let norm = 1.0 / (count.max(1) as f64 * win.iter().map(|w| w * w).sum::<f64>());
    let f = (0..nb).map(|k| k as f64 * fs / seg as f64).collect();
    let z = (0..nb).map(|k| if sii[k] > 0.0 { siu[k] / sii[k] } else { Complex64::new(0.0, 0.0) }).collect();
    let coherence = (0..nb)
        .map(|k| if suu[k] > 0.0 && sii[k] > 0.0 { siu[k].norm_sqr() / (suu[k] * sii[k]) } else { 0.0 })
        .collect();
    let suu: Vec<f64> = suu.iter().map(|s| s * norm).collect();
    let suu_max = suu.iter().cloned().fold(0.0, f64::max);
    ImpedanceEstimate { f, z, coherence, suu, suu_max }
}

/// The fitted impedance model, `theta` = ln of [Re, Le, L2, R2, Res, Cmes, Lces].
pub fn model_impedance(p: &[f64; 7], f: f64) -> Complex64 {
    model_impedance_and_gradient(p, f).0
}

/// Impedance and its derivatives with respect to ln(p_k).
fn model_impedance_and_gradient(p: &[f64; 7], f: f64) -> (Complex64, [Complex64; 7]) {
    let (z, g, _) = impedance_ext(p, &Ext::default(), f);
    (z, g)
}

pub use coilscope_core::effects::Effects;

/// Unknowns the small-signal effects add to the seven of the LR-2 model: lambda for creep,
/// the corner and R3 for LR-3.
fn n_extra(e: Effects) -> usize {
    e.creep as usize + 2 * e.lr3 as usize
}

/// Which effects the linear fit uses.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum EffectsChoice {
    /// The data decide: an effect is kept when it removes a share of the error the model
    /// leaves above the noise, and that much more than noise could ([`effect_pays`]), and
    /// creep's lambda comes out positive.
    #[default]
    Auto,
    /// Exactly these effects.
    Fixed(Effects),
}

/// Share of the error power above the noise floor that an effect must remove to be kept
/// (`Auto`). Without noise it is the rule "lower the residual by 5 %" (`1 - 0.95^2`).
pub const EFFECT_MIN_SHARE: f64 = 0.0975;

/// How far above what noise alone gives an effect's gain must be, per unknown it adds: the
/// error power it removes in units of the noise power of one bin. Fitting k unknowns to pure
/// noise removes about k/2 of them; a coloured residual (distortion, leakage) more. 25 per
/// unknown keeps chance gains out and lets an effect that noise hides at a tenth of the
/// floor in.
pub const EFFECT_MIN_CHI2: f64 = 25.0;

/// The least share of the LR-2 model's Le that a model with more effects may keep. An LR-3
/// branch whose corner lies above the band acts as an inductance with a small loss, and can
/// take Le's place: the fit then slides Le toward zero along a flat direction (a drawn
/// microspeaker's small-signal stage ended at Le = 1.5e-58 H, and the live model started from
/// it was not finite at its first sample). No added branch takes a hundredth of the voice
/// coil's own inductance away: such a model is a trade of unknowns, not physics.
pub const LE_COLLAPSE: f64 = 0.01;

/// Whether an effect with `unknowns` new unknowns that lowers the relative residual from
/// `r_cur` to `r_new` pays, on a record whose noise floor is `floor` (relative residual of
/// the noise alone; 0 where it is not known, as on an averaged impedance curve) over `bins`
/// frequency bins. The share is of the excess over the floor: on a record of a quiet
/// small-signal stage most of the residual is sensor noise, which no effect can lower, and a
/// share of the whole residual missed the creep and the LR-3 branches that the excess shows
/// (a 9 mm woofer at 0.2 V: creep lowered the residual by 3 % of it, 6 % of its power, and
/// its absence left the cold Re 3 % low).
pub fn effect_pays(r_cur: f64, r_new: f64, floor: f64, bins: usize, unknowns: usize) -> bool {
    let gain = r_cur * r_cur - r_new * r_new;
    let excess = (r_cur * r_cur - floor * floor).max(0.0);
    let noise_per_bin = floor * floor / bins.max(1) as f64;
    gain >= EFFECT_MIN_SHARE * excess
        && (noise_per_bin == 0.0 || gain >= EFFECT_MIN_CHI2 * unknowns as f64 * noise_per_bin)
}

/// Values of the extra effects at one point: creep's lambda with the bank at its reference,
/// the resonance `w_s = 1 / sqrt(Lces Cmes)` (see [`CreepAt`]), and the LR-3 branch (L3, R3).
#[derive(Clone, Copy, Debug, Default)]
struct Ext {
    creep: Option<CreepAt>,
    lr3: Option<(f64, f64)>,
}

/// Creep's lambda and what depends only on the parameters, not on the frequency: `Re b(w_s)`
/// and its slope `d Re b / d ln w` at the reference (computed once per evaluation, not per bin).
#[derive(Clone, Copy, Debug)]
struct CreepAt {
    lambda: f64,
    b_ref: f64,
    slope_ref: f64,
}

impl Ext {
    /// The effects' values for the LR-2 quantities `p` (the creep reference moves with them).
    fn new(p: &[f64; 7], lambda: Option<f64>, lr3: Option<(f64, f64)>) -> Ext {
        let creep = lambda.map(|lambda| {
            let ws = 1.0 / (p[6] * p[5]).sqrt();
            CreepAt {
                lambda,
                b_ref: coilscope_core::creep::bank(ws).re,
                slope_ref: coilscope_core::creep::bank_re_slope(ws),
            }
        });
        Ext { creep, lr3 }
    }
}

/// [`impedance_ext`]'s value: the impedance, its derivatives with respect to ln(p_k) of the
/// seven LR-2 quantities, and of the extras.
type Impedance = (Complex64, [Complex64; 7], [Complex64; 3]);

/// Impedance with the extra effects; derivatives with respect to ln(p_k) of the seven LR-2
/// quantities, and of the extras: `[d/d lambda, d/d ln L3, d/d ln R3]` (zero when absent).
///
/// The motional admittance is `1/Res + jw Cmes + kappa / (jw Lces)` with the creep's
/// stiffness factor `kappa = 1 + lambda (b(w) - Re b(w_s))`, `w_s = 1 / sqrt(Lces Cmes)`
/// ([`coilscope_core::creep`]); `kappa` moves with Lces and Cmes through `w_s`.
#[inline]
fn impedance_ext(p: &[f64; 7], e: &Ext, f: f64) -> Impedance {
    let [re, le, l2, r2, res, cmes, lces] = *p;
    let jw = Complex64::new(0.0, 2.0 * PI * f);
    let zl2 = jw * l2;
    let d2 = zl2 + r2;
    // Reciprocals once, then products: a complex division costs two real ones (the linear
    // fit evaluates this at every bin of every iteration).
    let inv_d2 = d2.inv();
    let inv_d22 = inv_d2 * inv_d2;
    let z2 = zl2 * r2 * inv_d2;
    let zero = Complex64::new(0.0, 0.0);
    let (kappa, dkappa_half, bank_rel) = match e.creep {
        Some(c) => {
            let b = coilscope_core::creep::bank(2.0 * PI * f) - c.b_ref;
            // d kappa / d ln Lces = d kappa / d ln Cmes = lambda h'(w_s) / 2.
            (1.0 + c.lambda * b, c.lambda * c.slope_ref / 2.0, b)
        }
        None => (Complex64::new(1.0, 0.0), 0.0, zero),
    };
    let inv_jwl = (jw * lces).inv();
    let y = 1.0 / res + jw * cmes + kappa * inv_jwl;
    let zm = y.inv();
    let mut z = re + jw * le + z2 + zm;
    let zm2 = zm * zm;
    let g = [
        Complex64::new(re, 0.0),
        jw * le,
        jw * r2 * r2 * inv_d22 * l2,
        zl2 * zl2 * inv_d22 * r2,
        zm2 * (1.0 / res),
        -zm2 * (jw * cmes + dkappa_half * inv_jwl),
        zm2 * (kappa - dkappa_half) * inv_jwl,
    ];
    let mut gx = [zero; 3];
    if e.creep.is_some() {
        gx[0] = -zm2 * bank_rel * inv_jwl;
    }
    if let Some((l3, r3)) = e.lr3 {
        let zl3 = jw * l3;
        let inv_d3 = (zl3 + r3).inv();
        let inv_d32 = inv_d3 * inv_d3;
        z += zl3 * r3 * inv_d3;
        gx[1] = jw * r3 * r3 * inv_d32 * l3;
        gx[2] = zl3 * zl3 * inv_d32 * r3;
    }
    (z, g, gx)
}

/// The two para-inductance branches in their canonical order, LR-2 the one with the larger
/// inductance (as `identify` names them: the model is the same with the two exchanged, see
/// `large::branch_swap`): exchanges `p`'s L2 and R2 with `lr3`'s L3 and R3, with their
/// relative sds, when L3 is the larger. Returns whether it did.
fn lr3_named_first(p: &mut [f64; 7], sigma_rel: &mut [f64; 7], lr3: &mut Option<([f64; 2], [f64; 2])>) -> bool {
    match lr3 {
        Some((v, sd)) if v[0] > p[2] => {
            std::mem::swap(&mut p[2], &mut v[0]);
            std::mem::swap(&mut p[3], &mut v[1]);
            std::mem::swap(&mut sigma_rel[2], &mut sd[0]);
            std::mem::swap(&mut sigma_rel[3], &mut sd[1]);
            true
        }
        _ => false,
    }
}

/// The electrical fit of a recording.
#[derive(Clone, Debug)]
pub struct LinearFit {
    /// [Re, Le, L2, R2, Res, Cmes, Lces] in SI (ohm, H, H, ohm, ohm, F, H).
    pub p: [f64; 7],
    /// Relative standard deviations of `p`: from the final Jacobian and residual, and the
    /// model choice's share where a model with more effects fits the data as well
    /// ([`LinearFit::model_rel`]).
    pub sigma_rel: [f64; 7],
    /// `|I - U/Z| / |I|` over the fitted bins (the current residual in the fitted band).
    pub residual_rel: f64,
    pub band: [f64; 2],
    pub bins: usize,
    pub iterations: usize,
    /// The H1 estimate (for .zma / CSV and plots).
    pub h1: ImpedanceEstimate,
    /// Bounded quantities the fit ended on (e.g. the L2/R2 corner at the band's edge: the
    /// branch is not identifiable from this record). Empty for a fit inside its bounds.
    pub at_bound: Vec<&'static str>,
    /// Detected skew: (samples the current channel lags the voltage, share of the current
    /// error that shifting it explains). `None` when a shift explains little (< 50 % of the
    /// error) or is below 0.05 samples.
    pub current_delay: Option<(f64, f64)>,
    /// The fitted transient term of a record that does not start and end at rest.
    pub transient: Transient,
    /// The effects in the chosen model (`fit.model`).
    pub effects: Effects,
    /// Creep: (lambda, its sd), when fitted.
    pub creep: Option<(f64, f64)>,
    /// LR-3: ([L3 H, R3 ohm], their relative sds), when fitted.
    pub lr3: Option<([f64; 2], [f64; 2])>,
    /// Every model fitted, with its current residual (`fit.models_tried`).
    pub tried: Vec<(String, f64)>,
    /// How far Le moves (relative) to a model with more effects that fits the data as well
    /// as the chosen one (the chosen model does not beat it by more than noise could:
    /// [`effect_pays`]); 0 when there is none. The data cannot tell the two apart, so Le is
    /// no better known than this: it is in `sigma_rel[1]`, and `measure` carries it into the
    /// Le band (a microspeaker whose LR-3 hid under the small stage's noise: Le 28 % off in
    /// a model without it, with an LR-3 model fitting as well).
    pub le_model_rel: f64,
    /// How far each of `p` moves (relative) to a model with more effects that fits the data
    /// as well as the chosen one (`le_model_rel` is Le's): the model choice's share of
    /// `sigma_rel` (`uncertainty.model_rel` of a result). The data cannot make that choice,
    /// so the parameters are no better known than this. None for the branch L2/R2, which a
    /// second branch shares by definition.
    pub model_rel: [f64; 7],
    /// The measurement chain, when estimated ([`LinearOptions::chain`]).
    pub chain: Option<ChainEstimate>,
    /// The LR-2 model's fit on the same bins, from which every model with effects grows:
    /// [`fit_linear_record_from`] starts there instead of fitting it again (the effects
    /// search of `identify` fits creep and LR-3 on the record its start was fitted on).
    pub lr2: Lr2Fit,
    /// A curve without a measured phase, fitted to its magnitude alone (`h1` then holds
    /// its minimum phase, [`crate::min_phase`]).
    pub magnitude_only: bool,
}

/// The LR-2 model's fit inside [`fit_linear_record`] (see [`LinearFit::lr2`]): its LM state,
/// its residual on the scout bins and whether it was fitted on every bin. Valid only for a
/// record with the same samples, rate and [`LinearOptions`] other than `effects`.
#[derive(Clone, Debug)]
pub struct Lr2Fit {
    state: LmState,
    scout_rel: f64,
    polished: bool,
}

/// The transient term of a fit (see `CurrentError`): coefficients of `Q(s / omega0)`.
#[derive(Clone, Debug)]
pub struct Transient {
    pub c: Vec<f64>,
    pub omega0: f64,
}

impl LinearFit {
    fn ext(&self) -> Ext {
        Ext::new(&self.p, self.creep.map(|c| c.0), self.lr3.map(|(v, _)| (v[0], v[1])))
    }
    /// The fitted model's impedance (ohm) at `f` (Hz), with its effects.
    pub fn impedance(&self, f: f64) -> Complex64 {
        impedance_ext(&self.p, &self.ext(), f).0
    }
    pub fn fs(&self) -> f64 {
        1.0 / (2.0 * PI * (self.p[6] * self.p[5]).sqrt())
    }
    pub fn qms(&self) -> f64 {
        2.0 * PI * self.fs() * self.p[5] * self.p[4]
    }
    pub fn qes(&self) -> f64 {
        2.0 * PI * self.fs() * self.p[5] * self.p[0]
    }
    /// A curve point's relative error against the model at `f` (Hz): `|1 - Z / Z_model|`, or
    /// `|1 - |Z| / |Z_model||` for a curve fitted to its magnitude alone.
    pub fn point_error(&self, f: f64, z: Complex64) -> f64 {
        let m = self.impedance(f);
        if self.magnitude_only {
            (1.0 - z.norm() / m.norm()).abs()
        } else {
            (1.0 - z / m).norm()
        }
    }
}

/// Fit the linear model to a small-signal recording of voltage `u` and current `i` at rate
/// `fs`, its ends free ([`Ends::Fitted`]), the effects chosen by the data
/// ([`EffectsChoice::Auto`]). `observe` sees every LM state (progress, logs).
pub fn fit_linear(
    u: &[f64],
    i: &[f64],
    fs: f64,
    origin: &str,
    observe: impl FnMut(&LmState),
) -> Result<LinearFit, String> {
    fit_linear_record(u, i, fs, origin, &LinearOptions::default(), observe)
}

/// What the linear fit assumes and may add.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LinearOptions {
    pub ends: Ends,
    pub effects: EffectsChoice,
    /// Estimate the measurement chain (the current channel's delay, both channels'
    /// AC-coupling corners; the bins next to mains hum left out), keeping the quantities the
    /// data ask for ([`LinearFit::chain`]).
    pub chain: bool,
}

impl LinearOptions {
    /// The linear start of a large-signal fit: ends at rest, the LR-2 model alone (callers
    /// that want the effects chosen set `effects`).
    pub const LARGE_SIGNAL_START: LinearOptions =
        LinearOptions { ends: Ends::AssumedAtRest, effects: EffectsChoice::Fixed(Effects::NONE), chain: false };
}

/// What the impedance fit assumes of a record's ends (see `CurrentError`'s transient term).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Ends {
    /// The record need not start and end at rest: the transient term is fitted with the
    /// rest. For every small-signal record (`linear`, a measurement's small stage, a
    /// replay's first seconds). A record that fades out still ends with the cone and the
    /// coil's currents moving: the leakage this leaves in the whole-record DFT was the
    /// largest error of the fit (4 s of IEC noise at 0.025 mm, noise-free: 18WU Re +0.13 %,
    /// L2 -1.8 %, with a residual of 7e-4; with the term 2e-6 and 2e-5, residual 4.5e-5),
    /// and since it is smooth in frequency, not noise, the sds did not cover it.
    #[default]
    Fitted,
    /// The record is taken as starting and ending at rest (no transient term): for the
    /// linear start of a *large-signal* fit (`identify`, the post-inverse's L2/R2), where the
    /// term's freedom absorbs distortion and replaces the LR-2 branch (18WU: L2, R2 -> 0).
    AssumedAtRest,
}

/// The norm of a problem's current bins (its residual's scale).
fn prob_norm(p: &CurrentError) -> f64 {
    p.i.iter().map(|c| c.norm_sqr()).sum::<f64>().sqrt()
}
/// Every `step`-th element.
fn keep<T: Copy>(v: &[T], step: usize) -> Vec<T> {
    v.iter().step_by(step).copied().collect()
}
/// `p` on at most `most` bins, evenly picked (a scout for the starts).
fn thin(p: &CurrentError, most: usize) -> CurrentError {
    let step = p.f.len().div_ceil(most);
    let mut t = CurrentError {
        f: keep(&p.f, step),
        u: keep(&p.u, step),
        i: keep(&p.i, step),
        w: keep(&p.w, step),
        norm: 1.0,
        map: p.map.clone(),
        omega0: p.omega0,
        n_transient: p.n_transient,
        effects: p.effects,
        chain: p.chain,
        magnitude_only: p.magnitude_only,
    };
    t.norm = t.i.iter().map(|c| c.norm_sqr()).sum::<f64>().sqrt();
    t
}

/// The linear fit (of a record or a curve) takes no large-signal effect: they vanish at small
/// currents and velocities.
fn refuse_large_signal_effects(opts: &LinearOptions, origin: &str) -> Result<(), String> {
    match opts.effects {
        EffectsChoice::Fixed(e) if e.has_large_signal() => {
            Err(format!("{origin}: {} act only at large signal (they vanish at small currents and velocities); the linear fit takes none, creep, lr3 or auto, and `identify` fits them", Effects { creep: false, lr3: false, ..e }.in_words()))
        }
        _ => Ok(()),
    }
}

/// [`fit_linear`] with [`LinearOptions`]: what to assume of the record's [`Ends`], and
/// which effects to fit.
pub fn fit_linear_record(
    u: &[f64],
    i: &[f64],
    fs: f64,
    origin: &str,
    opts: &LinearOptions,
    observe: impl FnMut(&LmState),
) -> Result<LinearFit, String> {
    fit_linear_record_from(u, i, fs, origin, opts, None, observe)
}

/// [`fit_linear_record`] that takes the LR-2 model's fit from `lr2` ([`LinearFit::lr2`] of a
/// fit of the same record with the same options but for `effects`) instead of fitting it
/// again: the same result, bit for bit (`lr2_fit_reused_is_the_fit`), the observer seeing the
/// LM states of the models with effects only.
pub fn fit_linear_record_from(
    u: &[f64],
    i: &[f64],
    fs: f64,
    origin: &str,
    opts: &LinearOptions,
    lr2: Option<&Lr2Fit>,
    mut observe: impl FnMut(&LmState),
) -> Result<LinearFit, String> {
    linear_record_from(u, i, fs, origin, opts, lr2, &mut observe)
}

/// [`fit_linear_record_from`]'s work, compiled once (not for each caller's observer).
fn linear_record_from(
    u: &[f64],
    i: &[f64],
    fs: f64,
    origin: &str,
    opts: &LinearOptions,
    lr2: Option<&Lr2Fit>,
    observe: &mut dyn FnMut(&LmState),
) -> Result<LinearFit, String> {
    refuse_large_signal_effects(opts, origin)?;
    check_channels(u, i, fs, opts.chain, origin)?;
    let h1 = h1_impedance(u, i, fs, segment_length(u.len(), fs));
    // Band: from the lowest excited, coherent bin to 0.45 fs (at most 20 kHz).
    let f_hi = (0.45 * fs).min(20000.0);
    let f_lo = 2.0_f64.max(h1.f[1]);
    let in_band: Vec<usize> = (1..h1.f.len()).filter(|&k| h1.f[k] >= f_lo && h1.f[k] <= f_hi).collect();
    let excited: Vec<usize> = in_band.iter().cloned().filter(|&k| h1.usable(k, 0.0)).collect();
    if excited.is_empty() {
        return Err(format!("{origin}: no excitation between {f_lo:.0} and {f_hi:.0} Hz"));
    }
    let median = crate::checks::median(excited.iter().map(|&k| h1.coherence[k]).collect());
    if median < 0.5 {
        return Err(format!(
            "{origin}: too little coherence between voltage and current (median {median:.2} over {} excited bins, {f_lo:.0}..{f_hi:.0} Hz); the excitation is too weak against noise, or the channels are not of one measurement",
            excited.len()
        ));
    }
    let coherent: Vec<usize> = excited.iter().cloned().filter(|&k| h1.coherence[k] >= MIN_COHERENCE).collect();
    let band = [h1.f[*coherent.first().ok_or("no coherent bins")?], h1.f[*coherent.last().unwrap()]];
    // Swapped channels: U/I of a loudspeaker is ohms, its inverse is siemens-small.
    let zmed = crate::checks::median(coherent.iter().map(|&k| h1.z[k].norm()).collect());
    if zmed < 0.5 {
        return Err(format!("{origin}: |U/I| is {zmed:.3} ohm (median); channels 1 and 2 look swapped (voltage must be channel 1, current channel 2), or the current scale is wrong"));
    }
    // Inverted current: a passive impedance has a positive real part at every frequency.
    // Below 500 Hz, where a channel skew of a sample or two rotates the phase by a few
    // degrees only (a skew is named by the fit below, not here).
    let mut low: Vec<usize> = coherent.iter().copied().filter(|&k| h1.f[k] <= 500.0).collect();
    if low.is_empty() {
        low = coherent.clone();
    }
    let re_med = crate::checks::median(low.iter().map(|&k| h1.z[k].re).collect());
    if re_med < 0.0 {
        return Err(format!(
            "{origin}: one channel looks inverted, the current or the voltage: U/I has a negative real part ({re_med:.3} ohm median over {} coherent bins up to {:.0} Hz), which no passive driver has. U/I alone cannot tell which of the two: check the sense resistor's leads (channel 2, the current) and the voltage probe's (channel 1), and invert the one wired backwards (swap its leads, or negate its scale factor)",
            low.len(),
            h1.f[*low.last().expect("not empty")]
        ));
    }
    if let Some((z, phase)) = current_is_voltage(&h1, &coherent) {
        return Err(format!(
            "{origin}: U/I is flat, {z:.4} (median) with phase within {phase:.2} degrees over {:.0} .. {:.0} Hz: no loudspeaker has that. Channel 2 records the voltage (or the load is a resistor): wire channel 2 across the sense resistor (for a resistor or loopback record, use `coilscope calibrate`)",
            band[0], band[1]
        ));
    }
    let p0 = initial_guess(&h1, band[0], band[1]).map_err(|e| format!("{origin}: {e}"))?;

    // Whole-record DFT; keep bins inside the band whose H1 bin is excited and coherent.
    // Noise on both channels: the current error of bin k has variance
    // s_i^2 + s_u^2 / |Z_k|^2. With equal relative noise on both channels (s_u / s_i =
    // u_rms / i_rms = z_ref) the ML weight is 1 / sqrt(1 + (z_ref / |Z_k|)^2), from the H1 |Z|.
    let n = u.len();
    let (uf, i_f) = (rfft(u), rfft(i));
    let df = fs / n as f64;
    let z_ref = rms(u) / rms(i);
    let map = ParamMap::for_band(band);
    let mut prob = CurrentError {
        f: vec![],
        u: vec![],
        i: vec![],
        w: vec![],
        norm: 1.0,
        map: map.clone(),
        omega0: 2.0 * PI * (band[0] * band[1]).sqrt(),
        n_transient: if opts.ends == Ends::Fitted { N_TRANSIENT } else { 0 },
        effects: Effects::NONE,
        chain: None,
        magnitude_only: false,
    };
    for k in 1..uf.len() {
        let f = k as f64 * df;
        if f < band[0] || f > band[1] {
            continue;
        }
        let kh = h1.bin(f);
        if h1.usable(kh, MIN_COHERENCE) && !(opts.chain && near_hum(f)) {
            let w = 1.0 / (1.0 + (z_ref / h1.z[kh].norm()).powi(2)).sqrt();
            prob.f.push(f);
            prob.u.push(uf[k] * w);
            prob.i.push(i_f[k] * w);
            prob.w.push(w);
        }
    }
    prob.norm = prob.i.iter().map(|c| c.norm_sqr()).sum::<f64>().sqrt();
    if opts.chain {
        prob.chain = Some(ChainTerms { fs, delay: true, hp_u: true, hp_i: true });
    }
    fit_bins(prob, h1, band, p0, opts, Some(fs), lr2, origin, observe)
}

/// How the absolute scale (Bl) was found.
#[derive(Clone, Debug, PartialEq)]
pub enum ScaleMethod {
    /// The moving mass given, with its relative sd (0: taken as exact).
    Mms { sd_rel: f64 },
    /// `mms_sd_rel`: the relative sd of the Mms it gave, from the two resonances' sds and the
    /// added mass's own (`added_sd`, kg).
    AddedMass { added: f64, added_sd: f64, fs_with: f64, mms_sd_rel: f64 },
    /// The displacement channel: its delay against the current (samples, estimated and
    /// taken out) and the relative sd of the Mms it gave.
    Displacement { delay_samples: f64, mms_sd_rel: f64 },
}

/// The identification result (`"format": "coilscope.result/1"`) of a linear fit.
pub fn result(p: &Parameters, fit: &LinearFit, method: &ScaleMethod, x_range: [f64; 2], recording: &str) -> ResultFile {
    let ts = coilscope_core::small_signal::thiele_small(p);
    let sd = |k: usize| fit.sigma_rel[k] * fit.p[k];
    // Relative uncertainties of the derived quantities, first order, independent terms.
    let s = fit.sigma_rel;
    let fs_rel = fs_rel_sd(fit);
    // The scale's own relative sd (added mass: from the resonances and the mass; a given
    // Mms: as the user gave it).
    let m = match method {
        ScaleMethod::AddedMass { mms_sd_rel, .. } => *mms_sd_rel,
        ScaleMethod::Mms { sd_rel } => *sd_rel,
        ScaleMethod::Displacement { mms_sd_rel, .. } => *mms_sd_rel,
    };
    let scale = match method {
        ScaleMethod::Mms { sd_rel } => Scale {
            method: "mms".into(),
            mms: Some(p.mms),
            mass_sd: (*sd_rel > 0.0).then_some(sd_rel * p.mms),
            ..Default::default()
        },
        ScaleMethod::AddedMass { added, added_sd, fs_with, .. } => Scale {
            method: "added-mass".into(),
            added_mass: Some(*added),
            mass_sd: (*added_sd > 0.0).then_some(*added_sd),
            fs_with_mass: Some(*fs_with),
            ..Default::default()
        },
        ScaleMethod::Displacement { delay_samples, .. } => {
            Scale { method: "displacement".into(), sensor_delay_samples: Some(*delay_samples), ..Default::default() }
        }
    };
    let mut unc = Uncertainty::new("standard deviations: cluster-robust sandwich covariance over groups of 16 neighbouring bins (holds when the residual is not white: distortion, model error), and the model choice's share where a model with more effects fits the data as well (its spread, under model.KEY, already in KEY's sd); the scale's share (a given mass's sd, the added-mass method's resonances) under scale.KEY, already in KEY's sd; a mass given without an sd is taken as exact");
    for (key, v) in [
        ("Re", sd(0)),
        ("Le", sd(1)),
        ("L2", sd(2)),
        ("R2", sd(3)),
        ("Res", sd(4)),
        ("Cmes", sd(5)),
        ("Lces", sd(6)),
        ("fs", fs_rel * ts.fs),
        // Bl^2 = Mms / Cmes, Kms = Bl^2 / Lces, Rms = Bl^2 / Res (first order, independent).
        ("Bl", 0.5 * (s[5].powi(2) + m * m).sqrt() * p.bl.c[0]),
        ("Kms", (s[5].powi(2) + s[6].powi(2) + m * m).sqrt() * p.kms.c[0]),
        ("Rms", (s[5].powi(2) + s[4].powi(2) + m * m).sqrt() * p.rms),
    ] {
        unc.set(key, v);
    }
    if m > 0.0 {
        unc.set("Mms", m * p.mms);
        // The scale's share of the sds above, in their units: what the mass moves.
        for (key, v) in coilscope_core::mass::scale_share(p, m) {
            unc.set(&format!("scale.{key}"), v);
        }
    }
    // The model choice's share of the sds above (in their units), where it has one.
    let mr = fit.model_rel;
    for (key, v) in [
        ("Re", mr[0] * fit.p[0]),
        ("Le", mr[1] * fit.p[1]),
        ("Res", mr[4] * fit.p[4]),
        ("Cmes", mr[5] * fit.p[5]),
        ("Lces", mr[6] * fit.p[6]),
        ("Bl", 0.5 * mr[5] * p.bl.c[0]),
        ("Kms", mr[5].hypot(mr[6]) * p.kms.c[0]),
        ("Rms", mr[5].hypot(mr[4]) * p.rms),
    ] {
        if v > 0.0 {
            unc.set(&format!("model.{key}"), v);
        }
    }
    if let Some((_, sd)) = fit.creep {
        unc.set("creep.lambda", sd);
    }
    if let Some((v, sd)) = fit.lr3 {
        unc.set("L3", sd[0] * v[0]);
        unc.set("R3", sd[1] * v[1]);
    }
    let fit_record = Fit {
        residual_rel: fit.residual_rel,
        x_range,
        band_hz: Some(fit.band),
        bins: Some(fit.bins),
        iterations: Some(fit.iterations),
        scale: Some(scale),
        motional: Some(
            [("Res", fit.p[4]), ("Cmes", fit.p[5]), ("Lces", fit.p[6])]
                .iter()
                .map(|(k, v)| (k.to_string(), *v))
                .collect(),
        ),
        model: fit.effects.model_name(),
        models_tried: Some(
            fit.tried
                .iter()
                .map(|(m, r)| ModelTrial { model: m.clone(), residual_rel: Some(*r), ..Default::default() })
                .collect(),
        ),
        ..Default::default()
    };
    let mut r = ResultFile::new("linear", recording, p.clone(), fit_record, unc, None);
    r.chain = fit.chain.as_ref().map(|c| c.to_chain());
    r
}

/// The H1 impedance as CSV with the model and the coherence.
pub fn impedance_csv(h1: &ImpedanceEstimate, fit: &LinearFit) -> String {
    let mut out = String::from(
        "frequency_hz,magnitude_ohm,phase_deg,real_ohm,imag_ohm,coherence,model_magnitude_ohm,model_phase_deg\n",
    );
    for k in 0..h1.f.len() {
        if h1.f[k] > 0.0 && h1.usable(k, 0.0) {
            let m = fit.impedance(h1.f[k]);
            let z = h1.z[k];
            out.push_str(&format!(
                "{:.4},{:.6},{:.4},{:.6},{:.6},{:.5},{:.6},{:.4}\n",
                h1.f[k],
                z.norm(),
                z.arg().to_degrees(),
                z.re,
                z.im,
                h1.coherence[k],
                m.norm(),
                m.arg().to_degrees()
            ));
        }
    }
    out
}

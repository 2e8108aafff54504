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
    /// Relative standard deviations of `p` (from the final Jacobian and residual).
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

/// The chain quantities a linear fit estimated: `[delay_i samples, hp_u Hz, hp_i Hz]`, their
/// sds, and which the data asked for (the others held at 0).
#[derive(Clone, Debug, PartialEq)]
pub struct ChainEstimate {
    pub values: [f64; 3],
    pub sd: [f64; 3],
    pub on: [bool; 3],
    /// Sample rate of the record (Hz).
    pub fs: f64,
}

/// A chain quantity is kept when its estimate is this many sds from 0 (and a corner comes out
/// positive); otherwise it is held at 0 and the fit repeated.
pub const CHAIN_SIGNIFICANCE: f64 = 4.0;

/// Smallest delay (samples) and corners (Hz) a fit keeps: below these a chain quantity
/// changes nothing a driver's parameters depend on (a 0.005-sample delay turns the phase at
/// 10 kHz by 0.4 degrees), however precisely it is measured.
pub const CHAIN_MIN: [f64; 3] = [0.005, 0.05, 0.05];

/// Mains hum's lines: the bins within this many Hz of a harmonic of 50 or 60 Hz (up to
/// [`HUM_HARMONICS`]) are left out of a fit that estimates the chain.
pub const HUM_GUARD_HZ: f64 = 0.75;
pub const HUM_HARMONICS: usize = 6;

/// The mains lines (Hz): the harmonics of 50 Hz, then those of 60 Hz not among them (300 Hz
/// is a line of both), up to [`HUM_HARMONICS`].
pub fn mains_lines() -> Vec<f64> {
    let mut lines: Vec<f64> = vec![];
    for mains in [50.0, 60.0] {
        for k in 1..=HUM_HARMONICS {
            let f = mains * k as f64;
            if !lines.contains(&f) {
                lines.push(f);
            }
        }
    }
    lines
}

/// Mains hum between the channels: in the current the voltage does not explain, `E = I -
/// U / Z` (whole-record DFT, `Z` the H1 estimate), so that the excitation, which fills the
/// bins around a line in either channel alone, is taken out and the hum stands against the
/// noise. Hum on the current channel shows in `E` as itself, hum on the voltage channel as
/// `-hum / Z`. Returns the strongest line `(Hz, amplitude relative to the current's RMS,
/// dB above the median of E's bins 2 to 10 Hz away)`; the amplitude is 0 for a line less
/// than 10 dB above its neighbourhood. `None` for a record too short to resolve the lines.
pub fn mains_hum(u: &[f64], i: &[f64], fs: f64) -> Option<(f64, f64, f64)> {
    let n = u.len();
    let df = fs / n as f64;
    if df > 0.5 || n != i.len() {
        return None;
    }
    let h1 = h1_impedance(u, i, fs, segment_length(n, fs));
    let (us, is) = (rfft(u), rfft(i));
    let total: f64 = is.iter().skip(1).map(|c| c.norm_sqr()).sum();
    if total <= 0.0 {
        return None;
    }
    let e = |k: usize| -> f64 {
        let z = h1.z[h1.bin(k as f64 * df)];
        if z.norm() > 0.0 && z.is_finite() {
            (is[k] - us[k] / z).norm_sqr()
        } else {
            is[k].norm_sqr()
        }
    };
    let bin = |f: f64| (f / df).round() as usize;
    mains_lines()
        .into_iter()
        .filter(|&f| bin(f + 10.0) < is.len())
        .map(|f| {
            // The line's power over +-2 bins (a line between bins leaks into its neighbours).
            let (k0, k1) = (bin(f).saturating_sub(2), bin(f) + 2);
            let p_line: f64 = (k0..=k1).map(e).sum();
            let neigh: Vec<f64> =
                (bin(f - 10.0)..=bin(f + 10.0)).filter(|&k| (k as f64 * df - f).abs() >= 2.0).map(e).collect();
            let floor = crate::checks::median(neigh).max(1e-300) * 5.0;
            let db = 10.0 * (p_line / floor).log10();
            let rel = if db > 10.0 { ((p_line - floor) / total).sqrt() } else { 0.0 };
            (f, rel, db)
        })
        .max_by(|a, b| a.1.total_cmp(&b.1))
}

/// A channel's mean, relative to its RMS, above which [`chain_signs`] names an offset. A
/// driver's current and voltage have next to no mean over a record of a zero-mean drive (the
/// current at DC is the voltage's over Re, and the cone ends where it started): drawn
/// drivers with Le(i), Rms(v) and 40 K of heating left up to 0.2 % of the current's RMS. An
/// offset below this is left to the fit's own checks (`dc-offset-current`).
pub const OFFSET_SIGN: f64 = 5e-3;

/// What a measurement chain leaves in a record that shows without a fit: mains hum standing
/// out of the current's error ([`mains_hum`]), and a mean on either channel above
/// [`OFFSET_SIGN`] of its RMS. One sentence per sign (empty: none). The skew and AC coupling
/// need the driver's model: the fit looks for them (`IdentifyOptions::detect_chain`).
pub fn chain_signs(u: &[f64], i: &[f64], fs: f64) -> Vec<String> {
    let mut signs = vec![];
    if let Some((f, rel, db)) = mains_hum(u, i, fs) {
        if rel > 0.0 {
            signs.push(format!(
                "mains hum at {f:.0} Hz ({:.2} % of the current's RMS, {db:.0} dB above the noise next to it)",
                100.0 * rel
            ));
        }
    }
    for (name, x, unit) in [("voltage", u, "V"), ("current", i, "A")] {
        let r = rms(x);
        let mean = x.iter().sum::<f64>() / x.len().max(1) as f64;
        if r > 0.0 && mean.abs() > OFFSET_SIGN * r {
            signs.push(format!(
                "an offset of {mean:.3e} {unit} on the {name} channel ({:.2} % of its RMS)",
                100.0 * mean.abs() / r
            ));
        }
    }
    signs
}

/// The voltage record of a `driver+shunt` wiring made into that of a `terminals` wiring: the
/// shunt's drop as the voltage channel recorded it taken out
/// ([`coilscope_core::chain::Chain::remove_shunt_drop`]), through `chain` when it is known
/// (ideal or calibrated), or through the chain estimated here (`None`): a linear fit of the
/// record as it is, with the chain estimated, in which the shunt is simply part of Re (the
/// delay, the corners and the gain do not depend on it). A `terminals` wiring is returned as
/// it is.
pub fn remove_shunt_drop(
    u_rec: &[f64],
    i_rec: &[f64],
    fs: f64,
    wiring: coilscope_core::chain::SenseWiring,
    chain: Option<&coilscope_core::chain::Chain>,
    origin: &str,
) -> Result<Vec<f64>, String> {
    let rs = wiring.series_ohm();
    if rs == 0.0 {
        return Ok(u_rec.to_vec());
    }
    let estimated;
    let c = match chain {
        Some(c) => c,
        None => {
            let opts = LinearOptions { chain: true, ..Default::default() };
            let fit = fit_linear_record(u_rec, i_rec, fs, origin, &opts, |_| {})?;
            estimated = fit.chain.as_ref().map(|c| c.to_chain()).unwrap_or_default();
            &estimated
        }
    };
    Ok(c.remove_shunt_drop(u_rec, i_rec, rs, fs))
}

/// Hum above which a channel is refused even when the chain is estimated (its relative
/// amplitude: -20 dB of the channel); without the chain, hum above [`HUM_REFUSED_IDEAL`]
/// (-40 dB: 3 % on a 4 s SB17 record left a residual 13x the noise floor) is refused with
/// the advice to estimate it.
pub const HUM_REFUSED: f64 = 0.1;
pub const HUM_REFUSED_IDEAL: f64 = 0.01;

/// Refuse a record whose hum would dominate the fit: see [`HUM_REFUSED`].
pub fn check_hum(u: &[f64], i: &[f64], fs: f64, chain_estimated: bool, origin: &str) -> Result<(), String> {
    if let Some((f, rel, db)) = mains_hum(u, i, fs) {
        let what = format!("{origin}: mains hum at {f:.0} Hz between the channels (on the current, or on the voltage through the driver) is {:.1} % of the current's RMS, {db:.0} dB above the noise next to it", 100.0 * rel);
        if rel > HUM_REFUSED {
            return Err(format!("{what}: far above the noise floor, it would dominate any fit. Fix the ground loop (one ground point, a balanced input, the shunt's ground at the card)"));
        }
        if !chain_estimated && rel > HUM_REFUSED_IDEAL {
            return Err(format!("{what}: fix the ground loop, or let the fit take the hum with --chain auto"));
        }
    }
    Ok(())
}

/// The current channel carries the voltage (or the load is a resistor): `U/I` flat in
/// magnitude (within 2 % between its 5th and 95th percentiles) and in phase (within 1
/// degree) over the coherent band, which no loudspeaker's impedance is.
fn current_is_voltage(h1: &ImpedanceEstimate, bins: &[usize]) -> Option<(f64, f64)> {
    let mut mags: Vec<f64> = bins.iter().map(|&k| h1.z[k].norm()).collect();
    mags.sort_by(f64::total_cmp);
    let (lo, hi) = (mags[mags.len() / 20], mags[mags.len() * 19 / 20]);
    let phase = bins.iter().map(|&k| h1.z[k].arg().abs()).fold(0.0, f64::max).to_degrees();
    (hi / lo < 1.02 && phase < 1.0).then(|| (crate::checks::median(mags), phase))
}

/// True when `f` (Hz) is within [`HUM_GUARD_HZ`] of a mains line.
pub fn near_hum(f: f64) -> bool {
    mains_lines().iter().any(|m| (f - m).abs() <= HUM_GUARD_HZ)
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

struct CurrentError {
    f: Vec<f64>,
    /// Weighted spectra (see `fit_linear`) and the weights.
    u: Vec<Complex64>,
    i: Vec<Complex64>,
    w: Vec<f64>,
    norm: f64,
    map: ParamMap,
    /// Reference angular frequency of the transient polynomial (rad/s).
    omega0: f64,
    /// Number of transient coefficients in theta (0 or [`N_TRANSIENT`]).
    n_transient: usize,
    /// The extra effects fitted; their unknowns follow the seven LR-2 ones in theta:
    /// lambda (creep), then the LR-3 corner (bounded as the LR-2 one) and ln R3.
    effects: Effects,
    /// The measurement chain's unknowns ([`ChainTerms`]), from [`CurrentError::chain_index`] in
    /// theta: the current channel's delay (samples), the voltage and current channels'
    /// AC-coupling corners (Hz), those that are on. `None`: an ideal chain.
    chain: Option<ChainTerms>,
    /// An impedance curve without a measured phase: each point's `u` takes the model's
    /// phase at theta, so that its error `1 - |Z_measured| / |Z_model|` is real and the fit
    /// is of the magnitude alone ([`fit_impedance_magnitude`]).
    magnitude_only: bool,
}

/// Which chain quantities a fit estimates (see [`coilscope_core::chain`]). The recorded
/// `U/I` is `Z H_u(f) / (H_i(f) e^{-j 2 pi f tau / fs})`, so the predicted recorded current
/// is `U_rec e^{-j 2 pi f tau / fs} H_i(f) / (H_u(f) Z)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ChainTerms {
    pub fs: f64,
    /// The current channel's delay (samples).
    pub delay: bool,
    /// The voltage channel's AC-coupling corner (Hz).
    pub hp_u: bool,
    /// The current channel's AC-coupling corner (Hz).
    pub hp_i: bool,
}

impl ChainTerms {
    /// The three, in theta's order.
    pub const NAMES: [&'static str; 3] = ["delay_i", "hp_u", "hp_i"];
    /// `[delay, hp_u, hp_i]` on or off.
    pub fn on(&self) -> [bool; 3] {
        [self.delay, self.hp_u, self.hp_i]
    }
    /// How many are on (their entries in theta).
    pub fn count(&self) -> usize {
        self.on().iter().filter(|b| **b).count()
    }
    /// `[delay samples, hp_u Hz, hp_i Hz]` from the chain's entries of theta (0 for those off).
    pub fn values(&self, th: &[f64]) -> [f64; 3] {
        let mut v = [0.0; 3];
        let mut k = 0;
        for (n, on) in self.on().into_iter().enumerate() {
            if on {
                v[n] = th[k];
                k += 1;
            }
        }
        v
    }
    /// The chain's factor at the chain's entries `th` of theta, ready for
    /// [`ChainFactor::at`] bin by bin: what depends on theta alone (the corners' filter
    /// coefficients, a tangent each) is computed here once, not in every bin.
    fn factor_at(&self, th: &[f64]) -> ChainFactor {
        let [tau, fu, fi] = self.values(th);
        let hp = |fc: f64| coilscope_core::chain::hp_coefficients(fc, self.fs);
        let h = CHAIN_CORNER_STEP;
        ChainFactor { terms: *self, tau, u: [hp(fu), hp(fu + h), hp(fu - h)], i: [hp(fi), hp(fi + h), hp(fi - h)] }
    }
}

/// Step (Hz) of the central differences that give the chain factor's derivatives in the
/// corners ([`ChainFactor::at`]).
const CHAIN_CORNER_STEP: f64 = 1e-4;

/// [`ChainTerms`] at one theta ([`ChainTerms::factor_at`]): the delay, and the AC-coupling
/// filters' coefficients (`coilscope_core::chain::hp_coefficients`) at each corner and at
/// the corner plus and minus [`CHAIN_CORNER_STEP`].
struct ChainFactor {
    terms: ChainTerms,
    tau: f64,
    /// `(g, a)` of the voltage channel's corner, and of it plus and minus the step.
    u: [(f64, f64); 3],
    /// The same for the current channel's corner.
    i: [(f64, f64); 3],
}

impl ChainFactor {
    /// The factor on the predicted current at `f` (Hz), `e^{-j 2 pi f tau / fs} H_i(f) /
    /// H_u(f)` with `H` as [`coilscope_core::chain::hp_response`], and with `deriv` its
    /// derivatives w.r.t. the chain's entries of theta (those on, in order; the corners' by
    /// central differences). The same values to the last bit as `hp_response` per corner
    /// (`the_chain_factor_is_hp_response_s`), with two sines and cosines per bin instead of
    /// fifteen and ten tangents: those were 75 % of a linear fit with the chain (the
    /// `--chain auto` start of `identify` on SB17's `-real-chain` record: 8.4 s).
    fn at(&self, f: f64, deriv: bool) -> (Complex64, Vec<Complex64>) {
        let fs = self.terms.fs;
        let zi = Complex64::from_polar(1.0, -2.0 * PI * f / fs);
        let hp = |ga: (f64, f64)| coilscope_core::chain::hp_response_at(ga, zi);
        let delay = Complex64::from_polar(1.0, -2.0 * PI * f * self.tau / fs);
        let c = |hu: Complex64, hi: Complex64| delay * hi / hu;
        let (hu, hi) = (hp(self.u[0]), hp(self.i[0]));
        let c0 = c(hu, hi);
        let mut d = vec![];
        if !deriv {
            return (c0, d);
        }
        let h = CHAIN_CORNER_STEP;
        if self.terms.delay {
            d.push(c0 * Complex64::new(0.0, -2.0 * PI * f / fs));
        }
        if self.terms.hp_u {
            d.push((c(hp(self.u[1]), hi) - c(hp(self.u[2]), hi)) / (2.0 * h));
        }
        if self.terms.hp_i {
            d.push((c(hu, hp(self.i[1])) - c(hu, hp(self.i[2]))) / (2.0 * h));
        }
        (c0, d)
    }
}

impl ChainTerms {
    /// The sds of `[delay, hp_u, hp_i]` from a covariance whose chain entries start at `ci`;
    /// NaN for those off and without a covariance.
    pub fn sds(&self, cov: Option<&DMatrix<f64>>, ci: usize) -> [f64; 3] {
        let mut sd = [f64::NAN; 3];
        let mut k = ci;
        for (n, on) in self.on().into_iter().enumerate() {
            if on {
                sd[n] = cov.map_or(f64::NAN, |c| sd_from_variance(c[(k, k)]));
                k += 1;
            }
        }
        sd
    }
}

/// `theta[t0..t0 + n_transient]` (`t0` = 7 + the extra effects' unknowns): the coefficients
/// of the transient term
/// ([`Ends::Fitted`]; none with [`Ends::AssumedAtRest`]: on a large-signal record its
/// freedom would absorb distortion).
///
/// The whole-record DFT relation `I = U / Z` is exact only for a record that starts and ends
/// at rest. A record cut from a running signal (a replay), or one whose excitation fades
/// out while the cone still moves, adds the difference of its initial and final states, whose DFT
/// is a rational function with
/// the system's own poles: `T(s) = Q(s) / (Z(s) D_Z(s))`, `Q` a polynomial of degree 3 (the
/// system has four states: i, i2, x, v), `D_Z` the denominator of `Z` (frequency-domain
/// identification, Pintelon and Schoukens). `Q` is fitted with the rest, linear in its
/// coefficients; on a record from rest to rest it comes out at the noise.
const N_TRANSIENT: usize = 4;

/// How the solver's unknowns `theta` map to the impedance model's parameters.
///
/// The natural coordinates are `q = [ln Re, ln Le, ln tau2, ln R2, ln Res, ln Cmes, ln Lces]`
/// with `tau2 = L2/R2`: logarithms keep every element positive. `tau2` is bounded so that the
/// corner `1/(2 pi tau2)` of the LR-2 branch lies inside the fitted band: outside it the branch
/// is a plain resistor (corner below the band: it trades exactly against Re, the fit slides to
/// Re = 0) or a plain inductor (above: it trades against Le). A bounded coordinate is
/// `q = lo + (hi - lo) s(theta)` with the logistic `s`; a fit that ends on a bound says so
/// ([`LinearFit::at_bound`]).
#[derive(Clone, Debug)]
struct ParamMap {
    /// Bounds of `q` (natural log units); infinite = unbounded.
    lo: [f64; 7],
    hi: [f64; 7],
}

fn logistic(t: f64) -> f64 {
    1.0 / (1.0 + (-t).exp())
}

/// The inverse of `q = lo + (hi - lo) logistic(theta)`, with `q` pulled at least `margin`
/// (a share of the range) inside its bounds.
fn bounded_theta(q: f64, lo: f64, hi: f64, margin: f64) -> f64 {
    let s = ((q - lo) / (hi - lo)).clamp(margin, 1.0 - margin);
    (s / (1.0 - s)).ln()
}

impl ParamMap {
    /// The map of a fit over `band` (Hz): the LR-2 corner stays inside it, its upper bound a
    /// few times the band's top (a corner just above it still shapes the impedance inside
    /// the band; the microspeaker sets have theirs at 21 kHz).
    fn for_band(band: [f64; 2]) -> ParamMap {
        let (mut lo, mut hi) = ([f64::NEG_INFINITY; 7], [f64::INFINITY; 7]);
        lo[2] = (1.0 / (2.0 * PI * CORNER_ABOVE_BAND * band[1])).ln();
        hi[2] = (1.0 / (2.0 * PI * band[0])).ln();
        ParamMap { lo, hi }
    }

    fn q(&self, theta: &[f64]) -> [f64; 7] {
        std::array::from_fn(|k| {
            if self.lo[k].is_finite() {
                self.lo[k] + (self.hi[k] - self.lo[k]) * logistic(theta[k])
            } else {
                theta[k]
            }
        })
    }
    /// `dq_k / dtheta_k`.
    fn dq(&self, theta: &[f64]) -> [f64; 7] {
        std::array::from_fn(|k| {
            if self.lo[k].is_finite() {
                let s = logistic(theta[k]);
                (self.hi[k] - self.lo[k]) * s * (1.0 - s)
            } else {
                1.0
            }
        })
    }
    /// `theta` of natural coordinates `q` (bounded ones pulled 1 % inside their bounds).
    fn theta(&self, q: &[f64; 7]) -> Vec<f64> {
        (0..7)
            .map(|k| if self.lo[k].is_finite() { bounded_theta(q[k], self.lo[k], self.hi[k], 0.01) } else { q[k] })
            .collect()
    }
    /// Impedance-model parameters `[Re, Le, L2, R2, Res, Cmes, Lces]` (SI).
    fn params(&self, theta: &[f64]) -> [f64; 7] {
        let q = self.q(theta);
        let mut p: [f64; 7] = std::array::from_fn(|k| q[k].exp());
        p[2] = (q[2] + q[3]).exp();
        p
    }
    /// Natural coordinates of model parameters.
    fn q_of(p: &[f64; 7]) -> [f64; 7] {
        let mut q: [f64; 7] = std::array::from_fn(|k| p[k].ln());
        q[2] = (p[2] / p[3]).ln();
        q
    }
    /// Names of the bounded coordinates whose logistic sits within 1e-3 of a bound.
    fn at_bound(&self, theta: &[f64]) -> Vec<&'static str> {
        (0..7)
            .filter(|&k| self.lo[k].is_finite() && !(1e-3..=1.0 - 1e-3).contains(&logistic(theta[k])))
            .map(|k| if k == 2 { "L2/R2 corner" } else { NAMES[k] })
            .collect()
    }
}

impl CurrentError {
    /// The measured `u` of bin `k` against a model impedance `z` there: as measured, or, for
    /// a curve without phase, its magnitude at the model's phase.
    fn u_at(&self, k: usize, z: Complex64) -> Complex64 {
        if self.magnitude_only {
            Complex64::from_polar(self.u[k].norm(), z.arg())
        } else {
            self.u[k]
        }
    }

    /// Where the chain's unknowns start in theta.
    fn chain_index(&self) -> usize {
        self.t0() + self.n_transient
    }

    /// Where the transient coefficients start in theta.
    fn t0(&self) -> usize {
        7 + n_extra(self.effects)
    }

    /// Where creep's lambda sits in theta.
    fn idx_lambda(&self) -> Option<usize> {
        self.effects.creep.then_some(7)
    }

    /// Where the LR-3 corner (then ln R3) sits in theta.
    fn idx_lr3(&self) -> Option<usize> {
        self.effects.lr3.then_some(7 + self.effects.creep as usize)
    }

    /// `ln tau3` of its bounded coordinate, and its slope `d ln tau3 / d theta`.
    fn tau3(&self, t: f64) -> (f64, f64) {
        let (lo, hi) = (self.map.lo[2], self.map.hi[2]);
        let s = logistic(t);
        (lo + (hi - lo) * s, (hi - lo) * s * (1.0 - s))
    }

    /// The extra effects' values at theta.
    fn ext(&self, theta: &[f64]) -> Ext {
        Ext::new(
            &self.map.params(theta),
            self.idx_lambda().map(|k| theta[k]),
            self.idx_lr3().map(|k| {
                let r3 = theta[k + 1].exp();
                (self.tau3(theta[k]).0.exp() * r3, r3)
            }),
        )
    }

    /// The transient coefficients in theta.
    fn transient<'t>(&self, theta: &'t [f64]) -> &'t [f64] {
        &theta[self.t0()..self.t0() + self.n_transient]
    }

    /// [`transient_term`] of bin `k`, or nothing (zeros) without a transient term
    /// ([`Ends::AssumedAtRest`], the large-signal start): there the term is zero and its
    /// derivatives enter times it, so a fit's residuals and Jacobian are the same to the
    /// last bit (the term took a fifth of a linear fit with the chain).
    fn transient_at(
        &self,
        p: &[f64; 7],
        imp: &Impedance,
        theta: &[f64],
        k: usize,
    ) -> (Complex64, [Complex64; 7], [Complex64; 3], [Complex64; N_TRANSIENT]) {
        if self.n_transient == 0 {
            let z = Complex64::new(0.0, 0.0);
            return (z, [z; 7], [z; 3], [z; N_TRANSIENT]);
        }
        transient_term(p, imp, self.transient(theta), self.omega0, self.f[k])
    }

    /// The chain's factor at theta ([`ChainTerms::factor_at`]), `None` for an ideal chain.
    fn chain_factor(&self, theta: &[f64]) -> Option<ChainFactor> {
        self.chain.map(|c| c.factor_at(&theta[self.chain_index()..]))
    }

    /// The chain's factor on the predicted current of bin `k` (1 for an ideal chain), with its
    /// derivatives when `deriv`.
    fn shift_d(&self, chain: Option<&ChainFactor>, k: usize, deriv: bool) -> (Complex64, Vec<Complex64>) {
        match chain {
            Some(c) => c.at(self.f[k], deriv),
            None => (Complex64::new(1.0, 0.0), vec![]),
        }
    }

    /// `|I - U/Z - T| / |I|` over the fitted bins, unweighted (the spec's `fit.residual_rel`),
    /// with the fitted chain's delay and coupling between `U/Z` and the recorded current.
    fn residual_rel(&self, theta: &[f64]) -> f64 {
        self.residual_and_floor(theta).0
    }

    /// [`CurrentError::residual_rel`] and the noise floor in the same terms: the current
    /// error's power per bin is the noise's plus the model's misfit, which a wrong model puts
    /// in the bins of a band (the resonance, the branches' corners) and noise in every bin.
    /// The median bin then holds noise: a bin's noise power is a complex Gaussian's, whose
    /// median is ln 2 times its mean. A misfit over most of the bins raises the floor, so
    /// that fewer effects pay: the safe side.
    fn residual_and_floor(&self, theta: &[f64]) -> (f64, f64) {
        let p = self.map.params(theta);
        let ext = self.ext(theta);
        let chain = self.chain_factor(theta);
        let mut t = 0.0;
        let mut e: Vec<f64> = Vec::with_capacity(self.f.len());
        for k in 0..self.f.len() {
            let imp = impedance_ext(&p, &ext, self.f[k]);
            let (z, tr) = (imp.0, transient_term(&p, &imp, self.transient(theta), self.omega0, self.f[k]).0);
            // The recorded current is the driver's through the chain (when one is fitted).
            let shift = self.shift_d(chain.as_ref(), k, false).0;
            e.push(((self.i[k] - self.u_at(k, z) * shift / z) / self.w[k] - tr).norm_sqr());
            t += (self.i[k] / self.w[k]).norm_sqr();
        }
        let total: f64 = e.iter().sum();
        let m = e.len();
        let floor = if m == 0 { 0.0 } else { crate::checks::median(e) / std::f64::consts::LN_2 * m as f64 };
        ((total / t).sqrt(), (floor / t).sqrt())
    }
}

/// The transient term `T = Q(s) / P(s)` at `f` (current, in the DFT's units), with
/// `Q(s) = sum_j c_j (s / omega0)^j` and `P = Z D_Z / (R2 Res)`, `D_Z = (s L2 + R2)(Res + s
/// Lces + s^2 Lces Cmes Res)` (ohm), `Z` with the extra effects (their own poles are left out
/// of `D_Z`: the term only has to absorb a record's ends). Returns `T`, `d ln P / d ln p_m`
/// (m over the seven model parameters), the same for the extras (as [`impedance_ext`]), and
/// the basis `(s / omega0)^j / P` (= `dT / dc_j`).
#[allow(clippy::type_complexity)]
#[inline]
fn transient_term(
    p: &[f64; 7],
    imp: &Impedance,
    c: &[f64],
    omega0: f64,
    f: f64,
) -> (Complex64, [Complex64; 7], [Complex64; 3], [Complex64; N_TRANSIENT]) {
    let [_, _, l2, r2, res, cmes, lces] = *p;
    let s = Complex64::new(0.0, 2.0 * PI * f);
    let (z, g, gx) = *imp;
    let a = s * l2 + r2;
    let lcr = s * s * lces * cmes * res;
    let b = res + s * lces + lcr;
    // Reciprocals once (see `impedance_ext`).
    let (inv_z, inv_a, inv_b) = (z.inv(), a.inv(), b.inv());
    let inv_pp = inv_z * inv_a * inv_b * (r2 * res);
    let mut dlnp: [Complex64; 7] = std::array::from_fn(|m| g[m] * inv_z);
    dlnp[2] += s * l2 * inv_a;
    dlnp[3] += r2 * inv_a - 1.0;
    dlnp[4] += (res + lcr) * inv_b - 1.0;
    dlnp[5] += lcr * inv_b;
    dlnp[6] += (s * lces + lcr) * inv_b;
    let x = s / omega0;
    let mut basis = [Complex64::new(0.0, 0.0); N_TRANSIENT];
    let mut pow = Complex64::new(1.0, 0.0);
    let mut t = Complex64::new(0.0, 0.0);
    for (j, bj) in basis.iter_mut().enumerate() {
        *bj = pow * inv_pp;
        t += c.get(j).copied().unwrap_or(0.0) * *bj;
        pow *= x;
    }
    (t, dlnp, gx.map(|d| d * inv_z), basis)
}

impl Problem for CurrentError {
    fn residual_jacobian(&self, theta: &[f64]) -> (DVector<f64>, DMatrix<f64>) {
        let p = self.map.params(theta);
        let dq = self.map.dq(theta);
        let ext = self.ext(theta);
        let (il, i3) = (self.idx_lambda(), self.idx_lr3());
        let dq3 = i3.map(|k| self.tau3(theta[k]).1).unwrap_or(0.0);
        let t0 = self.t0();
        let m = self.f.len();
        let np = theta.len();
        let chain = self.chain_factor(theta);
        let mut r = DVector::zeros(2 * m);
        let mut j = DMatrix::zeros(2 * m, np);
        for k in 0..m {
            // The impedance once per bin: the transient term takes it too.
            let imp = impedance_ext(&p, &ext, self.f[k]);
            let (tr, mut dlnp, mut dlnpx, basis) = self.transient_at(&p, &imp, theta, k);
            let (z, mut g, mut gx) = imp;
            // From d/d ln p to d/dq: L2 = tau2 R2, so ln R2 moves L2 too (L3 likewise).
            g[3] += g[2];
            dlnp[3] += dlnp[2];
            gx[2] += gx[1];
            dlnpx[2] += dlnpx[1];
            let (shift, dshift) = self.shift_d(chain.as_ref(), k, true);
            let wk = self.w[k] / self.norm;
            let uk = self.u_at(k, z);
            let e = (self.i[k] - uk * shift / z) / self.norm - wk * tr;
            r[2 * k] = e.re;
            r[2 * k + 1] = e.im;
            let a = uk * shift / (z * z) / self.norm;
            for c in 0..7 {
                // e = ... - w T and dT/dq = -T d ln P / dq.
                let d = (a * g[c] + wk * tr * dlnp[c]) * dq[c];
                j[(2 * k, c)] = d.re;
                j[(2 * k + 1, c)] = d.im;
            }
            if let Some(c) = il {
                let d = a * gx[0] + wk * tr * dlnpx[0];
                j[(2 * k, c)] = d.re;
                j[(2 * k + 1, c)] = d.im;
            }
            if let Some(c) = i3 {
                let d = (a * gx[1] + wk * tr * dlnpx[1]) * dq3;
                j[(2 * k, c)] = d.re;
                j[(2 * k + 1, c)] = d.im;
                let d = a * gx[2] + wk * tr * dlnpx[2];
                j[(2 * k, c + 1)] = d.re;
                j[(2 * k + 1, c + 1)] = d.im;
            }
            for (n, b) in basis.iter().enumerate().take(self.n_transient) {
                let d = -wk * b;
                j[(2 * k, t0 + n)] = d.re;
                j[(2 * k + 1, t0 + n)] = d.im;
            }
            for (n, ds) in dshift.iter().enumerate() {
                let d = -uk * ds / z / self.norm;
                j[(2 * k, self.chain_index() + n)] = d.re;
                j[(2 * k + 1, self.chain_index() + n)] = d.im;
            }
            if self.magnitude_only {
                // The error is `1 - |U| / |Z|`, real: its derivative is the real part of the
                // complex one at the model's phase; the imaginary row carries nothing.
                r[2 * k + 1] = 0.0;
                j.row_mut(2 * k + 1).fill(0.0);
            }
        }
        (r, j)
    }
    fn residual(&self, theta: &[f64]) -> DVector<f64> {
        let p = self.map.params(theta);
        let ext = self.ext(theta);
        let chain = self.chain_factor(theta);
        DVector::from_iterator(
            2 * self.f.len(),
            (0..self.f.len()).flat_map(|k| {
                let imp = impedance_ext(&p, &ext, self.f[k]);
                let tr = self.transient_at(&p, &imp, theta, k).0;
                let e = (self.i[k] - self.u_at(k, imp.0) * self.shift_d(chain.as_ref(), k, false).0 / imp.0)
                    / self.norm
                    - self.w[k] / self.norm * tr;
                [e.re, if self.magnitude_only { 0.0 } else { e.im }]
            }),
        )
    }
}

/// Start values from the H1 estimate (motional peak, half-power bandwidth, high-frequency
/// inductance).
fn initial_guess(h1: &ImpedanceEstimate, lo: f64, hi: f64) -> Result<[f64; 7], String> {
    let ok: Vec<usize> =
        (0..h1.f.len()).filter(|&k| h1.f[k] >= lo && h1.f[k] <= hi && h1.usable(k, MIN_COHERENCE)).collect();
    if ok.len() < 20 {
        return Err(format!("only {} usable frequency bins between {lo:.0} and {hi:.0} Hz", ok.len()));
    }
    let low: Vec<usize> = ok.iter().cloned().filter(|&k| h1.f[k] <= 2000.0_f64.min(hi / 2.0)).collect();
    let re = low.iter().map(|&k| h1.z[k].re).fold(f64::INFINITY, f64::min).max(1e-3);
    // The resonance: where the reactance turns from inductive to capacitive (Im Z from + to -,
    // held for a few bins), the one with the largest real part. The largest real part alone
    // is not it on a semi-inductive coil at high level: its LR-2 branch lifts Re Z towards
    // 2 kHz above a resonance that the nonlinearity smears (a 2.9 mH / 6.7 mH coil at 85 %
    // of its range gave 1.9 kHz for 35 Hz).
    let held = 3;
    let crossing = (held..low.len().saturating_sub(held))
        .filter(|&j| (j - held..j).all(|a| h1.z[low[a]].im > 0.0) && (j..j + held).all(|a| h1.z[low[a]].im <= 0.0))
        .map(|j| low[j])
        .max_by(|&a, &b| h1.z[a].re.total_cmp(&h1.z[b].re));
    let kpk = match crossing {
        Some(k) => k,
        None => *low.iter().max_by(|&&a, &&b| h1.z[a].re.total_cmp(&h1.z[b].re)).ok_or("no usable bins below 2 kHz")?,
    };
    let fs0 = h1.f[kpk];
    let res = (h1.z[kpk].re - re).max(0.1 * re);
    // Half-power points of the motional real part: bandwidth fs / Qms.
    let half = re + 0.5 * res;
    let below = low.iter().rev().filter(|&&k| k < kpk).find(|&&k| h1.z[k].re < half).map(|&k| h1.f[k]);
    let above = low.iter().filter(|&&k| k > kpk).find(|&&k| h1.z[k].re < half).map(|&k| h1.f[k]);
    let q = match (below, above) {
        (Some(a), Some(b)) if b > a => (fs0 / (b - a)).clamp(0.3, 50.0),
        _ => 3.0,
    };
    let cmes = q / (2.0 * PI * fs0 * res);
    let lces = 1.0 / ((2.0 * PI * fs0).powi(2) * cmes);
    let kh = *ok.last().unwrap();
    let wh = 2.0 * PI * h1.f[kh];
    let zh = h1.z[kh] - model_impedance(&[0.0, 0.0, 1e-12, 1e-12, res, cmes, lces], h1.f[kh]);
    let le = (zh.im / wh * 0.6).max(1e-7);
    // LR-2's resistance: what the branch adds to the real part at the top of the band (the
    // median over its top quarter, in log frequency, less the motional part).
    let f_top = hi * (lo / hi).powf(0.25);
    let top: Vec<f64> = ok
        .iter()
        .filter(|&&k| h1.f[k] >= f_top)
        .map(|&k| (h1.z[k] - model_impedance(&[0.0, 0.0, 1e-12, 1e-12, res, cmes, lces], h1.f[k])).re - re)
        .collect();
    let r2 = if top.is_empty() { (zh.re - re) * 2.0 } else { crate::checks::median(top) }.max(0.05 * re);
    Ok([re, le, le * 2.0, r2, res, cmes, lces])
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
            "{origin}: the current looks inverted: U/I has a negative real part ({re_med:.3} ohm median over {} coherent bins up to {:.0} Hz), which no passive driver has; swap the sense-resistor leads or invert channel 2 (its scale factor)",
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

/// The linear fit of a measured impedance curve `z` (ohm) at frequencies `f` (Hz, increasing),
/// e.g. a `.zma` file: the same model, model choice ([`LinearOptions::effects`]) and
/// uncertainty as for a record. `band` limits the fitted points (default: all up to 20 kHz).
///
/// Each point weighs alike and its error is relative, `1 - Z_measured / Z_model` (the
/// current error of a record at unit current, `I - U/Z` with `U = Z_measured`, `I = 1`), so
/// a log-spaced file weighs every octave alike, and `residual_rel` is the RMS relative
/// impedance error. A curve is the average of a measurement, with no record ends
/// ([`Ends::AssumedAtRest`]) and no measurement chain (a `.zma` is taken as calibrated; the
/// option `chain` is refused).
pub fn fit_impedance_curve(
    f: &[f64],
    z: &[Complex64],
    band: Option<[f64; 2]>,
    origin: &str,
    opts: &LinearOptions,
    mut observe: impl FnMut(&LmState),
) -> Result<LinearFit, String> {
    impedance_curve(f, z, band, origin, opts, false, &mut observe)
}

/// [`fit_impedance_curve`] of a curve without a measured phase (REW, LPM and many tools
/// export |Z| alone): magnitudes `mag` (ohm) at `f` (Hz). The error of each point is
/// `1 - |Z_measured| / |Z_model|`: a driver's impedance is minimum phase, as the model's is,
/// so the magnitude holds what the phase would tell, and the fit needs no phase of its own.
/// The start values take the curve's minimum phase ([`crate::min_phase`]), which is also
/// what `h1` holds. The sds are those of the magnitude alone.
pub fn fit_impedance_magnitude(
    f: &[f64],
    mag: &[f64],
    band: Option<[f64; 2]>,
    origin: &str,
    opts: &LinearOptions,
    mut observe: impl FnMut(&LmState),
) -> Result<LinearFit, String> {
    check_curve(f, &mag.iter().map(|&m| Complex64::new(m, 0.0)).collect::<Vec<_>>(), origin)?;
    check_magnitude_span(f, origin)?;
    let z = magnitude_curve(f, mag);
    impedance_curve(f, &z, band, origin, opts, true, &mut observe)
}

/// A curve's frequencies positive, finite and increasing, one finite non-zero impedance
/// each (what a file's reader checks, for callers that build a curve themselves).
fn check_curve(f: &[f64], z: &[Complex64], origin: &str) -> Result<(), String> {
    if f.len() != z.len() {
        return Err(format!("{origin}: {} frequencies for {} impedance points", f.len(), z.len()));
    }
    if let Some(k) = (0..f.len()).find(|&k| !(f[k].is_finite() && f[k] > 0.0) || (k > 0 && !(f[k] > f[k - 1]))) {
        return Err(format!("{origin}: frequency {} Hz at point {k} is not positive, finite and above the one before: give increasing frequencies", f[k]));
    }
    if let Some(k) = (0..z.len()).find(|&k| !(z[k].re.is_finite() && z[k].im.is_finite() && z[k].norm() > 0.0)) {
        return Err(format!("{origin}: impedance {} at {} Hz is not finite and non-zero", z[k], f[k]));
    }
    Ok(())
}

/// The fewest decades a curve without phase must span: the magnitude's slopes over the
/// resonance and the voice coil's rise are what tell the phase.
pub const MAGNITUDE_MIN_DECADES: f64 = 2.0;

/// Refuse a curve without phase that is too narrow for its phase to follow from |Z|.
fn check_magnitude_span(f: &[f64], origin: &str) -> Result<(), String> {
    let (lo, hi) =
        (f.iter().copied().filter(|&f| f > 0.0).fold(f64::INFINITY, f64::min), f.iter().copied().fold(0.0, f64::max));
    if !(hi / lo >= 10f64.powf(MAGNITUDE_MIN_DECADES)) {
        return Err(format!(
            "{origin}: the file has no phase, and its {lo:.1} .. {hi:.1} Hz spans {:.1} decades: a curve of |Z| alone must span at least {MAGNITUDE_MIN_DECADES} (from below the resonance into the voice coil's rise), or export the phase too",
            (hi / lo).log10()
        ));
    }
    Ok(())
}

/// A magnitude-only curve with its minimum phase.
fn magnitude_curve(f: &[f64], mag: &[f64]) -> Vec<Complex64> {
    let n = f.len().min(mag.len());
    crate::min_phase::min_phase(&f[..n], &mag[..n])
        .into_iter()
        .zip(mag)
        .map(|(ph, &m)| Complex64::from_polar(m, ph))
        .collect()
}

/// The band of an impedance curve where the lumped model holds, found by [`lumped_band`].
#[derive(Clone, Debug, PartialEq)]
pub struct LumpedBand {
    /// The band to fit (Hz): from the file's lowest frequency to where the model holds.
    pub band: [f64; 2],
    /// What the search found, in words (for the result's `fit.band_note`).
    pub note: String,
    /// No part of the curve held the model, not even the lowest: the whole curve is fitted,
    /// and the fit is doubtful whatever its own misfit ([`LumpedBand::warning`]).
    pub none_held: bool,
}

impl LumpedBand {
    /// The warning of a search that found no band holding the model: a curve that departs
    /// from it below the search's first top (ten times the resonance), or a fit of the lowest
    /// band that ended in a wrong minimum.
    pub fn warning(&self) -> Option<crate::checks::Warning> {
        self.none_held.then(|| {
            crate::checks::Warning::new(
                "no-lumped-band",
                format!("{}: the figures are of the whole curve, where the model is not known to hold; fit a band below the break-up (--band LO,HI)", self.note),
            )
        })
    }
}

/// Half-octave steps of [`lumped_band`]'s search, and where it starts: ten times the
/// curve's resonance (the peak and the voice coil's inductive rise both inside).
pub const LUMPED_STEP: f64 = std::f64::consts::SQRT_2;
pub const LUMPED_START_OVER_FS: f64 = 10.0;
/// A fit holds to its top when its whole band's misfit is within [`CURVE_RESIDUAL_WARN`] and
/// none of its half-octaves is missed by more than this many times that (a surround mode's
/// bump of 2-3 % stays in, a break-up region of 5 % and more does not).
pub const LUMPED_PART_BOUND: f64 = 2.0;

/// Where an impedance curve stops being a lumped driver: the top of the band to fit.
///
/// A driver's impedance follows the lumped model (Re, the voice coil's inductance and its
/// branches, the mass-spring resonance, creep) up to where the cone stops moving as one
/// piece; above that, break-up puts peaks and dips in |Z| that no lumped element has, and a
/// fit that takes them in moves Re and Le to reach them. The search fits the curve below tops
/// half an octave apart, from ten times the resonance (the peak and the voice coil's rise
/// inside) to the curve's end (at most 20 kHz). A fit holds to its top when its RMS relative
/// error over its whole band is within [`CURVE_RESIDUAL_WARN`] (the level at which a fit of a
/// curve is not trusted) and none of its half-octaves is missed by more than
/// [`LUMPED_PART_BOUND`] times that: a surround mode's bump of 2-3 % stays in the band, a
/// break-up region does not. The band ends at the highest top that holds; the note names
/// the first top above it that does not, and by how much it misses.
///
/// The break-up is judged by the same figures that judge a fit, not by a frequency: a
/// microspeaker that holds to 20 kHz keeps its whole band, a woofer that breaks up at 1 kHz
/// loses what is above. A misfit inside the found band still makes the fit doubtful
/// ([`curve_warnings`]).
///
/// `magnitude_only`: the curve has no measured phase (only `|z|` counts). It is searched
/// with its minimum phase ([`crate::min_phase`]), as a curve with its phase: break-up shows
/// in the phase as much as in |Z|, where a fit of |Z| alone could bend through it.
pub fn lumped_band(
    f: &[f64],
    z: &[Complex64],
    magnitude_only: bool,
    origin: &str,
    opts: &LinearOptions,
) -> Result<LumpedBand, String> {
    check_curve(f, z, origin)?;
    let rebuilt;
    let z = if magnitude_only {
        check_magnitude_span(f, origin)?;
        rebuilt = magnitude_curve(f, &z.iter().map(|z| z.norm()).collect::<Vec<_>>());
        &rebuilt[..]
    } else {
        z
    };
    let pts: Vec<usize> =
        (0..f.len().min(z.len())).filter(|&k| f[k] > 0.0 && f[k] <= 20000.0 && z[k].norm().is_finite()).collect();
    let (Some(&first), Some(&last)) = (pts.first(), pts.last()) else {
        return Err(format!("{origin}: no points between 0 and 20 kHz"));
    };
    let (lo, top) = (f[first], f[last]);
    let whole = [lo, top];
    // A curve without phase is searched with its minimum phase, as a curve with its phase:
    // the break-up's peaks and dips show in the phase as much as in |Z| (a passive one-port's
    // are minimum phase too), where a fit of |Z| alone can bend through them.
    let fit_to = |hi: f64| impedance_curve(f, z, Some([lo, hi]), origin, opts, false, &mut |_| {});
    // The misfit (RMS relative impedance error) of a fit over the points in (a, b].
    let misfit = |fit: &LinearFit, a: f64, b: f64| -> (f64, usize, f64, f64) {
        let (mut sum, mut n, mut worst, mut at) = (0.0, 0, 0.0, 0.0);
        for &k in pts.iter().filter(|&&k| f[k] > a && f[k] <= b) {
            let e = fit.point_error(f[k], z[k]);
            sum += e * e;
            n += 1;
            if e > worst {
                (worst, at) = (e, f[k]);
            }
        }
        ((sum / n.max(1) as f64).sqrt(), n, worst, at)
    };
    // The resonance from a first fit of the whole curve; a curve with too few points or no
    // fit of its own is left to the caller's fit to report.
    let Ok(full) = fit_to(top) else {
        return Ok(LumpedBand {
            band: whole,
            note: "the whole curve (no fit to search a band with)".into(),
            none_held: false,
        });
    };
    // The first top: ten times the resonance, two half-octaves above the bottom, and at least
    // 40 points below it (the fit has up to 10 unknowns); whichever is highest.
    let by_points = f[pts[pts.len().min(40) - 1]];
    let start = (LUMPED_START_OVER_FS * full.fs()).max(lo * LUMPED_STEP * LUMPED_STEP).max(by_points);
    if start >= top / LUMPED_STEP {
        let why = if by_points >= top / LUMPED_STEP {
            format!("it has too few points ({}) to fit a part of it", pts.len())
        } else {
            format!("it ends below {LUMPED_START_OVER_FS} times the resonance ({:.0} Hz)", full.fs())
        };
        return Ok(LumpedBand {
            band: whole,
            note: format!("the whole curve ({lo:.0} .. {top:.0} Hz): {why}"),
            none_held: false,
        });
    }
    // Every top, half an octave apart from the first: whether the fit to it holds, over its
    // whole band and in each half-octave above the first top (a narrow mode is averaged in; a
    // fit that holds to a higher top wins over a failure below it). A NaN misfit fails.
    let mut tops = vec![start];
    while *tops.last().expect("one") < top {
        tops.push((tops.last().expect("one") * LUMPED_STEP).min(top));
    }
    // The largest top whose fit holds, and the first failure above it, (top, misfit, worst, at).
    let mut held: Option<f64> = None;
    let mut failed_above: Option<(f64, f64, f64, f64)> = None;
    for (i, &t) in tops.iter().enumerate() {
        let Ok(fit) = fit_to(t) else { continue };
        let parts: Vec<(f64, usize, f64, f64)> = tops[..=i].windows(2).map(|s| misfit(&fit, s[0], s[1])).collect();
        let bad_part = parts.iter().filter(|p| p.1 > 0).find(|p| !(p.0 <= LUMPED_PART_BOUND * CURVE_RESIDUAL_WARN));
        if fit.residual_rel <= CURVE_RESIDUAL_WARN && bad_part.is_none() {
            held = Some(t);
            failed_above = None;
        } else if failed_above.is_none() {
            let (e, worst, at) = match bad_part {
                Some(&(e, _, worst, at)) => (e.max(fit.residual_rel), worst, at),
                None => (fit.residual_rel, f64::NAN, f64::NAN),
            };
            failed_above = Some((t, e, worst, at));
        }
    }
    match (held, failed_above) {
        (Some(h), Some((t, e, worst, at))) => {
            let band = [lo, h];
            let worst_text = if worst.is_finite() { format!(" (worst {:.1} % at {at:.0} Hz)", 100.0 * worst) } else { String::new() };
            let note = format!(
                "fitted {:.0} .. {:.0} Hz, where the lumped model holds: fitted to {t:.0} Hz it misses the curve by {:.1} % RMS{worst_text}, cone break-up or modes, which are left out (--band LO,HI sets the band)",
                band[0],
                band[1],
                100.0 * e,
            );
            Ok(LumpedBand { band, note, none_held: false })
        }
        (Some(_), None) => Ok(LumpedBand { band: whole, note: format!("the whole curve ({lo:.0} .. {top:.0} Hz): the lumped model holds to its end"), none_held: false }),
        // Not even the lowest part holds: the whole curve is fitted, and its fit's warnings
        // say how the model misses it.
        (None, _) => Ok(LumpedBand { band: whole, note: format!("the whole curve ({lo:.0} .. {top:.0} Hz): no part of it holds the lumped model within {:.0} % (from its first {start:.0} Hz on)", 100.0 * CURVE_RESIDUAL_WARN), none_held: true }),
    }
}

/// [`fit_impedance_curve`]'s work, compiled once (not for each caller's observer).
fn impedance_curve(
    f: &[f64],
    z: &[Complex64],
    band: Option<[f64; 2]>,
    origin: &str,
    opts: &LinearOptions,
    magnitude_only: bool,
    observe: &mut dyn FnMut(&LmState),
) -> Result<LinearFit, String> {
    if opts.chain {
        return Err(format!("{origin}: an impedance curve has no measurement chain to estimate (its tool calibrated it); --chain applies to records"));
    }
    refuse_large_signal_effects(opts, origin)?;
    check_curve(f, z, origin)?;
    let [lo, hi] = band.unwrap_or([0.0, 20000.0]);
    if !(lo >= 0.0 && hi > lo) {
        return Err(format!("{origin}: fit band {lo} .. {hi} Hz is empty (give LO < HI, Hz)"));
    }
    let keep: Vec<usize> = (0..f.len()).filter(|&k| f[k] > 0.0 && f[k] >= lo && f[k] <= hi).collect();
    if keep.len() < 20 {
        return Err(format!("{origin}: {} points between {lo:.0} and {hi:.0} Hz; at least 20 are needed", keep.len()));
    }
    let h1 = ImpedanceEstimate::from_curve(
        &keep.iter().map(|&k| f[k]).collect::<Vec<_>>(),
        &keep.iter().map(|&k| z[k]).collect::<Vec<_>>(),
    );
    let band = [h1.f[0], *h1.f.last().expect("20 points")];
    let zmed = crate::checks::median(h1.z.iter().map(|z| z.norm()).collect());
    if zmed < 0.5 {
        return Err(format!("{origin}: |Z| is {zmed:.3} ohm (median): an admittance, or a curve in other units? (an impedance file holds ohms)"));
    }
    let low: Vec<f64> = (0..h1.f.len()).filter(|&k| h1.f[k] <= 500.0).map(|k| h1.z[k].re).collect();
    let re_med = crate::checks::median(if low.is_empty() { h1.z.iter().map(|z| z.re).collect() } else { low });
    if re_med < 0.0 {
        return Err(format!("{origin}: the impedance has a negative real part ({re_med:.3} ohm median below 500 Hz), which no passive driver has: a phase of the wrong sign or 180 degrees off"));
    }
    let p0 = initial_guess(&h1, band[0], band[1]).map_err(|e| format!("{origin}: {e}"))?;
    let n = h1.f.len();
    let mut prob = CurrentError {
        f: h1.f.clone(),
        u: h1.z.clone(),
        i: vec![Complex64::new(1.0, 0.0); n],
        w: vec![1.0; n],
        norm: 1.0,
        map: ParamMap::for_band(band),
        omega0: 2.0 * PI * (band[0] * band[1]).sqrt(),
        n_transient: 0,
        effects: Effects::NONE,
        chain: None,
        magnitude_only,
    };
    prob.norm = prob_norm(&prob);
    fit_bins(prob, h1, band, p0, opts, None, None, origin, observe)
}

/// The fit proper, on the bins of `prob` (their `u`, `i` and weights set, `norm` too), from
/// the start `p0` found on `h1` in `band`; `fs` is the record's rate (none for an impedance
/// curve: no chain, no skew check); `lr2`: the LR-2 model's fit on these bins, taken instead
/// of fitting it ([`fit_linear_record_from`]).
#[allow(clippy::too_many_arguments)]
fn fit_bins(
    prob: CurrentError,
    h1: ImpedanceEstimate,
    band: [f64; 2],
    p0: [f64; 7],
    opts: &LinearOptions,
    fs: Option<f64>,
    lr2: Option<&Lr2Fit>,
    origin: &str,
    observe: &mut dyn FnMut(&LmState),
) -> Result<LinearFit, String> {
    let map = prob.map.clone();
    let n_chain = prob.chain.map_or(0, |c| c.count());
    // LM to convergence, or to a plateau: the cost lowered by less than PLATEAU_REL over
    // the last PLATEAU_ITERATIONS iterations. An effect the record does not have leaves a
    // flat direction along which LM creeps for ever (LR-3 on 18WU's small stage: 200
    // iterations, 4 s on 40 000 bins, the cost the same to 1e-9).
    let run = |p: &CurrentError, theta: Vec<f64>, max_iter: usize, observe: &mut dyn FnMut(&LmState)| {
        let mut s = LmState::new(p, theta);
        observe(&s);
        let mut costs = std::collections::VecDeque::from([s.cost]);
        while !s.converged && s.iteration < max_iter {
            s = lm_step(p, &s);
            // The damping after an accepted step follows how well the model predicted it
            // (`lambda_after_gain`).
            if s.last_decrease > 0.0 && s.gain_ratio.is_finite() {
                s.lambda = lambda_after_gain(s.step_lambda, s.gain_ratio);
            }
            observe(&s);
            costs.push_back(s.cost);
            if costs.len() > PLATEAU_ITERATIONS {
                let old = costs.pop_front().expect("not empty");
                if old - s.cost <= PLATEAU_REL * s.cost {
                    s.converged = true;
                }
            }
        }
        s
    };
    let better =
        |s: &LmState, b: &LmState| (s.converged && !b.converged) || (s.converged == b.converged && s.cost < b.cost);
    // Fit one model (the LR-2 quantities plus `effects`) from several starts: each start is
    // scouted on every k-th bin (at most SCOUT_BINS), the best is polished on all of them,
    // so the answer is the full-data optimum at a fraction of the cost.
    // A candidate whose scout residual is not below `gate` is not polished (it cannot win:
    // the effect does not gain its share of the excess on the scout bins). Returns
    // the problem, the state, the scout's residual and whether it was polished.
    // The problem of a model with `effects` on these bins.
    let with_effects = |effects: Effects| {
        let mut pr = CurrentError {
            f: prob.f.clone(),
            u: prob.u.clone(),
            i: prob.i.clone(),
            w: prob.w.clone(),
            map: prob.map.clone(),
            effects,
            chain: prob.chain,
            ..prob
        };
        pr.norm = prob.norm;
        pr
    };
    // `min_ln_le`: a start whose run ends with ln Le below it traded the voice coil's
    // inductance for an added branch ([`LE_COLLAPSE`]): it is taken only if every start did.
    let solve = |effects: Effects,
                 starts: &[Vec<f64>],
                 gate: f64,
                 min_ln_le: f64,
                 observe: &mut dyn FnMut(&LmState)|
     -> (CurrentError, LmState, f64, bool) {
        let pr = with_effects(effects);
        let scout = (pr.f.len() > 2 * SCOUT_BINS).then(|| thin(&pr, SCOUT_BINS));
        let scout_iterations =
            if gate.is_finite() && scout.is_some() { CANDIDATE_SCOUT_ITERATIONS } else { MAX_ITERATIONS };
        // The starts are independent: they run on all cores, each keeping its LM states,
        // which the observer then sees start by start, as if they had run in turn.
        let on = scout.as_ref().unwrap_or(&pr);
        let runs: Vec<(LmState, Vec<LmState>)> = std::thread::scope(|scope| {
            let handles: Vec<_> = starts
                .iter()
                .map(|th| {
                    scope.spawn(move || {
                        let mut seen = vec![];
                        let s = run(on, th.clone(), scout_iterations, &mut |st: &LmState| seen.push(st.clone()));
                        (s, seen)
                    })
                })
                .collect();
            handles.into_iter().map(|h| h.join().expect("an LM run does not panic")).collect()
        });
        let mut best: Option<LmState> = None;
        let kept = |s: &LmState| s.theta[1] >= min_ln_le;
        for (s, seen) in runs {
            seen.iter().for_each(&mut *observe);
            let replace = match best.as_ref() {
                None => true,
                Some(b) => (kept(&s) && !kept(b)) || (kept(&s) == kept(b) && better(&s, b)),
            };
            if replace {
                best = Some(s);
            }
        }
        let mut s = best.expect("at least one start");
        let scout_rel = scout.as_ref().unwrap_or(&pr).residual_rel(&s.theta);
        let polish = scout.is_some() && scout_rel < gate;
        if polish {
            s = run(&pr, s.theta.clone(), MAX_ITERATIONS, observe);
        }
        (pr, s, scout_rel, polish || scout.is_none())
    };
    // The LR-2 branch trades off against Re and Le: start from the heuristic guess and from
    // corners spread over the band, and keep the lowest cost among the converged runs (each
    // start is a full LM run, observed like any other).
    let q0 = ParamMap::q_of(&p0);
    // ln tau of corners at a quarter, a half and three quarters of the band (log scale): the
    // branches' starts spread over it.
    let spread_ln_tau =
        [0.25, 0.5, 0.75].map(|frac: f64| (1.0 / (2.0 * PI * (band[0] * (band[1] / band[0]).powf(frac)))).ln());
    let mut starts = vec![q0];
    for ln_tau in spread_ln_tau {
        for r2f in [0.25, 1.0, 4.0] {
            let mut q = q0;
            q[2] = ln_tau;
            q[3] += f64::ln(r2f);
            starts.push(q);
        }
    }
    let n_t = prob.n_transient;
    let base_starts: Vec<Vec<f64>> = starts
        .iter()
        .map(|q| {
            let mut th = map.theta(q);
            th.resize(7 + n_t + n_chain, 0.0);
            th
        })
        .collect();
    // Each fitted model with its current residual (on all bins; a candidate left unpolished
    // keeps its scout's, and cannot be chosen), and its scout residual.
    let (mut scout_r, mut polished): (Vec<f64>, Vec<bool>) = (vec![], vec![]);
    fn with_residual(
        scout_r: &mut Vec<f64>,
        polished: &mut Vec<bool>,
        (pr, s, sr, done): (CurrentError, LmState, f64, bool),
    ) -> (CurrentError, LmState, f64) {
        let r = if done { pr.residual_rel(&s.theta) } else { sr };
        scout_r.push(sr);
        polished.push(done);
        (pr, s, r)
    }
    let base = match lr2 {
        Some(b) => (with_effects(Effects::NONE), b.state.clone(), b.scout_rel, b.polished),
        None => solve(Effects::NONE, &base_starts, f64::INFINITY, f64::NEG_INFINITY, observe),
    };
    let lr2 = Lr2Fit { state: base.1.clone(), scout_rel: base.2, polished: base.3 };
    // theta[1] is ln Le (unbounded); below this a model with more effects took Le's place
    // ([`LE_COLLAPSE`]).
    let min_ln_le = base.1.theta[1] + LE_COLLAPSE.ln();
    let mut fitted = vec![with_residual(&mut scout_r, &mut polished, base)];
    // Starts of a model with more effects, from a fitted one: creep from lambda = 0.05 (the
    // middle of what Klippel's LPM reports), LR-3 from a corner 4x above and 4x below LR-2's
    // with R3 = 2.5 R2 and R2 (the branches are named by their corners afterwards).
    let grow = |from: &(CurrentError, LmState, f64), to: Effects| -> Vec<Vec<f64>> {
        let (pr, s, _) = from;
        let (th0, ext0) = (&s.theta, pr.ext(&s.theta));
        let base = &th0[..7];
        let trans = th0[pr.t0()..].to_vec();
        let lambda = ext0.creep.map_or(0.05, |c| c.lambda);
        let lr3s: Vec<(f64, f64)> = match (to.lr3, ext0.lr3) {
            (false, _) => vec![],
            (true, Some((l3, r3))) => vec![((l3 / r3).ln(), r3.ln())],
            (true, None) => {
                let q = map.q(base);
                let r2 = q[3];
                // And corners spread over the band, as LR-2's starts are: a second branch
                // far from where the LR-2 model put its one is reached from none of the two
                // beside it (a microspeaker with its branches at 7 and 17 kHz: LR-3's fit
                // stayed above LR-2's error from both).
                let mut v = vec![(q[2] - 4f64.ln(), r2 + 2.5f64.ln()), (q[2] + 4f64.ln(), r2)];
                v.extend(spread_ln_tau.map(|ln_tau| (ln_tau, r2)));
                // And at the band's top: a small coil's branches sit high (a microspeaker's at
                // 3.2 and 9.8 kHz on a band to 20 kHz; from the starts below, its fit made one
                // branch a 0.08 ohm resistor at 3 Hz beside Re, which came out 0.8 % low, and
                // Le took the other, 37 % high).
                v.push(((1.0 / (2.0 * PI * band[1])).ln(), r2));
                v
            }
        };
        let mut out = vec![];
        for &(ltau3, lr3) in if lr3s.is_empty() { &[(0.0, 0.0)][..] } else { &lr3s[..] } {
            let mut th = base.to_vec();
            if to.creep {
                th.push(lambda);
            }
            if to.lr3 {
                th.push(bounded_theta(ltau3, map.lo[2], map.hi[2], 0.01));
                th.push(lr3);
            }
            th.extend_from_slice(&trans);
            out.push(th);
        }
        out
    };
    let chosen = match opts.effects {
        EffectsChoice::Fixed(e) if e == Effects::NONE => 0,
        EffectsChoice::Fixed(e) => {
            let st = grow(&fitted[0], e);
            fitted.push(with_residual(&mut scout_r, &mut polished, solve(e, &st, f64::INFINITY, min_ln_le, observe)));
            1
        }
        EffectsChoice::Auto => {
            // Forward selection: add the effect that lowers the residual most, while one pays
            // ([`effect_pays`]: a share of the excess over the noise floor, well above what
            // noise gives) and creep's lambda is physical. The floor of a record is the
            // lowest any fitted model shows (a model's misfit can only raise it); an averaged
            // curve has none.
            let floor_of = |f: &(CurrentError, LmState, f64)| {
                if fs.is_some() {
                    f.0.residual_and_floor(&f.1.theta).1
                } else {
                    0.0
                }
            };
            let mut floor = floor_of(&fitted[0]);
            let bins = prob.f.len();
            let mut at = 0;
            loop {
                let cur = fitted[at].0.effects;
                let mut cands = vec![];
                if !cur.creep {
                    cands.push(Effects { creep: true, ..cur });
                }
                if !cur.lr3 {
                    cands.push(Effects { lr3: true, ..cur });
                }
                // A candidate is polished on every bin when its scout gains the share of the
                // excess (the relative floor is the same on the scout's thinned bins).
                let r_cur = fitted[at].2;
                let gate =
                    (scout_r[at].powi(2) - EFFECT_MIN_SHARE * (scout_r[at].powi(2) - floor * floor).max(0.0)).sqrt();
                let first = fitted.len();
                for e in cands {
                    let st = grow(&fitted[at], e);
                    let f = with_residual(&mut scout_r, &mut polished, solve(e, &st, gate, min_ln_le, observe));
                    if polished[fitted.len()] {
                        floor = floor.min(floor_of(&f));
                    }
                    fitted.push(f);
                }
                let mut best: Option<(usize, f64)> = None;
                for k in first..fitted.len() {
                    let (pr, s, r) = &fitted[k];
                    let lambda_ok = pr.idx_lambda().is_none_or(|j| s.theta[j] > 0.0);
                    let unknowns = n_extra(pr.effects) - n_extra(cur);
                    if polished[k]
                        && lambda_ok
                        && s.theta[1] >= min_ln_le
                        && effect_pays(r_cur, *r, floor, bins, unknowns)
                        && best.is_none_or(|(_, rb)| *r < rb)
                    {
                        best = Some((k, *r));
                    }
                }
                match best {
                    Some((k, _)) => at = k,
                    None => break at,
                }
            }
        }
    };
    let tried: Vec<(String, f64)> = fitted.iter().map(|(pr, _, r)| (pr.effects.model_name(), *r)).collect();
    // Models with more effects than the chosen one that the data do not tell from it (on
    // the scout's bins, where every candidate has a residual; the relative floor is the
    // same there): the spread of their Le is Le's model uncertainty.
    let le_model_rel = {
        let (ce, lc) = (fitted[chosen].0.effects, fitted[chosen].1.theta[1]);
        let scout_bins = SCOUT_BINS.min(prob.f.len());
        let floor = if fs.is_some() { fitted[chosen].0.residual_and_floor(&fitted[chosen].1.theta).1 } else { 0.0 };
        let d = (0..fitted.len())
            .filter(|&k| k != chosen && fitted[k].0.effects.union(ce) == fitted[k].0.effects)
            .filter(|&k| {
                !effect_pays(scout_r[k], scout_r[chosen], floor, scout_bins, n_extra(fitted[k].0.effects) - n_extra(ce))
            })
            .map(|k| (fitted[k].1.theta[1] - lc).abs())
            .fold(0.0, f64::max);
        (d.exp() - 1.0).min(1.0)
    };
    let (mut prob, mut s, _) = fitted.swap_remove(chosen);
    // Name the branches by their corners: LR-2 is the lower one.
    if let Some(k3) = prob.idx_lr3() {
        let q = map.q(&s.theta[..7]);
        let (ltau3, _) = prob.tau3(s.theta[k3]);
        if ltau3 > q[2] {
            let (ltau2, lr2, lr3) = (q[2], q[3], s.theta[k3 + 1]);
            let mut qn = q;
            qn[2] = ltau3;
            qn[3] = lr3;
            let th = map.theta(&qn);
            s.theta[2] = th[2];
            s.theta[3] = th[3];
            s.theta[k3] = bounded_theta(ltau2, map.lo[2], map.hi[2], 1e-9);
            s.theta[k3 + 1] = lr2;
        }
    }
    let free_of = |prob: &CurrentError, th: &[f64]| -> Vec<usize> {
        let inside = |t: f64| (1e-3..=1.0 - 1e-3).contains(&logistic(t));
        (0..th.len())
            .filter(|&k| (k >= 7 && Some(k) != prob.idx_lr3()) || (k < 7 && !map.lo[k].is_finite()) || inside(th[k]))
            .collect()
    };
    // The chain: keep the quantities whose estimates stand out of their sds (a corner also
    // positive), hold the others at 0 and fit again.
    if let Some(terms) = prob.chain {
        let ci = prob.chain_index();
        let cov = covariance_of(&prob, &s.theta, &free_of(&prob, &s.theta));
        let vals = terms.values(&s.theta[ci..]);
        let sds = terms.sds(cov.as_ref(), ci);
        // (NaN sds, those off or without a covariance, compare false: not significant.)
        let significant = |n: usize| {
            terms.on()[n]
                && vals[n].abs() > CHAIN_SIGNIFICANCE * sds[n]
                && vals[n].abs() >= CHAIN_MIN[n]
                && (n == 0 || vals[n] > 0.0)
        };
        let keep = ChainTerms { delay: significant(0), hp_u: significant(1), hp_i: significant(2), ..terms };
        if keep != terms {
            let mut th = s.theta[..ci].to_vec();
            let kv = keep.on();
            th.extend((0..3).filter(|&n| kv[n]).map(|n| vals[n]));
            let pr = CurrentError {
                f: prob.f.clone(),
                u: prob.u.clone(),
                i: prob.i.clone(),
                w: prob.w.clone(),
                map: prob.map.clone(),
                chain: (keep.count() > 0).then_some(keep),
                ..prob
            };
            s = run(&pr, th, MAX_ITERATIONS, observe);
            prob = pr;
        }
    }
    let mut p = map.params(&s.theta);
    let ext = prob.ext(&s.theta);
    // Relative sd of p_k is the sd of ln p_k: the covariance of theta mapped to q (and
    // ln L2 = q2 + q3).
    // A coordinate that ended on its bound is held there (its logistic's slope is ~0, which
    // would make J^T J singular and every sd NaN): it leaves the covariance, with sd 0.
    let dq = map.dq(&s.theta);
    let inside = |t: f64| (1e-3..=1.0 - 1e-3).contains(&logistic(t));
    let cov = covariance_of(&prob, &s.theta, &free_of(&prob, &s.theta));
    let mut sigma_rel: [f64; 7] = match &cov {
        Some(c) => {
            let cq = |a: usize, b: usize| c[(a, b)] * dq[a] * dq[b];
            std::array::from_fn(|k| {
                sd_from_variance(if k == 2 { cq(2, 2) + cq(3, 3) + 2.0 * cq(2, 3) } else { cq(k, k) })
            })
        }
        None => [f64::NAN; 7],
    };
    let creep = prob.idx_lambda().map(|k| (s.theta[k], cov.as_ref().map_or(f64::NAN, |c| sd_from_variance(c[(k, k)]))));
    let mut lr3 = prob.idx_lr3().map(|k| {
        let (l3, r3) = ext.lr3.expect("LR-3 fitted");
        let d3 = prob.tau3(s.theta[k]).1;
        let sd = cov.as_ref().map_or([f64::NAN; 2], |c| {
            let (a, b) = (k, k + 1);
            [sd_from_variance(c[(a, a)] * d3 * d3 + c[(b, b)] + 2.0 * c[(a, b)] * d3), sd_from_variance(c[(b, b)])]
        });
        ([l3, r3], sd)
    });
    sigma_rel[1] = sigma_rel[1].hypot(le_model_rel);
    let residual_rel = prob.residual_rel(&s.theta);
    if !s.converged {
        return Err(format!(
            "{origin}: the impedance fit did not converge in {} iterations (residual {residual_rel:.3e})",
            s.iteration
        ));
    }
    let mut at_bound = map.at_bound(&s.theta);
    if let Some(k) = prob.idx_lr3() {
        if !inside(s.theta[k]) {
            at_bound.push("L3/R3 corner");
        }
    }
    if s.theta[1] < min_ln_le {
        at_bound.push("Le");
    }
    let chain = fs.filter(|_| opts.chain).map(|fs| {
        let terms = prob.chain.unwrap_or(ChainTerms { fs, delay: false, hp_u: false, hp_i: false });
        let ci = prob.chain_index();
        let on = terms.on();
        let sds = terms.sds(cov.as_ref(), ci);
        ChainEstimate {
            values: terms.values(&s.theta[ci..]),
            sd: std::array::from_fn(|n| if on[n] { sds[n] } else { 0.0 }),
            on,
            fs,
        }
    });
    // Skewed channels: a current recorded late by tau samples multiplies U/I by
    // e^{j 2 pi f tau / fs}, which no passive circuit does. Let the same fit shift the current
    // channel: if that explains most of the error, the channels are skewed. With the chain
    // estimated, its delay is in the model (and reported there).
    let current_delay = match fs {
        Some(fs) if !opts.chain => {
            let mut check = CurrentError {
                chain: Some(ChainTerms { fs, delay: true, hp_u: false, hp_i: false }),
                ..thin(&prob, SCOUT_BINS)
            };
            check.norm = prob_norm(&check);
            let mut th = s.theta.clone();
            th.push(0.0);
            let base = LmState::new(&check, th.clone()).cost;
            let d = run(&check, th, MAX_ITERATIONS, &mut |_| {});
            let at = check.chain_index();
            (d.converged && d.cost < 0.25 * base && d.theta[at].abs() >= 0.05)
                .then(|| (d.theta[at], 1.0 - (d.cost / base).sqrt()))
        }
        _ => None,
    };
    let transient = Transient { c: prob.transient(&s.theta).to_vec(), omega0: prob.omega0 };
    if lr3_named_first(&mut p, &mut sigma_rel, &mut lr3) {
        for b in at_bound.iter_mut() {
            *b = match *b {
                "L2/R2 corner" => "L3/R3 corner",
                "L3/R3 corner" => "L2/R2 corner",
                other => other,
            };
        }
    }
    Ok(LinearFit {
        p,
        sigma_rel,
        residual_rel,
        band,
        bins: prob.f.len(),
        iterations: s.iteration,
        h1,
        at_bound,
        current_delay,
        transient,
        effects: prob.effects,
        creep,
        lr3,
        tried,
        le_model_rel,
        chain,
        lr2,
        magnitude_only: prob.magnitude_only,
    })
}

/// Bins per cluster of the linear fit's robust covariance (see [`covariance_of`]).
const COVARIANCE_CLUSTER_BINS: usize = 16;

/// Covariance of theta over its `free` entries only (the others held fixed, with zero rows
/// and columns): the cluster-robust [`sandwich_covariance`] over clusters of
/// [`COVARIANCE_CLUSTER_BINS`] neighbouring bins. The classical `sigma^2 (J^T J)^-1` took the
/// residual as white with one level; its largest part is distortion and leakage
/// concentrated near the resonance, and there its sds were 2-5x too small (52 %
/// of the truths within 2 sd, 87 % once the leakage was fitted; see
/// `linear_sigmas_cover_the_truth_over_seeds`).
fn covariance_of(p: &CurrentError, theta: &[f64], free: &[usize]) -> Option<DMatrix<f64>> {
    let (r, j) = p.residual_jacobian(theta);
    let jf = j.select_columns(free);
    let cf = sandwich_covariance(&jf, &r, 2 * COVARIANCE_CLUSTER_BINS)?;
    let mut c = DMatrix::zeros(theta.len(), theta.len());
    for (a, &ka) in free.iter().enumerate() {
        for (b, &kb) in free.iter().enumerate() {
            c[(ka, kb)] = cf[(a, b)];
        }
    }
    Some(c)
}

/// A parameter set from the electrical fit and a known moving mass (kg).
pub fn scale_by_mms(fit: &LinearFit, mms: f64) -> Result<Parameters, String> {
    if !(mms.is_finite() && mms > 0.0 && mms < 2.0) {
        return Err(format!("moving mass {mms} kg is not valid (0 .. 2 kg; give kg, not g)"));
    }
    let [re, le, l2, r2, res, cmes, lces] = fit.p;
    let bl2 = mms / cmes;
    Ok(Parameters {
        name: None,
        source: Some("coilscope linear (impedance fit)".into()),
        re,
        le: Poly::constant(le),
        l2r2: Some((Poly::constant(l2), Poly::constant(r2))),
        bl: Poly::constant(bl2.sqrt()),
        kms: Poly::constant(bl2 / lces),
        mms,
        rms: bl2 / res,
        sd: None,
        creep: fit.creep.map(|(lambda, _)| coilscope_core::params::Creep { lambda, f_ref: None }),
        l3r3: fit.lr3.map(|(v, _)| (v[0], v[1])),
        le_i: None,
        rms_v: None,
        thermal: None,
        x_range: None,
        extra: Default::default(),
    })
}

/// Moving mass from the resonance shift with a known added mass (kg):
/// `Mms = Madd / (c (fs / fs_with)^2 - 1)`, with `c = K(fs_with) / K(fs)` the suspension's
/// stiffness at the loaded resonance over that at the free one.
///
/// Without creep `c = 1`, the textbook formula. With creep the stiffness falls towards low
/// frequencies (about `lambda` per decade, [`coilscope_core::creep`]), so the loaded
/// resonance sits lower than a constant spring would put it, and the textbook formula takes
/// that for mass: on the SEAS L16RN-X (lambda 0.18, 45 -> 31 Hz) it gave Mms 14.07 g, 6 %
/// below the published 14.9-15.3 g; with `c` (from the free fit's lambda) 14.9 g.
pub fn added_mass_mms(fit: &LinearFit, with_mass: &LinearFit, added: f64) -> Result<f64, String> {
    added_mass_scale(fit, with_mass, added).map(|(m, _)| m)
}

/// Relative sd of a fit's resonance `fs = 1 / (2 pi sqrt(Lces Cmes))` (first order).
fn fs_rel_sd(fit: &LinearFit) -> f64 {
    0.5 * (fit.sigma_rel[5].powi(2) + fit.sigma_rel[6].powi(2)).sqrt()
}

/// [`added_mass_mms`] with its [`ScaleMethod`], whose relative sd of Mms follows from the
/// two resonances' sds: `d ln Mms = -2 c r^2 / (c r^2 - 1) d ln r`, `r = fs / fs_with`.
pub fn added_mass_scale(fit: &LinearFit, with_mass: &LinearFit, added: f64) -> Result<(f64, ScaleMethod), String> {
    let c = fit.creep.map_or(1.0, |(lambda, _)| {
        let w = |f: f64| coilscope_core::creep::bank(2.0 * PI * f).re;
        1.0 + lambda * (w(with_mass.fs()) - w(fit.fs()))
    });
    let ratio = c * (fit.fs() / with_mass.fs()).powi(2);
    if !(ratio > 1.02) {
        return Err(format!(
            "the added mass moved the resonance only from {:.2} Hz to {:.2} Hz; add more mass (about Mms/2 or more)",
            fit.fs(),
            with_mass.fs()
        ));
    }
    let r_rel = (fs_rel_sd(fit).powi(2) + fs_rel_sd(with_mass).powi(2)).sqrt();
    let mms_sd_rel = 2.0 * ratio / (ratio - 1.0) * r_rel;
    Ok((added / (ratio - 1.0), ScaleMethod::AddedMass { added, fs_with: with_mass.fs(), mms_sd_rel }))
}

/// Moving mass from a displacement channel `x` (m): fit `X = (Bl/Kms) G(f) I` with the known
/// resonance shape `G` and read `Bl = Lces / (Bl/Kms)`.
pub fn scale_by_displacement(fit: &LinearFit, i: &[f64], x: &[f64], fs: f64, origin: &str) -> Result<f64, String> {
    let (xf, i_f) = (rfft(x), rfft(i));
    let n = i.len();
    let (f_res, q) = (fit.fs(), fit.qms());
    let (mut num, mut den) = (0.0, 0.0);
    for k in 1..xf.len() {
        let f = k as f64 * fs / n as f64;
        if f < fit.band[0] || f > 4.0 * f_res {
            continue;
        }
        let g = 1.0 / Complex64::new(1.0 - (f / f_res).powi(2), f / (f_res * q));
        let gi = g * i_f[k];
        num += (gi.conj() * xf[k]).re;
        den += gi.norm_sqr();
    }
    let c = num / den;
    if !(c.is_finite()) || c == 0.0 {
        return Err(format!("{origin}: displacement (channel 3) does not follow the current"));
    }
    if c < 0.0 {
        return Err(format!(
            "{origin}: displacement (channel 3) has inverted polarity (x > 0 must be coil out for positive current)"
        ));
    }
    let bl = fit.p[6] / c;
    Ok(bl * bl * fit.p[5])
}

/// `s` filtered by the transfer `h(k, f)` of each whole-record DFT bin (exact for a record
/// that starts and ends at rest).
fn filter_record(s: &[f64], fs: f64, h: impl Fn(usize, f64) -> Complex64) -> Vec<f64> {
    let n = s.len();
    let mut spec = rfft(s);
    for (k, c) in spec.iter_mut().enumerate() {
        *c *= h(k, k as f64 * fs / n as f64);
    }
    let mut out = irfft(&spec, n);
    out.iter_mut().for_each(|v| *v /= n as f64);
    out
}

/// Displacement predicted from the current by the linear model (for the reached range).
pub fn predicted_displacement(p: &Parameters, i: &[f64], fs: f64) -> Vec<f64> {
    filter_record(i, fs, |k, f| {
        if k == 0 {
            Complex64::new(0.0, 0.0)
        } else {
            coilscope_core::small_signal::displacement_per_current(p, f)
        }
    })
}

/// The linear model's current for the measured voltage (A), with the fitted transient
/// term of a record that does not start and end at rest.
pub fn model_current(fit: &LinearFit, u: &[f64], fs: f64) -> Vec<f64> {
    let n = u.len();
    let mut spec = rfft(u);
    for (k, c) in spec.iter_mut().enumerate() {
        let f = k as f64 * fs / n as f64;
        *c = if k == 0 {
            *c / fit.p[0]
        } else {
            let imp = impedance_ext(&fit.p, &fit.ext(), f);
            *c / imp.0 + transient_term(&fit.p, &imp, &fit.transient.c, fit.transient.omega0, f).0
        };
    }
    let mut out = irfft(&spec, n);
    out.iter_mut().for_each(|v| *v /= n as f64);
    out
}

/// Relative current error above the noise floor below which a linear fit's misfit is not
/// material (at 0.5 % the small-signal parameters are off by about 1 %).
const LINEAR_MATERIAL_EXCESS: f64 = 0.005;

/// Share of the linear model's current error above which a record is called large-signal.
const NONLINEAR_SHARE_WARN: f64 = 0.3;

/// What makes a linear fit of this record doubtful, named: skewed channels, a fit on a
/// bound, a residual far above the noise floor, a record that drove the nonlinearities
/// (use `identify`). `p` is the scaled parameter set of `fit`.
pub fn linear_warnings(
    fit: &LinearFit,
    p: &Parameters,
    u: &[f64],
    i: &[f64],
    fs: f64,
) -> (crate::checks::NoiseFloor, Vec<crate::checks::Warning>) {
    use crate::checks::{residual_warnings, Warning};
    // The current error over the fitted band only (outside it nothing was fitted, and
    // above fs/3 a simulator's or a converter's band-limiting is not the driver's).
    let i_model = model_current(fit, u, fs);
    let r = filter_record(&i.iter().zip(&i_model).map(|(a, b)| a - b).collect::<Vec<_>>(), fs, |_, f| {
        Complex64::new(if f >= fit.band[0] && f <= fit.band[1] { 1.0 } else { 0.0 }, 0.0)
    });
    let (nf, mut w) = residual_warnings(&r, fs, "linear (small-signal) fit", rms(i), LINEAR_MATERIAL_EXCESS);
    if let Some((tau, share)) = fit.current_delay {
        w.push(Warning::new(
            "current-delay",
            format!(
                "the current channel is {tau:.2} samples {} the voltage ({:.1} us at {fs} Hz): shifting it explains {:.0} % of the fit's error. Channels of one interface sampled apart, or a wiring/latency mistake; the parameters of this fit are biased (Le, L2/R2 most)",
                if tau > 0.0 { "late against" } else { "early against" },
                1e6 * tau.abs() / fs,
                100.0 * share
            ),
        ));
    }
    w.extend(bound_warnings(fit));
    let excess = (nf.rms.powi(2) - nf.floor_rms.powi(2)).max(0.0).sqrt() / rms(i);
    if nf.ratio > 2.0 && excess >= LINEAR_MATERIAL_EXCESS {
        let x = predicted_displacement(p, i, fs);
        let share = large_signal_share(p, &r, i, &x, fs);
        if share > NONLINEAR_SHARE_WARN {
            let (lo, hi) = x.iter().fold((0.0f64, 0.0f64), |(a, b), v| (a.min(*v), b.max(*v)));
            w.push(Warning::new(
                "large-signal-record",
                format!(
                    "this is a large-signal record: x reached {:.2} .. {:.2} mm and the first-order effects of Bl(x), Kms(x) and Le(x) explain {:.0} % of the linear fit's error, so the small-signal parameters are biased (Kms, fs most). Fit it with `coilscope identify`, or record at a lower level (well below 10 % of the rated excursion) for `linear`",
                    lo * 1e3,
                    hi * 1e3,
                    100.0 * share
                ),
            ));
        }
    }
    // An error that follows the drive is a misfit whatever its spectrum's median says: SB17's
    // independent large-signal record through a real chain (AC coupling, skew) gave Re 7.6 %
    // and Kms 20 % off, a 6.8 % error 2.9x its "floor", and no warning (the nonlinearity
    // explained too little of it to call it a large-signal record).
    if !w.iter().any(|w| w.code == "residual-above-noise" || w.code == "large-signal-record") {
        let x = predicted_displacement(p, i, fs);
        w.extend(crate::checks::drive_warning(
            &r,
            u,
            &i_model,
            &x,
            fs,
            "linear (small-signal) fit",
            rms(i),
            LINEAR_MATERIAL_EXCESS,
        ));
    }
    (nf, w)
}

/// A fit that ended on a bound, named.
fn bound_warnings(fit: &LinearFit) -> Vec<crate::checks::Warning> {
    fit.at_bound
        .iter()
        .map(|&b| {
            if b == "Le" {
                return crate::checks::Warning::new(
                    "on-bound",
                    format!(
                        "Le slid toward zero ({:.3e} H, under {:.0} % of the LR-2 model's): the added effects' branch took the voice coil's inductance along a flat direction, so Le, L2 and R2 are not identified; fit with fewer effects",
                        fit.p[1],
                        100.0 * LE_COLLAPSE
                    ),
                );
            }
            crate::checks::Warning::new(
                "on-bound",
                format!(
                    "the fit ended on the bound of {b}: the L2/R2 branch's corner is not between the fitted band's bottom and {CORNER_ABOVE_BAND} times its top ({:.0} .. {:.0} Hz), so L2 and R2 are not identified by this input",
                    fit.band[0],
                    CORNER_ABOVE_BAND * fit.band[1]
                ),
            )
        })
        .collect()
}

/// The RMS relative impedance error above which a fit of an impedance curve is not
/// trusted. A good measurement of a driver that the model describes fits to well under 1 %
/// (the SEAS L16RN-X's .zma to 10 kHz: 0.6 %); cone break-up, a box, or a wrong file leave
/// several percent.
pub const CURVE_RESIDUAL_WARN: f64 = 0.02;

/// The relative sd above which a figure of the resonance fitted from an impedance curve is
/// not identified to the accuracy the README states for curves (Bl 2 %): a good curve gives
/// well under 1 % (|Z| alone up to 0.8 % for Re), a |Z|-only fit in a wrong minimum 5-1e69 %.
pub const FIGURE_SD_WARN: f64 = 0.02;

/// What makes a fit of an impedance curve doubtful: a bound, or a model that misses the
/// curve (a file has no noise floor to compare with: the threshold is
/// [`CURVE_RESIDUAL_WARN`]); the worst point is named.
pub fn curve_warnings(fit: &LinearFit) -> Vec<crate::checks::Warning> {
    let mut w = bound_warnings(fit);
    // The figures of the resonance (Re, Res, Cmes, Lces: Qms, Qts, fs, Bl) must come out
    // determined; a NaN sd counts as undetermined.
    let loose: Vec<String> = [0, 4, 5, 6]
        .iter()
        .filter(|&&k| !(fit.sigma_rel[k] <= FIGURE_SD_WARN))
        .map(|&k| format!("{} ({:.2e})", NAMES[k], fit.sigma_rel[k]))
        .collect();
    if !loose.is_empty() {
        w.push(crate::checks::Warning::new(
            "not-identified",
            format!(
                "the fit leaves {} undetermined (relative sd over {:.0} %): it ended in a wrong minimum, or the curve does not show the resonance; check the file, or fit a band around the resonance (--band LO,HI)",
                loose.join(", "),
                100.0 * FIGURE_SD_WARN
            ),
        ));
    }
    if fit.residual_rel > CURVE_RESIDUAL_WARN {
        let h = &fit.h1;
        let err = |k: usize| fit.point_error(h.f[k], h.z[k]);
        let worst = (0..h.f.len())
            .filter(|&k| h.f[k] >= fit.band[0] && h.f[k] <= fit.band[1])
            .max_by(|&a, &b| err(a).total_cmp(&err(b)));
        let at = worst.map(|k| format!(" (worst {:.1} % at {:.0} Hz)", 100.0 * err(k), h.f[k])).unwrap_or_default();
        w.push(crate::checks::Warning::new(
            "model-misses-curve",
            format!("the model misses the impedance curve by {:.1} % RMS{at}: cone break-up, a box or port, or a curve of something else. Fit a band the model holds in (--band LO,HI below the break-up), or check the file", 100.0 * fit.residual_rel),
        ));
    }
    w
}

/// Share of a linear fit's current error `r` that the first-order (perturbation) effects of
/// the large-signal terms explain. With the linear model's x and v, each nonlinearity adds a
/// voltage in the electrical loop (`x v`, `x^2 v` from Bl(x); `d(x i)/dt`, `d(x^2 i)/dt` from
/// Le(x)), which changes the current by `-e / Z(f)`, or a force on the cone (`x i`, `x^2 i`
/// from Bl(x); `x^2`, `x^3` from Kms(x); `i^2` from Le'(x)), which changes it by
/// `-Bl F / (Ze Zm_total)`. Noise is explained by none of them.
fn large_signal_share(p: &Parameters, r: &[f64], i: &[f64], x: &[f64], fs: f64) -> f64 {
    use crate::checks::explained_share;
    let n = r.len();
    // Central differences (d/dt).
    let d = |s: &[f64]| -> Vec<f64> {
        (0..n).map(|k| (s[(k + 1).min(n - 1)] - s[k.saturating_sub(1)]) * fs / 2.0).collect()
    };
    let v = d(x);
    let (bl, kms, le) = (p.bl.eval(0.0), p.kms.eval(0.0), p.le.eval(0.0));
    let filter = |s: &[f64], voltage: bool| -> Vec<f64> {
        filter_record(s, fs, |k, f| {
            if k == 0 {
                return Complex64::new(0.0, 0.0);
            }
            let jw = Complex64::new(0.0, 2.0 * PI * f);
            let ze = p.re
                + jw * le
                + p.l2r2.as_ref().map_or(Complex64::new(0.0, 0.0), |(l2, r2)| {
                    jw * l2.eval(0.0) * r2.eval(0.0) / (jw * l2.eval(0.0) + r2.eval(0.0))
                });
            let zm = jw * p.mms + p.rms + kms / jw;
            if voltage {
                -1.0 / (ze + bl * bl / zm)
            } else {
                -bl / (ze * (zm + bl * bl / ze))
            }
        })
    };
    let prod = |a: &[f64], b: &[f64]| -> Vec<f64> { a.iter().zip(b).map(|(a, b)| a * b).collect() };
    let x2 = prod(x, x);
    let regressors = vec![
        filter(&prod(x, &v), true),
        filter(&prod(&x2, &v), true),
        filter(&d(&prod(x, i)), true),
        filter(&d(&prod(&x2, i)), true),
        filter(&prod(x, i), false),
        filter(&prod(&x2, i), false),
        filter(&x2, false),
        filter(&prod(&x2, x), false),
        filter(&prod(i, i), false),
    ];
    explained_share(r, &regressors)
}

/// How the absolute scale (Bl) was found.
#[derive(Clone, Debug, PartialEq)]
pub enum ScaleMethod {
    Mms,
    /// `mms_sd_rel`: the relative sd of the Mms it gave, from the two resonances' sds.
    AddedMass {
        added: f64,
        fs_with: f64,
        mms_sd_rel: f64,
    },
    Displacement,
}

/// The identification result (`"format": "coilscope.result/1"`) of a linear fit.
pub fn result(p: &Parameters, fit: &LinearFit, method: &ScaleMethod, x_range: [f64; 2], recording: &str) -> ResultFile {
    let ts = coilscope_core::small_signal::thiele_small(p);
    let sd = |k: usize| fit.sigma_rel[k] * fit.p[k];
    // Relative uncertainties of the derived quantities, first order, independent terms.
    let s = fit.sigma_rel;
    let fs_rel = fs_rel_sd(fit);
    // The scale's own relative sd (added mass: from the resonances; a given Mms is exact).
    let m = match method {
        ScaleMethod::AddedMass { mms_sd_rel, .. } => *mms_sd_rel,
        _ => 0.0,
    };
    let scale = match method {
        ScaleMethod::Mms => Scale { method: "mms".into(), mms: Some(p.mms), ..Default::default() },
        ScaleMethod::AddedMass { added, fs_with, .. } => Scale {
            method: "added-mass".into(),
            added_mass: Some(*added),
            fs_with_mass: Some(*fs_with),
            ..Default::default()
        },
        ScaleMethod::Displacement => Scale { method: "displacement".into(), ..Default::default() },
    };
    let mut unc = Uncertainty::new("standard deviations: cluster-robust sandwich covariance over groups of 16 neighbouring bins (holds when the residual is not white: distortion, model error); the scale input, e.g. Mms, is taken as exact");
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

impl ChainEstimate {
    /// As a result's `chain` (the delay in s at sample rate `fs`).
    pub fn to_chain(&self) -> coilscope_core::chain::Chain {
        let fs = self.fs;
        let mut c = coilscope_core::chain::Chain {
            source: Some("estimated".into()),
            delay_i: self.values[0] / fs,
            hp_u: self.values[1],
            hp_i: self.values[2],
            ..Default::default()
        };
        for (n, key) in ChainTerms::NAMES.iter().enumerate() {
            if self.on[n] {
                c.sd.insert(key.to_string(), if n == 0 { self.sd[0] / fs } else { self.sd[n] });
                c.fitted.push(key.to_string());
            }
        }
        c
    }
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The linear fit names the larger branch LR-2, as `identify` does, its sds moving with
    /// it; one already in that order is left alone.
    #[test]
    fn the_larger_branch_is_named_lr2() {
        let mut p = [3.4, 1.1e-4, 2.7e-4, 0.0725, 72.0, 3.8e-4, 6.3e-2];
        let mut sd = [1e-4, 2e-3, 3e-3, 4e-3, 1e-3, 1e-3, 1e-3];
        let mut lr3 = Some(([5.4e-4, 0.29], [5e-3, 6e-3]));
        assert!(lr3_named_first(&mut p, &mut sd, &mut lr3));
        assert_eq!((p[2], p[3], sd[2], sd[3]), (5.4e-4, 0.29, 5e-3, 6e-3));
        assert_eq!(lr3, Some(([2.7e-4, 0.0725], [3e-3, 4e-3])));
        assert!(!lr3_named_first(&mut p, &mut sd, &mut lr3));
        assert!(!lr3_named_first(&mut p, &mut sd, &mut None));
    }

    /// `ChainFactor::at` (the corners' filter coefficients once per theta) gives what the
    /// chain factor was per bin, each corner through `hp_response`, to the last bit: its
    /// value and its derivatives, every combination of terms on, over random delays, corners
    /// and frequencies.
    #[test]
    fn the_chain_factor_is_hp_response_s() {
        use coilscope_core::chain::hp_response;
        use rand::Rng;
        let mut rng = coilscope_core::excitation::named_rng(3, "linear-test/chain-factor");
        for case in 0..64 {
            let fs = [44100.0, 48000.0, 96000.0][case % 3];
            let terms = ChainTerms { fs, delay: case & 4 == 0, hp_u: case & 8 == 0, hp_i: case & 16 == 0 };
            let th: Vec<f64> = [rng.random_range(-0.6..0.6), rng.random_range(0.0..6.0), rng.random_range(0.0..6.0)]
                .into_iter()
                .zip(terms.on())
                .filter(|(_, on)| *on)
                .map(|(v, _)| v)
                .collect();
            let [tau, fu, fi] = terms.values(&th);
            let c = |tau: f64, fu: f64, fi: f64, f: f64| {
                Complex64::from_polar(1.0, -2.0 * PI * f * tau / fs) * hp_response(fi, f, fs) / hp_response(fu, f, fs)
            };
            let prepared = terms.factor_at(&th);
            for _ in 0..50 {
                let f = rng.random_range(1.0..0.45 * fs);
                let (c0, d) = prepared.at(f, true);
                let h = CHAIN_CORNER_STEP;
                let mut want = vec![];
                if terms.delay {
                    want.push(c(tau, fu, fi, f) * Complex64::new(0.0, -2.0 * PI * f / fs));
                }
                if terms.hp_u {
                    want.push((c(tau, fu + h, fi, f) - c(tau, fu - h, fi, f)) / (2.0 * h));
                }
                if terms.hp_i {
                    want.push((c(tau, fu, fi + h, f) - c(tau, fu, fi - h, f)) / (2.0 * h));
                }
                assert_eq!(c0, c(tau, fu, fi, f), "case {case} at {f} Hz");
                assert_eq!(d, want, "case {case} at {f} Hz");
                assert_eq!(prepared.at(f, false), (c0, vec![]));
            }
        }
    }

    #[test]
    fn analytic_gradient_matches_finite_differences() {
        let p = [3.4, 1.1e-4, 5.4e-4, 0.29, 72.0, 3.8e-4, 6.3e-2];
        for f in [15.0, 32.0, 300.0, 5000.0] {
            let (z, g) = model_impedance_and_gradient(&p, f);
            for k in 0..7 {
                let h = 1e-6_f64;
                let mut a = p;
                let mut b = p;
                a[k] *= h.exp();
                b[k] *= (-h).exp();
                let fd = (model_impedance(&a, f) - model_impedance(&b, f)) / (2.0 * h);
                // Central differences: truncation ~h^2 |g|, round-off ~eps |Z| / h.
                let tol = 1e-6 * g[k].norm() + 1e-9 * z.norm();
                assert!((fd - g[k]).norm() < tol, "{} at {f}: {fd} vs {}", NAMES[k], g[k]);
            }
        }
    }

    #[test]
    fn the_current_error_jacobian_matches_finite_differences_with_transient_and_delay() {
        // Every column of the LM problem (bounded LR-2 corner, the extra effects' unknowns,
        // transient coefficients, the skew check's delay) against central differences of the
        // residual, for each set of effects.
        let p = [3.4, 1.1e-4, 5.4e-4, 0.29, 72.0, 3.8e-4, 6.3e-2];
        let freqs: Vec<f64> = (1..60).map(|k| 3.0 * 1.12f64.powi(k)).collect();
        let u: Vec<Complex64> = freqs
            .iter()
            .enumerate()
            .map(|(k, _)| Complex64::from_polar(1.0 + 0.1 * k as f64, 0.7 * k as f64))
            .collect();
        let i: Vec<Complex64> = freqs.iter().zip(&u).map(|(&f, u)| u / model_impedance(&p, f) * 1.01).collect();
        let w: Vec<f64> = freqs.iter().map(|f| 1.0 / (1.0 + f / 1000.0)).collect();
        let (mut lo, mut hi) = ([f64::NEG_INFINITY; 7], [f64::INFINITY; 7]);
        lo[2] = (1.0 / (2.0 * PI * 20000.0)).ln();
        hi[2] = (1.0 / (2.0 * PI * 3.0)).ln();
        let map = ParamMap { lo, hi };
        // A curve without phase is a curve's problem: unit current and weights, no transient
        // term, no chain.
        for (creep, lr3, magnitude_only) in [
            (false, false, false),
            (true, false, false),
            (false, true, false),
            (true, true, false),
            (false, false, true),
            (true, true, true),
        ] {
            let effects = Effects { creep, lr3, ..Effects::NONE };
            let prob = if magnitude_only {
                CurrentError {
                    f: freqs.clone(),
                    u: u.clone(),
                    i: vec![Complex64::new(1.0, 0.0); freqs.len()],
                    w: vec![1.0; freqs.len()],
                    norm: 3.0,
                    map: map.clone(),
                    omega0: 2.0 * PI * 250.0,
                    n_transient: 0,
                    effects,
                    chain: None,
                    magnitude_only,
                }
            } else {
                CurrentError {
                    f: freqs.clone(),
                    u: u.iter().zip(&w).map(|(u, w)| u * w).collect(),
                    i: i.iter().zip(&w).map(|(i, w)| i * w).collect(),
                    w: w.clone(),
                    norm: 3.0,
                    map: map.clone(),
                    omega0: 2.0 * PI * 250.0,
                    n_transient: N_TRANSIENT,
                    effects,
                    chain: Some(ChainTerms { fs: 48000.0, delay: true, hp_u: true, hp_i: true }),
                    magnitude_only,
                }
            };
            let mut th = map.theta(&ParamMap::q_of(&p));
            if creep {
                th.push(0.06);
            }
            if lr3 {
                th.extend([0.7, (0.8f64).ln()]);
            }
            if !magnitude_only {
                th.extend([0.02, -0.01, 0.005, 0.003, 0.4, 2.0, 3.5]);
            }
            let (_, jac) = prob.residual_jacobian(&th);
            for c in 0..th.len() {
                let h = 1e-6;
                let (mut a, mut b) = (th.clone(), th.clone());
                a[c] += h;
                b[c] -= h;
                let fd = (prob.residual(&a) - prob.residual(&b)) / (2.0 * h);
                let err = (&fd - jac.column(c)).amax();
                assert!(
                    err <= 1e-6 * fd.amax().max(1e-9),
                    "{effects:?}, magnitude only {magnitude_only}: column {c}: {err} of {}",
                    fd.amax()
                );
            }
        }
    }

    /// The fit's impedance with creep and LR-3 is the core's small-signal impedance of the
    /// same parameter set (two codes: the fit's electrical-analogue form and the core's
    /// mechanical form).
    #[test]
    fn impedance_with_effects_equals_the_core_small_signal_impedance() {
        let mut d = coilscope_core::embedded_driver("sb17cac35-4").unwrap();
        let (l2, r2) = (d.l2r2.as_ref().unwrap().0.c[0], d.l2r2.as_ref().unwrap().1.c[0]);
        d.creep = Some(coilscope_core::params::Creep { lambda: 0.07, f_ref: None });
        d.l3r3 = Some((0.6 * l2, 2.5 * r2));
        let bl2 = d.bl.c[0].powi(2);
        let p = [d.re, d.le.c[0], l2, r2, bl2 / d.rms, d.mms / bl2, bl2 / d.kms.c[0]];
        let e = Ext::new(&p, Some(0.07), d.l3r3);
        for f in [2.0, 10.0, 45.0, 100.0, 3000.0, 15000.0] {
            let a = impedance_ext(&p, &e, f).0;
            let b = coilscope_core::small_signal::impedance(&d, f);
            assert!((a - b).norm() < 1e-12 * b.norm(), "{f} Hz: {a} vs {b}");
        }
    }

    #[test]
    fn model_impedance_equals_the_core_small_signal_impedance() {
        let d = coilscope_core::embedded_driver("18wu-4741t-00").unwrap();
        let (l2, r2) = (d.l2r2.as_ref().unwrap().0.c[0], d.l2r2.as_ref().unwrap().1.c[0]);
        let bl2 = d.bl.c[0].powi(2);
        let p = [d.re, d.le.c[0], l2, r2, bl2 / d.rms, d.mms / bl2, bl2 / d.kms.c[0]];
        for f in [10.0, 23.6, 100.0, 3000.0] {
            let a = model_impedance(&p, f);
            let b = coilscope_core::small_signal::impedance(&d, f);
            assert!((a - b).norm() < 1e-12 * b.norm());
        }
    }
}

//! The choice of scheme and steps per sample ([`Stepper`]) from a driver's electrical rates.

use super::*;

/// Largest `|lambda| h` of the stiff electrical mode in an exponential step: the network is
/// integrated exactly, so this limit is for the accuracy of the rest. A stiff driver's
/// current follows the drive up to high frequencies (its Le filters little). Under IEC noise
/// at 90 % of x_range the microspeaker of `testdata/drivers` (`|lambda| / fs` = 10.1) missed
/// the tiny-step reference's current by 1.8e-4 (relative RMS) at 2 steps per sample, 4.0e-5
/// at 3, 1.3e-5 at 4 (its displacement by 8.9e-6, 2.4e-6, 9.1e-7) while the method took the
/// drive into its quadrature (a quadratic over each step); with the drive integrated exactly
/// as the quartic through five band-limited points ([`Drive`]),
/// 4.1e-5, 3.8e-6, 7.1e-7 (displacement 5.3e-6, 1.3e-6, 4.8e-7; `examples/steps`; the
/// second microspeaker, 10.8: 4.1e-5, 3.9e-6, 6.8e-7). The limit takes 3 steps up to
/// `|lambda| / fs` = 12 (were 4 from 9): a current three times closer than at 4 steps
/// before, a displacement within 1.5 times, a quarter fewer evaluations of the model (the
/// independent oracle: current 6.2e-8, displacement 5.7e-7, against 1.1e-7 and 6.1e-7 at 4
/// steps before). With each step's quartic through its own five points (at quarter steps):
/// 5.1e-6, 9.8e-7, 3.0e-7 (displacement unchanged; the second microspeaker
/// 1.2e-6, 1.9e-7, 5.5e-8), and at one step 9.3e-5 (displacement 5.1e-5).
pub const EXP_STIFF_LIMIT: f64 = 4.0;

/// Largest `|lambda| h` of the stiff network's fastest mode per exponential step in a fit's
/// model runs ([`fit_exp_steps_for`]), where [`EXP_STIFF_LIMIT`] holds a simulation's: 2
/// steps per sample up to `|lambda| / fs` = 12 (3 in a simulation).
///
/// Why: a fit's model only has to stay well below the record's noise, and a simulation is
/// the virtual world that tests hold fits to. At 2 steps each step's drive the quartic
/// through its own five points, the microspeakers of `testdata/drivers` (`|lambda| / fs` =
/// 10.1 and 10.8) missed the tiny-step reference's current by 5.1e-6 and 1.2e-6 (relative
/// RMS, IEC noise to 90 % of x_range), their displacement by 5.3e-6 and 1.6e-7
/// (`examples/steps`), 60 times below a 70 dB record's noise and 20 times below the
/// accuracy bar for the current (1e-4). Each residual run then costs two thirds of the evaluations of the model, and
/// the 0.1 g microspeaker's `identify` took 8.3 -> 7.4 s (the stages example) with the same
/// iterations and errors to four digits.
pub const FIT_EXP_STIFF_LIMIT: f64 = 6.0;

/// Largest `|lambda| h` of the fastest mode in a Jacobian's RK4 runs.
pub const JACOBIAN_STIFF_LIMIT: f64 = 1.5;

/// Largest `|lambda| h` of the fastest mode (one step per sample) at which a search stage's
/// Jacobian takes the explicit midpoint rule ([`Stepper::for_search_jacobian`]): inside the
/// rule's stability limit (2) with room, and above the bundled woofers' 0.51-0.83.
pub const SEARCH_MIDPOINT_LIMIT: f64 = 1.0;

/// What one exponential step costs in RK4 sub-steps (the `simulate` bench: 2 exponential
/// steps per sample ran 2.9-3.1 M samples/s, 4 RK4 sub-steps 2.5-2.9 M: 1.8).
pub const EXP_STEP_COST: f64 = 2.0;

/// Fewest exponential steps per sample, for the drive: one step per sample integrates it as a
/// polynomial over the sample, and a woofer's current then misses 2.6e-4 (relative RMS)
/// of the tiny-step reference's under broadband noise, its impedance 1.2e-3 at 8 kHz.
pub const EXP_MIN_STEPS: usize = 2;

/// How fast a parameter set's electrical modes are (1/s), for choosing steps.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rates {
    /// The LR-2 network's fastest eigenvalue, an upper bound: what sets the exponential
    /// method's steps ([`exp_steps_for`]).
    pub stiff: f64,
    /// The LR-3 branch's (`R3 / Le + R3 / L3`; 0 without it): in the exponential method's
    /// network ([`Electrical::network3`]), which integrates it exactly, so it sets no
    /// exponential steps (a microspeaker with a branch 1.5 times as fast as its LR-2
    /// network follows a tiny-step run as closely at 2, 3 and 4 steps as without it; with
    /// the branch outside the network such a set took RK4); classical RK4 must resolve it ([`Rates::total`]).
    pub lr3: f64,
}

impl Rates {
    /// A set without LR-3 whose network's fastest mode is `rate`.
    pub fn stiff(rate: f64) -> Self {
        Rates { stiff: rate, lr3: 0.0 }
    }

    /// The fastest mode overall (what classical RK4 must resolve).
    pub fn total(&self) -> f64 {
        self.stiff + self.lr3
    }
}

/// The integration scheme of a [`Stepper`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Scheme {
    /// Classical RK4 ([`rk4_sample`]).
    #[default]
    Rk4,
    /// The exponential method ([`etd4_sample`]): the electrical network exactly.
    Exponential,
    /// The explicit midpoint rule ([`midpoint_sample`]): the Jacobians of the search stages
    /// ([`Stepper::for_search_jacobian`]), never a model run whose result is kept.
    Midpoint,
    /// The exponential midpoint method ([`etd2_sample`]): a stiff driver's search Jacobians,
    /// never a model run whose result is kept.
    ExpMidpoint,
    /// The current's exponential method ([`etdc_sample`]): the current's decay and the
    /// drive exactly, RK4 for the rest; one step per sample for a woofer.
    ExpCurrent,
}

impl Scheme {
    /// The name result files use: `"rk4"` or `"exponential"`.
    pub fn name(self) -> &'static str {
        match self {
            Scheme::Rk4 => "rk4",
            Scheme::Exponential => "exponential",
            Scheme::Midpoint => "midpoint",
            Scheme::ExpMidpoint => "exponential-midpoint",
            Scheme::ExpCurrent => "exponential-current",
        }
    }

    /// How many intervals of the band-limited input each of `n` steps per sample takes (its
    /// points less one): two (start, midpoint, end), four for [`Scheme::ExpCurrent`] and for
    /// [`Scheme::Exponential`] at two steps or more (each step's drive the quartic through
    /// its own five points).
    pub(super) fn intervals_per_step(self, n: usize) -> usize {
        match self {
            Scheme::ExpCurrent => 4,
            Scheme::Exponential if n > 1 => 4,
            _ => 2,
        }
    }
}

/// How a model advances one sample: the scheme, the steps per sample and the band-limited
/// input at the points they need.
#[derive(Clone, Debug)]
pub struct Stepper {
    pub scheme: Scheme,
    pub(super) n: usize,
    pub(super) interp: Interpolator,
}

impl Stepper {
    /// `n` steps per sample of `scheme`.
    pub fn new(scheme: Scheme, n: usize) -> Self {
        let n = n.max(1);
        Stepper { scheme, n, interp: Interpolator::new(scheme.intervals_per_step(n) / 2 * n) }
    }

    /// The cheaper of the two schemes at the accuracy each is held to: classical RK4 with
    /// [`substeps_for`] sub-steps, unless [`exp_steps_for`] exponential steps cost less
    /// (one costs [`EXP_STEP_COST`] sub-steps). Woofers keep RK4 (2 sub-steps against 2
    /// exponential steps that cost twice as much), stiff microspeakers take the exponential one
    /// (3 steps instead of 21 sub-steps; a fit's model runs 2, [`Stepper::for_fit`]).
    pub fn for_rates(rates: Rates, fs: f64) -> Self {
        Stepper::cheaper(rates, fs, exp_steps_for(rates, fs))
    }

    /// RK4 with [`substeps_for`] sub-steps or `n_exp` exponential steps, whichever costs less.
    pub(super) fn cheaper(rates: Rates, fs: f64, n_exp: usize) -> Self {
        let n_rk = substeps_for(rates.total(), fs);
        if (EXP_STEP_COST * n_exp as f64) < n_rk as f64 {
            Stepper::new(Scheme::Exponential, n_exp)
        } else {
            Stepper::new(Scheme::Rk4, n_rk)
        }
    }

    /// The steps of a Jacobian's runs (dual numbers), where stability and the sensitivities'
    /// direction matter, not the last digit: one RK4 sub-step when the fastest mode allows
    /// it (`|lambda| h <= 1.5`, woofers), else one exponential step (the stiff network
    /// exactly, an LR-3 branch in it).
    pub fn for_jacobian(rates: Rates, fs: f64) -> Self {
        if rates.total() / fs <= JACOBIAN_STIFF_LIMIT {
            Stepper::new(Scheme::Rk4, 1)
        } else {
            Stepper::new(Scheme::Exponential, 1)
        }
    }

    /// The residual and Jacobian steppers of a fit: [`Stepper::for_rates`]'s choice with
    /// [`fit_exp_steps_for`]'s exponential steps (fewer than a simulation's,
    /// [`FIT_EXP_STIFF_LIMIT`]) and [`Stepper::for_jacobian`]. A fitted LR-3 branch is in
    /// the exponential method's network ([`Electrical::network3`]); outside it, a stiff
    /// driver's model with one took RK4 at 21 sub-steps (a fit's vanishing LR-3 start has `R3 / L3
    /// = 6 R2 / L2`, as fast as the
    /// network).
    pub fn for_fit(rates: Rates, fs: f64) -> (Self, Self) {
        (Stepper::cheaper(rates, fs, fit_exp_steps_for(rates, fs)), Stepper::for_jacobian(rates, fs))
    }

    /// Classical RK4 for the model runs and for the Jacobian's, with the sub-steps the
    /// fastest mode needs (`|lambda| h <= STIFF_LIMIT`, at least `MIN_SUBSTEPS`; and
    /// `|lambda| h <= JACOBIAN_STIFF_LIMIT`): the scheme before the exponential one, which the
    /// measurement path (the virtual device, the online estimator) keeps for now.
    pub fn rk4_for(rates: Rates, fs: f64) -> (Self, Self) {
        let n = substeps_for(rates.total(), fs);
        let n_jac = ((rates.total() / fs / JACOBIAN_STIFF_LIMIT).ceil() as usize).clamp(1, n);
        (Stepper::new(Scheme::Rk4, n), Stepper::new(Scheme::Rk4, n_jac))
    }

    /// The steps of a search stage's Jacobian runs ([`Stepper::for_fit`]'s otherwise): one
    /// step per sample of the explicit midpoint rule when the fastest mode allows it
    /// (`|lambda| h <= SEARCH_MIDPOINT_LIMIT`: woofers), two evaluations of the model per
    /// sample instead of RK4's four.
    ///
    /// Why: the search only ranks models and hands its estimate to the final fit, whose
    /// Jacobians stay RK4's (a Jacobian sets the fixed point of the final fit's chord
    /// iterations, and its last one the covariance). The midpoint rule's Jacobian is off a
    /// reference's by up to 15 % in Le(x)'s columns (which the stiff electrical mode
    /// carries: `|lambda| h` = 0.83 on SB17) and 1 % in the mechanical ones, against RK4's
    /// 1 % (`a_search_jacobian_is_near_the_final_fits`): enough for LM's steps, whose gain
    /// ratio the stages' stopping rule checks. On 18WU every search stage ended at the same
    /// error to four digits (order 2 in four iterations instead of three), and `identify`
    /// went 3.41 -> 2.89 s (the stages example), SB17 2.19 -> 1.90 s, PTT4 2.42 -> 2.04 s.
    /// Stiff drivers (the final fit's exponential steps) take the exponential midpoint rule
    /// ([`etd2_sample`], two evaluations instead of five) with the drive's exact integrals:
    /// the microspeaker's columns within 1.7-3.8 % of a reference for Le(x), 3.9-4.6 % for
    /// Bl, Kms, Rms, and its search's iterations unchanged (without those integrals Le(x)
    /// was 30 % off and the search took two more iterations). A fitted LR-3 branch is in
    /// the network of both.
    pub fn for_search_jacobian(rates: Rates, fs: f64) -> Self {
        if rates.total() / fs <= SEARCH_MIDPOINT_LIMIT {
            return Stepper::new(Scheme::Midpoint, 1);
        }
        let fit = Stepper::for_fit(rates, fs).1;
        match fit.scheme {
            Scheme::Exponential => Stepper::new(Scheme::ExpMidpoint, fit.n()),
            _ => fit,
        }
    }

    /// Steps per sample.
    pub fn n(&self) -> usize {
        self.n
    }

    /// How many input points [`Stepper::fill`] writes per sample: `2 n + 1`, or `4 n + 1` for
    /// [`Scheme::ExpCurrent`] and for [`Scheme::Exponential`] at two steps or more.
    pub fn points(&self) -> usize {
        2 * self.interp.n + 1
    }

    /// The input points of sample `m` ([`Interpolator::fill`]), [`Stepper::points`] of them.
    #[inline]
    pub fn fill(&self, u: &[f64], m: usize, out: &mut [f64]) {
        self.interp.fill(u, m, out)
    }

    /// Advance one sample period `dt`; `u_points` from [`Stepper::fill`].
    #[inline]
    pub fn sample<D, S, const N: usize>(&self, sys: &S, y: &[D; N], dt: f64, u_points: &[D]) -> [D; N]
    where
        D: DualNum<Primitive = f64> + Copy,
        S: Electrical<D, N>,
    {
        match self.scheme {
            Scheme::Rk4 => rk4_sample(sys, y, dt, u_points),
            Scheme::Exponential => etd4_sample(sys, y, dt, u_points),
            Scheme::Midpoint => midpoint_sample(sys, y, dt, u_points),
            Scheme::ExpMidpoint => etd2_sample(sys, y, dt, u_points),
            Scheme::ExpCurrent => etdc_sample(sys, y, dt, u_points),
        }
    }
}

/// Exponential steps per sample: the stiff network within [`EXP_STIFF_LIMIT`]; at least
/// [`EXP_MIN_STEPS`].
pub fn exp_steps_for(rates: Rates, fs: f64) -> usize {
    exp_steps_within(rates, fs, EXP_STIFF_LIMIT)
}

/// Exponential steps per sample that keep the stiff network within `stiff_limit`; at least
/// [`EXP_MIN_STEPS`].
pub(super) fn exp_steps_within(rates: Rates, fs: f64, stiff_limit: f64) -> usize {
    let n = (rates.stiff / fs / stiff_limit).ceil();
    (n as usize).clamp(EXP_MIN_STEPS, 4096)
}

/// Exponential steps per sample of a fit's model runs ([`Stepper::for_fit`]): the stiff
/// network within [`FIT_EXP_STIFF_LIMIT`]; at least [`EXP_MIN_STEPS`].
pub fn fit_exp_steps_for(rates: Rates, fs: f64) -> usize {
    exp_steps_within(rates, fs, FIT_EXP_STIFF_LIMIT)
}

/// Sub-steps per sample for a system whose fastest eigenvalue has magnitude `rate` (1/s).
pub fn substeps_for(rate: f64, fs: f64) -> usize {
    let n = (rate / fs / STIFF_LIMIT).ceil();
    (n as usize).clamp(MIN_SUBSTEPS, 4096)
}

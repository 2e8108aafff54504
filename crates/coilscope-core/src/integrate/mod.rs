//! Time integration at the recording rate.
//!
//! Three pieces, each tested against a slow reference:
//!
//! * [`Interpolator`]: the sampled voltage is treated as the samples of a continuous,
//!   band-limited signal (what an ADC or DAC delivers), not a staircase. Values between
//!   samples come from a Kaiser-windowed sinc (`HALF_TAPS` samples each side), exact at the
//!   sample instants, within 1e-6 of the band-limited signal up to fs/3 (16 kHz at 48 kHz)
//!   and within 3 % at 0.42 fs.
//! * [`rk4_sample`]: classical RK4 over `substeps` equal sub-steps per sample. The sub-step
//!   count is chosen per driver from the fastest electrical eigenvalue
//!   ([`crate::params::Parameters::stiffness_rate`]), so that the stiff current equation
//!   (Le/(Re+R2) down to a few microseconds in microspeakers) stays stable *and* accurate at
//!   48 kHz: `|lambda| h <= STIFF_LIMIT` with at least `MIN_SUBSTEPS` sub-steps.
//! * [`etd4_sample`]: an exponential Runge-Kutta method (Hochbruck and
//!   Ostermann's, stiff order 4) that integrates the currents' linear RL network
//!   ([`Electrical`]; with an LR-3 branch the 3 x 3 one, [`Electrical::network3`])
//!   exactly and the rest as a Runge-Kutta method does, so that the steps
//!   follow the drive and the mechanics instead of `Le / (Re + R2)`: a microspeaker needs 3
//!   steps per sample instead of 21 RK4 sub-steps (2 in a fit's model runs,
//!   [`Stepper::for_fit`]).
//!
//! [`Stepper`] holds the choice: [`Stepper::for_rates`] takes whichever of the two costs
//! less at the accuracy each is held to (woofers: RK4 with 2 sub-steps; stiff drivers: the
//! exponential method), [`Stepper::for_jacobian`] the cheap stable one for sensitivities.
//! Everything is generic over the scalar type, so dual numbers carry exact sensitivities of
//! the discretised trajectory (what identification needs).
//!
//! The parts, each in its file: `exponential` (the exponential schemes and the currents'
//! network), `stepper` (the choice of scheme and steps) and `interpolate` (the drive between
//! samples); here, the dynamics' traits and classical RK4.

use num_dual::{Dual64, DualNum, DualSVec64};

mod exponential;
mod interpolate;
mod stepper;
#[cfg(test)]
mod tests;

pub use exponential::*;
pub use interpolate::*;
pub use stepper::*;

/// Smallest derivative lane a long dual-number run keeps ([`FlushTiny`]); far below any
/// sensitivity that matters (a Jacobian's entries are 1e-6 .. 1 of the current per unit of
/// a normalised parameter) and far above the subnormal range (below 2.2e-308).
pub const TINY_LANE: f64 = 1e-280;

/// Sets a dual number's derivative lanes that have decayed below [`TINY_LANE`] to zero;
/// nothing for `f64`. A long run on dual numbers (a Jacobian's pass over a record) calls it on
/// its state after every sample.
///
/// Why: a sensitivity that stops being driven (that of the current to an `Re(t)` knot after
/// the knot's interval) decays through the subnormal range, where the processor takes
/// microcode assists on every operation, and, multiplied by factors close to 1 (a lightly
/// damped mechanical mode), rounds back onto the same subnormal value and stays there. On
/// the microspeaker of `testdata/drivers` the first two knots' lanes of x, v, i and i2 were
/// subnormal for 148 000 and 52 000 of the 240 000 samples of a search window, and that
/// pass took 1.2 s against 0.4 s: the 8 s `identify` went 24.5 -> 10.1 s with them flushed.
/// A lane set to zero from below 1e-280 moves the other lanes by less than 1e-274 (the test
/// `flushed_lanes_only_lose_what_is_below_tiny`), and `identify`'s iterations are the same
/// to the printed digit (the stages example, the microspeaker and 18WU).
pub trait FlushTiny {
    fn flush_tiny(&mut self);
}

/// Every lane of `lanes` below [`TINY_LANE`] set to zero: what [`FlushTiny`] does to a dual
/// number's derivative lanes, and the sensitivity equation's passes to their columns
/// (coilscope-ident's `sensitivity`).
#[inline(always)]
pub fn flush_tiny_lanes(lanes: &mut [f64]) {
    for v in lanes {
        if v.abs() < TINY_LANE {
            *v = 0.0;
        }
    }
}

impl FlushTiny for f64 {
    #[inline(always)]
    fn flush_tiny(&mut self) {}
}

impl FlushTiny for Dual64 {
    #[inline]
    fn flush_tiny(&mut self) {
        if self.eps.abs() < TINY_LANE {
            self.eps = 0.0;
        }
    }
}

impl<const N: usize> FlushTiny for DualSVec64<N> {
    #[inline]
    fn flush_tiny(&mut self) {
        if let Some(e) = self.eps.0.as_mut() {
            flush_tiny_lanes(e.as_mut_slice());
        }
    }
}

impl<const N: usize> FlushTiny for crate::jet::Jet<N> {
    #[inline]
    fn flush_tiny(&mut self) {
        flush_tiny_lanes(&mut self.eps);
    }
}

/// Taps on each side of the interpolation point.
pub const HALF_TAPS: usize = 16;
/// Kaiser window shape.
const KAISER_BETA: f64 = 14.0;
/// Fewest sub-steps per sample, for the accuracy of the forced response at audio frequencies:
/// with `|lambda| h <= STIFF_LIMIT` the current stays within 3e-5 (relative RMS) of a
/// 256-sub-step run under IEC noise at 90 % of x_range (SB17 at 2 sub-steps: 2.6e-5, PTT4 and
/// 18WU 7.5e-6, the large coil 1.2e-6; `examples/steps`), below the accuracy bar for the
/// current (1e-4). Four bought 1.5e-6 for twice the cost; one misses by 1.4-4.9e-4.
pub const MIN_SUBSTEPS: usize = 2;
/// Largest `|lambda| h` allowed for the fastest eigenvalue (RK4's real stability limit: 2.78).
pub const STIFF_LIMIT: f64 = 0.5;

/// A dynamical system `dy/dt = f(y, u)` with `N` states and a scalar input.
pub trait Dynamics<D, const N: usize> {
    fn deriv(&self, y: &[D; N], u: D) -> [D; N];
}

impl<D: DualNum<Primitive = f64> + Copy> Dynamics<D, { crate::model::NSTATE }> for crate::model::Model<D> {
    #[inline]
    fn deriv(&self, y: &[D; crate::model::NSTATE], u: D) -> [D; crate::model::NSTATE] {
        crate::model::Model::deriv(self, y, u)
    }
}

/// [`crate::model::ExtModel`] on its three state vectors: LR-3 only ([`crate::model::NLR3`]),
/// with creep ([`crate::model::NEXT`]), and with a box ([`crate::model::NBOX`]).
macro_rules! ext_model_on {
    ($($n:path),*) => {$(
        impl<D: DualNum<Primitive = f64> + Copy> Dynamics<D, { $n }> for crate::model::ExtModel<D> {
            #[inline]
            fn deriv(&self, y: &[D; $n], u: D) -> [D; $n] {
                crate::model::ExtModel::deriv_n(self, y, u)
            }
        }

        impl<D: DualNum<Primitive = f64> + Copy> Electrical<D, { $n }> for crate::model::ExtModel<D> {
            #[inline]
            fn electrical(&self, y: &[D; $n]) -> [[D; 2]; 2] {
                self.base.electrical_matrix(y[crate::model::idx::X], y[crate::model::idx::TV])
            }

            #[inline]
            fn network3(&self, y: &[D; $n]) -> Option<[[D; 3]; 3]> {
                self.lr3.map(|(l3, r3)| {
                    self.base.electrical_matrix3(y[crate::model::idx::X], y[crate::model::idx::TV], l3, r3)
                })
            }

            #[inline]
            fn input(&self, y: &[D; $n]) -> D {
                self.base.input_gain(y[crate::model::idx::X], y[crate::model::idx::I])
            }

            #[inline]
            fn current_rate_and_input(&self, y: &[D; $n]) -> (D, D) {
                self.base.current_rate_and_gain(y[crate::model::idx::X], y[crate::model::idx::I], y[crate::model::idx::TV])
            }
        }
    )*};
}

ext_model_on!(crate::model::NLR3, crate::model::NEXT, crate::model::NBOX);

impl<D: DualNum<Primitive = f64> + Copy> Electrical<D, { crate::model::NSTATE }> for crate::model::Model<D> {
    #[inline]
    fn electrical(&self, y: &[D; crate::model::NSTATE]) -> [[D; 2]; 2] {
        self.electrical_matrix(y[crate::model::idx::X], y[crate::model::idx::TV])
    }

    #[inline]
    fn input(&self, y: &[D; crate::model::NSTATE]) -> D {
        self.input_gain(y[crate::model::idx::X], y[crate::model::idx::I])
    }

    #[inline]
    fn current_rate_and_input(&self, y: &[D; crate::model::NSTATE]) -> (D, D) {
        self.current_rate_and_gain(y[crate::model::idx::X], y[crate::model::idx::I], y[crate::model::idx::TV])
    }
}

#[inline(always)]
fn axpy<D: DualNum<Primitive = f64> + Copy, const N: usize>(y: &[D; N], a: f64, k: &[D; N]) -> [D; N] {
    std::array::from_fn(|j| y[j] + k[j] * a)
}

/// One classical RK4 step of length `h` with input `u0` at the start, `um` at the midpoint and
/// `u1` at the end.
#[inline]
pub fn rk4_step<D, S, const N: usize>(sys: &S, y: &[D; N], h: f64, u0: D, um: D, u1: D) -> [D; N]
where
    D: DualNum<Primitive = f64> + Copy,
    S: Dynamics<D, N>,
{
    let k1 = sys.deriv(y, u0);
    let k2 = sys.deriv(&axpy(y, 0.5 * h, &k1), um);
    let k3 = sys.deriv(&axpy(y, 0.5 * h, &k2), um);
    let k4 = sys.deriv(&axpy(y, h, &k3), u1);
    std::array::from_fn(|j| y[j] + (k1[j] + (k2[j] + k3[j]) * 2.0 + k4[j]) * (h / 6.0))
}

/// Advance one sample period `dt` in `u_points.len() / 2` RK4 sub-steps. `u_points` holds
/// the input at `t + j dt / (2 n)`, `j = 0 ..= 2 n` (see [`Interpolator::fill`]).
#[inline]
pub fn rk4_sample<D, S, const N: usize>(sys: &S, y: &[D; N], dt: f64, u_points: &[D]) -> [D; N]
where
    D: DualNum<Primitive = f64> + Copy,
    S: Dynamics<D, N>,
{
    steps_over_sample(y, dt, u_points, |y, h, u0, um, u1| rk4_step(sys, y, h, u0, um, u1))
}

/// Advance one sample period `dt` in `u_points.len() / 2` steps of the explicit midpoint
/// rule (second order, two evaluations of the model per step: `y + h f(y + h/2 f(y, u0),
/// um)`), `u_points` as for [`rk4_sample`]. Stable for real `|lambda| h < 2`.
#[inline]
pub fn midpoint_sample<D, S, const N: usize>(sys: &S, y: &[D; N], dt: f64, u_points: &[D]) -> [D; N]
where
    D: DualNum<Primitive = f64> + Copy,
    S: Dynamics<D, N>,
{
    steps_over_sample(y, dt, u_points, |y, h, u0, um, _| {
        let k1 = sys.deriv(y, u0);
        axpy(y, h, &sys.deriv(&axpy(y, 0.5 * h, &k1), um))
    })
}

/// `u_points.len() / 2` equal steps `step(y, h, u0, um, u1)` over one sample period `dt`, the
/// input at each step's start, midpoint and end from `u_points`.
#[inline(always)]
fn steps_over_sample<D: Copy, const N: usize>(
    y: &[D; N],
    dt: f64,
    u_points: &[D],
    step: impl Fn(&[D; N], f64, D, D, D) -> [D; N],
) -> [D; N] {
    let n = (u_points.len() - 1) / 2;
    let h = dt / n as f64;
    let mut y = *y;
    for s in 0..n {
        y = step(&y, h, u_points[2 * s], u_points[2 * s + 1], u_points[2 * s + 2]);
    }
    y
}

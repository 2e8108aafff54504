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

use num_dual::{Dual64, DualNum, DualSVec64};

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

impl<D: DualNum<Primitive = f64> + Copy> Dynamics<D, { crate::model::NLR3 }> for crate::model::ExtModel<D> {
    #[inline]
    fn deriv(&self, y: &[D; crate::model::NLR3], u: D) -> [D; crate::model::NLR3] {
        crate::model::ExtModel::deriv_n(self, y, u)
    }
}

impl<D: DualNum<Primitive = f64> + Copy> Dynamics<D, { crate::model::NEXT }> for crate::model::ExtModel<D> {
    #[inline]
    fn deriv(&self, y: &[D; crate::model::NEXT], u: D) -> [D; crate::model::NEXT] {
        crate::model::ExtModel::deriv(self, y, u)
    }
}

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

impl<D: DualNum<Primitive = f64> + Copy> Electrical<D, { crate::model::NLR3 }> for crate::model::ExtModel<D> {
    #[inline]
    fn electrical(&self, y: &[D; crate::model::NLR3]) -> [[D; 2]; 2] {
        self.base.electrical_matrix(y[crate::model::idx::X], y[crate::model::idx::TV])
    }

    #[inline]
    fn network3(&self, y: &[D; crate::model::NLR3]) -> Option<[[D; 3]; 3]> {
        self.lr3.map(|(l3, r3)| self.base.electrical_matrix3(y[crate::model::idx::X], y[crate::model::idx::TV], l3, r3))
    }

    #[inline]
    fn input(&self, y: &[D; crate::model::NLR3]) -> D {
        self.base.input_gain(y[crate::model::idx::X], y[crate::model::idx::I])
    }

    #[inline]
    fn current_rate_and_input(&self, y: &[D; crate::model::NLR3]) -> (D, D) {
        self.base.current_rate_and_gain(y[crate::model::idx::X], y[crate::model::idx::I], y[crate::model::idx::TV])
    }
}

impl<D: DualNum<Primitive = f64> + Copy> Electrical<D, { crate::model::NEXT }> for crate::model::ExtModel<D> {
    #[inline]
    fn electrical(&self, y: &[D; crate::model::NEXT]) -> [[D; 2]; 2] {
        self.base.electrical_matrix(y[crate::model::idx::X], y[crate::model::idx::TV])
    }

    #[inline]
    fn network3(&self, y: &[D; crate::model::NEXT]) -> Option<[[D; 3]; 3]> {
        self.lr3.map(|(l3, r3)| self.base.electrical_matrix3(y[crate::model::idx::X], y[crate::model::idx::TV], l3, r3))
    }

    #[inline]
    fn input(&self, y: &[D; crate::model::NEXT]) -> D {
        self.base.input_gain(y[crate::model::idx::X], y[crate::model::idx::I])
    }

    #[inline]
    fn current_rate_and_input(&self, y: &[D; crate::model::NEXT]) -> (D, D) {
        self.base.current_rate_and_gain(y[crate::model::idx::X], y[crate::model::idx::I], y[crate::model::idx::TV])
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

/// A system whose stiff part is the linear electrical network of the currents `i` and `i2`
/// (states [`crate::model::idx::I`] and [`crate::model::idx::I2`]): what
/// [`etd4_sample`] integrates exactly.
pub trait Electrical<D, const N: usize>: Dynamics<D, N> {
    /// The matrix `A` (1/s) of `d(i, i2)/dt = A (i, i2) + ...` at state `y`: the current
    /// equations' dependence on the currents through the resistances, without the motional
    /// and nonlinear terms (those stay in the non-stiff remainder).
    fn electrical(&self, y: &[D; N]) -> [[D; 2]; 2];

    /// How the input `u` enters the current `i`'s rate at state `y`: `d(di/dt)/du` (1/H),
    /// `1 / (Le(x) h(i))` in the model. The exponential schemes take the drive's integrals
    /// with it ([`etd4_sample`] with two steps or more per sample, [`etd2_step`]).
    fn input(&self, y: &[D; N]) -> D;

    /// The 3 x 3 network of the currents `i`, `i2` and `i3` when the system has an LR-3
    /// branch (`i3` at [`crate::model::ext_idx::I3`]), which the exponential schemes then
    /// integrate exactly instead of [`Electrical::electrical`]'s 2 x 2; `None` without one.
    #[inline]
    fn network3(&self, _y: &[D; N]) -> Option<[[D; 3]; 3]> {
        None
    }

    /// The current's own rate `A[0][0]` of [`Electrical::electrical`] (1/s) and
    /// [`Electrical::input`] at state `y`, for [`etdc_step`]. The model computes both from
    /// one evaluation of `Le(x)`.
    #[inline]
    fn current_rate_and_input(&self, y: &[D; N]) -> (D, D)
    where
        D: Copy,
    {
        (self.electrical(y)[0][0], self.input(y))
    }
}

/// `1 / k!` for `k = 0 ..= 5`.
const INV_FACT: [f64; 6] = [1.0, 1.0, 0.5, 1.0 / 6.0, 1.0 / 24.0, 1.0 / 120.0];

/// `1 / (j + m)!` for `j = 0 .. 13`: the series of `phi_m`.
const fn series_coefficients(m: usize) -> [f64; 13] {
    let mut f = 1.0;
    let mut k = 2;
    while k <= m {
        f *= k as f64;
        k += 1;
    }
    let mut c = [0.0; 13];
    let mut j = 0;
    while j < 13 {
        c[j] = 1.0 / f;
        f *= (j + m + 1) as f64;
        j += 1;
    }
    c
}

/// `phi_0 .. phi_{K-1}` of a scalar (`K` <= 6): `phi_0 = e^z`, `phi_{k+1}(z) = (phi_k(z) -
/// 1/k!) / z`. Four for the method's coefficients, six with the drive's integrals
/// ([`EtdCoefficients::with_drive`]).
#[inline]
fn phis<D: DualNum<Primitive = f64> + Copy, const K: usize>(z: D) -> [D; K] {
    let mut p = [D::zero(); K];
    if z.re().abs() < 0.5 {
        // phi_{K-1} by its series sum_j z^j / (j + K - 1)! (13 terms: within 1e-16 for
        // |z| < 0.5), the others by the recurrence downwards, which has no cancellation.
        let c: [f64; 13] = const { series_coefficients(K - 1) };
        p[K - 1] = c.iter().rev().fold(D::zero(), |acc, &cj| acc * z + cj);
        for k in (0..K - 1).rev() {
            p[k] = z * p[k + 1] + INV_FACT[k];
        }
    } else {
        // The recurrence upwards loses about log10((k + 1) / |z|) digits per level near
        // |z| = 0.5: phi_5 keeps 1e-12 of itself there, the lower ones more.
        p[0] = z.exp();
        let r = z.recip();
        for k in 1..K {
            p[k] = (p[k - 1] - INV_FACT[k - 1]) * r;
        }
    }
    p
}

/// `phi_0 .. phi_5` at `z` and at `z / 2` ([`etdc_step`]'s), from one exponential:
/// `phi_k(z) = (e^z - sum_{j<k} z^j / j!) / z^k`, each level two operations after `e^{z/2}`
/// (the partial sums and the powers of `1 / z` are ready by then), where the recurrence
/// upwards waits on the level below. Both lose about `log10(k! / |z|^k)` digits at level
/// `k`; below `|z|` = [`PHI_PAIR_SERIES`] both are taken by [`phis`]' series (two Horner
/// chains of 13 terms each). With the series throughout, the step's own arithmetic was 41 %
/// of a simulation's time.
#[inline]
fn phis_and_halves<D: DualNum<Primitive = f64> + Copy>(z: D) -> ([D; 6], [D; 6]) {
    if z.re().abs() < PHI_PAIR_SERIES {
        return (phis(z), phis(z * 0.5));
    }
    let zh = z * 0.5;
    let eh = zh.exp();
    let e = eh * eh;
    let r = z.recip();
    let rh = r * 2.0;
    let (mut full, mut half) = ([e; 6], [eh; 6]);
    // Partial sums of the series and powers of 1/z, independent of the exponential.
    let (mut t, mut th, mut zk, mut zhk, mut rk, mut rhk) =
        (D::zero(), D::zero(), D::one(), D::one(), D::one(), D::one());
    for k in 1..6 {
        t += zk * INV_FACT[k - 1];
        th += zhk * INV_FACT[k - 1];
        zk *= z;
        zhk *= zh;
        rk *= r;
        rhk *= rh;
        full[k] = (e - t) * rk;
        half[k] = (eh - th) * rhk;
    }
    (full, half)
}

/// `|z|` below which [`phis_and_halves`] takes the series: at 0.2, `phi_5(z / 2)` by the
/// recurrence keeps 1e-9 of itself, and it weighs the drive's quartic term.
const PHI_PAIR_SERIES: f64 = 0.2;

/// Scalar functions `g_k` of a 2 x 2 matrix `M`, as `(alpha_k, beta_k)` with
/// `g_k(M) = alpha_k I + beta_k M` (the interpolating polynomial on its two eigenvalues).
/// The eigenvalues are real: `M` is an RL network's `-L^-1 R`, similar to a symmetric matrix.
#[inline]
fn matrix_functions<D: DualNum<Primitive = f64> + Copy, const K: usize>(
    m: &[[D; 2]; 2],
    g: impl Fn(D) -> [D; K],
) -> [(D, D); K] {
    let half_tr = (m[0][0] + m[1][1]) * 0.5;
    let diff = (m[0][0] - m[1][1]) * 0.5;
    let disc = diff * diff + m[0][1] * m[1][0];
    // Half the gap between the eigenvalues; kept away from zero (a vanishing L2 branch):
    // the divided difference then is the derivative's to O(gap^2), times a small M - mu2 I.
    let mut s = if disc.re() > 0.0 { disc.sqrt() } else { D::zero() };
    let floor = 1e-4 * (1.0 + half_tr.re().abs());
    if s.re() < floor {
        s = D::from(floor);
    }
    let (mu1, mu2) = (half_tr + s, half_tr - s);
    let (g1, g2) = (g(mu1), g(mu2));
    let inv_gap = (s * 2.0).recip();
    std::array::from_fn(|k| {
        let beta = (g1[k] - g2[k]) * inv_gap;
        (g2[k] - beta * mu2, beta)
    })
}

/// `p I + q A`: a function of the network matrix `A` (1/s) that is a polynomial of degree
/// one in it (every analytic function of a 2 x 2 matrix is one, `matrix_functions`).
#[derive(Clone, Copy, Debug)]
pub struct Pair<D> {
    p: D,
    q: D,
}

impl<D: DualNum<Primitive = f64> + Copy> Pair<D> {
    /// `(p I + q A) n`, given `an = A n`.
    #[inline(always)]
    fn apply(&self, n: [D; 2], an: [D; 2]) -> [D; 2] {
        [self.p * n[0] + self.q * an[0], self.p * n[1] + self.q * an[1]]
    }

    /// The pair of `c (alpha I + beta (s A))`: a function `(alpha, beta)` of the scaled
    /// matrix `s A` ([`matrix_functions`]), times `c`.
    #[inline(always)]
    fn of(f: (D, D), s: f64, c: f64) -> Self {
        Pair { p: f.0 * c, q: f.1 * (s * c) }
    }

    /// `(p I + q A) (v, 0)`: on a vector in the current `i` alone (the drive's).
    #[inline(always)]
    fn apply_to_current(&self, v: D, a: &[[D; 2]; 2]) -> [D; 2] {
        self.apply([v, D::zero()], [a[0][0] * v, a[1][0] * v])
    }

    #[inline(always)]
    fn plus(self, o: Self) -> Self {
        Pair { p: self.p + o.p, q: self.q + o.q }
    }
}

/// `s a`: the network matrix `a` (1/s) times a step (s).
#[inline(always)]
fn scaled<D: DualNum<Primitive = f64> + Copy>(a: &[[D; 2]; 2], s: f64) -> [[D; 2]; 2] {
    std::array::from_fn(|r| std::array::from_fn(|c| a[r][c] * s))
}

/// A 2 x 2 matrix times a vector.
#[inline(always)]
fn mat_vec<D: DualNum<Primitive = f64> + Copy>(m: &[[D; 2]; 2], v: [D; 2]) -> [D; 2] {
    [v[0] * m[0][0] + v[1] * m[0][1], v[0] * m[1][0] + v[1] * m[1][1]]
}

/// The coefficients of [`etd4_step`] for one network matrix `A` and step `h`: matrix
/// functions of `A h / 2` (the stages at `c = 1/2`) and `A h` (the stage at `c = 1` and the
/// result), each held as the two scalars of `p I + q A` ([`Pair`]: the `a_ij` and `b_i`
/// times `h`, which the step applies to a vector `n` as `p n + q (A n)`, `A n` once per
/// vector), and their values at `A = 0` on the other states. Computed once per sample (`A`
/// frozen at the sample's start) and shared by its steps. In the model's scalar type: a
/// Jacobian's dual numbers carry `A`'s dependence on the unknowns through the exponentials
/// (holding `A` at its value, a valid splitting too, made the microspeaker's final fit
/// crawl: 12 iterations at gain ratios 0.36 instead of 9 at 0.99, for 15 % less per
/// Jacobian).
///
/// Held as pairs: as 2 x 2 matrices the coefficients took a quarter of a
/// stiff driver's Jacobian (8-lane dual numbers: 14 matrices of four, each built from its
/// pair); as pairs the same values to rounding (`pairs_are_the_matrix_coefficients`).
#[derive(Clone, Copy, Debug)]
pub struct EtdCoefficients<D> {
    h: f64,
    a: [[D; 2]; 2],
    e5: Pair<D>,
    e1: Pair<D>,
    a21: Pair<D>,
    a31: Pair<D>,
    a32: Pair<D>,
    a41: Pair<D>,
    a42: Pair<D>,
    a51: Pair<D>,
    a52: Pair<D>,
    a54: Pair<D>,
    b1: Pair<D>,
    b4: Pair<D>,
    b5: Pair<D>,
    /// The drive's integrals over the half step and the step ([`EtdCoefficients::with_drive`]):
    /// `h c^{k+1} k! phi_{k+1}(c M)` for `c = 1/2` and `1`, `k = 0 ..= 4` ([`etd4_step`]).
    drive: Option<([Pair<D>; 5], [Pair<D>; 5])>,
}

impl<D: DualNum<Primitive = f64> + Copy> EtdCoefficients<D> {
    /// The coefficients for the network `a` (1/s) and step `h` (s): Hochbruck and
    /// Ostermann's (Acta Numerica 2010, Eq. 5.19), `phi_{j,i} = phi_j(c_i h A)`.
    #[inline]
    pub fn new(a: &[[D; 2]; 2], h: f64) -> Self {
        let (full, half) = (scaled(a, h), scaled(a, 0.5 * h));
        let [e5, p15, p25, p35] = matrix_functions(&half, phis::<D, 4>);
        let [e1, p11, p21, p31] = matrix_functions(&full, phis::<D, 4>);
        Self::from_functions(a, h, [e5, p15, p25, p35], [e1, p11, p21, p31], None)
    }

    /// [`EtdCoefficients::new`] with the drive's integrals, for steps that take the drive
    /// exactly ([`Drive`]).
    #[inline]
    pub fn with_drive(a: &[[D; 2]; 2], h: f64) -> Self {
        let (full, half) = (scaled(a, h), scaled(a, 0.5 * h));
        let [e5, p15, p25, p35, p45, p55] = matrix_functions(&half, phis::<D, 6>);
        let [e1, p11, p21, p31, p41, p51] = matrix_functions(&full, phis::<D, 6>);
        const FACT: [f64; 5] = [1.0, 1.0, 2.0, 6.0, 24.0];
        const HALF_POW: [f64; 5] = [0.5, 0.25, 0.125, 0.0625, 0.03125];
        let drive_half =
            std::array::from_fn(|k| Pair::of([p15, p25, p35, p45, p55][k], 0.5 * h, h * HALF_POW[k] * FACT[k]));
        let drive_full = std::array::from_fn(|k| Pair::of([p11, p21, p31, p41, p51][k], h, h * FACT[k]));
        Self::from_functions(a, h, [e5, p15, p25, p35], [e1, p11, p21, p31], Some((drive_half, drive_full)))
    }

    #[inline(always)]
    #[allow(clippy::type_complexity)]
    fn from_functions(
        a: &[[D; 2]; 2],
        h: f64,
        [e5, p15, p25, p35]: [(D, D); 4],
        [e1, p11, p21, p31]: [(D, D); 4],
        drive: Option<([Pair<D>; 5], [Pair<D>; 5])>,
    ) -> Self {
        let lin = |f: &[(D, D)], w: &[f64]| -> (D, D) {
            f.iter().zip(w).fold((D::zero(), D::zero()), |acc, (g, &c)| (acc.0 + g.0 * c, acc.1 + g.1 * c))
        };
        // a52 = a53 = phi2(M/2)/2 - phi3(M/2)/2 + phi2(M)/4 - phi3(M): a pair on each matrix.
        let a52h = lin(&[p25, p35], &[0.5, -0.5]);
        let a52f = lin(&[p21, p31], &[0.25, -1.0]);
        // a54 = phi2(M/2)/4 - a52; a51 = phi1(M/2)/2 - 2 a52 - a54.
        let a54h = lin(&[p25, a52h], &[0.25, -1.0]);
        let a54f = lin(&[a52f], &[-1.0]);
        let a51h = lin(&[p15, a52h, a54h], &[0.5, -2.0, -1.0]);
        let a51f = lin(&[a52f, a54f], &[-2.0, -1.0]);
        // `h f(M/2)` and `h f(M)` as pairs on A (M = A h).
        let on_half = |f: (D, D)| Pair::of(f, 0.5 * h, h);
        let on_full = |f: (D, D)| Pair::of(f, h, h);
        EtdCoefficients {
            h,
            a: *a,
            e5: Pair::of(e5, 0.5 * h, 1.0),
            e1: Pair::of(e1, h, 1.0),
            a21: on_half(lin(&[p15], &[0.5])),
            a31: on_half(lin(&[p15, p25], &[0.5, -1.0])),
            a32: on_half(p25),
            a41: on_full(lin(&[p11, p21], &[1.0, -2.0])),
            a42: on_full(p21),
            a51: on_half(a51h).plus(on_full(a51f)),
            a52: on_half(a52h).plus(on_full(a52f)),
            a54: on_half(a54h).plus(on_full(a54f)),
            b1: on_full(lin(&[p11, p21, p31], &[1.0, -3.0, 4.0])),
            b4: on_full(lin(&[p21, p31], &[-1.0, 4.0])),
            b5: on_full(lin(&[p21, p31], &[4.0, -8.0])),
            drive,
        }
    }
}

/// One exponential Runge-Kutta step of length `h`: Hochbruck and Ostermann's five-stage
/// method of stiff order 4 (Acta Numerica 2010, Eq. 5.19). The currents' linear network `A`
/// ([`Electrical::electrical`], frozen over the step) is integrated exactly, the rest
/// (mechanics, heat, the motional and nonlinear terms, the drive) by the method's
/// quadrature; on the states outside the network the step is a five-stage explicit
/// Runge-Kutta method of order 4. The stiff electrical mode then sets no limit on `h`, and
/// the stages stay accurate for the slow states the current drives (Cox and Matthews'
/// four-stage ETDRK4, tried first, has stiff order 2: its stage currents put an error of 3e-4
/// of the peak into a microspeaker's displacement at two steps per sample).
#[inline]
pub fn etd4_step<D, S, const N: usize>(
    sys: &S,
    y: &[D; N],
    k: &EtdCoefficients<D>,
    [u0, um, u1]: [D; 3],
    drive: Option<&Drive<D>>,
) -> [D; N]
where
    D: DualNum<Primitive = f64> + Copy,
    S: Dynamics<D, N>,
{
    use crate::model::idx::I;
    let (a, h) = (&k.a, k.h);
    let (mut ey5, mut ey1) = exponentials_on_currents(y, a, &k.e5, &k.e1);
    // With `drive`: the drive's exact integral to c h added to e^{cM} y on the currents, and
    // the drive (at its start's gain) taken out of N.
    let drive = drive.zip(k.drive.as_ref());
    if let Some((d, (half, full))) = drive {
        let add = |ey: &mut [D; 2], terms: &[Pair<D>; 5]| {
            let (mut p, mut q) = (D::zero(), D::zero());
            for (t, g) in terms.iter().zip(&d.g) {
                p += t.p * *g;
                q += t.q * *g;
            }
            ey[0] += (p + q * a[0][0]) * d.b;
            ey[1] += q * a[1][0] * d.b;
        };
        add(&mut ey5, half);
        add(&mut ey1, full);
    }
    let rest = |s: &[D; N], u: D| {
        let mut r = etd_rest(sys, a, s, u);
        if let Some((dr, _)) = drive {
            let d = dr.b * u;
            r.n[I] -= d;
            r.an[0] -= a[0][0] * d;
            r.an[1] -= a[1][0] * d;
        }
        r
    };
    let n1 = rest(y, u0);
    let s2 = etd_stage(y, h, ey5, &[(&k.a21, 0.5, &n1)]);
    let n2 = rest(&s2, um);
    let s3 = etd_stage(y, h, ey5, &[(&k.a31, 0.0, &n1), (&k.a32, 0.5, &n2)]);
    let n3 = rest(&s3, um);
    // Stages 2 and 3 share their coefficients in stages 4 and 5 (a42 = a43, a52 = a53).
    let n23 = Rest { n: std::array::from_fn(|j| n2.n[j] + n3.n[j]), an: [n2.an[0] + n3.an[0], n2.an[1] + n3.an[1]] };
    let s4 = etd_stage(y, h, ey1, &[(&k.a41, 0.0, &n1), (&k.a42, 0.5, &n23)]);
    let n4 = rest(&s4, u1);
    let s5 = etd_stage(y, h, ey5, &[(&k.a51, 0.25, &n1), (&k.a52, 0.125, &n23), (&k.a54, 0.0, &n4)]);
    let n5 = rest(&s5, um);
    etd_stage(y, h, ey1, &[(&k.b1, 1.0 / 6.0, &n1), (&k.b4, 1.0 / 6.0, &n4), (&k.b5, 2.0 / 3.0, &n5)])
}

/// The drive of one exponential step taken exactly ([`etd4_step`]): how it enters the
/// current's rate (`b`, [`Electrical::input`], frozen at the sample's start) and the step's
/// input as a polynomial `u(t h) = sum_k g_k t^k`, `t` in `[0, 1]`: the quartic through the
/// step's own five band-limited points, at quarter steps ([`etd4_sample`] with two steps per
/// sample or more; with one, the drive stays in the method's quadrature, which is exact for
/// the quadratic through the sample's three points).
#[derive(Clone, Copy, Debug)]
pub struct Drive<D> {
    pub b: D,
    pub g: [D; 5],
}

impl<D: DualNum<Primitive = f64> + Copy> Drive<D> {
    /// The quartic through `w` at `s = 0, 1/2, ..., 2`, in `s`, from [`QUARTIC`]'s weights
    /// ([`etdc_step`] takes it in `s = 2 t`).
    fn quartic(b: D, w: &[D]) -> Self {
        Drive { b, g: std::array::from_fn(|k| (0..5).fold(D::zero(), |acc, j| acc + w[j] * QUARTIC[k][j])) }
    }

    /// The quartic through the step's five points `w` at `t = 0, 1/4, ..., 1`, in `t`:
    /// [`Drive::quartic`] in `s = 2 t`, `g_k` scaled by `2^k` (exactly).
    fn of_step(b: D, w: &[D]) -> Self {
        let mut d = Drive::quartic(b, w);
        let mut scale = 1.0;
        for g in d.g.iter_mut() {
            *g *= scale;
            scale *= 2.0;
        }
        d
    }
}

/// The monomial coefficients of the quartic through five points at `s = j / 2`, `j = 0 ..
/// 4` (rows: `g_k`; columns: the points): the inverse of their Vandermonde matrix, from the
/// Lagrange basis polynomials.
const QUARTIC: [[f64; 5]; 5] = quartic_weights();

const fn quartic_weights() -> [[f64; 5]; 5] {
    let mut out = [[0.0; 5]; 5];
    let mut j = 0;
    while j < 5 {
        // prod_{l != j} (s - s_l) / (s_j - s_l), expanded: `poly` holds the first `len`
        // coefficients.
        let sj = 0.5 * j as f64;
        let (mut poly, mut len, mut denom) = ([0.0; 5], 1, 1.0);
        poly[0] = 1.0;
        let mut l = 0;
        while l < 5 {
            if l != j {
                let sl = 0.5 * l as f64;
                let mut next = [0.0; 5];
                let mut d = 0;
                while d < len {
                    next[d + 1] += poly[d];
                    next[d] -= poly[d] * sl;
                    d += 1;
                }
                poly = next;
                len += 1;
                denom *= sj - sl;
            }
            l += 1;
        }
        let mut k = 0;
        while k < 5 {
            out[k][j] = poly[k] / denom;
            k += 1;
        }
        j += 1;
    }
    out
}

/// The coefficients of [`etd2_step`] (as [`EtdCoefficients`]'s, pairs on `A`): `e^{M/2}`,
/// `e^M`, the stage's `h phi_1(M/2) / 2` and its drive's `h phi_2(M/2) / 2`, the result's `h
/// (phi_1(M) - 2 phi_2(M))`, `2 h phi_2(M)` and its drive's `h (4 phi_3(M) - phi_2(M))`, `M
/// = A h`.
#[derive(Clone, Copy, Debug)]
pub struct Etd2Coefficients<D> {
    h: f64,
    a: [[D; 2]; 2],
    e5: Pair<D>,
    e1: Pair<D>,
    a21: Pair<D>,
    c2: Pair<D>,
    b1: Pair<D>,
    b2: Pair<D>,
    d: Pair<D>,
}

impl<D: DualNum<Primitive = f64> + Copy> Etd2Coefficients<D> {
    #[inline]
    pub fn new(a: &[[D; 2]; 2], h: f64) -> Self {
        let (full, half) = (scaled(a, h), scaled(a, 0.5 * h));
        let [e5, p15, p25, ..] = matrix_functions(&half, phis::<D, 4>);
        let [e1, p11, p21, p31, ..] = matrix_functions(&full, phis::<D, 4>);
        let lin = |f: (D, D), g: (D, D), a: f64, b: f64| (f.0 * a + g.0 * b, f.1 * a + g.1 * b);
        Etd2Coefficients {
            h,
            a: *a,
            e5: Pair::of(e5, 0.5 * h, 1.0),
            e1: Pair::of(e1, h, 1.0),
            a21: Pair::of(p15, 0.5 * h, 0.5 * h),
            c2: Pair::of(p25, 0.5 * h, 0.5 * h),
            b1: Pair::of(lin(p11, p21, 1.0, -2.0), h, h),
            b2: Pair::of(p21, h, 2.0 * h),
            d: Pair::of(lin(p31, p21, 4.0, -1.0), h, h),
        }
    }
}

/// One step of the exponential midpoint method (Hochbruck and Ostermann's two-stage method
/// with `c_2 = 1/2`, Acta Numerica 2010, Section 5.2): the stage `e^{M/2} y + h/2 phi_1(M/2)
/// N(y, u0)`, the result `e^M y + h (phi_1(M) - 2 phi_2(M)) N(y, u0) + 2 h phi_2(M)
/// N(stage, um)`; on the states outside the network it is the explicit midpoint rule
/// ([`midpoint_sample`]). Two evaluations of the model instead of [`etd4_step`]'s five: a
/// stiff driver's search Jacobians ([`Stepper::for_search_jacobian`]), never a model run
/// whose result is kept.
///
/// The drive enters the current's rate as `b u` ([`Electrical::input`], `b` frozen at the
/// step's start), and a stiff current follows it within a fraction of the step: the stage
/// and the result add the exact integrals of the drive's change over them (linear through
/// `u0, um` on the stage, quadratic through `u0, um, u1` on the step), beyond what the two
/// evaluations hold (`u0` and `um`). Without them the stage's current lags the drive, and
/// the microspeaker's Le(x) columns missed a reference's by 30 % (with them 1.7-3.8 %; its
/// mechanical ones 3.9-4.6 %, the midpoint's quadrature of a current that follows the drive).
#[inline]
pub fn etd2_step<D, S, const N: usize>(
    sys: &S,
    y: &[D; N],
    k: &Etd2Coefficients<D>,
    b: D,
    u0: D,
    um: D,
    u1: D,
) -> [D; N]
where
    D: DualNum<Primitive = f64> + Copy,
    S: Dynamics<D, N>,
{
    let (a, h) = (&k.a, k.h);
    let (ey5, ey1) = exponentials_on_currents(y, a, &k.e5, &k.e1);
    let n1 = etd_rest(sys, a, y, u0);
    let stage_drive = k.c2.apply_to_current(b * (um - u0), a);
    let s2 = etd_stage(y, h, [ey5[0] + stage_drive[0], ey5[1] + stage_drive[1]], &[(&k.a21, 0.5, &n1)]);
    let n2 = etd_rest(sys, a, &s2, um);
    let dr = k.d.apply_to_current(b * (u1 - um * 2.0 + u0), a);
    etd_stage(y, h, [ey1[0] + dr[0], ey1[1] + dr[1]], &[(&k.b1, 0.0, &n1), (&k.b2, 1.0, &n2)])
}

/// [`etd2_step`]s over one sample, the network and the input gain frozen at the sample's
/// start.
#[inline]
pub fn etd2_sample<D, S, const N: usize>(sys: &S, y: &[D; N], dt: f64, u_points: &[D]) -> [D; N]
where
    D: DualNum<Primitive = f64> + Copy,
    S: Electrical<D, N>,
{
    if let Some(a) = sys.network3(y) {
        return net::etd2_sample_on(sys, y, dt, u_points, &a);
    }
    let n = (u_points.len() - 1) / 2;
    let k = Etd2Coefficients::new(&sys.electrical(y), dt / n as f64);
    let b = sys.input(y);
    steps_over_sample(y, dt, u_points, |y, _, u0, um, u1| etd2_step(sys, y, &k, b, u0, um, u1))
}

/// `e^{M/2} y` and `e^M y` on the currents (`e5`, `e1` as pairs on `a`): where every stage
/// of an exponential step starts.
#[inline(always)]
fn exponentials_on_currents<D: DualNum<Primitive = f64> + Copy, const N: usize>(
    y: &[D; N],
    a: &[[D; 2]; 2],
    e5: &Pair<D>,
    e1: &Pair<D>,
) -> ([D; 2], [D; 2]) {
    use crate::model::idx::{I, I2};
    let y_el = [y[I], y[I2]];
    let ay = mat_vec(a, y_el);
    (e5.apply(y_el, ay), e1.apply(y_el, ay))
}

/// The non-stiff remainder `N = f - A (i, i2)` of [`etd4_step`] at a stage, with `A N`'s
/// electrical part (what the coefficients' pairs apply to).
struct Rest<D, const N: usize> {
    n: [D; N],
    an: [D; 2],
}

#[inline(always)]
fn etd_rest<D, S, const N: usize>(sys: &S, a: &[[D; 2]; 2], s: &[D; N], u: D) -> Rest<D, N>
where
    D: DualNum<Primitive = f64> + Copy,
    S: Dynamics<D, N>,
{
    use crate::model::idx::{I, I2};
    let mut d = sys.deriv(s, u);
    let (i, i2) = (s[I], s[I2]);
    d[I] -= a[0][0] * i + a[0][1] * i2;
    d[I2] -= a[1][0] * i + a[1][1] * i2;
    let an = mat_vec(a, [d[I], d[I2]]);
    Rest { n: d, an }
}

/// A stage of [`etd4_step`]: `ey` (e^{cM} y on the currents) + sum_j (h a_j) N_j, and on the
/// other states y + h sum_j a_j(0) N_j (`at0`, zero terms left out).
#[inline(always)]
fn etd_stage<D: DualNum<Primitive = f64> + Copy, const N: usize>(
    y: &[D; N],
    h: f64,
    ey: [D; 2],
    terms: &[(&Pair<D>, f64, &Rest<D, N>)],
) -> [D; N] {
    use crate::model::idx::{I, I2};
    let mut s: [D; N] = *y;
    for j in (0..N).filter(|&j| j != I && j != I2) {
        for (_, at0, r) in terms.iter().filter(|t| t.1 != 0.0) {
            s[j] += r.n[j] * (at0 * h);
        }
    }
    let mut el = ey;
    for (coef, _, r) in terms {
        let t = coef.apply([r.n[I], r.n[I2]], r.an);
        el[0] += t[0];
        el[1] += t[1];
    }
    s[I] = el[0];
    s[I2] = el[1];
    s
}

/// [`rk4_sample`] with [`etd4_step`]s, the network and the drive's gain frozen at the
/// sample's start; `u_points` the band-limited input at `4 n + 1` equally spaced points (a
/// [`Stepper`] of [`Scheme::Exponential`] fills them), `n` steps, the drive over each the
/// quartic through its own five points, integrated exactly ([`Drive`]).
#[inline]
pub fn etd4_sample<D, S, const N: usize>(sys: &S, y: &[D; N], dt: f64, u_points: &[D]) -> [D; N]
where
    D: DualNum<Primitive = f64> + Copy,
    S: Electrical<D, N>,
{
    if let Some(a) = sys.network3(y) {
        return net::etd4_sample_on(sys, y, dt, u_points, &a);
    }
    if u_points.len() == 3 {
        // One step on the sample's three points (a Jacobian's runs): the method's own
        // quadrature takes the drive in `N`, exact for the quadratic through them.
        let k = EtdCoefficients::new(&sys.electrical(y), dt);
        return etd4_step(sys, y, &k, [u_points[0], u_points[1], u_points[2]], None);
    }
    let n = (u_points.len() - 1) / 4;
    let k = EtdCoefficients::with_drive(&sys.electrical(y), dt / n as f64);
    let b = sys.input(y);
    let mut y = *y;
    for s in 0..n {
        let w = &u_points[4 * s..4 * s + 5];
        let drive = Drive::of_step(b, w);
        y = etd4_step(sys, &y, &k, [w[0], w[2], w[4]], Some(&drive));
    }
    y
}

/// The exponential schemes on a 3 x 3 network: the currents `i`, `i2` and `i3` of a model
/// with an LR-3 branch ([`Electrical::network3`]), which [`etd4_sample`] and [`etd2_sample`]
/// hand to this module. The same methods as the 2 x 2 network's, written for a network of
/// `M` currents: each function of the network matrix is a polynomial of degree `M - 1` in it
/// ([`net::NetFn`], from its three real eigenvalues, [`net::Network`]). The 2 x 2 network
/// keeps its own code (pairs `p I + q A`): on it this generic code took 13 % longer in the
/// microspeaker's `identify` (5.3 -> 6.0 s, the same iterations), its small arrays of dual
/// numbers moved through memory where the pairs stay in registers.
mod net {
    use super::*;

    /// A network matrix `M` whose scalar functions `g_k` are taken as the coefficients of
    /// `g_k(M) = sum_j c_j M^j`: the 3 x 3 one's ([`matrix_functions3`]), the only size this
    /// module is taken at; the code stays generic over the size (the method does not depend
    /// on it).
    pub trait Network<D, const M: usize> {
        fn functions<const K: usize>(&self, g: impl Fn(D) -> [D; K]) -> [[D; M]; K];
    }

    impl<D: DualNum<Primitive = f64> + Copy> Network<D, 3> for [[D; 3]; 3] {
        #[inline(always)]
        fn functions<const K: usize>(&self, g: impl Fn(D) -> [D; K]) -> [[D; 3]; K] {
            matrix_functions3(self, g)
        }
    }

    /// The three real eigenvalues of a 3 x 3 RL network's matrix `M` (`-L^-1 R`, similar to a
    /// symmetric matrix: its eigenvalues are real), largest first, at least `floor` apart, as
    /// the roots of `det(mu I - M) = mu^3 + T mu^2 + S mu + P`: in `f64` by the trigonometric
    /// solution polished by Newton's method, then one Newton step in `D`, which carries each
    /// root's derivative (`-dP(mu) / P'(mu)`, the implicit function's). Two roots closer than
    /// the floor (the lower one moved to keep it) both take the derivative of the mean of the
    /// three (`-dT / 3`), where their own would divide by `P'` near zero.
    #[inline]
    pub(super) fn eigenvalues3<D: DualNum<Primitive = f64> + Copy>(m: &[[D; 3]; 3]) -> [D; 3] {
        let t = -(m[0][0] + m[1][1] + m[2][2]);
        let s = (m[0][0] * m[1][1] - m[0][1] * m[1][0])
            + (m[0][0] * m[2][2] - m[0][2] * m[2][0])
            + (m[1][1] * m[2][2] - m[1][2] * m[2][1]);
        let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
        let p = -det;
        let (tf, sf, pf) = (t.re(), s.re(), p.re());
        let poly = |x: f64| ((x + tf) * x + sf) * x + pf;
        let slope = |x: f64| (3.0 * x + 2.0 * tf) * x + sf;
        // x = y - T/3: y^3 + a y + b = 0.
        let a = sf - tf * tf / 3.0;
        let b = 2.0 * tf * tf * tf / 27.0 - tf * sf / 3.0 + pf;
        let mut mu = if a < 0.0 {
            let r = 2.0 * (-a / 3.0).sqrt();
            let arg = (3.0 * b / (a * r)).clamp(-1.0, 1.0);
            let phi = arg.acos() / 3.0;
            std::array::from_fn(|k| r * (phi - 2.0 * std::f64::consts::PI * k as f64 / 3.0).cos() - tf / 3.0)
        } else {
            [-tf / 3.0; 3]
        };
        for x in mu.iter_mut() {
            for _ in 0..3 {
                let d = slope(*x);
                if d != 0.0 && d.is_finite() {
                    let next = *x - poly(*x) / d;
                    if next.is_finite() {
                        *x = next;
                    }
                }
            }
        }
        mu.sort_by(|x, y| y.total_cmp(x));
        let floor = 1e-4 * (1.0 + mu.iter().fold(0.0f64, |acc, v| acc.max(v.abs())));
        let mut moved = [false; 3];
        for k in 1..3 {
            if mu[k - 1] - mu[k] < floor {
                mu[k] = mu[k - 1] - floor;
                moved[k] = true;
                moved[k - 1] = true;
            }
        }
        std::array::from_fn(|k| {
            let x = mu[k];
            let d = slope(x);
            let xd = D::from(x);
            if moved[k] || !(d.abs() > 0.0) {
                // The mean's derivative: -dT/3 (T's value part taken out).
                xd - (t - tf) * (1.0 / 3.0)
            } else {
                let pd = ((xd + t) * xd + s) * xd + p;
                xd - pd * (1.0 / d)
            }
        })
    }

    /// Scalar functions `g_k` of a 3 x 3 network matrix `M` as the coefficients `(c0, c1, c2)`
    /// of `g_k(M) = c0 I + c1 M + c2 M^2`: the interpolating polynomial on its three real
    /// eigenvalues ([`eigenvalues3`]) in Newton's form, from the largest (nearest zero) down:
    /// `g[mu1] + g[mu1, mu2] (M - mu1) + g[mu1, mu2, mu3] (M - mu1) (M - mu2)`.
    #[inline]
    pub(super) fn matrix_functions3<D: DualNum<Primitive = f64> + Copy, const K: usize>(
        m: &[[D; 3]; 3],
        g: impl Fn(D) -> [D; K],
    ) -> [[D; 3]; K] {
        let [mu1, mu2, mu3] = eigenvalues3(m);
        let (g1, g2, g3) = (g(mu1), g(mu2), g(mu3));
        let (i12, i23, i13) = ((mu1 - mu2).recip(), (mu2 - mu3).recip(), (mu1 - mu3).recip());
        std::array::from_fn(|k| {
            let f12 = (g1[k] - g2[k]) * i12;
            let f23 = (g2[k] - g3[k]) * i23;
            let f123 = (f12 - f23) * i13;
            [g1[k] - f12 * mu1 + f123 * mu1 * mu2, f12 - f123 * (mu1 + mu2), f123]
        })
    }

    /// `[f(0), f(1), .., f(M - 1)]` for the network's small arrays, built in place
    /// (`std::array::from_fn` on dual numbers was left out of line and moved its arrays
    /// through memcpy).
    #[inline(always)]
    fn build<T: Copy, const M: usize>(mut f: impl FnMut(usize) -> T) -> [T; M] {
        let mut out = [f(0); M];
        for (j, o) in out.iter_mut().enumerate().skip(1) {
            *o = f(j);
        }
        out
    }

    /// `sum_j c_j A^j` (`j < M`): a function of the `M x M` network matrix `A` (1/s), a
    /// polynomial of degree `M - 1` in it (every analytic function of the matrix is one,
    /// [`Network`]). Taken with `M` = 3 (an LR-3 branch); the 2 x 2 network holds its
    /// functions as [`Pair`]s.
    #[derive(Clone, Copy, Debug)]
    pub struct NetFn<D, const M: usize> {
        c: [D; M],
    }

    impl<D: DualNum<Primitive = f64> + Copy, const M: usize> NetFn<D, M> {
        /// `(sum_j c_j A^j) n`, given `kn = [n, A n, A^2 n, ..]` ([`krylov`]).
        #[inline(always)]
        fn apply(&self, kn: &[[D; M]; M]) -> [D; M] {
            build(|r| {
                let mut v = self.c[0] * kn[0][r];
                for j in 1..M {
                    v += self.c[j] * kn[j][r];
                }
                v
            })
        }

        /// `c f(s A)`: a function `f` of the scaled matrix `s A` ([`Network`]), times `c`.
        #[inline(always)]
        fn of(f: [D; M], s: f64, c: f64) -> Self {
            let mut sc = c;
            NetFn {
                c: build(|j| {
                    let v = f[j] * sc;
                    sc *= s;
                    v
                }),
            }
        }

        #[inline(always)]
        fn plus(self, o: Self) -> Self {
            NetFn { c: build(|j| self.c[j] + o.c[j]) }
        }
    }

    /// `s a`: the network matrix `a` (1/s) times a step (s).
    #[inline(always)]
    fn scaled<D: DualNum<Primitive = f64> + Copy, const M: usize>(a: &[[D; M]; M], s: f64) -> [[D; M]; M] {
        build(|r| build(|c| a[r][c] * s))
    }

    /// An M x M matrix times a vector.
    #[inline(always)]
    fn mat_vec<D: DualNum<Primitive = f64> + Copy, const M: usize>(m: &[[D; M]; M], v: [D; M]) -> [D; M] {
        build(|r| {
            let mut s = v[0] * m[r][0];
            for c in 1..M {
                s += v[c] * m[r][c];
            }
            s
        })
    }

    /// `[v, A v, A^2 v, ..]` (`M` vectors): what a [`NetFn`] applies to.
    #[inline(always)]
    fn krylov<D: DualNum<Primitive = f64> + Copy, const M: usize>(a: &[[D; M]; M], v: [D; M]) -> [[D; M]; M] {
        let mut k = [v; M];
        for j in 1..M {
            k[j] = mat_vec(a, k[j - 1]);
        }
        k
    }

    /// The states of the network's currents: `i`, `i2` and, in a 3 x 3 network, `i3`.
    /// A constant (`const { currents::<M>() }` at the call sites), so that the stages index
    /// their states at fixed places.
    const fn currents<const M: usize>() -> [usize; M] {
        use crate::model::{ext_idx::I3, idx::I, idx::I2};
        let all = [I, I2, I3];
        let mut out = [0; M];
        let mut k = 0;
        while k < M {
            out[k] = all[k];
            k += 1;
        }
        out
    }

    #[derive(Clone, Copy, Debug)]
    pub struct EtdCoefficients<D, const M: usize> {
        h: f64,
        a: [[D; M]; M],
        /// `[e, A e, ..]` of the unit vector on the current `i` ([`krylov`]): where the drive enters.
        ke: [[D; M]; M],
        e5: NetFn<D, M>,
        e1: NetFn<D, M>,
        a21: NetFn<D, M>,
        a31: NetFn<D, M>,
        a32: NetFn<D, M>,
        a41: NetFn<D, M>,
        a42: NetFn<D, M>,
        a51: NetFn<D, M>,
        a52: NetFn<D, M>,
        a54: NetFn<D, M>,
        b1: NetFn<D, M>,
        b4: NetFn<D, M>,
        b5: NetFn<D, M>,
        /// The drive's integrals over the half step and the step ([`EtdCoefficients::with_drive`]):
        /// `h c^{k+1} k! phi_{k+1}(c M)` for `c = 1/2` and `1`, `k = 0 ..= 4` ([`etd4_step`]).
        drive: Option<([NetFn<D, M>; 5], [NetFn<D, M>; 5])>,
    }

    /// `[e, A e, ..]` of the unit vector `e` on the current `i` (the first of the network's).
    #[inline(always)]
    fn krylov_of_current<D: DualNum<Primitive = f64> + Copy, const M: usize>(a: &[[D; M]; M]) -> [[D; M]; M] {
        krylov(a, build(|k| if k == 0 { D::one() } else { D::zero() }))
    }

    impl<D: DualNum<Primitive = f64> + Copy, const M: usize> EtdCoefficients<D, M>
    where
        [[D; M]; M]: Network<D, M>,
    {
        /// The coefficients for the network `a` (1/s) and step `h` (s): Hochbruck and
        /// Ostermann's (Acta Numerica 2010, Eq. 5.19), `phi_{j,i} = phi_j(c_i h A)`.
        #[inline]
        pub fn new(a: &[[D; M]; M], h: f64) -> Self {
            let (full, half) = (scaled(a, h), scaled(a, 0.5 * h));
            let [e5, p15, p25, p35] = half.functions(phis::<D, 4>);
            let [e1, p11, p21, p31] = full.functions(phis::<D, 4>);
            Self::from_functions(a, h, [e5, p15, p25, p35], [e1, p11, p21, p31], None)
        }

        /// [`EtdCoefficients::new`] with the drive's integrals, for steps that take the drive
        /// exactly ([`Drive`]).
        #[inline]
        pub fn with_drive(a: &[[D; M]; M], h: f64) -> Self {
            let (full, half) = (scaled(a, h), scaled(a, 0.5 * h));
            let [e5, p15, p25, p35, p45, p55] = half.functions(phis::<D, 6>);
            let [e1, p11, p21, p31, p41, p51] = full.functions(phis::<D, 6>);
            const FACT: [f64; 5] = [1.0, 1.0, 2.0, 6.0, 24.0];
            const HALF_POW: [f64; 5] = [0.5, 0.25, 0.125, 0.0625, 0.03125];
            let drive_half =
                std::array::from_fn(|k| NetFn::of([p15, p25, p35, p45, p55][k], 0.5 * h, h * HALF_POW[k] * FACT[k]));
            let drive_full = std::array::from_fn(|k| NetFn::of([p11, p21, p31, p41, p51][k], h, h * FACT[k]));
            Self::from_functions(a, h, [e5, p15, p25, p35], [e1, p11, p21, p31], Some((drive_half, drive_full)))
        }

        #[inline(always)]
        #[allow(clippy::type_complexity)]
        fn from_functions(
            a: &[[D; M]; M],
            h: f64,
            [e5, p15, p25, p35]: [[D; M]; 4],
            [e1, p11, p21, p31]: [[D; M]; 4],
            drive: Option<([NetFn<D, M>; 5], [NetFn<D, M>; 5])>,
        ) -> Self {
            let lin = |f: &[[D; M]], w: &[f64]| -> [D; M] {
                build(|j| {
                    let mut acc = D::zero();
                    for (g, &c) in f.iter().zip(w) {
                        acc += g[j] * c;
                    }
                    acc
                })
            };
            // a52 = a53 = phi2(M/2)/2 - phi3(M/2)/2 + phi2(M)/4 - phi3(M): a function on each matrix.
            let a52h = lin(&[p25, p35], &[0.5, -0.5]);
            let a52f = lin(&[p21, p31], &[0.25, -1.0]);
            // a54 = phi2(M/2)/4 - a52; a51 = phi1(M/2)/2 - 2 a52 - a54.
            let a54h = lin(&[p25, a52h], &[0.25, -1.0]);
            let a54f = lin(&[a52f], &[-1.0]);
            let a51h = lin(&[p15, a52h, a54h], &[0.5, -2.0, -1.0]);
            let a51f = lin(&[a52f, a54f], &[-2.0, -1.0]);
            // `h f(M/2)` and `h f(M)` as functions of A (M = A h).
            let on_half = |f: [D; M]| NetFn::of(f, 0.5 * h, h);
            let on_full = |f: [D; M]| NetFn::of(f, h, h);
            EtdCoefficients {
                h,
                a: *a,
                ke: krylov_of_current(a),
                e5: NetFn::of(e5, 0.5 * h, 1.0),
                e1: NetFn::of(e1, h, 1.0),
                a21: on_half(lin(&[p15], &[0.5])),
                a31: on_half(lin(&[p15, p25], &[0.5, -1.0])),
                a32: on_half(p25),
                a41: on_full(lin(&[p11, p21], &[1.0, -2.0])),
                a42: on_full(p21),
                a51: on_half(a51h).plus(on_full(a51f)),
                a52: on_half(a52h).plus(on_full(a52f)),
                a54: on_half(a54h).plus(on_full(a54f)),
                b1: on_full(lin(&[p11, p21, p31], &[1.0, -3.0, 4.0])),
                b4: on_full(lin(&[p21, p31], &[-1.0, 4.0])),
                b5: on_full(lin(&[p21, p31], &[4.0, -8.0])),
                drive,
            }
        }
    }

    #[inline]
    pub fn etd4_step<D, S, const N: usize, const M: usize>(
        sys: &S,
        y: &[D; N],
        k: &EtdCoefficients<D, M>,
        [u0, um, u1]: [D; 3],
        drive: Option<&Drive<D>>,
    ) -> [D; N]
    where
        D: DualNum<Primitive = f64> + Copy,
        S: Dynamics<D, N>,
    {
        let (a, h) = (&k.a, k.h);
        let (mut ey5, mut ey1) = exponentials_on_currents(y, a, &k.e5, &k.e1);
        // With `drive`: the drive's exact integral to c h added to e^{cM} y on the currents, and
        // the drive (at its start's gain) taken out of N.
        let drive = drive.zip(k.drive.as_ref());
        if let Some((d, (half, full))) = drive {
            let add = |ey: &mut [D; M], terms: &[NetFn<D, M>; 5]| {
                let mut c = [D::zero(); M];
                for (t, g) in terms.iter().zip(&d.g) {
                    for (cj, tj) in c.iter_mut().zip(&t.c) {
                        *cj += *tj * *g;
                    }
                }
                let v = NetFn { c }.apply(&k.ke);
                for (e, vj) in ey.iter_mut().zip(v) {
                    *e += vj * d.b;
                }
            };
            add(&mut ey5, half);
            add(&mut ey1, full);
        }
        let b = drive.map(|(d, _)| d.b);
        let rest = |s: &[D; N], u: D| etd_rest_driven(sys, a, s, u, b, &k.ke);
        let n1 = rest(y, u0);
        let s2 = etd_stage(y, h, ey5, &[(&k.a21, 0.5, &n1)]);
        let n2 = rest(&s2, um);
        let s3 = etd_stage(y, h, ey5, &[(&k.a31, 0.0, &n1), (&k.a32, 0.5, &n2)]);
        let n3 = rest(&s3, um);
        // Stages 2 and 3 share their coefficients in stages 4 and 5 (a42 = a43, a52 = a53).
        let n23 =
            Rest { n: std::array::from_fn(|j| n2.n[j] + n3.n[j]), kn: build(|q| build(|j| n2.kn[q][j] + n3.kn[q][j])) };
        let s4 = etd_stage(y, h, ey1, &[(&k.a41, 0.0, &n1), (&k.a42, 0.5, &n23)]);
        let n4 = rest(&s4, u1);
        let s5 = etd_stage(y, h, ey5, &[(&k.a51, 0.25, &n1), (&k.a52, 0.125, &n23), (&k.a54, 0.0, &n4)]);
        let n5 = rest(&s5, um);
        etd_stage(y, h, ey1, &[(&k.b1, 1.0 / 6.0, &n1), (&k.b4, 1.0 / 6.0, &n4), (&k.b5, 2.0 / 3.0, &n5)])
    }

    #[derive(Clone, Copy, Debug)]
    pub struct Etd2Coefficients<D, const M: usize> {
        h: f64,
        a: [[D; M]; M],
        ke: [[D; M]; M],
        e5: NetFn<D, M>,
        e1: NetFn<D, M>,
        a21: NetFn<D, M>,
        c2: NetFn<D, M>,
        b1: NetFn<D, M>,
        b2: NetFn<D, M>,
        d: NetFn<D, M>,
    }

    impl<D: DualNum<Primitive = f64> + Copy, const M: usize> Etd2Coefficients<D, M>
    where
        [[D; M]; M]: Network<D, M>,
    {
        #[inline]
        pub fn new(a: &[[D; M]; M], h: f64) -> Self {
            let (full, half) = (scaled(a, h), scaled(a, 0.5 * h));
            let [e5, p15, p25, ..] = half.functions(phis::<D, 4>);
            let [e1, p11, p21, p31, ..] = full.functions(phis::<D, 4>);
            let lin = |f: [D; M], g: [D; M], a: f64, b: f64| -> [D; M] { build(|j| f[j] * a + g[j] * b) };
            Etd2Coefficients {
                h,
                a: *a,
                ke: krylov_of_current(a),
                e5: NetFn::of(e5, 0.5 * h, 1.0),
                e1: NetFn::of(e1, h, 1.0),
                a21: NetFn::of(p15, 0.5 * h, 0.5 * h),
                c2: NetFn::of(p25, 0.5 * h, 0.5 * h),
                b1: NetFn::of(lin(p11, p21, 1.0, -2.0), h, h),
                b2: NetFn::of(p21, h, 2.0 * h),
                d: NetFn::of(lin(p31, p21, 4.0, -1.0), h, h),
            }
        }
    }

    /// `f(A) (v, 0, ..)`: a function of the network on a vector in the current `i` alone (the
    /// drive's), `ke` the Krylov vectors of that current's unit vector ([`krylov_of_current`]).
    #[inline(always)]
    fn on_current<D: DualNum<Primitive = f64> + Copy, const M: usize>(
        ke: &[[D; M]; M],
        f: &NetFn<D, M>,
        v: D,
    ) -> [D; M] {
        let kv: [[D; M]; M] = build(|q| build(|j| ke[q][j] * v));
        f.apply(&kv)
    }

    #[inline]
    pub fn etd2_step<D, S, const N: usize, const M: usize>(
        sys: &S,
        y: &[D; N],
        k: &Etd2Coefficients<D, M>,
        b: D,
        u0: D,
        um: D,
        u1: D,
    ) -> [D; N]
    where
        D: DualNum<Primitive = f64> + Copy,
        S: Dynamics<D, N>,
    {
        let (a, h) = (&k.a, k.h);
        let (ey5, ey1) = exponentials_on_currents(y, a, &k.e5, &k.e1);
        let n1 = etd_rest(sys, a, y, u0);
        let stage_drive = on_current(&k.ke, &k.c2, b * (um - u0));
        let s2 = etd_stage(y, h, build(|j| ey5[j] + stage_drive[j]), &[(&k.a21, 0.5, &n1)]);
        let n2 = etd_rest(sys, a, &s2, um);
        let dr = on_current(&k.ke, &k.d, b * (u1 - um * 2.0 + u0));
        etd_stage(y, h, build(|j| ey1[j] + dr[j]), &[(&k.b1, 0.0, &n1), (&k.b2, 1.0, &n2)])
    }

    #[inline(always)]
    pub(super) fn etd2_sample_on<D, S, const N: usize, const M: usize>(
        sys: &S,
        y: &[D; N],
        dt: f64,
        u_points: &[D],
        a: &[[D; M]; M],
    ) -> [D; N]
    where
        D: DualNum<Primitive = f64> + Copy,
        S: Electrical<D, N>,
        [[D; M]; M]: Network<D, M>,
    {
        let n = (u_points.len() - 1) / 2;
        let k = Etd2Coefficients::new(a, dt / n as f64);
        let b = sys.input(y);
        steps_over_sample(y, dt, u_points, |y, _, u0, um, u1| etd2_step(sys, y, &k, b, u0, um, u1))
    }

    /// `e^{M/2} y` and `e^M y` on the currents (`e5`, `e1` as functions of `a`): where every
    /// stage of an exponential step starts.
    #[inline(always)]
    fn exponentials_on_currents<D: DualNum<Primitive = f64> + Copy, const N: usize, const M: usize>(
        y: &[D; N],
        a: &[[D; M]; M],
        e5: &NetFn<D, M>,
        e1: &NetFn<D, M>,
    ) -> ([D; M], [D; M]) {
        let idx = const { currents::<M>() };
        let ky = krylov(a, build(|k| y[idx[k]]));
        (e5.apply(&ky), e1.apply(&ky))
    }

    /// The non-stiff remainder `N = f - A (i, i2, ..)` of [`etd4_step`] at a stage, with the
    /// Krylov vectors of its currents (`[N_el, A N_el, ..]`, what the coefficients apply to).
    struct Rest<D, const N: usize, const M: usize> {
        n: [D; N],
        kn: [[D; M]; M],
    }

    #[inline(always)]
    fn etd_rest<D, S, const N: usize, const M: usize>(sys: &S, a: &[[D; M]; M], s: &[D; N], u: D) -> Rest<D, N, M>
    where
        D: DualNum<Primitive = f64> + Copy,
        S: Dynamics<D, N>,
    {
        let idx = const { currents::<M>() };
        let mut d = sys.deriv(s, u);
        let linear = mat_vec(a, build(|k| s[idx[k]]));
        for k in 0..M {
            d[idx[k]] -= linear[k];
        }
        let kn = krylov(a, build(|k| d[idx[k]]));
        Rest { n: d, kn }
    }

    /// [`etd_rest`] less the drive `b u` (`b`: its gain, `None`: the drive stays in `N`) on the
    /// current, `ke` the Krylov vectors of that current's unit vector.
    #[inline(always)]
    fn etd_rest_driven<D, S, const N: usize, const M: usize>(
        sys: &S,
        a: &[[D; M]; M],
        s: &[D; N],
        u: D,
        b: Option<D>,
        ke: &[[D; M]; M],
    ) -> Rest<D, N, M>
    where
        D: DualNum<Primitive = f64> + Copy,
        S: Dynamics<D, N>,
    {
        let mut r = etd_rest(sys, a, s, u);
        if let Some(b) = b {
            let d = b * u;
            r.n[crate::model::idx::I] -= d;
            r.kn[0][0] -= d;
            for q in 1..M {
                for j in 0..M {
                    r.kn[q][j] -= ke[q][j] * d;
                }
            }
        }
        r
    }

    /// A stage of [`etd4_step`]: `ey` (e^{cM} y on the currents) + sum_j (h a_j) N_j, and on the
    /// other states y + h sum_j a_j(0) N_j (`at0`, zero terms left out).
    #[inline(always)]
    fn etd_stage<D: DualNum<Primitive = f64> + Copy, const N: usize, const M: usize>(
        y: &[D; N],
        h: f64,
        ey: [D; M],
        terms: &[(&NetFn<D, M>, f64, &Rest<D, N, M>)],
    ) -> [D; N] {
        let idx = const { currents::<M>() };
        let mut s: [D; N] = *y;
        for j in (0..N).filter(|j| !idx.contains(j)) {
            for (_, at0, r) in terms.iter().filter(|t| t.1 != 0.0) {
                s[j] += r.n[j] * (at0 * h);
            }
        }
        let mut el = ey;
        for (coef, _, r) in terms {
            let t = coef.apply(&r.kn);
            for k in 0..M {
                el[k] += t[k];
            }
        }
        for k in 0..M {
            s[idx[k]] = el[k];
        }
        s
    }

    /// [`etd4_sample`] on the network `a` (2 x 2, or 3 x 3 with an LR-3 branch).
    #[inline(always)]
    pub(super) fn etd4_sample_on<D, S, const N: usize, const M: usize>(
        sys: &S,
        y: &[D; N],
        dt: f64,
        u_points: &[D],
        a: &[[D; M]; M],
    ) -> [D; N]
    where
        D: DualNum<Primitive = f64> + Copy,
        S: Electrical<D, N>,
        [[D; M]; M]: Network<D, M>,
    {
        if u_points.len() == 3 {
            // One step on the sample's three points (a Jacobian's runs): the method's own
            // quadrature takes the drive in `N`, exact for the quadratic through them.
            let k = EtdCoefficients::new(a, dt);
            return etd4_step(sys, y, &k, [u_points[0], u_points[1], u_points[2]], None);
        }
        let n = (u_points.len() - 1) / 4;
        let k = EtdCoefficients::with_drive(a, dt / n as f64);
        let b = sys.input(y);
        let mut y = *y;
        for s in 0..n {
            let w = &u_points[4 * s..4 * s + 5];
            let drive = Drive::of_step(b, w);
            y = etd4_step(sys, &y, &k, [w[0], w[2], w[4]], Some(&drive));
        }
        y
    }
}

/// Advance one sample period `dt` in `(u_points.len() - 1) / 4` steps of the current's
/// exponential method ([`etdc_step`]), `u_points` the band-limited input at `4 n + 1`
/// equally spaced points (a [`Stepper`] of [`Scheme::ExpCurrent`] fills them).
#[inline]
pub fn etdc_sample<D, S, const N: usize>(sys: &S, y: &[D; N], dt: f64, u_points: &[D]) -> [D; N]
where
    D: DualNum<Primitive = f64> + Copy,
    S: Electrical<D, N>,
{
    let n = (u_points.len() - 1) / 4;
    let h = dt / n as f64;
    let mut y = *y;
    for s in 0..n {
        let w: [D; 5] = std::array::from_fn(|j| u_points[4 * s + j]);
        y = etdc_step(sys, &y, h, &w);
    }
    y
}

/// One step `h` of the current's exponential method: Cox and Matthews' ETDRK4 (J. Comput.
/// Phys. 176, 2002) with the linear part on the current alone, `c = A[0][0] = -(Re(T) + R2) /
/// Le(x)` of [`Electrical::electrical`] at the step's start, and the drive `b u(t)` (`b` of
/// [`Electrical::input`] at the step's start) integrated exactly as the quartic through the
/// five points `w` at `t = 0, h/4, .., h`. Every other state takes classical RK4's weights,
/// and so does what is left of the current's rate: the
/// motional and nonlinear terms, the LR-2 branch's coupling and the drive's change of `b`
/// over the step.
///
/// Why: a woofer's current decays at `|c| h` = 0.4-0.7 per sample at 48 kHz and follows the
/// drive to 20 kHz. RK4 at one sub-step missed the current of 256 sub-steps by 1.4-4.9e-4
/// (relative RMS under IEC noise at 90 % of the range), at two (eight evaluations of the
/// model, each waiting on the last; what a simulation takes) by 0.7-2.6e-5. The current's
/// own decay taken exactly brought SB17's miss at one step from 4.9e-4 to 2.6e-4 and no
/// other's; the drive's integral did the rest: 1.7-3.9e-6 at one step (four evaluations),
/// 0.5-1.4e-7 at two (`examples/steps`). A quadratic through the sample's three points in
/// its place missed as much as RK4: the drive's band-limited content between the samples
/// is what counts. The displacement stays at RK4's one-step error, 0.7-3.3e-6 (RK4 at two
/// sub-steps: 0.2-1.4e-7): the force `Bl i` enters the mechanics through RK4's quadrature.
///
/// Not for stiff networks: the LR-2 branch's coupling stays in the explicit part (a
/// microspeaker's `R2 / Le` is 7e4 /s), where [`etd4_step`] takes the whole network.
#[inline]
pub fn etdc_step<D, S, const N: usize>(sys: &S, y: &[D; N], h: f64, w: &[D; 5]) -> [D; N]
where
    D: DualNum<Primitive = f64> + Copy,
    S: Electrical<D, N>,
{
    use crate::model::idx::I;
    let (c, b) = sys.current_rate_and_input(y);
    let z = c * h;
    let (full, half) = phis_and_halves(z);
    // The quartic in s = 2 t (t = time / h): points at s = 0, 1/2, .., 2 ([`Drive::quartic`]),
    // u = sum_k gs_k s^k. Its integrals against the current's decay:
    // int_0^h e^{c (h - s)} u = h sum_k gs_k 2^k k! phi_{k+1}(z), and over the first half
    // h/2 sum_k gs_k k! phi_{k+1}(z / 2).
    let g = Drive::quartic(b, w).g;
    let (mut d1, mut dh) = (D::zero(), D::zero());
    for (k, &gs) in g.iter().enumerate() {
        let fact = 1.0 / INV_FACT[k];
        d1 += gs * full[k + 1] * (fact * (1u32 << k) as f64);
        dh += gs * half[k + 1] * fact;
    }
    let (d1, dh) = (d1 * b * h, dh * b * (0.5 * h));
    let (e, eh, q1h) = (full[0], half[0], half[1] * (0.5 * h));
    // The rate less the current's decay and the drive.
    let rest = |s: &[D; N], u: D| {
        let mut d = sys.deriv(s, u);
        d[I] -= c * s[I] + b * u;
        d
    };
    // A half-step stage from `base` on the rate `n`, plus `add` on the current.
    let stage = |base: &[D; N], n: &[D; N], add: D| -> [D; N] {
        std::array::from_fn(|k| if k == I { eh * base[k] + q1h * n[k] + add } else { base[k] + n[k] * (0.5 * h) })
    };
    let n1 = rest(y, w[0]);
    let a = stage(y, &n1, dh);
    let n2 = rest(&a, w[2]);
    let s3 = stage(y, &n2, dh);
    let n3 = rest(&s3, w[2]);
    let n23: [D; N] = std::array::from_fn(|k| n3[k] * 2.0 - n1[k]);
    let s4 = stage(&a, &n23, d1 - eh * dh);
    let n4 = rest(&s4, w[4]);
    let (p1, p2, p3) = (full[1], full[2], full[3]);
    let (b1, b23, b4) = (p1 - p2 * 3.0 + p3 * 4.0, p2 * 2.0 - p3 * 4.0, p3 * 4.0 - p2);
    std::array::from_fn(|k| {
        if k == I {
            e * y[k] + (b1 * n1[k] + b23 * (n2[k] + n3[k]) + b4 * n4[k]) * h + d1
        } else {
            y[k] + (n1[k] + (n2[k] + n3[k]) * 2.0 + n4[k]) * (h / 6.0)
        }
    })
}

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
    fn intervals_per_step(self, n: usize) -> usize {
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
    n: usize,
    interp: Interpolator,
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
    fn cheaper(rates: Rates, fs: f64, n_exp: usize) -> Self {
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
fn exp_steps_within(rates: Rates, fs: f64, stiff_limit: f64) -> usize {
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

fn bessel_i0(x: f64) -> f64 {
    let mut sum = 1.0;
    let mut term = 1.0;
    let q = x * x / 4.0;
    for k in 1..200 {
        term *= q / (k as f64 * k as f64);
        sum += term;
        if term < 1e-17 * sum {
            break;
        }
    }
    sum
}

/// The band-limited interpolation kernel at offset `t` (in samples).
pub fn kernel(t: f64) -> f64 {
    let half = HALF_TAPS as f64;
    if t.abs() >= half {
        return 0.0;
    }
    let sinc = if t == 0.0 { 1.0 } else { (std::f64::consts::PI * t).sin() / (std::f64::consts::PI * t) };
    let r = t / half;
    sinc * bessel_i0(KAISER_BETA * (1.0 - r * r).sqrt()) / bessel_i0(KAISER_BETA)
}

/// Dot product with independent partial sums (vectorisable: no chain of dependent adds).
/// Not inlined: inlined into [`Interpolator::fill`]'s loop, it was vectorised across the
/// rows of weights with a shuffle per tap (26 ns a sample of three points; out of line, 20).
#[inline(never)]
fn dot(a: &[f64; 2 * HALF_TAPS], b: &[f64; 2 * HALF_TAPS]) -> f64 {
    let mut acc = [0.0; 8];
    for (ca, cb) in a.chunks_exact(8).zip(b.chunks_exact(8)) {
        for k in 0..8 {
            acc[k] += ca[k] * cb[k];
        }
    }
    acc.iter().sum()
}

/// Band-limited values of a sampled signal at `2 n` equally spaced points per sample period.
#[derive(Clone, Debug)]
pub struct Interpolator {
    /// Sub-steps per sample (the points are at multiples of `1 / (2 n)` sample).
    pub n: usize,
    /// `weights[j - 1][k]`: weight of sample `m + k + 1 - HALF_TAPS` for the point
    /// `m + j / (2 n)`, `j = 1 .. 2 n - 1`.
    weights: Vec<[f64; 2 * HALF_TAPS]>,
}

impl Interpolator {
    pub fn new(n: usize) -> Self {
        let m = 2 * n;
        let weights = (1..m)
            .map(|j| {
                let tau = j as f64 / m as f64;
                let mut w = [0.0; 2 * HALF_TAPS];
                for (k, wk) in w.iter_mut().enumerate() {
                    let offset = k as f64 + 1.0 - HALF_TAPS as f64; // sample index relative to m
                    *wk = kernel(tau - offset);
                }
                // Exact for DC.
                let s: f64 = w.iter().sum();
                w.iter_mut().for_each(|x| *x /= s);
                w
            })
            .collect();
        Interpolator { n, weights }
    }

    /// Fill `out` (length `2 n + 1`) with the signal at `m + j / (2 n)`, `j = 0 ..= 2 n`.
    /// Samples outside `u` count as zero (the signal is silent before and after).
    pub fn fill(&self, u: &[f64], m: usize, out: &mut [f64]) {
        debug_assert_eq!(out.len(), 2 * self.n + 1);
        let at = |k: isize| if k >= 0 && (k as usize) < u.len() { u[k as usize] } else { 0.0 };
        out[0] = at(m as isize);
        out[2 * self.n] = at(m as isize + 1);
        let start = m as isize + 1 - HALF_TAPS as isize;
        // Inside the record the window is borrowed, not copied; at its ends it is built with
        // zeros.
        let edge: [f64; 2 * HALF_TAPS];
        let win: &[f64; 2 * HALF_TAPS] = match usize::try_from(start).ok().and_then(|s| u.get(s..s + 2 * HALF_TAPS)) {
            Some(w) => w.try_into().expect("window length"),
            None => {
                edge = std::array::from_fn(|k| at(start + k as isize));
                &edge
            }
        };
        for (o, w) in out[1..].iter_mut().zip(&self.weights) {
            *o = dot(w, win);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Decay {
        lambda: f64,
    }
    impl Dynamics<f64, 1> for Decay {
        fn deriv(&self, y: &[f64; 1], u: f64) -> [f64; 1] {
            [-self.lambda * y[0] + u]
        }
    }

    /// `[x, v, i, i2]`: a stiff RL network (`a`, 1/s) driven by `u`, and a spring-mass
    /// system the current pushes (`f = g i`), with a cubic spring to make it nonlinear.
    struct Network {
        a: [[f64; 2]; 2],
        g: f64,
        k3: f64,
    }
    impl<D: DualNum<Primitive = f64> + Copy> Dynamics<D, 4> for Network {
        fn deriv(&self, y: &[D; 4], u: D) -> [D; 4] {
            let [x, v, i, i2] = *y;
            let a = &self.a;
            [
                v,
                i * self.g - x * 4.0e4 - x * x * x * self.k3 - v * 20.0,
                i * a[0][0] + i2 * a[0][1] + u,
                i * a[1][0] + i2 * a[1][1],
            ]
        }
    }
    impl<D: DualNum<Primitive = f64> + Copy> Electrical<D, 4> for Network {
        fn electrical(&self, _: &[D; 4]) -> [[D; 2]; 2] {
            std::array::from_fn(|r| std::array::from_fn(|c| D::from(self.a[r][c])))
        }
        fn input(&self, _: &[D; 4]) -> D {
            D::one()
        }
    }

    fn reference(sys: &Network, y0: [f64; 4], t: f64, u: &dyn Fn(f64) -> f64) -> [f64; 4] {
        let n = 200_000;
        let h = t / n as f64;
        let mut y = y0;
        for k in 0..n {
            let t0 = k as f64 * h;
            y = rk4_step(sys, &y, h, u(t0), u(t0 + 0.5 * h), u(t0 + h));
        }
        y
    }

    /// A microspeaker-like network: eigenvalues about -4.7e5 and -0.9e5 /s.
    const STIFF: [[f64; 2]; 2] = [[-3.2e5, 6.7e4], [1.3e5, -1.3e5]];

    #[test]
    fn an_exponential_step_integrates_a_stiff_network_exactly() {
        // Constant drive, no coupling to the mechanics (g = 0): the currents' solution is
        // e^{Ah} y + A^-1 (e^{Ah} - I) b u, which the method reproduces at any step.
        let sys = Network { a: STIFF, g: 0.0, k3: 0.0 };
        let y0 = [0.0, 0.0, 0.3, -0.1];
        let h = 1.0 / 48000.0; // |lambda| h = 10
        let exact = reference(&sys, y0, h, &|_| 2.0e5);
        let k = EtdCoefficients::new(&sys.electrical(&y0), h);
        let y = etd4_step(&sys, &y0, &k, [2.0e5; 3], None);
        for j in 2..4 {
            assert!((y[j] - exact[j]).abs() < 1e-12 * exact[j].abs().max(1.0), "state {j}: {} vs {}", y[j], exact[j]);
        }
        // RK4 with one step is unstable there (|lambda| h = 10 > 2.78).
        let r = rk4_step(&sys, &y0, h, 2.0e5, 2.0e5, 2.0e5);
        assert!((r[2] - exact[2]).abs() > 1.0, "{}", r[2]);
    }

    /// `phi_k(M)` of a 2 x 2 matrix by its Taylor series `sum_j M^j / (j + k)!` (200 terms):
    /// slow, and obviously the definition.
    fn slow_phi(m: [[f64; 2]; 2], k: usize) -> [[f64; 2]; 2] {
        let mul = |x: [[f64; 2]; 2], y: [[f64; 2]; 2]| -> [[f64; 2]; 2] {
            std::array::from_fn(|r| std::array::from_fn(|c| x[r][0] * y[0][c] + x[r][1] * y[1][c]))
        };
        let mut sum = [[0.0; 2]; 2];
        let mut power = [[1.0, 0.0], [0.0, 1.0]];
        let mut fact: f64 = (1..=k).map(|v| v as f64).product();
        for j in 0..200 {
            for r in 0..2 {
                for c in 0..2 {
                    sum[r][c] += power[r][c] / fact;
                }
            }
            power = mul(power, m);
            fact *= (j + k + 1) as f64;
        }
        sum
    }

    /// The coefficients held as pairs `p I + q A` are Hochbruck and
    /// Ostermann's matrices (Eq. 5.19) computed from the slow series of each `phi_j(c h A)`,
    /// for a microspeaker's network (`|lambda| h` = 10, the closed forms) and a woofer's
    /// (0.3, the series).
    #[test]
    fn pairs_are_the_matrix_coefficients() {
        let h = 1.0 / 48000.0;
        for (a, tol) in [(STIFF, 1e-8), ([[-1.2e4, 2.0e3], [3.0e3, -3.0e3]], 1e-12)] {
            let k = EtdCoefficients::new(&a, h);
            let scaled =
                |c: f64| -> [[f64; 2]; 2] { std::array::from_fn(|r| std::array::from_fn(|j| a[r][j] * c * h)) };
            let ph = |j: usize, c: f64| slow_phi(scaled(c), j);
            let comb = |terms: &[([[f64; 2]; 2], f64)], scale: f64| -> [[f64; 2]; 2] {
                std::array::from_fn(|r| {
                    std::array::from_fn(|c| scale * terms.iter().map(|(m, w)| m[r][c] * w).sum::<f64>())
                })
            };
            let a52 = comb(&[(ph(2, 0.5), 0.5), (ph(3, 1.0), -1.0), (ph(2, 1.0), 0.25), (ph(3, 0.5), -0.5)], 1.0);
            let a54 = comb(&[(ph(2, 0.5), 0.25), (a52, -1.0)], 1.0);
            let a51 = comb(&[(ph(1, 0.5), 0.5), (a52, -2.0), (a54, -1.0)], 1.0);
            let cases: [(&str, &Pair<f64>, [[f64; 2]; 2]); 13] = [
                ("e5", &k.e5, ph(0, 0.5)),
                ("e1", &k.e1, ph(0, 1.0)),
                ("a21", &k.a21, comb(&[(ph(1, 0.5), 0.5)], h)),
                ("a31", &k.a31, comb(&[(ph(1, 0.5), 0.5), (ph(2, 0.5), -1.0)], h)),
                ("a32", &k.a32, comb(&[(ph(2, 0.5), 1.0)], h)),
                ("a41", &k.a41, comb(&[(ph(1, 1.0), 1.0), (ph(2, 1.0), -2.0)], h)),
                ("a42", &k.a42, comb(&[(ph(2, 1.0), 1.0)], h)),
                ("a51", &k.a51, comb(&[(a51, 1.0)], h)),
                ("a52", &k.a52, comb(&[(a52, 1.0)], h)),
                ("a54", &k.a54, comb(&[(a54, 1.0)], h)),
                ("b1", &k.b1, comb(&[(ph(1, 1.0), 1.0), (ph(2, 1.0), -3.0), (ph(3, 1.0), 4.0)], h)),
                ("b4", &k.b4, comb(&[(ph(2, 1.0), -1.0), (ph(3, 1.0), 4.0)], h)),
                ("b5", &k.b5, comb(&[(ph(2, 1.0), 4.0), (ph(3, 1.0), -8.0)], h)),
            ];
            for (name, pair, want) in cases {
                let scale = want.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
                for r in 0..2 {
                    for c in 0..2 {
                        let got = if r == c { pair.p } else { 0.0 } + pair.q * a[r][c];
                        assert!(
                            (got - want[r][c]).abs() <= tol * scale,
                            "{name}[{r}][{c}]: {got:e} vs {:e} (|A h| {:.1})",
                            want[r][c],
                            a[0][0].abs() * h
                        );
                    }
                }
            }
        }
    }

    /// With two steps or more per sample the exponential method takes the drive exactly, as
    /// the quartic through five points of each step (its own, at quarter steps): a stiff
    /// network (`|lambda| h` = 5 per step) under a quartic drive comes out exact, where the
    /// method's own quadrature (one step per sample, the drive in `N`) misses by the
    /// drive's cubic and quartic parts.
    #[test]
    fn the_exponential_method_takes_a_quartic_drive_exactly() {
        let sys = Network { a: STIFF, g: 0.0, k3: 0.0 };
        let y0 = [0.0, 0.0, 0.3, -0.1];
        let dt = 1.0 / 48000.0;
        let u = |t: f64| {
            let s = t / dt;
            2.0e5 * (1.0 - 0.7 * s + 1.9 * s * s - 2.3 * s * s * s + 1.1 * s * s * s * s)
        };
        let exact = reference(&sys, y0, dt, &u);
        for n in [2usize, 3, 5] {
            let pts: Vec<f64> = (0..=4 * n).map(|j| u(j as f64 * dt / (4 * n) as f64)).collect();
            let y = etd4_sample(&sys, &y0, dt, &pts);
            for j in 2..4 {
                assert!(
                    (y[j] - exact[j]).abs() < 1e-10 * exact[j].abs().max(1.0),
                    "{n} steps, state {j}: {} vs {}",
                    y[j],
                    exact[j]
                );
            }
        }
        let pts: Vec<f64> = (0..=2).map(|j| u(j as f64 * dt / 2.0)).collect();
        let one = etd4_sample(&sys, &y0, dt, &pts);
        assert!((one[2] - exact[2]).abs() > 1e-4 * exact[2].abs(), "one step: {} vs {}", one[2], exact[2]);
    }

    /// The current's exponential method takes the current's decay and a
    /// quartic drive exactly: a woofer's current equation alone (`|c| h` = 0.6 per sample, no
    /// coupling) under a quartic drive comes out exact at one step per sample, where RK4
    /// (one sub-step, the drive at three points) misses by the decay's and the drive's
    /// higher terms.
    #[test]
    fn the_current_exponential_method_takes_the_decay_and_a_quartic_drive_exactly() {
        let sys = Network { a: [[-2.9e4, 0.0], [0.0, 0.0]], g: 0.0, k3: 0.0 };
        let y0 = [0.0, 0.0, 0.3, -0.1];
        let dt = 1.0 / 48000.0;
        let u = |t: f64| {
            let s = t / dt;
            2.0e3 * (1.0 - 0.7 * s + 1.9 * s * s - 2.3 * s * s * s + 1.1 * s * s * s * s)
        };
        let exact = reference(&sys, y0, dt, &u);
        for n in [1usize, 2] {
            let pts: Vec<f64> = (0..=4 * n).map(|j| u(j as f64 * dt / (4 * n) as f64)).collect();
            let y = etdc_sample(&sys, &y0, dt, &pts);
            assert!((y[2] - exact[2]).abs() < 1e-12 * exact[2].abs(), "{n} steps: {} vs {}", y[2], exact[2]);
            assert_eq!(y[3], y0[3]);
        }
        let rk = rk4_sample(&sys, &y0, dt, &[u(0.0), u(0.5 * dt), u(dt)]);
        assert!((rk[2] - exact[2]).abs() > 1e-5 * exact[2].abs(), "RK4: {} vs {}", rk[2], exact[2]);
    }

    /// Relative errors (the larger of x's and i's) at 2 ms of 192, 384 and 768 steps of
    /// `step(sys, y, h, [u0, um, u1])` on the stiff network coupled to a nonlinear spring-mass
    /// system under a smooth two-tone drive (192 steps: 10.4 us, `|lambda| h` = 4.9, half a
    /// sample at 48 kHz), against a tiny-step RK4 reference.
    fn coupled_errors(step: impl Fn(&Network, &[f64; 4], f64, [f64; 3]) -> [f64; 4]) -> [f64; 3] {
        let sys = Network { a: STIFF, g: 3.0e3, k3: 2.0e9 };
        let u = |t: f64| {
            4.0e4 * (2.0 * std::f64::consts::PI * 700.0 * t).sin()
                + 1.0e4 * (2.0 * std::f64::consts::PI * 2300.0 * t).cos()
        };
        let t_end = 2.0e-3;
        let y0 = [1e-4, 0.0, 0.0, 0.0];
        let exact = reference(&sys, y0, t_end, &u);
        [192, 384, 768].map(|n: usize| {
            let h = t_end / n as f64;
            let mut y = y0;
            for s in 0..n {
                let t0 = s as f64 * h;
                y = step(&sys, &y, h, [u(t0), u(t0 + 0.5 * h), u(t0 + h)]);
            }
            ((y[0] - exact[0]) / exact[0]).abs().max(((y[2] - exact[2]) / exact[2]).abs())
        })
    }

    #[test]
    fn the_exponential_method_is_fourth_order_on_the_coupled_system() {
        // A smooth drive and the nonlinear mechanics: halving h divides the error by ~16
        // even though |lambda| h stays far above RK4's stability limit.
        let [e1, e2, e3] =
            coupled_errors(|sys, y, h, u| etd4_step(sys, y, &EtdCoefficients::new(&sys.electrical(y), h), u, None));
        assert!(e2 < 1e-5, "{e2:.3e}");
        let (r1, r2) = (e1 / e2, e2 / e3);
        assert!(r1 > 11.0 && r2 > 13.0, "error ratios {r1:.1}, {r2:.1} ({e1:.2e}, {e2:.2e}, {e3:.2e})");
    }

    /// The exponential midpoint rule ([`etd2_step`], the stiff drivers' search Jacobians)
    /// integrates the network exactly under a drive quadratic in time (its drive terms), at
    /// `|lambda| h` = 10; on the coupled nonlinear system it is second order.
    #[test]
    fn the_exponential_midpoint_rule_is_exact_on_the_network_and_second_order() {
        let sys = Network { a: STIFF, g: 0.0, k3: 0.0 };
        let y0 = [0.0, 0.0, 0.3, -0.1];
        let h = 1.0 / 48000.0;
        let u = |t: f64| 2.0e5 + 3.0e9 * t - 4.0e13 * t * t;
        let exact = reference(&sys, y0, h, &u);
        let k = Etd2Coefficients::new(&sys.electrical(&y0), h);
        let y = etd2_step(&sys, &y0, &k, 1.0, u(0.0), u(0.5 * h), u(h));
        for j in 2..4 {
            assert!((y[j] - exact[j]).abs() < 1e-11 * exact[j].abs().max(1.0), "state {j}: {} vs {}", y[j], exact[j]);
        }
        let [e1, e2, e3] = coupled_errors(|sys, y, h, [u0, um, u1]| {
            etd2_step(sys, y, &Etd2Coefficients::new(&sys.electrical(y), h), 1.0, u0, um, u1)
        });
        assert!(e1 < 1e-3, "{e1:.3e}");
        let (r1, r2) = (e1 / e2, e2 / e3);
        assert!(r1 > 3.0 && r2 > 3.5, "error ratios {r1:.1}, {r2:.1} ({e1:.2e}, {e2:.2e}, {e3:.2e})");
    }

    /// `[x, v, i, i2, -, -, i3]` (the currents where [`crate::model::ExtModel`] keeps them):
    /// a stiff 3 x 3 RL network (`a`, 1/s; the LR-3 branch's current `i3`) driven by `u`,
    /// and the spring-mass system the current pushes, as [`Network`].
    struct Network3<D> {
        a: [[D; 3]; 3],
        g: f64,
        k3: f64,
    }
    impl<D: DualNum<Primitive = f64> + Copy> Dynamics<D, 7> for Network3<D> {
        fn deriv(&self, y: &[D; 7], u: D) -> [D; 7] {
            let [x, v, i, i2, _, _, i3] = *y;
            let a = &self.a;
            let z = D::zero();
            [
                v,
                i * self.g - x * 4.0e4 - x * x * x * self.k3 - v * 20.0,
                a[0][0] * i + a[0][1] * i2 + a[0][2] * i3 + u,
                a[1][0] * i + a[1][1] * i2 + a[1][2] * i3,
                z,
                z,
                a[2][0] * i + a[2][1] * i2 + a[2][2] * i3,
            ]
        }
    }
    impl<D: DualNum<Primitive = f64> + Copy> Electrical<D, 7> for Network3<D> {
        fn electrical(&self, _: &[D; 7]) -> [[D; 2]; 2] {
            unreachable!("the 3 x 3 network is taken")
        }
        fn network3(&self, _: &[D; 7]) -> Option<[[D; 3]; 3]> {
            Some(self.a)
        }
        fn input(&self, _: &[D; 7]) -> D {
            D::one()
        }
    }

    /// `-L^-1 R` of a microspeaker with an LR-3 branch (Le 30 uH, L2 15 uH, L3 5 uH, Re 7.5,
    /// R2 2, R3 `r3` ohm): eigenvalues about -7e5, -3.5e5 and -0.6e5 /s with `r3` = 3, so
    /// `|lambda| h` up to 15 at 48 kHz.
    fn lr3_network<D: DualNum<Primitive = f64> + Copy>(r3: D) -> [[D; 3]; 3] {
        let (le, l2, l3, re, r2) = (30e-6, 15e-6, 5e-6, 7.5, 2.0);
        let z = D::zero();
        [
            [-(r3 + (re + r2)) / le, D::from(r2 / le), r3 / le],
            [D::from(r2 / l2), D::from(-r2 / l2), z],
            [r3 / l3, z, -r3 / l3],
        ]
    }

    fn reference3<D: DualNum<Primitive = f64> + Copy>(
        sys: &Network3<D>,
        y0: [D; 7],
        t: f64,
        u: &dyn Fn(f64) -> f64,
    ) -> [D; 7] {
        let n = 200_000;
        let h = t / n as f64;
        let mut y = y0;
        for k in 0..n {
            let t0 = k as f64 * h;
            y = rk4_step(sys, &y, h, D::from(u(t0)), D::from(u(t0 + 0.5 * h)), D::from(u(t0 + h)));
        }
        y
    }

    /// The three eigenvalues of an LR-3 network's matrix are the roots
    /// of its characteristic polynomial (to 1e-12 of the largest), in order, with the trace
    /// and the determinant theirs, and their dual parts the roots' derivatives (central
    /// differences); also with two branches of the same time constant and with a vanishing
    /// one (R3 1e-6 ohm), where two roots nearly meet.
    #[test]
    fn the_lr3_networks_eigenvalues_are_its_characteristic_roots() {
        for r3 in [3.0, 0.5, 1e-6] {
            for (name, a) in [
                ("microspeaker", lr3_network(Dual64::from(r3).derivative())),
                ("equal corners", {
                    let mut a = lr3_network(Dual64::from(r3).derivative());
                    // L3 = L2 R3 / R2: the branches' time constants equal.
                    let g = a[1][0];
                    a[2][0] = g;
                    a[2][2] = -g;
                    a
                }),
            ] {
                let mu = net::eigenvalues3(&a);
                let af: [[f64; 3]; 3] = std::array::from_fn(|r| std::array::from_fn(|c| a[r][c].re));
                let big = mu.iter().fold(0.0f64, |m, v| m.max(v.re.abs()));
                assert!(mu[0].re >= mu[1].re && mu[1].re >= mu[2].re, "{name} {r3}: order {mu:?}");
                let tr = af[0][0] + af[1][1] + af[2][2];
                assert!((mu.iter().map(|v| v.re).sum::<f64>() - tr).abs() < 1e-12 * big, "{name} {r3}: trace");
                let det = af[0][0] * (af[1][1] * af[2][2] - af[1][2] * af[2][1])
                    - af[0][1] * (af[1][0] * af[2][2] - af[1][2] * af[2][0])
                    + af[0][2] * (af[1][0] * af[2][1] - af[1][1] * af[2][0]);
                assert!((mu.iter().map(|v| v.re).product::<f64>() - det).abs() < 1e-9 * det.abs(), "{name} {r3}: det");
                // The derivatives d mu / d R3 against central differences of the f64 roots.
                let roots = |r: f64| {
                    let mut m = lr3_network(r);
                    if name == "equal corners" {
                        let g = m[1][0];
                        m[2][0] = g;
                        m[2][2] = -g;
                    }
                    net::eigenvalues3(&m)
                };
                let d = 1e-6 * r3;
                let (hi, lo) = (roots(r3 + d), roots(r3 - d));
                for k in 0..3 {
                    let fd = (hi[k] - lo[k]) / (2.0 * d);
                    let scale = (big / r3).max(fd.abs());
                    assert!((mu[k].eps - fd).abs() < 1e-4 * scale, "{name} {r3}: d mu{k}/dR3 {} vs {fd}", mu[k].eps);
                }
            }
        }
    }

    /// With an LR-3 branch the exponential method integrates the 3 x 3
    /// network of `i`, `i2` and `i3` exactly (a constant drive, no mechanics: `|lambda| h` =
    /// 15, where one RK4 step diverges), and takes a quartic drive exactly at two steps or
    /// more, as the 2 x 2 network's tests above; the exponential midpoint rule (a stiff
    /// driver's search Jacobians) too, under a drive quadratic in time.
    #[test]
    fn an_exponential_step_integrates_a_stiff_lr3_network_exactly() {
        let sys = Network3 { a: lr3_network(3.0), g: 0.0, k3: 0.0 };
        let y0 = [0.0, 0.0, 0.3, -0.1, 0.0, 0.0, 0.2];
        let dt = 1.0 / 48000.0;
        let states = [2, 3, 6];
        let check = |y: &[f64; 7], exact: &[f64; 7], tol: f64, what: &str| {
            for j in states {
                assert!(
                    (y[j] - exact[j]).abs() < tol * exact[j].abs().max(1.0),
                    "{what}, state {j}: {} vs {}",
                    y[j],
                    exact[j]
                );
            }
        };
        let exact = reference3(&sys, y0, dt, &|_| 2.0e5);
        check(&etd4_sample(&sys, &y0, dt, &[2.0e5; 3]), &exact, 1e-12, "one step, constant drive");
        let r = rk4_step(&sys, &y0, dt, 2.0e5, 2.0e5, 2.0e5);
        assert!((r[2] - exact[2]).abs() > 1.0, "one RK4 step: {}", r[2]);
        let u = |t: f64| {
            let s = t / dt;
            2.0e5 * (1.0 - 0.7 * s + 1.9 * s * s - 2.3 * s * s * s + 1.1 * s * s * s * s)
        };
        let exact = reference3(&sys, y0, dt, &u);
        for n in [2usize, 3, 5] {
            let pts: Vec<f64> = (0..=4 * n).map(|j| u(j as f64 * dt / (4 * n) as f64)).collect();
            check(&etd4_sample(&sys, &y0, dt, &pts), &exact, 1e-10, &format!("{n} steps, quartic drive"));
        }
        let q = |t: f64| 2.0e5 + 3.0e9 * t - 4.0e13 * t * t;
        let exact = reference3(&sys, y0, dt, &q);
        check(
            &etd2_sample(&sys, &y0, dt, &[q(0.0), q(0.5 * dt), q(dt)]),
            &exact,
            1e-11,
            "exponential midpoint, quadratic drive",
        );
    }

    /// On the LR-3 network coupled to the nonlinear mechanics the
    /// exponential method stays fourth order (`|lambda| h` from 7.5 down to 1.9), the
    /// exponential midpoint rule second order; and dual numbers through a sample's steps
    /// carry the sensitivity to R3 (against central differences), through the eigenvalues'
    /// derivatives.
    #[test]
    fn the_exponential_method_is_fourth_order_with_an_lr3_branch_and_carries_its_sensitivity() {
        let sys = Network3 { a: lr3_network(3.0), g: 3.0e3, k3: 2.0e9 };
        let u = |t: f64| {
            4.0e4 * (2.0 * std::f64::consts::PI * 700.0 * t).sin()
                + 1.0e4 * (2.0 * std::f64::consts::PI * 2300.0 * t).cos()
        };
        let t_end = 2.0e-3;
        let y0 = [1e-4, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let exact = reference3(&sys, y0, t_end, &u);
        let errors = |sample: &dyn Fn(&[f64; 7], f64, &[f64]) -> [f64; 7], pts: usize| {
            [192usize, 384, 768, 1536].map(|n| {
                let h = t_end / n as f64;
                let mut y = y0;
                for s in 0..n {
                    let t0 = s as f64 * h;
                    let p: Vec<f64> = (0..pts).map(|j| u(t0 + h * j as f64 / (pts - 1) as f64)).collect();
                    y = sample(&y, h, &p);
                }
                ((y[0] - exact[0]) / exact[0])
                    .abs()
                    .max(((y[2] - exact[2]) / exact[2]).abs())
                    .max(((y[6] - exact[6]) / exact[6]).abs())
            })
        };
        let [e1, e2, e3, e4] = errors(&|y, h, p| etd4_sample(&sys, y, h, p), 3);
        // (Measured: 7.4e-5, 8.5e-6, 6.8e-7, 4.6e-8: ratios 8.6, 12.5, 14.9 as |lambda| h
        // falls from 7.3 to 0.9, the 2 x 2 network's fastest mode being half as fast.)
        assert!(e2 < 1e-5, "{e2:.3e}");
        assert!(
            e1 / e2 > 7.0 && e2 / e3 > 11.0 && e3 / e4 > 13.0,
            "exponential: {e1:.2e}, {e2:.2e}, {e3:.2e}, {e4:.2e}"
        );
        let [m1, m2, m3, m4] = errors(&|y, h, p| etd2_sample(&sys, y, h, p), 3);
        assert!(
            m1 < 1e-3 && m1 / m2 > 3.0 && m2 / m3 > 3.5 && m3 / m4 > 3.5,
            "exponential midpoint: {m1:.2e}, {m2:.2e}, {m3:.2e}, {m4:.2e}"
        );
        // d(state)/dR3 over ten samples of two steps.
        let dt = 1.0 / 48000.0;
        let run = |r3: Dual64| {
            let sys = Network3 { a: lr3_network(r3), g: 3.0e3, k3: 2.0e9 };
            let mut y: [Dual64; 7] = [Dual64::from(0.0); 7];
            for m in 0..10 {
                let pts: Vec<Dual64> = (0..=8).map(|j| Dual64::from(u((m as f64 + j as f64 / 8.0) * dt))).collect();
                y = etd4_sample(&sys, &y, dt, &pts);
            }
            y
        };
        let exact = run(Dual64::from(3.0).derivative());
        let d = 1e-5;
        let (hi, lo) = (run(Dual64::from(3.0 + d)), run(Dual64::from(3.0 - d)));
        for j in [0, 2, 3, 6] {
            let fd = (hi[j].re - lo[j].re) / (2.0 * d);
            assert!((exact[j].eps - fd).abs() < 1e-5 * fd.abs(), "state {j}: {} vs {fd}", exact[j].eps);
        }
    }

    #[test]
    fn the_scalar_phi_functions_agree_across_their_two_evaluations() {
        // The series (|z| < 0.5) and the closed forms meet without a jump, and match
        // phi_k(z) = sum_j z^j / (j + k)! computed slowly.
        for z in [-0.5f64 - 1e-12, -0.5 + 1e-12, 0.4999999, 0.5000001, -0.2, 1e-9, -3.0, -40.0] {
            let (p, p4): ([f64; 6], [f64; 4]) = (phis(z), phis(z));
            for k in 0..4 {
                assert!((p4[k] - p[k]).abs() <= 1e-15 * p[k].abs(), "phi_{k}({z}): {} vs {}", p4[k], p[k]);
            }
            let slow = |k: usize| {
                if z.abs() > 1.0 {
                    // phi_k from its definition in exact-enough arithmetic for large |z|.
                    let mut v = z.exp();
                    let mut f = 1.0;
                    for j in 0..k {
                        v = (v - 1.0 / f) / z;
                        f *= (j + 1) as f64;
                    }
                    v
                } else {
                    let mut sum = 0.0;
                    let mut f: f64 = (1..=k).map(|v| v as f64).product();
                    for j in 0..40 {
                        sum += z.powi(j) / f;
                        f *= (j as usize + k + 1) as f64;
                    }
                    sum
                }
            };
            // phi_4 and phi_5 by the recurrence just above |z| = 0.5 lose digits (see phis).
            for k in 0..6 {
                let tol = if k < 4 { 1e-14 } else { 1e-11 };
                assert!(
                    (p[k] - slow(k)).abs() < tol * slow(k).abs().max(1e-3),
                    "phi_{k}({z}) = {} vs {}",
                    p[k],
                    slow(k)
                );
            }
        }
    }

    #[test]
    fn dual_numbers_carry_the_exponential_steps_sensitivity() {
        // d y(t) / d a00 through ten exponential steps equals a central difference.
        use num_dual::Dual64;
        let run = |d: Dual64| -> Dual64 {
            struct P(Dual64);
            impl Dynamics<Dual64, 4> for P {
                fn deriv(&self, y: &[Dual64; 4], u: Dual64) -> [Dual64; 4] {
                    let sys = Network { a: STIFF, g: 3.0e3, k3: 2.0e9 };
                    let mut d = sys.deriv(y, u);
                    d[2] += (self.0 - STIFF[0][0]) * y[2];
                    d
                }
            }
            impl Electrical<Dual64, 4> for P {
                fn electrical(&self, _: &[Dual64; 4]) -> [[Dual64; 2]; 2] {
                    [[self.0, Dual64::from(STIFF[0][1])], [Dual64::from(STIFF[1][0]), Dual64::from(STIFF[1][1])]]
                }
                fn input(&self, _: &[Dual64; 4]) -> Dual64 {
                    Dual64::from(1.0)
                }
            }
            let sys = P(d);
            let mut y = [Dual64::from(1e-4), Dual64::from(0.0), Dual64::from(0.1), Dual64::from(0.0)];
            let h = 1.0 / 48000.0;
            for s in 0..10 {
                let u = Dual64::from(3.0e4 * (s as f64 * 0.7).sin());
                let k = EtdCoefficients::new(&sys.electrical(&y), h);
                y = etd4_step(&sys, &y, &k, [u; 3], None);
            }
            y[0]
        };
        let a = STIFF[0][0];
        let exact = run(Dual64::from(a).derivative()).eps;
        let step = 1.0;
        let fd = (run(Dual64::from(a + step)).re - run(Dual64::from(a - step)).re) / (2.0 * step);
        assert!((exact - fd).abs() < 1e-6 * fd.abs(), "{exact} vs {fd}");
        assert!(exact.abs() > 0.0);
    }

    #[test]
    fn steppers_take_the_cheaper_scheme_with_an_lr3_branch_in_the_network() {
        let fs = 48000.0;
        // A woofer (SB17: |lambda| / fs = 0.83): RK4 with 2 sub-steps, 1 in the Jacobian.
        let woofer = Rates::stiff(0.83 * fs);
        let (r, j) = Stepper::for_fit(woofer, fs);
        assert_eq!((r.scheme, r.n(), j.scheme, j.n()), (Scheme::Rk4, 2, Scheme::Rk4, 1));
        // A slow coil (|lambda| / fs = 0.25) keeps 2; SB17 at 96 kHz too.
        assert_eq!(Stepper::for_rates(Rates::stiff(0.25 * fs), fs).n(), 2);
        assert_eq!(Stepper::for_rates(woofer, 2.0 * fs).n(), 2);
        // The microspeaker (|lambda| / fs = 10.4): 3 exponential steps in a simulation, 2 in
        // a fit's model runs (FIT_EXP_STIFF_LIMIT), 1 in the Jacobian; the steps' points: the
        // quartic's five per step, the one step's three...
        let micro = Rates::stiff(10.4 * fs);
        let sim = Stepper::for_rates(micro, fs);
        assert_eq!((sim.scheme, sim.n(), sim.points()), (Scheme::Exponential, 3, 13));
        let (r, j) = Stepper::for_fit(micro, fs);
        assert_eq!(
            (r.scheme, r.n(), r.points(), j.scheme, j.n(), j.points()),
            (Scheme::Exponential, 2, 9, Scheme::Exponential, 1, 3)
        );
        // (up to |lambda| / fs = 12 in a fit, then 3).
        assert_eq!(Stepper::for_fit(Rates::stiff(12.0 * fs), fs).0.n(), 2);
        assert_eq!(Stepper::for_fit(Rates::stiff(12.1 * fs), fs).0.n(), 3);
        // A search stage's Jacobian: the midpoint rule for woofers, the exponential midpoint
        // rule for the stiff ones (RK4 between the two limits).
        for (rates, scheme) in
            [(woofer, Scheme::Midpoint), (Rates::stiff(1.2 * fs), Scheme::Rk4), (micro, Scheme::ExpMidpoint)]
        {
            let s = Stepper::for_search_jacobian(rates, fs);
            assert_eq!(s.scheme, scheme, "{rates:?}");
            assert_eq!(s.n(), if scheme == Scheme::Midpoint { 1 } else { Stepper::for_fit(rates, fs).1.n() });
        }
        // A set with an LR-3 branch: in the exponential method's network, it sets no
        // exponential steps (the microspeaker keeps its 3 and 2, 1 in the Jacobian), and
        // counts in RK4's.
        let with_lr3 = Rates { stiff: 10.4 * fs, lr3: 15.0 * fs };
        let (r, j) = Stepper::for_fit(with_lr3, fs);
        assert_eq!(
            (exp_steps_for(with_lr3, fs), r.scheme, r.n(), j.scheme, j.n()),
            (3, Scheme::Exponential, 2, Scheme::Exponential, 1)
        );
        assert_eq!(substeps_for(with_lr3.total(), fs), 51);
        // A woofer's keeps RK4 (2 sub-steps against 2 exponential steps) until the branch
        // needs 5 RK4 sub-steps.
        assert_eq!(Stepper::for_rates(Rates { stiff: 0.83 * fs, lr3: 0.5 * fs }, fs).scheme, Scheme::Rk4);
        assert_eq!(Stepper::for_rates(Rates { stiff: 0.83 * fs, lr3: 1.5 * fs }, fs).scheme, Scheme::Exponential);
    }

    #[test]
    fn the_midpoint_rule_is_second_order_and_stable_below_2() {
        // y' = -y + u: halving h divides the error by ~4.
        let sys = Decay { lambda: 1.0 };
        let err = |n: usize| {
            let h = 1.0 / n as f64;
            let mut y = [1.0];
            for _ in 0..n {
                y = midpoint_sample(&sys, &y, h, &[0.0; 3]);
            }
            (y[0] - (-1.0f64).exp()).abs()
        };
        let (e1, e2) = (err(20), err(40));
        assert!((e1 / e2 - 4.0).abs() < 0.3, "ratio {}", e1 / e2);
        // The stiff mode at |lambda| h = 1.9 decays, at 2.1 grows.
        for (z, decays) in [(1.9, true), (2.1, false)] {
            let mut y = [1.0];
            for _ in 0..200 {
                y = midpoint_sample(&Decay { lambda: z }, &y, 1.0, &[0.0; 3]);
            }
            assert_eq!(y[0].abs() < 1.0, decays, "|lambda| h = {z}: {}", y[0]);
        }
    }

    #[test]
    fn rk4_is_fourth_order() {
        // y' = -y, exact exp(-t): halving h divides the error by ~16.
        let sys = Decay { lambda: 1.0 };
        let err = |n: usize| {
            let h = 1.0 / n as f64;
            let mut y = [1.0];
            for _ in 0..n {
                y = rk4_step(&sys, &y, h, 0.0, 0.0, 0.0);
            }
            (y[0] - (-1.0f64).exp()).abs()
        };
        let ratio = err(10) / err(20);
        assert!(ratio > 14.0 && ratio < 18.0, "{ratio}");
    }

    #[test]
    fn substeps_keep_the_fastest_mode_inside_the_accuracy_limit() {
        // A microspeaker with Le/(Re+R2) = 3 us at 48 kHz.
        let n = substeps_for(1.0 / 3e-6, 48000.0);
        assert!(n >= 14, "{n}");
        let h = 1.0 / 48000.0 / n as f64;
        assert!(h / 3e-6 <= STIFF_LIMIT + 1e-12);
        assert_eq!(substeps_for(1000.0, 48000.0), MIN_SUBSTEPS);
        // Stable and accurate: step response of the 3 us pole equals 1 - exp(-t/tau).
        let sys = Decay { lambda: 1.0 / 3e-6 };
        let mut y = [0.0];
        let pts = vec![1.0 / 3e-6; 2 * n + 1];
        for _ in 0..3 {
            y = rk4_sample(&sys, &y, 1.0 / 48000.0, &pts);
        }
        let exact = 1.0 - (-3.0 / 48000.0 / 3e-6f64).exp();
        assert!((y[0] - exact).abs() < 1e-6, "{} vs {}", y[0], exact);
    }

    #[test]
    fn interpolation_reproduces_band_limited_sines() {
        let fs = 48000.0;
        let it = Interpolator::new(4);
        let mut pts = vec![0.0; 9];
        for (f, tol) in [(50.0, 1e-6), (1000.0, 1e-6), (8000.0, 1e-6), (16000.0, 1e-6), (20000.0, 0.03)] {
            let u: Vec<f64> = (0..2000).map(|k| (2.0 * std::f64::consts::PI * f * k as f64 / fs + 0.3).sin()).collect();
            let mut worst: f64 = 0.0;
            for m in 100..1900 {
                it.fill(&u, m, &mut pts);
                for (j, p) in pts.iter().enumerate() {
                    let t = (m as f64 + j as f64 / 8.0) / fs;
                    let exact = (2.0 * std::f64::consts::PI * f * t + 0.3).sin();
                    worst = worst.max((p - exact).abs());
                }
            }
            assert!(worst < tol, "{f} Hz: {worst}");
        }
    }

    #[test]
    fn interpolation_is_exact_at_samples_and_treats_outside_as_silence() {
        let it = Interpolator::new(3);
        let u = [0.0, 1.0, -2.0, 0.5];
        let mut pts = vec![0.0; 7];
        it.fill(&u, 1, &mut pts);
        assert_eq!(pts[0], 1.0);
        assert_eq!(pts[6], -2.0);
        it.fill(&u, 3, &mut pts);
        assert_eq!(pts[6], 0.0);
        // Interior points equal a direct kernel sum (the slow reference).
        let direct: f64 = (0..4).map(|k| u[k] * kernel(1.5 - k as f64)).sum::<f64>();
        it.fill(&u, 1, &mut pts);
        let norm: f64 = (-20..20).map(|k| kernel(0.5 - k as f64)).sum();
        assert!((pts[3] - direct / norm).abs() < 1e-12);
    }
}

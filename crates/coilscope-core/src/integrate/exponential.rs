//! The exponential Runge-Kutta schemes ([`etd4_sample`], [`etd2_sample`], [`etdc_sample`]): the
//! currents' linear RL network ([`Electrical`]) integrated exactly, the rest as a Runge-Kutta
//! method does.

use super::*;

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
pub(super) const INV_FACT: [f64; 6] = [1.0, 1.0, 0.5, 1.0 / 6.0, 1.0 / 24.0, 1.0 / 120.0];

/// `1 / (j + m)!` for `j = 0 .. 13`: the series of `phi_m`.
pub(super) const fn series_coefficients(m: usize) -> [f64; 13] {
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
pub(super) fn phis<D: DualNum<Primitive = f64> + Copy, const K: usize>(z: D) -> [D; K] {
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
pub(super) fn phis_and_halves<D: DualNum<Primitive = f64> + Copy>(z: D) -> ([D; 6], [D; 6]) {
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
pub(super) const PHI_PAIR_SERIES: f64 = 0.2;

/// Scalar functions `g_k` of a 2 x 2 matrix `M`, as `(alpha_k, beta_k)` with
/// `g_k(M) = alpha_k I + beta_k M` (the interpolating polynomial on its two eigenvalues).
/// The eigenvalues are real: `M` is an RL network's `-L^-1 R`, similar to a symmetric matrix.
#[inline]
pub(super) fn matrix_functions<D: DualNum<Primitive = f64> + Copy, const K: usize>(
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
    pub(super) p: D,
    pub(super) q: D,
}

impl<D: DualNum<Primitive = f64> + Copy> Pair<D> {
    /// `(p I + q A) n`, given `an = A n`.
    #[inline(always)]
    pub(super) fn apply(&self, n: [D; 2], an: [D; 2]) -> [D; 2] {
        [self.p * n[0] + self.q * an[0], self.p * n[1] + self.q * an[1]]
    }

    /// The pair of `c (alpha I + beta (s A))`: a function `(alpha, beta)` of the scaled
    /// matrix `s A` ([`matrix_functions`]), times `c`.
    #[inline(always)]
    pub(super) fn of(f: (D, D), s: f64, c: f64) -> Self {
        Pair { p: f.0 * c, q: f.1 * (s * c) }
    }

    /// `(p I + q A) (v, 0)`: on a vector in the current `i` alone (the drive's).
    #[inline(always)]
    pub(super) fn apply_to_current(&self, v: D, a: &[[D; 2]; 2]) -> [D; 2] {
        self.apply([v, D::zero()], [a[0][0] * v, a[1][0] * v])
    }

    #[inline(always)]
    pub(super) fn plus(self, o: Self) -> Self {
        Pair { p: self.p + o.p, q: self.q + o.q }
    }
}

/// `s a`: the network matrix `a` (1/s) times a step (s).
#[inline(always)]
pub(super) fn scaled<D: DualNum<Primitive = f64> + Copy>(a: &[[D; 2]; 2], s: f64) -> [[D; 2]; 2] {
    std::array::from_fn(|r| std::array::from_fn(|c| a[r][c] * s))
}

/// A 2 x 2 matrix times a vector.
#[inline(always)]
pub(super) fn mat_vec<D: DualNum<Primitive = f64> + Copy>(m: &[[D; 2]; 2], v: [D; 2]) -> [D; 2] {
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
    pub(super) h: f64,
    pub(super) a: [[D; 2]; 2],
    pub(super) e5: Pair<D>,
    pub(super) e1: Pair<D>,
    pub(super) a21: Pair<D>,
    pub(super) a31: Pair<D>,
    pub(super) a32: Pair<D>,
    pub(super) a41: Pair<D>,
    pub(super) a42: Pair<D>,
    pub(super) a51: Pair<D>,
    pub(super) a52: Pair<D>,
    pub(super) a54: Pair<D>,
    pub(super) b1: Pair<D>,
    pub(super) b4: Pair<D>,
    pub(super) b5: Pair<D>,
    /// The drive's integrals over the half step and the step ([`EtdCoefficients::with_drive`]):
    /// `h c^{k+1} k! phi_{k+1}(c M)` for `c = 1/2` and `1`, `k = 0 ..= 4` ([`etd4_step`]).
    pub(super) drive: Option<([Pair<D>; 5], [Pair<D>; 5])>,
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
    pub(super) fn from_functions(
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
    pub(super) fn quartic(b: D, w: &[D]) -> Self {
        Drive { b, g: std::array::from_fn(|k| (0..5).fold(D::zero(), |acc, j| acc + w[j] * QUARTIC[k][j])) }
    }

    /// The quartic through the step's five points `w` at `t = 0, 1/4, ..., 1`, in `t`:
    /// [`Drive::quartic`] in `s = 2 t`, `g_k` scaled by `2^k` (exactly).
    pub(super) fn of_step(b: D, w: &[D]) -> Self {
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
pub(super) const QUARTIC: [[f64; 5]; 5] = quartic_weights();

pub(super) const fn quartic_weights() -> [[f64; 5]; 5] {
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
    pub(super) h: f64,
    pub(super) a: [[D; 2]; 2],
    pub(super) e5: Pair<D>,
    pub(super) e1: Pair<D>,
    pub(super) a21: Pair<D>,
    pub(super) c2: Pair<D>,
    pub(super) b1: Pair<D>,
    pub(super) b2: Pair<D>,
    pub(super) d: Pair<D>,
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
pub(super) fn exponentials_on_currents<D: DualNum<Primitive = f64> + Copy, const N: usize>(
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
pub(super) struct Rest<D, const N: usize> {
    pub(super) n: [D; N],
    pub(super) an: [D; 2],
}

#[inline(always)]
pub(super) fn etd_rest<D, S, const N: usize>(sys: &S, a: &[[D; 2]; 2], s: &[D; N], u: D) -> Rest<D, N>
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
pub(super) fn etd_stage<D: DualNum<Primitive = f64> + Copy, const N: usize>(
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
pub(super) mod net {
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
    pub(in crate::integrate) fn eigenvalues3<D: DualNum<Primitive = f64> + Copy>(m: &[[D; 3]; 3]) -> [D; 3] {
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

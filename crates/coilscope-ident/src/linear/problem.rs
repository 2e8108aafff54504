//! The output error on the current's DFT ([`CurrentError`]): the parameter map, the chain's
//! and the record ends' terms, and the analytic Jacobian.

use super::*;

pub(super) struct CurrentError {
    pub(super) f: Vec<f64>,
    /// Weighted spectra (see `fit_linear`) and the weights.
    pub(super) u: Vec<Complex64>,
    pub(super) i: Vec<Complex64>,
    pub(super) w: Vec<f64>,
    pub(super) norm: f64,
    pub(super) map: ParamMap,
    /// Reference angular frequency of the transient polynomial (rad/s).
    pub(super) omega0: f64,
    /// Number of transient coefficients in theta (0 or [`N_TRANSIENT`]).
    pub(super) n_transient: usize,
    /// The extra effects fitted; their unknowns follow the seven LR-2 ones in theta:
    /// lambda (creep), then the LR-3 corner (bounded as the LR-2 one) and ln R3.
    pub(super) effects: Effects,
    /// The measurement chain's unknowns ([`ChainTerms`]), from [`CurrentError::chain_index`] in
    /// theta: the current channel's delay (samples), the voltage and current channels'
    /// AC-coupling corners (Hz), those that are on. `None`: an ideal chain.
    pub(super) chain: Option<ChainTerms>,
    /// An impedance curve without a measured phase: each point's `u` takes the model's
    /// phase at theta, so that its error `1 - |Z_measured| / |Z_model|` is real and the fit
    /// is of the magnitude alone ([`fit_impedance_magnitude`]).
    pub(super) magnitude_only: bool,
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
    pub(super) fn factor_at(&self, th: &[f64]) -> ChainFactor {
        let [tau, fu, fi] = self.values(th);
        let hp = |fc: f64| coilscope_core::chain::hp_coefficients(fc, self.fs);
        let h = CHAIN_CORNER_STEP;
        ChainFactor { terms: *self, tau, u: [hp(fu), hp(fu + h), hp(fu - h)], i: [hp(fi), hp(fi + h), hp(fi - h)] }
    }
}

/// Step (Hz) of the central differences that give the chain factor's derivatives in the
/// corners ([`ChainFactor::at`]).
pub(super) const CHAIN_CORNER_STEP: f64 = 1e-4;

/// [`ChainTerms`] at one theta ([`ChainTerms::factor_at`]): the delay, and the AC-coupling
/// filters' coefficients (`coilscope_core::chain::hp_coefficients`) at each corner and at
/// the corner plus and minus [`CHAIN_CORNER_STEP`].
pub(super) struct ChainFactor {
    pub(super) terms: ChainTerms,
    pub(super) tau: f64,
    /// `(g, a)` of the voltage channel's corner, and of it plus and minus the step.
    pub(super) u: [(f64, f64); 3],
    /// The same for the current channel's corner.
    pub(super) i: [(f64, f64); 3],
}

impl ChainFactor {
    /// The factor on the predicted current at `f` (Hz), `e^{-j 2 pi f tau / fs} H_i(f) /
    /// H_u(f)` with `H` as [`coilscope_core::chain::hp_response`], and with `deriv` its
    /// derivatives w.r.t. the chain's entries of theta (those on, in order; the corners' by
    /// central differences). The same values to the last bit as `hp_response` per corner
    /// (`the_chain_factor_is_hp_response_s`), with two sines and cosines per bin instead of
    /// fifteen and ten tangents: those were 75 % of a linear fit with the chain (the
    /// `--chain auto` start of `identify` on SB17's `-real-chain` record: 8.4 s).
    pub(super) fn at(&self, f: f64, deriv: bool) -> (Complex64, Vec<Complex64>) {
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
pub(super) const N_TRANSIENT: usize = 4;

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
pub(super) struct ParamMap {
    /// Bounds of `q` (natural log units); infinite = unbounded.
    pub(super) lo: [f64; 7],
    pub(super) hi: [f64; 7],
}

pub(super) fn logistic(t: f64) -> f64 {
    1.0 / (1.0 + (-t).exp())
}

/// The inverse of `q = lo + (hi - lo) logistic(theta)`, with `q` pulled at least `margin`
/// (a share of the range) inside its bounds.
pub(super) fn bounded_theta(q: f64, lo: f64, hi: f64, margin: f64) -> f64 {
    let s = ((q - lo) / (hi - lo)).clamp(margin, 1.0 - margin);
    (s / (1.0 - s)).ln()
}

impl ParamMap {
    /// The map of a fit over `band` (Hz): the LR-2 corner stays inside it, its upper bound a
    /// few times the band's top (a corner just above it still shapes the impedance inside
    /// the band; the microspeaker sets have theirs at 21 kHz).
    pub(super) fn for_band(band: [f64; 2]) -> ParamMap {
        let (mut lo, mut hi) = ([f64::NEG_INFINITY; 7], [f64::INFINITY; 7]);
        lo[2] = (1.0 / (2.0 * PI * CORNER_ABOVE_BAND * band[1])).ln();
        hi[2] = (1.0 / (2.0 * PI * band[0])).ln();
        ParamMap { lo, hi }
    }

    pub(super) fn q(&self, theta: &[f64]) -> [f64; 7] {
        std::array::from_fn(|k| {
            if self.lo[k].is_finite() {
                self.lo[k] + (self.hi[k] - self.lo[k]) * logistic(theta[k])
            } else {
                theta[k]
            }
        })
    }
    /// `dq_k / dtheta_k`.
    pub(super) fn dq(&self, theta: &[f64]) -> [f64; 7] {
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
    pub(super) fn theta(&self, q: &[f64; 7]) -> Vec<f64> {
        (0..7)
            .map(|k| if self.lo[k].is_finite() { bounded_theta(q[k], self.lo[k], self.hi[k], 0.01) } else { q[k] })
            .collect()
    }
    /// Impedance-model parameters `[Re, Le, L2, R2, Res, Cmes, Lces]` (SI).
    pub(super) fn params(&self, theta: &[f64]) -> [f64; 7] {
        let q = self.q(theta);
        let mut p: [f64; 7] = std::array::from_fn(|k| q[k].exp());
        p[2] = (q[2] + q[3]).exp();
        p
    }
    /// Natural coordinates of model parameters.
    pub(super) fn q_of(p: &[f64; 7]) -> [f64; 7] {
        let mut q: [f64; 7] = std::array::from_fn(|k| p[k].ln());
        q[2] = (p[2] / p[3]).ln();
        q
    }
    /// Names of the bounded coordinates whose logistic sits within 1e-3 of a bound.
    pub(super) fn at_bound(&self, theta: &[f64]) -> Vec<&'static str> {
        (0..7)
            .filter(|&k| self.lo[k].is_finite() && !(1e-3..=1.0 - 1e-3).contains(&logistic(theta[k])))
            .map(|k| if k == 2 { "L2/R2 corner" } else { NAMES[k] })
            .collect()
    }
}

impl CurrentError {
    /// The measured `u` of bin `k` against a model impedance `z` there: as measured, or, for
    /// a curve without phase, its magnitude at the model's phase.
    pub(super) fn u_at(&self, k: usize, z: Complex64) -> Complex64 {
        if self.magnitude_only {
            Complex64::from_polar(self.u[k].norm(), z.arg())
        } else {
            self.u[k]
        }
    }

    /// Where the chain's unknowns start in theta.
    pub(super) fn chain_index(&self) -> usize {
        self.t0() + self.n_transient
    }

    /// Where the transient coefficients start in theta.
    pub(super) fn t0(&self) -> usize {
        7 + n_extra(self.effects)
    }

    /// Where creep's lambda sits in theta.
    pub(super) fn idx_lambda(&self) -> Option<usize> {
        self.effects.creep.then_some(7)
    }

    /// Where the LR-3 corner (then ln R3) sits in theta.
    pub(super) fn idx_lr3(&self) -> Option<usize> {
        self.effects.lr3.then_some(7 + self.effects.creep as usize)
    }

    /// `ln tau3` of its bounded coordinate, and its slope `d ln tau3 / d theta`.
    pub(super) fn tau3(&self, t: f64) -> (f64, f64) {
        let (lo, hi) = (self.map.lo[2], self.map.hi[2]);
        let s = logistic(t);
        (lo + (hi - lo) * s, (hi - lo) * s * (1.0 - s))
    }

    /// The extra effects' values at theta.
    pub(super) fn ext(&self, theta: &[f64]) -> Ext {
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
    pub(super) fn transient<'t>(&self, theta: &'t [f64]) -> &'t [f64] {
        &theta[self.t0()..self.t0() + self.n_transient]
    }

    /// [`transient_term`] of bin `k`, or nothing (zeros) without a transient term
    /// ([`Ends::AssumedAtRest`], the large-signal start): there the term is zero and its
    /// derivatives enter times it, so a fit's residuals and Jacobian are the same to the
    /// last bit (the term took a fifth of a linear fit with the chain).
    pub(super) fn transient_at(
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
    pub(super) fn chain_factor(&self, theta: &[f64]) -> Option<ChainFactor> {
        self.chain.map(|c| c.factor_at(&theta[self.chain_index()..]))
    }

    /// The chain's factor on the predicted current of bin `k` (1 for an ideal chain), with its
    /// derivatives when `deriv`.
    pub(super) fn shift_d(&self, chain: Option<&ChainFactor>, k: usize, deriv: bool) -> (Complex64, Vec<Complex64>) {
        match chain {
            Some(c) => c.at(self.f[k], deriv),
            None => (Complex64::new(1.0, 0.0), vec![]),
        }
    }

    /// `|I - U/Z - T| / |I|` over the fitted bins, unweighted (the spec's `fit.residual_rel`),
    /// with the fitted chain's delay and coupling between `U/Z` and the recorded current.
    pub(super) fn residual_rel(&self, theta: &[f64]) -> f64 {
        self.residual_and_floor(theta).0
    }

    /// [`CurrentError::residual_rel`] and the noise floor in the same terms: the current
    /// error's power per bin is the noise's plus the model's misfit, which a wrong model puts
    /// in the bins of a band (the resonance, the branches' corners) and noise in every bin.
    /// The median bin then holds noise: a bin's noise power is a complex Gaussian's, whose
    /// median is ln 2 times its mean. A misfit over most of the bins raises the floor, so
    /// that fewer effects pay: the safe side.
    pub(super) fn residual_and_floor(&self, theta: &[f64]) -> (f64, f64) {
        let (e, t) = self.bin_errors(theta);
        let e: Vec<f64> = e.iter().map(|e| e.norm_sqr()).collect();
        let total: f64 = e.iter().sum();
        let m = e.len();
        let floor = if m == 0 { 0.0 } else { crate::checks::median(e) / std::f64::consts::LN_2 * m as f64 };
        ((total / t).sqrt(), (floor / t).sqrt())
    }

    /// Each bin's current error in the terms of [`CurrentError::residual_rel`], and the
    /// power of the current it is relative to.
    fn bin_errors(&self, theta: &[f64]) -> (Vec<Complex64>, f64) {
        let p = self.map.params(theta);
        let ext = self.ext(theta);
        let chain = self.chain_factor(theta);
        let mut t = 0.0;
        let mut e = Vec::with_capacity(self.f.len());
        for k in 0..self.f.len() {
            let imp = impedance_ext(&p, &ext, self.f[k]);
            let (z, tr) = (imp.0, transient_term(&p, &imp, self.transient(theta), self.omega0, self.f[k]).0);
            // The recorded current is the driver's through the chain (when one is fitted).
            let shift = self.shift_d(chain.as_ref(), k, false).0;
            e.push((self.i[k] - self.u_at(k, z) * shift / z) / self.w[k] - tr);
            t += (self.i[k] / self.w[k]).norm_sqr();
        }
        (e, t)
    }

    /// The noise floor of an impedance curve (no record behind it, so no spectrum of the
    /// noise), in the terms of [`CurrentError::residual_rel`], from how rough the error is
    /// from point to point: the model's misfit is smooth over a dense curve (the resonance
    /// and the branches' corners span tens of points), the noise of each point independent.
    /// The second difference `d_k = e_k - (e_(k-1) + e_(k+1)) / 2` of the points' errors keeps
    /// 1.5 times the noise's power and little of the misfit; its median over the curve is
    /// robust to the few points where the misfit bends sharply. The median of a real
    /// Gaussian's power (|Z| alone: the error is real) is 0.455 times its mean, of a complex
    /// one ln 2. A smoothed curve (an averaged export) shows almost none: its floor is about
    /// zero, and an effect pays on its share of the whole residual ([`super::effect_pays`]).
    pub(super) fn roughness_floor(&self, theta: &[f64]) -> f64 {
        let (e, t) = self.bin_errors(theta);
        let m = e.len();
        if m < 8 || !(t > 0.0) {
            return 0.0;
        }
        let d2: Vec<f64> = (1..m - 1).map(|k| (e[k] - 0.5 * (e[k - 1] + e[k + 1])).norm_sqr()).collect();
        let median_share = if self.magnitude_only { CHI2_1_MEDIAN } else { std::f64::consts::LN_2 };
        let per_point = crate::checks::median(d2) / median_share / 1.5;
        let total: f64 = e.iter().map(|e| e.norm_sqr()).sum();
        // Never above the residual itself.
        let floor = (per_point * m as f64).min(total);
        if floor.is_finite() {
            (floor / t).sqrt()
        } else {
            0.0
        }
    }
}

/// The median of a chi-square variable of one degree of freedom: a real Gaussian's power
/// over its mean.
const CHI2_1_MEDIAN: f64 = 0.454_936_423_119_572_8;

/// The transient term `T = Q(s) / P(s)` at `f` (current, in the DFT's units), with
/// `Q(s) = sum_j c_j (s / omega0)^j` and `P = Z D_Z / (R2 Res)`, `D_Z = (s L2 + R2)(Res + s
/// Lces + s^2 Lces Cmes Res)` (ohm), `Z` with the extra effects (their own poles are left out
/// of `D_Z`: the term only has to absorb a record's ends). Returns `T`, `d ln P / d ln p_m`
/// (m over the seven model parameters), the same for the extras (as [`impedance_ext`]), and
/// the basis `(s / omega0)^j / P` (= `dT / dc_j`).
#[allow(clippy::type_complexity)]
#[inline]
pub(super) fn transient_term(
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

/// `part` of the H1 estimate at the bins `at` (ascending), each averaged over the bins of `at`
/// within a sixth of an octave around it (a twelfth on either side).
pub(super) fn sixth_octave_mean(h1: &ImpedanceEstimate, at: &[usize], part: impl Fn(Complex64) -> f64) -> Vec<f64> {
    let side = 2f64.powf(1.0 / 12.0);
    let mut sum = vec![0.0; at.len() + 1];
    for (j, &k) in at.iter().enumerate() {
        sum[j + 1] = sum[j] + part(h1.z[k]);
    }
    let (mut lo, mut hi) = (0, 0);
    at.iter()
        .map(|&k| {
            let f = h1.f[k];
            while h1.f[at[lo]] < f / side {
                lo += 1;
            }
            while hi < at.len() && h1.f[at[hi]] <= f * side {
                hi += 1;
            }
            (sum[hi] - sum[lo]) / (hi - lo) as f64
        })
        .collect()
}

/// Start values from the H1 estimate (motional peak, half-power bandwidth, high-frequency
/// inductance).
pub(super) fn initial_guess(h1: &ImpedanceEstimate, lo: f64, hi: f64) -> Result<[f64; 7], String> {
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
    // Both parts are smoothed over a sixth of an octave first: at high level the
    // nonlinearity and the noise make Im Z jitter about zero for tens of hertz across the
    // resonance (a 0.5 g microspeaker at 85 % of its range: no three bins of one sign between
    // 330 and 350 Hz), and the search on raw bins took a jitter about zero at 1.1 kHz, where
    // Re Z is hardly above Re, for the resonance; the linear fit from there lost the motional
    // branch (Cmes -> 1e36 F).
    let (re_s, im_s) = (sixth_octave_mean(h1, &low, |z| z.re), sixth_octave_mean(h1, &low, |z| z.im));
    let held = 3;
    let crossing = (held..low.len().saturating_sub(held))
        .filter(|&j| (j - held..j).all(|a| im_s[a] > 0.0) && (j..j + held).all(|a| im_s[a] <= 0.0))
        .max_by(|&a, &b| re_s[a].total_cmp(&re_s[b]));
    let jpk = match crossing {
        Some(j) => j,
        None => (0..low.len()).max_by(|&a, &b| re_s[a].total_cmp(&re_s[b])).ok_or("no usable bins below 2 kHz")?,
    };
    let kpk = low[jpk];
    let fs0 = h1.f[kpk];
    let res = (re_s[jpk] - re).max(0.1 * re);
    // Half-power points of the motional real part: bandwidth fs / Qms.
    let half = re + 0.5 * res;
    let below = (0..jpk).rev().find(|&j| re_s[j] < half).map(|j| h1.f[low[j]]);
    let above = (jpk + 1..low.len()).find(|&j| re_s[j] < half).map(|j| h1.f[low[j]]);
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

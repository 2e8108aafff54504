//! The nonlinear transducer model of the file contract — the one place it is written.
//!
//! States (SI): `[x, v, i, i2, Tv, Tm]` = displacement (m, + = coil out), velocity (m/s),
//! voice-coil current (A), current in the L2 branch (A), voice-coil and magnet temperature
//! rises above ambient (K). Input: terminal voltage u (V).
//!
//! ```text
//! u  = Re(Tv) i + d(Le(x) i)/dt + Bl(x) v + R2(x) (i - i2)
//! d(L2(x) i2)/dt = R2(x) (i - i2)
//! Mms dv/dt = Bl(x) i - Rms v - Kms(x) x + 1/2 Le'(x) i^2 + 1/2 L2'(x) i2^2
//! Ctv dTv/dt = Re(Tv) i^2 - (Tv - Tm)/Rtv
//! Ctm dTm/dt = R2 (i - i2)^2 + (Tv - Tm)/Rtv - Tm/Rtm,      Re(T) = Re (1 + alpha T)
//! ```
//!
//! With flux modulation (`Le_i`) the flux is `psi = Le(x) g(i) i`: `Le(x) di/dt` becomes
//! `Le(x) h(i) di/dt + Le'(x) g(i) i v` and the reluctance force `Le'(x) G(i)`, with
//! `h = d(i g)/di` and `G = int_0^i s g(s) ds` (both from the one coenergy `Le(x) G(i)`, so the
//! energy balance closes). With `Rms_v`, `Rms(|v|)` replaces `Rms`. Creep and LR-3, which
//! need states of their own, are in [`ExtModel`].
//!
//! The reluctance force is `+1/2 L'(x) i^2` (the seed paper's Eq. (1) prints the other sign;
//! its Eq. (3) and the energy balance agree with this one). The model is generic over the
//! scalar type `D` (f64, or `num_dual` dual numbers for exact Jacobians).

use crate::params::Parameters;
use crate::poly::Poly;
use num_dual::DualNum;

/// Number of states.
pub const NSTATE: usize = 6;
/// Index of each state in the state vector.
pub mod idx {
    pub const X: usize = 0;
    pub const V: usize = 1;
    pub const I: usize = 2;
    pub const I2: usize = 3;
    pub const TV: usize = 4;
    pub const TM: usize = 5;
}

/// The state vector `[x, v, i, i2, Tv, Tm]`.
pub type State<D> = [D; NSTATE];

/// Thermal constants in the model's scalar type.
#[derive(Clone, Debug)]
pub struct ThermalModel<D> {
    pub alpha: D,
    pub rtv: D,
    pub ctv: D,
    pub rtm: D,
    pub ctm: D,
    /// Convection cooling (s/m): `Rtv(v) = Rtv / (1 + rv |v|)`.
    pub rv: D,
    /// `1 / [rtv, ctv, rtm, ctm]`, taken once here rather than at every evaluation of the
    /// rates (a division is the slowest operation of the model's derivative).
    inv: [D; 4],
}

impl<D: DualNum<Primitive = f64> + Copy> ThermalModel<D> {
    /// The network of these constants (K/W, J/K, s/m; `alpha` 1/K).
    pub fn new(alpha: D, rtv: D, ctv: D, rtm: D, ctm: D, rv: D) -> Self {
        ThermalModel { alpha, rtv, ctv, rtm, ctm, rv, inv: [rtv.recip(), ctv.recip(), rtm.recip(), ctm.recip()] }
    }

    /// The two-node network's rates (K/s) of the coil and magnet rises `tv`, `tm` under the
    /// powers `pv` into the coil and `pm` into the magnet (W), as formats.md writes them, at
    /// coil speed `speed` = |v| (m/s; the convection cooling's `Rtv(v) = Rtv / (1 + rv |v|)`).
    #[inline]
    pub fn rates(&self, tv: D, tm: D, pv: D, pm: D, speed: D) -> (D, D) {
        // Times the constants' reciprocals: they do not wait on the state.
        let [rtv, ctv, rtm, ctm] = self.inv;
        let flow = (tv - tm) * rtv * (self.rv * speed + 1.0);
        ((pv - flow) * ctv, (pm + flow - tm * rtm) * ctm)
    }
}

/// The exact solution of the two-node network over `h` seconds with the powers and the speed
/// held ([`ThermalModel::held_step`]): the network is linear, `y' = A y + b`, so
/// `y(h) = y_eq + exp(A h) (y(0) - y_eq)` with the rest point `y_eq = -A^-1 b`. Built once for
/// a block length, a speed and the constants, then applied to any number of blocks with other
/// powers ([`HeldStep::apply`]); no step-size limit, however short the coil's time constant.
#[derive(Clone, Copy, Debug)]
pub struct HeldStep {
    /// `exp(A h)`, row-major.
    phi: [[f64; 2]; 2],
    /// `-A^-1` row-major: the rest point is `inv_neg_a b`.
    inv_neg_a: [[f64; 2]; 2],
    /// `b` per watt into the coil and per watt into the magnet: `b = Pv bv + Pm bm`.
    b_unit: [[f64; 2]; 2],
    /// The inputs it was built for: `(h, speed)`.
    key: (f64, f64),
}

impl HeldStep {
    /// The step of `m` over `h` (s) at coil speed `speed` (m/s). The matrix exponential by the
    /// network's two eigenvalues `l1 > l2` (real and distinct: `A` is similar to a symmetric
    /// matrix by the capacitances and its off-diagonal product is positive), in the form
    /// `exp(A h) = e^(l1 h) [ I (1 + e^(-2dh)) / 2 + (A - s I) (1 - e^(-2dh)) / (2d) ]`
    /// (`s` the mean, `d` half the gap), where no term overflows and none cancels, for any
    /// `h d`.
    pub fn new(m: &ThermalModel<f64>, h: f64, speed: f64) -> HeldStep {
        // A and b from the network's own rates ([`ThermalModel::rates`]), the one place its
        // equations are written: A's columns are the rates of a unit rise at no power, b's
        // those of a unit power at no rise.
        let r = |tv: f64, tm: f64, pv: f64, pm: f64| m.rates(tv, tm, pv, pm, speed);
        let (c0, c1) = (r(1.0, 0.0, 0.0, 0.0), r(0.0, 1.0, 0.0, 0.0));
        let a = [[c0.0, c1.0], [c0.1, c1.1]];
        let (bv, bm) = (r(0.0, 0.0, 1.0, 0.0), r(0.0, 0.0, 0.0, 1.0));
        let s = 0.5 * (a[0][0] + a[1][1]);
        let det = a[0][0] * a[1][1] - a[0][1] * a[1][0];
        // d^2 = ((a00 - a11) / 2)^2 + a01 a10: a sum of non-negative terms, no cancellation.
        let d = (0.25 * (a[0][0] - a[1][1]).powi(2) + a[0][1] * a[1][0]).sqrt();
        let e1 = ((s + d) * h).exp();
        let em = -(-2.0 * d * h).exp_m1(); // 1 - e^(-2dh), in [0, 1)
        let c = e1 * (1.0 - 0.5 * em); // e^(l1 h) (1 + e^(-2dh)) / 2
        let sh = if d * h > 1e-8 { e1 * em / (2.0 * d) } else { e1 * h * (1.0 - d * h) }; // e^(l1 h) (1 - e^(-2dh)) / (2d)
        let phi = [[c + sh * (a[0][0] - s), sh * a[0][1]], [sh * a[1][0], c + sh * (a[1][1] - s)]];
        let inv_neg_a = [[-a[1][1] / det, a[0][1] / det], [a[1][0] / det, -a[0][0] / det]];
        HeldStep { phi, inv_neg_a, b_unit: [[bv.0, bv.1], [bm.0, bm.1]], key: (h, speed) }
    }

    /// Whether this step was built for block length `h` and speed `speed` (bit for bit).
    pub fn is_for(&self, h: f64, speed: f64) -> bool {
        self.key == (h, speed)
    }

    /// `[Tv, Tm]` (K) at the end of the block from `y` at its start under the held powers
    /// `pv` into the coil and `pm` into the magnet (W).
    #[inline]
    pub fn apply(&self, y: [f64; 2], pv: f64, pm: f64) -> [f64; 2] {
        let [bv, bm] = self.b_unit;
        let (b0, b1) = (pv * bv[0] + pm * bm[0], pv * bv[1] + pm * bm[1]);
        let q = &self.inv_neg_a;
        let eq = [q[0][0] * b0 + q[0][1] * b1, q[1][0] * b0 + q[1][1] * b1];
        let (r0, r1) = (y[0] - eq[0], y[1] - eq[1]);
        let p = &self.phi;
        [eq[0] + p[0][0] * r0 + p[0][1] * r1, eq[1] + p[1][0] * r0 + p[1][1] * r1]
    }
}

impl ThermalModel<f64> {
    /// The coil and magnet rises `y = [Tv, Tm]` (K) after `h` seconds with the powers `pv`,
    /// `pm` (W) and the speed held: the network's exact solution ([`HeldStep`]). For one
    /// block; a series of blocks of one length and speed builds the [`HeldStep`] once.
    pub fn held_step(&self, y: [f64; 2], pv: f64, pm: f64, speed: f64, h: f64) -> [f64; 2] {
        HeldStep::new(self, h, speed).apply(y, pv, pm)
    }
}

/// The model's constants and power series, in scalar type `D`.
///
/// Built by [`Model::lift_from`] or [`Model::from_parts`], which also take the reciprocals of
/// `mms` and of a constant L2 once: change `mms` or `l2r2` by building a new model, not by
/// writing the field (`re`, the series and the effects may be written).
#[derive(Clone, Debug)]
pub struct Model<D> {
    pub re: D,
    pub le: Poly<D>,
    pub l2r2: Option<(Poly<D>, Poly<D>)>,
    pub bl: Poly<D>,
    pub kms: Poly<D>,
    pub mms: D,
    pub rms: D,
    pub thermal: Option<ThermalModel<D>>,
    /// Flux modulation (`Le_i`): the factor `g(i)` of the flux `psi = Le(x) g(i) i`
    /// (`g(0) = 1`); `None`: `g = 1`.
    pub le_i: Option<Poly<D>>,
    /// Velocity-dependent loss (`Rms_v`): `Rms(|v|)`, which replaces `rms` in the force.
    pub rms_v: Option<Poly<D>>,
    /// `1 / mms`, and `1 / L2` when the L2 series is a constant: taken once here rather than
    /// at every evaluation of the derivative ([`Model::from_parts`]).
    inv_mms: D,
    inv_l2: Option<D>,
}

impl Model<f64> {
    /// [`Model::deriv`] and its partial derivatives at state `s` (what a forward-sensitivity
    /// Jacobian propagates): with respect to the state, and to the values the parameters
    /// enter through there (`Bl(x)`, `Kms(x)`, `Le(x)`, `Le'(x)`, `Re`, `Rms`, `L2`, `R2`).
    /// For a fit's model: no thermal network, L2 and R2 constants, `Le_i` and `Rms_v` of
    /// degree 2 at most; `None` otherwise. Checked against dual numbers
    /// (`the_derivative_partials_are_the_dual_numbers`).
    #[inline]
    pub fn deriv_partials(&self, s: &State<f64>, u: f64) -> Option<(State<f64>, DerivPartials)> {
        if self.thermal.is_some()
            || self.le_i.as_ref().is_some_and(|g| g.c.len() > 3)
            || self.rms_v.as_ref().is_some_and(|r| r.c.len() > 3)
        {
            return None;
        }
        let (r2, inv_l2) = match &self.l2r2 {
            Some((l2, r2)) if l2.c.len() == 1 && r2.c.len() == 1 => (r2.c[0], 1.0 / l2.c[0]),
            Some(_) => return None,
            None => (0.0, 0.0),
        };
        let [x, v, i, i2, _, _] = *s;
        let (le, dle, d2le) = self.le.eval_d2(x);
        let (bl, dbl) = self.bl.eval_d(x);
        let (kms, dkms) = self.kms.eval_d(x);
        let inv_m = self.inv_mms;
        // The rates as `Model::deriv` computes them, operation for operation (its series
        // evaluated once here for both): with `Le_i` or `Rms_v` through `flux_modulated`.
        let flux = self.le_i.is_some() || self.rms_v.is_some();
        let (g, h, big) = self.flux_factors(i);
        // g'(i), h'(i) of `Le_i`'s g = sum c_k i^k, h = sum (k + 1) c_k i^k.
        let (dg, dh) = self.le_i.as_ref().map_or((0.0, 0.0), |p| {
            p.c.iter().enumerate().skip(1).fold((0.0, 0.0), |(a, b), (k, c)| {
                (a + k as f64 * c * i.powi(k as i32 - 1), b + ((k + 1) * k) as f64 * c * i.powi(k as i32 - 1))
            })
        });
        let (rms, drms) = match &self.rms_v {
            Some(r) => r.eval_d(v.abs()),
            None => (self.rms, 0.0),
        };
        let u2 = r2 * (i - i2);
        let (di, inv_d) = if flux {
            let dd = le * h;
            ((u - self.re * i - bl * v - u2 - dle * v * i * g) / dd, dd.recip())
        } else {
            let inv_le = le.recip();
            ((u - self.re * i - bl * v - u2 - dle * v * i) * inv_le, inv_le)
        };
        let force = bl * i - rms * v - kms * x + if flux { dle * big } else { dle * i * i * 0.5 };
        let d = [v, force * inv_m, di, if self.l2r2.is_some() { u2 * inv_l2 } else { 0.0 }, 0.0, 0.0];
        // Le_i's coefficients c_1, c_2: dg = i^k, dh = (k + 1) i^k, dG = i^(k + 2) / (k + 2).
        let le_i = std::array::from_fn(|j| {
            let k = j as i32 + 1;
            let (pg, ph, pbig) = (i.powi(k), (k + 1) as f64 * i.powi(k), i.powi(k + 2) / (k + 2) as f64);
            [dle * pbig * inv_m, (-dle * v * i * pg - di * le * ph) * inv_d]
        });
        let p = DerivPartials {
            v_state: [
                (dbl * i - dkms * x - kms + d2le * big) * inv_m,
                -(rms + drms * v.abs()) * inv_m,
                (bl + dle * i * g) * inv_m,
            ],
            i_state: [
                (-dbl * v - d2le * v * i * g - di * dle * h) * inv_d,
                (-bl - dle * i * g) * inv_d,
                (-self.re - r2 - dle * v * (g + i * dg) - di * le * dh) * inv_d,
                r2 * inv_d,
            ],
            i2_state: [r2 * inv_l2, -r2 * inv_l2],
            bl: [i * inv_m, -v * inv_d],
            kms: -x * inv_m,
            le: -di * h * inv_d,
            dle: [big * inv_m, -v * i * g * inv_d],
            re: -i * inv_d,
            rms: -v * inv_m,
            r2: [-(i - i2) * inv_d, (i - i2) * inv_l2],
            l2: -d[idx::I2] * inv_l2,
            le_i,
            rms_v2: -v * v.abs() * v.abs() * inv_m,
        };
        Some((d, p))
    }
}

/// The partial derivatives of a fit's [`Model::deriv`] at one state
/// ([`Model::deriv_partials`]), in SI units of the rates per unit of what they are taken by.
/// The rows are the states' rates `dv/dt`, `di/dt`, `di2/dt` (`dx/dt = v`; the thermal
/// states are off); entries not listed are zero.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct DerivPartials {
    /// `d(dv/dt) / d(x, v, i)`.
    pub v_state: [f64; 3],
    /// `d(di/dt) / d(x, v, i, i2)`.
    pub i_state: [f64; 4],
    /// `d(di2/dt) / d(i, i2)`.
    pub i2_state: [f64; 2],
    /// `d(dv/dt, di/dt) / d Bl(x)`.
    pub bl: [f64; 2],
    /// `d(dv/dt) / d Kms(x)`.
    pub kms: f64,
    /// `d(di/dt) / d Le(x)`.
    pub le: f64,
    /// `d(dv/dt, di/dt) / d Le'(x)`.
    pub dle: [f64; 2],
    /// `d(di/dt) / d Re`.
    pub re: f64,
    /// `d(dv/dt) / d Rms`.
    pub rms: f64,
    /// `d(di/dt, di2/dt) / d R2`.
    pub r2: [f64; 2],
    /// `d(di2/dt) / d L2`.
    pub l2: f64,
    /// `d(dv/dt, di/dt) / d c_k` of `Le_i`'s `g(i) = 1 + c_1 i + c_2 i^2`, `k = 1, 2`.
    pub le_i: [[f64; 2]; 2],
    /// `d(dv/dt) / d c_2` of `Rms_v`'s `Rms(|v|) = Rms + c_2 v^2`.
    pub rms_v2: f64,
}

/// The constants and series of a [`Model`] (its public fields but the thermal network), for
/// [`Model::from_parts`].
#[derive(Clone, Debug)]
pub struct Parts<D> {
    pub re: D,
    pub le: Poly<D>,
    pub l2r2: Option<(Poly<D>, Poly<D>)>,
    pub bl: Poly<D>,
    pub kms: Poly<D>,
    pub mms: D,
    pub rms: D,
    pub le_i: Option<Poly<D>>,
    pub rms_v: Option<Poly<D>>,
}

/// Instantaneous power flows (W) at one state: what the energy balance integrates.
#[derive(Clone, Copy, Debug, Default)]
pub struct Powers<D> {
    /// Electrical input u i.
    pub input: D,
    /// Joule loss in Re(T).
    pub re_loss: D,
    /// Eddy-current loss in R2.
    pub r2_loss: D,
    /// Mechanical loss in Rms.
    pub rms_loss: D,
    /// Eddy-current loss in R3 (the LR-3 branch of [`ExtModel`]; zero in [`Model`]).
    pub r3_loss: D,
    /// Loss in the creep bank's dampers ([`ExtModel`]; zero in [`Model`]).
    pub creep_loss: D,
    /// Loss in the box: its leak, the port's losses or the radiator's ([`ExtModel`]; zero in
    /// [`Model`]).
    pub box_loss: D,
}

impl Model<f64> {
    /// The model of a parameter set.
    pub fn new(p: &Parameters) -> Self {
        Model::<f64>::lift_from(p)
    }
}

impl<D: DualNum<Primitive = f64> + Copy> Model<D> {
    /// The model of a parameter set, with scalars of type `D` (zero derivative parts).
    pub fn lift_from(p: &Parameters) -> Self {
        let thermal = p.thermal.as_ref().map(|t| {
            ThermalModel::new(
                D::from(t.alpha),
                D::from(t.rtv),
                D::from(t.ctv),
                D::from(t.rtm),
                D::from(t.ctm),
                D::from(t.rv),
            )
        });
        let parts = Parts {
            re: D::from(p.re),
            le: p.le.lift(),
            l2r2: p.l2r2.as_ref().map(|(l2, r2)| (l2.lift(), r2.lift())),
            bl: p.bl.lift(),
            kms: p.kms.lift(),
            mms: D::from(p.mms),
            rms: D::from(p.rms),
            le_i: p.le_i.as_ref().map(|g| g.lift()),
            rms_v: p.rms_v.as_ref().map(|r| r.lift()),
        };
        Model { thermal, ..Model::from_parts(parts) }
    }

    /// The model of these constants and series, without the thermal network (a fit carries
    /// the heating in its `Re(t)` track instead).
    pub fn from_parts(p: Parts<D>) -> Self {
        let inv_l2 = p.l2r2.as_ref().filter(|(l2, _)| l2.c.len() == 1).map(|(l2, _)| l2.c[0].recip());
        Model {
            re: p.re,
            le: p.le,
            l2r2: p.l2r2,
            bl: p.bl,
            kms: p.kms,
            mms: p.mms,
            rms: p.rms,
            thermal: None,
            le_i: p.le_i,
            rms_v: p.rms_v,
            inv_mms: p.mms.recip(),
            inv_l2,
        }
    }

    /// Flux modulation at current `i`: `(g(i), h(i) = d(i g)/di, G(i) = int_0^i s g(s) ds)`;
    /// `(1, 1, i^2 / 2)` without `Le_i`. The flux is `Le(x) g i`, the incremental inductance
    /// `Le(x) h`, the magnetic coenergy `Le(x) G` and the energy `Le(x) (i^2 g - G)`.
    #[inline]
    pub fn flux_factors(&self, i: D) -> (D, D, D) {
        match &self.le_i {
            None => (D::one(), D::one(), i * i * 0.5),
            Some(g) => {
                // Horner on the three series in i: sum c_k i^k, sum (k+1) c_k i^k and
                // sum c_k i^k / (k+2) (then times i^2).
                let (mut gv, mut hv, mut big) = (D::zero(), D::zero(), D::zero());
                for (k, &c) in g.c.iter().enumerate().rev() {
                    let k = k as f64;
                    gv = gv * i + c;
                    hv = hv * i + c * (k + 1.0);
                    big = big * i + c * (1.0 / (k + 2.0));
                }
                (gv, hv, big * i * i)
            }
        }
    }

    /// The incremental inductance factor `h(i)` (1 without `Le_i`).
    pub fn le_i_incremental(&self, i: D) -> D {
        self.flux_factors(i).1
    }

    /// The mechanical resistance at velocity `v`: `Rms(|v|)`, or `Rms`.
    #[inline]
    pub fn rms_at(&self, v: D) -> D {
        match &self.rms_v {
            Some(r) => r.eval(v.abs()),
            None => self.rms,
        }
    }

    /// Voice-coil resistance at the voice-coil temperature rise `tv` (K).
    #[inline]
    pub fn re_at(&self, tv: D) -> D {
        match &self.thermal {
            Some(t) => self.re * (t.alpha * tv + 1.0),
            None => self.re,
        }
    }

    /// Time derivative of the state for terminal voltage `u`.
    #[inline]
    pub fn deriv(&self, s: &State<D>, u: D) -> State<D> {
        let [x, v, i, i2, tv, tm] = *s;
        let (le, dle) = self.le.eval_d(x);
        let bl = self.bl.eval(x);
        let kms = self.kms.eval(x);
        let re_t = self.re_at(tv);
        // LR-2 branch: voltage across it, its inductance slope, and its current derivative.
        let (u_l2r2, f_l2, di2, r2_loss) = match &self.l2r2 {
            Some((l2p, r2p)) => {
                let (l2, dl2) = l2p.eval_d(x);
                let r2 = r2p.eval(x);
                let u2 = r2 * (i - i2);
                // d(L2 i2)/dt = u2  =>  L2 di2/dt = u2 - L2' v i2
                let di2 = (u2 - dl2 * v * i2) * self.inv_l2.unwrap_or_else(|| l2.recip());
                (u2, dl2 * i2 * i2 * 0.5, di2, u2 * (i - i2))
            }
            None => (D::zero(), D::zero(), D::zero(), D::zero()),
        };
        // d(Le g(i) i)/dt = u - Re i - Bl v - u_L2R2  =>  Le h di/dt = ... - Le' v g i; the
        // reluctance force Le' G(i) (Le' i^2 / 2 without Le_i); the loss Rms(|v|) v.
        let (di, f_le, rms) = if self.le_i.is_none() && self.rms_v.is_none() {
            // Times the reciprocal rather than divided: the reciprocal starts as soon as Le(x)
            // is known, alongside the numerator, instead of after it (RK4's stages wait on
            // this value). With the constants' reciprocals below: the full model 2.59 -> 2.77 M
            // samples/s on SB17, 2.32 -> 2.42 on 18WU (divan medians; the machine moves 5-10 %).
            ((u - re_t * i - bl * v - u_l2r2 - dle * v * i) * le.recip(), dle * i * i * 0.5, self.rms)
        } else {
            self.flux_modulated(u - re_t * i - bl * v - u_l2r2, le, dle, i, v)
        };
        let force = bl * i - rms * v - kms * x + f_le + f_l2;
        let dv = force * self.inv_mms;
        let (dtv, dtm) = match &self.thermal {
            Some(t) => t.rates(tv, tm, re_t * i * i, r2_loss, v.abs()),
            None => (D::zero(), D::zero()),
        };
        [v, dv, di, di2, dtv, dtm]
    }

    /// The linear network of the currents at displacement `x` and coil temperature rise `tv`
    /// (1/s): `d(i, i2)/dt = A (i, i2) + ...` with `A = [[-(Re(T) + R2) / Le, R2 / Le],
    /// [R2 / L2, -R2 / L2]]`. The stiff part of the model, which
    /// [`crate::integrate::etd4_step`] integrates exactly; the motional terms (`Le' v`,
    /// `L2' v`) and flux modulation are left out (they are slow), and an LR-3 branch is in
    /// [`Model::electrical_matrix3`]'s network instead.
    #[inline]
    pub fn electrical_matrix(&self, x: D, tv: D) -> [[D; 2]; 2] {
        let inv_le = self.le.eval(x).recip();
        let re = self.re_at(tv);
        match &self.l2r2 {
            Some((l2, r2)) => {
                let r2 = r2.eval(x);
                let g2 = r2 * l2.eval(x).recip();
                [[-(re + r2) * inv_le, r2 * inv_le], [g2, -g2]]
            }
            None => [[-re * inv_le, D::zero()], [D::zero(), D::zero()]],
        }
    }

    /// [`Model::electrical_matrix`] with an LR-3 branch `(L3, R3)` in series (H, ohm): the
    /// network of `(i, i2, i3)`, `A = -L^-1 R` with `L = diag(Le, L2, L3)` and `R = [[Re(T) +
    /// R2 + R3, -R2, -R3], [-R2, R2, 0], [-R3, 0, R3]]` (1/s). [`ExtModel`]'s, which
    /// [`crate::integrate::etd4_step`] then integrates exactly.
    #[inline]
    pub fn electrical_matrix3(&self, x: D, tv: D, l3: D, r3: D) -> [[D; 3]; 3] {
        let inv_le = self.le.eval(x).recip();
        let re = self.re_at(tv);
        let g3 = r3 * l3.recip();
        let z = D::zero();
        match &self.l2r2 {
            Some((l2, r2)) => {
                let r2 = r2.eval(x);
                let g2 = r2 * l2.eval(x).recip();
                [[-(re + r2 + r3) * inv_le, r2 * inv_le, r3 * inv_le], [g2, -g2, z], [g3, z, -g3]]
            }
            None => [[-(re + r3) * inv_le, z, r3 * inv_le], [z, z, z], [g3, z, -g3]],
        }
    }

    /// The current's own rate `-(Re(T) + R2(x)) / Le(x)` (1/s, the `A[0][0]` of
    /// [`Model::electrical_matrix`]) and [`Model::input_gain`], from one evaluation of
    /// `Le(x)`: what [`crate::integrate::etdc_step`] takes exactly.
    #[inline]
    pub fn current_rate_and_gain(&self, x: D, i: D, tv: D) -> (D, D) {
        let inv_le = self.le.eval(x).recip();
        let r2 = self.l2r2.as_ref().map_or(D::zero(), |(_, r2)| r2.eval(x));
        let gain = match &self.le_i {
            None => inv_le,
            Some(_) => inv_le * self.le_i_incremental(i).recip(),
        };
        (-(self.re_at(tv) + r2) * inv_le, gain)
    }

    /// How the terminal voltage enters the current's rate at displacement `x` and current
    /// `i`: `d(di/dt)/du = 1 / (Le(x) h(i))` (1/H; `h = 1` without `Le_i`).
    #[inline]
    pub fn input_gain(&self, x: D, i: D) -> D {
        let le = self.le.eval(x);
        match &self.le_i {
            None => le.recip(),
            Some(_) => (le * self.le_i_incremental(i)).recip(),
        }
    }

    /// The current derivative, the reluctance force and the loss with `Le_i` or `Rms_v`:
    /// `(u_rest - Le' v g i) / (Le h)`, `Le' G(i)`, `Rms(|v|)`, where `u_rest` is the terminal
    /// voltage less `Re i`, `Bl v` and the LR-2 branch. Kept out of line: inlined, it made the
    /// plain model's `deriv` (the hot path of every fit) 15-30 % slower.
    #[inline(never)]
    fn flux_modulated(&self, u_rest: D, le: D, dle: D, i: D, v: D) -> (D, D, D) {
        let (g, h, big) = self.flux_factors(i);
        ((u_rest - dle * v * i * g) / (le * h), dle * big, self.rms_at(v))
    }

    /// Energy stored in the moving system (J): kinetic, suspension (`int Kms(s) s ds`) and
    /// magnetic (`Le (i^2 g(i) - G(i)) + 1/2 L2 i2^2`, which is `1/2 Le i^2 + ...` without
    /// `Le_i`). Heat is not included: it leaves as loss.
    pub fn stored_energy(&self, s: &State<D>) -> D {
        let [x, v, i, i2, _, _] = *s;
        let (g, _, big) = self.flux_factors(i);
        let mut e = self.mms * v * v * 0.5 + self.kms.moment_integral(x) + self.le.eval(x) * (i * i * g - big);
        if let Some((l2, _)) = &self.l2r2 {
            e += l2.eval(x) * i2 * i2 * 0.5;
        }
        e
    }

    /// Power flows at a state for terminal voltage `u`.
    pub fn powers(&self, s: &State<D>, u: D) -> Powers<D> {
        let [x, v, i, i2, tv, _] = *s;
        let r2_loss = match &self.l2r2 {
            Some((_, r2)) => r2.eval(x) * (i - i2) * (i - i2),
            None => D::zero(),
        };
        Powers {
            input: u * i,
            re_loss: self.re_at(tv) * i * i,
            r2_loss,
            rms_loss: self.rms_at(v) * v * v,
            r3_loss: D::zero(),
            creep_loss: D::zero(),
            box_loss: D::zero(),
        }
    }
}

/// Maxwell elements of the creep bank ([`crate::creep::taus`]).
pub const NCREEP: usize = 10;
/// States of the extended model: the six of [`Model`], the LR-3 branch current `i3`, and the
/// creep bank's damper positions `y_k` (m).
pub const NEXT: usize = NSTATE + 1 + NCREEP;
/// Index of the extended model's own states.
pub mod ext_idx {
    pub const I3: usize = super::NSTATE;
    pub const Y0: usize = super::NSTATE + 1;
    /// The box's first state, its gauge pressure `p` (Pa); then the port's flow `U` (m^3/s)
    /// or the radiator's `xp` (m) and `vp` (m/s).
    pub const BOX: usize = super::NEXT;
}

/// States of an extended model without the creep bank (LR-3 only): the six of [`Model`] and
/// `i3`, the first [`NLR3`] of [`ExtState`].
pub const NLR3: usize = NSTATE + 1;
/// The extended model's state vector `[x, v, i, i2, Tv, Tm, i3, y_1 .. y_NCREEP]`.
pub type ExtState<D> = [D; NEXT];
/// States of an extended model with a box: [`NEXT`] and the box's
/// ([`crate::enclosure::NBOXSTATE`]: its pressure, then the port's flow or the radiator's
/// excursion and velocity), from [`ext_idx::BOX`] on.
pub const NBOX: usize = NEXT + crate::enclosure::NBOXSTATE;

/// The creep bank in the model's scalar type (see [`crate::creep`]).
#[derive(Clone, Debug)]
pub struct CreepBank<D> {
    /// Stiffness of each element, `lambda Kms(0) / PER_DECADE` (N/m).
    pub dk: D,
    /// What the bank adds to the real stiffness at `f_ref`, taken off the static spring (N/m).
    pub kc: D,
    /// `1 / tau_k` (1/s).
    pub rate: [f64; NCREEP],
}

/// [`Model`] with the effects of real drivers that need states of their own (formats.md
/// "Extensions"), added as components to the same equations:
///
/// ```text
/// u  = ... + R3 (i - i3),                  L3 di3/dt = R3 (i - i3)        (LR-3, in series with LR-2)
/// Mms dv/dt = ... + Kc x - sum_k dK (x - y_k),   dy_k/dt = (x - y_k) / tau_k   (creep bank)
/// Ctm dTm/dt = ... + R3 (i - i3)^2          (its loss heats the magnet, as R2's does)
/// ```
///
/// The static spring is `Kms(x) - Kc`: the real part of the dynamic stiffness at `f_ref` is
/// `Kms(x)`. A box ([`crate::enclosure`]) adds the force `Sd p` of its air on the cone and
/// its own states from [`ext_idx::BOX`] on ([`NBOX`] states). Without any of these use
/// [`Model`] (six states: the fast path).
#[derive(Clone, Debug)]
pub struct ExtModel<D> {
    pub base: Model<D>,
    pub lr3: Option<(D, D)>,
    pub creep: Option<CreepBank<D>>,
    pub enclosure: Option<crate::enclosure::BoxModel<D>>,
}

impl ExtModel<f64> {
    /// The extended model of a parameter set.
    pub fn new(p: &Parameters) -> Self {
        ExtModel::<f64>::lift_from(p)
    }
}

impl<D: DualNum<Primitive = f64> + Copy> ExtModel<D> {
    /// The extended model of a parameter set in scalar type `D`.
    pub fn lift_from(p: &Parameters) -> Self {
        let (lambda, f_ref) = match &p.creep {
            Some(c) => {
                (Some(D::from(c.lambda)), Some(c.f_ref.unwrap_or_else(|| p.creep_f_ref().expect("creep present"))))
            }
            None => (None, None),
        };
        let enclosure = p.enclosure.as_ref().map(|e| {
            crate::enclosure::BoxModel::new(e, p.kms.c[0], p.mms, p.sd.expect("a set with a box has Sd (validated)"))
        });
        ExtModel {
            enclosure,
            ..ExtModel::from_parts(Model::lift_from(p), p.l3r3.map(|(l, r)| (D::from(l), D::from(r))), lambda, f_ref)
        }
    }

    /// The extended model of a [`Model`] and the effects' values in scalar type `D` (what a
    /// fit whose unknowns include them builds): LR-3 `(L3, R3)`, and creep's `lambda` with
    /// its reference `f_ref` (Hz; `None`: the resonance `sqrt(Kms(0) / Mms) / 2 pi`, which
    /// then moves with the unknowns).
    pub fn from_parts(base: Model<D>, lr3: Option<(D, D)>, lambda: Option<D>, f_ref: Option<f64>) -> Self {
        let creep = lambda.map(|lambda| {
            let taus = crate::creep::taus();
            assert_eq!(taus.len(), NCREEP, "the creep bank's size changed: update model::NCREEP");
            let k0 = base.kms.c[0];
            let w_ref = match f_ref {
                Some(f) => D::from(2.0 * std::f64::consts::PI * f),
                None => (k0 / base.mms).sqrt(),
            };
            CreepBank {
                dk: lambda * k0 / crate::creep::PER_DECADE as f64,
                kc: lambda * k0 * crate::creep::bank_re(w_ref),
                rate: std::array::from_fn(|k| 1.0 / taus[k]),
            }
        });
        ExtModel { base, lr3, creep, enclosure: None }
    }

    /// Time derivative of the extended state for terminal voltage `u`.
    #[inline]
    pub fn deriv(&self, s: &ExtState<D>, u: D) -> ExtState<D> {
        self.deriv_n(s, u)
    }

    /// [`ExtModel::deriv`] on the first `M` states: `M` = [`NBOX`] with a box, [`NEXT`]
    /// without, or [`NLR3`] (the six of [`Model`] and `i3`) when there is no creep bank either. An LR-3 model without creep then
    /// carries 7 states instead of 17: ten fewer dual numbers through every RK4 stage of a
    /// fit (measured: an LR-3 iteration of `identify` took twice a plain one's time).
    #[inline]
    pub fn deriv_n<const M: usize>(&self, s: &[D; M], u: D) -> [D; M] {
        debug_assert!(
            M == NBOX
                || (M == NEXT && self.enclosure.is_none())
                || (M == NLR3 && self.creep.is_none() && self.enclosure.is_none()),
            "{M} states cannot hold this model"
        );
        let base: State<D> = std::array::from_fn(|k| s[k]);
        let b = self.base.deriv(&base, u);
        let mut d = [D::zero(); M];
        d[..NSTATE].copy_from_slice(&b);
        let (x, i) = (s[idx::X], s[idx::I]);
        if let Some((l3, r3)) = self.lr3 {
            // The current equation: Le(x) h(i) di/dt = (what `Model` has) - u3.
            let i3 = s[ext_idx::I3];
            let u3 = r3 * (i - i3);
            d[ext_idx::I3] = u3 / l3;
            d[idx::I] -= u3 / (self.base.le.eval(x) * self.base.le_i_incremental(i));
            if let Some(t) = &self.base.thermal {
                d[idx::TM] += u3 * (i - i3) / t.ctm;
            }
        }
        if let Some(c) = &self.creep {
            let mut force = c.kc * x;
            for k in 0..NCREEP {
                let y = s[ext_idx::Y0 + k];
                force -= c.dk * (x - y);
                d[ext_idx::Y0 + k] = (x - y) * c.rate[k];
            }
            d[idx::V] += force / self.base.mms;
        }
        if let Some(b) = &self.enclosure {
            let r = b.rates(x, s[idx::V], std::array::from_fn(|k| s[ext_idx::BOX + k]));
            d[idx::V] += r.force / self.base.mms;
            d[ext_idx::BOX..ext_idx::BOX + crate::enclosure::NBOXSTATE].copy_from_slice(&r.d);
        }
        d
    }

    /// Stored energy (J): [`Model::stored_energy`] with the static spring `Kms(x) - Kc`, the
    /// creep springs `1/2 dK (x - y_k)^2`, the LR-3 inductance `1/2 L3 i3^2` and the box's
    /// ([`crate::enclosure::BoxModel::stored_energy`]), on [`NEXT`] or [`NBOX`] states.
    pub fn stored_energy<const M: usize>(&self, s: &[D; M]) -> D {
        let base: State<D> = std::array::from_fn(|k| s[k]);
        let mut e = self.base.stored_energy(&base);
        let x = s[idx::X];
        if let Some((l3, _)) = self.lr3 {
            e += l3 * s[ext_idx::I3] * s[ext_idx::I3] * 0.5;
        }
        if let Some(c) = &self.creep {
            e -= c.kc * x * x * 0.5;
            for k in 0..NCREEP {
                let dx = x - s[ext_idx::Y0 + k];
                e += c.dk * dx * dx * 0.5;
            }
        }
        if let (Some(b), true) = (&self.enclosure, M == NBOX) {
            e += b.stored_energy(x, std::array::from_fn(|k| s[ext_idx::BOX + k]));
        }
        e
    }

    /// Power flows at a state for terminal voltage `u`, on [`NEXT`] or [`NBOX`] states.
    pub fn powers<const M: usize>(&self, s: &[D; M], u: D) -> Powers<D> {
        let base: State<D> = std::array::from_fn(|k| s[k]);
        let mut p = self.base.powers(&base, u);
        if let Some((_, r3)) = self.lr3 {
            let d = s[idx::I] - s[ext_idx::I3];
            p.r3_loss = r3 * d * d;
        }
        if let Some(c) = &self.creep {
            let x = s[idx::X];
            for k in 0..NCREEP {
                // Damper force dK (x - y) times its velocity (x - y) / tau.
                let dx = x - s[ext_idx::Y0 + k];
                p.creep_loss += c.dk * dx * dx * c.rate[k];
            }
        }
        if let (Some(b), true) = (&self.enclosure, M == NBOX) {
            p.box_loss = b.loss(std::array::from_fn(|k| s[ext_idx::BOX + k]));
        }
        p
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::embedded_driver;
    use num_dual::Dual64;

    /// [`Model::deriv_partials`] against dual numbers: lanes on the four states and on
    /// shifts of each value the parameters enter through (`Bl(x)`, `Kms(x)`, `Le(x)` by
    /// their constant terms, `Le'(x)` by a slope through `x`, and `Re`, `Rms`, `R2`, `L2`,
    /// `Le_i`'s `c_1`, `c_2` and `Rms_v`'s `c_2`), SB17's curves off rest, the plain model
    /// and one with `Le_i` and `Rms_v`, to 1e-12 of each rate's largest term; the rates
    /// themselves to the last bit.
    #[test]
    fn the_derivative_partials_are_the_dual_numbers() {
        use crate::jet::Jet;
        type J = Jet<15>;
        let p = embedded_driver("sb17cac35-4").unwrap();
        let (l2, r2) = p.l2r2.as_ref().map(|(l, r)| (l.c[0], r.c[0])).unwrap();
        let (s, u): (State<f64>, f64) = ([2e-3, 0.3, 1.5, 0.4, 0.0, 0.0], 5.0);
        let lane = |k: usize, v: f64| J::constant(v).derivative(k);
        let shifted = |c: &[f64], k: usize| -> Poly<J> {
            Poly { c: c.iter().enumerate().map(|(j, &v)| if j == 0 { lane(k, v) } else { J::constant(v) }).collect() }
        };
        for effects in [false, true] {
            let (g, c2) = ([1.0, -0.05, 0.02], 0.4);
            // Le'(x) by eps: Le + eps (z - x) leaves Le(x) and moves its slope.
            let mut le = shifted(p.le.coefficients(), 6);
            le.c[0] -= J::constant(0.0).derivative(7) * s[0];
            le.c[1] += J::constant(0.0).derivative(7);
            let (le_i, rms_v) = if effects {
                (
                    Some(Poly { c: vec![J::constant(1.0), lane(12, g[1]), lane(13, g[2])] }),
                    Some(Poly { c: vec![lane(9, p.rms), J::constant(0.0), lane(14, c2)] }),
                )
            } else {
                (None, None)
            };
            let md = Model::from_parts(Parts {
                re: lane(8, p.re),
                le,
                l2r2: Some((Poly::constant(lane(11, l2)), Poly::constant(lane(10, r2)))),
                bl: shifted(p.bl.coefficients(), 4),
                kms: shifted(p.kms.coefficients(), 5),
                mms: J::constant(p.mms),
                rms: lane(9, p.rms),
                le_i,
                rms_v,
            });
            let sd: State<J> = std::array::from_fn(|k| if k < 4 { lane(k, s[k]) } else { J::constant(0.0) });
            let dd = md.deriv(&sd, J::constant(u));
            let (le_i, rms_v) = if effects {
                (Some(Poly { c: g.to_vec() }), Some(Poly { c: vec![p.rms, 0.0, c2] }))
            } else {
                (None, None)
            };
            let m = Model::from_parts(Parts {
                re: p.re,
                le: p.le.clone(),
                l2r2: Some((Poly::constant(l2), Poly::constant(r2))),
                bl: p.bl.clone(),
                kms: p.kms.clone(),
                mms: p.mms,
                rms: p.rms,
                le_i,
                rms_v,
            });
            let (d, q) = m.deriv_partials(&s, u).expect("a fit's model");
            let (lei, rv) = if effects { (q.le_i, q.rms_v2) } else { ([[0.0; 2]; 2], 0.0) };
            // Row by row: (rate, [(lane, partial)]).
            let rows: [(usize, Vec<(usize, f64)>); 3] = [
                (
                    idx::V,
                    vec![
                        (0, q.v_state[0]),
                        (1, q.v_state[1]),
                        (2, q.v_state[2]),
                        (3, 0.0),
                        (4, q.bl[0]),
                        (5, q.kms),
                        (6, 0.0),
                        (7, q.dle[0]),
                        (8, 0.0),
                        (9, q.rms),
                        (10, 0.0),
                        (11, 0.0),
                        (12, lei[0][0]),
                        (13, lei[1][0]),
                        (14, rv),
                    ],
                ),
                (
                    idx::I,
                    vec![
                        (0, q.i_state[0]),
                        (1, q.i_state[1]),
                        (2, q.i_state[2]),
                        (3, q.i_state[3]),
                        (4, q.bl[1]),
                        (5, 0.0),
                        (6, q.le),
                        (7, q.dle[1]),
                        (8, q.re),
                        (9, 0.0),
                        (10, q.r2[0]),
                        (11, 0.0),
                        (12, lei[0][1]),
                        (13, lei[1][1]),
                        (14, 0.0),
                    ],
                ),
                (
                    idx::I2,
                    vec![
                        (0, 0.0),
                        (1, 0.0),
                        (2, q.i2_state[0]),
                        (3, q.i2_state[1]),
                        (4, 0.0),
                        (5, 0.0),
                        (6, 0.0),
                        (7, 0.0),
                        (8, 0.0),
                        (9, 0.0),
                        (10, q.r2[1]),
                        (11, q.l2),
                        (12, 0.0),
                        (13, 0.0),
                        (14, 0.0),
                    ],
                ),
            ];
            let size = [s[0], s[1], s[2], s[3], 1.0, 1.0, 1.0, 1.0, p.re, p.rms, r2, l2, 1.0, 1.0, 1.0];
            for (row, want) in rows {
                assert_eq!(d[row], dd[row].re, "rate {row} (effects {effects})");
                let big = want.iter().map(|(k, _)| (dd[row].eps[*k] * size[*k]).abs()).fold(d[row].abs(), f64::max);
                for (k, got) in want {
                    assert!(
                        (got - dd[row].eps[k]).abs() <= 1e-12 * big,
                        "rate {row}, lane {k} (effects {effects}): {got:e} against {:e}",
                        dd[row].eps[k]
                    );
                }
            }
            // dx/dt = v, the thermal states off.
            assert_eq!(dd[idx::X].eps[1], 1.0);
        }
        let m = Model::new(&p);
        assert!(m.thermal.is_some() && m.deriv_partials(&s, u).is_none(), "a thermal network has no partials here");
    }

    #[test]
    fn static_equilibrium_under_dc_current_balances_force() {
        // With v = 0 and a DC current, dv/dt = 0 where Bl(x) i + 1/2 Le'(x) i^2 = Kms(x) x.
        let p = embedded_driver("sb17cac35-4").unwrap().three_state();
        let m = Model::new(&p);
        let i = 0.3;
        // Solve the static balance by bisection: the slow, obvious oracle.
        let f = |x: f64| p.bl.eval(x) * i + 0.5 * p.le.eval_d(x).1 * i * i - p.kms.eval(x) * x;
        let (mut a, mut b) = (-0.005, 0.005);
        for _ in 0..100 {
            let c = 0.5 * (a + b);
            if f(a) * f(c) <= 0.0 {
                b = c
            } else {
                a = c
            }
        }
        let x = 0.5 * (a + b);
        let d = m.deriv(&[x, 0.0, i, 0.0, 0.0, 0.0], p.re * i);
        assert!(d[idx::V].abs() < 1e-9, "{:?}", d);
        assert!(d[idx::I].abs() < 1e-9, "{:?}", d);
        assert!(x > 0.0, "positive current pushes the coil out");
    }

    #[test]
    fn powers_close_the_energy_balance_instantaneously() {
        // d/dt E_stored = P_in - losses, using dual numbers for dE/dt = grad E . f.
        for name in crate::params::embedded_driver_names() {
            let p = embedded_driver(name).unwrap();
            let m = Model::new(&p);
            let md: Model<Dual64> = Model::lift_from(&p);
            let s = [0.003, -0.4, 1.7, 0.6, 20.0, 2.0];
            let u = 7.5;
            let ds = m.deriv(&s, u);
            // Directional derivative of the stored energy along the flow.
            let sd: State<Dual64> = std::array::from_fn(|k| Dual64::new(s[k], ds[k]));
            let de_dt = md.stored_energy(&sd).eps;
            let pw = m.powers(&s, u);
            let balance = pw.input - pw.re_loss - pw.r2_loss - pw.rms_loss;
            assert!((de_dt - balance).abs() < 1e-12 * pw.input.abs(), "{name}: {de_dt} vs {balance}");
        }
    }

    /// The extended model conserves energy: dE/dt = P_in - every loss, with creep, LR-3,
    /// Le(i) (an asymmetric g(i)) and Rms(v).
    #[test]
    fn the_extended_model_closes_the_energy_balance_instantaneously() {
        for name in crate::params::embedded_driver_names() {
            let mut p = embedded_driver(name).unwrap();
            let (l2, r2) = p.l2r2.as_ref().map(|(l, r)| (l.c[0], r.c[0])).unwrap();
            p.creep = Some(crate::params::Creep { lambda: 0.07, f_ref: None });
            p.l3r3 = Some((0.6 * l2, 2.5 * r2));
            p.le_i = Some(Poly { c: vec![1.0, 0.02, -0.015] });
            p.rms_v = Some(Poly { c: vec![p.rms, 0.1 * p.rms, 0.8 * p.rms] });
            let m = ExtModel::new(&p);
            let md: ExtModel<Dual64> = ExtModel::lift_from(&p);
            let mut s = [0.0; NEXT];
            s[..NSTATE].copy_from_slice(&[0.003, -0.4, 1.7, 0.6, 20.0, 2.0]);
            s[ext_idx::I3] = -0.3;
            for k in 0..NCREEP {
                s[ext_idx::Y0 + k] = 0.001 * (k as f64 - 4.0);
            }
            let u = 7.5;
            let ds = m.deriv(&s, u);
            let sd: ExtState<Dual64> = std::array::from_fn(|k| Dual64::new(s[k], ds[k]));
            let de_dt = md.stored_energy(&sd).eps;
            let pw = m.powers(&s, u);
            assert!(pw.r3_loss > 0.0 && pw.creep_loss > 0.0);
            let balance = pw.input - pw.re_loss - pw.r2_loss - pw.rms_loss - pw.r3_loss - pw.creep_loss;
            assert!((de_dt - balance).abs() < 1e-12 * pw.input.abs(), "{name}: {de_dt} vs {balance}");
        }
    }

    /// Flux modulation against its definition, by slow numerics: the voltage across the voice
    /// coil is d/dt of the flux `Le(x) g(i) i` (central differences along the flow), and the
    /// reluctance force is d/dx of the coenergy `int_0^i Le(x) g(s) s ds` (Simpson's rule,
    /// central difference in x).
    #[test]
    fn flux_modulation_follows_from_the_flux_and_the_coenergy() {
        let mut p = embedded_driver("sb17cac35-4").unwrap();
        p.thermal = None;
        let g = Poly { c: vec![1.0, 0.03, -0.02, 0.004] };
        p.le_i = Some(g.clone());
        let m = ExtModel::new(&p);
        let base = Model::new(&Parameters { le_i: None, ..p.clone() });
        let (x, v, i, i2) = (0.002, 0.7, 2.1, 0.4);
        let mut s = [0.0; NEXT];
        s[..4].copy_from_slice(&[x, v, i, i2]);
        let u = 9.0;
        let d = m.deriv(&s, u);
        let psi = |x: f64, i: f64| p.le.eval(x) * g.eval(i) * i;
        // di/dt is ~1e4 A/s: a step of 1e-9 s keeps the second-order term below 1e-9.
        let h = 1e-9;
        let dpsi = (psi(x + v * h, i + d[idx::I] * h) - psi(x - v * h, i - d[idx::I] * h)) / (2.0 * h);
        let (l2, r2) = p.l2r2.as_ref().unwrap();
        let coil = u - p.re * i - p.bl.eval(x) * v - r2.eval(x) * (i - i2);
        assert!((dpsi - coil).abs() < 1e-7 * coil.abs(), "dpsi/dt {dpsi} vs {coil}");
        let coenergy = |x: f64| {
            let n = 2000;
            let f = |s: f64| p.le.eval(x) * g.eval(s) * s;
            let hh = i / n as f64;
            (0..=n)
                .map(|k| {
                    f(k as f64 * hh)
                        * if k == 0 || k == n {
                            1.0
                        } else if k % 2 == 1 {
                            4.0
                        } else {
                            2.0
                        }
                })
                .sum::<f64>()
                * hh
                / 3.0
        };
        let f_rel = (coenergy(x + 1e-6) - coenergy(x - 1e-6)) / 2e-6;
        let f_rest = p.bl.eval(x) * i - p.rms * v - p.kms.eval(x) * x + 0.5 * l2.eval_d(x).1 * i2 * i2;
        let want = (f_rest + f_rel) / p.mms;
        assert!((d[idx::V] - want).abs() < 1e-6 * want.abs(), "dv/dt {} vs {want}", d[idx::V]);
        // And the rest of the state follows Model's equations.
        let b = base.deriv(&std::array::from_fn(|k| s[k]), u);
        assert_eq!(d[idx::I2], b[idx::I2]);
    }

    /// Without creep and LR-3 the extended model is the model.
    #[test]
    fn the_extended_model_without_effects_is_the_model() {
        let p = embedded_driver("sb17cac35-4").unwrap();
        let (m, e) = (Model::new(&p), ExtModel::new(&p));
        let mut s = [0.0; NEXT];
        s[..NSTATE].copy_from_slice(&[0.003, -0.4, 1.7, 0.6, 20.0, 2.0]);
        let b: State<f64> = std::array::from_fn(|k| s[k]);
        assert_eq!(e.deriv(&s, 3.0)[..NSTATE], m.deriv(&b, 3.0)[..]);
    }

    /// An LR-3 model without creep runs on seven states: the same derivative as on all of
    /// them (the creep states stay at rest and feed nothing back).
    #[test]
    fn the_lr3_model_on_seven_states_is_the_lr3_model_on_all() {
        let mut p = embedded_driver("sb17cac35-4").unwrap();
        let (l2, r2) = (p.l2r2.as_ref().unwrap().0.c[0], p.l2r2.as_ref().unwrap().1.c[0]);
        p.l3r3 = Some((0.6 * l2, 2.5 * r2));
        let e = ExtModel::new(&p);
        let mut s = [0.0; NEXT];
        s[..NLR3].copy_from_slice(&[0.003, -0.4, 1.7, 0.6, 20.0, 2.0, 0.3]);
        let short: [f64; NLR3] = std::array::from_fn(|k| s[k]);
        let (full, seven) = (e.deriv(&s, 3.0), e.deriv_n(&short, 3.0));
        assert_eq!(full[..NLR3], seven[..]);
        assert!(full[NLR3..].iter().all(|d| *d == 0.0));
        assert!(seven[ext_idx::I3] != 0.0);
    }

    #[test]
    fn thermal_nodes_follow_their_equations() {
        let p = embedded_driver("sb17cac35-4").unwrap();
        let t = p.thermal.clone().unwrap();
        let m = Model::new(&p);
        let s = [0.0, 0.0, 2.0, 0.5, 10.0, 3.0];
        let d = m.deriv(&s, 0.0);
        let re_t = p.re * (1.0 + t.alpha * 10.0);
        let r2 = p.l2r2.as_ref().unwrap().1.c[0];
        assert!((d[idx::TV] - (re_t * 4.0 - 7.0 / t.rtv) / t.ctv).abs() < 1e-12);
        assert!((d[idx::TM] - (r2 * 1.5 * 1.5 + 7.0 / t.rtv - 3.0 / t.rtm) / t.ctm).abs() < 1e-12);
        // Convection: at 0.5 m/s (either direction) with rv 2 s/m the coil-to-magnet flow
        // doubles; the heat leaving the coil is the heat reaching the magnet.
        let mut q = p.clone();
        q.thermal.as_mut().unwrap().rv = 2.0;
        let m = Model::new(&q);
        for v in [0.5, -0.5] {
            let d = m.deriv(&[0.0, v, 2.0, 0.5, 10.0, 3.0], 0.0);
            assert!((d[idx::TV] - (re_t * 4.0 - 2.0 * 7.0 / t.rtv) / t.ctv).abs() < 1e-12);
            assert!((d[idx::TM] - (r2 * 1.5 * 1.5 + 2.0 * 7.0 / t.rtv - 3.0 / t.rtm) / t.ctm).abs() < 1e-12);
        }
    }

    /// The two-node network under held powers as a system for the oracle integrator.
    struct Held<'a>(&'a ThermalModel<f64>, f64, f64, f64);
    impl crate::integrate::Dynamics<f64, 2> for Held<'_> {
        fn deriv(&self, y: &[f64; 2], _u: f64) -> [f64; 2] {
            let (a, b) = self.0.rates(y[0], y[1], self.1, self.2, self.3);
            [a, b]
        }
    }

    /// [`HeldStep`] against the oracle (RK4 with steps of 1e-4 of the coil's time constant,
    /// where its error is below 1e-15 of the rise) for a woofer's network, a microspeaker's
    /// (a coil time constant of 0.1 s against blocks of 2 s: h d about 40, where the explicit
    /// step would need 100 sub-steps) and one with convection at speed, to 1e-10 of the
    /// rise; the rest point is the analytic one (all the heat leaves through Rtm:
    /// `Tm = (Pv + Pm) Rtm`, `Tv = Tm + Pv Rtv(v)`), and two half blocks make one block (the
    /// step is exact, so it composes).
    #[test]
    fn the_held_step_is_the_networks_exact_solution() {
        for (rtv, ctv, rtm, ctm, rv, speed, h) in [
            (3.2f64, 9.0f64, 1.1, 700.0, 0.0f64, 0.0f64, 0.1f64),
            (60.0, 0.0017, 25.0, 2.0, 0.0, 0.0, 2.0),
            (3.2, 9.0, 1.1, 700.0, 1.5, 0.4, 5.0),
        ] {
            let m = ThermalModel::new(0.00393, rtv, ctv, rtm, ctm, rv);
            let (pv, pm, y0) = (2.5, 0.3, [4.0, 1.5]);
            let tau = rtv * ctv / (1.0 + rv * speed);
            let n = ((h / (1e-4 * tau)).ceil() as usize).max(1000);
            let sys = Held(&m, pv, pm, speed);
            let mut oracle = y0;
            for _ in 0..n {
                oracle = crate::integrate::rk4_step(&sys, &oracle, h / n as f64, 0.0, 0.0, 0.0);
            }
            let exact = m.held_step(y0, pv, pm, speed, h);
            let scale = oracle[0].abs().max(1.0);
            for k in 0..2 {
                assert!(
                    (exact[k] - oracle[k]).abs() < 1e-10 * scale,
                    "node {k}: {} vs the oracle's {} (rtv {rtv}, ctv {ctv}, h {h})",
                    exact[k],
                    oracle[k]
                );
            }
            let step = HeldStep::new(&m, 0.5 * h, speed);
            let twice = step.apply(step.apply(y0, pv, pm), pv, pm);
            assert!(
                (twice[0] - exact[0]).abs() < 1e-12 * scale && (twice[1] - exact[1]).abs() < 1e-12 * scale,
                "{twice:?} vs {exact:?}"
            );
            let rest = m.held_step(y0, pv, pm, speed, 1e6 * tau.max(rtm * ctm));
            let tm = (pv + pm) * rtm;
            let tv = tm + pv * rtv / (1.0 + rv * speed);
            assert!(
                (rest[0] - tv).abs() < 1e-9 * tv && (rest[1] - tm).abs() < 1e-9 * tm,
                "rest {rest:?} vs [{tv}, {tm}]"
            );
            assert!(step.is_for(0.5 * h, speed) && !step.is_for(h, speed));
        }
    }
}

//! Pre-inverse compensation (seed paper 3.2.2.2.3, Fig. 6): the inverse of the model, used as
//! a controller ahead of the transducer.
//!
//! Given an input voltage `u_in`, the *linear reference* (the same driver with every power
//! series frozen at its rest value, no `Le_i`, no `Rms_v`, Re cold; see [`linear_reference`])
//! gives the displacement `x_ref(t)` the user asked for. The controller computes the drive
//! `u(t)` that makes the nonlinear model follow `x_ref` exactly. Displacement is the flat
//! output of the model (relative degree three, [`crate::normal_form`]): from `x, v, a, j` of
//! the reference (`a = x''`, `j = x'''`, exact from the reference's state) it takes
//!
//! 1. the current `i` that gives acceleration `a` (the force balance, solved by Newton's
//!    method: `Bl(x) i` plus the reluctance forces, less the suspension and the losses);
//! 2. its rate `di/dt` from the time derivative of that force balance (dual numbers carry
//!    the flow `x' = v, v' = a, ...` through the model);
//! 3. the voltage from the current equation: `u = (di/dt - di/dt|u=0) / (d(di/dt)/du)`,
//!    which is affine in `u`.
//!
//! Every step calls [`Model::deriv`]: the inverse is the model, solved for the input, not a
//! second copy of it. For the three-state model this is the normal form's
//! `u = (x''' - f(z)) / g(z)` (Eq. 9; a test checks they agree). The states the displacement
//! does not fix (the LR-2 branch current `i2`, the two temperatures) are integrated alongside
//! from the model, with the implicit trapezoidal rule for `i2` (stable for any `R2/L2`) and
//! Heun's rule for the temperatures.
//!
//! Sound pressure in the far field follows the cone acceleration, so a displacement that
//! follows the linear reference makes the pressure follow the linear reference's too: the
//! same drive compensates both.
//!
//! Limits, each counted and reported, never silent:
//! - the drive voltage (`max_volts`): samples beyond are clipped;
//! - the force factor: where the effective force per ampere `Bl(x) + Le'(x) i` (the slope
//!   of the force balance in `i`) falls below `min_force_factor` of `Bl(0)`, the current
//!   would run away (Bl(x) -> small at the ends of the gap); the slope is held at that floor,
//!   so the compensation is partial there instead of unbounded;
//! - the range: a reference that leaves `x_range` is refused (the model is not valid there,
//!   and neither is its inverse).
//!
//! Creep and LR-3 are linear effects and belong in the reference, which does not carry them
//! yet: a set with them is refused with that reason.

use crate::model::{idx, Model, State, NSTATE};
use crate::params::Parameters;
use crate::poly::Poly;
use crate::simulate::{simulate, SimError, SimOptions};
use num_dual::Dual64;

/// Options of [`compensate`].
#[derive(Clone, Debug, PartialEq)]
pub struct CompensateOptions {
    /// Largest drive magnitude (V); `None`: unlimited.
    pub max_volts: Option<f64>,
    /// Floor of the effective force factor `Bl(x) + Le'(x) i`, relative to `Bl(0)`.
    pub min_force_factor: f64,
}

impl Default for CompensateOptions {
    fn default() -> Self {
        CompensateOptions { max_volts: None, min_force_factor: 0.2 }
    }
}

/// The compensated drive and what the limits did.
#[derive(Clone, Debug)]
pub struct Compensation {
    /// The drive (V), one sample per input sample.
    pub drive: Vec<f64>,
    /// The displacement the drive makes the model follow (m): the linear reference's.
    pub x_target: Vec<f64>,
    /// The current the drive makes flow (A).
    pub current: Vec<f64>,
    /// Samples clipped at `max_volts`.
    pub clipped: usize,
    /// Samples where the force-factor floor acted.
    pub force_factor_limited: usize,
    /// Largest |drive| (V), after clipping.
    pub peak_volts: f64,
    /// Plain-language notes on the limits that acted.
    pub warnings: Vec<String>,
}

/// The linear reference of `p`: every power series at its rest value, no flux modulation,
/// a constant `Rms`, no thermal model (Re cold). Creep and LR-3 are kept (they are linear).
pub fn linear_reference(p: &Parameters) -> Parameters {
    let at_rest = |f: &Poly| Poly::constant(f.c[0]);
    Parameters {
        bl: at_rest(&p.bl),
        kms: at_rest(&p.kms),
        le: at_rest(&p.le),
        l2r2: p.l2r2.as_ref().map(|(l2, r2)| (at_rest(l2), at_rest(r2))),
        le_i: None,
        rms_v: None,
        thermal: None,
        ..p.clone()
    }
}

/// The drive that makes the transducer `p`, sampled at `fs`, follow the displacement of its
/// linear reference driven by `input` (V). See the module documentation.
pub fn compensate(p: &Parameters, fs: f64, input: &[f64], opts: &CompensateOptions) -> Result<Compensation, SimError> {
    compensate_to(p, &linear_reference(p), fs, input, opts)
}

/// [`compensate`] towards the displacement of another `reference` set driven by `input`
/// (normally a linear one: the pre-inverse identification keeps the reference fixed, from the
/// small-signal parameters, while it adapts `p`).
pub fn compensate_to(
    p: &Parameters,
    reference: &Parameters,
    fs: f64,
    input: &[f64],
    opts: &CompensateOptions,
) -> Result<Compensation, SimError> {
    if p.creep.is_some() || p.l3r3.is_some() {
        return Err(SimError::Input(
            "compensation of a set with creep or LR-3 is not implemented: both are linear and belong in the linear reference, which does not carry them yet; compensate the set without them (the nonlinearities Bl(x), Kms(x), Le(x), Le(i), Rms(v) are compensated)".into(),
        ));
    }
    if !(opts.min_force_factor > 0.0 && opts.min_force_factor < 1.0) {
        return Err(SimError::Input(format!("min_force_factor {} is not valid (0 < f < 1)", opts.min_force_factor)));
    }
    if let Some(m) = opts.max_volts {
        if !(m > 0.0 && m.is_finite()) {
            return Err(SimError::Input(format!("max_volts {m} is not valid (a positive voltage)")));
        }
    }
    let lin = reference;
    let reference = simulate(lin, fs, input, &SimOptions::default()).map_err(|e| match e {
        SimError::OutOfRange { t, reason, .. } => SimError::Input(format!("the linear reference leaves the driver's valid range at t = {t:.4} s ({reason}): the input asks for an excursion the parameter set does not describe; lower the input level")),
        e => e,
    })?;
    let ref_model = Model::new(lin);
    let ref_dual: Model<Dual64> = Model::lift_from(lin);
    let plant = Model::new(p);
    let plant_dual: Model<Dual64> = Model::lift_from(p);
    let bl0 = p.bl.c[0];
    let dt = 1.0 / fs;
    let n = input.len();

    // The reference's x, v, a and j at each sample instant.
    let flow = |k: usize| -> [f64; 4] {
        let s: State<f64> = [reference.x[k], reference.v[k], reference.i[k], reference.i2[k], 0.0, 0.0];
        let d = ref_model.deriv(&s, input[k]);
        let sd: State<Dual64> = std::array::from_fn(|j| Dual64::new(s[j], d[j]));
        let j = ref_dual.deriv(&sd, Dual64::from(input[k]))[idx::V].eps;
        [s[idx::X], s[idx::V], d[idx::V], j]
    };
    // `d(dv/dt)/di` (the effective force factor over Mms) held at or above the floor, and
    // whether the floor acted: the slope both the current's Newton step and its rate divide by.
    let floor = opts.min_force_factor * bl0.abs() / p.mms;
    let floored = |slope: f64| -> (f64, bool) {
        if slope.abs() < floor {
            (floor.copysign(if slope == 0.0 { bl0 } else { slope }), true)
        } else {
            (slope, false)
        }
    };
    // The current that gives acceleration `a` at (x, v) with the other states of `c`, from
    // `i0`; and whether the force-factor floor acted.
    let current = |c: &State<f64>, a: f64, i0: f64| -> (f64, bool) {
        let mut i = i0;
        let mut limited = false;
        for _ in 0..30 {
            let mut sd: State<Dual64> = std::array::from_fn(|j| Dual64::from(c[j]));
            sd[idx::I] = Dual64::new(i, 1.0);
            let dv = plant_dual.deriv(&sd, Dual64::from(0.0))[idx::V];
            let (slope, at_floor) = floored(dv.eps);
            limited |= at_floor;
            let step = (dv.re - a) / slope;
            i -= step;
            if step.abs() <= 1e-13 * (i.abs() + 1e-9) {
                break;
            }
        }
        (i, limited)
    };

    let mut c: State<f64> = [0.0; NSTATE];
    let mut out = Compensation {
        drive: Vec::with_capacity(n),
        x_target: reference.x.clone(),
        current: Vec::with_capacity(n),
        clipped: 0,
        force_factor_limited: 0,
        peak_volts: 0.0,
        warnings: vec![],
    };
    let mut fl = flow(0);
    (c[idx::X], c[idx::V]) = (fl[0], fl[1]);
    let mut limited;
    (c[idx::I], limited) = current(&c, fl[2], reference.i[0]);
    for k in 0..n {
        // di/dt from the time derivative of the force balance: the model's dv/dt along the
        // flow is affine in di/dt.
        let d0 = plant.deriv(&c, 0.0);
        let seeded = |di: f64| -> f64 {
            let mut rates = d0;
            rates[idx::V] = fl[2];
            rates[idx::I] = di;
            let sd: State<Dual64> = std::array::from_fn(|j| Dual64::new(c[j], rates[j]));
            plant_dual.deriv(&sd, Dual64::from(0.0))[idx::V].eps
        };
        let (e0, e1) = (seeded(0.0), seeded(1.0));
        let (slope, at_floor) = floored(e1 - e0);
        limited |= at_floor;
        let di = (fl[3] - e0) / slope;
        // The voltage from the current equation, affine in u.
        let g = plant.deriv(&c, 1.0)[idx::I] - d0[idx::I];
        let mut u = (di - d0[idx::I]) / g;
        if let Some(m) = opts.max_volts {
            if u.abs() > m {
                u = m.copysign(u);
                out.clipped += 1;
            }
        }
        if !u.is_finite() {
            return Err(SimError::OutOfRange {
                t: k as f64 / fs,
                sample: k,
                state: c,
                reason: "the inverse has no finite drive here".into(),
            });
        }
        out.force_factor_limited += limited as usize;
        out.peak_volts = out.peak_volts.max(u.abs());
        out.drive.push(u);
        out.current.push(c[idx::I]);
        if k + 1 == n {
            break;
        }
        // Advance the states the displacement does not fix.
        let fl1 = flow(k + 1);
        let mut c1 = c;
        (c1[idx::X], c1[idx::V]) = (fl1[0], fl1[1]);
        for j in [idx::I2, idx::TV, idx::TM] {
            c1[j] = c[j] + dt * d0[j];
        }
        (c1[idx::I], _) = current(&c1, fl1[2], c[idx::I] + dt * di);
        if p.l2r2.is_some() {
            // di2/dt = b - q i2 (affine in i2): the trapezoidal rule, solved for i2.
            let affine = |s: &State<f64>| {
                let mut z = *s;
                z[idx::I2] = 0.0;
                let b = plant.deriv(&z, 0.0)[idx::I2];
                z[idx::I2] = 1.0;
                (b, b - plant.deriv(&z, 0.0)[idx::I2])
            };
            let ((b0, q0), (b1, q1)) = (affine(&c), affine(&c1));
            c1[idx::I2] = (c[idx::I2] * (1.0 - 0.5 * dt * q0) + 0.5 * dt * (b0 + b1)) / (1.0 + 0.5 * dt * q1);
        }
        let d1 = plant.deriv(&c1, 0.0);
        for j in [idx::TV, idx::TM] {
            c1[j] = c[j] + 0.5 * dt * (d0[j] + d1[j]);
        }
        (c1[idx::I], limited) = current(&c1, fl1[2], c1[idx::I]);
        c = c1;
        fl = fl1;
    }
    if out.clipped > 0 {
        out.warnings.push(format!("the drive was clipped at {:.3} V in {} of {} samples: there the transducer does not follow the linear reference (raise max_volts or lower the input)", opts.max_volts.unwrap_or(f64::INFINITY), out.clipped, n));
    }
    if out.force_factor_limited > 0 {
        out.warnings.push(format!("the force factor fell below {:.0} % of Bl(0) in {} of {} samples: there the compensation is partial (the current it needs runs away as Bl(x) falls)", 100.0 * opts.min_force_factor, out.force_factor_limited, n));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::{embedded_driver, embedded_driver_names};

    fn tone(fs: f64, f: f64, volts: f64, seconds: f64) -> Vec<f64> {
        let n = (seconds * fs) as usize;
        let fade = (0.1 * fs) as usize;
        (0..n)
            .map(|k| {
                let env =
                    if k < fade { 0.5 - 0.5 * (std::f64::consts::PI * k as f64 / fade as f64).cos() } else { 1.0 };
                env * volts * (2.0 * std::f64::consts::PI * f * k as f64 / fs).sin()
            })
            .collect()
    }

    #[test]
    fn the_three_state_inverse_is_the_normal_form_eq9() {
        // u = (x''' - f(z)) / g(z) at every sample of the compensated trajectory.
        for name in embedded_driver_names() {
            let p = embedded_driver(name).unwrap().three_state();
            let fs = 48000.0;
            let u_in = tone(fs, 30.0, 4.0, 0.2);
            let c = compensate(&p, fs, &u_in, &CompensateOptions::default()).unwrap();
            let lin = linear_reference(&p);
            let r = simulate(&lin, fs, &u_in, &SimOptions::default()).unwrap();
            let lm = Model::new(&lin);
            let m = Model::new(&p);
            for k in (100..u_in.len()).step_by(97) {
                let s = [r.x[k], r.v[k], r.i[k], 0.0, 0.0, 0.0];
                let d = lm.deriv(&s, u_in[k]);
                let ld: Model<Dual64> = Model::lift_from(&lin);
                let sd: State<Dual64> = std::array::from_fn(|j| Dual64::new(s[j], d[j]));
                let jerk = ld.deriv(&sd, Dual64::from(u_in[k]))[idx::V].eps;
                let z = [r.x[k], r.v[k], d[idx::V]];
                let st = crate::normal_form::inverse(&m, &z).unwrap();
                let u = (jerk - crate::normal_form::f(&m, &st)) / crate::normal_form::g(&m, &st);
                assert!(
                    (u - c.drive[k]).abs() < 1e-8 * u.abs().max(1.0),
                    "{name} sample {k}: Eq. 9 gives {u}, the inverse {}",
                    c.drive[k]
                );
                assert!((st[2] - c.current[k]).abs() < 1e-9 * st[2].abs().max(1.0));
            }
        }
    }

    #[test]
    fn the_model_driven_by_the_compensated_drive_follows_the_linear_reference() {
        // The full model (LR-2, heating) at a level where Bl, Kms and Le change by tens of %.
        for name in embedded_driver_names() {
            let p = embedded_driver(name).unwrap();
            let fs = 48000.0;
            let [lo, hi] = p.x_range.unwrap();
            let unit = tone(fs, 30.0, 1.0, 0.5);
            let lin = linear_reference(&p);
            let peak = simulate(&lin, fs, &unit, &SimOptions::default()).unwrap().summary();
            let g = 0.8 * hi.min(-lo) / peak.x_max.max(-peak.x_min);
            let u_in: Vec<f64> = unit.iter().map(|v| v * g).collect();
            let c = compensate(&p, fs, &u_in, &CompensateOptions::default()).unwrap();
            assert!(c.warnings.is_empty(), "{name}: {:?}", c.warnings);
            let plain = simulate(&p, fs, &u_in, &SimOptions::default()).unwrap();
            let comp = simulate(&p, fs, &c.drive, &SimOptions::default()).unwrap();
            let dev =
                |x: &[f64]| x.iter().zip(&c.x_target).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max) / hi.min(-lo);
            let (e_plain, e_comp) = (dev(&plain.x), dev(&comp.x));
            println!("{name}: largest deviation from the linear reference, of the range: plain {e_plain:.2e}, compensated {e_comp:.2e}");
            assert!(e_plain > 0.02, "{name}: the level does not make the driver nonlinear ({e_plain:.2e})");
            assert!(e_comp < 1e-7, "{name}: the compensated driver leaves the reference by {e_comp:.2e} of the range");
        }
    }

    #[test]
    fn limits_are_counted_and_named() {
        let p = embedded_driver("sb17cac35-4").unwrap();
        let fs = 48000.0;
        let u_in = tone(fs, 30.0, 3.0, 0.3);
        let c = compensate(&p, fs, &u_in, &CompensateOptions { max_volts: Some(1.0), ..Default::default() }).unwrap();
        assert!(c.clipped > 0 && c.peak_volts <= 1.0);
        assert!(c.warnings.iter().any(|w| w.contains("clipped at 1.000 V")), "{:?}", c.warnings);
        // A reference beyond the range is refused, naming the time.
        let e = compensate(&p, fs, &tone(fs, 20.0, 60.0, 0.3), &CompensateOptions::default()).unwrap_err().to_string();
        assert!(e.contains("leaves the driver's valid range") && e.contains("lower the input level"), "{e}");
        // Creep is refused with the reason.
        let e = compensate(&p.with_typical_creep(), fs, &u_in, &CompensateOptions::default()).unwrap_err().to_string();
        assert!(e.contains("creep or LR-3"), "{e}");
    }
}

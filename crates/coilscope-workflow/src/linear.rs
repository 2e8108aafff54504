//! `coilscope linear`: the small-signal (Thiele/Small) fit of a record or of an impedance
//! curve, its absolute scale, the warnings and the verdict.

use crate::attach_warnings;
use crate::chain::{detect, mark_wiring, ChainMode};
use coilscope_core::chain::{Chain, SenseWiring};
use coilscope_core::mass::Mass;
use coilscope_core::result::ResultFile;
use coilscope_core::{Complex64, Parameters};
use coilscope_ident::checks::{NoiseFloor, Warning};
use coilscope_ident::linear::{
    added_mass_scale, curve_warnings, displacement_scale, fit_impedance_curve, fit_impedance_magnitude,
    fit_linear_record, linear_warnings, lumped_band, predicted_displacement, result, scale_by_mms, EffectsChoice,
    LinearFit, LinearOptions, ScaleMethod,
};
use coilscope_ident::lm::LmState;
use coilscope_io::impedance::ImpedanceCurve;
use coilscope_io::Recording;

/// What a fit of a curve without phase says of it (`fit.phase_note`).
pub const MAGNITUDE_ONLY_NOTE: &str = "the file has no phase: fitted to |Z| alone (a driver's impedance, as the model's, is minimum phase, so |Z| holds what the phase would tell); the sds are those of |Z| alone";

/// What is fitted: a record (voltage and current, optionally displacement) or a measured
/// impedance curve (a shunt's series resistance already taken out).
#[derive(Clone, Debug)]
pub enum LinearInput {
    Record(Recording),
    Curve(ImpedanceCurve),
}

impl LinearInput {
    /// A measured curve as the fit takes it: across the driver alone. A curve measured across
    /// driver and shunt (`wiring`) has the shunt's plain series resistance taken out, which
    /// needs the phase (|Z| - R is not |Z - R|); `origin` names the file in the error.
    pub fn curve_across_driver(mut c: ImpedanceCurve, wiring: SenseWiring, origin: &str) -> Result<Self, String> {
        let r = wiring.series_ohm();
        if c.magnitude_only && r != 0.0 {
            return Err(format!(
                "{origin}: the file has no phase, so the shunt's {r} ohm cannot be taken out of it (|Z| - R is not |Z - R|): export the phase too, or measure with the voltage across the driver's terminals"
            ));
        }
        c.z.iter_mut().for_each(|z| *z -= r);
        Ok(LinearInput::Curve(c))
    }

    fn is_curve(&self) -> bool {
        matches!(self, LinearInput::Curve(_))
    }
}

/// The absolute scale.
#[derive(Clone, Debug)]
pub enum Scale {
    /// The moving mass, weighed or known (with its sd where known).
    Mms(Mass),
    /// An added mass (with its sd where known) and the same driver measured with it (a
    /// record or a curve, as the first input).
    AddedMass { mass: Mass, with: Box<LinearInput>, origin: String },
    /// The record's displacement channel.
    Displacement,
}

/// How to fit.
#[derive(Clone, Debug)]
pub struct LinearRequest {
    pub origin: String,
    pub effects: EffectsChoice,
    pub chain: ChainMode,
    pub wiring: SenseWiring,
    /// Radiating area (m^2), for Vas.
    pub sd: Option<f64>,
    /// A curve's fitted band (Hz).
    pub band: Option<[f64; 2]>,
    /// A curve's measurement level (V rms), for the excursion it reached.
    pub volts: Option<f64>,
}

impl LinearRequest {
    /// A request with the command line's defaults.
    pub fn new(origin: impl Into<String>) -> Self {
        LinearRequest {
            origin: origin.into(),
            effects: EffectsChoice::Auto,
            chain: ChainMode::Detect,
            wiring: SenseWiring::Terminals,
            sd: None,
            band: None,
            volts: None,
        }
    }
}

/// The outcome of [`linear`].
pub struct Linear {
    pub fit: LinearFit,
    pub params: Parameters,
    pub method: ScaleMethod,
    /// The displacement range the record reached (m; a curve's with `volts`, else zero).
    pub x_range: [f64; 2],
    /// The result file, warnings and verdict attached.
    pub result: ResultFile,
    pub warnings: Vec<Warning>,
    pub floor: Option<NoiseFloor>,
    /// The chain was estimated because the record showed one: what it showed.
    pub detected: Vec<String>,
}

impl Linear {
    pub fn trustworthy(&self) -> bool {
        crate::trustworthy(&self.result)
    }
}

/// Peak displacement (m) of a driver with parameters `p` measured with impedance `z` at
/// frequencies `f` by a sine (or stepped sweep) of `volts` RMS: the largest `sqrt(2) |U / Z|
/// |X / I|`, the displacement per current of the small-signal network
/// ([`coilscope_core::small_signal::displacement_per_current`], with creep's dynamic stiffness
/// where the set has creep).
pub fn curve_peak_displacement(p: &Parameters, f: &[f64], z: &[Complex64], volts: f64) -> f64 {
    f.iter()
        .zip(z)
        .map(|(&f, &z)| {
            (std::f64::consts::SQRT_2 * volts / z * coilscope_core::small_signal::displacement_per_current(p, f)).norm()
        })
        .fold(0.0, f64::max)
}

/// Whether a record's fit without the chain shows what a chain does: a skew of the channels
/// (the fit's own check), or an error far above its floor or following the drive.
fn shows_chain(fit: &LinearFit, warnings: &[Warning]) -> bool {
    fit.current_delay.is_some()
        || warnings
            .iter()
            .any(|w| matches!(w.code.as_ref(), "residual-above-noise" | "residual-follows-drive" | "current-delay"))
}

/// The checks of a record's fit ([`linear_warnings`]), on the driver's signals: behind the
/// chain the fit estimated, where it estimated one (its delay and coupling inverted, each
/// channel's offset taken out).
fn record_warnings(fit: &LinearFit, params: &Parameters, r: &Recording) -> (NoiseFloor, Vec<Warning>) {
    let fs = r.fs as f64;
    match fit.chain.as_ref().filter(|c| c.on.iter().any(|&on| on)) {
        Some(c) => {
            let (u, i, _, _) = c.to_chain().invert_calibrated(&r.u, &r.i, fs);
            linear_warnings(fit, params, &u, &i, fs)
        }
        None => linear_warnings(fit, params, &r.u, &r.i, fs),
    }
}

/// Fit one input with `opts`.
fn fit_input(
    input: &LinearInput,
    origin: &str,
    opts: &LinearOptions,
    band: Option<[f64; 2]>,
    progress: &mut dyn FnMut(&LmState),
) -> Result<LinearFit, String> {
    match input {
        LinearInput::Record(r) => fit_linear_record(&r.u, &r.i, r.fs as f64, origin, opts, &mut *progress),
        LinearInput::Curve(c) if c.magnitude_only => fit_impedance_magnitude(
            &c.f,
            &c.z.iter().map(|z| z.norm()).collect::<Vec<_>>(),
            band,
            origin,
            opts,
            &mut *progress,
        ),
        LinearInput::Curve(c) => fit_impedance_curve(&c.f, &c.z, band, origin, opts, &mut *progress),
    }
}

/// The small-signal fit of `input`, scaled by `scale`. A record is first made the driver's
/// terminal signals (a calibrated chain inverted, a shunt's drop taken out); with
/// [`ChainMode::Detect`] its chain is estimated when the record shows one: hum or an offset,
/// or a fit without the chain that misses the record in the ways a chain makes it.
pub fn linear(
    input: LinearInput,
    scale: Scale,
    req: &LinearRequest,
    progress: impl FnMut(&LmState),
) -> Result<Linear, String> {
    let mut progress = progress;
    linear_body(input, scale, req, &mut progress)
}

fn prepare(input: &mut LinearInput, req: &LinearRequest, origin: &str) -> Result<Option<Chain>, String> {
    match input {
        LinearInput::Record(r) => req.chain.prepare(r, origin, req.wiring),
        LinearInput::Curve(_) if matches!(req.chain, ChainMode::Calibrated(_)) => Err(format!("{origin}: an impedance curve has no measurement chain to invert (its tool calibrated it); --chain FILE applies to records")),
        LinearInput::Curve(_) => Ok(None),
    }
}

fn linear_body(
    mut input: LinearInput,
    scale: Scale,
    req: &LinearRequest,
    progress: &mut dyn FnMut(&LmState),
) -> Result<Linear, String> {
    let origin = req.origin.as_str();
    if let Some(v) = req.volts {
        if !(v.is_finite() && v > 0.0 && v < 1000.0) {
            return Err(format!("--volts {v}: give the measurement's RMS voltage (V, 0 .. 1000)"));
        }
    }
    if let Some(s) = req.sd {
        if !(s.is_finite() && s > 0.0 && s < 2.0) {
            return Err(format!("--sd {s}: give the radiating area in m^2 (e.g. 0.0118)"));
        }
    }
    let calibrated = prepare(&mut input, req, origin)?;
    if matches!(scale, Scale::Displacement) && !matches!(&input, LinearInput::Record(r) if r.x.is_some()) {
        return Err(format!("{origin}: no absolute scale: give --mms KG, or --added-mass KG with a second measurement, or record a displacement channel (3)"));
    }
    // The chain: asked for, or found in the record (signs without a fit first).
    let mut detected = match (&req.chain, &input) {
        (ChainMode::Detect, LinearInput::Record(r)) => detect(&r.u, &r.i, r.fs as f64).found,
        _ => vec![],
    };
    let mut chain = req.chain.estimate() || !detected.is_empty();
    let opts = |chain: bool| LinearOptions { effects: req.effects, chain, ..Default::default() };
    // A curve's band: the one given, or where the lumped model holds (below break-up); the
    // measurement with an added mass is fitted in the same band.
    let (mut band_note, mut band_warning) = (None, None);
    let found;
    let req = match (&input, req.band) {
        (LinearInput::Curve(c), None) => {
            let b = lumped_band(&c.f, &c.z, c.magnitude_only, origin, &opts(false))?;
            band_warning = b.warning();
            band_note = Some(b.note);
            found = LinearRequest { band: Some(b.band), ..req.clone() };
            &found
        }
        _ => req,
    };
    let mut fit = fit_input(&input, origin, &opts(chain), req.band, progress)?;
    let (mut mms, mut method) = scale_mms(&fit, &input, &scale, req, origin, chain)?;
    let mut params = scale_by_mms(&fit, mms)?;
    // Looking for the skew and the coupling: a record whose plain fit misses in the ways a
    // chain makes it is fitted again with the chain, kept where that finds one.
    if let (ChainMode::Detect, false, LinearInput::Record(r)) = (&req.chain, chain, &input) {
        let (_, w) = record_warnings(&fit, &params, r);
        if shows_chain(&fit, &w) {
            let with = fit_input(&input, origin, &opts(true), req.band, progress)?;
            if let Some(c) = with.chain.as_ref().filter(|c| c.on.iter().any(|&on| on)) {
                detected.push(format!(
                    "the fit without a chain missed the record, and the fit with it found {}",
                    coilscope_core::chain::Chain::describe_fitted(&c.to_chain(), r.fs as f64)
                ));
                chain = true;
                fit = with;
                (mms, method) = scale_mms(&fit, &input, &scale, req, origin, chain)?;
                params = scale_by_mms(&fit, mms)?;
            }
        }
    }
    params.sd = req.sd;
    params.source = Some(format!("coilscope linear {origin}"));
    let x_range = match &input {
        LinearInput::Record(r) => {
            let x_pred = match &r.x {
                Some(x) => x.clone(),
                None => predicted_displacement(&params, &r.i, r.fs as f64),
            };
            [x_pred.iter().cloned().fold(0.0, f64::min), x_pred.iter().cloned().fold(0.0, f64::max)]
        }
        LinearInput::Curve(c) => req.volts.map_or([0.0, 0.0], |v| {
            let peak = curve_peak_displacement(&params, &c.f, &c.z, v);
            [-peak, peak]
        }),
    };
    let mut res = result(&params, &fit, &method, x_range, origin);
    res.fit.band_note = band_note;
    if matches!(&input, LinearInput::Curve(c) if c.magnitude_only) {
        res.fit.phase_note = Some(MAGNITUDE_ONLY_NOTE.to_string());
    }
    if calibrated.is_some() {
        res.chain = calibrated;
    }
    mark_wiring(&mut res.chain, req.wiring);
    let (floor, warnings) = match &input {
        LinearInput::Record(r) => {
            let (floor, w) = record_warnings(&fit, &params, r);
            (Some(floor), w)
        }
        LinearInput::Curve(_) => (None, curve_warnings(&fit).into_iter().chain(band_warning).collect()),
    };
    attach_warnings(&mut res, floor.as_ref(), &warnings);
    Ok(Linear { fit, params, method, x_range, result: res, warnings, floor, detected })
}

/// The moving mass of a fit by `scale` (the added-mass method fits the second measurement
/// with the first's model, so that the resonance shift compares like with like).
fn scale_mms(
    fit: &LinearFit,
    input: &LinearInput,
    scale: &Scale,
    req: &LinearRequest,
    origin: &str,
    chain: bool,
) -> Result<(f64, ScaleMethod), String> {
    match scale {
        Scale::Mms(m) => Ok((m.kg, ScaleMethod::Mms { sd_rel: m.sd_rel() })),
        Scale::AddedMass { mass, with, origin: o2 } => {
            if !(mass.kg.is_finite() && mass.kg > 0.0 && mass.kg < 2.0) {
                return Err(format!("--added-mass {} kg: give the added mass (0 .. 2 kg)", mass.kg));
            }
            if with.is_curve() != input.is_curve() {
                return Err(format!("{o2}: the measurement with the added mass must be of the same kind as {origin} (both records or both impedance curves)"));
            }
            let mut second = (**with).clone();
            prepare(&mut second, req, o2)?;
            let same = LinearOptions { effects: EffectsChoice::Fixed(fit.effects), chain, ..Default::default() };
            let fit2 = fit_input(&second, o2, &same, req.band, &mut |_| {})?;
            // The added mass's own sd goes one to one into Mms (Mms = added / (ratio - 1)).
            added_mass_scale(fit, &fit2, mass.kg).map(|(m, method)| match method {
                ScaleMethod::AddedMass { added, fs_with, mms_sd_rel, .. } => (
                    m,
                    ScaleMethod::AddedMass {
                        added,
                        added_sd: mass.sd_kg,
                        fs_with,
                        mms_sd_rel: mms_sd_rel.hypot(mass.sd_rel()),
                    },
                ),
                other => (m, other),
            })
        }
        Scale::Displacement => match input {
            LinearInput::Record(Recording { i, x: Some(x), fs, .. }) => {
                displacement_scale(fit, i, x, *fs as f64, origin)
            }
            _ => Err(format!("{origin}: the displacement scale needs a record with a displacement channel (3)")),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::{curve_peak_displacement, LinearInput};
    use coilscope_core::chain::SenseWiring;
    use coilscope_core::Complex64;
    use coilscope_io::impedance::ImpedanceCurve;

    /// A curve measured across driver and shunt loses the shunt's resistance, and one
    /// without phase is refused, by name, rather than fitted with Re off by the shunt.
    #[test]
    fn a_shunts_resistance_is_taken_out_of_a_curve_with_phase_only() {
        let curve = |magnitude_only| ImpedanceCurve {
            f: vec![10.0, 100.0],
            z: vec![Complex64::new(6.5, 1.0), Complex64::new(7.0, -2.0)],
            comments: vec![],
            magnitude_only,
        };
        let wiring = SenseWiring::DriverPlusShunt { ohm: 0.5 };
        match LinearInput::curve_across_driver(curve(false), wiring, "z.zma") {
            Ok(LinearInput::Curve(c)) => {
                assert_eq!(c.z, vec![Complex64::new(6.0, 1.0), Complex64::new(6.5, -2.0)]);
            }
            _ => panic!("a curve with phase takes the shunt out"),
        }
        let e = LinearInput::curve_across_driver(curve(true), wiring, "z.zma").unwrap_err();
        assert!(e.contains("z.zma") && e.contains("0.5 ohm") && e.contains("no phase"), "{e}");
        assert!(LinearInput::curve_across_driver(curve(true), SenseWiring::Terminals, "z.zma").is_ok());
    }
    use coilscope_core::excitation::{generate, Excitation, SignalSpec};
    use coilscope_core::simulate::{simulate, SimOptions};
    use coilscope_core::small_signal::impedance;

    /// The peak displacement `linear --volts` reports for a curve is the one the time-domain
    /// model plays at that sine, creep's softer suspension below the resonance included
    /// (a bundled woofer with typical creep, 0.05 V: linear; the last second of 4 s).
    #[test]
    fn a_curves_peak_displacement_is_the_simulated_sines() {
        let p = coilscope_core::params::embedded_driver("sb17cac35-4").unwrap().with_typical_creep();
        let fs = 48000.0;
        for freq in [12.0, 40.0, 150.0] {
            let spec = SignalSpec { fs, seconds: 4.0, rms: 0.05, fade: 0.5, seed: 1 };
            let u = generate(&Excitation::Sine { freq }, &spec).unwrap();
            let tr = simulate(&p, fs, &u, &SimOptions::default()).unwrap();
            // The last second before the fade-out: half the peak-to-peak, free of creep's slow
            // offset.
            let tail = &tr.x[(2.5 * fs) as usize..(3.5 * fs) as usize];
            let sim =
                0.5 * (tail.iter().cloned().fold(f64::MIN, f64::max) - tail.iter().cloned().fold(f64::MAX, f64::min));
            let curve = curve_peak_displacement(&p, &[freq], &[impedance(&p, freq)], 0.05);
            let err = curve / sim - 1.0;
            assert!(err.abs() < 0.005, "{freq} Hz: curve {curve:.4e} m, simulated {sim:.4e} m ({:+.2} %)", 100.0 * err);
        }
    }
}

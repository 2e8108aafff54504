//! `coilscope identify`: the large-signal identification of a record, with the checks its
//! result carries and the verdict they give.

use crate::attach_warnings;
use crate::chain::{detect, mark_wiring, ChainMode};
use coilscope_core::chain::{Chain, SenseWiring};
use coilscope_core::mass::Mass;
use coilscope_core::result::ResultFile;
use coilscope_core::Parameters;
use coilscope_ident::checks::{NoiseFloor, Warning};
use coilscope_ident::large::{identify, IdentifyError, IdentifyOptions, LargeFit, Progress};
use coilscope_ident::linear::EffectsChoice;
use coilscope_io::Recording;

/// What to identify, and how.
#[derive(Clone, Debug)]
pub struct IdentifyRequest {
    /// The record's name in messages and in the result.
    pub origin: String,
    /// Moving mass (kg); `None`: from the displacement channel (a record without one is
    /// refused).
    pub mms: Option<f64>,
    /// The relative sd of `mms` as given (0: taken as exact), carried into Bl, Kms, Rms, Mms
    /// and their bands.
    pub mms_sd_rel: f64,
    /// Power-series order; `None`: chosen on held-out data.
    pub order: Option<usize>,
    pub effects: EffectsChoice,
    pub chain: ChainMode,
    pub wiring: SenseWiring,
    /// Radiating area (m^2), for Vas.
    pub sd: Option<f64>,
    /// Worker threads (0: every core).
    pub threads: usize,
    /// The driver is in this box; `None`: free air.
    pub enclosure: Option<coilscope_ident::large::InBox>,
}

impl IdentifyRequest {
    /// A request with the command line's defaults.
    pub fn new(origin: impl Into<String>, mms: Option<f64>) -> Self {
        IdentifyRequest {
            origin: origin.into(),
            mms,
            mms_sd_rel: 0.0,
            order: None,
            effects: EffectsChoice::Auto,
            chain: ChainMode::Detect,
            wiring: SenseWiring::Terminals,
            sd: None,
            threads: 0,
            enclosure: None,
        }
    }
}

/// The box of an identification in a box (`identify --enclosure TYPE`): the type (`closed`,
/// `vented`, `passive_radiator` or `auto`), the driver's radiating area `sd` (m^2, needed),
/// a closed box's net volume `vb` (m^3, needed for a closed box), the port's area and the
/// radiator's area (m^2) where known.
pub fn in_box(
    enclosure: &str,
    sd: Option<f64>,
    vb: Option<f64>,
    port_area: Option<f64>,
    sp: Option<f64>,
) -> Result<coilscope_ident::large::InBox, String> {
    let choice = coilscope_ident::box_fit::BoxChoice::parse(enclosure)?;
    let sd = sd.ok_or("a driver in a box needs its radiating area Sd (--sd, m^2): the box air pushes on it")?;
    for (name, v) in [("Sd", Some(sd)), ("Vb", vb), ("port_area", port_area), ("Sp", sp)] {
        if let Some(v) = v {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{name} = {v}: it must be a positive number (SI units: m^2, or m^3 for Vb)"));
            }
        }
    }
    Ok(coilscope_ident::large::InBox { choice, sd, vb, port_area, sp })
}

/// The outcome of [`identify_record`].
pub struct Identified {
    pub fit: LargeFit,
    /// The result file, its warnings and verdict attached (`fit.trustworthy`).
    pub result: ResultFile,
    pub warnings: Vec<Warning>,
    pub floor: NoiseFloor,
    /// Why the fit stopped short of convergence, when it did (the best estimate is kept).
    pub failure: Option<String>,
    /// Where the absolute scale came from.
    pub mms_source: String,
    /// The chain was estimated: asked for, or found in the record (`detected` says what).
    pub chain_estimated: bool,
    pub detected: Vec<String>,
}

impl Identified {
    pub fn trustworthy(&self) -> bool {
        crate::trustworthy(&self.result)
    }
}

/// The post-inverse (equation-error) estimate of a record with a displacement channel: the
/// whole parameter set, Mms included. Its L2/R2 come from the linear fit of the same record
/// (the equation error cannot separate them).
pub fn post_inverse_of(
    u: &[f64],
    i: &[f64],
    x: &[f64],
    fs: f64,
    order: usize,
    origin: &str,
) -> Result<Parameters, String> {
    let lin = coilscope_ident::linear::fit_linear_record(
        u,
        i,
        fs,
        origin,
        &coilscope_ident::linear::LinearOptions::LARGE_SIGNAL_START,
        |_| {},
    )?;
    coilscope_ident::post_inverse::post_inverse(u, i, x, fs, order, Some((lin.p[2], lin.p[3])), origin)
}

/// Identify `rec` (changed in place into the driver's terminal signals where a calibrated
/// chain or a shunt's drop is taken out). `progress` sees the fit's iterations. An `Err` is
/// a record or request that cannot be fitted, with what would be valid.
pub fn identify_record(
    rec: &mut Recording,
    req: &IdentifyRequest,
    progress: impl FnMut(&Progress),
) -> Result<Identified, String> {
    let mut progress = progress;
    identify_body(rec, req, &mut progress)
}

fn identify_body(
    rec: &mut Recording,
    req: &IdentifyRequest,
    progress: &mut dyn FnMut(&Progress),
) -> Result<Identified, String> {
    let origin = req.origin.as_str();
    let fs = rec.fs as f64;
    if let Some(o) = req.order {
        if !(2..=8).contains(&o) {
            return Err(format!("--order {o}: give a power-series order from 2 to 8"));
        }
    }
    if let Some(s) = req.sd {
        if !(s.is_finite() && s > 0.0 && s < 1.0) {
            return Err(format!("--sd {s}: give the radiating area in m^2 (e.g. 0.0118)"));
        }
    }
    let calibrated = req.chain.prepare(rec, origin, req.wiring)?;
    // With a displacement channel: the equation-error (post-inverse) estimate gives Mms (when
    // not given), the start values, and a cross-check of the output-error result.
    let given = |m: f64| Mass { kg: m, sd_kg: req.mms_sd_rel * m };
    let (mms, mms_source, post) = match (req.mms, &rec.x) {
        (m, Some(x)) => {
            let pi = post_inverse_of(&rec.u, &rec.i, x, fs, req.order.unwrap_or(4), origin)?;
            match m {
                Some(m) => (m, format!("given (--mms {})", given(m)), Some(pi)),
                None => (pi.mms, "displacement channel (post-inverse equation error)".to_string(), Some(pi)),
            }
        }
        (Some(m), None) => (m, format!("given (--mms {})", given(m)), None),
        (None, None) => {
            return Err(format!(
                "{origin}: no absolute scale: give --mms KG (moving mass), or record a displacement channel (3)"
            ))
        }
    };
    // The chain: asked for, or found in the record.
    let detected = match req.chain {
        ChainMode::Detect => detect(&rec.u, &rec.i, fs).found,
        _ => vec![],
    };
    let chain = req.chain.estimate() || !detected.is_empty();
    let init = post.as_ref().map(|p| Parameters { mms, x_range: None, ..p.clone() });
    let opts = IdentifyOptions {
        mms,
        order: req.order,
        init,
        effects: req.effects,
        chain,
        detect_chain: req.chain == ChainMode::Detect && !chain,
        threads: req.threads,
        enclosure: req.enclosure.clone(),
        ..Default::default()
    };
    let (fit, failure) = match identify(&rec.u, &rec.i, fs, origin, &opts, &mut *progress) {
        Ok(f) => (f, None),
        Err(IdentifyError::NotConverged { message, best }) => (*best, Some(message)),
        Err(e) => return Err(e.to_string()),
    };
    let chain_estimated = fit.chain.is_some();
    let mut detected = detected;
    if let Some(why) = &fit.chain_detected {
        detected.push(why.clone());
    }
    let mut fit = fit;
    fit.params.sd = req.sd;
    fit.params.source = Some(format!("coilscope identify {origin}"));
    let mut result = fit.result(origin, &mms_source);
    if req.mms.is_some() {
        result.uncertainty.carry_mass_sd(&result.parameters, req.mms_sd_rel);
    }
    // The skew check looks at the record without a chain: with the chain estimated or
    // calibrated the delay is taken out (and reported in `chain`), so it would warn of what
    // is already corrected.
    let delay_handled = chain_estimated || calibrated.is_some();
    if calibrated.is_some() {
        result.chain = calibrated;
    }
    mark_wiring(&mut result.chain, req.wiring);
    let (floor, warnings) = checks(&fit, fs, delay_handled);
    if failure.is_some() {
        result.fit.trustworthy = Some(false);
    }
    attach_warnings(&mut result, Some(&floor), &warnings);
    if let Some(pi) = &post {
        result.cross_check = Some(cross_check(&fit, pi));
    }
    Ok(Identified { fit, result, warnings, floor, failure, mms_source, chain_estimated, detected })
}

/// The checks of a large-signal fit's final error: far above its noise floor, following the
/// drive, or showing a skew of the channels (unless the chain's delay was taken out).
fn checks(fit: &LargeFit, fs: f64, delay_handled: bool) -> (NoiseFloor, Vec<Warning>) {
    // The current error behind the estimated chain (its offsets and hum are fitted, not error).
    let k = fit.settle;
    let r: Vec<f64> = fit.i_phys[k..].iter().zip(&fit.i_model[k..]).map(|(a, b)| a - b).collect();
    let i_rms = coilscope_core::simulate::rms(&fit.i_phys);
    // An excess over the floor below the model's own systematic part (what a record of
    // another simulator, or none of noise, leaves) moves nothing the bands do not carry.
    let material = coilscope_ident::large::CURVE_SYSTEMATIC_REL;
    let (floor, mut warnings) = coilscope_ident::checks::residual_warnings(&r, fs, "large-signal fit", i_rms, material);
    // An error that follows the drive is a misfit even when its spectrum looks like a floor;
    // beside a residual far above its floor it names the likelier cause (a recording chain).
    warnings.extend(coilscope_ident::checks::drive_warning(
        &r,
        &fit.u_phys[k..],
        &fit.i_model[k..],
        &fit.x_model[k..],
        fs,
        "large-signal fit",
        i_rms,
        material,
    ));
    let final_delay = if delay_handled { None } else { coilscope_ident::checks::residual_delay(&r, &fit.i_model[k..]) };
    if let Some((tau, share)) = final_delay {
        warnings.push(Warning::new(
            "current-delay",
            format!(
                "the current channel looks skewed against the voltage: shifting it {tau:+.2} samples ({:+.1} us at {fs} Hz; + is late) explains {:.0} % of the large-signal fit's error, and the fit has taken part of the skew into its parameters, so the skew can be larger. Channels of one interface sampled apart, or a wiring/latency mistake; the parameters are biased (Le, Kms(x), Bl(x)). Estimate the chain with --chain auto, or calibrate the card (coilscope calibrate) and give --chain FILE",
                1e6 * tau / fs,
                100.0 * share
            ),
        ));
    } else if let Some(lin) = fit.linear.as_ref().filter(|_| !delay_handled) {
        if let Some((tau, share)) = lin.current_delay {
            warnings.push(Warning::new(
                "current-delay",
                format!(
                    "the current channel is {tau:.2} samples {} the voltage (shifting it explains {:.0} % of the small-signal fit's error): the channels are skewed, and Le, L2/R2 and Bl are biased",
                    if tau > 0.0 { "late against" } else { "early against" },
                    100.0 * share
                ),
            ));
        }
    }
    (floor, warnings)
}

/// The output-error result against the post-inverse one: the largest difference of each
/// curve over the reached range, relative to the output-error value at rest.
fn cross_check(fit: &LargeFit, pi: &Parameters) -> coilscope_core::result::CrossCheck {
    let dev = |a: &coilscope_core::Poly, b: &coilscope_core::Poly| {
        let [lo, hi] = fit.x_range;
        (0..=200).map(|k| lo + (hi - lo) * k as f64 / 200.0).map(|x| (a.eval(x) - b.eval(x)).abs()).fold(0.0, f64::max)
            / b.eval(0.0).abs()
    };
    let p = &fit.params;
    let diff = [
        ("Bl", dev(&pi.bl, &p.bl)),
        ("Kms", dev(&pi.kms, &p.kms)),
        ("Le", dev(&pi.le, &p.le)),
        ("Mms", (pi.mms / p.mms - 1.0).abs()),
        ("Rms", (pi.rms / p.rms - 1.0).abs()),
    ];
    coilscope_core::result::CrossCheck {
        method: "post-inverse equation error with the measured displacement".into(),
        parameters: pi.clone(),
        max_rel_difference: diff.iter().map(|(k, v)| (k.to_string(), *v)).collect(),
    }
}

/// The chain a fit reports, if any (estimated or calibrated).
pub fn reported_chain(result: &ResultFile) -> Option<&Chain> {
    result.chain.as_ref()
}

//! `identify --method volterra` (seed paper 3.2.2.1): Bl(x), Kms(x) and Le(x) to second order
//! from the 2nd and 3rd harmonics of a readable multitone, the linear part given (a start from
//! `linear`); its result with the truncation's and the resolution's warnings. Called by the
//! command line; the workflow is here so that every caller gets the same result and warnings.

use crate::chain::ChainMode;
use coilscope_core::chain::SenseWiring;
use coilscope_core::result::ResultFile;
use coilscope_core::simulate::{simulate, SimOptions};
use coilscope_core::Parameters;
use coilscope_ident::checks::Warning;
use coilscope_io::Recording;
use serde_json::json;

/// What the Volterra method gave: the result (its warnings attached) and what a summary
/// prints.
pub struct VolterraIdentified {
    pub result: ResultFile,
    pub warnings: Vec<Warning>,
    /// The fitted set, its `x_range` the reach of the fitted model under the record.
    pub params: Parameters,
    pub reach: [f64; 2],
    /// The tones (Hz) and the steady periods averaged.
    pub tones_hz: Vec<usize>,
    pub periods: usize,
    /// The kernel fit's chi^2 per degree of freedom, and the series' truncation (the fitted
    /// model's full response against its kernels, in the lines' noise): about 1 or less where
    /// the series holds.
    pub chi2_dof: f64,
    pub truncation: f64,
}

/// The linear part the kernels are fitted around: `start`'s values at rest (its curves'
/// constant terms), with the radiating area `sd` where given.
pub fn linear_start(start: Parameters, sd: Option<f64>) -> Parameters {
    Parameters {
        bl: coilscope_core::Poly::constant(start.bl.c[0]),
        kms: coilscope_core::Poly::constant(start.kms.c[0]),
        le: coilscope_core::Poly::constant(start.le.c[0]),
        l2r2: start.l2r2.map(|(l, r)| (coilscope_core::Poly::constant(l.c[0]), coilscope_core::Poly::constant(r.c[0]))),
        sd: sd.or(start.sd),
        ..start
    }
}

/// The Volterra identification of the record `rec` (named `origin`) around the linear part
/// `start` (from [`linear_start`]; `start_spec` names it in the result), the card's chain
/// undone as `chain` and `wiring` say (a chain is not estimated: its lines carry no transient
/// to tell it).
pub fn identify_volterra(
    rec: &mut Recording,
    origin: &str,
    start: &Parameters,
    start_spec: &str,
    chain_choice: &ChainMode,
    wiring: SenseWiring,
) -> Result<VolterraIdentified, String> {
    use coilscope_ident::volterra::{identify_volterra_weighted, record_lines, truncation_check};
    if matches!(chain_choice, ChainMode::Estimate) {
        return Err("--chain auto: the Volterra method does not estimate a chain (its lines carry no transient to tell it); calibrate the card (`coilscope calibrate`) and give --chain FILE, or --chain none".into());
    }
    let calibrated = chain_choice.undo(rec, origin, wiring)?;
    let fs = rec.fs as f64;
    let lines = record_lines(&rec.u, &rec.i, fs, origin)?;
    let (measured, noise) = lines.harmonics(start);
    let fit = identify_volterra_weighted(start, &measured, Some(&noise))?;
    let trunc = truncation_check(&fit, &lines, &measured, &noise)?;
    let chi2 = fit.chi2_dof.unwrap_or(f64::NAN);
    // The reach: the fitted model driven by the record.
    let mut q = fit.params.clone();
    q.x_range = None;
    let trace = simulate(&q, fs, &rec.u, &SimOptions::default())
        .map_err(|e| format!("{origin}: the fitted model under the record: {e}"))?;
    let from = lines.starts[0];
    let reach = trace.x[from..].iter().fold([0.0f64, 0.0f64], |a, &v| [a[0].min(v), a[1].max(v)]);
    q.x_range = Some(reach);
    q.source = Some(format!("coilscope identify --method volterra {origin}"));
    let mut warnings = vec![];
    if chi2 > 2.0 || trunc > 1.0 {
        warnings.push(Warning::new(
            "volterra-truncation",
            format!(
                "the level is too high for the third-order Volterra series: the kernels leave {chi2:.1} times the lines' noise variance unexplained, and the fitted model's own full response differs from its kernels by {trunc:.1} times it. The distortion feeds back into the nonlinearities (seed paper 3.2.2.1) and the fitted coefficients absorb it: lower the level, or use the full identification (`--method full`, on noise at high level)"
            ),
        ));
    }
    let mut unc = coilscope_core::result::Uncertainty::new(format!(
        "Volterra method: sd of the second-order series from the kernel fit's covariance, the lines' noise from the scatter of {} periods (scaled up by the fit's chi^2 per degree of freedom where above 1); the values at rest are --start's (sd 0 at x = 0). The truncation of the series is not in the sd: see the warnings",
        lines.starts.len()
    ));
    for which in ["Bl", "Kms", "Le"] {
        let band = fit.band(which, reach, 21);
        // A nonlinearity smaller than its sd over the reach is not resolved.
        let f = match which {
            "Bl" => &q.bl,
            "Kms" => &q.kms,
            _ => &q.le,
        };
        let size = band.x.iter().map(|&x| (f.eval(x) - f.c[0]).abs()).fold(0.0, f64::max);
        let worst_sd = band.sd.iter().cloned().fold(0.0, f64::max);
        if worst_sd > size {
            warnings.push(Warning::new(
                "volterra-unresolved",
                format!(
                    "{which}(x): its change over the reach ({:.3} % of its value at rest) is smaller than its sd ({:.3} %): the record does not resolve this nonlinearity (its lines are at the noise; record longer, or at a somewhat higher level)",
                    100.0 * size / f.c[0].abs(),
                    100.0 * worst_sd / f.c[0].abs()
                ),
            ));
        }
        unc.set_band(which, band);
    }
    let result_fit = coilscope_core::result::Fit {
        method: Some(format!(
            "Volterra (seed paper 3.2.2.1): H2, H3 of a readable multitone ({} tones, {}-{} Hz, {} steady periods averaged); Bl, Kms, Le to second order fitted to the current's 2nd and 3rd harmonic ratios; linear part from {start_spec}",
            lines.bins.len(),
            lines.bins[0],
            lines.bins[lines.bins.len() - 1],
            lines.starts.len()
        )),
        residual_rel: fit.misfit,
        x_range: reach,
        order: Some(2),
        model: "LR-2, Bl/Kms/Le to second order".into(),
        ..Default::default()
    };
    let lim = coilscope_core::limits::limits(&q, reach);
    let mut result = ResultFile::new("large-signal", origin, q.clone(), result_fit, unc, Some(&lim));
    result.chain = calibrated;
    result.other.insert(
        "volterra".into(),
        json!({
            "tones_hz": lines.bins, "periods": lines.starts.len(), "chi2_dof": chi2, "truncation": trunc,
            "lines": measured.iter().zip(&noise).map(|(h, n)| json!({"freq": h.freq, "volts_rms": h.volts, "ratio2": [h.ratio(2).re, h.ratio(2).im], "ratio3": [h.ratio(3).re, h.ratio(3).im], "sd2": n[0], "sd3": n[1]})).collect::<Vec<_>>(),
        }),
    );
    crate::attach_warnings(&mut result, None, &warnings);
    Ok(VolterraIdentified {
        result,
        warnings,
        params: q,
        reach,
        tones_hz: lines.bins,
        periods: lines.starts.len(),
        chi2_dof: chi2,
        truncation: trunc,
    })
}

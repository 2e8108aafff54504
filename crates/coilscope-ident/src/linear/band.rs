//! Impedance curves (measured files): the fits of a complex or a magnitude-only curve, and the
//! search for the band where the lumped model holds ([`lumped_band`]).

use super::*;

/// The linear fit of a measured impedance curve `z` (ohm) at frequencies `f` (Hz, increasing),
/// e.g. a `.zma` file: the same model, model choice ([`LinearOptions::effects`]) and
/// uncertainty as for a record. `band` limits the fitted points (default: all up to 20 kHz).
///
/// Each point weighs alike and its error is relative, `1 - Z_measured / Z_model` (the
/// current error of a record at unit current, `I - U/Z` with `U = Z_measured`, `I = 1`), so
/// a log-spaced file weighs every octave alike, and `residual_rel` is the RMS relative
/// impedance error. A curve is the average of a measurement, with no record ends
/// ([`Ends::AssumedAtRest`]) and no measurement chain (a `.zma` is taken as calibrated; the
/// option `chain` is refused).
pub fn fit_impedance_curve(
    f: &[f64],
    z: &[Complex64],
    band: Option<[f64; 2]>,
    origin: &str,
    opts: &LinearOptions,
    mut observe: impl FnMut(&LmState),
) -> Result<LinearFit, String> {
    impedance_curve(f, z, band, origin, opts, false, &mut observe)
}

/// [`fit_impedance_curve`] of a curve without a measured phase (REW, LPM and many tools
/// export |Z| alone): magnitudes `mag` (ohm) at `f` (Hz). The error of each point is
/// `1 - |Z_measured| / |Z_model|`: a driver's impedance is minimum phase, as the model's is,
/// so the magnitude holds what the phase would tell, and the fit needs no phase of its own.
/// The start values take the curve's minimum phase ([`crate::min_phase`]), which is also
/// what `h1` holds. The sds are those of the magnitude alone.
pub fn fit_impedance_magnitude(
    f: &[f64],
    mag: &[f64],
    band: Option<[f64; 2]>,
    origin: &str,
    opts: &LinearOptions,
    mut observe: impl FnMut(&LmState),
) -> Result<LinearFit, String> {
    check_curve(f, &mag.iter().map(|&m| Complex64::new(m, 0.0)).collect::<Vec<_>>(), origin)?;
    check_magnitude_span(f, origin)?;
    let z = magnitude_curve(f, mag);
    impedance_curve(f, &z, band, origin, opts, true, &mut observe)
}

/// A curve's frequencies positive, finite and increasing, one finite non-zero impedance
/// each (what a file's reader checks, for callers that build a curve themselves).
pub(super) fn check_curve(f: &[f64], z: &[Complex64], origin: &str) -> Result<(), String> {
    if f.len() != z.len() {
        return Err(format!("{origin}: {} frequencies for {} impedance points", f.len(), z.len()));
    }
    if let Some(k) = (0..f.len()).find(|&k| !(f[k].is_finite() && f[k] > 0.0) || (k > 0 && !(f[k] > f[k - 1]))) {
        return Err(format!("{origin}: frequency {} Hz at point {k} is not positive, finite and above the one before: give increasing frequencies", f[k]));
    }
    if let Some(k) = (0..z.len()).find(|&k| !(z[k].re.is_finite() && z[k].im.is_finite() && z[k].norm() > 0.0)) {
        return Err(format!("{origin}: impedance {} at {} Hz is not finite and non-zero", z[k], f[k]));
    }
    Ok(())
}

/// The fewest decades a curve without phase must span: the magnitude's slopes over the
/// resonance and the voice coil's rise are what tell the phase.
pub const MAGNITUDE_MIN_DECADES: f64 = 2.0;

/// Refuse a curve without phase that is too narrow for its phase to follow from |Z|.
pub(super) fn check_magnitude_span(f: &[f64], origin: &str) -> Result<(), String> {
    let (lo, hi) =
        (f.iter().copied().filter(|&f| f > 0.0).fold(f64::INFINITY, f64::min), f.iter().copied().fold(0.0, f64::max));
    if !(hi / lo >= 10f64.powf(MAGNITUDE_MIN_DECADES)) {
        return Err(format!(
            "{origin}: the file has no phase, and its {lo:.1} .. {hi:.1} Hz spans {:.1} decades: a curve of |Z| alone must span at least {MAGNITUDE_MIN_DECADES} (from below the resonance into the voice coil's rise), or export the phase too",
            (hi / lo).log10()
        ));
    }
    Ok(())
}

/// A magnitude-only curve with its minimum phase.
pub(super) fn magnitude_curve(f: &[f64], mag: &[f64]) -> Vec<Complex64> {
    let n = f.len().min(mag.len());
    crate::min_phase::min_phase(&f[..n], &mag[..n])
        .into_iter()
        .zip(mag)
        .map(|(ph, &m)| Complex64::from_polar(m, ph))
        .collect()
}

/// The band of an impedance curve where the lumped model holds, found by [`lumped_band`].
#[derive(Clone, Debug, PartialEq)]
pub struct LumpedBand {
    /// The band to fit (Hz): from the file's lowest frequency to where the model holds.
    pub band: [f64; 2],
    /// What the search found, in words (for the result's `fit.band_note`).
    pub note: String,
    /// No part of the curve held the model, not even the lowest: the whole curve is fitted,
    /// and the fit is doubtful whatever its own misfit ([`LumpedBand::warning`]).
    pub none_held: bool,
}

impl LumpedBand {
    /// The warning of a search that found no band holding the model: a curve that departs
    /// from it below the search's first top (ten times the resonance), or a fit of the lowest
    /// band that ended in a wrong minimum.
    pub fn warning(&self) -> Option<crate::checks::Warning> {
        self.none_held.then(|| {
            crate::checks::Warning::new(
                "no-lumped-band",
                format!("{}: the figures are of the whole curve, where the model is not known to hold; fit a band below the break-up (--band LO,HI)", self.note),
            )
        })
    }
}

/// Half-octave steps of [`lumped_band`]'s search, and where it starts: ten times the
/// curve's resonance (the peak and the voice coil's inductive rise both inside).
pub const LUMPED_STEP: f64 = std::f64::consts::SQRT_2;
pub const LUMPED_START_OVER_FS: f64 = 10.0;
/// A fit holds to its top when its whole band's misfit is within [`CURVE_RESIDUAL_WARN`] and
/// none of its half-octaves is missed by more than this many times that (a surround mode's
/// bump of 2-3 % stays in, a break-up region of 5 % and more does not).
pub const LUMPED_PART_BOUND: f64 = 2.0;

/// Where an impedance curve stops being a lumped driver: the top of the band to fit.
///
/// A driver's impedance follows the lumped model (Re, the voice coil's inductance and its
/// branches, the mass-spring resonance, creep) up to where the cone stops moving as one
/// piece; above that, break-up puts peaks and dips in |Z| that no lumped element has, and a
/// fit that takes them in moves Re and Le to reach them. The search fits the curve below tops
/// half an octave apart, from ten times the resonance (the peak and the voice coil's rise
/// inside) to the curve's end (at most 20 kHz). A fit holds to its top when its RMS relative
/// error over its whole band is within [`CURVE_RESIDUAL_WARN`] (the level at which a fit of a
/// curve is not trusted) and none of its half-octaves is missed by more than
/// [`LUMPED_PART_BOUND`] times that: a surround mode's bump of 2-3 % stays in the band, a
/// break-up region does not. The band ends at the highest top that holds; the note names
/// the first top above it that does not, and by how much it misses.
///
/// The break-up is judged by the same figures that judge a fit, not by a frequency: a
/// microspeaker that holds to 20 kHz keeps its whole band, a woofer that breaks up at 1 kHz
/// loses what is above. A misfit inside the found band still makes the fit doubtful
/// ([`curve_warnings`]).
///
/// `magnitude_only`: the curve has no measured phase (only `|z|` counts). It is searched
/// with its minimum phase ([`crate::min_phase`]), as a curve with its phase: break-up shows
/// in the phase as much as in |Z|, where a fit of |Z| alone could bend through it.
pub fn lumped_band(
    f: &[f64],
    z: &[Complex64],
    magnitude_only: bool,
    origin: &str,
    opts: &LinearOptions,
) -> Result<LumpedBand, String> {
    check_curve(f, z, origin)?;
    let rebuilt;
    let z = if magnitude_only {
        check_magnitude_span(f, origin)?;
        rebuilt = magnitude_curve(f, &z.iter().map(|z| z.norm()).collect::<Vec<_>>());
        &rebuilt[..]
    } else {
        z
    };
    let pts: Vec<usize> =
        (0..f.len().min(z.len())).filter(|&k| f[k] > 0.0 && f[k] <= 20000.0 && z[k].norm().is_finite()).collect();
    let (Some(&first), Some(&last)) = (pts.first(), pts.last()) else {
        return Err(format!("{origin}: no points between 0 and 20 kHz"));
    };
    let (lo, top) = (f[first], f[last]);
    let whole = [lo, top];
    // A curve without phase is searched with its minimum phase, as a curve with its phase:
    // the break-up's peaks and dips show in the phase as much as in |Z| (a passive one-port's
    // are minimum phase too), where a fit of |Z| alone can bend through them.
    let fit_to = |hi: f64| impedance_curve(f, z, Some([lo, hi]), origin, opts, false, &mut |_| {});
    // The misfit (RMS relative impedance error) of a fit over the points in (a, b].
    let misfit = |fit: &LinearFit, a: f64, b: f64| -> (f64, usize, f64, f64) {
        let (mut sum, mut n, mut worst, mut at) = (0.0, 0, 0.0, 0.0);
        for &k in pts.iter().filter(|&&k| f[k] > a && f[k] <= b) {
            let e = fit.point_error(f[k], z[k]);
            sum += e * e;
            n += 1;
            if e > worst {
                (worst, at) = (e, f[k]);
            }
        }
        ((sum / n.max(1) as f64).sqrt(), n, worst, at)
    };
    // The resonance from a first fit of the whole curve; a curve with too few points or no
    // fit of its own is left to the caller's fit to report.
    let Ok(full) = fit_to(top) else {
        return Ok(LumpedBand {
            band: whole,
            note: "the whole curve (no fit to search a band with)".into(),
            none_held: false,
        });
    };
    // The first top: ten times the resonance, two half-octaves above the bottom, and at least
    // 40 points below it (the fit has up to 10 unknowns); whichever is highest.
    let by_points = f[pts[pts.len().min(40) - 1]];
    let start = (LUMPED_START_OVER_FS * full.fs()).max(lo * LUMPED_STEP * LUMPED_STEP).max(by_points);
    if start >= top / LUMPED_STEP {
        let why = if by_points >= top / LUMPED_STEP {
            format!("it has too few points ({}) to fit a part of it", pts.len())
        } else {
            format!("it ends below {LUMPED_START_OVER_FS} times the resonance ({:.0} Hz)", full.fs())
        };
        return Ok(LumpedBand {
            band: whole,
            note: format!("the whole curve ({lo:.0} .. {top:.0} Hz): {why}"),
            none_held: false,
        });
    }
    // Every top, half an octave apart from the first: whether the fit to it holds, over its
    // whole band and in each half-octave above the first top (a narrow mode is averaged in; a
    // fit that holds to a higher top wins over a failure below it). A NaN misfit fails.
    let mut tops = vec![start];
    while *tops.last().expect("one") < top {
        tops.push((tops.last().expect("one") * LUMPED_STEP).min(top));
    }
    // The largest top whose fit holds, and the first failure above it, (top, misfit, worst, at).
    let mut held: Option<f64> = None;
    let mut failed_above: Option<(f64, f64, f64, f64)> = None;
    for (i, &t) in tops.iter().enumerate() {
        let Ok(fit) = fit_to(t) else { continue };
        let parts: Vec<(f64, usize, f64, f64)> = tops[..=i].windows(2).map(|s| misfit(&fit, s[0], s[1])).collect();
        let bad_part = parts.iter().filter(|p| p.1 > 0).find(|p| !(p.0 <= LUMPED_PART_BOUND * CURVE_RESIDUAL_WARN));
        if fit.residual_rel <= CURVE_RESIDUAL_WARN && bad_part.is_none() {
            held = Some(t);
            failed_above = None;
        } else if failed_above.is_none() {
            let (e, worst, at) = match bad_part {
                Some(&(e, _, worst, at)) => (e.max(fit.residual_rel), worst, at),
                None => (fit.residual_rel, f64::NAN, f64::NAN),
            };
            failed_above = Some((t, e, worst, at));
        }
    }
    match (held, failed_above) {
        (Some(h), Some((t, e, worst, at))) => {
            let band = [lo, h];
            let worst_text = if worst.is_finite() { format!(" (worst {:.1} % at {at:.0} Hz)", 100.0 * worst) } else { String::new() };
            let note = format!(
                "fitted {:.0} .. {:.0} Hz, where the lumped model holds: fitted to {t:.0} Hz it misses the curve by {:.1} % RMS{worst_text}, cone break-up or modes, which are left out (--band LO,HI sets the band)",
                band[0],
                band[1],
                100.0 * e,
            );
            Ok(LumpedBand { band, note, none_held: false })
        }
        (Some(_), None) => Ok(LumpedBand { band: whole, note: format!("the whole curve ({lo:.0} .. {top:.0} Hz): the lumped model holds to its end"), none_held: false }),
        // Not even the lowest part holds: the whole curve is fitted, and its fit's warnings
        // say how the model misses it.
        (None, _) => Ok(LumpedBand { band: whole, note: format!("the whole curve ({lo:.0} .. {top:.0} Hz): no part of it holds the lumped model within {:.0} % (from its first {start:.0} Hz on)", 100.0 * CURVE_RESIDUAL_WARN), none_held: true }),
    }
}

/// [`fit_impedance_curve`]'s work, compiled once (not for each caller's observer).
pub(super) fn impedance_curve(
    f: &[f64],
    z: &[Complex64],
    band: Option<[f64; 2]>,
    origin: &str,
    opts: &LinearOptions,
    magnitude_only: bool,
    observe: &mut dyn FnMut(&LmState),
) -> Result<LinearFit, String> {
    if opts.chain {
        return Err(format!("{origin}: an impedance curve has no measurement chain to estimate (its tool calibrated it); --chain applies to records"));
    }
    refuse_large_signal_effects(opts, origin)?;
    check_curve(f, z, origin)?;
    let [lo, hi] = band.unwrap_or([0.0, 20000.0]);
    if !(lo >= 0.0 && hi > lo) {
        return Err(format!("{origin}: fit band {lo} .. {hi} Hz is empty (give LO < HI, Hz)"));
    }
    let keep: Vec<usize> = (0..f.len()).filter(|&k| f[k] > 0.0 && f[k] >= lo && f[k] <= hi).collect();
    if keep.len() < 20 {
        return Err(format!("{origin}: {} points between {lo:.0} and {hi:.0} Hz; at least 20 are needed", keep.len()));
    }
    let h1 = ImpedanceEstimate::from_curve(
        &keep.iter().map(|&k| f[k]).collect::<Vec<_>>(),
        &keep.iter().map(|&k| z[k]).collect::<Vec<_>>(),
    );
    let band = [h1.f[0], *h1.f.last().expect("20 points")];
    let zmed = crate::checks::median(h1.z.iter().map(|z| z.norm()).collect());
    if zmed < 0.5 {
        return Err(format!("{origin}: |Z| is {zmed:.3} ohm (median): an admittance, or a curve in other units? (an impedance file holds ohms)"));
    }
    let low: Vec<f64> = (0..h1.f.len()).filter(|&k| h1.f[k] <= 500.0).map(|k| h1.z[k].re).collect();
    let re_med = crate::checks::median(if low.is_empty() { h1.z.iter().map(|z| z.re).collect() } else { low });
    if re_med < 0.0 {
        return Err(format!("{origin}: the impedance has a negative real part ({re_med:.3} ohm median below 500 Hz), which no passive driver has: a phase of the wrong sign or 180 degrees off"));
    }
    let p0 = initial_guess(&h1, band[0], band[1]).map_err(|e| format!("{origin}: {e}"))?;
    let n = h1.f.len();
    let mut prob = CurrentError {
        f: h1.f.clone(),
        u: h1.z.clone(),
        i: vec![Complex64::new(1.0, 0.0); n],
        w: vec![1.0; n],
        norm: 1.0,
        map: ParamMap::for_band(band),
        omega0: 2.0 * PI * (band[0] * band[1]).sqrt(),
        n_transient: 0,
        effects: Effects::NONE,
        chain: None,
        magnitude_only,
    };
    prob.norm = prob_norm(&prob);
    fit_bins(prob, h1, band, p0, opts, None, None, origin, observe)
}

//! The checks of a small-signal fit: a residual above the noise, a large-signal record, a
//! figure on a bound or not pinned down.

use super::*;

/// Relative current error above the noise floor below which a linear fit's misfit is not
/// material (at 0.5 % the small-signal parameters are off by about 1 %).
pub(super) const LINEAR_MATERIAL_EXCESS: f64 = 0.005;

/// Share of the linear model's current error above which a record is called large-signal.
pub(super) const NONLINEAR_SHARE_WARN: f64 = 0.3;

/// What makes a linear fit of this record doubtful, named: skewed channels, a fit on a
/// bound, a residual far above the noise floor, a record that drove the nonlinearities
/// (use `identify`). `p` is the scaled parameter set of `fit`.
pub fn linear_warnings(
    fit: &LinearFit,
    p: &Parameters,
    u: &[f64],
    i: &[f64],
    fs: f64,
) -> (crate::checks::NoiseFloor, Vec<crate::checks::Warning>) {
    use crate::checks::{residual_warnings, Warning};
    // The current error over the fitted band only (outside it nothing was fitted, and
    // above fs/3 a simulator's or a converter's band-limiting is not the driver's).
    let i_model = model_current(fit, u, fs);
    let r = filter_record(&i.iter().zip(&i_model).map(|(a, b)| a - b).collect::<Vec<_>>(), fs, |_, f| {
        Complex64::new(if f >= fit.band[0] && f <= fit.band[1] { 1.0 } else { 0.0 }, 0.0)
    });
    let (nf, mut w) = residual_warnings(&r, fs, "linear (small-signal) fit", rms(i), LINEAR_MATERIAL_EXCESS);
    if let Some((tau, share)) = fit.current_delay {
        w.push(Warning::new(
            "current-delay",
            format!(
                "the current channel is {tau:.2} samples {} the voltage ({:.1} us at {fs} Hz): shifting it explains {:.0} % of the fit's error. Channels of one interface sampled apart, or a wiring/latency mistake; the parameters of this fit are biased (Le, L2/R2 most)",
                if tau > 0.0 { "late against" } else { "early against" },
                1e6 * tau.abs() / fs,
                100.0 * share
            ),
        ));
    }
    w.extend(bound_warnings(fit));
    let excess = (nf.rms.powi(2) - nf.floor_rms.powi(2)).max(0.0).sqrt() / rms(i);
    if nf.ratio > 2.0 && excess >= LINEAR_MATERIAL_EXCESS {
        let x = predicted_displacement(p, i, fs);
        let share = large_signal_share(p, &r, i, &x, fs);
        if share > NONLINEAR_SHARE_WARN {
            let (lo, hi) = x.iter().fold((0.0f64, 0.0f64), |(a, b), v| (a.min(*v), b.max(*v)));
            w.push(Warning::new(
                "large-signal-record",
                format!(
                    "this is a large-signal record: x reached {:.2} .. {:.2} mm and the first-order effects of Bl(x), Kms(x) and Le(x) explain {:.0} % of the linear fit's error, so the small-signal parameters are biased (Kms, fs most). Fit it with `coilscope identify`, or record at a lower level (well below 10 % of the rated excursion) for `linear`",
                    lo * 1e3,
                    hi * 1e3,
                    100.0 * share
                ),
            ));
        }
    }
    // An error that follows the drive is a misfit whatever its spectrum's median says: SB17's
    // independent large-signal record through a real chain (AC coupling, skew) gave Re 7.6 %
    // and Kms 20 % off, a 6.8 % error 2.9x its "floor", and no warning (the nonlinearity
    // explained too little of it to call it a large-signal record).
    if !w.iter().any(|w| w.code == "residual-above-noise" || w.code == "large-signal-record") {
        let x = predicted_displacement(p, i, fs);
        w.extend(crate::checks::drive_warning(
            &r,
            u,
            &i_model,
            &x,
            fs,
            "linear (small-signal) fit",
            rms(i),
            LINEAR_MATERIAL_EXCESS,
        ));
    }
    (nf, w)
}

/// A fit that ended on a bound, named.
pub(super) fn bound_warnings(fit: &LinearFit) -> Vec<crate::checks::Warning> {
    fit.at_bound
        .iter()
        .map(|&b| {
            if b == "Le" {
                return crate::checks::Warning::new(
                    "on-bound",
                    format!(
                        "Le slid toward zero ({:.3e} H, under {:.0} % of the LR-2 model's): the added effects' branch took the voice coil's inductance along a flat direction, so Le, L2 and R2 are not identified; fit with fewer effects",
                        fit.p[1],
                        100.0 * LE_COLLAPSE
                    ),
                );
            }
            crate::checks::Warning::new(
                "on-bound",
                format!(
                    "the fit ended on the bound of {b}: the L2/R2 branch's corner is not between the fitted band's bottom and {CORNER_ABOVE_BAND} times its top ({:.0} .. {:.0} Hz), so L2 and R2 are not identified by this input",
                    fit.band[0],
                    CORNER_ABOVE_BAND * fit.band[1]
                ),
            )
        })
        .collect()
}

/// The RMS relative impedance error above which a fit of an impedance curve is not
/// trusted. A good measurement of a driver that the model describes fits to well under 1 %
/// (the SEAS L16RN-X's .zma to 10 kHz: 0.6 %); cone break-up, a box, or a wrong file leave
/// several percent.
pub const CURVE_RESIDUAL_WARN: f64 = 0.02;

/// The relative sd above which a figure of the resonance fitted from an impedance curve is
/// not identified to the accuracy the README states for curves (Bl 2 %): a good curve gives
/// well under 1 % (|Z| alone up to 0.8 % for Re), a |Z|-only fit in a wrong minimum 5-1e69 %.
pub const FIGURE_SD_WARN: f64 = 0.02;

/// What makes a fit of an impedance curve doubtful: a bound, or a model that misses the
/// curve (a file has no noise floor to compare with: the threshold is
/// [`CURVE_RESIDUAL_WARN`]); the worst point is named.
pub fn curve_warnings(fit: &LinearFit) -> Vec<crate::checks::Warning> {
    let mut w = bound_warnings(fit);
    // The figures of the resonance (Re, Res, Cmes, Lces: Qms, Qts, fs, Bl) must come out
    // determined; a NaN sd counts as undetermined.
    let loose: Vec<String> = [0, 4, 5, 6]
        .iter()
        .filter(|&&k| !(fit.sigma_rel[k] <= FIGURE_SD_WARN))
        .map(|&k| format!("{} ({:.2e})", NAMES[k], fit.sigma_rel[k]))
        .collect();
    if !loose.is_empty() {
        w.push(crate::checks::Warning::new(
            "not-identified",
            format!(
                "the fit leaves {} undetermined (relative sd over {:.0} %): it ended in a wrong minimum, or the curve does not show the resonance; check the file, or fit a band around the resonance (--band LO,HI)",
                loose.join(", "),
                100.0 * FIGURE_SD_WARN
            ),
        ));
    }
    if fit.residual_rel > CURVE_RESIDUAL_WARN {
        let h = &fit.h1;
        let err = |k: usize| fit.point_error(h.f[k], h.z[k]);
        let worst = (0..h.f.len())
            .filter(|&k| h.f[k] >= fit.band[0] && h.f[k] <= fit.band[1])
            .max_by(|&a, &b| err(a).total_cmp(&err(b)));
        let at = worst.map(|k| format!(" (worst {:.1} % at {:.0} Hz)", 100.0 * err(k), h.f[k])).unwrap_or_default();
        w.push(crate::checks::Warning::new(
            "model-misses-curve",
            format!("the model misses the impedance curve by {:.1} % RMS{at}: cone break-up, a box or port, or a curve of something else. Fit a band the model holds in (--band LO,HI below the break-up), or check the file", 100.0 * fit.residual_rel),
        ));
    }
    w
}

/// Share of a linear fit's current error `r` that the first-order (perturbation) effects of
/// the large-signal terms explain. With the linear model's x and v, each nonlinearity adds a
/// voltage in the electrical loop (`x v`, `x^2 v` from Bl(x); `d(x i)/dt`, `d(x^2 i)/dt` from
/// Le(x)), which changes the current by `-e / Z(f)`, or a force on the cone (`x i`, `x^2 i`
/// from Bl(x); `x^2`, `x^3` from Kms(x); `i^2` from Le'(x)), which changes it by
/// `-Bl F / (Ze Zm_total)`. Noise is explained by none of them.
pub(super) fn large_signal_share(p: &Parameters, r: &[f64], i: &[f64], x: &[f64], fs: f64) -> f64 {
    use crate::checks::explained_share;
    let n = r.len();
    // Central differences (d/dt).
    let d = |s: &[f64]| -> Vec<f64> {
        (0..n).map(|k| (s[(k + 1).min(n - 1)] - s[k.saturating_sub(1)]) * fs / 2.0).collect()
    };
    let v = d(x);
    let (bl, kms, le) = (p.bl.eval(0.0), p.kms.eval(0.0), p.le.eval(0.0));
    let filter = |s: &[f64], voltage: bool| -> Vec<f64> {
        filter_record(s, fs, |k, f| {
            if k == 0 {
                return Complex64::new(0.0, 0.0);
            }
            let jw = Complex64::new(0.0, 2.0 * PI * f);
            let ze = p.re
                + jw * le
                + p.l2r2.as_ref().map_or(Complex64::new(0.0, 0.0), |(l2, r2)| {
                    jw * l2.eval(0.0) * r2.eval(0.0) / (jw * l2.eval(0.0) + r2.eval(0.0))
                });
            let zm = jw * p.mms + p.rms + kms / jw;
            if voltage {
                -1.0 / (ze + bl * bl / zm)
            } else {
                -bl / (ze * (zm + bl * bl / ze))
            }
        })
    };
    let prod = |a: &[f64], b: &[f64]| -> Vec<f64> { a.iter().zip(b).map(|(a, b)| a * b).collect() };
    let x2 = prod(x, x);
    let regressors = vec![
        filter(&prod(x, &v), true),
        filter(&prod(&x2, &v), true),
        filter(&d(&prod(x, i)), true),
        filter(&d(&prod(&x2, i)), true),
        filter(&prod(x, i), false),
        filter(&prod(&x2, i), false),
        filter(&x2, false),
        filter(&prod(&x2, x), false),
        filter(&prod(i, i), false),
    ];
    explained_share(r, &regressors)
}

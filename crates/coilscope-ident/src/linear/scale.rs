//! The absolute scale: Bl and the mechanical parameters from a known Mms, an added mass or a
//! displacement channel; the displacement and current a fit predicts.

use super::*;

/// A parameter set from the electrical fit and a known moving mass (kg).
pub fn scale_by_mms(fit: &LinearFit, mms: f64) -> Result<Parameters, String> {
    if !(mms.is_finite() && mms > 0.0 && mms < 2.0) {
        return Err(format!("moving mass {mms} kg is not valid (0 .. 2 kg; give kg, not g)"));
    }
    let [re, le, l2, r2, res, cmes, lces] = fit.p;
    let bl2 = mms / cmes;
    Ok(Parameters {
        name: None,
        source: Some("coilscope linear (impedance fit)".into()),
        re,
        le: Poly::constant(le),
        l2r2: Some((Poly::constant(l2), Poly::constant(r2))),
        bl: Poly::constant(bl2.sqrt()),
        kms: Poly::constant(bl2 / lces),
        mms,
        rms: bl2 / res,
        sd: None,
        creep: fit.creep.map(|(lambda, _)| coilscope_core::params::Creep { lambda, f_ref: None }),
        l3r3: fit.lr3.map(|(v, _)| (v[0], v[1])),
        le_i: None,
        rms_v: None,
        thermal: None,
        enclosure: None,
        x_range: None,
        extra: Default::default(),
    })
}

/// Moving mass from the resonance shift with a known added mass (kg):
/// `Mms = Madd / (c (fs / fs_with)^2 - 1)`, with `c = K(fs_with) / K(fs)` the suspension's
/// stiffness at the loaded resonance over that at the free one.
///
/// Without creep `c = 1`, the textbook formula. With creep the stiffness falls towards low
/// frequencies (about `lambda` per decade, [`coilscope_core::creep`]), so the loaded
/// resonance sits lower than a constant spring would put it, and the textbook formula takes
/// that for mass: on the SEAS L16RN-X (lambda 0.18, 45 -> 31 Hz) it gave Mms 14.07 g, 6 %
/// below the published 14.9-15.3 g; with `c` (from the free fit's lambda) 14.9 g.
pub fn added_mass_mms(fit: &LinearFit, with_mass: &LinearFit, added: f64) -> Result<f64, String> {
    added_mass_scale(fit, with_mass, added).map(|(m, _)| m)
}

/// Relative sd of a fit's resonance `fs = 1 / (2 pi sqrt(Lces Cmes))` (first order).
pub(super) fn fs_rel_sd(fit: &LinearFit) -> f64 {
    0.5 * (fit.sigma_rel[5].powi(2) + fit.sigma_rel[6].powi(2)).sqrt()
}

/// [`added_mass_mms`] with its [`ScaleMethod`], whose relative sd of Mms follows from the
/// two resonances' sds: `d ln Mms = -2 c r^2 / (c r^2 - 1) d ln r`, `r = fs / fs_with`.
pub fn added_mass_scale(fit: &LinearFit, with_mass: &LinearFit, added: f64) -> Result<(f64, ScaleMethod), String> {
    let c = fit.creep.map_or(1.0, |(lambda, _)| {
        let w = |f: f64| coilscope_core::creep::bank(2.0 * PI * f).re;
        1.0 + lambda * (w(with_mass.fs()) - w(fit.fs()))
    });
    let ratio = c * (fit.fs() / with_mass.fs()).powi(2);
    if !(ratio > 1.02) {
        return Err(format!(
            "the added mass moved the resonance only from {:.2} Hz to {:.2} Hz; add more mass (about Mms/2 or more)",
            fit.fs(),
            with_mass.fs()
        ));
    }
    let r_rel = (fs_rel_sd(fit).powi(2) + fs_rel_sd(with_mass).powi(2)).sqrt();
    let mms_sd_rel = 2.0 * ratio / (ratio - 1.0) * r_rel;
    Ok((added / (ratio - 1.0), ScaleMethod::AddedMass { added, added_sd: 0.0, fs_with: with_mass.fs(), mms_sd_rel }))
}

/// Moving mass from a displacement channel `x` (m): fit `X = (Bl/Kms) G(f) I` with the known
/// resonance shape `G` and read `Bl = Lces / (Bl/Kms)`.
pub fn scale_by_displacement(fit: &LinearFit, i: &[f64], x: &[f64], fs: f64, origin: &str) -> Result<f64, String> {
    displacement_scale(fit, i, x, fs, origin).map(|(m, _)| m)
}

/// Largest delay (samples, either way) of a displacement sensor against the current that
/// [`displacement_scale`] searches: a vibrometer's own processing delays it by tens of
/// samples (a measured spectrum's velocity lagged by about 20).
pub const SENSOR_DELAY_MAX: f64 = 64.0;

/// [`scale_by_displacement`] with its [`ScaleMethod`]: the displacement channel's delay
/// against the current (a sensor's own, samples, positive when it lags) estimated with the
/// scale, and the relative sd of the Mms it gives.
///
/// `X = c G(f) I e^{-j 2 pi f d / fs}` over the bins from the fit's band to 4 fs, with `G` the
/// resonance's second-order shape and `c = Bl Cms`-like gain: `d` maximises the
/// correlation (a search in 1/8 sample steps), `c` is its least-squares gain, its variance
/// the residual's power over the bins. Then `Bl = Lces / c` and `Mms = Bl^2 Cmes`, whose
/// relative sd is `2 sd(c)/c`, `2 sd(Lces)` and `sd(Cmes)` in quadrature (the fit's sds;
/// their correlation left out). A delay left in would turn the gain's phase and read as
/// mass: 20 samples made Mms 12 % high on a measured spectrum.
pub fn displacement_scale(
    fit: &LinearFit,
    i: &[f64],
    x: &[f64],
    fs: f64,
    origin: &str,
) -> Result<(f64, ScaleMethod), String> {
    let (xf, i_f) = (rfft(x), rfft(i));
    let n = i.len();
    let (f_res, q) = (fit.fs(), fit.qms());
    let bins: Vec<(f64, Complex64, Complex64)> = (1..xf.len())
        .filter_map(|k| {
            let f = k as f64 * fs / n as f64;
            if f < fit.band[0] || f > 4.0 * f_res {
                return None;
            }
            let g = 1.0 / Complex64::new(1.0 - (f / f_res).powi(2), f / (f_res * q));
            Some((f, g * i_f[k], xf[k]))
        })
        .collect();
    let gain_at = |d: f64| {
        let (mut num, mut den) = (0.0, 0.0);
        for &(f, gi, xk) in &bins {
            let gd = gi * Complex64::from_polar(1.0, -2.0 * PI * f * d / fs);
            num += (gd.conj() * xk).re;
            den += gd.norm_sqr();
        }
        (num / den, num * num / den, den)
    };
    let steps = (8.0 * SENSOR_DELAY_MAX) as i64;
    let d =
        (-steps..=steps).map(|s| s as f64 / 8.0).max_by(|a, b| gain_at(*a).1.total_cmp(&gain_at(*b).1)).unwrap_or(0.0);
    let (c, _, den) = gain_at(d);
    if !(c.is_finite()) || c == 0.0 || bins.len() < 3 {
        return Err(format!("{origin}: displacement (channel 3) does not follow the current"));
    }
    if c < 0.0 {
        return Err(format!(
            "{origin}: displacement (channel 3) has inverted polarity (x > 0 must be coil out for positive current)"
        ));
    }
    let resid: f64 = bins
        .iter()
        .map(|&(f, gi, xk)| (xk - c * gi * Complex64::from_polar(1.0, -2.0 * PI * f * d / fs)).norm_sqr())
        .sum();
    // A complex residual per bin; two unknowns (gain and delay).
    let c_sd = (resid / (bins.len() as f64 - 2.0).max(1.0) / (2.0 * den)).sqrt();
    let bl = fit.p[6] / c;
    let s = fit.sigma_rel;
    let mms_sd_rel = (2.0 * c_sd / c).hypot(2.0 * s[6]).hypot(s[5]);
    Ok((bl * bl * fit.p[5], ScaleMethod::Displacement { delay_samples: d, mms_sd_rel }))
}

/// `s` filtered by the transfer `h(k, f)` of each whole-record DFT bin (exact for a record
/// that starts and ends at rest).
pub(super) fn filter_record(s: &[f64], fs: f64, h: impl Fn(usize, f64) -> Complex64) -> Vec<f64> {
    let n = s.len();
    let mut spec = rfft(s);
    for (k, c) in spec.iter_mut().enumerate() {
        *c *= h(k, k as f64 * fs / n as f64);
    }
    let mut out = irfft(&spec, n);
    out.iter_mut().for_each(|v| *v /= n as f64);
    out
}

/// Displacement predicted from the current by the linear model (for the reached range).
pub fn predicted_displacement(p: &Parameters, i: &[f64], fs: f64) -> Vec<f64> {
    filter_record(i, fs, |k, f| {
        if k == 0 {
            Complex64::new(0.0, 0.0)
        } else {
            coilscope_core::small_signal::displacement_per_current(p, f)
        }
    })
}

/// The linear model's current for the measured voltage (A), with the fitted transient
/// term of a record that does not start and end at rest.
pub fn model_current(fit: &LinearFit, u: &[f64], fs: f64) -> Vec<f64> {
    let n = u.len();
    let mut spec = rfft(u);
    for (k, c) in spec.iter_mut().enumerate() {
        let f = k as f64 * fs / n as f64;
        *c = if k == 0 {
            *c / fit.p[0]
        } else {
            let imp = impedance_ext(&fit.p, &fit.ext(), f);
            *c / imp.0 + transient_term(&fit.p, &imp, &fit.transient.c, fit.transient.omega0, f).0
        };
    }
    let mut out = irfft(&spec, n);
    out.iter_mut().for_each(|v| *v /= n as f64);
    out
}

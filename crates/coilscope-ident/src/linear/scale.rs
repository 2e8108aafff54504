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
    let (xf, i_f) = (rfft(x), rfft(i));
    let n = i.len();
    let (f_res, q) = (fit.fs(), fit.qms());
    let (mut num, mut den) = (0.0, 0.0);
    for k in 1..xf.len() {
        let f = k as f64 * fs / n as f64;
        if f < fit.band[0] || f > 4.0 * f_res {
            continue;
        }
        let g = 1.0 / Complex64::new(1.0 - (f / f_res).powi(2), f / (f_res * q));
        let gi = g * i_f[k];
        num += (gi.conj() * xf[k]).re;
        den += gi.norm_sqr();
    }
    let c = num / den;
    if !(c.is_finite()) || c == 0.0 {
        return Err(format!("{origin}: displacement (channel 3) does not follow the current"));
    }
    if c < 0.0 {
        return Err(format!(
            "{origin}: displacement (channel 3) has inverted polarity (x > 0 must be coil out for positive current)"
        ));
    }
    let bl = fit.p[6] / c;
    Ok(bl * bl * fit.p[5])
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

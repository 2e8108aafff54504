//! Exports other tools read: the thermal model as a speakersafetyd configuration, the
//! power series as a KLIPPEL-style table, and the small-signal impedance as `.zma` / `.frd`.
//!
//! **speakersafetyd** (Asahi Linux's speaker-protection daemon, `conf/<maker>/<model>.conf`,
//! read with `configparser`'s case-sensitive INI loader): per speaker a `[Speaker/NAME]`
//! section with `group`, `tr_coil`, `tr_magnet`, `tau_coil`, `tau_magnet`, `t_limit`,
//! `t_headroom`, `z_nominal`, `a_t_20c`, `a_t_35c`, `is_scale`, `vs_scale`, `is_chan`,
//! `vs_chan`, and the machine's `[Globals]` and `[Controls]`. Its model is a cascade of two
//! first-order lags driven by the power `p`: the magnet towards `t_ambient + p tr_magnet`
//! with `tau_magnet`, the coil towards `t_magnet + p tr_coil` with `tau_coil`. From the
//! two-node network of the file contract: `tr_coil = Rtv`, `tr_magnet = Rtm` (the same steady
//! rises), and the two time constants are the network's own (the eigenvalues of its 2x2
//! system: the fast one the coil's, the slow one the magnet's), so that both models rise
//! with the same time constants. The daemon's machine-side keys (channels, scales, mixer
//! controls) are not the driver's: they come from [`SafetydOptions`], with the values of a
//! two-channel I/V-sense codec as defaults, and the file says which to edit.

use coilscope_core::params::Parameters;

/// The machine-side keys of a speakersafetyd file, and the speaker's limit.
#[derive(Clone, Debug, PartialEq)]
pub struct SafetydOptions {
    /// Section name: `[Speaker/NAME]`.
    pub name: String,
    /// Absolute coil temperature limit (degrees C).
    pub t_limit: f64,
    /// Ambient temperature the daemon assumes (degrees C, `[Globals] t_ambient`).
    pub t_ambient: f64,
    pub t_headroom: f64,
    pub t_window: f64,
    pub t_hysteresis: f64,
    pub group: usize,
    pub channels: usize,
    pub is_chan: usize,
    pub vs_chan: usize,
    /// Full-scale current (A) and voltage (V) of the I/V-sense converters.
    pub is_scale: f64,
    pub vs_scale: f64,
}

impl Default for SafetydOptions {
    fn default() -> Self {
        SafetydOptions {
            name: "Speaker".into(),
            t_limit: 120.0,
            t_ambient: 35.0,
            t_headroom: 10.0,
            t_window: 20.0,
            t_hysteresis: 5.0,
            group: 0,
            channels: 2,
            is_chan: 0,
            vs_chan: 1,
            is_scale: 3.75,
            vs_scale: 14.0,
        }
    }
}

/// The time constants (s) of the two-node thermal network, fast (coil) then slow (magnet):
/// `-1 / eigenvalue` of `d/dt [Tv, Tm]`.
pub fn thermal_time_constants(rtv: f64, ctv: f64, rtm: f64, ctm: f64) -> (f64, f64) {
    let a = -1.0 / (rtv * ctv);
    let b = 1.0 / (rtv * ctv);
    let c = 1.0 / (rtv * ctm);
    let d = -(1.0 / rtv + 1.0 / rtm) / ctm;
    let tr = a + d;
    let det = a * d - b * c;
    let disc = (tr * tr - 4.0 * det).max(0.0).sqrt();
    let (l_fast, l_slow) = ((tr - disc) / 2.0, (tr + disc) / 2.0);
    (-1.0 / l_fast, -1.0 / l_slow)
}

/// The speakersafetyd configuration of a parameter set with a thermal model. Refused: a set
/// without `thermal`, a limit that leaves no room above the ambient and the daemon's window,
/// a channel beyond `channels`.
pub fn speakersafetyd(p: &Parameters, o: &SafetydOptions) -> Result<String, String> {
    let t = p.thermal.as_ref().ok_or("the result has no thermal parameters (parameters.thermal): measure them with a long-term test, `coilscope measure ... --duration 600 --volts V`")?;
    if !(o.t_limit - o.t_window > o.t_ambient) {
        return Err(format!(
            "--t-limit {} C must be above the ambient {} C plus the daemon's window {} C (speakersafetyd refuses it)",
            o.t_limit, o.t_ambient, o.t_window
        ));
    }
    if o.is_chan >= o.channels || o.vs_chan >= o.channels {
        return Err(format!("is_chan {} / vs_chan {} must be below channels {}", o.is_chan, o.vs_chan, o.channels));
    }
    if o.name.is_empty() || o.name.contains(['[', ']', '\n']) {
        return Err(format!("speaker name {:?}: give a name without brackets or line breaks", o.name));
    }
    let (tau_coil, tau_magnet) = thermal_time_constants(t.rtv, t.ctv, t.rtm, t.ctm);
    // alpha is given at 20 C in the set; referred to 35 C: alpha / (1 + 15 alpha).
    let a20 = t.alpha;
    let a35 = a20 / (1.0 + 15.0 * a20);
    let who = p.name.clone().unwrap_or_else(|| "driver".into());
    let mut s = String::new();
    s.push_str(&format!("; speakersafetyd configuration written by coilscope for {who}\n"));
    s.push_str(&format!(
        "; thermal model: Rtv {:.4} K/W, Ctv {:.4} J/K, Rtm {:.4} K/W, Ctm {:.2} J/K{}\n",
        t.rtv,
        t.ctv,
        t.rtm,
        t.ctm,
        if t.rv > 0.0 { format!(", convection rv {:.3} s/m (not in speakersafetyd's model: its coil resistance is the one at rest, the conservative one)", t.rv) } else { String::new() }
    ));
    s.push_str("; [Globals], [Controls], is_scale, vs_scale, is_chan, vs_chan and group describe the machine, not the driver: edit them for yours\n\n");
    s.push_str(&format!("[Globals]\nvisense_pcm = 2\nt_ambient = {:.1}\nt_hysteresis = {:.1}\nt_window = {:.1}\nchannels = {}\nperiod = 4096\nlink_gains = True\n\n", o.t_ambient, o.t_hysteresis, o.t_window, o.channels));
    s.push_str("[Controls]\nvsense = VSENSE Switch\nisense = ISENSE Switch\namp_gain = Amp Gain Volume\nvolume = Speaker Volume\n\n");
    s.push_str(&format!(
        "[Speaker/{}]\ngroup = {}\ntr_coil = {:.4}\ntr_magnet = {:.4}\ntau_coil = {:.4}\ntau_magnet = {:.4}\nt_limit = {:.1}\nt_headroom = {:.1}\nz_nominal = {:.4}\na_t_20c = {:.8}\na_t_35c = {:.8}\nis_scale = {}\nvs_scale = {}\nis_chan = {}\nvs_chan = {}\n",
        o.name, o.group, t.rtv, t.rtm, tau_coil, tau_magnet, o.t_limit, o.t_headroom, p.re, a20, a35, o.is_scale, o.vs_scale, o.is_chan, o.vs_chan
    ));
    Ok(s)
}

/// The power series as KLIPPEL LSI tabulates them: one row per x-dependent parameter, the
/// coefficients in millimetres (`Bl` in N/A/mm^n, `Kms` in N/mm/mm^n, `Le`, `L2` in
/// mH/mm^n, `R2` in ohm/mm^n), `c0` the value at rest.
pub fn power_series_csv(p: &Parameters) -> String {
    let mut rows: Vec<(&str, &str, &coilscope_core::Poly, f64)> =
        vec![("Bl", "N/A/mm^n", &p.bl, 1.0), ("Kms", "N/mm/mm^n", &p.kms, 1e-3), ("Le", "mH/mm^n", &p.le, 1e3)];
    if let Some((l2, r2)) = &p.l2r2 {
        rows.push(("L2", "mH/mm^n", l2, 1e3));
        rows.push(("R2", "ohm/mm^n", r2, 1.0));
    }
    let n = rows.iter().map(|r| r.2.c.len()).max().unwrap_or(1);
    let mut s = String::from("parameter,unit");
    for j in 0..n {
        s.push_str(&format!(",c{j}"));
    }
    s.push('\n');
    for (name, unit, f, scale) in rows {
        s.push_str(&format!("{name},{unit}"));
        for j in 0..n {
            match f.c.get(j) {
                Some(c) => s.push_str(&format!(",{:.6e}", c * scale * 1e-3f64.powi(j as i32))),
                None => s.push(','),
            }
        }
        s.push('\n');
    }
    s
}

/// The small-signal impedance of `p` at rest on `points` log-spaced frequencies from `f_lo`
/// to `f_hi` (Hz), for [`crate::impedance::zma_text`] and [`frd_text`].
pub fn impedance_curve(p: &Parameters, f_lo: f64, f_hi: f64, points: usize) -> crate::impedance::ImpedanceCurve {
    let f: Vec<f64> = (0..points).map(|k| f_lo * (f_hi / f_lo).powf(k as f64 / (points - 1).max(1) as f64)).collect();
    let z = f.iter().map(|&v| coilscope_core::small_signal::impedance(p, v)).collect();
    crate::impedance::ImpedanceCurve {
        f,
        z,
        magnitude_only: false,
        comments: vec![format!(
            "coilscope: small-signal impedance of {} at rest",
            p.name.clone().unwrap_or_else(|| "the driver".into())
        )],
    }
}

/// `.frd` text of an impedance (frequency Hz, magnitude ohm, phase degrees; `*` comments),
/// as crossover tools (VituixCAD, XSim) read impedance in FRD form: the `.zma` layout.
pub fn frd_text(curve: &crate::impedance::ImpedanceCurve) -> String {
    crate::impedance::curve_text(curve, "Impedance")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The eigen time constants: for a magnet much heavier than the coil, about Rtv Ctv (the
    /// coil) and Rtm (Ctm + Ctv) (the magnet, the coil riding on it), and each a root of the
    /// network's characteristic equation.
    #[test]
    fn time_constants_of_the_network() {
        let (rtv, ctv, rtm, ctm) = (3.2, 9.0, 1.1, 700.0);
        let (tc, tm) = thermal_time_constants(rtv, ctv, rtm, ctm);
        assert!((tc / (rtv * ctv) - 1.0).abs() < 0.02, "{tc}");
        assert!((tm / (rtm * (ctm + ctv)) - 1.0).abs() < 0.02, "{tm}");
        // Both eigenvalues satisfy the characteristic equation.
        let (a, b, c, d) = (-1.0 / (rtv * ctv), 1.0 / (rtv * ctv), 1.0 / (rtv * ctm), -(1.0 / rtv + 1.0 / rtm) / ctm);
        for tau in [tc, tm] {
            let l = -1.0 / tau;
            assert!(((a - l) * (d - l) - b * c).abs() < 1e-6 * (b * c).abs(), "{tau}");
        }
    }

    #[test]
    fn power_series_in_millimetres() {
        let p = coilscope_core::embedded_driver("sb17cac35-4").unwrap();
        let t = power_series_csv(&p);
        let bl: Vec<f64> = t
            .lines()
            .find(|l| l.starts_with("Bl,"))
            .unwrap()
            .split(',')
            .skip(2)
            .filter(|v| !v.is_empty())
            .map(|v| v.parse().unwrap())
            .collect();
        // Bl(1 mm) from the table in mm equals Bl(1e-3 m) from the set in SI.
        let at_mm: f64 = bl.iter().enumerate().map(|(j, c)| c * 1f64.powi(j as i32)).sum();
        assert!((at_mm / p.bl.eval(1e-3) - 1.0).abs() < 1e-6);
        let kms: Vec<f64> = t
            .lines()
            .find(|l| l.starts_with("Kms,"))
            .unwrap()
            .split(',')
            .skip(2)
            .filter(|v| !v.is_empty())
            .map(|v| v.parse().unwrap())
            .collect();
        let k_mm: f64 = kms.iter().enumerate().map(|(j, c)| c * 2f64.powi(j as i32)).sum();
        assert!((k_mm * 1e3 / p.kms.eval(2e-3) - 1.0).abs() < 1e-6, "Kms in N/mm at 2 mm");
    }
}

//! `quasistatic`: the static and quasi-static point-by-point measurement.

use crate::args::QuasiArgs;
use crate::measure::{corrected, open_card};
use crate::Failure;
use coilscope_core::excitation::{generate, Excitation, SignalSpec};
use coilscope_core::result::ResultFile;
use coilscope_core::simulate::{simulate, SimOptions};
use coilscope_core::small_signal::thiele_small;
use coilscope_core::Parameters;
use coilscope_io::{load_parameters, write_json};
use serde_json::json;

pub(crate) fn cmd_quasistatic(a: QuasiArgs) -> Result<(), Failure> {
    use coilscope_ident::quasi_static::{quasi_static, Offset, Played, Push, QuasiStaticOptions};
    let (out, points, reach, hold, order) = (a.out.as_path(), a.points, a.reach, a.hold, a.order);
    coilscope_io::check_writable(out).map_err(|e| e.to_string())?;
    if !(reach > 0.0 && reach <= 1.0) {
        return Err(format!("--reach {reach} is not valid (0 .. 1 of the range)").into());
    }
    if !(0.5..=600.0).contains(&hold) {
        return Err(format!("--hold {hold} s is not valid (0.5 .. 600 s)").into());
    }
    if let (Some(c), false) = (&a.card.chain, a.card.card) {
        return Err(format!("--chain {}: quasistatic corrects a sound card's chain with --card only; the virtual driver is measured through ideal channels (leave --chain out)", c.display()).into());
    }
    let fs = if a.card.card { a.rate as f64 } else { 48000.0 };
    let ac = generate(
        &Excitation::Pink { f_lo: 5.0, f_hi: 16000.0, crest: None },
        &SignalSpec { fs, seconds: 2.0, rms: 1.0, fade: 0.0, seed: 1 },
    )?;
    let (q, opts, set_name, name, device, offset) = if a.card.card {
        // A real driver: what the virtual set would tell, the user gives.
        let mms = a.mms.ok_or(
            "quasistatic --card needs --mms KG (the moving mass: the absolute scale of the small-signal fits)",
        )?;
        let xmax = a.xmax.ok_or("quasistatic --card needs --xmax LENGTH: how far the working points may go on each side (the driver's Xmax from its data sheet, or less)")?;
        if !(mms > 0.0 && mms < 10.0) {
            return Err(format!("--mms {mms} kg is not valid (0 .. 10 kg)").into());
        }
        if !(a.ac_volts > 0.0 && a.ac_volts <= 5.0) {
            return Err(format!("--ac-volts {} is not valid (0 .. 5 V rms)", a.ac_volts).into());
        }
        let offset = match a.offset.as_str() {
            "mass" => Offset::Mass,
            "pressure" => Offset::Pressure { sd: a.sd.ok_or("quasistatic --card --offset pressure needs --sd M2 (the diaphragm's area)")? },
            _ => return Err("quasistatic --card: a sound card's output is AC-coupled and cannot hold a DC current through the coil; hold the points by --offset mass (masses on the cone) or --offset pressure (a sealed box)".to_string().into()),
        };
        let mut device = open_card(&a.card, a.rate)?;
        if let Some((c, wiring)) = a.card.correction()? {
            device = corrected(device, c, wiring)?.0;
        }
        let describe = device.describe();
        let opts = QuasiStaticOptions {
            mms,
            points,
            reach,
            range: [-xmax, xmax],
            hold_s: hold,
            record_s: 2.0,
            ac_volts: a.ac_volts,
            order,
            fs,
            offset,
        };
        let mut operator =
            coilscope_measure::quasi_static_card::PromptOperator::new(std::io::stdin().lock(), std::io::stderr());
        eprintln!("quasistatic on {describe}: {points} working points to {:.0} % of +-{:.2} mm, offset by {}; a gauge on the cone reads the static displacement (q stops)", reach * 100.0, xmax * 1e3, opts.offset_name());
        let q = quasi_static(
            coilscope_measure::quasi_static_card::card_play(device.as_mut(), &mut operator, offset, 4800),
            &ac,
            &opts,
        )?;
        (q, opts, None, "the driver on the card".to_string(), describe, offset)
    } else {
        let driver = a.driver.as_deref().unwrap_or_default();
        let p = a.world.apply(load_parameters(driver).map_err(|e| e.to_string())?);
        if let Some(e) = &p.enclosure {
            return Err(format!("{driver}: the set puts the driver in a {} box (`enclosure`); the quasi-static method measures the suspension in free air (in a box it would add the air's stiffness to Kms(x)): remove `enclosure`", e.type_name()).into());
        }
        let range = p.x_range.ok_or_else(|| {
            format!("{driver}: the set has no x_range: the working points need the range they may go to")
        })?;
        // The small signal at about 2 % of the range at the resonance (a linear estimate).
        let ts = thiele_small(&p);
        let per_volt = p.bl.c[0] / (p.re * p.kms.c[0]) * ts.qts.max(0.3);
        let ac_volts = (0.02 * range[1].min(-range[0]) / per_volt).clamp(0.01, 1.0);
        let offset = match a.offset.as_str() {
            "mass" => Offset::Mass,
            "pressure" => Offset::Pressure {
                sd: p.sd.ok_or_else(|| {
                    format!("{driver}: --offset pressure needs the diaphragm's area: the set has no Sd (m^2)")
                })?,
            },
            _ => Offset::Current,
        };
        let opts = QuasiStaticOptions {
            mms: p.mms,
            points,
            reach,
            range,
            hold_s: hold,
            record_s: 2.0,
            ac_volts,
            order,
            fs,
            offset,
        };
        let play = |d: &[f64], push: Push| {
            let q = Parameters { mms: p.mms + push.added_mass, ..p.clone() };
            simulate(&q, fs, d, &SimOptions { force: push.force, ..Default::default() })
                .map(|t| Played::from((t.u, t.i, t.x)))
                .map_err(|e| e.to_string())
        };
        let q = quasi_static(play, &ac, &opts)?;
        let name = p.name.clone().unwrap_or_else(|| driver.to_string());
        (q, opts, p.name.clone(), name.clone(), format!("virtual {name}"), offset)
    };
    println!(
        "coilscope quasistatic: {name}, {points} working points to {:.0} % of the range, {hold} s hold, offset by {}",
        reach * 100.0,
        opts.offset_name()
    );
    println!(
        "  {:>8} {:>9} {:>9} {:>8} {:>8} {:>9} {:>9} {:>8}",
        "U_dc V", "x_dc mm", "I_dc A", "Re ohm", "Bl T m", "Kms N/m", "k_t N/m", "Le mH"
    );
    for w in &q.points {
        println!(
            "  {:>8.3} {:>9.3} {:>9.4} {:>8.4} {:>8.4} {:>9.1} {:>9.1} {:>8.4}",
            w.u_dc,
            w.x_dc * 1e3,
            w.i_dc,
            w.re_dc,
            w.bl,
            w.kms_static,
            w.k_tangent,
            w.le * 1e3
        );
    }
    println!("  stiffness at rest: dynamic (small signal at the resonance) {:.1} N/m, static (the secants' series) {:.1} N/m", q.k_dynamic_rest, q.params.kms.eval(0.0));
    if q.rest_drift.is_finite() {
        println!("  rest position 1.5 s after the largest offset is released: {:+.4} mm", q.rest_drift * 1e3);
    }
    // Points short of the reach asked for are not an error (the DC a point needs grows as Bl
    // falls and Kms rises), but the user is told, and where the curves end.
    if let Some([lo, hi]) = q.params.x_range {
        let asked = [reach * opts.range[0], reach * opts.range[1]];
        let share = (lo / asked[0]).min(hi / asked[1]);
        if share < 0.95 {
            println!(
                "  note: the points reached {:+.2} .. {:+.2} mm, {:.0} % of the {:+.2} .. {:+.2} mm asked (--reach {reach}): the offset a point needs grows as Bl falls and Kms rises; the curves end at the last points (fit.x_range), beyond them they are not measured",
                lo * 1e3,
                hi * 1e3,
                100.0 * share,
                asked[0] * 1e3,
                asked[1] * 1e3
            );
        }
    }
    for w in &q.warnings {
        println!("  warning: {w}");
    }
    let fit = coilscope_core::result::Fit {
        trustworthy: Some(q.warnings.is_empty()),
        warnings: Some(q.warnings.iter().map(|w| coilscope_core::result::Warning::new("quasi-static", w.clone())).collect()),
        method: Some(format!(
            "quasi-static point by point (seed paper 3.2.1; IEC 62458 10.2/10.3): offsets by {}, static displacement and force balance for Kms, the small-signal impedance at each point for Bl and Le; power series fitted to the points",
            opts.offset_name()
        )),
        residual_rel: f64::NAN,
        x_range: q.params.x_range.unwrap_or([0.0, 0.0]),
        order: Some(order),
        ..Default::default()
    };
    let lim = coilscope_core::limits::limits(&q.params, fit.x_range);
    // The driver's name, so that `report --compare` can tell two drivers apart.
    let qp = Parameters { name: set_name, ..q.params.clone() };
    let mut unc = coilscope_core::result::Uncertainty::new(format!(
        "bands of the series from the working points' sds (each point's small-signal fit, at least {} % of the value), scaled up by the series fit's chi^2 per degree of freedom where above 1",
        100.0 * coilscope_ident::quasi_static::POINT_SD_FLOOR
    ));
    for (which, band) in ["Bl", "Kms", "Le"].iter().zip(&q.bands) {
        unc.set_band(which, band.clone());
    }
    let mut r = ResultFile::new("quasi-static", &device, qp, fit, unc, Some(&lim));
    r.other.insert(
        "quasi_static".into(),
        json!({
            "offset": opts.offset_name(),
            "points": q.points.iter().map(|w| json!({"U_dc": w.u_dc, "I_dc": w.i_dc, "force_N": w.force, "added_mass_kg": w.push.added_mass, "pressure_Pa": match offset { Offset::Pressure { sd } => w.force / sd, _ => 0.0 }, "x_dc": w.x_dc, "Re_dc": w.re_dc, "Bl": w.bl, "Bl_eff": w.bl_eff, "Kms_static": w.kms_static, "k_tangent": w.k_tangent, "k_eff": w.k_eff, "Le": w.le})).collect::<Vec<_>>(),
            "k_dynamic_rest": q.k_dynamic_rest,
            "rest_drift_m": q.rest_drift,
            "hold_s": hold,
        }),
    );
    write_json(out, &r).map_err(|e| e.to_string())?;
    println!("  wrote {}", out.display());
    if q.warnings.is_empty() {
        Ok(())
    } else {
        Err(Failure::Untrusted(format!("{}: {}", out.display(), q.warnings.join("; "))))
    }
}

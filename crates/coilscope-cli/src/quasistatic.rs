//! `quasistatic`: the static and quasi-static point-by-point measurement.

use crate::args::QuasiArgs;
use crate::measure::{corrected, open_card};
use crate::Failure;
use coilscope_io::{load_parameters, write_json};
use coilscope_workflow::quasistatic::{
    reach_short, result_file, small_signal, virtual_options, virtual_quasistatic, QuasiRequest,
};

pub(crate) fn cmd_quasistatic(a: QuasiArgs) -> Result<(), Failure> {
    use coilscope_ident::quasi_static::{quasi_static, Offset, QuasiStaticOptions};
    let (out, points, reach, hold, order) = (a.out.as_path(), a.points, a.reach, a.hold, a.order);
    coilscope_io::check_writable(out).map_err(|e| e.to_string())?;
    let req = QuasiRequest { points, reach, hold_s: hold, order };
    req.check()?;
    if let (Some(c), false) = (&a.card.chain, a.card.card) {
        return Err(format!("--chain {}: quasistatic corrects a sound card's chain with --card only; the virtual driver is measured through ideal channels (leave --chain out)", c.display()).into());
    }
    let fs = if a.card.card { a.rate as f64 } else { 48000.0 };
    let (q, opts, set_name, name, device) = if a.card.card {
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
            &small_signal(fs)?,
            &opts,
        )?;
        (q, opts, None, "the driver on the card".to_string(), describe)
    } else {
        let driver = a.driver.as_deref().unwrap_or_default();
        let p = a.world.apply(load_parameters(driver).map_err(|e| e.to_string())?);
        let opts = virtual_options(&p, &req, &a.offset, driver)?;
        let q = virtual_quasistatic(&p, &opts)?;
        let name = p.name.clone().unwrap_or_else(|| driver.to_string());
        (q, opts, p.name.clone(), name.clone(), format!("virtual {name}"))
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
    if let (Some(share), Some([lo, hi])) = (reach_short(&q, &opts), q.params.x_range) {
        println!(
            "  note: the points reached {:+.2} .. {:+.2} mm, {:.0} % of the {:+.2} .. {:+.2} mm asked (--reach {reach}): the offset a point needs grows as Bl falls and Kms rises; the curves end at the last points (fit.x_range), beyond them they are not measured",
            lo * 1e3,
            hi * 1e3,
            100.0 * share,
            reach * opts.range[0] * 1e3,
            reach * opts.range[1] * 1e3
        );
    }
    for w in &q.warnings {
        println!("  warning: {w}");
    }
    // The driver's name, so that `report --compare` can tell two drivers apart.
    let r = result_file(&q, &opts, set_name, &device);
    write_json(out, &r).map_err(|e| e.to_string())?;
    println!("  wrote {}", out.display());
    if q.warnings.is_empty() {
        Ok(())
    } else {
        Err(Failure::Untrusted(format!("{}: {}", out.display(), q.warnings.join("; "))))
    }
}

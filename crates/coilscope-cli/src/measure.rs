//! `measure`, `devices` and `runs`: the dynamic measurement of a virtual driver, a replayed record or
//! a driver on a sound card, its live page and Ctrl-C handling, and the run database.

use crate::args::{CardArgs, LimitArgs, MeasureArgs};
use crate::report::cmd_report;
use crate::{iec_noise, Failure, EXIT_INTERRUPTED};
use coilscope_core::chain::SenseWiring;
use coilscope_io::{load_parameters, read_recording, write_json};
use coilscope_workflow::chain::mark_wiring;
use serde_json::json;

/// `device` read through the card's calibration `c`, corrected block by block, and the
/// calibration used: it knows the card (delay, corners, gain), not this run's offsets or hum
/// (found in the lead-in).
pub(crate) fn corrected(
    device: Box<dyn coilscope_measure::device::Device>,
    c: coilscope_core::chain::Chain,
    wiring: SenseWiring,
) -> Result<(Box<dyn coilscope_measure::device::Device>, coilscope_core::chain::Chain), String> {
    let cal = coilscope_core::chain::Chain { dc_u: 0.0, dc_i: 0.0, hum: None, ..c };
    Ok((Box::new(coilscope_measure::card::Corrected::new(device, &cal, wiring)?), cal))
}

#[cfg(feature = "soundcard")]
pub(crate) fn open_card(c: &CardArgs, rate: u32) -> Result<Box<dyn coilscope_measure::device::Device>, String> {
    use coilscope_measure::soundcard::{SoundCardDevice, SoundCardOptions};
    let o = SoundCardOptions {
        output: c.card_out.clone(),
        input: c.card_in.clone(),
        fs: rate as f64,
        out_channels: c.out_channels,
        drive_channel: c.drive_channel,
        in_channels: c.in_channels,
        u_channel: c.u_channel,
        i_channel: c.i_channel,
        out_volts_fs: c.out_volts_fs,
        u_volts_fs: c.u_volts_fs,
        i_volts_fs: c.i_volts_fs,
        sense_ohm: c.sense_ohm,
        ..Default::default()
    };
    Ok(Box::new(SoundCardDevice::open(&o)?))
}

#[cfg(not(feature = "soundcard"))]
pub(crate) fn open_card(_: &CardArgs, _: u32) -> Result<Box<dyn coilscope_measure::device::Device>, String> {
    Err(NO_SOUNDCARD.into())
}

#[cfg(not(feature = "soundcard"))]
const NO_SOUNDCARD: &str = "this coilscope was built without sound-card support: rebuild with `cargo build --release --features soundcard` (Debian/Ubuntu: apt install libasound2-dev first)";

#[cfg(feature = "soundcard")]
pub(crate) fn cmd_devices() -> Result<(), String> {
    let (inputs, outputs) = coilscope_measure::soundcard::list_devices()?;
    println!("inputs:  {}", if inputs.is_empty() { "none".into() } else { inputs.join(", ") });
    println!("outputs: {}", if outputs.is_empty() { "none".into() } else { outputs.join(", ") });
    Ok(())
}

#[cfg(not(feature = "soundcard"))]
pub(crate) fn cmd_devices() -> Result<(), String> {
    Err(NO_SOUNDCARD.into())
}

pub(crate) fn cmd_measure(a: MeasureArgs) -> Result<(), Failure> {
    use coilscope_db::{Store, Target};
    use coilscope_measure::device::Device;
    use coilscope_measure::signal::Source;
    use coilscope_workflow::measure::{replay, virtual_driver, Prepared};
    use std::io::IsTerminal;
    // A sound card's device need not be `Send`; the workflow's are.
    let take = |p: Prepared| -> (Box<dyn Device>, Prepared) {
        let (d, p) = p.split();
        (d, p)
    };
    let (mut device, Prepared { mms, mms_source, mms_sd_rel, sd, notes, .. }): (Box<dyn Device>, Prepared) = match (
        &a.virtual_driver,
        &a.replay,
    ) {
        (Some(d), None) => {
            let given = load_parameters(d).map_err(|e| e.to_string())?;
            let noise = (a.noise[0], a.noise[1]);
            virtual_driver(&given, d, a.world.workflow(), a.mms, a.sd, a.rate as f64, noise, a.seed).map(take)?
        }
        (None, Some(r)) => {
            let rec = read_recording(r, None).map_err(|e| e.to_string())?;
            replay(rec, &r.display().to_string(), a.mms, a.sd).map(take)?
        }
        (None, None) if a.card.card => {
            coilscope_workflow::measure::check_sd(a.sd)?;
            let mms = a.mms.ok_or("--card needs --mms MASS (the absolute scale: weigh the cone, or measure it by the added-mass method with `coilscope linear`)")?;
            (open_card(&a.card, a.rate)?, Prepared::given(mms, a.sd))
        }
        _ => {
            return Err(
                "give the device: --virtual DRIVER (embedded name or parameter file), --replay REC.wav or --card"
                    .into(),
            )
        }
    };
    for n in &notes {
        println!("{n}");
    }
    // The card's chain and wiring: corrected block by block (a virtual driver with a chain is
    // recorded through a simulated card first).
    let mut reported_chain = None;
    if let Some((c, wiring)) = a.card.correction()? {
        if a.replay.is_some() {
            return Err(Failure::from("--chain and --sense-wiring apply to --card and --virtual, not to a --replay (fit a record with `coilscope identify --chain FILE`)".to_string()));
        }
        if a.virtual_driver.is_some() {
            let full_scale = (a.card.u_volts_fs, a.card.i_volts_fs / a.card.sense_ohm);
            device = Box::new(coilscope_measure::card::SimulatedCard::new(
                device,
                &coilscope_core::chain::Chain { source: Some("simulated".into()), ..c.clone() },
                wiring,
                full_scale,
            )?);
        }
        let cal;
        (device, cal) = corrected(device, c, wiring)?;
        reported_chain = Some(coilscope_core::chain::Chain { source: Some("calibrated".into()), ..cal });
        mark_wiring(&mut reported_chain, wiring);
    }
    let fs = device.fs();
    let mut source = match &a.music {
        Some(m) => Source::music(m, fs)?,
        None => Source::noise(&iec_noise(a.crest), fs, a.seed)?,
    };
    // The live page, before the first block; a virtual or replayed run is paced to real time
    // for it unless --pace says otherwise (a sound card is paced by its clock).
    let pace = match (a.serve.pace, a.card.card) {
        (Some(_), true) => {
            return Err(Failure::from(
                "--pace applies to --virtual and --replay; a sound card plays in real time".to_string(),
            ))
        }
        (Some(f), false) if !(f > 0.0 && f.is_finite()) => {
            return Err(Failure::from(format!(
                "--pace {f}: give a positive factor of real time (1: real time, 4: four times faster)"
            )))
        }
        (Some(f), false) => Some(f),
        (None, false) if a.serve.serve.is_some() => Some(1.0),
        (None, _) => None,
    };
    if !(a.serve.serve_linger >= 0.0 && a.serve.serve_linger.is_finite()) {
        return Err(Failure::from(format!("--serve-linger {}: give seconds, 0 or more", a.serve.serve_linger)));
    }
    let server = a
        .serve
        .serve
        .as_deref()
        .map(|addr| coilscope_live::LiveServer::start(addr, a.serve.serve_public))
        .transpose()?;
    if let Some(s) = &server {
        s.info(&device.describe(), source.name(), device.controllable(), fs);
        eprintln!("live page: {}", s.url());
    }
    let interrupt = interrupt_flag();
    let opts = coilscope_measure::MeasureOptions {
        mms,
        target_x: a.target_x,
        max_dt: a.max_dt,
        kms_limit: a.kms_limit,
        max_volts: a.max_volts,
        start_volts: a.start_volts,
        duration: a.duration,
        hold_volts: a.volts,
        cool: a.cool,
        max_seconds: a.max_seconds.max(a.duration.unwrap_or(0.0)),
        order: a.order,
        interrupt: Some(interrupt.clone()),
        ..Default::default()
    };
    opts.validate()?;
    std::fs::create_dir_all(&a.out)
        .map_err(|e| format!("{}: cannot create the output directory: {e}", a.out.display()))?;
    let options = json!({"target_x": opts.target_x, "max_dt": opts.max_dt, "kms_limit": opts.kms_limit, "max_volts": opts.max_volts, "duration": opts.duration, "volts": opts.hold_volts, "cool": opts.cool, "excitation": source.name(), "mms": mms});
    let target = a.db.as_deref().map_or_else(|| Target::Sqlite(a.out.join("run.sqlite")), Target::parse);
    let mut store = Store::create(&target, &device.describe(), &options)?;
    let tty = std::io::stderr().is_terminal();
    let mut last_print = -1.0;
    let controllable = device.controllable();
    if controllable {
        eprintln!("measuring {} with {} (run {} in {})", device.describe(), source.name(), store.run, target.name());
    } else {
        eprintln!("identifying from the {} (run {} in {})", device.describe(), store.run, target.name());
    }
    let started = std::time::Instant::now();
    let result = coilscope_measure::measure(device.as_mut(), &mut source, &opts, Some(&mut store), |l| {
        if let Some(s) = &server {
            s.block(l);
        }
        if let Some(f) = pace {
            let due = std::time::Duration::from_secs_f64(l.t / f);
            if let Some(wait) = due.checked_sub(started.elapsed()) {
                std::thread::sleep(wait);
            }
        }
        if l.t - last_print >= 1.0 || l.update.is_some() && tty {
            last_print = l.t;
            // Before the small-signal fit there is no estimate yet: a dash, not NaN.
            let re = if l.re.is_finite() { format!("{:.4}", l.re) } else { "  -   ".to_string() };
            let err = if l.residual.is_finite() { format!("{:.1e}", l.residual) } else { "  -   ".to_string() };
            let state = format!(
                "x {:+6.2} .. {:+6.2} mm  dT {:5.1} K  Re {re} ohm  err {err}",
                l.x_min * 1e3,
                l.x_max * 1e3,
                l.dtv
            );
            // The expected time to convergence, and when the run stops at the latest.
            let eta = match l.eta {
                Some(e) => format!("ETA ~{e:.0} s (stops by {:.0} s)", l.end),
                None => format!("ETA -  (stops by {:.0} s)", l.end),
            };
            // A replay's level was set when it was recorded: no drive level, no controller.
            let line = if controllable {
                format!(
                    "t {:6.1} s  {:<12} {:7.3} V  {state}  limited by {}  {eta}",
                    l.t,
                    l.stage.name(),
                    l.volts,
                    l.limited_by
                )
            } else {
                format!("t {:6.1} s  {state}  {eta}", l.t)
            };
            if tty {
                eprint!("\r{line}   ");
            } else {
                eprintln!("{line}");
            }
        }
    });
    if tty {
        eprintln!();
    }
    let mut m = match result {
        Ok(m) => m,
        Err(e) => {
            // Nothing was estimated yet (the small-signal stage failed): the result says so.
            let j = coilscope_core::result::FailedResult::new(&e, &device.describe(), source.name());
            let _ = write_json(&a.out.join("result.json"), &j);
            let _ = store.finish(0.0, &format!("failed: {e}"), Some(&j));
            if let Some(s) = server {
                s.done("failed", &e, None);
                linger(s, a.serve.serve_linger, &interrupt);
            }
            return Err(Failure::from(format!("{e}; written to {}", a.out.join("result.json").display())));
        }
    };
    let j = coilscope_workflow::measure::result_of(&mut m, &mms_source, mms_sd_rel, sd, reported_chain);
    write_json(&a.out.join("result.json"), &j).map_err(|e| e.to_string())?;
    let status = coilscope_workflow::measure::status(&m);
    store.finish(m.seconds, status, Some(&j))?;
    for w in m.warnings() {
        eprintln!("warning [{}]: {}", w.code, w.message);
    }
    let p = &m.params;
    println!("{status}: {}", m.stop_reason.describe());
    println!(
        "measured {:.1} s, peak x {:.2} mm, voice-coil rise up to {:.1} K, {} updates, window residual {:.2e}",
        m.seconds,
        m.x_peak_max * 1e3,
        m.dtv_max,
        m.updates,
        m.residual_rel
    );
    println!(
        "start (the first {} s): Re {:.4} ohm, Bl {:.3} T m, Kms {:.1} N/m, Rms {:.3} kg/s",
        opts.small_seconds,
        m.small.re,
        m.small.bl.eval(0.0),
        m.small.kms.eval(0.0),
        m.small.rms
    );
    // An sd the fit could not give (a degenerate small-signal fit) is said so, not printed as NaN.
    let re_cold_sd = if m.re_cold_sd.is_finite() {
        format!("+- {:.1e}", m.re_cold_sd)
    } else {
        "(no sd: the small-signal fit gave none)".to_string()
    };
    println!("cold Re (the temperature reference: the small-signal stage refitted with the final model when converged, else its impedance fit): {:.4} ohm {re_cold_sd}", m.re_cold);
    let [lo, hi] = m.x_range;
    println!("large signal (end), over {:.2} .. {:.2} mm:", lo * 1e3, hi * 1e3);
    // The functions of x of the parameter schema (constants among them on one line below).
    for e in coilscope_core::schema::ENTRIES.iter().filter(|e| e.kind == coilscope_core::schema::Kind::SeriesX) {
        if let Some(coilscope_core::schema::Value::Series(f)) = p.get(e.key) {
            let ((unit, k), name) = (e.display, e.key);
            if f.c.len() > 1 {
                println!(
                    "  {name:<4} {:10.4} {:10.4} {:10.4} {unit}  (x_min, 0, x_max)",
                    f.eval(lo) * k,
                    f.eval(0.0) * k,
                    f.eval(hi) * k
                );
            }
        }
    }
    let mut model = format!("model {}", m.effects.model_name());
    if let Some(c) = &p.creep {
        model += &format!(", creep lambda {:.4}", c.lambda);
    }
    if let Some((l3, r3)) = p.l3r3 {
        model += &format!(", L3 {:.4} mH, R3 {:.4} ohm", l3 * 1e3, r3);
    }
    if let Some(g) = &p.le_i {
        model += &format!(", Le(i) g = {:?}", g.c.iter().map(|c| format!("{c:.3e}")).collect::<Vec<_>>());
    }
    if let Some(r) = &p.rms_v {
        model += &format!(", Rms(v) = {:.4} + {:.4} v^2 kg/s", r.c[0], r.c.get(2).copied().unwrap_or(0.0));
    }
    if m.dropped != coilscope_core::effects::Effects::NONE {
        model += &format!(" ({})", m.models_note());
    }
    println!("  {model}");
    for (t, e) in &m.events {
        println!("  at {t:.1} s: {e}");
    }
    println!("wrote {} and run {} in {}", a.out.join("result.json").display(), store.run, target.name());
    if !a.no_report {
        let t = coilscope_core::limits::Thresholds::default();
        let defaults = LimitArgs { xbl: t.bl, xc: t.cms, xl: t.le, max_dt: a.max_dt };
        let result = a.out.join("result.json");
        // The measurement is stored whatever happens to its report.
        if let Err(e) =
            cmd_report(&result.to_string_lossy(), &a.out.join("report.html"), a.db.as_deref(), None, None, &defaults)
        {
            eprintln!("warning: the report was not written: {e}");
        }
    }
    if let Some(s) = server {
        s.done(status, &m.stop_reason.describe(), (!a.no_report).then_some(a.out.as_path()));
        linger(s, a.serve.serve_linger, &interrupt);
    }
    let written = a.out.join("result.json");
    match m.stop_reason {
        coilscope_measure::StopReason::Interrupted { .. } => {
            Err(Failure::Interrupted(format!("{}; written to {}", m.stop_reason.describe(), written.display())))
        }
        coilscope_measure::StopReason::Failed { .. } => {
            Err(Failure::Error(format!("{}; written to {}", m.stop_reason.describe(), written.display())))
        }
        ref r if !r.is_success() => {
            Err(Failure::Untrusted(format!("{}; written to {}", r.describe(), written.display())))
        }
        _ => Ok(()),
    }
}

/// Set while the live page lingers after the run: Ctrl-C then ends the serving, and says so.
static LINGERING: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Keep the live page (and the report it links) served for `seconds` after the run, or until
/// Ctrl-C.
fn linger(server: coilscope_live::LiveServer, seconds: f64, interrupt: &std::sync::atomic::AtomicBool) {
    if seconds > 0.0 {
        eprintln!(
            "live page: the run is over; serving {} and its report for {seconds:.0} s more (Ctrl-C ends it)",
            server.url()
        );
        let end = std::time::Instant::now() + std::time::Duration::from_secs_f64(seconds);
        // A Ctrl-C during the run has already been answered by the run's end.
        LINGERING.store(true, std::sync::atomic::Ordering::SeqCst);
        interrupt.store(false, std::sync::atomic::Ordering::SeqCst);
        while std::time::Instant::now() < end && !interrupt.load(std::sync::atomic::Ordering::SeqCst) {
            std::thread::sleep(std::time::Duration::from_millis(100));
        }
    }
    server.stop();
}

/// A flag that Ctrl-C (SIGINT) sets: the measurement finishes its block, writes its result,
/// report and database rows marked interrupted, and exits 130. A second Ctrl-C kills at once.
fn interrupt_flag() -> std::sync::Arc<std::sync::atomic::AtomicBool> {
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::Arc;
    let flag = Arc::new(AtomicBool::new(false));
    let f = flag.clone();
    let installed = ctrlc::set_handler(move || {
        if f.swap(true, Ordering::SeqCst) {
            std::process::exit(EXIT_INTERRUPTED as i32);
        }
        if LINGERING.load(Ordering::SeqCst) {
            eprintln!("\ninterrupt: the live page stops (the result is written)");
        } else {
            eprintln!("\ninterrupt: finishing the block and writing the result (Ctrl-C again to quit at once)");
        }
    });
    if let Err(e) = installed {
        eprintln!("warning: Ctrl-C cannot be caught ({e}): an interrupted run will not write its result");
    }
    flag
}

pub(crate) fn cmd_runs(spec: &str) -> Result<(), String> {
    let target = coilscope_db::Target::parse(spec);
    let runs = coilscope_db::list_runs(&target)?;
    if runs.is_empty() {
        println!("{}: no runs", target.name());
    }
    for r in runs {
        print!(
            "run {:>3}  {:<12} {:8.1} s  {:>6} states  {:>4} estimates  {:>4} units  {}",
            r.id, r.status, r.seconds, r.states, r.estimates, r.units, r.device
        );
        if let Some(l) = r.last {
            print!(
                "  | last t {:.1} s: x {:+.2} .. {:+.2} mm, dT {:.1} K, {:.3} V",
                l.t,
                l.x_min * 1e3,
                l.x_max * 1e3,
                l.dtv,
                l.gain
            );
        }
        println!();
    }
    Ok(())
}

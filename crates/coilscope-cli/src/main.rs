//! `coilscope`: large-signal parameters of electrodynamic transducers.
//!
//! A thin shell over the library crates: parse arguments, call one library function per
//! step, print. Every failure is one line on stderr and a non-zero exit code:
//!
//! | code | meaning |
//! |---|---|
//! | 0 | done, and the result can be trusted |
//! | 2 | error: bad input, or the work could not be done (nothing trustworthy written) |
//! | 3 | a result was written but is not trustworthy: not converged, or a warning that the fit does
//! not describe the record (the best estimate is on disk, `fit.converged`/`fit.warnings` say why) |
//! | 130 | interrupted (Ctrl-C): the result so far is written and marked interrupted |

mod args;
mod calibrate;
mod distortion;
mod drivers;
mod identify;
mod linear;
mod measure;
mod qc;
mod quasistatic;
mod report;
mod simulate;

use args::{Command, DistortionArgs, FitArgs, LinearArgs, MeasureArgs, QuasiArgs, SimulateArgs};
use calibrate::cmd_calibrate;
use clap::Parser;
use coilscope_core::chain::SenseWiring;
use coilscope_core::excitation::Excitation;
use coilscope_core::Parameters;
use coilscope_io::load_parameters;
use coilscope_workflow::chain::ChainMode;
use distortion::cmd_distortion;
use drivers::{cmd_drivers, print_params};
use identify::{cmd_identify, cmd_identify_batch, cmd_identify_volterra};
use linear::cmd_linear;
use measure::{cmd_devices, cmd_measure, cmd_runs};
use quasistatic::cmd_quasistatic;
use report::{cmd_compensate, cmd_diagnose, cmd_export, cmd_report, ExportFormat};
use simulate::cmd_simulate;
use std::path::Path;
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "coilscope",
    version,
    about = "Large-signal parameters of electrodynamic transducers (Bl(x), Kms(x), Le(x), thermal) from voltage and current",
    after_help = "Exit codes: 0 done and trustworthy; 2 error (bad input, nothing trustworthy written); 3 result written but not trustworthy (not converged, or warnings: see fit.warnings); 130 interrupted (result so far written)."
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// `--sense-wiring` and `--sense-ohm`.
fn parse_wiring(wiring: &str, ohm: Option<f64>) -> Result<SenseWiring, Failure> {
    let w = SenseWiring::parse(wiring, ohm).map_err(Failure::from)?;
    if w == SenseWiring::Terminals && ohm.is_some() {
        return Err(Failure::from("--sense-ohm is for --sense-wiring driver+shunt (the resistor whose drop the voltage channel records); with `terminals` the current channel is already in amperes".to_string()));
    }
    Ok(w)
}

/// The wiring of a fit: `--sense-wiring`/`--sense-ohm`, else a chain file's, else `terminals`.
fn fit_wiring(a: &FitArgs, chain: &ChainMode) -> Result<SenseWiring, Failure> {
    match (&a.sense_wiring, chain) {
        (Some(w), _) => parse_wiring(w, a.sense_ohm),
        (None, ChainMode::Calibrated(c)) if c.sense_wiring.is_some() => {
            let w = c.sense_wiring.as_deref().unwrap_or_default();
            SenseWiring::parse(w, a.sense_ohm.or(c.sense_ohm))
                .map_err(|e| Failure::from(format!("the chain file's sense_wiring {w:?}: {e}")))
        }
        (None, _) => parse_wiring("terminals", a.sense_ohm),
    }
}

/// `--chain`: `detect`, `auto`, `none`, or a chain file.
fn parse_chain(text: &str) -> Result<ChainMode, Failure> {
    ChainMode::parse(text).map_err(Failure::from)
}

/// Exit code of an error (bad input, or the work could not be done).
const EXIT_ERROR: u8 = 2;
/// Exit code of a result that was written but cannot be trusted.
const EXIT_UNTRUSTED: u8 = 3;
/// Exit code of a unit that failed its end-of-line limits (`qc test`).
const EXIT_REJECTED: u8 = 4;
/// Exit code of an interrupted run (128 + SIGINT, as shells report it).
const EXIT_INTERRUPTED: u8 = 130;

/// How a command failed; each kind has its exit code.
#[derive(Debug)]
enum Failure {
    /// Bad input, or the work could not be done.
    Error(String),
    /// A result is on disk, but not trustworthy (the message says why and where it is).
    Untrusted(String),
    /// Stopped by Ctrl-C after writing what it had.
    Interrupted(String),
    /// The unit failed its end-of-line test (the message names the figures).
    Rejected(String),
}

impl From<String> for Failure {
    fn from(e: String) -> Self {
        Failure::Error(e)
    }
}

impl From<&str> for Failure {
    fn from(e: &str) -> Self {
        Failure::Error(e.to_string())
    }
}

/// A reader that closes the pipe early (`coilscope quasistatic ... | head`) ends the program
/// quietly, as it does any Unix tool, instead of a panic in `println!` (Rust ignores SIGPIPE
/// by default, so the write fails and `println!` panics).
#[cfg(unix)]
fn restore_sigpipe() {
    // SAFETY: setting a signal's disposition to its default, before any thread starts.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

fn main() -> ExitCode {
    #[cfg(unix)]
    restore_sigpipe();
    // A value an option's parser refused (`--mms 15 lb`, `--xmax 4 cm`) is one line that
    // names the option, the value and what would be valid, as every other bad input is.
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) if e.kind() == clap::error::ErrorKind::ValueValidation => {
            let text = e.render().to_string();
            eprintln!("{}", text.lines().next().unwrap_or("error: an option's value is not valid"));
            return ExitCode::from(2);
        }
        Err(e) => e.exit(),
    };
    let result: Result<(), Failure> = match cli.command {
        Command::Simulate { driver, excitation, volts, seconds, out, laser, snr_db, seed, rate, input, freq, band, crest, tones, fade, scale, world, chain, sense_wiring, sense_ohm, enclosure } => parse_wiring(&sense_wiring, sense_ohm)
            .and_then(|wiring| cmd_simulate(SimulateArgs { driver, excitation, volts, seconds, out, laser, snr_db, seed, rate, input, freq, band, crest, tones, fade, scale, world, chain, wiring, enclosure }).map_err(Failure::from)),
        Command::Linear { recording, impedance, mms, added_mass, with_mass, with_mass_impedance, band, volts, effects, enclosure, driver, sp, fit } => {
            cmd_linear(LinearArgs { enclosure, driver, sp, recording, impedance, mms, added_mass, with_mass, with_mass_impedance, band, volts, effects, fit })
        }
        Command::Identify { recording, jobs, method, start, mms, order, effects, enclosure, vb, port_area, sp, fit } => parse_chain(&fit.chain).and_then(|chain| {
            let in_box = match &enclosure {
                None => None,
                Some(t) => Some(coilscope_workflow::identify::in_box(t, fit.sd, vb, port_area, sp).map_err(Failure::from)?),
            };
            if recording.len() > 1 {
                if in_box.is_some() {
                    return Err(Failure::from("--enclosure identifies one recording; a batch is of drivers in free air"));
                }
                return cmd_identify_batch(&recording, jobs, &fit.out);
            }
            if in_box.is_some() && method == "volterra" {
                return Err(Failure::from("--enclosure is for the full identification (--method full); the Volterra method knows no box"));
            }
            let recording = &recording[0];
            if jobs.is_some() {
                Err(Failure::from("--jobs applies to several recordings (a batch); one recording uses every core by itself"))
            } else if method == "volterra" {
                cmd_identify_volterra(recording, start.as_deref(), mms.map(|m| m.kg), order, &effects, &chain, fit_wiring(&fit, &chain)?, fit.sd, fit.scale.as_deref(), &fit.out)
            } else if start.is_some() {
                Err(Failure::from("--start is the Volterra method's small-signal set (--method volterra); the full identification finds its own start"))
            } else {
                cmd_identify(recording, mms, order, &effects, &chain, fit_wiring(&fit, &chain)?, fit.sd, in_box, fit.scale.as_deref(), &fit.out)
            }
        }),
        Command::Calibrate { recording, resistor, loopback, scale, out, sense_wiring, sense_ohm } => parse_wiring(&sense_wiring, sense_ohm).and_then(|w| cmd_calibrate(&recording, resistor, loopback, w, scale.as_deref(), &out)),
        Command::Measure { no_report, virtual_driver, world, card, replay, out, db, mms, sd, target_x, max_dt, kms_limit, max_volts, start_volts, music, duration, volts, cool_after, cool_volts, max_seconds, order, noise, rate, seed, crest, serve } => {
            cmd_measure(MeasureArgs {
                no_report,
                db,
                virtual_driver,
                world,
                card,
                replay,
                out,
                mms,
                sd,
                target_x,
                max_dt,
                kms_limit,
                max_volts,
                start_volts,
                music,
                duration,
                volts,
                cool: cool_after.zip(cool_volts),
                max_seconds,
                order,
                noise,
                rate,
                seed,
                crest,
                serve,
            })
        }
        Command::Devices => cmd_devices().map_err(Failure::from),
        Command::Runs { database } => cmd_runs(&database).map_err(Failure::from),
        Command::Distortion { params, freq, freq2, ratio, volts, output, multitone, band, tones, sweep, levels, temp_rise, json, seed } => {
            cmd_distortion(DistortionArgs { params, freq, freq2, ratio, volts, output: output.into(), multitone, band, tones, sweep, levels, temp_rise, json, seed }).map_err(Failure::from)
        }
        Command::Diagnose { params, limits, json } => cmd_diagnose(&params, &limits, json).map_err(Failure::from),
        Command::Report { result, out, db, volts, compare, limits } => cmd_report(&result, &out, db.as_deref(), volts, compare.as_deref(), &limits).map_err(Failure::from),
        Command::Compensate { params, input, out, max_volts, min_force_factor, scale } => cmd_compensate(&params, &input, &out, max_volts, min_force_factor, scale).map_err(Failure::from),
        Command::Quasistatic { driver, out, points, reach, hold, order, world, offset, mms, xmax, sd, ac_volts, rate, card } => {
            cmd_quasistatic(QuasiArgs { driver, out, points, reach, hold, order, world, offset, mms, xmax, sd, ac_volts, rate, card })
        }
        Command::Drivers => cmd_drivers().map_err(Failure::from),
        Command::Export { result, protection, unit_id, measured_at, speakersafetyd, power_series, zma, frd: _, out, name, t_limit, t_ambient, channels, is_chan, vs_chan, is_scale, vs_scale, group } => {
            let o = coilscope_io::export::SafetydOptions { name, t_limit, t_ambient, channels, is_chan, vs_chan, is_scale, vs_scale, group, ..Default::default() };
            let format = if protection {
                ExportFormat::Protection { unit_id, measured_at }
            } else if speakersafetyd {
                ExportFormat::Speakersafetyd
            } else if power_series {
                ExportFormat::PowerSeries
            } else if zma {
                ExportFormat::Zma
            } else {
                ExportFormat::Frd
            };
            cmd_export(&result, format, &out, &o).map_err(Failure::from)
        }
        Command::Qc { action } => qc::cmd_qc(action),
        Command::Check { params, json } => load_parameters(&params).map_err(|e| Failure::Error(e.to_string())).map(|p| {
            if json {
                println!("{}", serde_json::to_string_pretty(&p.to_json_value()).unwrap_or_default());
            } else {
                print_params(&p)
            }
        }),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(Failure::Error(e)) => {
            eprintln!("error: {e}");
            ExitCode::from(EXIT_ERROR)
        }
        Err(Failure::Untrusted(e)) => {
            eprintln!("not trustworthy: {e}");
            ExitCode::from(EXIT_UNTRUSTED)
        }
        Err(Failure::Interrupted(e)) => {
            eprintln!("interrupted: {e}");
            ExitCode::from(EXIT_INTERRUPTED)
        }
        Err(Failure::Rejected(e)) => {
            eprintln!("FAIL: {e}");
            ExitCode::from(EXIT_REJECTED)
        }
    }
}

/// The set's constants and values at rest, a line each, in the parameter schema's order and
/// display units (`coilscope_core::schema`), with the result's sd (`uncertainty.<key>`) where
/// it has one; `skip`: keys shown otherwise. The thermal constants are not fitted here.
fn print_values(p: &Parameters, uncertainty: &coilscope_core::result::Uncertainty, skip: &[&str]) {
    let shown = p
        .values_at_rest()
        .filter(|(e, _)| e.component != coilscope_core::schema::Component::Thermal && !skip.contains(&e.key));
    for (e, v) in shown {
        let (unit, scale) = e.display;
        let sd = uncertainty.value(e.key).map(|s| format!("+- {:.2e}", s * scale)).unwrap_or_default();
        println!("  {:<6} {:>12} {:<5} {}", e.short(), format!("{:.4}", v * scale), unit, sd);
    }
}

/// `--effects`: `auto`, or a list for [`coilscope_ident::linear::Effects::parse`].
fn parse_effects(text: &str) -> Result<coilscope_ident::linear::EffectsChoice, Failure> {
    use coilscope_ident::linear::{Effects, EffectsChoice};
    match text.trim() {
        "auto" => Ok(EffectsChoice::Auto),
        other => Ok(EffectsChoice::Fixed(Effects::parse(other).map_err(|e| format!("--effects {other:?}: {e}"))?)),
    }
}

/// Print a result's warnings, one line each.
fn print_warnings(warnings: &[coilscope_ident::checks::Warning]) {
    for w in warnings {
        eprintln!("warning [{}]: {}", w.code, w.message);
    }
}

/// Exit 3 (result written, not trustworthy) when there are warnings.
fn untrusted_if_warned(warnings: &[coilscope_ident::checks::Warning], out: &Path) -> Result<(), Failure> {
    if warnings.is_empty() {
        return Ok(());
    }
    let codes: Vec<&str> = warnings.iter().map(|w| w.code.as_ref()).collect();
    Err(Failure::Untrusted(format!(
        "{} warning(s) ({}); the result is written to {} with fit.trustworthy = false",
        warnings.len(),
        codes.join(", "),
        out.display()
    )))
}

fn print_json(v: &serde_json::Value) {
    println!("{}", serde_json::to_string_pretty(v).expect("JSON values serialise"));
}

/// The IEC noise with `--crest` (None: the default crest [`coilscope_core::excitation::IEC_CREST`]).
fn iec_noise(crest: Option<f64>) -> Excitation {
    match crest {
        None => Excitation::Iec,
        Some(c) if c.is_infinite() => Excitation::IecCrest { crest: None },
        Some(c) => Excitation::IecCrest { crest: Some(c) },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    /// Every flag of every subcommand says what it is.
    #[test]
    fn every_flag_has_help() {
        let mut missing = Vec::new();
        let root = Cli::command();
        for sub in root.get_subcommands() {
            for arg in sub.get_arguments() {
                let id = arg.get_id().as_str();
                if id == "help" || id == "version" {
                    continue;
                }
                if arg.get_help().is_none_or(|h| h.to_string().trim().is_empty()) {
                    missing.push(format!("{} --{}", sub.get_name(), arg.get_long().unwrap_or(id)));
                }
            }
            if sub.get_about().is_none() {
                missing.push(format!("{} (no about)", sub.get_name()));
            }
        }
        assert!(missing.is_empty(), "flags without help: {missing:?}");
    }
}

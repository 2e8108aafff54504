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

use clap::{Parser, Subcommand, ValueEnum};
use coilscope_core::chain::SenseWiring;
use coilscope_core::excitation::{add_sensor_noise, crest_factor, generate, Excitation, SignalSpec};
use coilscope_core::result::ResultFile;
use coilscope_core::simulate::{simulate, SimOptions};
use coilscope_core::small_signal::thiele_small;
use coilscope_core::{embedded_driver, embedded_driver_names, Parameters};
use coilscope_io::{load_parameters, read_recording, read_voltage, write_json, write_recording, Recording};
use coilscope_workflow::chain::{load_chain, mark_wiring, ChainMode};
use serde_json::json;
use std::path::{Path, PathBuf};
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

/// The virtual driver's world (`--world`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum World {
    /// The parameter set as given.
    Published,
    /// Plus typical LOG creep where the set has none (lambda 0.05 at the resonance), as a real
    /// suspension has.
    Real,
}

impl World {
    fn apply(self, p: Parameters) -> Parameters {
        match self {
            World::Published => p,
            World::Real => p.with_typical_creep(),
        }
    }
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum ExcitationKind {
    /// IEC 60268-1 simulated programme signal (Table II band levels; crest factor 2, --crest CF or inf).
    Noise,
    /// Band-limited pink noise (--band, --crest).
    Pink,
    /// Sine (--freq).
    Sine,
    /// Log-spaced multitone (--band, --tones, --crest).
    Multitone,
    /// Logarithmic sweep over --band.
    Sweep,
    /// Periodic (1 s) multitone whose tones' 2nd and 3rd harmonics can be read, for
    /// `identify --method volterra` (--band, --tones, --crest); about half the resonance to
    /// 20 times it, at a small level.
    Readable,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum OutputKind {
    /// Far-field sound pressure (cone acceleration).
    Pressure,
    /// Voice-coil displacement.
    Displacement,
    /// Terminal current.
    Current,
}

impl From<OutputKind> for coilscope_analysis::distortion::Output {
    fn from(k: OutputKind) -> Self {
        use coilscope_analysis::distortion::Output;
        match k {
            OutputKind::Pressure => Output::Pressure,
            OutputKind::Displacement => Output::Displacement,
            OutputKind::Current => Output::Current,
        }
    }
}

/// Arguments shared by the fits of a recording (`linear`, `identify`).
#[derive(clap::Args, Clone, Debug)]
struct FitArgs {
    /// Effective radiating area (m^2), for Vas.
    #[arg(long)]
    sd: Option<f64>,
    /// Scale factors of integer-PCM recordings (V, A [, m] per count).
    #[arg(long, num_args = 2..=3, value_names = ["V", "A"])]
    scale: Option<Vec<f64>>,
    /// The measurement chain between the driver and the recorded channels: `detect` (the
    /// default: estimated with the driver where the record shows one: a skew of the
    /// channels, AC coupling, offsets or mains hum), `auto` (always estimated), `none` (the
    /// channels are the driver's voltage and current, exactly), or a chain FILE from
    /// `coilscope calibrate` (delay, corners and gain known; each record's offsets are found).
    #[arg(long, default_value = "detect")]
    chain: String,
    /// Where the voltage channel is connected: `terminals` (across the driver alone:
    /// preferred) or `driver+shunt` (across driver and sense resistor in series, as a
    /// low-side shunt with single-ended inputs gives; the shunt's drop is taken out, so give
    /// --sense-ohm, measured four-wire).
    /// Default: the chain file's wiring, else `terminals`.
    #[arg(long, value_name = "WIRING")]
    sense_wiring: Option<String>,
    /// The sense resistor (ohm) of `--sense-wiring driver+shunt`.
    #[arg(long, value_name = "OHM")]
    sense_ohm: Option<f64>,
    /// Result file (JSON, coilscope.result/1). `linear` also writes the measured impedance
    /// beside it as .zma and .csv.
    #[arg(long)]
    out: PathBuf,
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

/// Limit thresholds and the thermal limit, shared by `diagnose` and `report`.
#[derive(clap::Args, Clone, Copy, Debug)]
struct LimitArgs {
    /// XBl threshold: Bl falls to this fraction of Bl(0).
    #[arg(long, default_value_t = 0.82)]
    xbl: f64,
    /// XC threshold: Cms falls to this fraction of Cms(0).
    #[arg(long, default_value_t = 0.75)]
    xc: f64,
    /// XL threshold: Le changes by this fraction of Le(0).
    #[arg(long, default_value_t = 0.10)]
    xl: f64,
    /// Voice-coil temperature rise limit for the thermal power handling (K).
    #[arg(long, default_value_t = 50.0)]
    max_dt: f64,
}

impl LimitArgs {
    fn thresholds(&self) -> Result<coilscope_core::limits::Thresholds, String> {
        let t = coilscope_core::limits::Thresholds { bl: self.xbl, cms: self.xc, le: self.xl };
        t.validate().map_err(|e| format!("{e} (--xbl, --xc, --xl)"))?;
        if !(self.max_dt.is_finite() && self.max_dt > 0.0 && self.max_dt <= 300.0) {
            return Err(format!("--max-dt {} K is not valid (0 .. 300 K)", self.max_dt));
        }
        Ok(t)
    }
}

#[derive(Subcommand)]
enum Command {
    /// Simulate a driver (virtual transducer) and write a recording: voltage, current [, displacement].
    Simulate {
        /// Embedded driver name (see `coilscope drivers`) or parameter file (JSON).
        driver: String,
        /// Excitation signal (ignored with --input).
        #[arg(long, value_enum, default_value = "noise")]
        excitation: ExcitationKind,
        /// RMS voltage at the terminals (V). With --input: rescale the file to this RMS.
        #[arg(long)]
        volts: Option<f64>,
        /// Duration (s).
        #[arg(long, default_value_t = 4.0)]
        seconds: f64,
        /// Output recording (32-bit float WAV, physical units).
        #[arg(long)]
        out: PathBuf,
        /// Also record the displacement (channel 3), as a laser would.
        #[arg(long)]
        laser: bool,
        /// Add Gaussian sensor noise this many dB below each channel's RMS.
        #[arg(long)]
        snr_db: Option<f64>,
        /// Seed of the excitation and sensor-noise RNGs.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Sample rate (Hz).
        #[arg(long, default_value_t = 48000)]
        rate: u32,
        /// Drive with channel 1 of this WAV (volts) instead of a generated excitation.
        #[arg(long)]
        input: Option<PathBuf>,
        /// Sine frequency (Hz).
        #[arg(long, default_value_t = 50.0)]
        freq: f64,
        /// Band of pink noise, multitone or sweep (Hz).
        #[arg(long, num_args = 2, value_names = ["LO", "HI"])]
        band: Option<Vec<f64>>,
        /// Crest-factor target: noise (default 2; inf: not limited, Gaussian as IEC 60268-1
        /// itself), pink noise, multitone.
        #[arg(long)]
        crest: Option<f64>,
        /// Number of multitone tones.
        #[arg(long, default_value_t = 30)]
        tones: usize,
        /// Fade-in and fade-out (s).
        #[arg(long, default_value_t = 0.05)]
        fade: f64,
        /// Scale factors of an integer-PCM --input (V per count).
        #[arg(long)]
        scale: Option<f64>,
        /// The driver's world: `published` is the set as given; `real` adds LOG creep (lambda
        /// 0.05, an assumption) to a set without it, as `measure --virtual` does by default.
        #[arg(long, value_enum, default_value = "published")]
        world: World,
        /// Record through this measurement chain (a chain file: `delay_i` s, `hp_u`, `hp_i`
        /// Hz, `gain_i`, `dc_u` V, `dc_i` A, `hum`; as `coilscope calibrate` writes or a
        /// result's `chain`), as a real sound card would; default: ideal channels.
        #[arg(long, value_name = "FILE")]
        chain: Option<PathBuf>,
        /// Where the voltage channel is connected: `terminals` or `driver+shunt` (it then
        /// also records the drop across --sense-ohm).
        #[arg(long, default_value = "terminals", value_name = "WIRING")]
        sense_wiring: String,
        /// The sense resistor (ohm) of `--sense-wiring driver+shunt`.
        #[arg(long, value_name = "OHM")]
        sense_ohm: Option<f64>,
    },
    /// Small-signal (Thiele/Small) parameters from the impedance of a recording, or of a
    /// measured impedance file (--impedance Z.zma: REW, ARTA, LIMP, DATS, Klippel).
    Linear {
        /// Recording (WAV: voltage V, current A [, displacement m]).
        #[arg(required_unless_present = "impedance", conflicts_with = "impedance")]
        recording: Option<PathBuf>,
        /// Impedance file instead of a recording: .zma (frequency Hz, magnitude ohm, phase
        /// deg; `*` comment lines), .frd/.txt alike, or CSV with named columns.
        #[arg(long, value_name = "Z.zma")]
        impedance: Option<PathBuf>,
        /// Known moving mass (kg) for the absolute scale.
        #[arg(long)]
        mms: Option<f64>,
        /// Added mass (kg) of the added-mass method; needs --with-mass (records) or
        /// --with-mass-impedance (impedance files).
        #[arg(long)]
        added_mass: Option<f64>,
        /// Recording of the same driver with the added mass.
        #[arg(long, conflicts_with = "impedance")]
        with_mass: Option<PathBuf>,
        /// Impedance file of the same driver with the added mass.
        #[arg(long, value_name = "Z2.zma", requires = "impedance")]
        with_mass_impedance: Option<PathBuf>,
        /// Impedance files: the fitted band `LO,HI` (Hz); default: the band where the lumped
        /// model holds, found from the file (below the cone's break-up; the output says where).
        #[arg(long, value_name = "LO,HI", requires = "impedance")]
        band: Option<String>,
        /// Impedance files: the RMS voltage of the measurement, for the displacement it
        /// reached (fit.x_range); without it the level is unknown and x_range is [0, 0].
        #[arg(long, requires = "impedance")]
        volts: Option<f64>,
        /// Effects to fit besides LR-2: `auto` (the data decide: an effect is kept when it
        /// lowers the residual by 5 % or more), `none`, `creep` (LOG creep, lambda), `lr3` (a
        /// second para-inductance branch L3/R3), or `creep,lr3`. (Le(i) and Rms(v) vanish at
        /// small signal: `identify` fits them.)
        #[arg(long, default_value = "auto")]
        effects: String,
        #[command(flatten)]
        fit: FitArgs,
    },
    /// Large-signal parameters (Bl(x), Kms(x), Le(x), L2, R2, Rms, Re(t)) from a recording of
    /// voltage and current at high level: output-error fit of the nonlinear model.
    Identify {
        /// Recording (WAV: voltage V, current A [, displacement m]). Several recordings (a
        /// production line's batch): --out is a directory, each result is OUT/NAME.json, and
        /// the recordings are identified --jobs at a time.
        #[arg(required = true, num_args = 1..)]
        recording: Vec<PathBuf>,
        /// With several recordings: how many are identified at once (default: one per core,
        /// each on one core).
        #[arg(long)]
        jobs: Option<usize>,
        /// Moving mass (kg), the absolute scale. Without it, a displacement channel (3) gives it.
        #[arg(long)]
        mms: Option<f64>,
        /// Power-series order of Bl, Kms and Le (2 ..= 8); default: chosen on held-out data.
        #[arg(long)]
        order: Option<usize>,
        /// Effects to fit besides LR-2: `auto` (chosen on held-out data: kept when it lowers
        /// the held-out current error by 1 % or more), `none`, or a comma-separated list of
        /// `creep` (LOG creep), `lr3` (second para-inductance branch), `lei` (flux modulation
        /// Le(i): g(i) = 1 + g1 i + g2 i^2) and `rmsv` (velocity-dependent loss Rms + c2 v^2).
        #[arg(long, default_value = "auto")]
        effects: String,
        /// `full`: the output-error fit of the whole nonlinear model (any excitation, any
        /// level). `volterra`: the seed paper's Volterra method (3.2.2.1) on a record of
        /// `simulate --excitation readable` at small level: the 2nd and 3rd harmonic of each
        /// tone give the kernels H2, H3, and Bl, Kms, Le are fitted to second order with the
        /// linear part from --start; it fails at high level (the distortion feeds back), which
        /// the result's warnings say.
        #[arg(long, default_value = "full", value_parser = ["full", "volterra"])]
        method: String,
        /// `--method volterra`: the small-signal parameters (a result of `coilscope linear`,
        /// or a parameter set; only the values at rest are used).
        #[arg(long, value_name = "FILE")]
        start: Option<String>,
        #[command(flatten)]
        fit: FitArgs,
    },
    /// Calibrate the measurement chain (the current channel's delay and gain against the
    /// voltage channel, each channel's AC-coupling corner) from a record of a known resistor
    /// in the driver's place, or of a loopback. Writes a chain file for `--chain FILE`.
    Calibrate {
        /// Recording (WAV: voltage, current) of broadband noise from 0.3 Hz, 40 s or more.
        recording: PathBuf,
        /// The resistor (ohm, measured) in the driver's place.
        #[arg(long, required_unless_present = "loopback", conflicts_with = "loopback")]
        resistor: Option<f64>,
        /// Both channels record the same voltage (the gain is channel 2's over channel 1's).
        #[arg(long)]
        loopback: bool,
        /// Where the voltage channel is connected: `terminals` (across the resistor alone) or
        /// `driver+shunt` (across the resistor and the sense resistor in series); kept in the
        /// chain file, so that records made with it later are read the same way.
        #[arg(long, default_value = "terminals", value_name = "WIRING", conflicts_with = "loopback")]
        sense_wiring: String,
        /// The sense resistor (ohm) of `--sense-wiring driver+shunt`.
        #[arg(long, value_name = "OHM")]
        sense_ohm: Option<f64>,
        /// Scale factors of integer-PCM recordings (V, A per count).
        #[arg(long, num_args = 2..=3, value_names = ["V", "A"])]
        scale: Option<Vec<f64>>,
        /// Chain file (JSON).
        #[arg(long)]
        out: PathBuf,
    },
    /// Dynamic measurement: play noise or music, ramp the level up from quiet, identify the
    /// model online, protect the driver (excursion, temperature, stiffness), stop on
    /// convergence. Writes DIR/result.json and DIR/run.sqlite; live state on the terminal.
    Measure {
        /// Do not write DIR/report.html (the HTML report with PNG plots and CSV curves).
        #[arg(long)]
        no_report: bool,
        /// Virtual transducer: embedded driver name or parameter file (the default device).
        #[arg(long = "virtual", value_name = "DRIVER", conflicts_with_all = ["replay", "card"])]
        virtual_driver: Option<String>,
        /// The virtual driver's world: `real` adds LOG creep (lambda 0.05, an assumption) to a
        /// set without it, as real suspensions creep; `published` is the set as given.
        #[arg(long, value_enum, default_value = "real")]
        world: World,
        #[command(flatten)]
        card: CardArgs,
        /// Replay a recording (WAV: voltage, current, and optionally displacement) instead of
        /// driving a device; its displacement channel (a laser) gives the absolute scale when --mms
        /// is not given.
        #[arg(long, value_name = "WAV", conflicts_with = "card")]
        replay: Option<PathBuf>,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
        /// Moving mass (kg); for a virtual driver its own Mms is the default.
        #[arg(long)]
        mms: Option<f64>,
        /// Target peak excursion, a length with its unit (4.5mm, 0.0045m, 450um; a bare
        /// number is metres and must be plausible); default: the safe range where
        /// Kms(x)/Kms(0) reaches --kms-limit.
        #[arg(long, value_name = "LENGTH", value_parser = parse_length)]
        target_x: Option<f64>,
        /// Largest voice-coil temperature rise (K).
        #[arg(long, default_value_t = 50.0, value_name = "K")]
        max_dt: f64,
        /// Largest stiffness increase Kms(x)/Kms(0).
        #[arg(long, default_value_t = 2.0)]
        kms_limit: f64,
        /// Largest drive level (V rms).
        #[arg(long, default_value_t = 20.0)]
        max_volts: f64,
        /// Level of the small-signal stage (V rms).
        #[arg(long, default_value_t = 0.2)]
        start_volts: f64,
        /// Music or any audio file as excitation (its sample rate is used), instead of IEC noise.
        #[arg(long, value_name = "FILE")]
        music: Option<PathBuf>,
        /// Long-term test: run this many seconds (simulated or real), whatever the convergence.
        #[arg(long, value_name = "S")]
        duration: Option<f64>,
        /// Long-term test at a fixed level (V rms); the high-pass keeps x in range.
        #[arg(long)]
        volts: Option<f64>,
        /// Long-term test: from this many seconds on, hold the lower --cool-volts (a cooling
        /// phase: heating and cooling separate the coil's and the magnet's thermal paths).
        #[arg(long, value_name = "S", requires = "cool_volts")]
        cool_after: Option<f64>,
        /// The cooling phase's level (V rms), below --volts.
        #[arg(long, value_name = "V", requires = "cool_after")]
        cool_volts: Option<f64>,
        /// Stop without convergence after this many seconds.
        #[arg(long, default_value_t = 60.0)]
        max_seconds: f64,
        /// Power-series order of Bl, Kms, Le.
        #[arg(long, default_value_t = 6)]
        order: usize,
        /// Sensor noise of the virtual device: voltage (V rms) and current (A rms).
        #[arg(long, num_args = 2, value_names = ["V", "A"], default_values_t = [1e-4, 1e-4])]
        noise: Vec<f64>,
        /// Sample rate of the virtual device or the sound card (Hz).
        #[arg(long, default_value_t = 48000)]
        rate: u32,
        /// Seed of the excitation and sensor noise.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Crest factor of the IEC 60268-1 noise (peak / RMS; default 2, as power tests use;
        /// `inf`: not limited, Gaussian, as the standard itself). Its band levels stay Table II's.
        #[arg(long)]
        crest: Option<f64>,
        #[command(flatten)]
        serve: ServeArgs,
    },
    /// Write a result for another tool: the thermal model as a speakersafetyd configuration,
    /// the power series as a KLIPPEL-style table (CSV, millimetres), or the small-signal
    /// impedance as .zma / .frd.
    #[command(group(clap::ArgGroup::new("format").required(true).args(["speakersafetyd", "power_series", "zma", "frd"])))]
    Export {
        /// Result file (coilscope.result/1), parameter file or embedded driver name.
        result: String,
        /// speakersafetyd configuration (INI): tr_coil, tr_magnet, tau_coil, tau_magnet from
        /// the thermal parameters, t_limit and the machine's keys from the options below.
        #[arg(long)]
        speakersafetyd: bool,
        /// The power series of Bl, Kms, Le (and L2, R2) in N/A/mm^n, N/mm/mm^n, mH/mm^n (CSV).
        #[arg(long)]
        power_series: bool,
        /// The small-signal impedance at rest, 5 Hz .. 20 kHz, as .zma (REW, ARTA, LIMP, ...).
        #[arg(long)]
        zma: bool,
        /// The same as .frd (frequency, ohm, degrees), as crossover tools read impedance.
        #[arg(long)]
        frd: bool,
        /// The file to write.
        #[arg(long)]
        out: PathBuf,
        /// speakersafetyd: the speaker's section name (`[Speaker/NAME]`).
        #[arg(long, default_value = "Speaker")]
        name: String,
        /// speakersafetyd: the coil's absolute temperature limit (degrees C).
        #[arg(long, default_value_t = 120.0)]
        t_limit: f64,
        /// speakersafetyd: the ambient temperature the daemon assumes (degrees C).
        #[arg(long, default_value_t = 35.0)]
        t_ambient: f64,
        /// speakersafetyd: channels of the machine's I/V-sense capture.
        #[arg(long, default_value_t = 2)]
        channels: usize,
        /// speakersafetyd: the capture channel of this speaker's current sense.
        #[arg(long, default_value_t = 0)]
        is_chan: usize,
        /// speakersafetyd: the capture channel of this speaker's voltage sense.
        #[arg(long, default_value_t = 1)]
        vs_chan: usize,
        /// speakersafetyd: the current sense's full scale (A).
        #[arg(long, default_value_t = 3.75)]
        is_scale: f64,
        /// speakersafetyd: the voltage sense's full scale (V).
        #[arg(long, default_value_t = 14.0)]
        vs_scale: f64,
        /// speakersafetyd: the speaker group (speakers of a group share a gain).
        #[arg(long, default_value_t = 0)]
        group: usize,
    },
    /// List the sound devices (inputs and outputs) for measure --card (build with --features soundcard).
    Devices,
    /// List the runs of a measurement database (DIR/run.sqlite), including interrupted ones.
    Runs {
        /// The database (or the measurement directory holding run.sqlite).
        database: PathBuf,
    },
    /// Static and quasi-static point-by-point measurement (seed paper 3.2.1; IEC 62458 10.2,
    /// 10.3) on the virtual driver: a DC offset per working point, the static displacement
    /// (laser) and the small-signal impedance at each; power series fitted to the points.
    Quasistatic {
        /// Virtual driver: embedded name or parameter file (not with --card).
        #[arg(required_unless_present = "card", conflicts_with = "card")]
        driver: Option<String>,
        /// Result file (JSON: the fitted set, and every working point under `quasi_static`).
        #[arg(long)]
        out: PathBuf,
        /// Working points (odd).
        #[arg(long, default_value_t = 9)]
        points: usize,
        /// The outermost points as a share of the range on each side.
        #[arg(long, default_value_t = 0.8)]
        reach: f64,
        /// Seconds each offset is held before the small signal (a creeping suspension needs
        /// several: its slowest element relaxes in about 3 s).
        #[arg(long, default_value_t = 5.0)]
        hold: f64,
        /// Power-series order of the fitted curves.
        #[arg(long, default_value_t = 4)]
        order: usize,
        /// The virtual driver's world (`real` adds LOG creep 0.05).
        #[arg(long, value_enum, default_value = "published")]
        world: World,
        /// How the coil is held off rest: `current` (a DC current: it heats the coil),
        /// `mass` (an added mass under gravity) or `pressure` (on the diaphragm; needs the
        /// set's Sd): no current, so no heating (IEC 62458 10.2/10.3).
        #[arg(long, default_value = "current", value_parser = ["current", "mass", "pressure"])]
        offset: String,
        /// With --card: the driver's moving mass (kg), the small-signal fits' absolute scale.
        #[arg(long, requires = "card")]
        mms: Option<f64>,
        /// With --card: how far the working points may go on each side, a length with its
        /// unit (the driver's Xmax from its data sheet, or less: 4mm).
        #[arg(long, value_name = "LENGTH", value_parser = parse_length, requires = "card")]
        xmax: Option<f64>,
        /// With --card and --offset pressure: the diaphragm's area Sd (m^2).
        #[arg(long, value_name = "M2", requires = "card")]
        sd: Option<f64>,
        /// With --card: the small signal's level at each point (V rms at the terminals).
        #[arg(long, value_name = "V", default_value_t = 0.1)]
        ac_volts: f64,
        /// With --card: the sample rate (Hz).
        #[arg(long, default_value_t = 48000)]
        rate: u32,
        /// A real driver through a sound card (feature soundcard): the points are held by an
        /// added mass or a pressure (a card's output cannot hold a DC current), the terminal
        /// asks you to apply each one and to read the static displacement on a gauge.
        #[command(flatten)]
        card: CardArgs,
    },
    /// Pre-inverse compensation (seed paper 3.2.2.2.3, Fig. 6): the drive that makes the
    /// driver's displacement, and so its sound pressure, follow its linear model's for an
    /// input signal. The inverse of the model (normal form, Eq. 9) used as a controller.
    Compensate {
        /// Embedded driver name, parameter file or result file (JSON).
        params: String,
        /// The input signal (WAV, channel 1, volts): what the linear driver should play.
        #[arg(long)]
        input: PathBuf,
        /// The compensated drive (mono 32-bit float WAV, volts): play this instead.
        #[arg(long)]
        out: PathBuf,
        /// Clip the drive at this magnitude (V): the amplifier's limit.
        #[arg(long)]
        max_volts: Option<f64>,
        /// Floor of the force factor Bl(x) + Le'(x) i the inverse divides by, relative to
        /// Bl(0) (where Bl(x) falls at the ends of the gap, the current it asks for runs away).
        #[arg(long, default_value_t = 0.2)]
        min_force_factor: f64,
        /// Scale factor of an integer-PCM --input (V per count).
        #[arg(long)]
        scale: Option<f64>,
    },
    /// Predicted distortion of a parameter set (or result) by simulation to the steady state:
    /// HD2/HD3/THD of a sine, each nonlinearity's share and the Volterra prediction; the IMD of
    /// a two-tone (--freq2); a multitone spectrum (--multitone); sweeps (--sweep, --levels).
    Distortion {
        /// Embedded driver name, parameter file or result file.
        params: String,
        /// Sine frequency (Hz); the low tone f1 of a two-tone.
        #[arg(long)]
        freq: Option<f64>,
        /// High tone f2 of a two-tone (Hz): intermodulation d2, d3 (IEC 60268-5).
        #[arg(long)]
        freq2: Option<f64>,
        /// Amplitude of f2 relative to f1 in a two-tone.
        #[arg(long, default_value_t = 1.0)]
        ratio: f64,
        /// Level: RMS voltage of the whole input signal (V); not needed with --levels.
        #[arg(long, required_unless_present = "levels")]
        volts: Option<f64>,
        /// The signal the distortion is measured in.
        #[arg(long, value_enum, default_value = "pressure")]
        output: OutputKind,
        /// A multitone of --tones tones over --band instead of a sine.
        #[arg(long)]
        multitone: bool,
        /// Multitone band (Hz).
        #[arg(long, num_args = 2, value_names = ["F_LO", "F_HI"])]
        band: Option<Vec<f64>>,
        /// Number of multitone tones.
        #[arg(long, default_value_t = 30)]
        tones: usize,
        /// Frequency sweep: HD2/HD3/THD and each nonlinearity's share from F_LO to F_HI (3 per octave).
        #[arg(long, num_args = 2, value_names = ["F_LO", "F_HI"])]
        sweep: Option<Vec<f64>>,
        /// Level sweep at --freq (V RMS): full model against the Volterra series.
        #[arg(long, num_args = 1.., value_delimiter = ',')]
        levels: Option<Vec<f64>>,
        /// Voice-coil temperature rise at which Re is taken (K).
        #[arg(long, default_value_t = 0.0)]
        temp_rise: f64,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
        /// Seed of the multitone's random phases.
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
    /// Limits and diagnosis of a parameter set or result: XBl, XC, XL (thresholds changeable),
    /// Xsym and the Bl rest-position shift, Ak, polarity check, thermal power handling.
    Diagnose {
        /// Embedded driver name, parameter file or result file.
        params: String,
        #[command(flatten)]
        limits: LimitArgs,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Write a self-contained HTML report of a result (or parameter set), with PNG plots and
    /// CSV curves in `<stem>_files/`.
    Report {
        /// Result file (coilscope.result/1), parameter file or embedded driver name.
        result: String,
        /// The HTML file to write.
        #[arg(long)]
        out: PathBuf,
        /// Run database with the measurement's time series (default: run.sqlite beside the result).
        #[arg(long)]
        db: Option<PathBuf>,
        /// Level of the distortion analysis (V RMS); default: 70 % of the reach.
        #[arg(long)]
        volts: Option<f64>,
        /// Another result of the same driver to draw over this one (dashed), with a table of
        /// the differences: a quasi-static result against a dynamic one shows the static
        /// stiffness and the rest drift of a creeping suspension (seed paper 3.2.1).
        #[arg(long, value_name = "RESULT")]
        compare: Option<String>,
        #[command(flatten)]
        limits: LimitArgs,
    },
    /// List the embedded real drivers.
    Drivers,
    /// Validate a parameter set and print its small-signal figures.
    Check {
        /// Embedded driver name, drawn driver (population:SEED, population:CLASS:SEED) or
        /// parameter file.
        params: String,
        /// Print the parameter set itself (the file contract's JSON), e.g. to keep a drawn
        /// driver as a file.
        #[arg(long)]
        json: bool,
    },
}

/// A length on the command line, in metres: `4mm`, `4 mm`, `0.004m`, `400um` (or `µm`); a
/// bare number is metres (SI, like every other input) and is refused when no transducer
/// excursion could be meant (below 10 µm or above 0.1 m), with the likely intent named.
fn parse_length(s: &str) -> Result<f64, String> {
    let t = s.trim();
    let split = t.find(|c: char| c.is_alphabetic() || c == 'µ').unwrap_or(t.len());
    let (num, unit) = (t[..split].trim(), t[split..].trim());
    let v: f64 =
        num.parse().map_err(|_| format!("'{s}' is not a length: write a number and a unit, e.g. 4mm or 0.004m"))?;
    if !v.is_finite() {
        return Err(format!("'{s}' is not a finite length"));
    }
    let m = match unit {
        "m" => v,
        "mm" => v * 1e-3,
        "um" | "µm" => v * 1e-6,
        "" => {
            if v != 0.0 && !(1e-5..=0.1).contains(&v.abs()) {
                return Err(format!(
                    "{v} m = {} mm is not a plausible excursion: did you mean {v}mm? (a bare number is metres)",
                    v * 1e3
                ));
            }
            v
        }
        other => return Err(format!("unknown length unit '{other}' in '{s}': use m, mm or um")),
    };
    Ok(m)
}

/// Exit code of an error (bad input, or the work could not be done).
const EXIT_ERROR: u8 = 2;
/// Exit code of a result that was written but cannot be trusted.
const EXIT_UNTRUSTED: u8 = 3;
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
    let cli = Cli::parse();
    let result: Result<(), Failure> = match cli.command {
        Command::Simulate { driver, excitation, volts, seconds, out, laser, snr_db, seed, rate, input, freq, band, crest, tones, fade, scale, world, chain, sense_wiring, sense_ohm } => parse_wiring(&sense_wiring, sense_ohm)
            .and_then(|wiring| cmd_simulate(SimulateArgs { driver, excitation, volts, seconds, out, laser, snr_db, seed, rate, input, freq, band, crest, tones, fade, scale, world, chain, wiring }).map_err(Failure::from)),
        Command::Linear { recording, impedance, mms, added_mass, with_mass, with_mass_impedance, band, volts, effects, fit } => {
            cmd_linear(LinearArgs { recording, impedance, mms, added_mass, with_mass, with_mass_impedance, band, volts, effects, fit })
        }
        Command::Identify { recording, jobs, method, start, mms, order, effects, fit } => parse_chain(&fit.chain).and_then(|chain| {
            if recording.len() > 1 {
                return cmd_identify_batch(&recording, jobs, &fit.out);
            }
            let recording = &recording[0];
            if jobs.is_some() {
                Err(Failure::from("--jobs applies to several recordings (a batch); one recording uses every core by itself"))
            } else if method == "volterra" {
                cmd_identify_volterra(recording, start.as_deref(), mms, order, &effects, &chain, fit_wiring(&fit, &chain)?, fit.sd, fit.scale.as_deref(), &fit.out)
            } else if start.is_some() {
                Err(Failure::from("--start is the Volterra method's small-signal set (--method volterra); the full identification finds its own start"))
            } else {
                cmd_identify(recording, mms, order, &effects, &chain, fit_wiring(&fit, &chain)?, fit.sd, fit.scale.as_deref(), &fit.out)
            }
        }),
        Command::Calibrate { recording, resistor, loopback, scale, out, sense_wiring, sense_ohm } => parse_wiring(&sense_wiring, sense_ohm).and_then(|w| cmd_calibrate(&recording, resistor, loopback, w, scale.as_deref(), &out)),
        Command::Measure { no_report, virtual_driver, world, card, replay, out, mms, target_x, max_dt, kms_limit, max_volts, start_volts, music, duration, volts, cool_after, cool_volts, max_seconds, order, noise, rate, seed, crest, serve } => {
            cmd_measure(MeasureArgs {
                no_report,
                virtual_driver,
                world,
                card,
                replay,
                out,
                mms,
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
        Command::Export { result, speakersafetyd, power_series, zma, frd, out, name, t_limit, t_ambient, channels, is_chan, vs_chan, is_scale, vs_scale, group } => {
            let o = coilscope_io::export::SafetydOptions { name, t_limit, t_ambient, channels, is_chan, vs_chan, is_scale, vs_scale, group, ..Default::default() };
            cmd_export(&result, speakersafetyd, power_series, zma, frd, &out, &o).map_err(Failure::from)
        }
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
    }
}

struct SimulateArgs {
    world: World,
    driver: String,
    excitation: ExcitationKind,
    volts: Option<f64>,
    seconds: f64,
    out: PathBuf,
    laser: bool,
    snr_db: Option<f64>,
    seed: u64,
    rate: u32,
    input: Option<PathBuf>,
    freq: f64,
    band: Option<Vec<f64>>,
    crest: Option<f64>,
    tones: usize,
    fade: f64,
    scale: Option<f64>,
    chain: Option<PathBuf>,
    wiring: SenseWiring,
}

/// Where the summary of a recording goes: `NAME.info.json` beside `NAME.wav`.
fn info_path(out: &Path) -> PathBuf {
    let stem = out.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "recording".into());
    out.with_file_name(format!("{stem}.info.json"))
}

fn cmd_simulate(a: SimulateArgs) -> Result<(), String> {
    let params = a.world.apply(load_parameters(&a.driver).map_err(|e| e.to_string())?);
    if let Some(db) = a.snr_db {
        if !(db.is_finite() && db > 0.0) {
            return Err(format!("--snr-db {db}: give a positive number of dB (e.g. 70)"));
        }
    }
    let (fs, u, what) = match &a.input {
        Some(path) => {
            let (fs, mut u) = read_voltage(path, a.scale.map(|s| vec![s]).as_deref()).map_err(|e| e.to_string())?;
            if let Some(v) = a.volts {
                let r = coilscope_core::simulate::rms(&u);
                if r == 0.0 {
                    return Err(format!(
                        "{}: the voltage channel is silent; cannot scale it to {v} V RMS",
                        path.display()
                    ));
                }
                u.iter_mut().for_each(|x| *x *= v / r);
            }
            (fs as f64, u, json!({"input": path.display().to_string()}))
        }
        None => {
            let volts = a.volts.ok_or("--volts RMS is required with a generated excitation (e.g. --volts 2)")?;
            let band = match &a.band {
                Some(b) => (b[0], b[1]),
                None => (10.0, (8000.0f64).min(0.45 * a.rate as f64)),
            };
            let exc = match a.excitation {
                ExcitationKind::Noise => iec_noise(a.crest),
                ExcitationKind::Pink => Excitation::Pink { f_lo: band.0, f_hi: band.1, crest: a.crest },
                ExcitationKind::Sine => Excitation::Sine { freq: a.freq },
                ExcitationKind::Multitone => {
                    Excitation::Multitone { f_lo: band.0, f_hi: band.1, count: a.tones, crest: a.crest }
                }
                ExcitationKind::Sweep => Excitation::Sweep { f_lo: band.0, f_hi: band.1 },
                ExcitationKind::Readable => {
                    Excitation::Readable { f_lo: band.0, f_hi: band.1, count: a.tones, crest: a.crest }
                }
            };
            let spec = SignalSpec { fs: a.rate as f64, seconds: a.seconds, rms: volts, fade: a.fade, seed: a.seed };
            let u = generate(&exc, &spec)?;
            let cf = crest_factor(&u);
            (
                a.rate as f64,
                u,
                json!({"excitation": format!("{exc:?}"), "rms": volts, "seconds": a.seconds, "crest_factor": cf, "seed": a.seed}),
            )
        }
    };
    let trace = simulate(&params, fs, &u, &SimOptions::default()).map_err(|e| e.to_string())?;
    let s = trace.summary();
    // The channels: the wiring, then the chain (the sensor noise after both).
    let mut chain = a
        .chain
        .as_deref()
        .map(load_chain)
        .transpose()?
        .map(|c| coilscope_core::chain::Chain { source: Some("simulated".into()), ..c });
    let u_channel = a.wiring.channel_voltage(&trace.u, &trace.i);
    let (u_rec, i_rec) = match &chain {
        Some(c) => c.apply(&u_channel, &trace.i, fs),
        None => (u_channel, trace.i.clone()),
    };
    let mut rec = Recording { fs: fs as u32, u: u_rec, i: i_rec, x: a.laser.then(|| trace.x.clone()) };
    mark_wiring(&mut chain, a.wiring);
    if let Some(db) = a.snr_db {
        add_sensor_noise(&mut rec.u, db, a.seed, "sensor-noise/voltage");
        add_sensor_noise(&mut rec.i, db, a.seed, "sensor-noise/current");
        if let Some(x) = &mut rec.x {
            add_sensor_noise(x, db, a.seed, "sensor-noise/displacement");
        }
    }
    write_recording(&a.out, &rec).map_err(|e| e.to_string())?;
    let info = json!({
        "x_min": s.x_min, "x_max": s.x_max, "x_p01": s.x_p01, "x_p99": s.x_p99,
        "u_rms": s.u_rms, "i_rms": s.i_rms, "dT_end": s.dt_end, "dT_max": s.dt_max,
        "dTm_end": s.dtm_end, "p_mean": s.p_mean,
        "driver": params.name.clone().unwrap_or_else(|| a.driver.clone()),
        "fs": fs, "samples": u.len(), "substeps": trace.substeps, "scheme": trace.scheme.name(), "snr_db": a.snr_db, "laser": a.laser,
        "signal": what,
        "chain": chain,
    });
    let info_file = info_path(&a.out);
    write_json(&info_file, &info).map_err(|e| e.to_string())?;

    let name = params.name.as_deref().unwrap_or(&a.driver);
    println!(
        "coilscope simulate: {name}, {:.2} s at {} Hz ({} scheme, {} step{} per sample)",
        u.len() as f64 / fs,
        fs,
        trace.scheme.name(),
        trace.substeps,
        if trace.substeps == 1 { "" } else { "s" }
    );
    let range = params
        .x_range
        .map(|[lo, hi]| format!(" ({:.0} % / {:.0} % of x_range)", 100.0 * s.x_min / lo, 100.0 * s.x_max / hi))
        .unwrap_or_default();
    println!("  peak excursion   {:+.3} mm .. {:+.3} mm{range}", s.x_min * 1e3, s.x_max * 1e3);
    println!("  voltage, current {:.3} V RMS, {:.3} A RMS", s.u_rms, s.i_rms);
    println!("  electrical power {:.3} W (mean u i)", s.p_mean);
    println!("  voice coil       +{:.3} K at the end (max +{:.3} K), magnet +{:.4} K", s.dt_end, s.dt_max, s.dtm_end);
    if trace.range_excess > 0.0 {
        println!("  warning: x exceeded x_range by {:.3} mm (parameters extrapolated)", trace.range_excess * 1e3);
    }
    println!("  wrote {} and {}", a.out.display(), info_file.display());
    Ok(())
}

/// `linear`'s arguments.
struct LinearArgs {
    recording: Option<PathBuf>,
    impedance: Option<PathBuf>,
    mms: Option<f64>,
    added_mass: Option<f64>,
    with_mass: Option<PathBuf>,
    with_mass_impedance: Option<PathBuf>,
    band: Option<String>,
    volts: Option<f64>,
    effects: String,
    fit: FitArgs,
}

/// `--band LO,HI` (Hz).
fn parse_band(text: &str) -> Result<[f64; 2], Failure> {
    let v: Vec<f64> = text
        .split([',', ':'])
        .map(|t| t.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| format!("--band {text:?}: give LO,HI in Hz, e.g. 10,2000"))?;
    match v[..] {
        [lo, hi] if lo >= 0.0 && hi > lo && hi.is_finite() => Ok([lo, hi]),
        _ => Err(Failure::from(format!("--band {text:?}: give LO,HI in Hz with 0 <= LO < HI, e.g. 10,2000"))),
    }
}

fn cmd_linear(a: LinearArgs) -> Result<(), Failure> {
    use coilscope_ident::linear::ScaleMethod;
    use coilscope_workflow::linear::{linear, LinearInput, LinearRequest, Scale};
    let (scale, out) = (a.fit.scale.as_deref(), a.fit.out.as_path());
    let chain = parse_chain(&a.fit.chain)?;
    let wiring = fit_wiring(&a.fit, &chain)?;
    let effects = parse_effects(&a.effects)?;
    let band = a.band.as_deref().map(parse_band).transpose()?;
    let (path, is_curve) = match (&a.recording, &a.impedance) {
        (Some(p), None) => (p.clone(), false),
        (None, Some(p)) => (p.clone(), true),
        _ => return Err("give a recording or --impedance FILE (one of them)".into()),
    };
    let origin = path.display().to_string();
    if is_curve && matches!(chain, ChainMode::Calibrated(_)) {
        return Err(Failure::from(format!("{origin}: an impedance curve has no measurement chain to invert (its tool calibrated it); --chain FILE applies to records")));
    }
    // A curve measured across driver and shunt: the shunt is a plain series resistance.
    let read_input = |p: &Path| -> Result<LinearInput, Failure> {
        if is_curve {
            let mut c = coilscope_io::impedance::read_impedance(p).map_err(|e| e.to_string())?;
            if c.magnitude_only && wiring.series_ohm() != 0.0 {
                // |Z| - R is not |Z - R|: the shunt cannot be taken out of a magnitude alone.
                return Err(Failure::from(format!(
                    "{}: the file has no phase, so the shunt's {} ohm cannot be taken out of it (|Z| - R is not |Z - R|): export the phase too, or measure with the voltage across the driver's terminals",
                    p.display(),
                    wiring.series_ohm()
                )));
            }
            c.z.iter_mut().for_each(|z| *z -= wiring.series_ohm());
            Ok(LinearInput::Curve(c))
        } else {
            Ok(LinearInput::Record(read_recording(p, scale).map_err(|e| e.to_string())?))
        }
    };
    let input = read_input(&path)?;
    let has_x = matches!(&input, LinearInput::Record(r) if r.x.is_some());
    let with_mass = if is_curve { a.with_mass_impedance.as_ref() } else { a.with_mass.as_ref() };
    let with_name = if is_curve { "--with-mass-impedance Z2.zma" } else { "--with-mass REC2.wav" };
    // Refuse a missing or doubled scale before spending time on the fit.
    let scale = match (a.mms, a.added_mass, with_mass, has_x) {
        (Some(m), None, None, _) => Scale::Mms(m),
        (None, Some(m), Some(p2), _) => {
            Scale::AddedMass { mass: m, with: Box::new(read_input(p2)?), origin: p2.display().to_string() }
        }
        (None, None, None, true) => Scale::Displacement,
        (None, Some(_), None, _) | (None, None, Some(_), _) => {
            return Err(format!("--added-mass KG and {with_name} go together").into())
        }
        (Some(_), _, _, _) => return Err(format!("give one scale: --mms, or --added-mass with {with_name}").into()),
        (None, None, None, false) => {
            let x = if is_curve { "" } else { ", or record a displacement channel (3)" };
            return Err(Failure::from(format!(
                "{origin}: no absolute scale: give --mms KG, or --added-mass KG {with_name}{x}"
            )));
        }
    };
    let live = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let progress = |s: &coilscope_ident::lm::LmState| {
        if live && (s.iteration.is_multiple_of(5) || s.converged) {
            eprint!("\r  fitting impedance: iteration {:3}, residual {:.3e}   ", s.iteration, (2.0 * s.cost).sqrt());
        }
    };
    let req = LinearRequest { origin: origin.clone(), effects, chain, wiring, sd: a.fit.sd, band, volts: a.volts };
    let done = linear(input.clone(), scale, &req, progress)?;
    if live {
        eprintln!();
    }
    for d in &done.detected {
        eprintln!("chain: estimated, as the record shows one: {d}");
    }
    print_warnings(&done.warnings);
    let (fit, params, result, x_range) = (&done.fit, &done.params, &done.result, done.x_range);
    write_json(out, result).map_err(|e| e.to_string())?;
    let csv = out.with_extension("csv");
    let mut wrote = vec![out.display().to_string()];
    if !is_curve {
        let zma = out.with_extension("zma");
        let (f, z) = fit.h1.coherent();
        let comments = vec![
            format!("coilscope linear: H1 impedance of {origin} (coherent bins)"),
            "Data: Impedance (ohms), Phase (degrees)".to_string(),
        ];
        coilscope_io::impedance::write_zma(
            &zma,
            &coilscope_io::impedance::ImpedanceCurve { f, z, comments, magnitude_only: false },
        )
        .map_err(|e| e.to_string())?;
        wrote.push(zma.display().to_string());
    }
    coilscope_io::atomic_write(&csv, coilscope_ident::linear::impedance_csv(&fit.h1, fit).as_bytes())
        .map_err(|e| e.to_string())?;
    wrote.push(csv.display().to_string());
    let ts = thiele_small(params);
    let u = &result.uncertainty;
    let pm = |k: &str, scale: f64| u.value(k).map(|v| format!("+- {:.2e}", v * scale)).unwrap_or_default();
    match &input {
        LinearInput::Record(r) => {
            println!("coilscope linear: {} ({:.2} s at {} Hz)", path.display(), r.u.len() as f64 / r.fs as f64, r.fs);
            println!(
                "  fit {:.1} .. {:.0} Hz, {} bins, residual {:.3e} (current, relative RMS), {} iterations",
                fit.band[0], fit.band[1], fit.bins, fit.residual_rel, fit.iterations
            );
        }
        LinearInput::Curve(c) => {
            println!(
                "coilscope linear: {} (impedance file, {} points, {:.1} .. {:.0} Hz)",
                path.display(),
                c.f.len(),
                c.f[0],
                c.f[c.f.len() - 1]
            );
            println!(
                "  fit {:.1} .. {:.0} Hz, {} points, residual {:.3e} (impedance, relative RMS), {} iterations",
                fit.band[0], fit.band[1], fit.bins, fit.residual_rel, fit.iterations
            );
            if let Some(note) = &result.fit.band_note {
                println!("  band: {note}");
            }
            if let Some(note) = &result.fit.phase_note {
                println!("  phase: {note}");
            }
        }
    }
    let scale_text = match &done.method {
        ScaleMethod::Mms => "Mms given".to_string(),
        ScaleMethod::AddedMass { added, fs_with, .. } => {
            format!("added mass {:.3} g, fs with mass {:.3} Hz", added * 1e3, fs_with)
        }
        ScaleMethod::Displacement => "displacement channel".to_string(),
    };
    println!("  scale: {scale_text}");
    if let (Some(c), LinearInput::Record(r)) = (&fit.chain, &input) {
        println!("  chain: {}", c.to_chain().describe_fitted(r.fs as f64));
    }
    println!(
        "  model: {} (tried: {})",
        fit.effects.model_name(),
        fit.tried.iter().map(|(m, r)| format!("{m} {r:.2e}")).collect::<Vec<_>>().join(", ")
    );
    print_values(params, u, &[]);
    println!("  {:<6} {:>12} {:<5} {}", "fs", format!("{:.3}", ts.fs), "Hz", pm("fs", 1.0));
    println!(
        "  {:<6} {:>12}      (at fs, with creep's loss: Rms at fs {:.4} kg/s)",
        "Qms",
        format!("{:.4}", ts.qms),
        ts.rms_fs
    );
    println!("  {:<6} {:>12}", "Qes", format!("{:.4}", ts.qes));
    println!("  {:<6} {:>12}", "Qts", format!("{:.4}", ts.qts));
    if let Some(v) = ts.vas {
        println!("  {:<6} {:>12} {:<5}", "Vas", format!("{:.3}", v * 1e3), "l");
    }
    if !is_curve || a.volts.is_some() {
        println!("  x reached {:+.3} .. {:+.3} mm", x_range[0] * 1e3, x_range[1] * 1e3);
    } else {
        println!("  x reached: unknown (give --volts, the measurement's RMS voltage)");
    }
    println!("  wrote {}", wrote.join(", "));
    untrusted_if_warned(&done.warnings, out)
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

fn resonance(p: &Parameters) -> f64 {
    thiele_small(p).fs
}

fn print_params(p: &Parameters) {
    let ts = thiele_small(p);
    println!("{}", p.name.as_deref().unwrap_or("(unnamed)"));
    println!(
        "  Re {:.3} ohm, Le(0) {:.4} mH, Bl(0) {:.3} T m, Kms(0) {:.1} N/m, Mms {:.3} g, Rms {:.3} kg/s",
        p.re,
        p.le.c[0] * 1e3,
        p.bl.c[0],
        p.kms.c[0],
        p.mms * 1e3,
        p.rms
    );
    if let Some((l2, r2)) = &p.l2r2 {
        println!("  L2 {:.4} mH, R2 {:.3} ohm", l2.c[0] * 1e3, r2.c[0]);
    }
    if let Some((l3, r3)) = p.l3r3 {
        println!("  L3 {:.4} mH, R3 {:.3} ohm", l3 * 1e3, r3);
    }
    if let Some(c) = &p.creep {
        println!("  creep lambda {:.4} (LOG, reference {:.2} Hz)", c.lambda, p.creep_f_ref().unwrap_or(0.0));
    }
    println!(
        "  fs {:.2} Hz, Qms {:.3}, Qes {:.3}, Qts {:.3}, Rms at fs {:.3} kg/s (with creep's loss)",
        ts.fs, ts.qms, ts.qes, ts.qts, ts.rms_fs
    );
    match p.x_range {
        Some([lo, hi]) => println!("  x_range {:.2} .. {:.2} mm", lo * 1e3, hi * 1e3),
        None => println!("  x_range not given"),
    }
    println!("  electrical time constant Le/(Re+R2) >= {:.2} us", p.min_electrical_time_constant() * 1e6);
}

fn cmd_drivers() -> Result<(), String> {
    for name in embedded_driver_names() {
        let p = embedded_driver(name).ok_or("embedded driver missing")?;
        let [lo, hi] = p.x_range.unwrap_or([0.0, 0.0]);
        println!(
            "{name:<15} {:<40} fs {:6.2} Hz  x_range {:+.1} .. {:+.1} mm",
            p.name.as_deref().unwrap_or(""),
            resonance(&p),
            lo * 1e3,
            hi * 1e3
        );
    }
    Ok(())
}

/// The post-inverse (equation-error) estimate of a record with a displacement channel
/// ([`coilscope_workflow::identify::post_inverse_of`]).
fn post_inverse_of(
    u: &[f64],
    i: &[f64],
    x: &[f64],
    fs: f64,
    order: usize,
    origin: &str,
) -> Result<Parameters, Failure> {
    Ok(coilscope_workflow::identify::post_inverse_of(u, i, x, fs, order, origin)?)
}

fn cmd_calibrate(
    path: &Path,
    resistor: Option<f64>,
    loopback: bool,
    wiring: SenseWiring,
    scale: Option<&[f64]>,
    out: &Path,
) -> Result<(), Failure> {
    let origin = path.display().to_string();
    let r = match (resistor, loopback) {
        (Some(r), false) if r.is_finite() && r > 0.0 && r < 1e6 => r,
        (Some(r), false) => {
            return Err(Failure::from(format!("--resistor {r}: give the resistor's measured value in ohm (> 0)")))
        }
        _ => 1.0,
    };
    let rec = read_recording(path, scale).map_err(|e| e.to_string())?;
    let fs = rec.fs as f64;
    // Across resistor and shunt, the voltage channel sees both.
    let cal = coilscope_ident::calibrate::calibrate(&rec.u, &rec.i, fs, r + wiring.series_ohm(), &origin)?;
    let mut chain = cal.chain.clone();
    if !loopback {
        wiring.mark(&mut chain);
    }
    let info = serde_json::json!({
        "format": "coilscope.chain/1",
        "record": origin,
        "fs_hz": fs,
        "load": if loopback { "loopback".to_string() } else { format!("resistor {r} ohm") },
        "band_hz": cal.band,
        "bins": cal.bins,
        "residual_in_noise": cal.residual_in_noise,
        "residual_rel": cal.residual_rel,
    });
    for (k, v) in info.as_object().expect("an object") {
        chain.other.insert(k.clone(), v.clone());
    }
    write_json(out, &chain).map_err(|e| e.to_string())?;
    let sd = |k: &str| chain.sd.get(k).copied().unwrap_or(f64::NAN);
    println!(
        "coilscope calibrate: {} ({:.1} s at {} Hz, {})",
        origin,
        rec.u.len() as f64 / fs,
        rec.fs,
        if loopback { "loopback".to_string() } else { format!("resistor {r} ohm") }
    );
    println!(
        "  fit {:.2} .. {:.0} Hz, {} bins, residual {:.2}x the noise ({:.2e} relative)",
        cal.band[0], cal.band[1], cal.bins, cal.residual_in_noise, cal.residual_rel
    );
    println!(
        "  current channel {:+.4} +- {:.4} samples late ({:+.3} us), gain {:.5} +- {:.1e} against the voltage's",
        chain.delay_i * fs,
        sd("delay_i") * fs,
        chain.delay_i * 1e6,
        chain.gain_i.unwrap_or(1.0),
        sd("gain_i")
    );
    if chain.fitted.iter().any(|k| k == "hp_u") {
        println!(
            "  AC coupling: voltage {:.3} +- {:.3} Hz, current {:.3} +- {:.3} Hz",
            chain.hp_u,
            sd("hp_u"),
            chain.hp_i,
            sd("hp_i")
        );
    } else if let Some(n) = chain.other.get("note").and_then(|v| v.as_str()) {
        println!("  AC coupling: {n}");
    }
    println!("  wrote {} (use it as --chain {})", out.display(), out.display());
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn cmd_identify(
    path: &Path,
    mms: Option<f64>,
    order: Option<usize>,
    effects: &str,
    chain: &ChainMode,
    wiring: SenseWiring,
    sd: Option<f64>,
    scale: Option<&[f64]>,
    out: &Path,
) -> Result<(), Failure> {
    use coilscope_ident::large::Stage;
    use coilscope_workflow::identify::{identify_record, IdentifyRequest};
    let origin = path.display().to_string();
    let mut rec = read_recording(path, scale).map_err(|e| e.to_string())?;
    let live = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let t0 = std::time::Instant::now();
    let progress = |p: &coilscope_ident::large::Progress| {
        if live {
            let stage = match p.stage {
                Stage::Estimate { order } => format!("order {order} on the estimation part"),
                Stage::Final { order } => format!("order {order} on the whole record"),
            };
            eprint!(
                "\r  {:5.1} s  fitting {stage}: iteration {:2}, current error {:.3e}        ",
                t0.elapsed().as_secs_f64(),
                p.state.iteration,
                p.residual_rel
            );
        }
    };
    // A batch's worker runs on one core (`cmd_identify_batch`).
    let threads = std::env::var(JOB_THREADS).ok().and_then(|v| v.parse().ok()).unwrap_or(0);
    let req = IdentifyRequest {
        origin: origin.clone(),
        mms,
        order,
        effects: parse_effects(effects)?,
        chain: chain.clone(),
        wiring,
        sd,
        threads,
    };
    let done = identify_record(&mut rec, &req, progress);
    if live {
        eprintln!();
    }
    let done = done?;
    for d in &done.detected {
        eprintln!("chain: estimated, as the record shows one: {d}");
    }
    print_warnings(&done.warnings);
    write_json(out, &done.result).map_err(|e| e.to_string())?;
    print_large_summary(path, &rec, &done.fit, &done.result, t0.elapsed().as_secs_f64());
    match &done.failure {
        Some(m) => Err(Failure::Untrusted(format!("{m}; written to {}", out.display()))),
        None => {
            println!("  result: {}", out.display());
            untrusted_if_warned(&done.warnings, out)
        }
    }
}

/// The environment variable that sets `identify`'s Jacobian threads (a batch's workers: 1).
const JOB_THREADS: &str = "COILSCOPE_THREADS";

/// `identify A.wav B.wav ... --out DIR`: each recording identified by a worker process of
/// this program with the same options (`OUT/NAME.json`), `jobs` at a time, each on one core:
/// on a production line whole records in parallel keep every core busy, where one record's
/// fit leaves a second core partly idle. A worker's failure is its recording's, not the
/// batch's; the exit code is the worst of the workers'.
fn cmd_identify_batch(recordings: &[PathBuf], jobs: Option<usize>, out: &Path) -> Result<(), Failure> {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let jobs = jobs.unwrap_or(cores);
    if jobs == 0 {
        return Err(Failure::from("--jobs 0: give at least 1"));
    }
    if out.is_file() || out.extension().is_some_and(|e| e == "json") {
        return Err(Failure::from(format!(
            "{}: with {} recordings --out is a directory (each result is OUT/NAME.json)",
            out.display(),
            recordings.len()
        )));
    }
    let mut names = std::collections::BTreeMap::new();
    for r in recordings {
        let stem = r
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .ok_or_else(|| format!("{}: not a file name", r.display()))?;
        if let Some(other) = names.insert(stem.clone(), r) {
            return Err(Failure::from(format!(
                "{} and {} would both write {}.json: give recordings with different names",
                other.display(),
                r.display(),
                stem
            )));
        }
    }
    std::fs::create_dir_all(out).map_err(|e| format!("{}: cannot create the output directory: {e}", out.display()))?;
    let exe = std::env::current_exe().map_err(|e| format!("cannot find this program to start the workers: {e}"))?;
    // The worker's arguments: this invocation's, less the recordings, --out and --jobs.
    let given: Vec<std::ffi::OsString> = std::env::args_os().skip(1).collect();
    let mut options = vec![];
    let mut k = 0;
    while k < given.len() {
        let a = given[k].to_string_lossy();
        let takes_value = |flag: &str| a == flag;
        if takes_value("--out") || takes_value("--jobs") {
            k += 2;
            continue;
        }
        if a.starts_with("--out=") || a.starts_with("--jobs=") || recordings.iter().any(|r| r.as_os_str() == given[k]) {
            k += 1;
            continue;
        }
        options.push(given[k].clone());
        k += 1;
    }
    let t0 = std::time::Instant::now();
    let queue = std::sync::Mutex::new(recordings.iter().collect::<std::collections::VecDeque<_>>());
    let done = std::sync::Mutex::new(vec![]);
    std::thread::scope(|scope| {
        for _ in 0..jobs.min(recordings.len()) {
            scope.spawn(|| loop {
                let Some(r) = queue.lock().unwrap_or_else(|e| e.into_inner()).pop_front() else { break };
                let stem = r.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
                let result = out.join(format!("{stem}.json"));
                let t = std::time::Instant::now();
                let o = std::process::Command::new(&exe)
                    .args(&options)
                    .arg(r)
                    .arg("--out")
                    .arg(&result)
                    .env(JOB_THREADS, "1")
                    .stdin(std::process::Stdio::null())
                    .output();
                let (code, text) = match o {
                    Ok(o) => (
                        o.status.code().unwrap_or(2),
                        format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr)),
                    ),
                    Err(e) => (2, format!("cannot start a worker: {e}")),
                };
                // Each recording's report whole, as it finishes.
                let mut stdout = std::io::stdout().lock();
                use std::io::Write as _;
                let _ = writeln!(
                    stdout,
                    "== {} ({:.1} s, exit {code})
{}",
                    r.display(),
                    t.elapsed().as_secs_f64(),
                    text.trim_end()
                );
                done.lock().unwrap_or_else(|e| e.into_inner()).push((r.clone(), code, result));
            });
        }
    });
    let mut done = done.into_inner().unwrap_or_else(|e| e.into_inner());
    done.sort();
    println!("batch: {} recordings in {:.1} s, {jobs} at a time", done.len(), t0.elapsed().as_secs_f64());
    for (r, code, result) in &done {
        let what = match code {
            0 => format!("ok: {}", result.display()),
            3 => format!("written but not trustworthy (see its warnings): {}", result.display()),
            _ => "failed (see its report above)".to_string(),
        };
        println!("  {:<40} {what}", r.display().to_string());
    }
    let worst = done.iter().map(|d| d.1).max().unwrap_or(0);
    let bad = done.iter().filter(|d| d.1 != 0).count();
    match worst {
        0 => Ok(()),
        3 => {
            Err(Failure::Untrusted(format!("{bad} of {} recordings gave results that are not trustworthy", done.len())))
        }
        _ => Err(Failure::Error(format!("{bad} of {} recordings failed or are not trustworthy", done.len()))),
    }
}

/// `identify --method volterra`: the seed paper's Volterra identification (3.2.2.1) on a
/// recorded readable multitone. Every number traces to `coilscope_ident::volterra`: the lines
/// (`record_lines`), the ratios and their noise (`RecordLines::harmonics`), the fit and its
/// covariance (`identify_volterra_weighted`), the truncation check (`truncation_check`).
#[allow(clippy::too_many_arguments)]
fn cmd_identify_volterra(
    path: &Path,
    start: Option<&str>,
    mms: Option<f64>,
    order: Option<usize>,
    effects: &str,
    chain_choice: &ChainMode,
    wiring: SenseWiring,
    sd: Option<f64>,
    scale: Option<&[f64]>,
    out: &Path,
) -> Result<(), Failure> {
    use coilscope_ident::checks::Warning;
    use coilscope_ident::volterra::{identify_volterra_weighted, record_lines, truncation_check};
    let origin = path.display().to_string();
    if let Some(o) = order.filter(|&o| o != 2) {
        return Err(Failure::from(format!("--order {o}: the Volterra method gives the series to second order (the kernels to third order depend on x^0 .. x^2 only); leave --order out")));
    }
    if effects != "auto" && effects != "none" {
        return Err(Failure::from(format!("--effects {effects}: the Volterra method fits Bl, Kms, Le to the kernels of the start's linear model; its effects (creep, LR-3) come from --start")));
    }
    if mms.is_some() {
        return Err(Failure::from(
            "--mms: the Volterra method takes the moving mass (and the rest of the linear part) from --start",
        ));
    }
    let start_spec = start.ok_or("--method volterra needs --start FILE: the small-signal parameters (run `coilscope linear` on a noise record of the driver, or give a parameter set)")?;
    let start = coilscope_report::input_from(start_spec)?.params;
    let start = Parameters {
        bl: coilscope_core::Poly::constant(start.bl.c[0]),
        kms: coilscope_core::Poly::constant(start.kms.c[0]),
        le: coilscope_core::Poly::constant(start.le.c[0]),
        l2r2: start.l2r2.map(|(l, r)| (coilscope_core::Poly::constant(l.c[0]), coilscope_core::Poly::constant(r.c[0]))),
        sd: sd.or(start.sd),
        ..start
    };
    let mut rec = read_recording(path, scale).map_err(|e| e.to_string())?;
    if matches!(chain_choice, ChainMode::Estimate) {
        return Err(Failure::from("--chain auto: the Volterra method does not estimate a chain (its lines carry no transient to tell it); calibrate the card (`coilscope calibrate`) and give --chain FILE, or --chain none"));
    }
    let calibrated = chain_choice.undo(&mut rec, &origin, wiring)?;
    let fs = rec.fs as f64;
    let t0 = std::time::Instant::now();
    let lines = record_lines(&rec.u, &rec.i, fs, &origin)?;
    let (measured, noise) = lines.harmonics(&start);
    let fit = identify_volterra_weighted(&start, &measured, Some(&noise))?;
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
    let mut result = ResultFile::new("large-signal", &origin, q.clone(), result_fit, unc, Some(&lim));
    result.chain = calibrated;
    result.other.insert(
        "volterra".into(),
        json!({
            "tones_hz": lines.bins, "periods": lines.starts.len(), "chi2_dof": chi2, "truncation": trunc,
            "lines": measured.iter().zip(&noise).map(|(h, n)| json!({"freq": h.freq, "volts_rms": h.volts, "ratio2": [h.ratio(2).re, h.ratio(2).im], "ratio3": [h.ratio(3).re, h.ratio(3).im], "sd2": n[0], "sd3": n[1]})).collect::<Vec<_>>(),
        }),
    );
    coilscope_workflow::attach_warnings(&mut result, None, &warnings);
    print_warnings(&warnings);
    write_json(out, &result).map_err(|e| e.to_string())?;
    let pct = |f: &coilscope_core::Poly, x: f64| 100.0 * (f.eval(x) / f.c[0] - 1.0);
    println!(
        "coilscope identify --method volterra: {origin}, {} tones {}-{} Hz, {} periods, {:.2} s",
        lines.bins.len(),
        lines.bins[0],
        lines.bins[lines.bins.len() - 1],
        lines.starts.len(),
        t0.elapsed().as_secs_f64()
    );
    println!("  reach {:+.3} .. {:+.3} mm; kernel chi^2/dof {chi2:.2}, truncation {trunc:.2} (both about 1 or less where the series holds)", 1e3 * reach[0], 1e3 * reach[1]);
    for (name, f) in [("Bl", &q.bl), ("Kms", &q.kms), ("Le", &q.le)] {
        println!(
            "  {name:>3}(x) at the reach: {:+.2} % / {:+.2} % of its value at rest",
            pct(f, reach[0]),
            pct(f, reach[1])
        );
    }
    println!("  result: {}", out.display());
    untrusted_if_warned(&warnings, out)
}

fn print_large_summary(
    path: &Path,
    rec: &Recording,
    fit: &coilscope_ident::large::LargeFit,
    result: &ResultFile,
    seconds: f64,
) {
    let p = &fit.params;
    let fs = rec.fs as f64;
    println!(
        "coilscope identify: {} ({:.2} s at {} Hz), fitted in {:.1} s",
        path.display(),
        rec.u.len() as f64 / fs,
        rec.fs,
        seconds
    );
    println!(
        "  order {} ({}), {} iterations, current error {:.3e} (relative RMS), x reached {:.3} .. {:.3} mm",
        fit.order,
        if fit.trials.is_empty() { "given".to_string() } else { "chosen on held-out data".to_string() },
        fit.iterations,
        fit.residual_rel,
        fit.x_range[0] * 1e3,
        fit.x_range[1] * 1e3
    );
    for t in &fit.trials {
        println!("    order {}: estimation {:.3e}, validation {:.3e}", t.order, t.estimation_rel, t.validation_rel);
    }
    let tried = fit.models_tried();
    let words = |t: &coilscope_core::result::ModelTrial| {
        match (t.validation_rel, t.screen_gain) {
        (Some(v), _) => match t.validation_rel_before {
            Some(b) => format!("{} validation {v:.3e} (went on alone from {b:.3e}: the next trial's gain was within what its fit had left)", t.model),
            None => format!("{} validation {v:.3e}", t.model),
        },
        (None, Some(g)) if t.outscored_by.is_some() => format!("{} not fitted: {} took its round (could gain {:.2e})", t.model, t.outscored_by.as_deref().unwrap_or_default(), g),
        (None, Some(g)) => format!("{} screened out (could gain {:.2e})", t.model, g),
        (None, None) => t.model.clone(),
    }
    };
    println!(
        "  model {} ({})",
        fit.layout.effects.model_name(),
        if tried.is_empty() { "given".to_string() } else { tried.iter().map(words).collect::<Vec<_>>().join(", ") }
    );
    if let Some(c) = &fit.chain {
        println!("  chain: {}", c.describe_fitted(fit.fs));
    }
    let u = &result.uncertainty;
    // Bl, Kms and Le are shown as curves below.
    print_values(p, u, &["Bl", "Kms", "Le"]);
    let [lo, hi] = fit.x_range;
    println!(
        "  {:<6} {:>14} {:>14} {:>14}",
        "",
        format!("x={:.2} mm", lo * 1e3),
        "x=0",
        format!("x={:.2} mm", hi * 1e3)
    );
    for (name, unit, scale) in [("Bl", "T m", 1.0), ("Kms", "N/m", 1.0), ("Le", "mH", 1e3)] {
        let b = fit.band(name, 3);
        let cell = |k: usize| format!("{:.4} +- {:.1e}", b.value[k] * scale, b.sd[k] * scale);
        let f = match name {
            "Bl" => &p.bl,
            "Kms" => &p.kms,
            _ => &p.le,
        };
        println!("  {:<6} {:>14} {:>14} {:>14}  {unit}", name, cell(0), format!("{:.4}", f.eval(0.0) * scale), cell(2));
    }
    if let Some(l) = &result.limits {
        let lim = |v: Option<f64>, beyond: Option<f64>| match v {
            Some(v) => format!("{:.2} mm", v * 1e3),
            None => format!("> {:.2} mm", beyond.unwrap_or(0.0) * 1e3),
        };
        println!(
            "  limits: XBl {}, XC {}, XL {}, Xsym {}, Ak {:.1} %",
            lim(l.xbl, l.xbl_beyond),
            lim(l.xc, l.xc_beyond),
            lim(l.xl, l.xl_beyond),
            l.xsym.map(|v| format!("{:+.2} mm", v * 1e3)).unwrap_or("-".into()),
            l.ak
        );
    }
    if let Some(d) = &result.cross_check {
        let pc = |k: &str| 100.0 * d.max_rel_difference.get(k).copied().unwrap_or(f64::NAN);
        println!(
            "  cross-check (post-inverse, measured x): Bl {:.2} %, Kms {:.2} %, Le {:.2} %, Mms {:.2} %",
            pc("Bl"),
            pc("Kms"),
            pc("Le"),
            pc("Mms")
        );
    }
    if let Some(dt) = result.thermal.as_ref().and_then(|t| t.dt_end) {
        println!(
            "  voice coil: Re {:.4} -> {:.4} ohm over the record (+{:.2} K)",
            fit.re_track[0].1,
            fit.re_track.last().unwrap().1,
            dt
        );
        if !fit.layout.heat_taus.is_empty() {
            println!("  Re(t): knots every {:.2} s plus heating terms (time constants {:?} s): the coil heated faster than the knots could follow", fit.layout.knot_dt, fit.layout.heat_taus);
        }
    }
}

/// A sound card as the device (`measure --card`); the calibration turns full scale into
/// volts and amperes. Needs a build with `--features soundcard`.
#[derive(clap::Args, Debug)]
struct CardArgs {
    /// Measure a real transducer through a sound card (output -> amplifier -> driver; inputs:
    /// terminal voltage and the voltage across a sense resistor).
    #[arg(long)]
    card: bool,
    /// Output device (as `coilscope devices` lists it); default: the system's default.
    #[arg(long, value_name = "NAME", requires = "card")]
    card_out: Option<String>,
    /// Input device; default: the system's default.
    #[arg(long, value_name = "NAME", requires = "card")]
    card_in: Option<String>,
    /// Output channel that drives the amplifier (0-based), of --out-channels.
    #[arg(long, default_value_t = 0)]
    drive_channel: usize,
    /// Number of output channels the output device is opened with.
    #[arg(long, default_value_t = 2)]
    out_channels: u16,
    /// Input channel holding the voltage (0-based, of --in-channels): across the driver's
    /// terminals, or across driver and shunt (--sense-wiring).
    #[arg(long, default_value_t = 0)]
    u_channel: usize,
    /// Input channel holding the sense-resistor voltage (the current), 0-based.
    #[arg(long, default_value_t = 1)]
    i_channel: usize,
    /// Number of input channels the input device is opened with.
    #[arg(long, default_value_t = 2)]
    in_channels: u16,
    /// Volts at the driver's terminals for a full-scale output sample (amplifier gain included).
    #[arg(long, default_value_t = 10.0, value_name = "V")]
    out_volts_fs: f64,
    /// Volts at the terminals for a full-scale sample on the voltage input (divider included).
    #[arg(long, default_value_t = 10.0, value_name = "V")]
    u_volts_fs: f64,
    /// Volts across the sense resistor for a full-scale sample on the current input.
    #[arg(long, default_value_t = 1.0, value_name = "V")]
    i_volts_fs: f64,
    /// The sense resistor (ohm).
    #[arg(long, default_value_t = 0.1, value_name = "OHM")]
    sense_ohm: f64,
    /// The card's calibration (a chain file from `coilscope calibrate`): its delay, AC
    /// coupling and gain are corrected block by block, the offsets found in a 0.5 s silent
    /// lead-in. With `measure --virtual`: the virtual driver is recorded through a simulated
    /// card with this chain (its offsets and hum too) and measured through the correction.
    #[arg(long, value_name = "FILE")]
    chain: Option<PathBuf>,
    /// Where the voltage input is connected: `terminals` (across the driver alone: preferred)
    /// or `driver+shunt` (across driver and --sense-ohm in series: its drop is taken out).
    /// Default: the chain file's, else `terminals`.
    #[arg(long, value_name = "WIRING")]
    sense_wiring: Option<String>,
}

/// `device` read through the card's calibration `c`, corrected block by block, and the
/// calibration used: it knows the card (delay, corners, gain), not this run's offsets or hum
/// (found in the lead-in).
fn corrected(
    device: Box<dyn coilscope_measure::device::Device>,
    c: coilscope_core::chain::Chain,
    wiring: SenseWiring,
) -> Result<(Box<dyn coilscope_measure::device::Device>, coilscope_core::chain::Chain), String> {
    let cal = coilscope_core::chain::Chain { dc_u: 0.0, dc_i: 0.0, hum: None, ..c };
    Ok((Box::new(coilscope_measure::card::Corrected::new(device, &cal, wiring)?), cal))
}

impl CardArgs {
    /// The card's chain file (as given) and the wiring, when there is something to correct:
    /// a `--chain`, or a wiring other than `terminals` (measure --card and quasistatic --card
    /// alike).
    fn correction(&self) -> Result<Option<(coilscope_core::chain::Chain, SenseWiring)>, String> {
        let chain = self.chain.as_deref().map(load_chain).transpose()?;
        let wiring = self.wiring(chain.as_ref())?;
        Ok((chain.is_some() || wiring != SenseWiring::Terminals).then(|| (chain.unwrap_or_default(), wiring)))
    }

    /// The sense wiring: `--sense-wiring`, else the chain file's, else `terminals`.
    fn wiring(&self, chain: Option<&coilscope_core::chain::Chain>) -> Result<SenseWiring, String> {
        match (&self.sense_wiring, chain) {
            (Some(w), _) => SenseWiring::parse(w, Some(self.sense_ohm)),
            (None, Some(c)) if c.sense_wiring.is_some() => SenseWiring::parse(
                c.sense_wiring.as_deref().unwrap_or_default(),
                Some(c.sense_ohm.unwrap_or(self.sense_ohm)),
            ),
            (None, _) => Ok(SenseWiring::Terminals),
        }
    }
}

#[cfg(feature = "soundcard")]
fn open_card(c: &CardArgs, rate: u32) -> Result<Box<dyn coilscope_measure::device::Device>, String> {
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
fn open_card(_: &CardArgs, _: u32) -> Result<Box<dyn coilscope_measure::device::Device>, String> {
    Err(NO_SOUNDCARD.into())
}

#[cfg(not(feature = "soundcard"))]
const NO_SOUNDCARD: &str = "this coilscope was built without sound-card support: rebuild with `cargo build --release --features soundcard` (Debian/Ubuntu: apt install libasound2-dev first)";

#[cfg(feature = "soundcard")]
fn cmd_devices() -> Result<(), String> {
    let (inputs, outputs) = coilscope_measure::soundcard::list_devices()?;
    println!("inputs:  {}", if inputs.is_empty() { "none".into() } else { inputs.join(", ") });
    println!("outputs: {}", if outputs.is_empty() { "none".into() } else { outputs.join(", ") });
    Ok(())
}

#[cfg(not(feature = "soundcard"))]
fn cmd_devices() -> Result<(), String> {
    Err(NO_SOUNDCARD.into())
}

struct MeasureArgs {
    no_report: bool,
    virtual_driver: Option<String>,
    world: World,
    card: CardArgs,
    replay: Option<PathBuf>,
    out: PathBuf,
    mms: Option<f64>,
    target_x: Option<f64>,
    max_dt: f64,
    kms_limit: f64,
    max_volts: f64,
    start_volts: f64,
    music: Option<PathBuf>,
    duration: Option<f64>,
    cool: Option<(f64, f64)>,
    volts: Option<f64>,
    max_seconds: f64,
    order: usize,
    noise: Vec<f64>,
    rate: u32,
    seed: u64,
    crest: Option<f64>,
    serve: ServeArgs,
}

/// `measure --serve`: the live page (`coilscope_live`), an observer of the run.
#[derive(clap::Args, Debug, Clone)]
struct ServeArgs {
    /// Serve a live page of the measurement at ADDR (IP:PORT; without a value 127.0.0.1:8640;
    /// port 0 picks a free one): traces of u, i, x, v, the temperature, the curves with their
    /// bands as they converge, the level, protection and convergence state, the live
    /// distortion, and the report's link at the end. It only watches: nothing on the page
    /// changes the run. Embedded page, no network needed.
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = coilscope_live::DEFAULT_ADDR)]
    serve: Option<String>,
    /// Allow --serve on an address other than loopback (anyone who reaches it sees the run).
    #[arg(long, requires = "serve")]
    serve_public: bool,
    /// After the run, keep serving the page and the report it links for this many seconds
    /// (Ctrl-C ends it sooner).
    #[arg(long, value_name = "S", default_value_t = 300.0)]
    serve_linger: f64,
    /// Play a virtual or replayed run at FACTOR times real time (1: as a sound card would).
    /// Default: as fast as the computer can; 1 with --serve, so that the page is watchable.
    #[arg(long, value_name = "FACTOR")]
    pace: Option<f64>,
}

/// The IEC noise with `--crest` (None: the default crest [`coilscope_core::excitation::IEC_CREST`]).
fn iec_noise(crest: Option<f64>) -> Excitation {
    match crest {
        None => Excitation::Iec,
        Some(c) if c.is_infinite() => Excitation::IecCrest { crest: None },
        Some(c) => Excitation::IecCrest { crest: Some(c) },
    }
}

fn cmd_measure(a: MeasureArgs) -> Result<(), Failure> {
    use coilscope_measure::device::{Device, ReplayDevice, VirtualDevice};
    use coilscope_measure::signal::Source;
    use coilscope_measure::store::Store;
    use std::io::IsTerminal;
    let (mut device, mms, mms_source): (Box<dyn Device>, f64, String) = match (&a.virtual_driver, &a.replay) {
        (Some(d), None) => {
            let given = load_parameters(d).map_err(|e| e.to_string())?;
            let p = a.world.apply(given.clone());
            if p != given {
                println!("virtual world: real (LOG creep lambda {} assumed, as real suspensions creep; --world published for the set as given)", coilscope_core::params::TYPICAL_CREEP_LAMBDA);
            }
            let dev = VirtualDevice::new(&p, a.rate as f64, (a.noise[0], a.noise[1]), a.seed)?;
            let (mms, src) = match a.mms {
                Some(m) => (m, "given (--mms)".to_string()),
                None => (p.mms, format!("the virtual driver's own Mms ({d})")),
            };
            (Box::new(dev), mms, src)
        }
        (None, Some(r)) => {
            // A displacement channel (a laser) gives the absolute scale, as for `identify`:
            // Mms from the post-inverse (equation-error) fit of the whole record.
            let rec = read_recording(r, None).map_err(|e| e.to_string())?;
            let name = r.display().to_string();
            let (mms, src) = match (a.mms, &rec.x) {
                (Some(m), _) => (m, "given (--mms)".to_string()),
                (None, Some(x)) => {
                    let pi = post_inverse_of(&rec.u, &rec.i, x, rec.fs as f64, 4, &name)?;
                    eprintln!("Mms {:.3} g from the displacement channel (post-inverse equation error)", pi.mms * 1e3);
                    (pi.mms, "displacement channel (post-inverse equation error)".to_string())
                }
                (None, None) => return Err(Failure::from(format!("{name}: --replay needs an absolute scale: give --mms KG (moving mass), or a recording with a displacement channel (3, m)"))),
            };
            (Box::new(ReplayDevice::from_samples(&name, rec.fs as f64, rec.u, rec.i)), mms, src)
        }
        (None, None) if a.card.card => {
            let mms = a.mms.ok_or("--card needs --mms KG (the absolute scale: weigh the cone, or measure it by the added-mass method with `coilscope linear`)")?;
            (open_card(&a.card, a.rate)?, mms, "given (--mms)".to_string())
        }
        _ => {
            return Err(
                "give the device: --virtual DRIVER (embedded name or parameter file), --replay REC.wav or --card"
                    .into(),
            )
        }
    };
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
    let mut store = Store::create(&a.out.join("run.sqlite"), &device.describe(), &options)?;
    let tty = std::io::stderr().is_terminal();
    let mut last_print = -1.0;
    let controllable = device.controllable();
    if controllable {
        eprintln!(
            "measuring {} with {} (run {} in {})",
            device.describe(),
            source.name(),
            store.run,
            a.out.join("run.sqlite").display()
        );
    } else {
        eprintln!(
            "identifying from the {} (run {} in {})",
            device.describe(),
            store.run,
            a.out.join("run.sqlite").display()
        );
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
            // A replay's level was set when it was recorded: no drive level, no controller.
            let line = if controllable {
                format!(
                    "t {:6.1} s  {:<12} {:7.3} V  {state}  limited by {}",
                    l.t,
                    l.stage.name(),
                    l.volts,
                    l.limited_by
                )
            } else {
                format!("t {:6.1} s  {state}", l.t)
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
    m.mms_source = mms_source;
    let mut j = m.result();
    if reported_chain.is_some() {
        j.chain = reported_chain;
    }
    write_json(&a.out.join("result.json"), &j).map_err(|e| e.to_string())?;
    let status = match m.stop_reason {
        _ if m.converged => "converged",
        coilscope_measure::StopReason::Interrupted { .. } => "interrupted",
        coilscope_measure::StopReason::Failed { .. } => "failed",
        coilscope_measure::StopReason::DurationOver { .. } => "finished",
        _ => "not converged",
    };
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
    println!("wrote {} and {}", a.out.join("result.json").display(), a.out.join("run.sqlite").display());
    if !a.no_report {
        let t = coilscope_core::limits::Thresholds::default();
        let defaults = LimitArgs { xbl: t.bl, xc: t.cms, xl: t.le, max_dt: a.max_dt };
        let result = a.out.join("result.json");
        // The measurement is stored whatever happens to its report.
        if let Err(e) = cmd_report(&result.to_string_lossy(), &a.out.join("report.html"), None, None, None, &defaults) {
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

fn cmd_runs(path: &Path) -> Result<(), String> {
    let db = if path.is_dir() { path.join("run.sqlite") } else { path.to_path_buf() };
    let runs = coilscope_measure::store::list_runs(&db)?;
    if runs.is_empty() {
        println!("{}: no runs", db.display());
    }
    for r in runs {
        print!(
            "run {:>3}  {:<12} {:8.1} s  {:>6} states  {:>4} estimates  {}",
            r.id, r.status, r.seconds, r.states, r.estimates, r.device
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

struct DistortionArgs {
    params: String,
    freq: Option<f64>,
    freq2: Option<f64>,
    ratio: f64,
    volts: Option<f64>,
    output: coilscope_analysis::distortion::Output,
    multitone: bool,
    band: Option<Vec<f64>>,
    tones: usize,
    sweep: Option<Vec<f64>>,
    levels: Option<Vec<f64>>,
    temp_rise: f64,
    json: bool,
    seed: u64,
}

fn print_json(v: &serde_json::Value) {
    println!("{}", serde_json::to_string_pretty(v).expect("JSON values serialise"));
}

/// `quasistatic`: the point-by-point measurement on a virtual driver.
#[allow(clippy::too_many_arguments)]
struct QuasiArgs {
    driver: Option<String>,
    out: PathBuf,
    points: usize,
    reach: f64,
    hold: f64,
    order: usize,
    world: World,
    offset: String,
    mms: Option<f64>,
    xmax: Option<f64>,
    sd: Option<f64>,
    ac_volts: f64,
    rate: u32,
    card: CardArgs,
}

fn cmd_quasistatic(a: QuasiArgs) -> Result<(), Failure> {
    use coilscope_ident::quasi_static::{quasi_static, Offset, Played, Push, QuasiStaticOptions};
    let (out, points, reach, hold, order) = (a.out.as_path(), a.points, a.reach, a.hold, a.order);
    if !(reach > 0.0 && reach <= 1.0) {
        return Err(format!("--reach {reach} is not valid (0 .. 1 of the range)").into());
    }
    if !(0.5..=600.0).contains(&hold) {
        return Err(format!("--hold {hold} s is not valid (0.5 .. 600 s)").into());
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

/// `export`: one file for another tool, written atomically.
fn cmd_export(
    spec: &str,
    speakersafetyd: bool,
    power_series: bool,
    zma: bool,
    frd: bool,
    out: &Path,
    o: &coilscope_io::export::SafetydOptions,
) -> Result<(), String> {
    use coilscope_io::export;
    let input = coilscope_report::input_from(spec)?;
    let mut p = input.params;
    // A measured set has no name of its own: the result's device or recording names it.
    if p.name.is_none() {
        p.name = input.result.map(|r| r.recording).filter(|r| !r.is_empty());
    }
    let (text, what) = if speakersafetyd {
        (export::speakersafetyd(&p, o).map_err(|e| format!("{spec}: {e}"))?, "speakersafetyd configuration")
    } else if power_series {
        (export::power_series_csv(&p), "power series (mm)")
    } else {
        let curve = export::impedance_curve(&p, 5.0, 20_000.0, 400);
        if zma {
            (coilscope_io::impedance::zma_text(&curve), "impedance (.zma)")
        } else if frd {
            (export::frd_text(&curve), "impedance (.frd)")
        } else {
            return Err("give the format: --speakersafetyd, --power-series, --zma or --frd".into());
        }
    };
    coilscope_io::atomic_write(out, text.as_bytes()).map_err(|e| e.to_string())?;
    println!("wrote {} ({what})", out.display());
    Ok(())
}

/// `compensate`: the pre-inverse drive, and what the model predicts it does (the largest
/// deviation of the displacement from the linear reference, plain and compensated).
fn cmd_compensate(
    params: &str,
    input: &Path,
    out: &Path,
    max_volts: Option<f64>,
    min_force_factor: f64,
    scale: Option<f64>,
) -> Result<(), String> {
    use coilscope_core::inverse::{compensate, CompensateOptions};
    let p = coilscope_report::input_from(params)?.params;
    let (fs, u) = read_voltage(input, scale.map(|s| vec![s]).as_deref()).map_err(|e| e.to_string())?;
    if u.is_empty() {
        return Err(format!("{}: the input has no samples", input.display()));
    }
    let c = compensate(&p, fs as f64, &u, &CompensateOptions { max_volts, min_force_factor })
        .map_err(|e| format!("{}: {e}", input.display()))?;
    coilscope_io::write_voltage(out, fs, &c.drive).map_err(|e| e.to_string())?;
    let dev = |x: &[f64]| x.iter().zip(&c.x_target).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    let peak = c.x_target.iter().fold(0.0f64, |a, v| a.max(v.abs()));
    let sim =
        |d: &[f64]| simulate(&p, fs as f64, d, &SimOptions::default()).map(|t| dev(&t.x)).map_err(|e| e.to_string());
    let name = p.name.clone().unwrap_or_else(|| params.to_string());
    println!("coilscope compensate: {name}, {:.2} s at {fs} Hz", u.len() as f64 / fs as f64);
    println!("  linear reference peak excursion {:.3} mm", peak * 1e3);
    println!("  drive peak {:.3} V (input {:.3} V)", c.peak_volts, u.iter().fold(0.0f64, |a, v| a.max(v.abs())));
    match (sim(&u), sim(&c.drive)) {
        (Ok(a), Ok(b)) => println!(
            "  the model's displacement off the linear reference (largest): plain {a:.3e} m, compensated {b:.3e} m"
        ),
        (Err(e), _) | (_, Err(e)) => println!("  (the model's check did not run: {e})"),
    }
    for w in &c.warnings {
        println!("  warning: {w}");
    }
    println!("  wrote {}", out.display());
    Ok(())
}

fn cmd_distortion(a: DistortionArgs) -> Result<(), String> {
    use coilscope_analysis::db;
    use coilscope_analysis::distortion::{self as d, SteadyOptions};
    let input = coilscope_report::input_from(&a.params)?;
    let p = &input.params;
    if !(a.temp_rise.is_finite() && (0.0..=300.0).contains(&a.temp_rise)) {
        return Err(format!("--temp-rise {} K is not valid (0 .. 300 K)", a.temp_rise));
    }
    let opts = SteadyOptions { dt_coil: a.temp_rise, ..SteadyOptions::default() };
    let e = |e: coilscope_analysis::AnalysisError| e.to_string();
    let name = p.name.clone().unwrap_or_else(|| a.params.clone());
    let out = a.output.name();
    let volts = a.volts.unwrap_or(f64::NAN);
    if a.multitone {
        let band = a.band.clone().unwrap_or_else(|| vec![20.0, 10_000.0]);
        let m = d::multitone(p, band[0], band[1], a.tones, volts, a.output, a.seed, &opts).map_err(e)?;
        if a.json {
            print_json(&m.to_json());
        } else {
            println!("{name}: {} tones {:.0} .. {:.0} Hz, {:.3} V RMS, {out}", m.tones.len(), band[0], band[1], volts);
            println!("  multitone total distortion {:.2} dB ({:.3} %)", db(m.mtd), 100.0 * m.mtd);
            println!(
                "  DC displacement {:+.4} mm, x {:+.3} .. {:+.3} mm",
                m.x_dc * 1e3,
                m.x_peak[0] * 1e3,
                m.x_peak[1] * 1e3
            );
        }
        return Ok(());
    }
    if let (Some(_), Some(_)) = (&a.sweep, a.freq) {
        return Err("--sweep F_LO F_HI sets the frequencies itself: drop --freq".into());
    }
    // A frequency sweep needs no --freq (it runs from F_LO to F_HI).
    let freq = a.freq.or(a.sweep.as_ref().map(|b| b[0])).ok_or(
        "--freq F is required (the sine, or the low tone of a two-tone); or use --multitone or --sweep F_LO F_HI",
    )?;
    if let Some(f2) = a.freq2 {
        let im = d::intermod(p, freq, f2, volts, a.ratio, a.output, &opts).map_err(e)?;
        if a.json {
            print_json(&im.to_json());
        } else {
            println!(
                "{name}: two-tone {:.2} Hz + {:.2} Hz (f2/f1 amplitude {}), {:.3} V RMS, {out}",
                im.f1, im.f2, im.amplitude_ratio, volts
            );
            println!("  d2 (f2 +- f1)   {:8.2} dB  {:8.4} %", db(im.d2), 100.0 * im.d2);
            println!("  d3 (f2 +- 2f1)  {:8.2} dB  {:8.4} %", db(im.d3), 100.0 * im.d3);
            for (l, f, r) in &im.lines {
                println!("    {l:<7} {f:9.2} Hz {:8.2} dB", db(*r));
            }
            println!(
                "  DC displacement {:+.4} mm, x {:+.3} .. {:+.3} mm",
                im.x_dc * 1e3,
                im.x_peak[0] * 1e3,
                im.x_peak[1] * 1e3
            );
        }
        return Ok(());
    }
    if let Some(levels) = &a.levels {
        let rows = d::level_sweep(p, freq, levels, a.output, &opts).map_err(e)?;
        let div = d::divergence_level(&rows, 1.0);
        if a.json {
            let v: Vec<_> = rows.iter().map(|r| serde_json::json!({"volts_rms": r.volts, "full": r.full.to_json(), "volterra": {"HD2": r.volterra.0, "HD3": r.volterra.1, "x_dc": r.volterra_x_dc}})).collect();
            print_json(&serde_json::json!({"freq": freq, "rows": v, "volterra_divergence_1dB_volts": div}));
        } else {
            println!("{name}: sine {freq} Hz, {out}; full model against the 3rd-order Volterra series");
            println!("  {:>9} {:>9} {:>9} {:>11} {:>11}", "V RMS", "HD2 dB", "HD3 dB", "HD2 Volt.", "HD3 Volt.");
            for r in &rows {
                println!(
                    "  {:9.3} {:9.2} {:9.2} {:11.2} {:11.2}",
                    r.volts,
                    db(r.full.hd(2)),
                    db(r.full.hd(3)),
                    db(r.volterra.0),
                    db(r.volterra.1)
                );
            }
            match div {
                Some(v) => println!("  the Volterra series is off by more than 1 dB from {v:.3} V"),
                None => println!("  the Volterra series stays within 1 dB over these levels"),
            }
        }
        return Ok(());
    }
    let freqs = match &a.sweep {
        Some(b) => d::log_frequencies(b[0], b[1], 3),
        None => vec![freq],
    };
    let sweep = d::frequency_sweep(p, &freqs, volts, a.output, &opts).map_err(e)?;
    let q = d::with_only(p, &d::Nonlinearity::ALL, a.temp_rise);
    let probes: Vec<_> = sweep.iter().map(|an| coilscope_analysis::volterra::probe(&q, an.total.freq)).collect();
    if a.json {
        let v: Vec<_> = sweep
            .iter()
            .zip(&probes)
            .map(|(an, pr)| {
                let (h2, h3) = pr.hd(a.output, volts);
                let mut j = an.to_json();
                j["volterra"] = serde_json::json!({"HD2": h2, "HD3": h3, "HD2_dB": db(h2), "HD3_dB": db(h3), "x_dc": pr.x_dc(volts), "kernels": pr.to_json()});
                j
            })
            .collect();
        print_json(&if v.len() == 1 { v[0].clone() } else { serde_json::Value::Array(v) });
        return Ok(());
    }
    println!("{name}: sine, {:.3} V RMS, {out}", volts);
    for (an, pr) in sweep.iter().zip(&probes) {
        let t = &an.total;
        let (v2, v3) = pr.hd(a.output, volts);
        println!(
            "  {:.2} Hz: x {:+.3} .. {:+.3} mm, DC displacement {:+.4} mm",
            t.freq,
            t.x_peak[0] * 1e3,
            t.x_peak[1] * 1e3,
            t.x_dc * 1e3
        );
        println!("    {:<10} {:>9} {:>9} {:>9}", "", "HD2 dB", "HD3 dB", "THD dB");
        println!("    {:<10} {:9.2} {:9.2} {:9.2}", "total", db(t.hd(2)), db(t.hd(3)), db(t.thd()));
        for (nl, h) in &an.parts {
            println!(
                "    {:<10} {:9.2} {:9.2} {:9.2}",
                format!("{} only", nl.key()),
                db(h.hd(2)),
                db(h.hd(3)),
                db(h.thd())
            );
        }
        println!("    {:<10} {:9.2} {:9.2}", "Volterra", db(v2), db(v3));
        println!(
            "    dominant: {}; the parts' HD2 lines add up to the total within {:.1} %",
            an.dominant().name(),
            100.0 * an.sum_mismatch(2)
        );
    }
    Ok(())
}

fn cmd_diagnose(spec: &str, l: &LimitArgs, json: bool) -> Result<(), String> {
    let th = l.thresholds()?;
    let input = coilscope_report::input_from(spec)?;
    let d = coilscope_analysis::diagnosis::diagnose(&input.params, input.range, th, l.max_dt);
    if json {
        print_json(&d.to_json());
        return Ok(());
    }
    let mm = |v: Option<f64>| {
        v.map(|x| format!("{:.2} mm", x * 1e3))
            .unwrap_or_else(|| format!("beyond the reach ({:.2} mm)", d.limits.reach * 1e3))
    };
    println!(
        "{}: over {:.2} .. {:.2} mm",
        input.params.name.clone().unwrap_or_else(|| spec.into()),
        input.range[0] * 1e3,
        input.range[1] * 1e3
    );
    println!("  XBl (Bl {:.0} %)   {}", th.bl * 100.0, mm(d.limits.xbl));
    println!("  XC  (Cms {:.0} %)  {}", th.cms * 100.0, mm(d.limits.xc));
    println!("  XL  (Le {:.0} %)   {}", th.le * 100.0, mm(d.limits.xl));
    println!("  Ak               {:.1} %", d.limits.ak);
    println!("  Bl               {}", d.bl_shift_advice());
    let pol = &d.polarity;
    println!(
        "  polarity         {} (Le(-{:.2} mm) / Le(+{:.2} mm) = {:.3})",
        pol.verdict,
        pol.at * 1e3,
        pol.at * 1e3,
        pol.le_minus / pol.le_plus
    );
    match &d.thermal {
        Some(t) => {
            println!("  thermal (+{:.0} K) {:.1} W continuous in Re; {:.2} V RMS worst sine ({:.0} Hz); {:.2} V RMS IEC noise ({:.1} W nominal)", t.dt_max, t.p_max, t.volts_sine, t.f_sine, t.volts_iec, t.p_nominal_iec);
        }
        None => println!("  thermal          no thermal parameters in the set"),
    }
    Ok(())
}

fn cmd_report(
    spec: &str,
    out: &Path,
    db: Option<&Path>,
    volts: Option<f64>,
    compare: Option<&str>,
    l: &LimitArgs,
) -> Result<(), String> {
    let th = l.thresholds()?;
    if let Some(v) = volts {
        if !(v.is_finite() && v > 0.0 && v <= 500.0) {
            return Err(format!("--volts {v} is not valid (0 .. 500 V RMS)"));
        }
    }
    let mut input = coilscope_report::input_from(spec)?;
    let db_path = db
        .map(Path::to_path_buf)
        .or_else(|| Path::new(spec).parent().map(|d| d.join("run.sqlite")).filter(|p| p.exists()));
    if let Some(path) = db_path {
        // The database must be this measurement's: its last run's device is the result's.
        if let (Some(m), Some(run)) = (
            input.result.as_ref().and_then(|r| r.measurement.as_ref()),
            coilscope_measure::store::list_runs(&path)?.last(),
        ) {
            if run.device != m.device {
                return Err(format!("{}: its last run (#{}) measured {:?}, but {spec} is of {:?}: give the run database of this measurement (--db), or none", path.display(), run.id, run.device, m.device));
            }
        }
        let rows = coilscope_measure::store::read_states(&path, None)?;
        if !rows.is_empty() {
            input.states = Some(coilscope_report::TimeSeries {
                t: rows.iter().map(|r| r.t).collect(),
                x_min: rows.iter().map(|r| r.x_min).collect(),
                x_max: rows.iter().map(|r| r.x_max).collect(),
                dtv: rows.iter().map(|r| r.dtv).collect(),
            });
        }
    }
    if let Some(c) = compare {
        let other = coilscope_report::input_from(c)?;
        if let (Some(a), Some(b)) = (&input.params.name, &other.params.name) {
            if a != b {
                return Err(format!("--compare {c}: that result is of {b:?}, this one of {a:?}; compare two measurements of the same driver"));
            }
        }
        input.compare = Some(Box::new(other));
    }
    let opts = coilscope_report::ReportOptions { thresholds: th, dt_max: l.max_dt, volts, ..Default::default() };
    let rep = coilscope_report::build(&input, &opts)?;
    let written = coilscope_report::write(&rep, out, opts.png_size)?;
    for w in &rep.warnings {
        eprintln!("warning: the report could not draw {w}");
    }
    println!(
        "report: {} plots, distortion at {:.2} V RMS{}",
        rep.charts.len(),
        rep.volts,
        rep.volterra_divergence.map(|v| format!(", Volterra off by > 1 dB from {v:.2} V")).unwrap_or_default()
    );
    println!(
        "wrote {} and {} files in {}",
        out.display(),
        written.len() - 1,
        coilscope_report::files_dir(out).display()
    );
    Ok(())
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

    #[test]
    fn lengths_take_a_unit_or_plausible_metres() {
        let near = |s: &str, m: f64| (parse_length(s).unwrap() - m).abs() <= 1e-12 * m;
        assert!(
            near("4mm", 4e-3)
                && near("4.5 mm", 4.5e-3)
                && near("0.004m", 0.004)
                && near("450um", 450e-6)
                && near("0.004", 0.004)
        );
        assert!(parse_length("4").unwrap_err().contains("did you mean 4mm"));
        assert!(parse_length("0.000004").unwrap_err().contains("did you mean"));
        assert!(parse_length("4in").unwrap_err().contains("unknown length unit"));
        assert!(parse_length("mm").is_err());
    }
}

//! The command line: the subcommands with their arguments and help text, and the argument sets the
//! commands take.

use clap::{Subcommand, ValueEnum};
use coilscope_core::chain::SenseWiring;
use coilscope_core::mass::Mass;
use coilscope_core::Parameters;
use coilscope_workflow::chain::load_chain;
use std::path::PathBuf;

/// The virtual driver's world (`--world`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub(crate) enum World {
    /// The parameter set as given.
    Published,
    /// Plus typical LOG creep where the set has none (lambda 0.05 at the resonance), as a real
    /// suspension has.
    Real,
}

impl World {
    pub(crate) fn apply(self, p: Parameters) -> Parameters {
        self.workflow().apply(p)
    }

    /// The same world in the workflow library.
    pub(crate) fn workflow(self) -> coilscope_workflow::measure::World {
        match self {
            World::Published => coilscope_workflow::measure::World::Published,
            World::Real => coilscope_workflow::measure::World::Real,
        }
    }
}

#[derive(Clone, Copy, Debug, ValueEnum)]
pub(crate) enum ExcitationKind {
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
pub(crate) enum OutputKind {
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
pub(crate) struct FitArgs {
    /// Effective radiating area (m^2), for Vas.
    #[arg(long, id = "sd_given")]
    pub(crate) sd: Option<f64>,
    /// Scale factors of integer-PCM recordings (V, A [, m] per count).
    #[arg(long, num_args = 2..=3, value_names = ["V", "A"])]
    pub(crate) scale: Option<Vec<f64>>,
    /// The measurement chain between the driver and the recorded channels: `detect` (the
    /// default: estimated with the driver where the record shows one: a skew of the
    /// channels, AC coupling, offsets or mains hum), `auto` (always estimated), `none` (the
    /// channels are the driver's voltage and current, exactly), or a chain FILE from
    /// `coilscope calibrate` (delay, corners and gain known; each record's offsets are found).
    #[arg(long, default_value = "detect")]
    pub(crate) chain: String,
    /// Where the voltage channel is connected: `terminals` (across the driver alone:
    /// preferred) or `driver+shunt` (across driver and sense resistor in series, as a
    /// low-side shunt with single-ended inputs gives; the shunt's drop is taken out, so give
    /// --sense-ohm, measured four-wire).
    /// Default: the chain file's wiring, else `terminals`.
    #[arg(long, value_name = "WIRING")]
    pub(crate) sense_wiring: Option<String>,
    /// The sense resistor (ohm) of `--sense-wiring driver+shunt`.
    #[arg(long, value_name = "OHM")]
    pub(crate) sense_ohm: Option<f64>,
    /// Result file (JSON, coilscope.result/1). `linear` of a recording also writes the
    /// measured impedance beside it as .zma and .csv; `identify` of several recordings takes
    /// a directory here (one OUT/NAME.json each).
    #[arg(long)]
    pub(crate) out: PathBuf,
}

/// Limit thresholds and the thermal limit, shared by `diagnose` and `report`.
#[derive(clap::Args, Clone, Copy, Debug)]
pub(crate) struct LimitArgs {
    /// XBl threshold: Bl falls to this fraction of Bl(0).
    #[arg(long, default_value_t = 0.82)]
    pub(crate) xbl: f64,
    /// XC threshold: Cms falls to this fraction of Cms(0).
    #[arg(long, default_value_t = 0.75)]
    pub(crate) xc: f64,
    /// XL threshold: Le changes by this fraction of Le(0).
    #[arg(long, default_value_t = 0.10)]
    pub(crate) xl: f64,
    /// Voice-coil temperature rise limit for the thermal power handling (K).
    #[arg(long, default_value_t = 50.0)]
    pub(crate) max_dt: f64,
}

impl LimitArgs {
    pub(crate) fn thresholds(&self) -> Result<coilscope_core::limits::Thresholds, String> {
        let t = coilscope_core::limits::Thresholds { bl: self.xbl, cms: self.xc, le: self.xl };
        t.validate().map_err(|e| format!("{e} (--xbl, --xc, --xl)"))?;
        if !(self.max_dt.is_finite() && self.max_dt > 0.0 && self.max_dt <= 300.0) {
            return Err(format!("--max-dt {} K is not valid (0 .. 300 K)", self.max_dt));
        }
        Ok(t)
    }
}

// One value of it is parsed per run and taken apart at once: its size does not matter, and
// boxing the card's arguments would only clutter every command that reads them.
#[allow(clippy::large_enum_variant)]
#[derive(Subcommand)]
pub(crate) enum Command {
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
        /// Band of pink noise, multitone or sweep (Hz): `LO HI` or `LO,HI`.
        #[arg(long, num_args = 1..=2, value_names = ["LO", "HI"])]
        band: Option<Vec<String>>,
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
        /// Put the driver in this box: a JSON file with the box (`{"type": "vented", "Vb":
        /// 0.02, "fb": 38, ...}`, see docs/formats.md `enclosure`), a parameter set with one,
        /// or a recording's description with `world.enclosure`. The driver needs Sd.
        #[arg(long, value_name = "BOX.json")]
        enclosure: Option<PathBuf>,
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
        /// Known moving mass for the absolute scale, with its unit and, where known, its sd:
        /// 15.3g±0.3g (or 15.3g+-0.3g; a bare number is kg). The sd goes into Bl, Kms, Rms
        /// and Mms (`uncertainty.scale.KEY`); without one the mass is taken as exact.
        #[arg(long, value_name = "MASS")]
        mms: Option<Mass>,
        /// Added mass of the added-mass method, as --mms (8g±0.05g); needs --with-mass
        /// (records) or --with-mass-impedance (impedance files).
        #[arg(long, value_name = "MASS")]
        added_mass: Option<Mass>,
        /// Recording of the same driver with the added mass.
        #[arg(long, conflicts_with = "impedance")]
        with_mass: Option<PathBuf>,
        /// Impedance file of the same driver with the added mass.
        #[arg(long, value_name = "Z2.zma", requires = "impedance")]
        with_mass_impedance: Option<PathBuf>,
        /// Impedance files: the fitted band (Hz), `LO HI` or `LO,HI`; default: the band where
        /// the lumped model holds, found from the file (below the cone's break-up; the output
        /// says where).
        #[arg(long, num_args = 1..=2, value_names = ["LO", "HI"], requires = "impedance")]
        band: Option<Vec<String>>,
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
        /// Fit the box the driver works into instead: `closed`, `vented`, `passive_radiator`
        /// or `auto` (the type from the data, and which it chose). The input is the driver's
        /// impedance in the box, at a low level; --driver gives the driver's own set.
        #[arg(long, value_name = "TYPE", requires = "driver")]
        enclosure: Option<String>,
        /// With --enclosure: the driver's parameter set, measured in free air (a parameter
        /// file, a result of `coilscope linear`, or an embedded driver). It needs Sd (or --sd).
        #[arg(long, value_name = "DRIVER", requires = "enclosure")]
        driver: Option<String>,
        /// With --enclosure: a passive radiator's area (m^2); without it Sd is taken and the
        /// result says so.
        #[arg(long, value_name = "M2", requires = "enclosure")]
        sp: Option<f64>,
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
        /// Moving mass, the absolute scale, with its unit and, where known, its sd: 15.3g±0.3g
        /// (a bare number is kg); the sd goes into Bl, Kms, Rms and Mms and their bands.
        /// Without it, a displacement channel (3) gives the scale.
        #[arg(long, value_name = "MASS")]
        mms: Option<Mass>,
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
        /// The driver is in a box: `closed`, `vented`, `passive_radiator` or `auto` (the type
        /// the record's impedance shows). The box's values are identified with the driver's
        /// (result: `parameters.enclosure`); needs --sd.
        #[arg(long, value_name = "TYPE", requires = "sd_given")]
        enclosure: Option<String>,
        /// A closed box's net volume (m^3): the box air and the suspension are springs on the
        /// same cone, and the terminals see only their sum, so a closed box needs it.
        #[arg(long, value_name = "M3", requires = "enclosure")]
        vb: Option<f64>,
        /// A vented box's port area (m^2): the port's quadratic loss is then given as
        /// `port_loss`, else as `knl`.
        #[arg(long, value_name = "M2", requires = "enclosure")]
        port_area: Option<f64>,
        /// A passive radiator's area (m^2); without it Sd is taken, and the radiator's mass,
        /// stiffness and loss are over that area.
        #[arg(long, value_name = "M2", requires = "enclosure")]
        sp: Option<f64>,
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
        /// The run database: a SQLite file, or a PostgreSQL server
        /// (`postgres://user@host/database`) that a fleet of stations writes to (default:
        /// DIR/run.sqlite).
        #[arg(long, value_name = "FILE|URL")]
        db: Option<String>,
        /// Moving mass, with its unit and, where known, its sd: 15.3g±0.3g (a bare number is
        /// kg); for a virtual driver its own Mms is the default.
        #[arg(long, value_name = "MASS")]
        mms: Option<Mass>,
        /// Effective radiating area (m^2), for Vas; for a virtual driver its own Sd is the
        /// default.
        #[arg(long, value_name = "M2")]
        sd: Option<f64>,
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
    /// Write a result for another tool: a unit's protection model and calibration, the
    /// thermal model as a speakersafetyd configuration, the power series as a KLIPPEL-style
    /// table (CSV, millimetres), or the small-signal impedance as .zma / .frd.
    #[command(group(clap::ArgGroup::new("format").required(true).args(["protection", "speakersafetyd", "power_series", "zma", "frd"])))]
    Export {
        /// Result file (coilscope.result/1), parameter file or embedded driver name.
        result: String,
        /// The unit's protection model (JSON, coilscope.protection/1): its whole parameter set,
        /// creep as a bank of springs, the excursion limit (IEC 62458: the smallest of XBl, XC,
        /// XL), the temperature limit (--t-limit) and the calibration record (Re at
        /// --measured-at, alpha, Re at 20 and 25 C, --unit-id).
        #[arg(long)]
        protection: bool,
        /// --protection: the unit's id (serial number) in its calibration record; default the
        /// set's name.
        #[arg(long)]
        unit_id: Option<String>,
        /// --protection: the unit's temperature (degrees C) when its Re was measured.
        #[arg(long, default_value_t = 25.0)]
        measured_at: f64,
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
        /// --protection and speakersafetyd: the coil's absolute temperature limit (degrees C).
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
    /// End-of-line test of a production line: learn limits from golden units, test a unit
    /// against them (exit 4 when it fails), or a lot's capability (Cpk).
    Qc {
        #[command(subcommand)]
        action: QcAction,
    },
    /// List the runs of a run database (DIR/run.sqlite, or a fleet's PostgreSQL server), with
    /// their status: a run whose writer was killed is marked `killed`.
    Runs {
        /// The database: a measurement directory (its run.sqlite), a SQLite file, or a
        /// `postgres://user@host/database` URL.
        database: String,
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
        /// Multitone band (Hz): `LO HI` or `LO,HI`.
        #[arg(long, num_args = 1..=2, value_names = ["LO", "HI"])]
        band: Option<Vec<String>>,
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
        /// Run database with the measurement's time series (default: run.sqlite beside the
        /// result): a SQLite file or a `postgres://` URL.
        #[arg(long, value_name = "FILE|URL")]
        db: Option<String>,
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

pub(crate) struct SimulateArgs {
    pub(crate) world: World,
    pub(crate) driver: String,
    pub(crate) excitation: ExcitationKind,
    pub(crate) volts: Option<f64>,
    pub(crate) seconds: f64,
    pub(crate) out: PathBuf,
    pub(crate) laser: bool,
    pub(crate) snr_db: Option<f64>,
    pub(crate) seed: u64,
    pub(crate) rate: u32,
    pub(crate) input: Option<PathBuf>,
    pub(crate) freq: f64,
    pub(crate) band: Option<Vec<String>>,
    pub(crate) crest: Option<f64>,
    pub(crate) tones: usize,
    pub(crate) fade: f64,
    pub(crate) scale: Option<f64>,
    pub(crate) chain: Option<PathBuf>,
    pub(crate) wiring: SenseWiring,
    pub(crate) enclosure: Option<PathBuf>,
}

/// `linear`'s arguments.
pub(crate) struct LinearArgs {
    pub(crate) enclosure: Option<String>,
    pub(crate) driver: Option<String>,
    pub(crate) sp: Option<f64>,
    pub(crate) recording: Option<PathBuf>,
    pub(crate) impedance: Option<PathBuf>,
    pub(crate) mms: Option<Mass>,
    pub(crate) added_mass: Option<Mass>,
    pub(crate) with_mass: Option<PathBuf>,
    pub(crate) with_mass_impedance: Option<PathBuf>,
    pub(crate) band: Option<Vec<String>>,
    pub(crate) volts: Option<f64>,
    pub(crate) effects: String,
    pub(crate) fit: FitArgs,
}

/// A sound card as the device (`measure --card`); the calibration turns full scale into
/// volts and amperes. Needs a build with `--features soundcard`.
#[derive(clap::Args, Debug)]
pub(crate) struct CardArgs {
    /// Measure a real transducer through a sound card (output -> amplifier -> driver; inputs:
    /// terminal voltage and the voltage across a sense resistor).
    #[arg(long)]
    pub(crate) card: bool,
    /// Output device (as `coilscope devices` lists it); default: the system's default.
    #[arg(long, value_name = "NAME", requires = "card")]
    pub(crate) card_out: Option<String>,
    /// Input device; default: the system's default.
    #[arg(long, value_name = "NAME", requires = "card")]
    pub(crate) card_in: Option<String>,
    /// Output channel that drives the amplifier (0-based), of --out-channels.
    #[arg(long, default_value_t = 0)]
    pub(crate) drive_channel: usize,
    /// Number of output channels the output device is opened with.
    #[arg(long, default_value_t = 2)]
    pub(crate) out_channels: u16,
    /// Input channel holding the voltage (0-based, of --in-channels): across the driver's
    /// terminals, or across driver and shunt (--sense-wiring).
    #[arg(long, default_value_t = 0)]
    pub(crate) u_channel: usize,
    /// Input channel holding the sense-resistor voltage (the current), 0-based.
    #[arg(long, default_value_t = 1)]
    pub(crate) i_channel: usize,
    /// Number of input channels the input device is opened with.
    #[arg(long, default_value_t = 2)]
    pub(crate) in_channels: u16,
    /// Volts at the driver's terminals for a full-scale output sample (amplifier gain included).
    #[arg(long, default_value_t = 10.0, value_name = "V")]
    pub(crate) out_volts_fs: f64,
    /// Volts at the terminals for a full-scale sample on the voltage input (divider included).
    #[arg(long, default_value_t = 10.0, value_name = "V")]
    pub(crate) u_volts_fs: f64,
    /// Volts across the sense resistor for a full-scale sample on the current input.
    #[arg(long, default_value_t = 1.0, value_name = "V")]
    pub(crate) i_volts_fs: f64,
    /// The sense resistor (ohm).
    #[arg(long, default_value_t = 0.1, value_name = "OHM")]
    pub(crate) sense_ohm: f64,
    /// The card's calibration (a chain file from `coilscope calibrate`): its delay, AC
    /// coupling and gain are corrected block by block, the offsets found in a 0.5 s silent
    /// lead-in. With `measure --virtual` the virtual driver is recorded through a simulated
    /// card with this chain (its offsets and hum too) and measured through the correction;
    /// `quasistatic` takes it with `--card` only.
    #[arg(long, value_name = "FILE")]
    pub(crate) chain: Option<PathBuf>,
    /// Where the voltage input is connected: `terminals` (across the driver alone: preferred)
    /// or `driver+shunt` (across driver and --sense-ohm in series: its drop is taken out).
    /// Default: the chain file's, else `terminals`.
    #[arg(long, value_name = "WIRING")]
    pub(crate) sense_wiring: Option<String>,
}

impl CardArgs {
    /// The card's chain file (as given) and the wiring, when there is something to correct:
    /// a `--chain`, or a wiring other than `terminals` (measure --card and quasistatic --card
    /// alike).
    pub(crate) fn correction(&self) -> Result<Option<(coilscope_core::chain::Chain, SenseWiring)>, String> {
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

pub(crate) struct MeasureArgs {
    pub(crate) no_report: bool,
    pub(crate) db: Option<String>,
    pub(crate) virtual_driver: Option<String>,
    pub(crate) world: World,
    pub(crate) card: CardArgs,
    pub(crate) replay: Option<PathBuf>,
    pub(crate) out: PathBuf,
    pub(crate) mms: Option<Mass>,
    pub(crate) sd: Option<f64>,
    pub(crate) target_x: Option<f64>,
    pub(crate) max_dt: f64,
    pub(crate) kms_limit: f64,
    pub(crate) max_volts: f64,
    pub(crate) start_volts: f64,
    pub(crate) music: Option<PathBuf>,
    pub(crate) duration: Option<f64>,
    pub(crate) cool: Option<(f64, f64)>,
    pub(crate) volts: Option<f64>,
    pub(crate) max_seconds: f64,
    pub(crate) order: usize,
    pub(crate) noise: Vec<f64>,
    pub(crate) rate: u32,
    pub(crate) seed: u64,
    pub(crate) crest: Option<f64>,
    pub(crate) serve: ServeArgs,
}

/// `measure --serve`: the live page (`coilscope_live`), an observer of the run.
#[derive(clap::Args, Debug, Clone)]
pub(crate) struct ServeArgs {
    /// Serve a live page of the measurement at ADDR (IP:PORT; without a value 127.0.0.1:8640;
    /// port 0 picks a free one): traces of u, i, x, v, the temperature, the curves with their
    /// bands as they converge, the level, protection and convergence state, the live
    /// distortion, and the report's link at the end. It only watches: nothing on the page
    /// changes the run. Embedded page, no network needed.
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = coilscope_live::DEFAULT_ADDR)]
    pub(crate) serve: Option<String>,
    /// Allow --serve on an address other than loopback (anyone who reaches it sees the run).
    #[arg(long, requires = "serve")]
    pub(crate) serve_public: bool,
    /// After the run, keep serving the page and the report it links for this many seconds
    /// (Ctrl-C ends it sooner).
    #[arg(long, value_name = "S", default_value_t = 300.0)]
    pub(crate) serve_linger: f64,
    /// Play a virtual or replayed run at FACTOR times real time (1: as a sound card would).
    /// Default: as fast as the computer can; 1 with --serve, so that the page is watchable.
    #[arg(long, value_name = "FACTOR")]
    pub(crate) pace: Option<f64>,
}

pub(crate) struct DistortionArgs {
    pub(crate) params: String,
    pub(crate) freq: Option<f64>,
    pub(crate) freq2: Option<f64>,
    pub(crate) ratio: f64,
    pub(crate) volts: Option<f64>,
    pub(crate) output: coilscope_analysis::distortion::Output,
    pub(crate) multitone: bool,
    pub(crate) band: Option<Vec<String>>,
    pub(crate) tones: usize,
    pub(crate) sweep: Option<Vec<f64>>,
    pub(crate) levels: Option<Vec<f64>>,
    pub(crate) temp_rise: f64,
    pub(crate) json: bool,
    pub(crate) seed: u64,
}

/// `quasistatic`: the point-by-point measurement on a virtual driver.
#[allow(clippy::too_many_arguments)]
pub(crate) struct QuasiArgs {
    pub(crate) driver: Option<String>,
    pub(crate) out: PathBuf,
    pub(crate) points: usize,
    pub(crate) reach: f64,
    pub(crate) hold: f64,
    pub(crate) order: usize,
    pub(crate) world: World,
    pub(crate) offset: String,
    pub(crate) mms: Option<f64>,
    pub(crate) xmax: Option<f64>,
    pub(crate) sd: Option<f64>,
    pub(crate) ac_volts: f64,
    pub(crate) rate: u32,
    pub(crate) card: CardArgs,
}

/// A `--band` in Hz, given as two values (`LO HI`) or one (`LO,HI`; `LO:HI` too), with
/// `0 <= LO < HI`.
pub(crate) fn parse_band(given: &[String]) -> Result<[f64; 2], String> {
    let text = given.join(",");
    let bad =
        || format!("--band {}: give LO HI (or LO,HI) in Hz with 0 <= LO < HI, e.g. --band 10 2000", given.join(" "));
    let v: Vec<f64> = text
        .split([',', ':'])
        .filter(|t| !t.trim().is_empty())
        .map(|t| t.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| bad())?;
    match v[..] {
        [lo, hi] if lo >= 0.0 && hi > lo && hi.is_finite() => Ok([lo, hi]),
        _ => Err(bad()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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

    #[test]
    fn a_band_is_two_values_or_one_with_a_comma() {
        let band = |v: &[&str]| parse_band(&v.iter().map(|s| s.to_string()).collect::<Vec<_>>());
        assert_eq!(band(&["10", "2000"]), Ok([10.0, 2000.0]));
        assert_eq!(band(&["10,2000"]), Ok([10.0, 2000.0]));
        assert_eq!(band(&["10:2000"]), Ok([10.0, 2000.0]));
        for bad in [&["10"][..], &["2000", "10"], &["10,20,30"], &["a,b"], &["-5", "10"], &["10", "inf"]] {
            let e = band(bad).unwrap_err();
            assert!(e.contains("LO HI (or LO,HI)") && e.contains(&bad.join(" ")), "{bad:?}: {e}");
        }
    }
}

/// What `qc` does.
#[derive(Subcommand)]
pub(crate) enum QcAction {
    /// Learn a line's limits from its golden units' results (or parameter sets): per figure
    /// (Re, fs, Qts, Qms, Rms, Bl(0), Kms(0), Le(0), the Bl and Kms symmetry points, Xmax)
    /// mean +- k sd. Edit the file to set limits by hand.
    Learn {
        /// The golden units' results (at least 5; 30 or more make limits that hold).
        #[arg(required = true, num_args = 1..)]
        results: Vec<String>,
        /// The limits' width in the golden units' sds.
        #[arg(long, default_value_t = 3.0)]
        k: f64,
        /// The limits file to write (JSON, coilscope.qc-limits/1).
        #[arg(long)]
        out: PathBuf,
    },
    /// Test a unit's result against the limits: pass (exit 0), or fail (exit 4) naming each
    /// figure outside, by how much and what it likely means, with the coil's offset where Bl's
    /// symmetry point is off.
    Test {
        /// The units' results (identify or measure), parameter sets or short records (`.wav`,
        /// with --mms): one, or a lot (a station's), each judged and, with --db, written as
        /// it is judged.
        #[arg(required = true, num_args = 1..)]
        results: Vec<String>,
        /// The line's limits (`qc learn`).
        #[arg(long)]
        limits: PathBuf,
        /// Also write the verdict (JSON; one unit only).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Write every unit's set and verdict to this run database, as the station's run: a
        /// SQLite file, or a `postgres://user@host/database` URL that every station of a line
        /// writes to.
        #[arg(long, value_name = "FILE|URL")]
        db: Option<String>,
        /// The station's name in the database.
        #[arg(long, default_value = "station", requires = "db")]
        station: String,
        /// The unit's id (one unit only; default: the file's name without `.json` or `.wav`).
        #[arg(long)]
        unit_id: Option<String>,
        /// For units given as records (`.wav`: voltage and current, as `identify` reads
        /// them): the moving mass (kg), the scale of every mechanical figure; each record is
        /// identified as `identify` does, then judged.
        #[arg(long)]
        mms: Option<f64>,
        /// For records: the effects searched (as `identify --effects`; `none` is fastest on
        /// a line whose golden units showed none).
        #[arg(long, default_value = "auto")]
        effects: String,
        /// For records: the measurement chain (as `identify --chain`).
        #[arg(long, default_value = "detect")]
        chain: String,
        /// For records: worker threads per record (0: every core).
        #[arg(long, default_value_t = 0)]
        threads: usize,
    },
    /// A lot's capability against the limits: per figure its mean, sd, Cpk and the units
    /// outside.
    Stats {
        /// The lot's results (or give --db).
        #[arg(required_unless_present = "db", conflicts_with = "db", num_args = 1..)]
        results: Vec<String>,
        /// The line's limits (`qc learn`).
        #[arg(long)]
        limits: PathBuf,
        /// Also write the table (JSON).
        #[arg(long)]
        out: Option<PathBuf>,
        /// The lot from a run database (`qc test --db`): every unit tested, or one station
        /// run's (--run).
        #[arg(long, value_name = "FILE|URL")]
        db: Option<String>,
        /// With --db: the station run whose units are the lot (`coilscope runs` lists them).
        #[arg(long, requires = "db")]
        run: Option<i64>,
        /// Also write the lot's page (HTML): per figure its histogram against the limits and
        /// its control chart, with Cpk; PNG and CSV in `<stem>_files/`.
        #[arg(long, value_name = "HTML")]
        report: Option<PathBuf>,
    },
    /// A unit's history from a run database: its figures at every test, and how far each
    /// drifted from its first test, in the limits' sds.
    History {
        /// The unit's id.
        unit: String,
        /// The run database (`qc test --db`).
        #[arg(long, value_name = "FILE|URL")]
        db: String,
        /// The line's limits (their amplitude and sds).
        #[arg(long)]
        limits: PathBuf,
        /// Also write the history (JSON).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Also write the unit's page (HTML): each figure at every test over time, against
        /// the limits; PNG and CSV in `<stem>_files/`.
        #[arg(long, value_name = "HTML")]
        report: Option<PathBuf>,
    },
}

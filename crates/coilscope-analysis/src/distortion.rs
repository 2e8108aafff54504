//! Distortion of the full nonlinear model by simulation to the periodic steady state.
//!
//! Every excitation here is periodic in a window of `T` seconds: each tone has an integer
//! number of cycles in `T` (it sits on FFT bin `k`, at `k / T` Hz). The model is integrated
//! window after window from rest until two consecutive windows agree (every spectral line of
//! x and i changes by less than `tol` of the largest line); the last window is then exactly
//! one period of the steady state and its FFT has no leakage and needs no window function.
//!
//! The model is the whole one ([`Plant`]): creep's Maxwell bank and the LR-3 branch are
//! integrated with the six states. Creep's slowest damper relaxes in seconds; after each
//! window its dampers are put on the periodic orbit the window's excursion leads to
//! ([`Plant::settle_creep_to_period`]), so the steady state still takes a few windows.
//!
//! The input is not interpolated: the tone sum is synthesised once, by an inverse FFT, on the
//! fine grid the RK4 sub-steps use (`2 n_sub` points per sample), so the integrator sees the
//! exact periodic voltage.
//!
//! Phasors are peak amplitudes: a line `A cos(2 pi k t / T + phi)` reads `A e^{j phi}`.
//!
//! Each nonlinearity's contribution is the distortion of the model with only that
//! nonlinearity left x-dependent ([`with_only`]); for small distortion the complex lines of the
//! three parts add up to the line of the full model (the cross terms are of higher order).

use crate::AnalysisError;
use coilscope_core::excitation::named_rng;
use coilscope_core::fft::{irfft, rfft};
use coilscope_core::integrate::Stepper;
use coilscope_core::model::{idx, NSTATE};
use coilscope_core::simulate::Plant;
use coilscope_core::{Parameters, Poly};
use rand::Rng;
use realfft::num_complex::Complex64 as C;
use serde_json::{json, Value};
use std::f64::consts::{PI, SQRT_2};

/// The signal the distortion is measured in.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Output {
    /// Far-field sound pressure, proportional to the cone acceleration dv/dt.
    Pressure,
    /// Voice-coil displacement x.
    Displacement,
    /// Terminal current i.
    Current,
}

impl Output {
    pub fn name(self) -> &'static str {
        match self {
            Output::Pressure => "sound pressure (cone acceleration)",
            Output::Displacement => "displacement",
            Output::Current => "current",
        }
    }
    pub fn key(self) -> &'static str {
        match self {
            Output::Pressure => "pressure",
            Output::Displacement => "displacement",
            Output::Current => "current",
        }
    }
}

/// One of the three nonlinearities of the model.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Nonlinearity {
    /// Force factor Bl(x): parametric excitation and back EMF.
    Bl,
    /// Stiffness Kms(x).
    Kms,
    /// Inductance Le(x), with L2(x), R2(x) and the reluctance forces.
    Le,
}

impl Nonlinearity {
    pub const ALL: [Nonlinearity; 3] = [Nonlinearity::Bl, Nonlinearity::Kms, Nonlinearity::Le];
    pub fn name(self) -> &'static str {
        match self {
            Nonlinearity::Bl => "Bl(x)",
            Nonlinearity::Kms => "Kms(x)",
            Nonlinearity::Le => "Le(x)",
        }
    }
    pub fn key(self) -> &'static str {
        match self {
            Nonlinearity::Bl => "Bl",
            Nonlinearity::Kms => "Kms",
            Nonlinearity::Le => "Le",
        }
    }
}

fn constant_at_rest(f: &Poly) -> Poly {
    Poly::constant(f.c[0])
}

/// The set `p` with only the nonlinearities in `keep` left x-dependent (the others frozen at
/// their rest value), no thermal model, and Re at a voice-coil rise of `dt_coil` kelvin.
pub fn with_only(p: &Parameters, keep: &[Nonlinearity], dt_coil: f64) -> Parameters {
    let mut q = p.clone();
    if let Some(t) = &p.thermal {
        q.re = p.re * (1.0 + t.alpha * dt_coil);
    }
    q.thermal = None;
    if !keep.contains(&Nonlinearity::Bl) {
        q.bl = constant_at_rest(&p.bl);
    }
    if !keep.contains(&Nonlinearity::Kms) {
        q.kms = constant_at_rest(&p.kms);
    }
    if !keep.contains(&Nonlinearity::Le) {
        q.le = constant_at_rest(&p.le);
        q.l2r2 = p.l2r2.as_ref().map(|(l2, r2)| (constant_at_rest(l2), constant_at_rest(r2)));
    }
    q
}

/// A tone on bin `bin` of the window: `amplitude cos(2 pi bin t / T + phase)` volts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Tone {
    pub bin: usize,
    /// Peak voltage (V).
    pub amplitude: f64,
    pub phase: f64,
}

/// A periodic excitation: tones on the bins of a window of `period` seconds.
#[derive(Clone, Debug, PartialEq)]
pub struct Periodic {
    pub period: f64,
    pub tones: Vec<Tone>,
}

/// Options of the steady-state search.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SteadyOptions {
    /// The lowest simulation rate (Hz); raised to keep `harmonics` harmonics of the highest
    /// tone below 0.4 of the rate.
    pub min_fs: f64,
    /// Harmonic orders that must stay below 0.4 fs.
    pub harmonics: usize,
    /// Convergence: the largest change of a line between windows, relative to the largest line.
    pub tol: f64,
    /// Give up after this much simulated time (s).
    pub max_seconds: f64,
    /// Voice-coil temperature rise (K) at which Re is taken.
    pub dt_coil: f64,
}

impl Default for SteadyOptions {
    fn default() -> Self {
        SteadyOptions { min_fs: 48_000.0, harmonics: 10, tol: 1e-8, max_seconds: 30.0, dt_coil: 0.0 }
    }
}

/// One period of the steady state, as spectra (peak phasors per bin, DC as the mean).
#[derive(Clone, Debug)]
pub struct Response {
    pub period: f64,
    pub fs: f64,
    /// Samples per period.
    pub n: usize,
    pub x: Vec<C>,
    pub i: Vec<C>,
    /// Cone acceleration dv/dt.
    pub a: Vec<C>,
    /// Smallest and largest displacement in the period (m).
    pub x_peak: [f64; 2],
    /// Simulated time until the steady state (s).
    pub seconds: f64,
}

impl Response {
    /// The line of `out` at `bin`.
    pub fn line(&self, out: Output, bin: usize) -> C {
        let s = match out {
            Output::Pressure => &self.a,
            Output::Displacement => &self.x,
            Output::Current => &self.i,
        };
        s.get(bin).copied().unwrap_or(C::new(0.0, 0.0))
    }
    /// Frequency of a bin (Hz).
    pub fn freq(&self, bin: usize) -> f64 {
        bin as f64 / self.period
    }
    /// Mean displacement (m).
    pub fn x_dc(&self) -> f64 {
        self.x[0].re
    }
    /// The highest bin that is analysed (below 0.4 fs).
    pub fn max_bin(&self) -> usize {
        ((0.4 * self.fs * self.period).floor() as usize).min(self.x.len() - 1)
    }
}

fn check_periodic(p: &Parameters, exc: &Periodic) -> Result<(), AnalysisError> {
    if !(exc.period.is_finite() && exc.period > 0.0 && exc.period <= 10.0) {
        return Err(AnalysisError::Input(format!("the period {} s is not valid (0 .. 10 s)", exc.period)));
    }
    if exc.tones.is_empty() {
        return Err(AnalysisError::Input("the excitation has no tones".into()));
    }
    for t in &exc.tones {
        if t.bin == 0
            || !(t.amplitude.is_finite() && t.amplitude >= 0.0 && t.amplitude <= 1000.0)
            || !t.phase.is_finite()
        {
            return Err(AnalysisError::Input(format!(
                "tone on bin {} with amplitude {} V is not valid (bin >= 1, 0 .. 1000 V peak)",
                t.bin, t.amplitude
            )));
        }
    }
    p.validate("distortion").map_err(|e| AnalysisError::Input(e.to_string()))
}

/// Integrate `p` under the periodic excitation until the periodic steady state.
pub fn steady_state(p: &Parameters, exc: &Periodic, opts: &SteadyOptions) -> Result<Response, AnalysisError> {
    run_steady(&with_only(p, &Nonlinearity::ALL, opts.dt_coil), exc, opts)
}

/// The steady state of a set that is already prepared (thermal off).
fn run_steady(q: &Parameters, exc: &Periodic, opts: &SteadyOptions) -> Result<Response, AnalysisError> {
    check_periodic(q, exc)?;
    let t = exc.period;
    let k_max = exc.tones.iter().map(|t| t.bin).max().unwrap_or(1);
    let f_max = k_max as f64 / t;
    let fs_target = opts.min_fs.max(opts.harmonics.max(1) as f64 * f_max / 0.4);
    let n = (fs_target * t).ceil() as usize;
    let fs = n as f64 / t;
    if n > 4_000_000 {
        return Err(AnalysisError::Input(format!(
            "a period of {t} s at {fs:.0} Hz is too long ({n} samples); use shorter periods or lower tones"
        )));
    }
    let stepper = Stepper::for_rates(q.rates(), fs);
    // The input at the stepper's points ([`Stepper::points`]): `per` intervals per sample.
    let per = stepper.points() - 1;
    let fine = per * n;
    let mut spec = vec![C::new(0.0, 0.0); fine / 2 + 1];
    for tone in &exc.tones {
        if tone.bin >= n / 2 {
            return Err(AnalysisError::Input(format!(
                "tone at {:.1} Hz is above the analysis band",
                tone.bin as f64 / t
            )));
        }
        spec[tone.bin] += C::from_polar(0.5 * tone.amplitude, tone.phase);
    }
    let mut u = irfft(&spec, fine);
    u.push(u[0]);
    // The whole model: the six states and, where the set has them, creep's and LR-3's.
    let mut plant = Plant::new(q);
    let dt = 1.0 / fs;
    let bounds = q.x_range.map(|[lo, hi]| [lo * 1.1, hi * 1.1]);
    let mut s = [0.0f64; NSTATE];
    let (mut xs, mut is, mut acc) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
    let mut prev: Option<(Vec<C>, Vec<C>)> = None;
    let mut windows = 0usize;
    let max_windows = ((opts.max_seconds / t).ceil() as usize).max(3);
    let mut change = f64::INFINITY;
    loop {
        let window_start = plant.ext_state();
        for m in 0..n {
            let up = &u[per * m..=per * (m + 1)];
            let x = s[idx::X];
            if s.iter().any(|v| !v.is_finite()) {
                return Err(AnalysisError::Range("the integration diverged (the state is no longer finite)".into()));
            }
            if let Some([lo, hi]) = bounds {
                if x < lo || x > hi {
                    return Err(AnalysisError::Range(format!("x = {:.3} mm is outside x_range [{:.3}, {:.3}] mm + 10 %, where the parameters are not valid; lower the level", x * 1e3, lo / 1.1 * 1e3, hi / 1.1 * 1e3)));
                }
            }
            xs[m] = x;
            is[m] = s[idx::I];
            acc[m] = plant.deriv(&s, up[0])[idx::V];
            plant.step(&stepper, &mut s, dt, up);
        }
        windows += 1;
        if let Some(start) = &window_start {
            plant.settle_creep_to_period(start, t);
        }
        let (fx, fi) = (rfft(&xs), rfft(&is));
        if let Some((px, pi)) = &prev {
            let rel = |a: &[C], b: &[C]| {
                let top = a.iter().map(|c| c.norm()).fold(0.0, f64::max).max(1e-300);
                a.iter().zip(b).map(|(a, b)| (a - b).norm()).fold(0.0, f64::max) / top
            };
            change = rel(&fx, px).max(rel(&fi, pi));
            if change <= opts.tol && windows as f64 * t >= 0.05 {
                let scale = |mut v: Vec<C>| {
                    let nn = n as f64;
                    v[0] /= nn;
                    for c in v.iter_mut().skip(1) {
                        *c *= 2.0 / nn;
                    }
                    v
                };
                let x_peak = [
                    xs.iter().copied().fold(f64::INFINITY, f64::min),
                    xs.iter().copied().fold(f64::NEG_INFINITY, f64::max),
                ];
                return Ok(Response {
                    period: t,
                    fs,
                    n,
                    x: scale(fx),
                    i: scale(fi),
                    a: scale(rfft(&acc)),
                    x_peak,
                    seconds: windows as f64 * t,
                });
            }
        }
        if windows >= max_windows {
            return Err(AnalysisError::NotSteady { seconds: windows as f64 * t, change });
        }
        prev = Some((fx, fi));
    }
}

fn check_level(volts: f64) -> Result<(), AnalysisError> {
    if !(volts.is_finite() && volts > 0.0 && volts <= 500.0) {
        return Err(AnalysisError::Input(format!("--volts {volts} is not valid: give the RMS voltage, 0 .. 500 V")));
    }
    Ok(())
}

fn check_freq(name: &str, f: f64) -> Result<(), AnalysisError> {
    if !(f.is_finite() && (1.0..=20_000.0).contains(&f)) {
        return Err(AnalysisError::Input(format!("{name} {f} Hz is not valid (1 .. 20000 Hz)")));
    }
    Ok(())
}

/// A sine's harmonic distortion.
#[derive(Clone, Debug)]
pub struct Harmonics {
    pub freq: f64,
    /// RMS volts.
    pub volts: f64,
    pub output: Output,
    /// The fundamental line of the output (its unit: m/s^2, m or A, peak).
    pub fundamental: C,
    /// `(order, line / fundamental)` for orders 2, 3, ... below 0.4 fs.
    pub lines: Vec<(usize, C)>,
    /// Mean displacement (m).
    pub x_dc: f64,
    /// Smallest and largest displacement (m).
    pub x_peak: [f64; 2],
}

impl Harmonics {
    /// The ratio of harmonic `order` to the fundamental (complex).
    pub fn ratio(&self, order: usize) -> C {
        self.lines.iter().find(|(h, _)| *h == order).map(|l| l.1).unwrap_or(C::new(0.0, 0.0))
    }
    pub fn hd(&self, order: usize) -> f64 {
        self.ratio(order).norm()
    }
    /// Total harmonic distortion `sqrt(sum_n |P_n|^2) / |P_1|` over the analysed orders.
    pub fn thd(&self) -> f64 {
        self.lines.iter().map(|(_, c)| c.norm_sqr()).sum::<f64>().sqrt()
    }
    pub fn to_json(&self) -> Value {
        json!({
            "freq": self.freq, "volts_rms": self.volts, "output": self.output.key(),
            "HD2": self.hd(2), "HD3": self.hd(3), "THD": self.thd(),
            "HD2_dB": crate::db(self.hd(2)), "HD3_dB": crate::db(self.hd(3)), "THD_dB": crate::db(self.thd()),
            "harmonics": self.lines.iter().map(|(h, c)| json!({"order": h, "ratio": c.norm(), "dB": crate::db(c.norm()), "phase": c.arg()})).collect::<Vec<_>>(),
            "x_dc": self.x_dc, "x_peak": self.x_peak,
        })
    }
}

/// The window for a sine: whole periods, at least `min_seconds`.
fn sine_window(freq: f64, min_seconds: f64) -> (f64, usize) {
    let m = (freq * min_seconds).ceil().max(1.0) as usize;
    (m as f64 / freq, m)
}

fn sine_harmonics(
    q: &Parameters,
    freq: f64,
    volts: f64,
    output: Output,
    opts: &SteadyOptions,
) -> Result<Harmonics, AnalysisError> {
    let (period, bin) = sine_window(freq, 0.05);
    let exc = Periodic { period, tones: vec![Tone { bin, amplitude: volts * SQRT_2, phase: 0.0 }] };
    let r = run_steady(q, &exc, opts)?;
    let fund = r.line(output, bin);
    let lines = (2..=opts.harmonics.max(2))
        .map(|h| h * bin)
        .take_while(|&b| b <= r.max_bin())
        .map(|b| (b / bin, r.line(output, b) / fund))
        .collect();
    Ok(Harmonics { freq, volts, output, fundamental: fund, lines, x_dc: r.x_dc(), x_peak: r.x_peak })
}

/// Harmonic distortion of a sine of `volts` RMS at `freq` with every nonlinearity.
pub fn harmonics(
    p: &Parameters,
    freq: f64,
    volts: f64,
    output: Output,
    opts: &SteadyOptions,
) -> Result<Harmonics, AnalysisError> {
    check_freq("--freq", freq)?;
    check_level(volts)?;
    sine_harmonics(&with_only(p, &Nonlinearity::ALL, opts.dt_coil), freq, volts, output, opts)
}

/// The full model's distortion and each nonlinearity's, alone.
#[derive(Clone, Debug)]
pub struct Analysis {
    pub total: Harmonics,
    pub parts: Vec<(Nonlinearity, Harmonics)>,
}

impl Analysis {
    /// `|sum of the parts' lines - total line| / |total line|` for harmonic `order`.
    pub fn sum_mismatch(&self, order: usize) -> f64 {
        let sum: C = self.parts.iter().map(|(_, h)| h.ratio(order)).sum();
        (sum - self.total.ratio(order)).norm() / self.total.hd(order).max(1e-300)
    }
    /// The nonlinearity with the largest harmonic power alone.
    pub fn dominant(&self) -> Nonlinearity {
        self.parts.iter().max_by(|a, b| a.1.thd().total_cmp(&b.1.thd())).map(|p| p.0).unwrap_or(Nonlinearity::Kms)
    }
    pub fn to_json(&self) -> Value {
        let mut total = self.total.to_json();
        total["contributions"] = self
            .parts
            .iter()
            .map(|(nl, h)| {
                let mut o = h.to_json();
                o["nonlinearity"] = nl.name().into();
                (nl.key().to_string(), o)
            })
            .collect::<serde_json::Map<_, _>>()
            .into();
        total["dominant"] = self.dominant().name().into();
        total["contributions_sum_mismatch"] = json!({"HD2": self.sum_mismatch(2), "HD3": self.sum_mismatch(3)});
        total
    }
}

/// Harmonic distortion of a sine, total and per nonlinearity.
pub fn analyse(
    p: &Parameters,
    freq: f64,
    volts: f64,
    output: Output,
    opts: &SteadyOptions,
) -> Result<Analysis, AnalysisError> {
    let total = harmonics(p, freq, volts, output, opts)?;
    let parts = Nonlinearity::ALL
        .iter()
        .map(|&nl| sine_harmonics(&with_only(p, &[nl], opts.dt_coil), freq, volts, output, opts).map(|h| (nl, h)))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Analysis { total, parts })
}

/// Two-tone intermodulation (IEC 60268-5): `f1` low, `f2` high.
#[derive(Clone, Debug)]
pub struct Intermod {
    pub f1: f64,
    /// The high tone as analysed (on the window's bin grid).
    pub f2: f64,
    pub volts: f64,
    /// Amplitude of f2 over amplitude of f1.
    pub amplitude_ratio: f64,
    pub output: Output,
    /// Second-order IMD `(|P(f2-f1)| + |P(f2+f1)|) / |P(f2)|`.
    pub d2: f64,
    /// Third-order IMD `(|P(f2-2f1)| + |P(f2+2f1)|) / |P(f2)|`.
    pub d3: f64,
    /// `(label, frequency, |line| / |P(f2)|)`.
    pub lines: Vec<(String, f64, f64)>,
    pub x_dc: f64,
    pub x_peak: [f64; 2],
}

impl Intermod {
    pub fn to_json(&self) -> Value {
        json!({
            "f1": self.f1, "f2": self.f2, "volts_rms": self.volts, "amplitude_ratio_f2_f1": self.amplitude_ratio,
            "output": self.output.key(), "d2": self.d2, "d3": self.d3,
            "d2_dB": crate::db(self.d2), "d3_dB": crate::db(self.d3),
            "lines": self.lines.iter().map(|(l, f, r)| json!({"label": l, "freq": f, "ratio": r, "dB": crate::db(*r)})).collect::<Vec<_>>(),
            "x_dc": self.x_dc, "x_peak": self.x_peak,
        })
    }
}

/// Intermodulation of a two-tone of `volts` RMS in total, `f2`'s amplitude `ratio` times `f1`'s.
pub fn intermod(
    p: &Parameters,
    f1: f64,
    f2: f64,
    volts: f64,
    ratio: f64,
    output: Output,
    opts: &SteadyOptions,
) -> Result<Intermod, AnalysisError> {
    check_freq("--freq", f1)?;
    check_freq("--freq2", f2)?;
    check_level(volts)?;
    if !(ratio.is_finite() && ratio > 0.0 && ratio <= 10.0) {
        return Err(AnalysisError::Input(format!("the amplitude ratio {ratio} is not valid (0 .. 10)")));
    }
    if f2 < 3.0 * f1 {
        return Err(AnalysisError::Input(format!(
            "--freq2 {f2} Hz must be at least 3 times --freq {f1} Hz (IEC 60268-5: f1 low, f2 high)"
        )));
    }
    let (period, k1) = sine_window(f1, 0.2);
    let k2 = (f2 * period).round() as usize;
    let products = [k2 - 2 * k1, k2 - k1, k2 + k1, k2 + 2 * k1];
    let others: Vec<usize> = (1..=6).map(|h| h * k1).chain([k2, 2 * k2]).collect();
    if products.iter().any(|b| others.contains(b)) {
        return Err(AnalysisError::Input(format!(
            "--freq2 {f2} Hz puts intermodulation lines on harmonics of --freq {f1} Hz; move f2 off a multiple of f1"
        )));
    }
    // Total RMS `volts`: A1^2 (1 + ratio^2) / 2 = volts^2.
    let a1 = volts * (2.0 / (1.0 + ratio * ratio)).sqrt();
    let exc = Periodic {
        period,
        tones: vec![Tone { bin: k1, amplitude: a1, phase: 0.0 }, Tone { bin: k2, amplitude: a1 * ratio, phase: 0.0 }],
    };
    let q = with_only(p, &Nonlinearity::ALL, opts.dt_coil);
    let r = run_steady(&q, &exc, opts)?;
    let ref2 = r.line(output, k2).norm();
    let lev = |b: usize| r.line(output, b).norm() / ref2;
    let labels = ["f2-2f1", "f2-f1", "f2+f1", "f2+2f1"];
    let lines = labels.iter().zip(products).map(|(l, b)| (l.to_string(), r.freq(b), lev(b))).collect();
    Ok(Intermod {
        f1,
        f2: r.freq(k2),
        volts,
        amplitude_ratio: ratio,
        output,
        d2: lev(products[1]) + lev(products[2]),
        d3: lev(products[0]) + lev(products[3]),
        lines,
        x_dc: r.x_dc(),
        x_peak: r.x_peak,
    })
}

/// A multitone's distortion spectrum.
#[derive(Clone, Debug)]
pub struct MultitoneResult {
    pub volts: f64,
    pub output: Output,
    /// Tone frequencies (Hz) and their output lines (peak).
    pub tones: Vec<(f64, f64)>,
    /// Distortion lines: every other bin up to 20 kHz / 0.4 fs, `(Hz, peak)`.
    pub distortion: Vec<(f64, f64)>,
    /// Multitone total distortion: distortion power over tone power.
    pub mtd: f64,
    pub x_dc: f64,
    pub x_peak: [f64; 2],
}

impl MultitoneResult {
    pub fn to_json(&self) -> Value {
        json!({
            "volts_rms": self.volts, "output": self.output.key(),
            "MTD": self.mtd, "MTD_dB": crate::db(self.mtd),
            "tones": self.tones.iter().map(|(f, a)| [*f, *a]).collect::<Vec<_>>(),
            "distortion": self.distortion.iter().filter(|(_, a)| *a > 0.0).map(|(f, a)| [*f, *a]).collect::<Vec<_>>(),
            "x_dc": self.x_dc, "x_peak": self.x_peak,
            "note": "tones and distortion are [Hz, peak line in the output's unit]; MTD = sqrt(distortion power / tone power)",
        })
    }
}

/// `count` log-spaced tones from `f_lo` to `f_hi` on a 1 Hz grid with seeded random phases
/// (RNG "multitone-phase"), equal amplitudes, `volts` RMS in total.
pub fn multitone(
    p: &Parameters,
    f_lo: f64,
    f_hi: f64,
    count: usize,
    volts: f64,
    output: Output,
    seed: u64,
    opts: &SteadyOptions,
) -> Result<MultitoneResult, AnalysisError> {
    check_freq("the lowest tone", f_lo)?;
    check_freq("the highest tone", f_hi)?;
    check_level(volts)?;
    if !(f_hi > f_lo && (2..=200).contains(&count)) {
        return Err(AnalysisError::Input(format!(
            "multitone {count} tones in {f_lo} .. {f_hi} Hz is not valid (2 .. 200 tones, f_hi > f_lo)"
        )));
    }
    let period = 1.0;
    let mut bins: Vec<usize> = (0..count)
        .map(|k| (f_lo * (f_hi / f_lo).powf(k as f64 / (count - 1) as f64)).round().max(1.0) as usize)
        .collect();
    bins.dedup();
    let mut rng = named_rng(seed, "multitone-phase");
    let amp = volts * (2.0 / bins.len() as f64).sqrt();
    let tones: Vec<Tone> =
        bins.iter().map(|&bin| Tone { bin, amplitude: amp, phase: rng.random_range(0.0..2.0 * PI) }).collect();
    let exc = Periodic { period, tones };
    let q = with_only(p, &Nonlinearity::ALL, opts.dt_coil);
    let opts = SteadyOptions { harmonics: opts.harmonics.min(3), ..*opts };
    let r = run_steady(&q, &exc, &opts)?;
    let top = r.max_bin().min((20_000.0 * period) as usize);
    let mut t = Vec::new();
    let mut d = Vec::new();
    for b in 1..=top {
        let a = r.line(output, b).norm();
        if bins.contains(&b) {
            t.push((r.freq(b), a))
        } else {
            d.push((r.freq(b), a))
        }
    }
    let pt: f64 = t.iter().map(|x| x.1 * x.1).sum();
    let pd: f64 = d.iter().map(|x| x.1 * x.1).sum();
    Ok(MultitoneResult {
        volts,
        output,
        tones: t,
        distortion: d,
        mtd: (pd / pt).sqrt(),
        x_dc: r.x_dc(),
        x_peak: r.x_peak,
    })
}

/// Log-spaced frequencies, `per_octave` per octave, from `f_lo` to `f_hi` inclusive.
pub fn log_frequencies(f_lo: f64, f_hi: f64, per_octave: usize) -> Vec<f64> {
    let n = ((f_hi / f_lo).log2() * per_octave as f64).round().max(1.0) as usize;
    (0..=n).map(|k| f_lo * (f_hi / f_lo).powf(k as f64 / n as f64)).collect()
}

/// The analysis at each frequency (total and parts) at one level.
pub fn frequency_sweep(
    p: &Parameters,
    freqs: &[f64],
    volts: f64,
    output: Output,
    opts: &SteadyOptions,
) -> Result<Vec<Analysis>, AnalysisError> {
    freqs.iter().map(|&f| analyse(p, f, volts, output, opts)).collect()
}

/// The RMS sine level at which the linear model's peak displacement over `freqs` is `x_peak`:
/// a safe default level for sweeps (stiffening only lowers the real excursion).
pub fn level_for_excursion(p: &Parameters, freqs: &[f64], x_peak: f64) -> f64 {
    let h = freqs
        .iter()
        .map(|&f| {
            let z = coilscope_core::small_signal::impedance(p, f);
            (coilscope_core::small_signal::displacement_per_current(p, f) / z).norm()
        })
        .fold(0.0, f64::max);
    x_peak / (SQRT_2 * h.max(1e-300))
}

/// Full model against its Volterra approximation at one level.
#[derive(Clone, Debug)]
pub struct LevelRow {
    pub volts: f64,
    pub full: Harmonics,
    /// Volterra `(HD2, HD3)`.
    pub volterra: (f64, f64),
    pub volterra_x_dc: f64,
}

impl LevelRow {
    /// The larger of the HD2 and HD3 differences (dB), counting only lines above -100 dB.
    pub fn error_db(&self) -> f64 {
        let d = |full: f64, v: f64| if full.max(v) > 1e-5 { (crate::db(full) - crate::db(v)).abs() } else { 0.0 };
        d(self.full.hd(2), self.volterra.0).max(d(self.full.hd(3), self.volterra.1))
    }
}

/// HD2/HD3 of the full model and of the Volterra series at each level (RMS volts) of a sine.
pub fn level_sweep(
    p: &Parameters,
    freq: f64,
    levels: &[f64],
    output: Output,
    opts: &SteadyOptions,
) -> Result<Vec<LevelRow>, AnalysisError> {
    let q = with_only(p, &Nonlinearity::ALL, opts.dt_coil);
    let pr = crate::volterra::probe(&q, freq);
    levels
        .iter()
        .map(|&v| {
            harmonics(p, freq, v, output, opts).map(|full| LevelRow {
                volts: v,
                full,
                volterra: pr.hd(output, v),
                volterra_x_dc: pr.x_dc(v),
            })
        })
        .collect()
}

/// The lowest level of a sweep at which the Volterra series is off by more than `tol_db`.
pub fn divergence_level(rows: &[LevelRow], tol_db: f64) -> Option<f64> {
    rows.iter().find(|r| r.error_db() > tol_db).map(|r| r.volts)
}

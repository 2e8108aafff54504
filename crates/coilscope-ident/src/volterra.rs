//! Volterra-based identification (seed paper 3.2.2.1, Fig. 3): the distortion a transducer
//! produces is read as its second- and third-order Volterra kernels, and the nonlinear
//! parameters are fitted to those kernels.
//!
//! The measurement: sines at several frequencies, each in its steady state; of the current
//! (what the terminals give), the complex ratios of the 2nd and 3rd harmonic to the
//! fundamental. The model: the diagonal kernels of the model by harmonic probing
//! ([`coilscope_analysis::volterra::probe`]), `H2(f,f) a / H1(f)` and `H3(f,f,f) a^2 / H1(f)`
//! for a cosine of complex amplitude `a`. The kernels to the third order depend on the power
//! series only up to `x^2`: the fit gives `Bl`, `Kms`, `Le` to second order (`b1, b2, k1,
//! k2, l1, l2`), with the linear parameters (the rest values, Re, Mms, Rms, L2/R2) from the
//! small-signal fit.
//!
//! It is exact where the Volterra series is: at small amplitude. The paper's point is where
//! it fails: at large amplitude the distortion the nonlinearities produce feeds back into
//! their own generation (Bl(x) and Kms(x) change by tens of percent, the displacement's
//! harmonics move x, which moves Bl and Kms again), the series truncated after the third
//! order no longer describes the response, and the fitted coefficients absorb what the
//! truncation leaves out. `volterra_kernels.rs` tabulates the error over level.

use crate::lm::{lm_step, LmState, Problem};
use coilscope_analysis::distortion::{Harmonics, Output};
use coilscope_analysis::volterra::probe;
use coilscope_core::{Parameters, Poly};
use nalgebra::{DMatrix, DVector};
use realfft::num_complex::Complex64 as C;

/// The fitted second-order series and what the fit left.
#[derive(Clone, Debug)]
pub struct VolterraFit {
    /// `start` with Bl, Kms, Le replaced by the fitted second-order series.
    pub params: Parameters,
    /// RMS of the fitted ratios less the measured, relative to the RMS of the measured.
    pub misfit: f64,
    /// The unknowns: `[b1, b2, k1, k2, l1, l2]` with `Bl(x) = Bl(0) (1 + b1 x/xs + b2
    /// (x/xs)^2)` and the same for Kms and Le.
    pub theta: Vec<f64>,
    /// Their covariance: `(J'J)^-1` scaled by the residual's variance per degree of freedom
    /// (at least 1 when the residual is weighted by the measured noise).
    pub cov: DMatrix<f64>,
    /// The displacement scale `xs` (m): half the smaller side of the start's `x_range`.
    pub xs: f64,
    /// With the measured noise given: the weighted residual's `chi^2` per degree of freedom
    /// (about 1 when the kernels explain the lines to the noise; far above where the
    /// third-order series does not describe the response any more).
    pub chi2_dof: Option<f64>,
}

impl VolterraFit {
    /// The band (value and sd on `points` displacements over `range`) of `which` (`Bl`,
    /// `Kms`, `Le`) from the covariance of the series' coefficients (the rest value is the
    /// small-signal fit's, taken as known: the sd is 0 at x = 0).
    pub fn band(&self, which: &str, range: [f64; 2], points: usize) -> coilscope_core::result::Band {
        let (f, k) = match which {
            "Bl" => (&self.params.bl, 0),
            "Kms" => (&self.params.kms, 2),
            _ => (&self.params.le, 4),
        };
        let c0 = f.c[0];
        let x: Vec<f64> =
            (0..points).map(|j| range[0] + (range[1] - range[0]) * j as f64 / (points - 1).max(1) as f64).collect();
        let value = x.iter().map(|&v| f.eval(v)).collect();
        let sd = x
            .iter()
            .map(|&v| {
                let g = [c0 * v / self.xs, c0 * (v / self.xs).powi(2)];
                let c = &self.cov;
                (g[0] * g[0] * c[(k, k)] + 2.0 * g[0] * g[1] * c[(k, k + 1)] + g[1] * g[1] * c[(k + 1, k + 1)])
                    .max(0.0)
                    .sqrt()
            })
            .collect();
        coilscope_core::result::Band { x, value, sd }
    }
}

struct Kernels<'a> {
    start: &'a Parameters,
    measured: &'a [Harmonics],
    /// Displacement scale (m) of the unknowns: theta = c_j x_s^j / c_0.
    xs: f64,
    /// Residual weights per tone and order (2, 3).
    weight: Vec<[f64; 2]>,
}

impl Kernels<'_> {
    fn params(&self, th: &[f64]) -> Parameters {
        let s = self.start;
        let series = |c0: f64, a: f64, b: f64| Poly { c: vec![c0, c0 * a / self.xs, c0 * b / (self.xs * self.xs)] };
        Parameters {
            bl: series(s.bl.c[0], th[0], th[1]),
            kms: series(s.kms.c[0], th[2], th[3]),
            le: series(s.le.c[0], th[4], th[5]),
            ..s.clone()
        }
    }
}

impl Problem for Kernels<'_> {
    fn residual(&self, th: &[f64]) -> DVector<f64> {
        let q = self.params(th);
        let mut r = Vec::with_capacity(4 * self.measured.len());
        for (h, w) in self.measured.iter().zip(&self.weight) {
            let (r2, r3) = probe(&q, h.freq).ratios(Output::Current, h.volts);
            for (d, w) in [(r2 - h.ratio(2), w[0]), (r3 - h.ratio(3), w[1])] {
                r.push(d.re * w);
                r.push(d.im * w);
            }
        }
        DVector::from_vec(r)
    }

    fn residual_jacobian(&self, th: &[f64]) -> (DVector<f64>, DMatrix<f64>) {
        let r = self.residual(th);
        let mut j = DMatrix::zeros(r.len(), th.len());
        for c in 0..th.len() {
            let h = 1e-6 * th[c].abs().max(1e-3);
            let mut tp = th.to_vec();
            tp[c] += h;
            let rp = self.residual(&tp);
            j.column_mut(c).copy_from(&((rp - &r) / h));
        }
        (r, j)
    }
}

pub use coilscope_core::excitation::{is_readable_multitone, readable_multitone};

/// The current's 2nd and 3rd harmonic ratios of each tone of a [`readable_multitone`] in a
/// steady-state response, as [`Harmonics`] for [`identify_volterra`]: the line at `2 f_k`
/// and `3 f_k` over the fundamental, each rotated back by the tone's phase (`a_k = A e^{j
/// phi}` turns `H2 a^2 / (H1 a)` by `phi` and `H3 a^3 / (H1 a)` by `2 phi`).
pub fn multitone_harmonics(
    r: &coilscope_analysis::distortion::Response,
    tones: &[coilscope_analysis::distortion::Tone],
) -> Vec<Harmonics> {
    tones
        .iter()
        .map(|t| {
            let f1 = r.line(Output::Current, t.bin);
            let rot = |k: i32| C::from_polar(1.0, -(k as f64) * t.phase);
            let lines = vec![
                (2usize, r.line(Output::Current, 2 * t.bin) / f1 * rot(1)),
                (3usize, r.line(Output::Current, 3 * t.bin) / f1 * rot(2)),
            ];
            Harmonics {
                freq: r.freq(t.bin),
                volts: t.amplitude / std::f64::consts::SQRT_2,
                output: Output::Current,
                fundamental: f1,
                lines,
                x_dc: r.x_dc(),
                x_peak: r.x_peak,
            }
        })
        .collect()
}

/// Fit Bl, Kms, Le to second order to the measured current harmonics `measured` (sines of
/// [`coilscope_analysis::distortion::harmonics`] with `Output::Current`, at least two
/// frequencies), the linear parameters and the start of the series from `start`.
pub fn identify_volterra(start: &Parameters, measured: &[Harmonics]) -> Result<VolterraFit, String> {
    identify_volterra_weighted(start, measured, None)
}

/// The sd a harmonic ratio is weighed with: its measured noise `noise`, with a floor of
/// 1e-3 of the tone's distortion `size` (`|ratio2| + |ratio3|`), so that a noise-free line
/// does not take all the weight. The fit and the truncation check weigh alike.
fn line_sd(noise: f64, size: f64) -> f64 {
    noise.hypot(1e-3 * size)
}

/// [`identify_volterra`] with the measured lines' noise: `noise[k]` the sd of the real (and
/// of the imaginary) part of tone `k`'s 2nd and 3rd harmonic ratio. The residual is weighted
/// by it (with a floor of 1e-3 of the tone's distortion, so that a noise-free line does not
/// take all the weight), and the fit reports its `chi2_dof`.
pub fn identify_volterra_weighted(
    start: &Parameters,
    measured: &[Harmonics],
    noise: Option<&[[f64; 2]]>,
) -> Result<VolterraFit, String> {
    if measured.len() < 2 {
        return Err(format!(
            "{} tone(s): the Volterra fit needs the harmonics of at least two frequencies",
            measured.len()
        ));
    }
    if let Some(h) = measured.iter().find(|h| h.output != Output::Current) {
        return Err(format!(
            "the tone at {} Hz gives {:?}; the Volterra fit reads the current's harmonics",
            h.freq, h.output
        ));
    }
    let xs = start.x_range.map_or(1e-3, |[lo, hi]| 0.5 * hi.min(-lo));
    if let Some(n) = noise {
        if n.len() != measured.len() {
            return Err(format!("{} noise entries for {} tones", n.len(), measured.len()));
        }
    }
    let weight = measured
        .iter()
        .enumerate()
        .map(|(k, h)| {
            let size = (h.hd(2) + h.hd(3)).max(1e-12);
            match noise {
                Some(n) => [0, 1].map(|o| 1.0 / line_sd(n[k][o], size)),
                None => [1.0 / size; 2],
            }
        })
        .collect();
    let prob = Kernels { start, measured, xs, weight };
    let c = |f: &Poly, j: usize| f.c.get(j).copied().unwrap_or(0.0) * xs.powi(j as i32) / f.c[0];
    let th0 =
        vec![c(&start.bl, 1), c(&start.bl, 2), c(&start.kms, 1), c(&start.kms, 2), c(&start.le, 1), c(&start.le, 2)];
    let mut s = LmState::new(&prob, th0);
    for _ in 0..200 {
        s = lm_step(&prob, &s);
        if s.converged || s.last_decrease < 1e-14 {
            break;
        }
    }
    let (r, j) = prob.residual_jacobian(&s.theta);
    let dof = (r.len() as f64 - s.theta.len() as f64).max(1.0);
    let var = r.norm_squared() / dof;
    let chi2_dof = noise.map(|_| var);
    let scale = if noise.is_some() { var.max(1.0) } else { var };
    let cov =
        (j.transpose() * &j).try_inverse().map(|m| m * scale).unwrap_or_else(|| DMatrix::from_element(6, 6, f64::NAN));
    // The misfit relative to the measured lines (the unweighted ratios).
    let unweighted =
        Kernels { weight: measured.iter().map(|h| [1.0 / (h.hd(2) + h.hd(3)).max(1e-12); 2]).collect(), ..prob };
    let ru = unweighted.residual(&s.theta);
    Ok(VolterraFit {
        params: unweighted.params(&s.theta),
        misfit: (ru.norm_squared() / (ru.len() as f64 / 2.0)).sqrt() / 2f64.sqrt(),
        theta: s.theta,
        cov,
        xs,
        chi2_dof,
    })
}

/// The tone lines of a recorded [`coilscope_core::excitation::Excitation::Readable`]
/// multitone, period by period.
#[derive(Clone, Debug)]
pub struct RecordLines {
    /// The tones' bins (Hz: the period is 1 s).
    pub bins: Vec<usize>,
    /// The analysed periods (their first sample, in samples).
    pub starts: Vec<usize>,
    /// Per analysed period, per tone: the voltage's and the current's lines at `f`, `2f`, `3f`
    /// (peak phasors, V and A).
    pub u: Vec<Vec<[C; 3]>>,
    pub i: Vec<Vec<[C; 3]>>,
}

impl RecordLines {
    /// The current's 2nd and 3rd harmonic ratios of each tone (as [`multitone_harmonics`]
    /// gives them on a simulated steady state), averaged over the periods, and their noise
    /// (the sd of the mean of the real and imaginary parts, from the scatter between periods).
    /// The part of each harmonic line that the voltage's own line at that frequency drives
    /// through the small-signal admittance of `start` is taken off first (an amplifier's
    /// distortion is not the transducer's).
    pub fn harmonics(&self, start: &Parameters) -> (Vec<Harmonics>, Vec<[f64; 2]>) {
        let np = self.u.len();
        let mut out = vec![];
        let mut noise = vec![];
        for (k, &bin) in self.bins.iter().enumerate() {
            let f = bin as f64 / coilscope_core::excitation::READABLE_PERIOD;
            let y = [2.0, 3.0].map(|m| 1.0 / coilscope_core::small_signal::impedance(start, m * f));
            let per: Vec<[C; 2]> = (0..np)
                .map(|p| {
                    let (u, i) = (self.u[p][k], self.i[p][k]);
                    let phi = u[0].arg();
                    [
                        (i[1] - u[1] * y[0]) / i[0] * C::from_polar(1.0, -phi),
                        (i[2] - u[2] * y[1]) / i[0] * C::from_polar(1.0, -2.0 * phi),
                    ]
                })
                .collect();
            let mean = [0, 1].map(|o| per.iter().map(|r| r[o]).sum::<C>() / np as f64);
            let sd = [0, 1].map(|o| {
                if np < 2 {
                    return f64::NAN;
                }
                let var = per.iter().map(|r| (r[o] - mean[o]).norm_sqr()).sum::<f64>() / (2.0 * (np - 1) as f64);
                (var / np as f64).sqrt()
            });
            let u1 = self.u.iter().map(|u| u[k][0].norm()).sum::<f64>() / np as f64;
            let i1 = self.i.iter().map(|i| i[k][0]).sum::<C>() / np as f64;
            out.push(Harmonics {
                freq: f,
                volts: u1 / std::f64::consts::SQRT_2,
                output: Output::Current,
                fundamental: i1,
                lines: vec![(2, mean[0]), (3, mean[1])],
                x_dc: f64::NAN,
                x_peak: [f64::NAN; 2],
            });
            noise.push(sd);
        }
        (out, noise)
    }
}

/// Read a recorded readable multitone (`simulate --excitation readable`, or that signal
/// played through a card): find the steady periods (after the fade-in and the settling; not
/// the fade-out), the tones in the voltage, check that they are a readable set, and take the
/// lines of every period.
pub fn record_lines(u: &[f64], i: &[f64], fs: f64, origin: &str) -> Result<RecordLines, String> {
    use coilscope_core::excitation::READABLE_PERIOD;
    let np = (fs * READABLE_PERIOD).round() as usize;
    if ((fs * READABLE_PERIOD) - np as f64).abs() > 1e-9 || np < 64 {
        return Err(format!("{origin}: the Volterra method reads a multitone periodic in {READABLE_PERIOD} s; the rate {fs} Hz is not a whole number of hertz"));
    }
    let periods = u.len().min(i.len()) / np;
    let rms = |k: usize| coilscope_core::simulate::rms(&u[k * np..(k + 1) * np]);
    let levels: Vec<f64> = (0..periods).map(rms).collect();
    let med = crate::checks::median(levels.clone());
    // Steady: the level of the middle periods (the fades change it), after the first such.
    let steady: Vec<usize> =
        (0..periods).filter(|&k| med > 0.0 && (levels[k] / med - 1.0).abs() < 1e-3).skip(1).collect();
    if steady.len() < 3 && periods >= 5 {
        return Err(format!(
            "{origin}: the voltage's level changes from one {READABLE_PERIOD} s period to the next ({} of {periods} periods at the median level): not a periodic multitone. The Volterra method reads the lines of `--excitation readable` (noise and music are for the full identification, `--method full`)",
            steady.len() + 1
        ));
    }
    if steady.len() < 3 {
        return Err(format!("{origin}: {} steady period(s) of {READABLE_PERIOD} s ({periods} in the record): the Volterra method averages at least 3 after the first; record 6 s or more of `--excitation readable`", steady.len()));
    }
    let spec = |x: &[f64], k: usize| -> Vec<C> {
        let s = &x[k * np..(k + 1) * np];
        coilscope_core::fft::rfft(s).into_iter().map(|c| c * (2.0 / np as f64)).collect()
    };
    let us: Vec<Vec<C>> = steady.iter().map(|&k| spec(u, k)).collect();
    let is: Vec<Vec<C>> = steady.iter().map(|&k| spec(i, k)).collect();
    let nb = np / 2 + 1;
    let mean_mag: Vec<f64> = (0..nb).map(|b| us.iter().map(|s| s[b]).sum::<C>().norm() / us.len() as f64).collect();
    let top = mean_mag.iter().skip(1).cloned().fold(0.0, f64::max);
    let bins: Vec<usize> = (1..nb).filter(|&b| mean_mag[b] > 1e-3 * top).collect();
    // The voltage must repeat: the periods' spectra agree on the tones.
    let spread =
        us.iter().map(|s| bins.iter().map(|&b| (s[b] - us[0][b]).norm()).fold(0.0, f64::max)).fold(0.0, f64::max);
    if spread > 1e-2 * top {
        return Err(format!("{origin}: the voltage is not periodic in {READABLE_PERIOD} s (the tones change by {:.1} % between periods): the Volterra method needs `--excitation readable`", 100.0 * spread / top));
    }
    if bins.len() < 2 {
        return Err(format!("{origin}: {} tone(s) in the voltage; the Volterra fit needs at least two", bins.len()));
    }
    if 3 * bins[bins.len() - 1] >= (0.45 * fs * READABLE_PERIOD) as usize {
        return Err(format!(
            "{origin}: the highest tone ({} Hz) has its 3rd harmonic above 0.45 of the rate {fs} Hz",
            bins[bins.len() - 1]
        ));
    }
    if !coilscope_core::excitation::is_readable_multitone(&bins) {
        return Err(format!(
            "{origin}: the tones in the voltage ({} from {} to {} Hz) are not a readable set: intermodulation of other tones lands on some tone's 2nd or 3rd harmonic, which the diagonal kernels cannot explain. Record `--excitation readable`",
            bins.len(),
            bins[0],
            bins[bins.len() - 1]
        ));
    }
    let take = |s: &Vec<Vec<C>>| -> Vec<Vec<[C; 3]>> {
        s.iter().map(|sp| bins.iter().map(|&b| [sp[b], sp[2 * b], sp[3 * b]]).collect()).collect()
    };
    Ok(RecordLines { u: take(&us), i: take(&is), bins, starts: steady.iter().map(|&k| k * np).collect() })
}

/// The truncation check of a Volterra fit on recorded lines: the fitted parameters' full
/// model is run to its steady state under the record's own multitone (the tones' measured
/// amplitudes and phases), and its harmonic ratios are compared with what the fitted
/// kernels predict for them, in units of the lines' noise: the mean square of those
/// differences per line. About 0 where the third-order series describes the fitted model at
/// this level; above 1 the truncation moves the lines by more than the noise, and the fit
/// has taken that into its coefficients (biased, however well the kernels fit the lines:
/// the paper's feed-back of the distortion).
pub fn truncation_check(
    fit: &VolterraFit,
    lines: &RecordLines,
    measured: &[Harmonics],
    noise: &[[f64; 2]],
) -> Result<f64, String> {
    use coilscope_analysis::distortion::{steady_state, Periodic, SteadyOptions, Tone};
    let np = lines.u.len() as f64;
    let tones: Vec<Tone> = lines
        .bins
        .iter()
        .enumerate()
        .map(|(k, &bin)| {
            let u1 = lines.u.iter().map(|u| u[k][0]).sum::<C>() / np;
            Tone { bin, amplitude: u1.norm(), phase: u1.arg() }
        })
        .collect();
    let period = coilscope_core::excitation::READABLE_PERIOD;
    // The series are fitted for the record's small reach, not for the start's range.
    let q = Parameters { x_range: None, ..fit.params.clone() };
    let r = steady_state(&q, &Periodic { period, tones: tones.clone() }, &SteadyOptions::default())
        .map_err(|e| format!("the truncation check's steady state: {e}"))?;
    let full = multitone_harmonics(&r, &tones);
    let mut sum = 0.0;
    let mut count = 0usize;
    for ((h, m), n) in full.iter().zip(measured).zip(noise) {
        let (r2, r3) = probe(&fit.params, m.freq).ratios(Output::Current, m.volts);
        let size = m.hd(2) + m.hd(3);
        for (d, s) in [(h.ratio(2) - r2, n[0]), (h.ratio(3) - r3, n[1])] {
            let s = line_sd(s, size);
            sum += (d.re / s).powi(2) + (d.im / s).powi(2);
            count += 2;
        }
    }
    Ok(sum / count.max(1) as f64)
}

/// One level of [`level_study`].
#[derive(Clone, Debug, PartialEq)]
pub struct LevelRow {
    /// Peak displacement over the range's smaller side.
    pub frac: f64,
    /// RMS voltage of the multitone (V).
    pub volts: f64,
    /// Largest error of the fitted Bl, Kms, Le over half the range, relative to the size of
    /// the model's own second-order nonlinearity there (`max |q - t2| / max |t2 - t2(0)|`).
    pub err: [f64; 3],
    /// The kernels' relative misfit.
    pub misfit: f64,
}

/// The error of [`LevelRow::err`] for one curve.
pub fn series_error(q: &Poly, t: &Poly, xs: f64) -> f64 {
    let t2 = Poly { c: t.c.iter().take(3).copied().collect() };
    let grid = (0..=40).map(|k| xs * (k as f64 / 20.0 - 1.0));
    let size = grid.clone().map(|x| (t2.eval(x) - t2.c[0]).abs()).fold(0.0, f64::max);
    grid.map(|x| (q.eval(x) - t2.eval(x)).abs()).fold(0.0, f64::max) / size
}

/// The Volterra identification against level on a model `p` (with `x_range`): at each
/// fraction of the range in `fracs`, a readable multitone of eight tones from half the
/// resonance to 20 times it (1 s period) is run to its steady state on `p`, the level set so
/// that the peak displacement is that fraction, and Bl, Kms, Le are fitted to its kernels
/// with the linear part of `p` known: where the series is exact (small level) the fit
/// returns `p`'s second-order series; above it the feed-back of the distortion, which the
/// truncated series leaves out, moves the coefficients (seed paper 3.2.2.1). Noise-free:
/// what the method itself does, not what a record's noise adds.
pub fn level_study(p: &Parameters, fracs: &[f64]) -> Result<Vec<LevelRow>, String> {
    use coilscope_analysis::distortion::{steady_state, Periodic, SteadyOptions, Tone};
    let [lo, hi] = p.x_range.ok_or("the Volterra study needs the model's x_range")?;
    let range = hi.min(-lo);
    let f0 = p.resonance_hz();
    let bins = readable_multitone((0.5 * f0).round().max(1.0) as usize, (20.0 * f0).round() as usize, 8);
    if bins.len() < 3 {
        return Err(format!("only {} readable tones between {:.0} and {:.0} Hz", bins.len(), 0.5 * f0, 20.0 * f0));
    }
    let mut start = p.clone();
    start.bl = Poly::constant(p.bl.c[0]);
    start.kms = Poly::constant(p.kms.c[0]);
    start.le = Poly::constant(p.le.c[0]);
    let tones = |g: f64| -> Vec<Tone> {
        bins.iter().enumerate().map(|(k, &bin)| Tone { bin, amplitude: g, phase: 1.7 * k as f64 }).collect()
    };
    let opts = SteadyOptions::default();
    let run = |g: f64| {
        steady_state(p, &Periodic { period: coilscope_core::excitation::READABLE_PERIOD, tones: tones(g) }, &opts)
            .map_err(|e| e.to_string())
    };
    let mut rows = vec![];
    let mut g = 0.1;
    for &frac in fracs {
        let mut r = run(g)?;
        for _ in 0..4 {
            let peak = r.x_peak[1].max(-r.x_peak[0]);
            if (peak / (frac * range) - 1.0).abs() < 0.03 {
                break;
            }
            g *= frac * range / peak;
            r = run(g)?;
        }
        let fit = identify_volterra(&start, &multitone_harmonics(&r, &tones(g)))?;
        let q = &fit.params;
        let xs = 0.5 * range;
        let err = [series_error(&q.bl, &p.bl, xs), series_error(&q.kms, &p.kms, xs), series_error(&q.le, &p.le, xs)];
        rows.push(LevelRow { frac, volts: g * (bins.len() as f64 / 2.0).sqrt(), err, misfit: fit.misfit });
    }
    Ok(rows)
}

//! The band where the lumped model holds (`linear --impedance` without `--band`), on
//! impedance curves of fresh population drivers.
//!
//! * A curve the lumped model describes (with the driver's creep and LR-3, and 0.3 % of
//!   measurement noise) is fitted whole.
//! * A curve with cone modes: parts of the cone hang on the coil's part through springs and
//!   dampers (five parts of 10 % of Mms, half an octave apart from 40 times the resonance or
//!   6 kHz, Q 8). The figures an engineer compares (Re, Bl with Mms given, fs, Qms and Qts at
//!   fs with creep's loss) are within the bounds the README states for real files: Re 1 %,
//!   Bl 2 %, fs 1 %, Qms 5 %, Qts 3 %. (Through a driver's small motional impedance up there,
//!   such modes move |Z| by a few percent at most, and the band often stays whole.)
//! * The same curves without their phase (|Z| alone, as many tools export them): the same
//!   figures within the same bounds, except Re, which |Z| alone may leave less certain: within
//!   1 % or 3 of its sd.
//! * A curve that the lumped model misses above a frequency (a ripple of 8 %, as a measured
//!   break-up region shows): the band ends within an octave of it, and the figures hold.

use coilscope_core::small_signal::{dynamic_stiffness, impedance, thiele_small};
use coilscope_core::{Complex64, Parameters, Poly};
use coilscope_ident::linear::{
    curve_warnings, fit_impedance_curve, fit_impedance_magnitude, lumped_band, scale_by_mms, LinearOptions,
};
use coilscope_testkit::population::{cases, draws, keep_failure};
use rand::{Rng, SeedableRng};
use std::f64::consts::PI;

/// A cone part of mass `m` (kg) on the coil's part through a spring and a damper, resonant at
/// `f` (Hz) with quality `q`.
struct ConeMode {
    m: f64,
    f: f64,
    q: f64,
}

impl ConeMode {
    /// The force per velocity it takes at the coil's part (N s/m): its mass behind the
    /// spring and damper, `1 / (1 / (jw m) + 1 / (r + k / jw))`.
    fn impedance(&self, w: f64) -> Complex64 {
        let jw = Complex64::new(0.0, w);
        let wk = 2.0 * PI * self.f;
        let (k, r) = (self.m * wk * wk, wk * self.m / self.q);
        1.0 / (1.0 / (jw * self.m) + 1.0 / (r + k / jw))
    }
}

/// A cone's break-up from `f1` (Hz) up: five parts of 10 % of `mms` each, resonant half an
/// octave apart, Q 8 (a stiff cone's modes, which put a region of peaks and dips in |Z|).
fn cone_break_up(mms: f64, f1: f64) -> Vec<ConeMode> {
    (0..5).map(|k| ConeMode { m: 0.1 * mms, f: f1 * 2f64.powf(0.5 * k as f64), q: 8.0 }).collect()
}

/// The driver's impedance (ohm) at `f` with the cone modes: the lumped electrical part, and
/// the motional part over the mechanical impedance in which the modes' masses move apart.
fn impedance_with_modes(p: &Parameters, modes: &[ConeMode], f: f64) -> Complex64 {
    let w = 2.0 * PI * f;
    let jw = Complex64::new(0.0, w);
    let blocked = impedance(&Parameters { bl: Poly::constant(1e-12), ..p.clone() }, f);
    let moving = p.mms - modes.iter().map(|m| m.m).sum::<f64>();
    let zm =
        p.rms + jw * moving + dynamic_stiffness(p, w) / jw + modes.iter().map(|m| m.impedance(w)).sum::<Complex64>();
    blocked + p.bl.c[0].powi(2) / zm
}

/// A curve from 10 Hz (or a fifth of the resonance, if higher) to 20 kHz, 600 log-spaced
/// points, with complex relative noise of `noise` RMS.
fn curve(p: &Parameters, modes: &[ConeMode], noise: f64, seed: u64) -> (Vec<f64>, Vec<Complex64>) {
    let lo = (thiele_small(p).fs / 5.0).max(10.0);
    let n = 600;
    let f: Vec<f64> = (0..n).map(|k| lo * (20000.0 / lo).powf(k as f64 / (n - 1) as f64)).collect();
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let mut gauss =
        || -> f64 { (-2.0 * rng.random::<f64>().max(1e-300).ln()).sqrt() * (2.0 * PI * rng.random::<f64>()).cos() };
    let z = f
        .iter()
        .map(|&f| {
            impedance_with_modes(p, modes, f)
                * Complex64::new(1.0 + noise / 2f64.sqrt() * gauss(), noise / 2f64.sqrt() * gauss())
        })
        .collect();
    (f, z)
}

fn rel(a: f64, b: f64) -> f64 {
    (a - b).abs() / b.abs()
}

/// The figures a fit in the found band gives, against the truth's, each with its bound: the
/// failures named, what the fit did in words, the top of the band found, and whether the fit
/// warned (was loud: `linear` exits 3 on it), and whether the band search found no part holding
/// the lumped model (`LumpedBand::none_held`).
fn figures_off(
    p: &Parameters,
    f: &[f64],
    z: &[Complex64],
    magnitude_only: bool,
    label: &str,
) -> (Vec<String>, String, f64, bool, bool) {
    let opts = LinearOptions::default();
    let band = lumped_band(f, z, magnitude_only, label, &opts).unwrap_or_else(|e| panic!("{label}: {e}"));
    let fit = if magnitude_only {
        fit_impedance_magnitude(
            f,
            &z.iter().map(|z| z.norm()).collect::<Vec<_>>(),
            Some(band.band),
            label,
            &opts,
            |_| {},
        )
    } else {
        fit_impedance_curve(f, z, Some(band.band), label, &opts, |_| {})
    }
    .unwrap_or_else(|e| panic!("{label}: {e}"));
    let got = scale_by_mms(&fit, p.mms).unwrap();
    let (tg, tt) = (thiele_small(&got), thiele_small(p));
    // |Z| alone leaves Re less certain where the coil's branches and creep share its slopes
    // (a woofer with LR-3 and creep: Re sd 0.8 % at 0.3 % noise): there the bound is the
    // fit's own 3 sd, which the user is given. A NaN sd fails (`max` would drop it).
    let re_sd = fit.sigma_rel[0];
    let re_bound = if magnitude_only {
        if re_sd.is_finite() {
            0.01f64.max(3.0 * re_sd)
        } else {
            f64::NAN
        }
    } else {
        0.01
    };
    let rows = [
        ("Re", got.re, p.re, re_bound),
        ("Bl", got.bl.c[0], p.bl.c[0], 0.02),
        ("fs", tg.fs, tt.fs, 0.01),
        ("Qms", tg.qms, tt.qms, 0.05),
        ("Qts", tg.qts, tt.qts, 0.03),
    ];
    // `!(e <= bound)`: a NaN fails.
    let off = rows
        .iter()
        .filter(|(_, g, t, b)| !(rel(*g, *t) <= *b))
        .map(|(k, g, t, b)| format!("{k} {g:.5} vs {t:.5} ({:+.2} %, bound {:.0} %)", 100.0 * (g / t - 1.0), 100.0 * b))
        .collect();
    let warned: Vec<String> =
        curve_warnings(&fit).into_iter().chain(band.warning()).map(|w| w.code.to_string()).collect();
    let text = format!(
        "band {:.0} .. {:.0} Hz ({}), model {} (truth {}), residual {:.2e}, Re sd {:.2e} (relative), warnings {warned:?} (on the bound of {:?}) tried {:?} corners fit {:.0} {:?} truth {:?} {:?}",
        band.band[0],
        band.band[1],
        band.note,
        fit.effects.model_name(),
        truth_model(p),
        fit.residual_rel,
        fit.sigma_rel[0],
        fit.at_bound,
        fit.tried,
        fit.p[3] / (2.0 * PI * fit.p[2]),
        fit.lr3.map(|(v, _)| v[1] / (2.0 * PI * v[0])),
        p.l2r2.as_ref().map(|(l, r)| r.eval(0.0) / (2.0 * PI * l.eval(0.0))),
        p.l3r3.map(|(l, r)| r / (2.0 * PI * l))
    );
    (off, text, band.band[1], !warned.is_empty(), band.none_held)
}

/// The truth's small-signal effects, named as a fit's model.
fn truth_model(p: &Parameters) -> String {
    let mut m = "LR-2".to_string();
    if p.l3r3.is_some() {
        m.push_str("+LR-3");
    }
    if p.creep.is_some() {
        m.push_str("+creep");
    }
    m
}

/// Over fresh drivers for `test`: `make` gives each one's curve and what was done to it, and
/// `top_ok` judges the band's top (Hz) on the curve's frequencies. Each driver is right (every
/// figure within its bound) or loud (the fit warns, so `linear` exits 3 with the reason); a
/// driver fails on a figure off its bound without a warning, or a top not as expected, and
/// is kept. At most a quarter may be loud of the drivers whose branch corners lie below
/// `reach` (Hz, where the curve stops being lumped): over 128 drivers of two seeds 3-12 %
/// were (each on a bound of the L2/R2 branch in a band cut below break-up, or the search
/// finding none), and 16 draws keep a chance failure of that bound near 1 %. A driver with a
/// corner above it (a microspeaker's branch at 7-13 kHz, its cone breaking up from 5 kHz)
/// cannot have the branch identified: its fit ends on the corner's bound and says so, which
/// is right; those are counted apart.
fn over_drivers(
    test: &str,
    magnitude_only: bool,
    make: impl Fn(&Parameters, u64) -> (String, Vec<f64>, Vec<Complex64>),
    top_ok: impl Fn(&Parameters, &[f64], f64) -> bool,
    reach: impl Fn(&Parameters) -> f64,
) {
    let mut failures = vec![];
    let (mut loud, mut n, mut beyond, mut loud_beyond) = (0, 0, 0, 0);
    for d in draws(test, cases(16)) {
        let p = d.natural();
        let label = format!("{} ({})", d.name(), p.name.clone().unwrap_or_default());
        let (what, f, z) = make(&p, d.seed);
        let (off, text, top, warned, none_held) = figures_off(&p, &f, &z, magnitude_only, &label);
        println!("{label}: {what}: {text}; off {off:?}");
        if truth_corners(&p).into_iter().all(|c| c <= reach(&p)) {
            n += 1;
            loud += usize::from(warned);
        } else {
            beyond += 1;
            loud_beyond += usize::from(warned);
        }
        // A search that found no band holding (break-up below its first top, 10 fs: a
        // microspeaker resonating at 930 Hz whose cone breaks up from 5 kHz) fits the whole
        // curve and must say so, loudly (its warning `no-lumped-band`).
        let nothing_held = none_held && warned;
        if !(top_ok(&p, &f, top) || nothing_held) || (!off.is_empty() && !warned) {
            failures
                .push(format!("{label}: {what}: {text}; off: {off:?}; kept as {}", keep_failure(&label, &p).display()));
        }
    }
    println!("{loud} of {n} fits loud; {loud_beyond} of {beyond} with a branch corner above the curve's lumped part");
    assert!(failures.is_empty(), "{failures:#?}");
    assert!(loud * 4 <= n, "{loud} of {n} fits were loud (warned): more than a quarter");
}

/// The corners of the truth's branches (Hz).
fn truth_corners(p: &Parameters) -> Vec<f64> {
    let mut c: Vec<f64> = p.l2r2.iter().map(|(l, r)| r.eval(0.0) / (2.0 * PI * l.eval(0.0))).collect();
    c.extend(p.l3r3.map(|(l, r)| r / (2.0 * PI * l)));
    c
}

#[test]
fn a_lumped_drivers_curve_is_fitted_whole() {
    let whole =
        |_: &Parameters, f: &[f64], top: f64| top == f.iter().copied().filter(|&f| f <= 20000.0).fold(0.0, f64::max);
    over_drivers(
        "a_lumped_drivers_curve_is_fitted_whole",
        false,
        |p, seed| {
            let (f, z) = curve(p, &[], 0.003, seed);
            ("lumped".into(), f, z)
        },
        whole,
        |_| 20000.0,
    );
}

#[test]
fn cone_modes_leave_the_figures_within_their_bounds() {
    over_drivers(
        "cone_modes_leave_the_figures_within_their_bounds",
        false,
        |p, seed| {
            let f1 = (40.0 * thiele_small(p).fs).min(6000.0);
            let (f, z) = curve(p, &cone_break_up(p.mms, f1), 0.003, seed);
            (format!("first mode {f1:.0} Hz"), f, z)
        },
        |_, _, _| true,
        |p| (40.0 * thiele_small(p).fs).min(6000.0),
    );
}

/// Where the curve departs from the lumped model (Hz): 30 times the resonance, at most 5 kHz.
fn departs_at(p: &Parameters) -> f64 {
    (30.0 * thiele_small(p).fs).min(5000.0)
}

/// A curve that departs from the lumped model at [`departs_at`]: above it a ripple of 8 %
/// over a third of an octave.
fn departing_curve(p: &Parameters, seed: u64) -> (Vec<f64>, Vec<Complex64>) {
    let fb = departs_at(p);
    let (f, mut z) = curve(p, &[], 0.003, seed);
    for (f, z) in f.iter().zip(z.iter_mut()) {
        if *f > fb {
            *z *= 1.0 + 0.08 * (2.0 * PI * 3.0 * (f / fb).log2()).sin();
        }
    }
    (f, z)
}

/// Above `fb` the curve has what no lumped element makes (a ripple of 8 % over a third of an
/// octave, as a real cone's break-up region shows on a measured |Z|): the band ends within
/// an octave of `fb`, and the figures hold.
#[test]
fn the_band_ends_where_the_model_stops_holding() {
    over_drivers(
        "the_band_ends_where_the_model_stops_holding",
        false,
        |p, seed| {
            let (f, z) = departing_curve(p, seed);
            (format!("departs from {:.0} Hz", departs_at(p)), f, z)
        },
        |p, _, top| (departs_at(p) / 2.0..=departs_at(p) * 2.0).contains(&top),
        departs_at,
    );
}

/// |Z| alone (a file without its phase column): the same figures within the same bounds,
/// from the magnitude and the model's own minimum phase.
#[test]
fn a_magnitude_only_curve_gives_the_drivers_figures() {
    over_drivers(
        "a_magnitude_only_curve_gives_the_drivers_figures",
        true,
        |p, seed| {
            let (f, z) = curve(p, &[], 0.003, seed);
            ("|Z| alone".into(), f, z)
        },
        |_, _, _| true,
        |_| 20000.0,
    );
}

/// Drivers a fresh draw failed on, kept: each with whether its curve is |Z| alone, the
/// curve's seed, whether it is still open (run and printed, not asserted, until fixed), and
/// whether the curve departs from the lumped model ([`departing_curve`]).
const KEPT: [(&str, bool, u64, bool, bool); 16] = [
    // Open: |Z| alone, the model right (LR-2+LR-3+creep, the branch corners within 2 % of
    // the truth's) and Re 1.17 % high at a Re sd of 0.26 % (4.5 sd), no warning.
    ("population:woofer:3479215817", true, 3479215817, true, false),
    // Open: |Z| alone, the whole curve lumped (10 Hz - 20 kHz): LR-2+LR-3 taken and creep left
    // out (LR-2+LR-3+creep gained nothing on |Z|), Re 4.0 % low and Qts 4.1 % low at a Re sd
    // of 0.33 % (12 sd), without a warning.
    ("population:subwoofer:424281019", true, 424281019, true, false),
    // |Z| alone: LR-2+LR-3 taken and creep left out (it lowered the residual from 2.21e-3 to
    // 2.10e-3, under 5 % of the whole, though the noise floor is 2.0e-3), Re 2.7 % low and Qts
    // 3.4 % low at a Re sd of 0.32 %, no warning. Right since an effect pays on its share of
    // the excess over the curve's noise floor, read from the residual's roughness.
    ("population:subwoofer:1210072753", true, 1210072753, false, false),
    // Open, the same kind at a larger scale: |Z| alone, LR-2+LR-3 taken and creep left out
    // (2.22e-3 to 2.18e-3, under the 5 %), its LR-3 corner at 13 Hz: Re 34 % low and Qts 34 %
    // low at a Re sd of 1.2 %, no warning. Still open with the curve's noise floor (2.1e-3 of
    // |Z| alone): the gain is under 25 times a point's noise power, what one unknown must
    // remove.
    ("population:woofer:3406531035", true, 3406531035, true, false),
    // The same kind: |Z| alone, LR-2+LR-3 taken and creep left out (2.14e-3 to 2.08e-3,
    // under 5 % of the whole; noise floor 2.0e-3), its LR-3 corner at 11 Hz for the truth's
    // 40 Hz: Re 4.8 % low and Qts 5.0 % low at a Re sd of 0.63 %, no warning. Right with the
    // curve's noise floor.
    ("population:midwoofer:1956822810", true, 1956822810, false, false),
    // |Z| alone: Re 1.3 % high (LR-2+LR-3+creep, 0.3 % noise), 1.65 of its sd (0.8 %).
    ("population:woofer:3042703063", true, 3042703063, false, false),
    // |Z| alone: the LR-2 corner on its bound, Re 1.03 % high: loud (on-bound), so right or
    // loud holds; kept so that it stays loud or becomes right.
    ("population:fullrange:1444849663", true, 1444849663, false, false),
    // A heavily damped microspeaker (Qms 1.3) with creep (lambda 0.094) and an LR-3 branch
    // of 10 Le whose corner (645 Hz) sits at the resonance (565 Hz): the fit took LR-2+LR-3
    // without creep, and Bl was 2.3 % low with Mms given. Right with the curve's noise floor.
    ("population:microspeaker:3590927445", false, 3590927445, false, false),
    // |Z| alone: LR-2+LR-3 with its second corner at 17 Hz (the truth's at 567 and 1510 Hz)
    // misfit by 1.7 %, under the 2 % of a file's misfit warning, with Re's sd 4e69 and Qts
    // 0: now loud (not-identified).
    ("population:midwoofer:1257859559", true, 1257859559, false, false),
    // Open: a microspeaker resonating at 730 Hz whose curve departs from 5 kHz, below the
    // band search's first top (10 fs): that top holds by the search's rule (2.0 % RMS, no
    // half-octave over 4 %) with the ripple from 5.0 to 7.3 kHz in it, which the fit absorbs
    // (LR-2 alone, corner 2.6 kHz; the truth's at 3.3 and 1.2 kHz, with creep): residual
    // 1.7 %, Bl 2.4 % high and Qts 3.5 % low, without a warning.
    ("population:microspeaker:1150845130", false, 1150845130, true, true),
    // Open, the same: resonance 770 Hz, fitted to 7.7 kHz through the departure at 2.0 %
    // RMS, Re 1.3 % high, no warning.
    ("population:microspeaker:3869504122", false, 3869504122, true, true),
    // Open, the same: departing from 5 kHz, fitted to 6.9 kHz with LR-2 alone (the truth's
    // LR-3 and creep not taken), residual 1.74 % where the curve's noise floor is 0.3 %: Re
    // 1.0 % high, Bl 3.5 % high and Qts 4.5 % low, no warning.
    ("population:microspeaker:711463070", false, 711463070, true, true),
    // |Z| alone: the band search's lowest band (to 185 Hz) did not hold, so the whole curve
    // was fitted (0.2 % misfit) with Re 1.1 % low at 0.13 % sd and no warning: now loud
    // (no-lumped-band).
    ("population:subwoofer:489810587", true, 489810587, false, false),
    // |Z| alone: LR-2+LR-3 without creep, Re 31 % low and Qts 30 % low at a Re sd of 5.2 %,
    // under the first not-identified threshold (10 %): now loud at 2 %.
    ("population:subwoofer:2244346992", true, 2244346992, false, false),
    // A lumped curve cut at 9.2 kHz: the fit to 13 kHz ended in a wrong minimum (LR-2's
    // start 21 % off, the model's 0.3 %) and missed by 20.9 %, so the search stopped there;
    // the figures are right. Kept for its figures; the band's top is the open part.
    ("population:midwoofer:2837248491", false, 2837248491, false, false),
    // A microspeaker resonating at 354 Hz whose curve departs from 5 kHz: the band search's
    // top was not near the departure, and the fit ended with a NaN residual (Re 22.5 % high,
    // fs 2381 Hz, Bl 97 % low), loud (not-identified). Kept so that it stays loud or becomes
    // right; the band's top is the open part.
    ("population:microspeaker:3483913383", false, 3483913383, false, true),
];

#[test]
fn kept_curves_give_the_drivers_figures() {
    let mut failures = vec![];
    for (name, magnitude_only, seed, open, departs) in KEPT {
        let p =
            coilscope_core::population::parse_name(name).expect("a population name").expect("a valid name").natural();
        let (f, z) = if departs { departing_curve(&p, seed) } else { curve(&p, &[], 0.003, seed) };
        let (off, text, _, warned, _) = figures_off(&p, &f, &z, magnitude_only, name);
        println!("{name} (|Z| alone: {magnitude_only}, open: {open}): {text}; off {off:?}");
        if !off.is_empty() && !warned && !open {
            failures.push(format!("{name}: {text}; off: {off:?}"));
        }
        if off.is_empty() && open {
            println!("{name} now passes: make it a kept case that is asserted");
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

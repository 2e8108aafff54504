//! Python bindings of coilscope (`import coilscope`): the module `coilscope._coilscope`,
//! wrapped by `coilscope/__init__.py` into numpy arrays and dicts.
//!
//! Parameter sets and results cross as the file contract's JSON text (`coilscope.parameters/1`,
//! `coilscope.result/1`), so that Python sees exactly what the files hold; signals cross as
//! sequences of floats (numpy arrays in, lists out, turned into arrays by the wrapper). Long
//! computations release the GIL. Every error is a `ValueError` whose message is the one the
//! command line prints.

use coilscope_core::excitation::{generate as gen, Excitation, SignalSpec};
use coilscope_core::simulate::{simulate as sim, SimOptions};
use coilscope_core::Parameters;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

fn err<E: std::fmt::Display>(e: E) -> PyErr {
    PyValueError::new_err(e.to_string())
}

/// A parameter set from JSON text, an embedded driver's name or a file path.
fn params_from(spec: &str) -> PyResult<Parameters> {
    if spec.trim_start().starts_with('{') {
        let v: serde_json::Value =
            serde_json::from_str(spec).map_err(|e| err(format!("parameters: not JSON ({e})")))?;
        // A result file gives its parameters.
        let v = if v.get("format").and_then(|f| f.as_str()).is_some_and(|f| f.starts_with("coilscope.result")) {
            v["parameters"].clone()
        } else {
            v
        };
        let p = Parameters::from_json_value(&v, "parameters").map_err(err)?;
        p.validate("parameters").map_err(err)?;
        Ok(p)
    } else {
        coilscope_io::load_parameters(spec).map_err(err)
    }
}

fn check_fs(fs: f64) -> PyResult<()> {
    if !(fs.is_finite() && (1000.0..=1.0e6).contains(&fs)) {
        return Err(err(format!("sample rate {fs} Hz is not valid (1 kHz .. 1 MHz)")));
    }
    Ok(())
}

fn check_pair(u: &[f64], i: &[f64]) -> PyResult<()> {
    if u.len() != i.len() {
        return Err(err(format!("voltage and current differ in length ({} and {} samples)", u.len(), i.len())));
    }
    if let Some(k) = u.iter().chain(i).position(|v| !v.is_finite()) {
        return Err(err(format!("sample {k} of the voltage/current is not finite")));
    }
    Ok(())
}

/// The embedded real drivers' names.
#[pyfunction]
fn drivers() -> Vec<String> {
    coilscope_core::embedded_driver_names().iter().map(|s| s.to_string()).collect()
}

/// A parameter set (JSON text, embedded name or file) as contract JSON text, validated.
#[pyfunction]
fn parameters(spec: &str) -> PyResult<String> {
    Ok(params_from(spec)?.to_json_value().to_string())
}

/// A seeded excitation (V): `noise` (IEC 60268-1), `pink`, `sine`, `multitone`, `sweep`,
/// `readable` (the Volterra method's multitone).
#[pyfunction]
#[pyo3(signature = (kind, fs, seconds, rms, seed=1, band=None, freq=None, tones=30, fade=0.05))]
#[allow(clippy::too_many_arguments)]
fn generate(
    kind: &str,
    fs: f64,
    seconds: f64,
    rms: f64,
    seed: u64,
    band: Option<(f64, f64)>,
    freq: Option<f64>,
    tones: usize,
    fade: f64,
) -> PyResult<Vec<f64>> {
    let (lo, hi) = band.unwrap_or((10.0, (8000.0f64).min(0.45 * fs)));
    let exc = match kind {
        "noise" => Excitation::Iec,
        "pink" => Excitation::Pink { f_lo: lo, f_hi: hi, crest: None },
        "sine" => Excitation::Sine { freq: freq.ok_or_else(|| err("a sine needs freq (Hz)"))? },
        "multitone" => Excitation::Multitone { f_lo: lo, f_hi: hi, count: tones, crest: None },
        "sweep" => Excitation::Sweep { f_lo: lo, f_hi: hi },
        "readable" => Excitation::Readable { f_lo: lo, f_hi: hi, count: tones, crest: None },
        other => {
            return Err(err(format!("excitation {other:?}: give noise, pink, sine, multitone, sweep or readable")))
        }
    };
    gen(&exc, &SignalSpec { fs, seconds, rms, fade, seed }).map_err(err)
}

/// Simulate a voltage record on a parameter set: `(x m, v m/s, i A, coil rise K, magnet rise K)`.
#[pyfunction]
#[allow(clippy::type_complexity)]
fn simulate(
    py: Python<'_>,
    params: &str,
    fs: f64,
    u: Vec<f64>,
) -> PyResult<(Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>)> {
    let p = params_from(params)?;
    check_fs(fs)?;
    let t = py.allow_threads(|| sim(&p, fs, &u, &SimOptions::default())).map_err(err)?;
    Ok((t.x, t.v, t.i, t.tv, t.tm))
}

/// The moving mass `kg` with its sd `sd` (kg, 0: exact), checked as the command line's
/// `--mms 15.3g±0.3g` is.
fn mass(kg: f64, sd: f64) -> PyResult<coilscope_core::mass::Mass> {
    coilscope_core::mass::Mass::parse(&format!("{kg}±{sd}")).map_err(err)
}

/// A record of the Python caller's samples.
fn record(u: Vec<f64>, i: Vec<f64>, fs: f64) -> coilscope_io::Recording {
    coilscope_io::Recording { fs: fs.round() as u32, u, i, x: None }
}

/// `chain`: `detect` (the default, as on the command line), `auto`, `none`.
fn chain_mode(chain: &str) -> PyResult<coilscope_workflow::chain::ChainMode> {
    use coilscope_workflow::chain::ChainMode;
    match chain {
        "detect" => Ok(ChainMode::Detect),
        "auto" => Ok(ChainMode::Estimate),
        "none" => Ok(ChainMode::Ideal),
        other => Err(err(format!("chain {other:?}: give detect, auto or none"))),
    }
}

/// The small-signal fit of a record (`coilscope linear`, Mms given): the result as JSON text,
/// with its warnings and verdict (`fit.trustworthy`) as the command line gives them.
#[pyfunction]
#[pyo3(signature = (u, i, fs, mms, chain="detect", mms_sd=0.0))]
fn linear(py: Python<'_>, u: Vec<f64>, i: Vec<f64>, fs: f64, mms: f64, chain: &str, mms_sd: f64) -> PyResult<String> {
    use coilscope_workflow::linear::{linear as fit, LinearInput, LinearRequest, Scale};
    let m = mass(mms, mms_sd)?;
    check_fs(fs)?;
    check_pair(&u, &i)?;
    let req = LinearRequest { chain: chain_mode(chain)?, ..LinearRequest::new("python") };
    py.allow_threads(|| {
        fit(LinearInput::Record(record(u, i, fs)), Scale::Mms(m), &req, |_| {})
            .map(|l| l.result.to_json_value().to_string())
    })
    .map_err(err)
}

/// An impedance curve from the Python caller's `f` (Hz), `z_re` and `z_im` (ohm).
fn curve_from(
    f: Vec<f64>,
    z_re: Vec<f64>,
    z_im: Vec<f64>,
    magnitude_only: bool,
) -> PyResult<coilscope_io::impedance::ImpedanceCurve> {
    if f.len() != z_re.len() || f.len() != z_im.len() {
        return Err(err(format!(
            "f, z_re and z_im have {}, {} and {} points: give one impedance per frequency",
            f.len(),
            z_re.len(),
            z_im.len()
        )));
    }
    let z = z_re.iter().zip(&z_im).map(|(&re, &im)| coilscope_core::Complex64::new(re, im)).collect();
    Ok(coilscope_io::impedance::ImpedanceCurve { f, z, comments: vec![], magnitude_only })
}

/// The small-signal fit of a measured impedance curve (`coilscope linear --impedance`, Mms
/// given): `f` (Hz), `z_re`, `z_im` (ohm). `band`: the fitted band (Hz); without it, the band
/// where the lumped model holds (below break-up), as the command line finds it
/// (`fit.band_note` says where). `magnitude_only`: only `|z|` is data (a file without
/// phase): fitted to the magnitude alone. The result as JSON text, with its warnings and
/// verdict.
#[pyfunction]
#[pyo3(signature = (f, z_re, z_im, mms, band=None, magnitude_only=false, mms_sd=0.0))]
#[allow(clippy::too_many_arguments)]
fn linear_impedance(
    py: Python<'_>,
    f: Vec<f64>,
    z_re: Vec<f64>,
    z_im: Vec<f64>,
    mms: f64,
    band: Option<(f64, f64)>,
    magnitude_only: bool,
    mms_sd: f64,
) -> PyResult<String> {
    use coilscope_workflow::linear::{linear as fit, LinearInput, LinearRequest, Scale};
    let m = mass(mms, mms_sd)?;
    let curve = curve_from(f, z_re, z_im, magnitude_only)?;
    let req = LinearRequest { band: band.map(|(lo, hi)| [lo, hi]), ..LinearRequest::new("python") };
    py.allow_threads(|| {
        fit(LinearInput::Curve(curve), Scale::Mms(m), &req, |_| {}).map(|l| l.result.to_json_value().to_string())
    })
    .map_err(err)
}

/// The keys of a parameter set that the contract does not define but that lie within an edit
/// or two of one it does, each with the key it likely meant (`[("Bll", "Bl")]`): the set
/// loads, but the parameter meant is absent.
#[pyfunction]
fn near_miss_keys(params: &str) -> PyResult<Vec<(String, String)>> {
    Ok(params_from(params)?.near_miss_keys().into_iter().map(|(k, m)| (k, m.to_string())).collect())
}

/// The small-signal impedance of a parameter set (ohm, `(re, im)` at each `f` in Hz): the
/// network of the one model, with the set's box (`enclosure`) where it has one.
#[pyfunction]
fn impedance(params: &str, f: Vec<f64>) -> PyResult<(Vec<f64>, Vec<f64>)> {
    let p = params_from(params)?;
    if let Some(k) = f.iter().position(|v| !(v.is_finite() && *v > 0.0)) {
        return Err(err(format!("f[{k}] = {}: frequencies must be positive (Hz)", f[k])));
    }
    Ok(f.iter().map(|&f| coilscope_core::small_signal::impedance(&p, f)).map(|z| (z.re, z.im)).unzip())
}

/// The box a known driver works into from its impedance in the box (`coilscope linear
/// --enclosure`): `f` (Hz), `z_re`, `z_im` (ohm), the driver's own set, the box's type
/// (`closed`, `vented`, `passive_radiator`, `auto`) and a radiator's area `sp` (m^2). The
/// result as JSON text, with its warnings and verdict as the command line gives them.
#[pyfunction]
#[pyo3(signature = (f, z_re, z_im, driver, enclosure="auto", sp=None, magnitude_only=false))]
#[allow(clippy::too_many_arguments)]
fn linear_enclosure(
    py: Python<'_>,
    f: Vec<f64>,
    z_re: Vec<f64>,
    z_im: Vec<f64>,
    driver: &str,
    enclosure: &str,
    sp: Option<f64>,
    magnitude_only: bool,
) -> PyResult<String> {
    use coilscope_workflow::enclosure::{fit_enclosure, BoxRequest};
    use coilscope_workflow::linear::LinearInput;
    let p = params_from(driver)?;
    let choice = coilscope_ident::box_fit::BoxChoice::parse(enclosure).map_err(err)?;
    let curve = curve_from(f, z_re, z_im, magnitude_only)?;
    let req = BoxRequest { origin: "python".into(), choice, sp, band: None };
    py.allow_threads(|| {
        fit_enclosure(&LinearInput::Curve(curve), &p, &req).map(|b| b.result.to_json_value().to_string())
    })
    .map_err(err)
}

/// The large-signal identification of a record (`coilscope identify`): the result as JSON
/// text, with its warnings and verdict (`fit.trustworthy`) as the command line gives them.
/// `order`: the power series' order (default: chosen on held-out data). `enclosure`: the
/// driver is in a box of this type (`identify --enclosure`), with `sd`, `vb`, `port_area`
/// and `sp` as the command line's options.
#[pyfunction]
#[pyo3(signature = (u, i, fs, mms, order=None, chain="detect", enclosure=None, sd=None, vb=None, port_area=None, sp=None, mms_sd=0.0))]
#[allow(clippy::too_many_arguments)]
fn identify(
    py: Python<'_>,
    u: Vec<f64>,
    i: Vec<f64>,
    fs: f64,
    mms: f64,
    order: Option<usize>,
    chain: &str,
    enclosure: Option<&str>,
    sd: Option<f64>,
    vb: Option<f64>,
    port_area: Option<f64>,
    sp: Option<f64>,
    mms_sd: f64,
) -> PyResult<String> {
    use coilscope_workflow::identify::{identify_record, in_box, IdentifyRequest};
    let m = mass(mms, mms_sd)?;
    check_fs(fs)?;
    check_pair(&u, &i)?;
    let enclosure = enclosure.map(|t| in_box(t, sd, vb, port_area, sp)).transpose().map_err(err)?;
    let req = IdentifyRequest {
        order,
        chain: chain_mode(chain)?,
        sd,
        enclosure,
        mms_sd_rel: m.sd_rel(),
        ..IdentifyRequest::new("python", Some(m.kg))
    };
    py.allow_threads(|| {
        let mut rec = record(u, i, fs);
        identify_record(&mut rec, &req, |_| {}).map(|d| {
            let mut r = d.result;
            if let Some(m) = d.failure {
                r.fit.stop_reason = Some(m);
            }
            r.to_json_value().to_string()
        })
    })
    .map_err(err)
}

/// A recording's channels (`coilscope_io::read_recording`: 2 or 3 channels, the sidecar's
/// scales applied): `(fs, u, i, x)`.
#[pyfunction]
#[allow(clippy::type_complexity)]
fn read_recording(path: &str) -> PyResult<(f64, Vec<f64>, Vec<f64>, Option<Vec<f64>>)> {
    let r = coilscope_io::read_recording(std::path::Path::new(path), None).map_err(err)?;
    Ok((r.fs as f64, r.u, r.i, r.x))
}

/// Write a recording as the command line does (32-bit float WAV, atomically).
#[pyfunction]
#[pyo3(signature = (path, fs, u, i, x=None))]
fn write_recording(path: &str, fs: u32, u: Vec<f64>, i: Vec<f64>, x: Option<Vec<f64>>) -> PyResult<()> {
    check_fs(fs as f64)?;
    check_pair(&u, &i)?;
    if let Some(x) = &x {
        check_pair(&u, x)?;
    }
    coilscope_io::write_recording(std::path::Path::new(path), &coilscope_io::Recording { fs, u, i, x }).map_err(err)
}

fn run_measure(
    py: Python<'_>,
    prepared: coilscope_workflow::measure::Prepared,
    seed: u64,
    max_seconds: f64,
) -> PyResult<String> {
    use coilscope_measure::signal::Source;
    use coilscope_measure::{measure, MeasureOptions};
    use coilscope_workflow::measure::{result_of, Prepared};
    let (mut dev, Prepared { mms, mms_source, mms_sd_rel, sd, .. }) = prepared.split();
    let mut src = Source::noise(&Excitation::Iec, dev.fs(), seed).map_err(err)?;
    let opts = MeasureOptions { mms, max_seconds, ..Default::default() };
    opts.validate().map_err(err)?;
    let mut m = py.allow_threads(|| measure(dev.as_mut(), &mut src, &opts, None, |_| {})).map_err(err)?;
    Ok(result_of(&mut m, &mms_source, mms_sd_rel, sd, None).to_json_value().to_string())
}

/// A dynamic measurement of a virtual driver (`coilscope measure --virtual`, IEC noise,
/// 0.1 mV / 0.1 mA sensor noise): the result as JSON text. `world`: `real` (the command
/// line's default: typical creep added where the set has none) or `published`.
#[pyfunction]
#[pyo3(signature = (driver, seed=1, fs=48000.0, max_seconds=60.0, world="real"))]
fn measure_virtual(
    py: Python<'_>,
    driver: &str,
    seed: u64,
    fs: f64,
    max_seconds: f64,
    world: &str,
) -> PyResult<String> {
    use coilscope_workflow::measure::{virtual_driver, World};
    check_fs(fs)?;
    let p = params_from(driver)?;
    let world = World::parse(world).map_err(err)?;
    let name = if driver.trim_start().starts_with('{') { "the parameter set" } else { driver };
    let prepared = virtual_driver(&p, name, world, None, None, fs, (1e-4, 1e-4), seed).map_err(err)?;
    run_measure(py, prepared, seed, max_seconds)
}

/// The online estimator on a recording (`coilscope measure --replay`): the result as JSON text.
#[pyfunction]
#[pyo3(signature = (u, i, fs, mms, max_seconds=600.0, mms_sd=0.0))]
fn measure_replay(
    py: Python<'_>,
    u: Vec<f64>,
    i: Vec<f64>,
    fs: f64,
    mms: f64,
    max_seconds: f64,
    mms_sd: f64,
) -> PyResult<String> {
    check_fs(fs)?;
    check_pair(&u, &i)?;
    let prepared =
        coilscope_workflow::measure::replay(record(u, i, fs), "python", Some(mass(mms, mms_sd)?), None).map_err(err)?;
    run_measure(py, prepared, 1, max_seconds)
}

/// Harmonic distortion of a sine on a parameter set, each nonlinearity's share and the
/// Volterra prediction (`coilscope distortion --json`, the same workflow): JSON text.
#[pyfunction]
#[pyo3(signature = (params, freq, volts, output="pressure", temp_rise=0.0))]
fn distortion(py: Python<'_>, params: &str, freq: f64, volts: f64, output: &str, temp_rise: f64) -> PyResult<String> {
    use coilscope_analysis::distortion::Output;
    let p = params_from(params)?;
    let out = match output {
        "pressure" => Output::Pressure,
        "displacement" => Output::Displacement,
        "current" => Output::Current,
        o => return Err(err(format!("output {o:?}: give pressure, displacement or current"))),
    };
    let s =
        py.allow_threads(|| coilscope_workflow::distortion::sine(&p, &[freq], volts, out, temp_rise)).map_err(err)?;
    Ok(s[0].to_json().to_string())
}

/// The static and quasi-static point-by-point measurement of a virtual driver (`coilscope
/// quasistatic`, the same workflow): the result as JSON text, its warnings and verdict as the
/// command line gives them. `offset`: `current`, `mass` or `pressure`.
#[pyfunction]
#[pyo3(signature = (driver, points=9, reach=0.8, hold=5.0, order=4, offset="current"))]
fn quasistatic(
    py: Python<'_>,
    driver: &str,
    points: usize,
    reach: f64,
    hold: f64,
    order: usize,
    offset: &str,
) -> PyResult<String> {
    use coilscope_workflow::quasistatic::{result_file, virtual_options, virtual_quasistatic, QuasiRequest};
    let p = params_from(driver)?;
    let name = if driver.trim_start().starts_with('{') { "the parameter set" } else { driver };
    let req = QuasiRequest { points, reach, hold_s: hold, order };
    let opts = virtual_options(&p, &req, offset, name).map_err(err)?;
    let q = py.allow_threads(|| virtual_quasistatic(&p, &opts)).map_err(err)?;
    let device = format!("virtual {}", p.name.as_deref().unwrap_or(name));
    Ok(result_file(&q, &opts, p.name.clone(), &device).to_json_value().to_string())
}

#[pymodule]
fn _coilscope(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(drivers, m)?)?;
    m.add_function(wrap_pyfunction!(parameters, m)?)?;
    m.add_function(wrap_pyfunction!(generate, m)?)?;
    m.add_function(wrap_pyfunction!(simulate, m)?)?;
    m.add_function(wrap_pyfunction!(linear, m)?)?;
    m.add_function(wrap_pyfunction!(linear_impedance, m)?)?;
    m.add_function(wrap_pyfunction!(linear_enclosure, m)?)?;
    m.add_function(wrap_pyfunction!(impedance, m)?)?;
    m.add_function(wrap_pyfunction!(near_miss_keys, m)?)?;
    m.add_function(wrap_pyfunction!(identify, m)?)?;
    m.add_function(wrap_pyfunction!(read_recording, m)?)?;
    m.add_function(wrap_pyfunction!(write_recording, m)?)?;
    m.add_function(wrap_pyfunction!(measure_virtual, m)?)?;
    m.add_function(wrap_pyfunction!(measure_replay, m)?)?;
    m.add_function(wrap_pyfunction!(distortion, m)?)?;
    m.add_function(wrap_pyfunction!(quasistatic, m)?)?;
    Ok(())
}

//! Wall time of the large-signal identification of an 8 s, 48 kHz recording (pink noise to
//! 85 % of x_range, thermal model on, 70 dB sensor noise), all cores:
//! `cargo bench -p coilscope-ident --bench identify`. Also one Jacobian and one residual of
//! the order-4 problem, the two costs every LM iteration pays.

use coilscope_core::excitation::{add_sensor_noise, generate, Excitation, SignalSpec};
use coilscope_core::simulate::{gain_for_peak, SimOptions};
use coilscope_core::{embedded_driver, Parameters};
use coilscope_ident::large::{identify, IdentifyOptions, Layout, OutputError, Scales};
use coilscope_ident::lm::Problem;
use std::sync::OnceLock;

fn main() {
    divan::main();
}

const FS: f64 = 48000.0;

struct Rec {
    p: Parameters,
    u: Vec<f64>,
    i: Vec<f64>,
}

fn record(name: &str) -> Rec {
    record_seed(name, 1)
}

/// An embedded driver, or one of `testdata/drivers` (the microspeaker: Le 30 uH, Re 7.5 ohm,
/// 0.1 g, its electrical time constant 3.4 us with the LR-2 branch).
fn driver(name: &str) -> Parameters {
    embedded_driver(name).unwrap_or_else(|| {
        let path = format!("{}/../../testdata/drivers/{name}.json", env!("CARGO_MANIFEST_DIR"));
        Parameters::from_json_str(&std::fs::read_to_string(&path).unwrap(), &path).unwrap()
    })
}

fn record_seed(name: &str, seed: u64) -> Rec {
    let p = driver(name);
    let [lo, hi] = p.x_range.unwrap();
    let target = 0.85 * hi.min(-lo);
    let unit = generate(
        &Excitation::Pink { f_lo: 10.0, f_hi: 8000.0, crest: Some(3.0) },
        &SignalSpec { fs: FS, seconds: 8.0, rms: 1.0, fade: 0.05, seed },
    )
    .unwrap();
    let (_, tr) = gain_for_peak(&p, FS, &unit, target, &SimOptions::default()).unwrap();
    let (mut u, mut i) = (tr.u, tr.i);
    add_sensor_noise(&mut u, 70.0, seed, "sensor-noise/voltage");
    add_sensor_noise(&mut i, 70.0, seed, "sensor-noise/current");
    Rec { p, u, i }
}

fn rec(name: &str) -> &'static Rec {
    static SB17: OnceLock<Rec> = OnceLock::new();
    static W18: OnceLock<Rec> = OnceLock::new();
    static PTT: OnceLock<Rec> = OnceLock::new();
    static MICRO: OnceLock<Rec> = OnceLock::new();
    match name {
        "sb17cac35-4" => SB17.get_or_init(|| record(name)),
        "18wu-4741t-00" => W18.get_or_init(|| record(name)),
        "microspeaker-0g1" => MICRO.get_or_init(|| record(name)),
        _ => PTT.get_or_init(|| record(name)),
    }
}

/// The microspeaker of `testdata/drivers` (Le 30 uH, L2 15 uH, R2 2 ohm: 21 RK4 sub-steps
/// per sample at 48 kHz, or 3 exponential steps, the scheme it takes; 1 in the Jacobian),
/// LR-2, one sample. The record is made before the timed run (its simulation, 1-1.5 s,
/// would otherwise be inside this bench's one sample).
#[divan::bench(args = ["microspeaker-0g1"], sample_count = 1, sample_size = 1)]
fn identify_8s_microspeaker(b: divan::Bencher, name: &str) {
    rec(name);
    b.bench_local(|| identify_8s(name));
}

/// The whole `identify` (linear start, order selection, final fit, covariance), the LR-2
/// model given (no effects chosen).
#[divan::bench(args = ["sb17cac35-4", "ptt4.0w04-01a", "18wu-4741t-00"], sample_count = 3, sample_size = 1)]
fn identify_8s(name: &str) {
    let r = rec(name);
    let lr2 = coilscope_ident::linear::EffectsChoice::Fixed(coilscope_ident::linear::Effects::NONE);
    let f = identify(
        &r.u,
        &r.i,
        FS,
        "bench",
        &IdentifyOptions { mms: r.p.mms, effects: lr2, ..Default::default() },
        |_| {},
    )
    .unwrap();
    assert!(f.residual_rel < 0.01);
}

/// The same with the effects chosen on held-out data (the default): creep, LR-3 and both are
/// tried at the chosen order. The target: 5 s for each bundled driver.
#[divan::bench(args = ["sb17cac35-4", "ptt4.0w04-01a", "18wu-4741t-00"], sample_count = 2, sample_size = 1)]
fn identify_8s_effects_auto(name: &str) {
    let r = rec(name);
    let f = identify(&r.u, &r.i, FS, "bench", &IdentifyOptions { mms: r.p.mms, ..Default::default() }, |_| {}).unwrap();
    assert!(f.residual_rel < 0.01);
}

/// The microspeaker of `testdata/drivers` with the effects chosen on held-out data (one
/// sample; the record made before the timed run). The 5 s target with the real-driver
/// model is for a microspeaker too.
#[divan::bench(args = ["microspeaker-0g1"], sample_count = 1, sample_size = 1)]
fn identify_8s_effects_auto_microspeaker(b: divan::Bencher, name: &str) {
    rec(name);
    b.bench_local(|| identify_8s_effects_auto(name));
}

/// A production line's batch: four 8 s SB17 records (seeds 1-4, LR-2), identified
/// one at a time on all cores (`workers` 1: what four `identify` calls do), or by one worker
/// per core each on one core (`workers` 2: what `identify A B C D --out DIR` does, less
/// its process start-up, a few milliseconds).
#[divan::bench(args = [1, 2], sample_count = 2, sample_size = 1)]
fn batch_of_4_sb17(workers: usize) {
    static RECS: OnceLock<Vec<Rec>> = OnceLock::new();
    let recs = RECS.get_or_init(|| (1..=4).map(|s| record_seed("sb17cac35-4", s)).collect());
    let next = std::sync::atomic::AtomicUsize::new(0);
    let threads = if workers == 1 { 0 } else { 1 };
    std::thread::scope(|scope| {
        for _ in 0..workers {
            scope.spawn(|| {
                while let Some(r) = recs.get(next.fetch_add(1, std::sync::atomic::Ordering::Relaxed)) {
                    let lr2 = coilscope_ident::linear::EffectsChoice::Fixed(coilscope_ident::linear::Effects::NONE);
                    let f = identify(
                        &r.u,
                        &r.i,
                        FS,
                        "bench",
                        &IdentifyOptions { mms: r.p.mms, effects: lr2, threads, ..Default::default() },
                        |_| {},
                    )
                    .unwrap();
                    assert!(f.residual_rel < 0.01);
                }
            });
        }
    });
}

fn problem(r: &'static Rec) -> (OutputError<'static>, Vec<f64>) {
    let p = &r.p;
    let sc = Scales {
        re: p.re,
        le: p.le.eval(0.0),
        l2: 5e-4,
        r2: 0.3,
        bl: p.bl.eval(0.0),
        kms: p.kms.eval(0.0),
        rms: p.rms,
    };
    let lay = Layout::new(4, 5, 2.0, 0.005, sc, true, p.mms);
    let th = lay.theta_from(p, None);
    let threads = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    (OutputError::new(lay, &r.u, &r.i, FS, 0..r.u.len(), p.rates(), 0.05, threads), th)
}

/// One Jacobian (23 columns, 8 s) of the order-4 problem, all cores.
#[divan::bench(sample_count = 5, sample_size = 1)]
fn jacobian_order4(b: divan::Bencher) {
    let (prob, th) = problem(rec("sb17cac35-4"));
    b.bench_local(|| prob.jacobian(&th));
}

/// [`jacobian_order4`]'s problem as a search stage takes its Jacobian (the midpoint rule,
/// `OutputError::searching`), all cores.
#[divan::bench(sample_count = 5, sample_size = 1)]
fn jacobian_order4_search(b: divan::Bencher) {
    let (prob, th) = problem(rec("sb17cac35-4"));
    let prob = prob.searching();
    b.bench_local(|| prob.jacobian(&th));
}

/// [`jacobian_order4`]'s Jacobian in passes of the given widths (as
/// [`jacobian_microspeaker_widths`]), all cores.
#[divan::bench(args = ["8,8,7", "10,10,3", "12,11", "8,8,4,3", "4,4,4,4,4,3", "12,8,3"], sample_count = 5, sample_size = 1)]
fn jacobian_order4_widths(b: divan::Bencher, w: &str) {
    let (prob, th) = problem(rec("sb17cac35-4"));
    let widths: Vec<usize> = w.split(',').map(|v| v.parse().unwrap()).collect();
    b.bench_local(|| prob.jacobian_in(&th, &widths));
}

/// The microspeaker's order-2 problem over its whole 8 s record (17 columns) on `threads`
/// workers, and theta at the truth.
fn micro_problem(threads: usize) -> (OutputError<'static>, Vec<f64>) {
    let r = rec("microspeaker-0g1");
    let p = &r.p;
    let (l2, r2) = p.l2r2.as_ref().map(|(l, r)| (l.c[0], r.c[0])).unwrap();
    let sc = Scales { re: p.re, le: p.le.eval(0.0), l2, r2, bl: p.bl.eval(0.0), kms: p.kms.eval(0.0), rms: p.rms };
    let lay = Layout::new(2, 5, 2.0, 0.005, sc, true, p.mms);
    let th = lay.theta_from(p, None);
    (OutputError::new(lay, &r.u, &r.i, FS, 0..r.u.len(), p.rates(), 0.05, threads), th)
}

/// [`jacobian_microspeaker`]'s Jacobian in passes of the given widths (each pass one run on
/// dual numbers as wide as its columns need: 4, 8, 10 or 12 lanes), two workers: what
/// `large::PASS_COSTS` was measured with.
#[divan::bench(args = ["9,8", "12,5", "10,4,3", "8,8,1", "4,4,4,4,1", "8,4,4,1"], sample_count = 3, sample_size = 1)]
fn jacobian_microspeaker_widths(b: divan::Bencher, w: &str) {
    let (prob, th) = micro_problem(2);
    let widths: Vec<usize> = w.split(',').map(|v| v.parse().unwrap()).collect();
    b.bench_local(|| prob.jacobian_in(&th, &widths));
}

/// One Jacobian (17 columns, 8 s) of the microspeaker's order-2 problem, all cores: the
/// exponential scheme's dual-number runs (one step per sample), what its `identify` spends
/// most of its time in.
#[divan::bench(args = ["plain", "spare heat"], sample_count = 3, sample_size = 1)]
fn jacobian_microspeaker(b: divan::Bencher, which: &str) {
    let (prob, th) = micro_problem(std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1));
    let prob = if which == "plain" { prob } else { prob.with_spare_heat() };
    b.bench_local(|| prob.jacobian(&th));
}

/// `J^T J` of the order-4 problem's Jacobian (23 columns, 8 s): `lm::gram` (blocked rows,
/// both cores) against nalgebra's `tr_mul` (one column pair at a time, one core); the two
/// are the same matrix to the last bit.
#[divan::bench(args = ["gram", "tr_mul"], sample_count = 5, sample_size = 1)]
fn gram_order4(b: divan::Bencher, which: &str) {
    let (prob, th) = problem(rec("sb17cac35-4"));
    let j = prob.jacobian(&th);
    match which {
        "gram" => b.bench_local(|| coilscope_ident::lm::gram(&j)),
        _ => b.bench_local(|| j.tr_mul(&j)),
    }
}

/// One residual (8 s) of the order-4 problem, one core: a full run of the model each time
/// ([`bench_residual`]; until 2026-11 this bench measured the residual cache, 71 us).
#[divan::bench(sample_count = 6, sample_size = 1)]
fn residual_order4(b: divan::Bencher) {
    let (prob, th) = problem(rec("sb17cac35-4"));
    bench_residual(b, &prob, &th);
}

/// The same residual with LR-3 (seven states) and with creep (all seventeen of the extended
/// model), one core: what the effects search pays per model run.
#[divan::bench(args = ["lr3", "creep"], sample_count = 6, sample_size = 1)]
fn residual_order4_effects(b: divan::Bencher, which: &str) {
    let r = rec("sb17cac35-4");
    let mut p = r.p.clone();
    let (l2, r2) = (p.l2r2.as_ref().unwrap().0.c[0], p.l2r2.as_ref().unwrap().1.c[0]);
    let effects = match which {
        "lr3" => {
            p.l3r3 = Some((0.6 * l2, 2.5 * r2));
            coilscope_ident::linear::Effects { lr3: true, ..coilscope_ident::linear::Effects::NONE }
        }
        _ => {
            p.creep = Some(coilscope_core::params::Creep { lambda: 0.05, f_ref: None });
            coilscope_ident::linear::Effects { creep: true, ..coilscope_ident::linear::Effects::NONE }
        }
    };
    let sc = Scales {
        re: p.re,
        le: p.le.eval(0.0),
        l2: 5e-4,
        r2: 0.3,
        bl: p.bl.eval(0.0),
        kms: p.kms.eval(0.0),
        rms: p.rms,
    };
    let lay = Layout::new(4, 5, 2.0, 0.005, sc, true, p.mms).with_effects(effects);
    let th = lay.theta_from(&p, None);
    let prob = OutputError::new(lay, &r.u, &r.i, FS, 0..r.u.len(), p.rates(), 0.05, 1);
    bench_residual(b, &prob, &th);
}

/// Full residual runs of `prob`: `residual` keeps the last theta's residual, so the samples
/// alternate between `th` and a theta 1e-9 away from it.
fn bench_residual(b: divan::Bencher, prob: &OutputError, th: &[f64]) {
    let mut other = th.to_vec();
    other[0] *= 1.0 + 1e-9;
    let mut flip = false;
    b.bench_local(|| {
        flip = !flip;
        prob.residual(if flip { th } else { &other })
    });
}

/// The linear fits `identify` starts from, on the first 4 s of SB17's record: `start`, the
/// small-signal effects chosen (the start model's fit), and `chain`, through a sound card
/// (the current 0.3 sample late, AC coupling at 2 and 4 Hz, offsets, 50 Hz hum: the stages
/// example's card) with the card estimated, the fit `--chain auto` runs beside it. One
/// sample each: a fit is deterministic.
#[divan::bench(args = ["start", "chain"], sample_count = 3, sample_size = 1)]
fn linear_start(b: divan::Bencher, which: &str) {
    use coilscope_core::chain::{Chain, Hum};
    use coilscope_ident::linear::{fit_linear_record, EffectsChoice, LinearOptions};
    let r = rec("sb17cac35-4");
    let m = (4.0 * FS) as usize;
    let chain = which == "chain";
    let (u, i) = if chain {
        let peak = |v: &[f64]| v.iter().fold(0.0f64, |a, x| a.max(x.abs()));
        let (pu, pi) = (peak(&r.u), peak(&r.i));
        let card = Chain {
            delay_i: 0.3 / FS,
            hp_u: 2.0,
            hp_i: 4.0,
            dc_u: 5e-3 * pu,
            dc_i: 5e-3 * pi,
            hum: Some(Hum { f: 50.0, u: vec![[1e-3 * pu, 0.3]], i: vec![[1e-3 * pi, 1.1]] }),
            ..Default::default()
        };
        card.apply(&r.u[..m], &r.i[..m], FS)
    } else {
        (r.u[..m].to_vec(), r.i[..m].to_vec())
    };
    let opts = if chain {
        LinearOptions { chain: true, ..LinearOptions::LARGE_SIGNAL_START }
    } else {
        LinearOptions { effects: EffectsChoice::Auto, ..LinearOptions::LARGE_SIGNAL_START }
    };
    b.bench_local(|| fit_linear_record(&u, &i, FS, "bench", &opts, |_| {}).unwrap());
}

//! Wall time of `coilscope identify` as the command runs it ([`identify_record`]: the chain's
//! detection, the fit, the checks), on 8 s at 48 kHz of SB17 (pink noise to 85 % of x_range,
//! coil heating, 70 dB sensor noise), all cores:
//! `cargo bench -p coilscope-workflow --bench identify_record`.
//!
//! - `plain_without_detection` and `plain_detected` on the same plain record: what the default
//!   `--chain detect` costs a record that has no chain (the two medians' ratio);
//! - `card_detected`: the record through a sound card (AC coupling on both channels, a
//!   fraction of a sample of skew, DC, hum), whose chain the default finds and estimates;
//! - `station_unit_one_core`: a production station's unit (`qc test UNIT.wav --effects none
//!   --chain none --threads 1`): 3 s of pink noise to 70 % of the range, on one core, and its
//!   verdict's set (the line's budget is 3 s of computing per unit).

use coilscope_core::embedded_driver;
use coilscope_io::Recording;
use coilscope_testkit::world::{card_chain, record, Record};
use coilscope_workflow::chain::ChainMode;
use coilscope_workflow::identify::{identify_record, IdentifyRequest};
use std::sync::OnceLock;

fn main() {
    divan::main();
}

const FS: f64 = 48000.0;
const SEED: u64 = 1;

fn plain() -> &'static Record {
    static R: OnceLock<Record> = OnceLock::new();
    R.get_or_init(|| record(&embedded_driver("sb17cac35-4").unwrap(), SEED, FS, 8.0, 0.85, None).unwrap())
}

fn card() -> &'static Record {
    static R: OnceLock<Record> = OnceLock::new();
    R.get_or_init(|| {
        let chain = |u: &[f64], i: &[f64]| card_chain(SEED, u, i, FS);
        record(&embedded_driver("sb17cac35-4").unwrap(), SEED, FS, 8.0, 0.85, Some(&chain)).unwrap()
    })
}

fn run(rec: &Record, chain: ChainMode) -> bool {
    let mut r = Recording { fs: FS as u32, u: rec.u.clone(), i: rec.i.clone(), x: None };
    let req = IdentifyRequest { chain, ..IdentifyRequest::new("bench", Some(rec.truth.mms)) };
    identify_record(&mut r, &req, |_| {}).unwrap().trustworthy()
}

#[divan::bench(sample_count = 5, sample_size = 1)]
fn plain_without_detection() -> bool {
    run(plain(), ChainMode::Ideal)
}

#[divan::bench(sample_count = 5, sample_size = 1)]
fn plain_detected() -> bool {
    run(plain(), ChainMode::Detect)
}

#[divan::bench(sample_count = 5, sample_size = 1)]
fn card_detected() -> bool {
    run(card(), ChainMode::Detect)
}

fn station_record() -> &'static Record {
    static R: OnceLock<Record> = OnceLock::new();
    R.get_or_init(|| record(&embedded_driver("sb17cac35-4").unwrap(), SEED, FS, 3.0, 0.7, None).unwrap())
}

#[divan::bench(sample_count = 5, sample_size = 1)]
fn station_unit_one_core() -> bool {
    use coilscope_ident::linear::{Effects, EffectsChoice};
    let rec = station_record();
    let mut r = Recording { fs: FS as u32, u: rec.u.clone(), i: rec.i.clone(), x: None };
    let req = IdentifyRequest {
        chain: ChainMode::Ideal,
        effects: EffectsChoice::Fixed(Effects::NONE),
        threads: 1,
        ..IdentifyRequest::new("bench", Some(rec.truth.mms))
    };
    coilscope_workflow::qc::unit_from_record(&mut r, &req).unwrap().1
}

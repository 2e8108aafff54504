//! Fresh drivers on every run.
//!
//! The base seed is `COILSCOPE_POPULATION_SEED` when it is set (CI sets it from the commit, so
//! a CI run can be repeated), else the clock, so that every run judges the code on drivers it
//! has not seen. Each test draws its own seeds from the base and prints them with the base:
//! `COILSCOPE_POPULATION_SEED=B` repeats a run, and `population:CLASS:SEED` names one
//! driver to every command (`coilscope simulate population:woofer:17 ...`).

use coilscope_core::population::{draw, Draw};
use coilscope_core::Parameters;
use std::path::PathBuf;

/// The run's base seed: `COILSCOPE_POPULATION_SEED` (a whole number, or a hex commit hash of
/// which the first 16 digits are taken), or the clock.
pub fn base_seed() -> u64 {
    match std::env::var("COILSCOPE_POPULATION_SEED") {
        Ok(s) if !s.trim().is_empty() => {
            let s = s.trim();
            s.parse::<u64>().ok().or_else(|| u64::from_str_radix(&s[..s.len().min(16)], 16).ok()).unwrap_or_else(|| {
                panic!("COILSCOPE_POPULATION_SEED={s:?}: expected a whole number or a hex commit hash")
            })
        }
        _ => {
            std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(1)
        }
    }
}

fn mix(mut z: u64) -> u64 {
    // splitmix64: seeds that differ in one bit draw unrelated drivers.
    z = z.wrapping_add(0x9e3779b97f4a7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58476d1ce4e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d049bb133111eb);
    z ^ (z >> 31)
}

/// How many cases a population test takes: `COILSCOPE_POPULATION_CASES` when set (an offline
/// sweep of hundreds), else `default`.
pub fn cases(default: usize) -> usize {
    std::env::var("COILSCOPE_POPULATION_CASES").ok().and_then(|s| s.trim().parse().ok()).unwrap_or(default)
}

/// `n` seeds for `test`, from the run's base seed; printed so that a failure can be drawn again.
/// Seeds are kept below 2^32 so that a name such as `population:woofer:123456` stays short.
pub fn seeds(test: &str, n: usize) -> Vec<u64> {
    let base = base_seed();
    let salt = test.bytes().fold(0xcbf29ce484222325u64, |h, b| (h ^ b as u64).wrapping_mul(0x100000001b3));
    let seeds: Vec<u64> = (0..n as u64).map(|k| mix(base ^ mix(salt.wrapping_add(k))) >> 32).collect();
    println!(
        "{test}: population base seed {base} (COILSCOPE_POPULATION_SEED={base} draws these again): seeds {seeds:?}"
    );
    seeds
}

/// The drivers of `n` fresh seeds for `test`.
pub fn draws(test: &str, n: usize) -> Vec<Draw> {
    seeds(test, n).into_iter().map(draw).collect()
}

/// Write a driver a test failed on as a parameter file, and return its path: the failure
/// message names it (and its `population:...` name), so that it can be kept as a regression
/// case in `testdata/population/`.
pub fn keep_failure(label: &str, p: &Parameters) -> PathBuf {
    let dir = std::env::temp_dir().join("coilscope-population-failures");
    let _ = std::fs::create_dir_all(&dir);
    let file: String =
        label.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '.' { c } else { '_' }).collect();
    let path = dir.join(format!("{file}.json"));
    let text = serde_json::to_string_pretty(&p.to_json_value()).unwrap_or_default();
    if std::fs::write(&path, text).is_err() {
        eprintln!("could not write {}", path.display());
    }
    path
}

/// A driver a population test once failed on, kept in `testdata/population/NAME.json`: a
/// parameter set with a `regression` key saying which test (`measure` or `identify`), whether
/// the record went through a card, the seed it failed with and why.
#[derive(Clone, Debug)]
pub struct Regression {
    pub name: String,
    pub params: Parameters,
    pub test: String,
    pub card: bool,
    pub seed: u64,
    pub why: String,
}

/// The regression drivers kept for `test` (`measure` or `identify`) whose failure is fixed,
/// in name order: every CI run takes its slice of them.
pub fn regressions(test: &str) -> Vec<Regression> {
    regressions_in("", test)
}

/// The runs of the kept regression drivers for `test`: each driver with the seed it failed
/// with and two more (1 and 2), its reason printed.
pub fn regression_runs(test: &str) -> Vec<(Regression, u64)> {
    let mut runs = Vec::new();
    for r in regressions(test) {
        println!("regression:{}: {}", r.name, r.why);
        for seed in [r.seed, 1, 2] {
            runs.push((r.clone(), seed));
        }
    }
    runs
}

/// The regression drivers kept for `test` whose failure is still open
/// (`testdata/population/open/`): the offline sweeps run them with the fresh draws, so that
/// they fail until these pass; fixed, a driver moves up a directory.
pub fn open_regressions(test: &str) -> Vec<Regression> {
    regressions_in("open", test)
}

fn regressions_in(sub: &str, test: &str) -> Vec<Regression> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../testdata/population").join(sub);
    let mut paths: Vec<PathBuf> = std::fs::read_dir(&dir)
        .map(|d| {
            d.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.extension().is_some_and(|e| e == "json")).collect()
        })
        .unwrap_or_default();
    paths.sort();
    let mut out = Vec::new();
    for path in paths {
        let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let params = Parameters::from_json_str(&text, &path.display().to_string()).unwrap_or_else(|e| panic!("{e}"));
        let meta = params
            .extra
            .get("regression")
            .unwrap_or_else(|| panic!("{}: no `regression` key (test, card, seed, why)", path.display()))
            .clone();
        let kind = meta["test"].as_str().unwrap_or_default().to_string();
        if kind != test {
            continue;
        }
        out.push(Regression {
            name: path.file_stem().unwrap().to_string_lossy().into_owned(),
            params,
            test: kind,
            card: meta["card"].as_bool().unwrap_or(false),
            seed: meta["seed"].as_u64().unwrap_or(1),
            why: meta["why"].as_str().unwrap_or_default().to_string(),
        });
    }
    out
}

#[test]
fn every_kept_regression_driver_reads_and_says_why() {
    let all: Vec<Regression> =
        ["measure", "identify"].iter().flat_map(|t| regressions(t).into_iter().chain(open_regressions(t))).collect();
    assert!(!all.is_empty());
    for r in all {
        assert!(!r.why.is_empty(), "{}: say why it is kept", r.name);
        r.params.validate(&r.name).unwrap();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seeds_differ_between_tests_and_repeat_for_a_base() {
        std::env::set_var("COILSCOPE_POPULATION_SEED", "12345");
        let a = seeds("a", 4);
        assert_eq!(a, seeds("a", 4));
        assert_ne!(a, seeds("b", 4));
        std::env::set_var("COILSCOPE_POPULATION_SEED", "b0d72db0c0ffee00aa");
        assert_eq!(base_seed(), 0xb0d72db0c0ffee00);
        std::env::remove_var("COILSCOPE_POPULATION_SEED");
    }
}

//! Spreading a release sweep over CI runs instead of dropping cases.
//!
//! `COILSCOPE_SWEEP_SLICE=k/n` (0 <= k < n) keeps the cases whose index i in their test's list
//! has i % n == k. `.ci/run` sets it from the commit, so every case runs once every n commits
//! while one CI run stays short; unset (the default, and what a developer runs) keeps every
//! case. Shared by the ident and measure sweeps (`#[path]` from the measure crate).

/// The slice of a sweep this run covers: (k, n).
pub fn sweep_slice() -> (usize, usize) {
    // Unset or empty: every case.
    let s = std::env::var("COILSCOPE_SWEEP_SLICE").unwrap_or_default();
    if s.trim().is_empty() {
        return (0, 1);
    }
    let parsed = s.split_once('/').and_then(|(k, n)| Some((k.trim().parse::<usize>().ok()?, n.trim().parse::<usize>().ok()?)));
    match parsed {
        Some((k, n)) if n >= 1 && k < n => (k, n),
        _ => panic!("COILSCOPE_SWEEP_SLICE={s:?}: expected k/n with 0 <= k < n, e.g. 1/4 (unset it to run every case)"),
    }
}

/// The cases of `cases` in this run's slice; says which, so a CI log shows what ran.
pub fn in_slice<T>(test: &str, cases: Vec<T>) -> Vec<T> {
    let (k, n) = sweep_slice();
    let total = cases.len();
    let kept: Vec<T> = cases.into_iter().enumerate().filter(|(i, _)| i % n == k).map(|(_, c)| c).collect();
    if n > 1 {
        println!("{test}: slice {k}/{n} of the sweep (COILSCOPE_SWEEP_SLICE): {} of {total} cases", kept.len());
    }
    kept
}

//! Spreading a release sweep over CI runs instead of dropping cases.
//!
//! `COILSCOPE_SWEEP_SLICE=k/n` (0 <= k < n) keeps the cases whose index i in their test's list
//! has i % n == k ([`slice_has`]). `.ci/run` sets k from the number of commits, so
//! consecutive CI runs take consecutive slices and every case runs once in n runs; unset (the
//! default, and what a developer runs) keeps every case. A sweep of fewer cases than slices
//! runs one of them in each slice, never none: a sweep that ran nothing must not pass.

/// The slice of a sweep this run covers: (k, n).
pub fn sweep_slice() -> (usize, usize) {
    let s = std::env::var("COILSCOPE_SWEEP_SLICE").unwrap_or_default();
    if s.trim().is_empty() {
        return (0, 1);
    }
    let parsed =
        s.split_once('/').and_then(|(k, n)| Some((k.trim().parse::<usize>().ok()?, n.trim().parse::<usize>().ok()?)));
    match parsed {
        Some((k, n)) if n >= 1 && k < n => (k, n),
        _ => panic!("COILSCOPE_SWEEP_SLICE={s:?}: expected k/n with 0 <= k < n, e.g. 1/4 (unset it to run every case)"),
    }
}

/// Whether case `i` of `total` is in slice `k` of `n`: `i % n == k`; a sweep of fewer cases
/// than slices runs case `k % total`, so that every slice runs one case and every case runs
/// in n consecutive runs.
pub fn slice_has(i: usize, total: usize, k: usize, n: usize) -> bool {
    if total < n {
        i == k % total
    } else {
        i % n == k
    }
}

/// The cases of `cases` in this run's slice; says which, so a CI log shows what ran. Panics
/// when the slice keeps no case (an empty sweep).
pub fn in_slice<T>(test: &str, cases: Vec<T>) -> Vec<T> {
    let (k, n) = sweep_slice();
    let total = cases.len();
    let kept: Vec<T> =
        cases.into_iter().enumerate().filter(|(i, _)| slice_has(*i, total, k, n)).map(|(_, c)| c).collect();
    println!("{test}: slice {k}/{n} of the sweep (COILSCOPE_SWEEP_SLICE): {} of {total} cases", kept.len());
    assert!(!kept.is_empty(), "{test}: slice {k}/{n} keeps none of the sweep's {total} cases: a sweep that runs nothing passes nothing (give it at least {n} cases)");
    kept
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_case_runs_in_n_consecutive_slices_and_no_slice_is_empty() {
        let n = 4;
        for total in [1, 2, 3, 4, 10] {
            let mut seen = vec![0; total];
            for k in 0..n {
                let kept: Vec<usize> = (0..total).filter(|&i| slice_has(i, total, k, n)).collect();
                assert!(!kept.is_empty(), "slice {k}/{n} of {total} cases is empty");
                kept.iter().for_each(|&i| seen[i] += 1);
            }
            assert!(seen.iter().all(|&c| c >= 1), "{total} cases: {seen:?}");
            if total >= n {
                assert!(seen.iter().all(|&c| c == 1));
            }
        }
    }
}

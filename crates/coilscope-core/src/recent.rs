//! A few values kept by key, for computations that are asked for again with the same inputs
//! (the chain's phase factors and currents to match in a fit: each an FFT-sized vector).

use std::sync::{Arc, Mutex};

/// The last `cap` values computed, by key, the most recently used last; shared between
/// threads. A value is computed outside the lock, so two threads asking for the same new key
/// may both compute it (the same value, kept twice until it ages out). A clone starts empty:
/// what was kept belongs to the original's inputs.
pub struct Recent<K, V> {
    cap: usize,
    kept: Mutex<Vec<(K, Arc<V>)>>,
}

impl<K: PartialEq, V> Recent<K, V> {
    /// Keeping at most `cap` values.
    pub const fn new(cap: usize) -> Self {
        Recent { cap, kept: Mutex::new(Vec::new()) }
    }

    /// The value kept for `key`, else `compute()`, kept (the least recently used one goes
    /// when `cap` are kept).
    pub fn get_or_compute(&self, key: K, compute: impl FnOnce() -> V) -> Arc<V> {
        {
            let mut kept = self.kept.lock().unwrap_or_else(|e| e.into_inner());
            if let Some(at) = kept.iter().position(|(k, _)| *k == key) {
                let hit = kept.remove(at);
                let v = hit.1.clone();
                kept.push(hit);
                return v;
            }
        }
        let v = Arc::new(compute());
        let mut kept = self.kept.lock().unwrap_or_else(|e| e.into_inner());
        if self.cap > 0 && kept.len() >= self.cap {
            kept.remove(0);
        }
        if self.cap > 0 {
            kept.push((key, v.clone()));
        }
        v
    }
}

impl<K, V> Clone for Recent<K, V> {
    fn clone(&self) -> Self {
        Recent { cap: self.cap, kept: Mutex::new(Vec::new()) }
    }
}

impl<K, V> std::fmt::Debug for Recent<K, V> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Recent {{ cap: {} }}", self.cap)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A kept key is not computed again; the least recently used key goes first; a clone
    /// starts empty.
    #[test]
    fn keeps_the_most_recently_used() {
        let r: Recent<u32, u32> = Recent::new(2);
        let calls = std::cell::Cell::new(0);
        let get = |r: &Recent<u32, u32>, k: u32| {
            *r.get_or_compute(k, || {
                calls.set(calls.get() + 1);
                10 * k
            })
        };
        assert_eq!((get(&r, 1), get(&r, 2), calls.get()), (10, 20, 2));
        assert_eq!((get(&r, 1), calls.get()), (10, 2), "kept");
        assert_eq!((get(&r, 3), calls.get()), (30, 3), "2 goes: 1 was used last");
        assert_eq!((get(&r, 1), calls.get()), (10, 3), "1 still kept");
        assert_eq!((get(&r, 2), calls.get()), (20, 4), "2 was gone");
        let c = r.clone();
        assert_eq!((get(&c, 1), calls.get()), (10, 5), "a clone starts empty");
    }
}

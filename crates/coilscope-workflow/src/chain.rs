//! The measurement chain of a record: what the sound card did to the channels (a skew, AC
//! coupling, offsets, mains hum; `coilscope_core::chain`), and what a workflow does about it.
//!
//! Every record made through a sound card carries a chain. By default ([`ChainMode::Detect`])
//! a workflow looks for one in the record ([`detect`]: cheap tests of what each part of a
//! chain leaves in the data) and estimates it where it finds one; a plain record keeps the
//! plain (and faster) fit. `auto` always estimates it, `none` takes the channels as ideal,
//! and a chain file (`coilscope calibrate`'s) inverts a calibrated card.

use coilscope_core::chain::{Chain, SenseWiring};
use coilscope_io::Recording;
use std::path::Path;

/// What to do about the measurement chain (one per request: its size does not matter).
#[derive(Clone, Debug, PartialEq)]
#[allow(clippy::large_enum_variant)]
pub enum ChainMode {
    /// Look for a chain in the record and estimate it where one shows (the default).
    Detect,
    /// Estimate the chain whatever the record shows (`--chain auto`).
    Estimate,
    /// Take the channels as ideal (`--chain none`).
    Ideal,
    /// A calibrated chain, inverted before the fit (`--chain FILE`).
    Calibrated(Chain),
}

impl ChainMode {
    /// `detect`, `auto`, `none`, or a chain file (`coilscope calibrate`'s, or a result with a
    /// `chain`).
    pub fn parse(text: &str) -> Result<ChainMode, String> {
        match text.trim() {
            "detect" => Ok(ChainMode::Detect),
            "auto" => Ok(ChainMode::Estimate),
            "none" => Ok(ChainMode::Ideal),
            other => {
                let path = Path::new(other);
                if !path.exists() {
                    return Err(format!("--chain {other:?}: give `detect` (estimate the measurement chain where the record shows one; the default), `auto` (always estimate it), `none` (ideal channels), or a chain file written by `coilscope calibrate` (no such file)"));
                }
                load_chain(path).map(ChainMode::Calibrated)
            }
        }
    }

    /// Whether the fit estimates the chain without a look first.
    pub fn estimate(&self) -> bool {
        matches!(self, ChainMode::Estimate)
    }

    /// The hum a record may carry before it is refused is larger where the chain (its hum
    /// among it) is fitted: estimated, or possibly so.
    fn hum_fitted(&self) -> bool {
        matches!(self, ChainMode::Estimate | ChainMode::Detect)
    }

    /// Make `rec` the physical voltage and current behind the recorded channels: refuse heavy
    /// hum ([`coilscope_ident::linear::check_hum`], stricter when the chain is not
    /// estimated), then invert a calibrated chain (each record's offsets found). Returns the
    /// chain to report (calibrated only).
    ///
    /// A `driver+shunt` wiring's voltage record is first made a `terminals` one
    /// ([`coilscope_ident::linear::remove_shunt_drop`], through this chain, or through the one
    /// estimated for the purpose).
    pub fn prepare(&self, rec: &mut Recording, origin: &str, wiring: SenseWiring) -> Result<Option<Chain>, String> {
        coilscope_ident::linear::check_hum(&rec.u, &rec.i, rec.fs as f64, self.hum_fitted(), origin)?;
        self.undo(rec, origin, wiring)
    }

    /// The record as the driver's terminals saw it: the shunt's drop taken out, a calibrated
    /// chain inverted (no hum check: the Volterra method reads lines that avoid the mains).
    pub fn undo(&self, rec: &mut Recording, origin: &str, wiring: SenseWiring) -> Result<Option<Chain>, String> {
        let fs = rec.fs as f64;
        if wiring != SenseWiring::Terminals {
            let ideal = Chain::default();
            let known = match self {
                ChainMode::Ideal => Some(&ideal),
                ChainMode::Calibrated(c) => Some(c),
                ChainMode::Estimate | ChainMode::Detect => None,
            };
            rec.u = coilscope_ident::linear::remove_shunt_drop(&rec.u, &rec.i, fs, wiring, known, origin)?;
        }
        match self {
            ChainMode::Calibrated(c) => {
                let (u, i, dc_u, dc_i) = c.invert_calibrated(&rec.u, &rec.i, fs);
                (rec.u, rec.i) = (u, i);
                Ok(Some(Chain { source: Some("calibrated".into()), dc_u, dc_i, ..c.clone() }))
            }
            _ => Ok(None),
        }
    }
}

/// A chain file: `coilscope calibrate`'s, or a result file's `chain`.
pub fn load_chain(path: &Path) -> Result<Chain, String> {
    let name = path.display();
    let text = std::fs::read_to_string(path).map_err(|e| format!("{name}: cannot read the chain file ({e})"))?;
    let v: serde_json::Value = serde_json::from_str(&text).map_err(|e| format!("{name}: not JSON ({e})"))?;
    let v = v.get("chain").cloned().unwrap_or(v);
    let c: Chain = serde_json::from_value(v)
        .map_err(|e| format!("{name}: not a chain ({e}); write one with `coilscope calibrate`"))?;
    let bad = |k: &str, val: f64, valid: &str| Err(format!("{name}: {k} = {val} is not valid ({valid})"));
    if !(c.delay_i.is_finite() && c.delay_i.abs() < 0.01) {
        return bad("delay_i", c.delay_i, "seconds, |delay| < 10 ms");
    }
    for (k, fc) in [("hp_u", c.hp_u), ("hp_i", c.hp_i)] {
        if !(fc.is_finite() && (0.0..100.0).contains(&fc)) {
            return bad(k, fc, "Hz, 0 (DC-coupled) .. 100");
        }
    }
    if let Some(g) = c.gain_i {
        if !(g.is_finite() && g > 0.1 && g < 10.0) {
            return bad("gain_i", g, "the current channel's gain against the voltage's, 0.1 .. 10");
        }
    }
    Ok(c)
}

/// Record the wiring in a reported chain (a `driver+shunt` one always; `terminals` when a
/// chain is reported anyway).
pub fn mark_wiring(chain: &mut Option<Chain>, wiring: SenseWiring) {
    if wiring != SenseWiring::Terminals || chain.is_some() {
        wiring.mark(chain.get_or_insert_with(Default::default));
    }
}

/// What [`detect`] found of a chain in a record: a sentence per part found (empty: none).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Detection {
    pub found: Vec<String>,
}

impl Detection {
    pub fn any(&self) -> bool {
        !self.found.is_empty()
    }
}

/// Look for a measurement chain in a record without a fit: hum and offsets
/// ([`coilscope_ident::linear::chain_signs`]). The skew and the AC coupling show against the
/// driver's model, and the fits look for those themselves.
pub fn detect(u: &[f64], i: &[f64], fs: f64) -> Detection {
    Detection { found: coilscope_ident::linear::chain_signs(u, i, fs) }
}

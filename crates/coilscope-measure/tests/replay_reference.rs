//! Replay of the independent simulator's recordings (`shared/recordings`, not made by
//! coilscope): the measurement pipeline in replay mode (no control of the level) must identify
//! each driver from its small-signal record followed by its large-signal record played three
//! times (every record starts and ends at rest, so they join without a jump of the state; the
//! coil cools back to ambient at each join, which the Re tracking follows). Truth: the driver
//! file. Tolerances as in the identification issue, over the range the live model reached.

use coilscope_core::{embedded_driver, Poly};
use coilscope_io::read_recording;
use coilscope_measure::device::ReplayDevice;
use coilscope_measure::signal::Source;
use coilscope_measure::{measure, MeasureOptions};
use std::path::{Path, PathBuf};

fn shared_recordings() -> Option<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/recordings");
    if dir.exists() {
        Some(dir)
    } else {
        assert!(
            std::env::var_os("COILSCOPE_NO_SHARED").is_some(),
            "{} is missing: these tests need shared/ beside the checkout (set COILSCOPE_NO_SHARED=1 to skip them knowingly)",
            dir.display()
        );
        None
    }
}

fn worst(f: &Poly, g: &Poly, [lo, hi]: [f64; 2]) -> f64 {
    (0..=400).map(|k| lo + (hi - lo) * k as f64 / 400.0).map(|x| (f.eval(x) - g.eval(x)).abs()).fold(0.0, f64::max) / g.eval(0.0).abs()
}

#[test]
fn replayed_reference_recordings_identify_every_driver() {
    let Some(dir) = shared_recordings() else { return };
    for name in ["sb17cac35-4", "ptt4.0w04-01a", "18wu-4741t-00"] {
        let p = embedded_driver(name).unwrap();
        let small = read_recording(&dir.join(format!("{name}-small.wav")), None).unwrap();
        let large = read_recording(&dir.join(format!("{name}-large.wav")), None).unwrap();
        let (mut u, mut i) = (small.u.clone(), small.i.clone());
        for _ in 0..3 {
            u.extend_from_slice(&large.u);
            i.extend_from_slice(&large.i);
        }
        let mut dev = ReplayDevice::from_samples(name, small.fs as f64, u, i);
        // The replay ignores the drive; the source only sets the block length.
        let mut src = Source::noise(&coilscope_core::excitation::Excitation::Iec, small.fs as f64, 1).unwrap();
        let opts = MeasureOptions { mms: p.mms, small_seconds: 2.5, ..Default::default() };
        let m = measure(&mut dev, &mut src, &opts, None, |_| {}).unwrap_or_else(|e| panic!("{name}: {e}"));
        let q = &m.params;
        let r = m.x_range;
        let (e_bl, e_k, e_le) = (worst(&q.bl, &p.bl, r), worst(&q.kms, &p.kms, r), worst(&q.le, &p.le, r));
        let e_re = (m.re_cold / p.re - 1.0).abs();
        let e_rms = (q.rms / p.rms - 1.0).abs();
        println!(
            "{name}: {} after {:.1} s; Bl {:.3} %, Kms {:.3} %, Le {:.3} %, Re(cold) {:.3} %, Rms {:.3} % over {:.2}..{:.2} mm",
            if m.converged { "converged" } else { "not converged" },
            m.seconds,
            100.0 * e_bl,
            100.0 * e_k,
            100.0 * e_le,
            100.0 * e_re,
            100.0 * e_rms,
            r[0] * 1e3,
            r[1] * 1e3
        );
        assert!(e_bl <= 0.02 && e_k <= 0.02 && e_le <= 0.05, "{name}: Bl {e_bl}, Kms {e_k}, Le {e_le}");
        assert!(e_re <= 0.01 && e_rms <= 0.01, "{name}: Re {e_re}, Rms {e_rms}");
        // The range covers most of what the record reached.
        let info: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join(format!("{name}-large.info.json"))).unwrap()).unwrap();
        let reached = info["x_max"].as_f64().unwrap() - info["x_min"].as_f64().unwrap();
        assert!(r[1] - r[0] >= 0.7 * reached, "{name}: range {:?} m of {reached} m reached", r);
    }
}

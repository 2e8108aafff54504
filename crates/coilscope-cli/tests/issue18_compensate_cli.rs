//! Issue 18: `coilscope compensate` end to end: a 30 Hz tone in, the drive out; the drive,
//! played by `simulate --input`, moves the driver as the linear reference does (the check
//! the command prints), and bad inputs get one clear line.

use std::process::{Command, Output};

fn coilscope(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_coilscope")).args(args).output().unwrap()
}

#[test]
fn compensate_writes_a_drive_that_linearises_the_displacement() {
    let d = tempfile::tempdir().unwrap();
    let tone = d.path().join("tone.wav");
    let drive = d.path().join("drive.wav");
    let p = |p: &std::path::Path| p.to_str().unwrap().to_string();
    let o = coilscope(&["simulate", "sb17cac35-4", "--excitation", "sine", "--freq", "30", "--volts", "3", "--seconds", "1", "--out", &p(&tone)]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = coilscope(&["compensate", "sb17cac35-4", "--input", &p(&tone), "--out", &p(&drive)]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout).into_owned();
    // "... (largest): plain A m, compensated B m": B at least 1e4 below A.
    let line = text.lines().find(|l| l.contains("off the linear reference")).unwrap_or_else(|| panic!("{text}"));
    let nums: Vec<f64> = line.split_whitespace().filter_map(|w| w.parse::<f64>().ok()).collect();
    assert_eq!(nums.len(), 2, "{line}");
    assert!(nums[0] > 1e-4 && nums[1] < 1e-4 * nums[0], "{line}");
    let (fs, u) = coilscope_io::read_voltage(&drive, None).unwrap();
    assert_eq!((fs, u.len()), (48000, 48000));
    // Clipping is reported.
    let o = coilscope(&["compensate", "sb17cac35-4", "--input", &p(&tone), "--out", &p(&drive), "--max-volts", "2"]);
    assert!(o.status.success());
    assert!(String::from_utf8_lossy(&o.stdout).contains("warning: the drive was clipped at 2.000 V"));
    // Too loud for the range: one clear line, exit 2.
    let loud = d.path().join("loud.wav");
    let u: Vec<f64> = (0..14400).map(|k| 60.0 * (2.0 * std::f64::consts::PI * 20.0 * k as f64 / 48000.0).sin()).collect();
    coilscope_io::write_voltage(&loud, 48000, &u).unwrap();
    let o = coilscope(&["compensate", "sb17cac35-4", "--input", &p(&loud), "--out", &p(&drive)]);
    assert_eq!(o.status.code(), Some(2));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("leaves the driver's valid range") && e.trim_end().lines().count() == 1, "{e}");
    let o = coilscope(&["compensate", "sb17cac35-4", "--input", "/nonexistent.wav", "--out", &p(&drive)]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("/nonexistent.wav"));
}

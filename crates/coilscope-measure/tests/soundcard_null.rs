//! The sound-card backend on ALSA's `null` device (headless: playback discards, capture gives
//! zeros): it opens, paces blocks at the sample rate, calibrates, and the measurement stops
//! with a clear error on the silent channels instead of hanging or panicking. Bad devices and
//! settings get messages that name what is wrong.
//!
//! cpal lists ALSA's `default` and the hardware cards, so the tests point `default` at the
//! null plugin with a configuration of their own (`ALSA_CONFIG_PATH`, set once before the
//! first ALSA call of the process); a machine's own ALSA setup is not touched.
#![cfg(feature = "soundcard")]

use coilscope_core::excitation::Excitation;
use coilscope_measure::device::Device;
use coilscope_measure::signal::Source;
use coilscope_measure::soundcard::{list_devices, SoundCardDevice, SoundCardOptions};
use coilscope_measure::{measure, MeasureOptions};

fn null() -> SoundCardOptions {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let path = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("coilscope-alsa-null.conf");
        std::fs::write(&path, "</usr/share/alsa/alsa.conf>\npcm.!default { type null }\n").unwrap();
        // Safety of set_var: this runs once, before any thread of this process calls ALSA
        // (every test goes through here first).
        std::env::set_var("ALSA_CONFIG_PATH", &path);
    });
    SoundCardOptions { output: Some("default".into()), input: Some("default".into()), ..Default::default() }
}

#[test]
fn the_null_default_device_is_listed() {
    null();
    let (inputs, outputs) = list_devices().unwrap();
    assert!(
        inputs.iter().any(|n| n == "default") && outputs.iter().any(|n| n == "default"),
        "inputs {inputs:?}, outputs {outputs:?}"
    );
}

#[test]
fn blocks_come_whole_and_calibrated() {
    let mut dev = SoundCardDevice::open(&null()).unwrap();
    assert_eq!(dev.fs(), 48000.0);
    let mut n = 0;
    for _ in 0..5 {
        let b = dev.play(&vec![1.0; 4800]).unwrap().unwrap();
        assert_eq!((b.u.len(), b.i.len()), (4800, 4800));
        // The null capture is silence: 0 V and 0 A after calibration.
        assert!(b.u.iter().chain(b.i.iter()).all(|v| *v == 0.0));
        n += b.u.len();
    }
    assert_eq!(n, 24000);
    assert!(dev.describe().contains("default"));
}

#[test]
fn a_measurement_on_silent_channels_stops_with_a_clear_error() {
    let mut dev = SoundCardDevice::open(&null()).unwrap();
    let mut src = Source::noise(&Excitation::Iec, 48000.0, 1).unwrap();
    let opts = MeasureOptions { mms: 0.01, small_seconds: 1.0, max_seconds: 4.0, ..Default::default() };
    let e = measure(&mut dev, &mut src, &opts, None, |_| {}).err().expect("silent channels must fail");
    assert!(e.contains("silent") && e.contains("voltage"), "{e}");
}

#[test]
fn bad_devices_and_settings_get_clear_errors() {
    let e = SoundCardDevice::open(&SoundCardOptions { output: Some("no-such-card".into()), ..null() }).err().unwrap();
    assert!(e.contains("no-such-card") && e.contains("default"), "{e}");
    for (opts, key) in [
        (SoundCardOptions { sense_ohm: 0.0, ..null() }, "--sense-ohm"),
        (SoundCardOptions { u_channel: 1, i_channel: 1, ..null() }, "--u-channel"),
        (SoundCardOptions { i_channel: 5, ..null() }, "--i-channel"),
        (SoundCardOptions { drive_channel: 2, ..null() }, "--drive-channel"),
        (SoundCardOptions { fs: 44100.5, ..null() }, "--fs"),
    ] {
        let e = SoundCardDevice::open(&opts).err().unwrap();
        assert!(e.contains(key), "{key}: {e}");
    }
    // A drive beyond the output's full scale is refused, not clipped.
    let mut dev = SoundCardDevice::open(&SoundCardOptions { out_volts_fs: 2.0, ..null() }).unwrap();
    let e = dev.play(&[0.0, 2.5, 0.0]).err().unwrap();
    assert!(e.contains("--out-volts-fs") && e.contains("2.500"), "{e}");
}

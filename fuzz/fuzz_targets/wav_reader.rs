//! The WAV reader on arbitrary bytes: a clear error or a recording, never a panic or an
//! allocation the file cannot back. Integer PCM is read with unit scales.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(r) = coilscope_io::read_recording_bytes(data, "fuzz.wav", Some(&[1.0, 1.0, 1.0])) {
        assert_eq!(r.u.len(), r.i.len());
        assert!(r.u.iter().chain(&r.i).all(|v| v.is_finite()));
    }
    let _ = coilscope_io::read_recording_bytes(data, "fuzz.wav", None);
});

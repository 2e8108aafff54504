//! The fuzz targets' kept inputs (`fuzz/regressions/<target>/`), replayed
//! through the same readers on the stable toolchain. Each must give a clear error or a value,
//! never a panic. The targets themselves run with `cargo fuzz run <target>` (see
//! `fuzz/Cargo.toml`).

use std::path::PathBuf;

fn inputs(target: &str) -> Vec<(String, Vec<u8>)> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../fuzz/regressions").join(target);
    let mut v: Vec<_> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().path())
        .collect();
    v.sort();
    assert!(!v.is_empty(), "{}: no kept inputs", dir.display());
    v.into_iter().map(|p| (p.file_name().unwrap().to_string_lossy().into_owned(), std::fs::read(&p).unwrap())).collect()
}

#[test]
fn wav_reader_inputs_give_errors_or_recordings() {
    for (name, bytes) in inputs("wav_reader") {
        for scale in [Some(&[1.0, 1.0, 1.0][..]), None] {
            match coilscope_io::read_recording_bytes(&bytes, &name, scale) {
                Ok(r) => assert!(r.u.len() == r.i.len() && r.u.iter().chain(&r.i).all(|v| v.is_finite()), "{name}"),
                Err(e) => assert!(e.to_string().starts_with(&name), "{name}: the message must name the file: {e}"),
            }
        }
    }
}

#[test]
fn the_claimed_length_of_a_wav_is_not_trusted() {
    let bytes = std::fs::read(
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../fuzz/regressions/wav_reader/huge-claimed-length.wav"),
    )
    .unwrap();
    // The header claims 4 GiB; the two frames that are there are read, or a clear error.
    match coilscope_io::read_recording_bytes(&bytes, "huge.wav", None) {
        Ok(r) => assert!(r.u.len() <= 2),
        Err(e) => assert!(e.to_string().contains("huge.wav"), "{e}"),
    }
}

#[test]
fn params_json_inputs_give_errors_or_sets() {
    for (name, bytes) in inputs("params_json") {
        let Ok(text) = std::str::from_utf8(&bytes) else { continue };
        if let Ok(p) = coilscope_core::Parameters::from_json_str(text, &name) {
            let _ = coilscope_core::small_signal::thiele_small(&p);
            coilscope_core::Parameters::from_json_value(&p.to_json_value(), "round trip").unwrap();
        }
    }
}

#[test]
fn result_json_inputs_give_errors_or_inputs() {
    for (name, bytes) in inputs("result_json") {
        let Ok(text) = std::str::from_utf8(&bytes) else { continue };
        if let Err(e) = coilscope_report::input_from_text(text, &name) {
            assert!(e.contains(&name), "{name}: the message must name the file: {e}");
        }
    }
}

/// `coilscope quasistatic ... | head` once panicked in `println!` on the
/// closed pipe ("failed printing to stdout: Broken pipe"). A closed pipe ends the program
/// quietly, as any Unix tool.
#[cfg(unix)]
#[test]
fn a_closed_pipe_is_not_a_panic() {
    use std::process::{Command, Stdio};
    let mut child = Command::new(env!("CARGO_BIN_EXE_coilscope"))
        .args(["check", "sb17cac35-4"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Close the read end before the program writes.
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!err.contains("panicked"), "{err}");
}

//! The result reader (`coilscope report`/`diagnose` input) on arbitrary text: a clear error or
//! an input, never a panic.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let _ = coilscope_report::input_from_text(text, "fuzz-result.json");
});

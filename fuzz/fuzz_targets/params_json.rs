//! The parameter-set reader on arbitrary text: a clear error or a set whose every number is
//! finite, never a panic. An accepted set must also survive a model evaluation.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    if let Ok(p) = coilscope_core::Parameters::from_json_str(text, "fuzz.json") {
        let _ = coilscope_core::small_signal::thiele_small(&p);
        let back = p.to_json_value();
        coilscope_core::Parameters::from_json_value(&back, "round trip").expect("a set that was read is written back readable");
    }
});

//! `cfg(no_shared)`: `../shared` (the independent reference data beside the checkout) is
//! missing and `COILSCOPE_NO_SHARED` is set. The tests that need it are then compiled as
//! ignored, so the test run reports them as skipped, never as passed; without the variable
//! they run and fail, naming what is missing (CI never sets it).
fn main() {
    println!("cargo::rustc-check-cfg=cfg(no_shared)");
    println!("cargo::rerun-if-env-changed=COILSCOPE_NO_SHARED");
    let dir = std::path::Path::new(&std::env::var("CARGO_MANIFEST_DIR").unwrap()).join("../../../shared");
    println!("cargo::rerun-if-changed={}", dir.display());
    if !dir.exists() && std::env::var_os("COILSCOPE_NO_SHARED").is_some() {
        println!("cargo::rustc-cfg=no_shared");
    }
}

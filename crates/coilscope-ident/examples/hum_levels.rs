//! Print the mains hum `linear`/`identify` would see between the channels of each record
//! given on the command line (the check behind their hum refusal).
fn main() {
    for path in std::env::args().skip(1) {
        let r = coilscope_io::read_recording(std::path::Path::new(&path), None).unwrap();
        let h = coilscope_ident::linear::mains_hum(&r.u, &r.i, r.fs as f64);
        println!("{path}: {h:?}");
    }
}

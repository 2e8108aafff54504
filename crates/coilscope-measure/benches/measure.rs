//! Processing speed of the virtual measurement (release, one core), per driver: 20 s of
//! measurement (IEC noise from silence, target 85 % of x_range, run as a long-term test so
//! that it does not stop at convergence), and the virtual device alone over the same 20 s
//! (the device is the simulated transducer, not processing: subtract it). Real-time factor
//! = 20 s / (measurement - device).
use coilscope_core::embedded_driver;
use coilscope_core::excitation::Excitation;
use coilscope_measure::device::{Device, VirtualDevice};
use coilscope_measure::signal::Source;
use coilscope_measure::{measure, MeasureOptions};

const DRIVERS: [&str; 3] = ["sb17cac35-4", "ptt4.0w04-01a", "18wu-4741t-00"];
const SECONDS: f64 = 20.0;

fn main() {
    divan::main();
}

#[divan::bench(args = DRIVERS, sample_count = 3)]
fn measure_20s(name: &str) -> f64 {
    let p = embedded_driver(name).unwrap();
    let [lo, hi] = p.x_range.unwrap();
    let mut dev = VirtualDevice::new(&p, 48000.0, (1e-4, 1e-4), 1).unwrap();
    let mut src = Source::noise(&Excitation::Iec, 48000.0, 2).unwrap();
    let opts = MeasureOptions {
        mms: p.mms,
        target_x: Some(0.85 * hi.min(-lo)),
        duration: Some(SECONDS),
        ..Default::default()
    };
    measure(&mut dev, &mut src, &opts, None, |_| {}).unwrap().seconds
}

#[divan::bench(args = DRIVERS, sample_count = 3)]
fn virtual_device_alone_20s(name: &str) {
    let p = embedded_driver(name).unwrap();
    let mut dev = VirtualDevice::new(&p, 48000.0, (1e-4, 1e-4), 1).unwrap();
    let mut src = Source::noise(&Excitation::Iec, 48000.0, 2).unwrap();
    for _ in 0..(SECONDS * 10.0) as usize {
        let d: Vec<f64> = src.next_block(4800).iter().map(|v| v * 3.0).collect();
        divan::black_box(dev.play(&d).unwrap());
    }
}

//! Processing speed of the virtual measurement (release, one core): the whole loop on SB17
//! (IEC noise, target 85 % of x_range) until convergence (about 19 s of measurement), and the
//! virtual device alone over the same length (the device is not processing: subtract it).
use coilscope_core::excitation::Excitation;
use coilscope_core::embedded_driver;
use coilscope_measure::device::{Device, VirtualDevice};
use coilscope_measure::signal::Source;
use coilscope_measure::{measure, MeasureOptions};

fn main() {
    divan::main();
}

#[divan::bench(sample_count = 3)]
fn measure_sb17_to_convergence() -> f64 {
    let p = embedded_driver("sb17cac35-4").unwrap();
    let [lo, hi] = p.x_range.unwrap();
    let mut dev = VirtualDevice::new(&p, 48000.0, (1e-4, 1e-4), 1).unwrap();
    let mut src = Source::noise(&Excitation::Iec, 48000.0, 2).unwrap();
    let m = measure(&mut dev, &mut src, &MeasureOptions { mms: p.mms, target_x: Some(0.85 * hi.min(-lo)), ..Default::default() }, None, |_| {}).unwrap();
    m.seconds
}

#[divan::bench(sample_count = 3)]
fn virtual_device_alone_19s() {
    let p = embedded_driver("sb17cac35-4").unwrap();
    let mut dev = VirtualDevice::new(&p, 48000.0, (1e-4, 1e-4), 1).unwrap();
    let mut src = Source::noise(&Excitation::Iec, 48000.0, 2).unwrap();
    for _ in 0..190 {
        let d: Vec<f64> = src.next_block(4800).iter().map(|v| v * 5.0).collect();
        divan::black_box(dev.play(&d).unwrap());
    }
}

use coilscope_core::excitation::Excitation;
use coilscope_core::embedded_driver;
use coilscope_measure::device::{Device, VirtualDevice, Block, Truth};
use coilscope_measure::signal::Source;
use coilscope_measure::{measure, MeasureOptions};
use std::cell::RefCell;
use std::rc::Rc;

struct Spy { d: VirtualDevice, last: Rc<RefCell<f64>> }
impl Device for Spy {
    fn fs(&self) -> f64 { self.d.fs() }
    fn play(&mut self, drive: &[f64]) -> Result<Option<Block>, String> {
        let before = self.d.truth().unwrap().x_peak;
        let _ = before;
        let r = self.d.play(drive);
        *self.last.borrow_mut() = self.d.truth().unwrap().x_peak;
        r
    }
    fn truth(&self) -> Option<Truth> { self.d.truth() }
    fn describe(&self) -> String { self.d.describe() }
    fn controllable(&self) -> bool { true }
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let name = &a[1];
    let seed: u64 = a[2].parse().unwrap();
    let sv: f64 = a[3].parse().unwrap();
    let p = embedded_driver(name).unwrap_or_else(|| coilscope_io::load_parameters(name).unwrap());
    let fs = 48000.0;
    let last = Rc::new(RefCell::new(0.0));
    let mut dev = Spy { d: VirtualDevice::new(&p, fs, (1e-4, 1e-4), seed).unwrap(), last: last.clone() };
    let mut src = if a.len() > 4 { Source::music(std::path::Path::new(&a[4]), fs).unwrap() } else { Source::noise(&Excitation::Iec, fs, seed).unwrap() };
    let opts = MeasureOptions { mms: p.mms, start_volts: sv, ..Default::default() };
    let r = measure(&mut dev, &mut src, &opts, None, |l| {
        println!("t {:6.2} {:5} V {:6.3} live {:+6.2}..{:+6.2} true-peak-sofar {:5.2} lim {:?} {} upd {:?} ch {:?}", l.t, l.stage.name(), l.volts, l.x_min*1e3, l.x_max*1e3, *last.borrow()*1e3, l.x_limit.map(|x| x*1e3), l.limited_by, l.update, l.change);
    });
    match r { Ok(m) => println!("{}", m.stop_reason), Err(e) => println!("ERR {e}") }
}

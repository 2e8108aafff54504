//! `quasistatic --card`, headless. The virtual driver is recorded through a
//! simulated sound card of our own ([`SimulatedCard`]: AC coupling at 2 Hz and 4 Hz, the
//! current 0.3 sample late and 1.5 % hot, offsets, 50 Hz hum, a 0.1 ohm shunt in the voltage
//! channel, 24-bit converters) and measured through [`Corrected`] with the card's
//! calibration, as `quasistatic --card --chain` does. The person at the bench is a program:
//! it places the masses to the nearest 0.1 g (or sets the pressure to the nearest pascal) —
//! not exactly what was asked — and reads a dial gauge of 0.01 mm resolution.
//!
//! Bound: the accuracy bound, Bl(x) and Kms(x) within 2 % over 80 % of the range, for a driver
//! without creep (measured: see the printout; asserted at 2 %).

use coilscope_core::chain::{Chain, Hum, SenseWiring};
use coilscope_core::excitation::{generate, Excitation, SignalSpec};
use coilscope_core::{embedded_driver, Parameters, Poly};
use coilscope_ident::quasi_static::{quasi_static, Offset, Push, QuasiStaticOptions, GRAVITY};
use coilscope_measure::card::{Corrected, SimulatedCard};
use coilscope_measure::device::{Block, Device, VirtualDevice};
use coilscope_measure::quasi_static_card::{card_play, Operator};
use std::cell::RefCell;
use std::rc::Rc;

const FS: f64 = 48000.0;
const WIRING: SenseWiring = SenseWiring::DriverPlusShunt { ohm: 0.1 };

/// The virtual driver shared by the card (which plays through it) and the bench (which
/// pushes its cone and reads its displacement).
struct Shared(Rc<RefCell<VirtualDevice>>);

impl Device for Shared {
    fn fs(&self) -> f64 {
        self.0.borrow().fs()
    }
    fn play(&mut self, drive: &[f64]) -> Result<Option<Block>, String> {
        self.0.borrow_mut().play(drive)
    }
    fn describe(&self) -> String {
        self.0.borrow().describe()
    }
}

/// The person at the bench: rounds what is asked to what can be placed or set, and reads the
/// gauge to its resolution.
struct Bench {
    dev: Rc<RefCell<VirtualDevice>>,
    asked: Vec<Push>,
}

impl Operator for Bench {
    fn apply(&mut self, _: usize, push: Push, offset: Offset) -> Result<Option<Push>, String> {
        self.asked.push(push);
        let applied = match offset {
            Offset::Mass => {
                let m = (push.added_mass * 1e4).round() / 1e4;
                Push { force: push.force.signum() * m * GRAVITY, added_mass: m }
            }
            Offset::Pressure { sd } => Push { force: (push.force / sd).round() * sd, added_mass: 0.0 },
            Offset::Current => unreachable!(),
        };
        self.dev.borrow_mut().set_push(applied.force, applied.added_mass);
        Ok(Some(applied))
    }
    fn read_x(&mut self, _: usize) -> Result<f64, String> {
        Ok((self.dev.borrow().x_now() * 1e5).round() / 1e5)
    }
}

fn card() -> Chain {
    Chain {
        delay_i: 0.3 / FS,
        hp_u: 2.0,
        hp_i: 4.0,
        gain_i: Some(1.015),
        dc_u: 0.05,
        dc_i: 0.01,
        hum: Some(Hum { f: 50.0, u: vec![[3e-4, 0.4]], i: vec![[5e-5, -1.2]] }),
        ..Default::default()
    }
}

/// Largest `|f / g - 1|` over `[lo, hi]`.
fn worst(f: &Poly, g: &Poly, lo: f64, hi: f64) -> f64 {
    (0..=100)
        .map(|k| lo + (hi - lo) * k as f64 / 100.0)
        .map(|x| (f.eval(x) / g.eval(x) - 1.0).abs())
        .fold(0.0, coilscope_testkit::check::nan_max)
}

fn run(p: &Parameters, offset: Offset) -> (f64, f64, usize, coilscope_ident::quasi_static::QuasiStatic) {
    let virt = Rc::new(RefCell::new(VirtualDevice::new(p, FS, (1e-4, 1e-4), 3).unwrap()));
    let sim = SimulatedCard::new(Shared(virt.clone()), &card(), WIRING, (100.0, 30.0)).unwrap();
    let cal = Chain { dc_u: 0.0, dc_i: 0.0, hum: None, ..card() };
    let mut dev = Corrected::new(sim, &cal, WIRING).unwrap();
    let mut bench = Bench { dev: virt, asked: vec![] };
    let ac = generate(
        &Excitation::Pink { f_lo: 5.0, f_hi: 16000.0, crest: None },
        &SignalSpec { fs: FS, seconds: 2.0, rms: 1.0, fade: 0.0, seed: 7 },
    )
    .unwrap();
    let opts = QuasiStaticOptions {
        mms: p.mms,
        points: 9,
        reach: 0.8,
        range: p.x_range.unwrap(),
        hold_s: 2.0,
        record_s: 2.0,
        ac_volts: 0.1,
        order: 4,
        fs: FS,
        offset,
    };
    let q = quasi_static(card_play(&mut dev, &mut bench, offset, 4800), &ac, &opts).unwrap_or_else(|e| panic!("{e}"));
    let [lo, hi] = q.params.x_range.unwrap();
    let (bl, kms) = (worst(&q.params.bl, &p.bl, lo, hi), worst(&q.params.kms, &p.kms, lo, hi));
    (bl, kms, bench.asked.len(), q)
}

#[test]
fn quasi_static_through_a_calibrated_card_with_masses_and_a_pressure() {
    for (name, pressure) in [("sb17cac35-4", false), ("ptt4.0w04-01a", true)] {
        let p = embedded_driver(name).unwrap();
        let offset = if pressure { Offset::Pressure { sd: p.sd.unwrap() } } else { Offset::Mass };
        let (bl, kms, asked, q) = run(&p, offset);
        let [lo, hi] = q.params.x_range.unwrap();
        let [rlo, rhi] = p.x_range.unwrap();
        println!(
            "{name} by {offset:?}: Bl {:.3} %, Kms {:.3} % over {:.2}..{:.2} mm ({asked} points asked); warnings {:?}",
            100.0 * bl,
            100.0 * kms,
            lo * 1e3,
            hi * 1e3,
            q.warnings
        );
        for w in &q.points {
            println!(
                "  force {:+.4} N, mass {:.2} g: x {:+.3} mm, Bl {:.4} (true {:.4}), Kms {:.1} (true {:.1})",
                w.force,
                w.push.added_mass * 1e3,
                w.x_dc * 1e3,
                w.bl,
                p.bl.eval(w.x_dc),
                w.kms_static,
                p.kms.eval(w.x_dc)
            );
        }
        // Every point was asked of the operator (the rest point too), and what they applied,
        // not what was asked, is in the result.
        assert_eq!(asked, 9, "{name}");
        assert!(q.points.iter().any(|w| w.push.added_mass > 0.0 || w.force != 0.0), "{name}");
        // The points reach most of the 80 % asked for on both sides (the method plans each
        // point from the last one's stiffness, which the suspension's rise outruns, as with
        // a DC current).
        assert!(lo < 0.6 * rlo && hi > 0.6 * rhi, "{name}: points over {lo}..{hi} of {rlo}..{rhi}");
        assert!(bl < 0.02 && kms < 0.02, "{name}: Bl {bl}, Kms {kms}");
        assert!(q.warnings.is_empty(), "{name}: {:?}", q.warnings);
    }
}

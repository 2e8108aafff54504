//! The quasi-static point-by-point method ([`coilscope_ident::quasi_static`]) on real hardware:
//! `coilscope quasistatic --card`.
//!
//! A sound card's output is AC-coupled: it cannot hold a DC current through the coil. The
//! working points are therefore held without current, as IEC 62458 10.2/10.3 allow: by an
//! **added mass** under gravity (the driver facing up pushes the coil in, facing down pulls it
//! out) or by a **pressure** on the diaphragm (a sealed box pumped up or down). The card
//! records the small-signal voltage and current at each point (its calibration, if any,
//! applied block by block by [`crate::card::Corrected`]), and the static displacement is read
//! by the person at the bench on a gauge (a dial indicator or a laser's own display) — the
//! card's inputs carry no DC.
//!
//! The person is an [`Operator`]: [`PromptOperator`] asks on a terminal; tests put a
//! program in their place that moves a virtual driver and reads its true displacement.

use crate::device::Device;
use coilscope_ident::quasi_static::{Offset, Played, Push, GRAVITY};
use std::io::{BufRead, Write};

/// Seconds of silence after a point's small signal before the gauge is read.
pub const SETTLE_S: f64 = 0.5;

/// The person at the bench (or a program in their place).
pub trait Operator {
    /// Apply `push` at working point `point` (1 is at rest: nothing applied) by `offset`,
    /// and say what was applied where it differs (`None`: as asked).
    fn apply(&mut self, point: usize, push: Push, offset: Offset) -> Result<Option<Push>, String>;
    /// The static displacement the gauge reads now (m, + = coil out).
    fn read_x(&mut self, point: usize) -> Result<f64, String>;
}

/// `play` of [`coilscope_ident::quasi_static::quasi_static`] on a device: at each working
/// point the operator applies the push, the device plays the drive in blocks of `block`
/// samples (silence while the suspension settles, then the small signal), and the operator
/// reads the gauge; its reading is the point's displacement over the whole record.
pub fn card_play<'a>(
    device: &'a mut dyn Device,
    operator: &'a mut dyn Operator,
    offset: Offset,
    block: usize,
) -> impl FnMut(&[f64], Push) -> Result<Played, String> + 'a {
    let mut point = 0;
    move |drive: &[f64], push: Push| {
        point += 1;
        if offset == Offset::Current {
            return Err("a sound card's output is AC-coupled and cannot hold a DC current: hold the working points by an added mass (--offset mass) or a pressure (--offset pressure)".into());
        }
        let applied = operator.apply(point, push, offset)?;
        let (mut u, mut i) = (Vec::with_capacity(drive.len()), Vec::with_capacity(drive.len()));
        for chunk in drive.chunks(block.max(1)) {
            let b = device
                .play(chunk)?
                .ok_or_else(|| format!("{}: the device stopped at working point {point}", device.describe()))?;
            if b.u.len() != chunk.len() || b.i.len() != chunk.len() {
                return Err(format!(
                    "{}: a block of {} samples came back as {} / {} (voltage / current) at working point {point}",
                    device.describe(),
                    chunk.len(),
                    b.u.len(),
                    b.i.len()
                ));
            }
            u.extend(b.u);
            i.extend(b.i);
        }
        // The small signal stops and the cone comes to rest before the gauge is read (read
        // during the noise, it is off by the noise's own excursion: 3 % of SB17's first point).
        let settle = vec![0.0; (SETTLE_S * device.fs()) as usize];
        for chunk in settle.chunks(block.max(1)) {
            device
                .play(chunk)?
                .ok_or_else(|| format!("{}: the device stopped at working point {point}", device.describe()))?;
        }
        let x = operator.read_x(point)?;
        if !x.is_finite() {
            return Err(format!("working point {point}: the displacement {x} is not a number"));
        }
        Ok(Played { u, i, x: vec![x; drive.len()], applied })
    }
}

/// An operator on a terminal: says what to apply, reads what was applied and the gauge.
pub struct PromptOperator<R, W> {
    input: R,
    output: W,
}

impl<R: BufRead, W: Write> PromptOperator<R, W> {
    pub fn new(input: R, output: W) -> Self {
        PromptOperator { input, output }
    }

    /// Ask, and read one answer (`None`: an empty line); `q` stops the measurement.
    fn ask(&mut self, point: usize, question: &str) -> Result<Option<String>, String> {
        write!(self.output, "{question} ")
            .and_then(|_| self.output.flush())
            .map_err(|e| format!("cannot write the prompt: {e}"))?;
        let mut line = String::new();
        let n = self.input.read_line(&mut line).map_err(|e| format!("cannot read the answer: {e}"))?;
        if n == 0 {
            return Err(format!("working point {point}: the input ended before the answer (run quasistatic --card on a terminal, or pipe every answer)"));
        }
        let t = line.trim();
        if t.eq_ignore_ascii_case("q") {
            return Err(format!("stopped by the operator at working point {point}"));
        }
        Ok((!t.is_empty()).then(|| t.to_string()))
    }

    /// Ask for a number until one comes (three tries).
    fn number(&mut self, point: usize, question: &str, what: &str) -> Result<Option<f64>, String> {
        for _ in 0..3 {
            match self.ask(point, question)? {
                None => return Ok(None),
                Some(t) => match t.parse::<f64>() {
                    Ok(v) if v.is_finite() => return Ok(Some(v)),
                    _ => {
                        let _ = writeln!(self.output, "  '{t}' is not {what}");
                    }
                },
            }
        }
        Err(format!("working point {point}: no valid {what} in three answers"))
    }
}

impl<R: BufRead, W: Write> Operator for PromptOperator<R, W> {
    fn apply(&mut self, point: usize, push: Push, offset: Offset) -> Result<Option<Push>, String> {
        let side = if push.force > 0.0 { "coil out" } else { "coil in" };
        match offset {
            _ if push.force == 0.0 => {
                let what = if matches!(offset, Offset::Pressure { .. }) {
                    "vent the box"
                } else {
                    "take every mass off the cone"
                };
                self.ask(point, &format!("point {point} (rest): {what}; press Enter when the cone has settled"))?;
                Ok(None)
            }
            Offset::Mass => {
                let grams = 1e3 * push.added_mass;
                let facing = if push.force > 0.0 { "facing down (a hanging mass)" } else { "facing up" };
                let q = format!("point {point}: place about {grams:.1} g on the cone, the driver {facing} ({side}); press Enter, or type the mass you placed (g):");
                Ok(self.number(point, &q, "a mass in grams")?.map(|g| {
                    let m = g.abs() * 1e-3;
                    Push { force: push.force.signum() * m * GRAVITY, added_mass: m }
                }))
            }
            Offset::Pressure { sd } => {
                let pa = push.force / sd;
                let q = format!("point {point}: set the pressure on the diaphragm to {pa:+.1} Pa ({side}; + pushes the coil out); press Enter, or type the pressure you set (Pa, signed):");
                Ok(self.number(point, &q, "a pressure in pascals")?.map(|p| Push { force: p * sd, added_mass: 0.0 }))
            }
            Offset::Current => Err("the DC-current offset needs a DC-coupled output: not on a sound card".into()),
        }
    }

    fn read_x(&mut self, point: usize) -> Result<f64, String> {
        let q = format!("point {point}: the gauge's static displacement (mm, + = coil out):");
        for _ in 0..3 {
            if let Some(v) = self.number(point, &q, "a displacement in millimetres")? {
                return Ok(v * 1e-3);
            }
            let _ = writeln!(self.output, "  the displacement is needed: the stiffness comes from it");
        }
        Err(format!("working point {point}: no displacement given"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn op(script: &str) -> PromptOperator<std::io::Cursor<Vec<u8>>, Vec<u8>> {
        PromptOperator::new(std::io::Cursor::new(script.as_bytes().to_vec()), Vec::new())
    }

    #[test]
    fn prompts_read_what_was_applied_and_the_gauge() {
        let mut o = op("\n12.5\n-0.84\nabc\n\n+35\n0.6\nq\n");
        // Rest: nothing asked but Enter.
        assert_eq!(o.apply(1, Push::default(), Offset::Mass).unwrap(), None);
        // A mass asked for, another placed: the force keeps the side asked for.
        let asked = Push { force: -0.12, added_mass: 0.12 / GRAVITY };
        let got = o.apply(2, asked, Offset::Mass).unwrap().unwrap();
        assert!((got.added_mass - 0.0125).abs() < 1e-12 && (got.force + 0.0125 * GRAVITY).abs() < 1e-12, "{got:?}");
        assert!((o.read_x(2).unwrap() + 0.84e-3).abs() < 1e-15);
        // Not a number, then Enter: as asked.
        assert_eq!(o.apply(3, asked, Offset::Mass).unwrap(), None);
        let got = o.apply(4, Push { force: 0.4, added_mass: 0.0 }, Offset::Pressure { sd: 0.0133 }).unwrap().unwrap();
        assert!((got.force - 35.0 * 0.0133).abs() < 1e-12, "{got:?}");
        assert!((o.read_x(4).unwrap() - 0.6e-3).abs() < 1e-15);
        let e = o.read_x(5).unwrap_err();
        assert!(e.contains("stopped by the operator at working point 5"), "{e}");
        let e = o.read_x(6).unwrap_err();
        assert!(e.contains("input ended"), "{e}");
        let text = String::from_utf8(o.output).unwrap();
        assert!(
            text.contains("place about 12.2 g on the cone, the driver facing up (coil in)")
                && text.contains("'abc' is not a mass in grams"),
            "{text}"
        );
        assert!(text.contains("+30.1 Pa (coil out;"), "{text}");
    }

    #[test]
    fn a_dc_current_offset_is_refused_on_a_card() {
        struct Never;
        impl Operator for Never {
            fn apply(&mut self, _: usize, _: Push, _: Offset) -> Result<Option<Push>, String> {
                unreachable!()
            }
            fn read_x(&mut self, _: usize) -> Result<f64, String> {
                unreachable!()
            }
        }
        let p = coilscope_core::embedded_driver("sb17cac35-4").unwrap();
        let mut dev = crate::device::VirtualDevice::new(&p, 48000.0, (0.0, 0.0), 1).unwrap();
        let mut never = Never;
        let mut play = card_play(&mut dev, &mut never, Offset::Current, 4800);
        let e = play(&[0.1; 100], Push::default()).unwrap_err();
        assert!(e.contains("AC-coupled") && e.contains("--offset mass"), "{e}");
    }
}

//! The measurement chain inside the output error: the model driven by the voltage behind the
//! voltage channel's coupling and compared through the current channel's.

use super::*;

/// The measurement chain in the output error ([`coilscope_core::chain`]): the model is driven
/// by the voltage behind the voltage channel's AC coupling, and compared with the current
/// behind the current channel's coupling and delay, less offsets and hum:
///
/// ```text
/// u   = hp_inverse(u_rec - dc_u, hp_u)
/// r   = W ( i_model(u) - ( delay(hp_inverse(i_rec, hp_i), -tau) - sum_k c_k b_k ) )
/// ```
///
/// `W` is a fixed whitening high-pass ([`ChainSetup::whiten_hz`]). The unknowns follow the
/// layout's in theta: those of `terms` that are on (`tau` samples, `hp_u`, `hp_i` Hz), then
/// the `c_k` of the basis `b_k`: a constant and a ramp (an offset behind an AC coupling
/// integrates into both) and a cosine and a sine at each mains line (50 and 60 Hz and their
/// harmonics up to [`crate::linear::HUM_HARMONICS`]): the current channel's hum and what the
/// voltage channel's hum drives through the driver. Linear in the `c_k`; `tau` and `hp_i` act
/// on the record only (their Jacobian columns by central differences, no model run); `hp_u`
/// changes the drive (two model runs).
///
/// `dc_u`, the voltage channel's offset, is an unknown only behind an AC coupling
/// ([`ChainSetup::dc_u_free`]). There it becomes a constant plus a ramp
/// (`hp_inverse(1)[n] = 1/g + 2 K n`): a drive that moves the coil's rest position through the
/// record, which the nonlinearities see, so the data fix it. Held instead at the offset that
/// leaves the voltage least along that shape
/// ([`voltage_behind`](coilscope_core::chain::voltage_behind)), it also took the driver's
/// own low-frequency content: on SB17's `-real-chain` record (no offset on the voltage) it gave
/// -9e-5 V, Kms(x) came out tilted by +-0.2 % and the truth lay 13 sd outside its band (through
/// the harsh world's 1-5 Hz couplings: Kms 0.16-0.36 % off, the large coil 4.4 sd outside,
/// where the fitted offset gives 0.002-0.02 %).
///
/// On a DC-coupled voltage channel the record cannot tell an offset of the card from a DC the
/// amplifier puts on the driver: they differ only in a DC current, which moves the rest
/// position, and curves shifted along x describe the driver about it exactly. Fitted there,
/// `dc_u` wandered along that direction (5-40 mV off through the harsh world's DC-coupled
/// cards, Kms 0.9-4.2 % off at the range's edges, bands 10-30x the error). So it is held at
/// the convention that the drive has no mean over the record (x = 0 of the curves is the rest
/// position under the record's mean drive), and the drive's own mean, which that convention
/// cannot know, goes into the covariance ([`ChainSetup::dc_u_sd`], [`with_nuisance`]).
#[derive(Clone)]
pub struct ChainSetup {
    pub u_rec: Vec<f64>,
    pub i_rec: Vec<f64>,
    pub terms: crate::linear::ChainTerms,
    /// `(what, signal)`: `dc`, `ramp`, `cos 50`, `sin 50`, ...
    pub basis: Vec<(String, Vec<f64>)>,
    /// The basis signals' spectra as [`coilscope_core::chain::delay`] takes them (for its
    /// padding), computed once: the Jacobian's basis columns are the basis delayed by each
    /// iteration's `tau`, one inverse FFT each.
    pub(super) basis_spectra:
        std::sync::Arc<std::sync::Mutex<Option<std::sync::Arc<Vec<coilscope_core::chain::DelaySpectrum>>>>>,
    /// Corner (Hz) of the whitening high-pass put on the residual and the Jacobian (0: none):
    /// the current channel's coupling at the start estimate. Behind an inverted coupling the
    /// sensor noise is no longer white: below the corner it grows as `fc / f`, a random walk
    /// (1e-4 A over 10 s for SB17's 4 Hz current channel at 70 dB SNR). Unweighted, that walk
    /// pulled the current's offset 2.4 % off (5 sd) on SB17's `-real-chain` record, as the
    /// sandwich's blocks (0.05 s) cannot see it (Kms's tilt there was `dc_u`'s, not this). A
    /// fixed filter (not moved with theta) is a constant weighting: weighted least squares
    /// with the noise white again.
    pub whiten_hz: f64,
    /// `dc_u` is an unknown (in [`ChainSetup::u_unit`], after the corners); otherwise it is
    /// held at the offset that leaves the drive without a mean ([`ChainSetup::voltage`]).
    /// Held through the search; free in the final fit when the search's voltage corner is
    /// above [`DC_COUPLED_HZ`].
    pub dc_u_free: bool,
    /// Unit of a free `dc_u` in theta (V): 1e-5 of the recorded voltage's RMS (one unit is
    /// also the step of its Jacobian column's central difference).
    pub u_unit: f64,
    /// The last [`KEPT_TARGETS`] currents to match ([`ChainSetup::target`]), by the bits of
    /// the chain's unknowns: a fit asks for the one at its theta for the residual, again for
    /// the Jacobian's chain columns there and for the held-out part's run (an FFT pair of
    /// the record's padded length each, 0.26 M sines and cosines, the inverse coupling and
    /// the basis taken off). A clone starts empty (a setup changed by a clone keys its own).
    pub(super) targets: coilscope_core::recent::Recent<Vec<u64>, Vec<f64>>,
}

/// Currents to match a [`ChainSetup`] keeps.
pub(super) const KEPT_TARGETS: usize = 4;

impl ChainSetup {
    pub fn new(u_rec: &[f64], i_rec: &[f64], terms: crate::linear::ChainTerms) -> Self {
        let n = u_rec.len();
        let fs = terms.fs;
        // In units of the current's RMS, so that the unknowns are of order one as the
        // layout's are (and J^T J stays well conditioned).
        let a = coilscope_core::simulate::rms(i_rec).max(1e-12);
        let mut basis = vec![
            ("dc".to_string(), vec![a; n]),
            ("ramp".to_string(), (0..n).map(|m| a * m as f64 / n as f64).collect()),
        ];
        for f in crate::linear::mains_lines().into_iter().filter(|&f| f < 0.45 * fs) {
            let w = 2.0 * std::f64::consts::PI * f / fs;
            basis.push((format!("cos {f}"), (0..n).map(|m| a * (w * m as f64).cos()).collect()));
            basis.push((format!("sin {f}"), (0..n).map(|m| a * (w * m as f64).sin()).collect()));
        }
        let u_unit = 1e-5 * coilscope_core::simulate::rms(u_rec).max(1e-12);
        ChainSetup {
            u_rec: u_rec.to_vec(),
            i_rec: i_rec.to_vec(),
            terms,
            basis,
            basis_spectra: Default::default(),
            whiten_hz: 0.0,
            dc_u_free: false,
            u_unit,
            targets: coilscope_core::recent::Recent::new(KEPT_TARGETS),
        }
    }
    /// `v` (a residual or a Jacobian column over the fitted samples) through the whitening
    /// high-pass ([`ChainSetup::whiten_hz`]).
    pub fn whiten(&self, v: &mut [f64]) {
        if self.whiten_hz > 0.0 {
            let mut f = coilscope_core::chain::HighPass::new(self.whiten_hz, self.terms.fs);
            for x in v.iter_mut() {
                *x = f.push(*x);
            }
        }
    }
    /// [`ChainSetup::whiten`] on each column of `data` (column-major, `rows` a column; a
    /// Jacobian's storage), the same values to the last bit, on `threads` workers. The
    /// filter's recursion is one chain of dependent operations per column: four columns go
    /// through the loop together, so that their chains overlap (one at a time, the whitening
    /// of SB17 `-real-all`'s Jacobians took 3 % of `identify`'s time on one core).
    pub fn whiten_columns(&self, data: &mut [f64], rows: usize, threads: usize) {
        if !(self.whiten_hz > 0.0) || rows == 0 {
            return;
        }
        let filter = coilscope_core::chain::HighPass::new(self.whiten_hz, self.terms.fs);
        let four = |cols: &mut [f64]| {
            let mut f = [filter; 4];
            for m in 0..rows {
                for (c, f) in f.iter_mut().enumerate() {
                    cols[c * rows + m] = f.push(cols[c * rows + m]);
                }
            }
        };
        let work = |part: &mut [f64]| {
            let mut quads = part.chunks_exact_mut(4 * rows);
            for q in quads.by_ref() {
                four(q);
            }
            for col in quads.into_remainder().chunks_exact_mut(rows) {
                self.whiten(col);
            }
        };
        let ncols = data.len() / rows;
        if threads < 2 || ncols < 8 {
            return work(data);
        }
        // Two halves of whole groups of four columns.
        let (left, right) = data.split_at_mut((ncols / 8 * 4) * rows);
        std::thread::scope(|scope| {
            scope.spawn(|| work(left));
            work(right);
        });
    }
    /// Unknowns of the chain in theta.
    pub fn n(&self) -> usize {
        self.basis_index() + self.basis.len()
    }
    /// Index of a free `dc_u` in the chain's part of theta.
    pub fn dc_u_index(&self) -> Option<usize> {
        self.dc_u_free.then(|| self.terms.count())
    }
    /// Index of the basis' first coefficient in the chain's part of theta.
    pub fn basis_index(&self) -> usize {
        self.terms.count() + self.dc_u_free as usize
    }
    /// `[tau samples, hp_u Hz, hp_i Hz]` of the chain's part of theta.
    pub fn values(&self, th_c: &[f64]) -> [f64; 3] {
        self.terms.values(th_c)
    }
    /// The drive: the voltage behind the channel (coupling `hp_u` of `th_c`), less the offset
    /// `dc_u` (V); and `dc_u`. A free `dc_u` is theta's; a held one is the one that leaves the
    /// drive least along the offset's shape
    /// ([`voltage_behind`](coilscope_core::chain::voltage_behind): on a DC-coupled channel,
    /// without a mean).
    pub fn voltage(&self, th_c: &[f64]) -> (Vec<f64>, f64) {
        let fu = self.values(th_c)[1];
        let Some(k) = self.dc_u_index() else {
            return coilscope_core::chain::voltage_behind(&self.u_rec, fu, self.terms.fs);
        };
        let dc = th_c[k] * self.u_unit;
        let mut u = coilscope_core::chain::hp_inverse(&self.u_rec, fu, self.terms.fs);
        if dc != 0.0 {
            let shape = coilscope_core::chain::offset_behind(u.len(), fu, self.terms.fs);
            u.iter_mut().zip(&shape).for_each(|(v, o)| *v -= dc * o);
        }
        (u, dc)
    }
    /// The voltage channel's offset (V) at coupling `hp_u` (Hz): see [`ChainSetup::voltage`].
    pub fn dc_u(&self, hp_u: f64) -> f64 {
        coilscope_core::chain::voltage_behind(&self.u_rec, hp_u, self.terms.fs).1
    }
    /// The sd (V) of `dc_u` that the drive's own mean leaves: the convention takes the drive's
    /// mean over the record as 0, which it is only to within its sampling spread, about
    /// `sqrt(S(0) / T)`. `S(0)` is read off the drive's lowest DFT bins (below
    /// [`DRIVE_MEAN_HZ`], at least four; `E|X_k|^2 = E|X_0|^2` for a spectrum flat there);
    /// behind an AC coupling, divided by the offset's shape's mean.
    pub fn dc_u_sd(&self, th_c: &[f64]) -> f64 {
        let fu = self.values(th_c)[1];
        let (u, _) = self.voltage(th_c);
        let n = u.len();
        let fs = self.terms.fs;
        let bins = ((DRIVE_MEAN_HZ * n as f64 / fs) as usize).max(4).min(n / 2);
        let spec = coilscope_core::fft::rfft(&u);
        let power = spec[1..=bins].iter().map(|x| x.norm_sqr()).sum::<f64>() / bins as f64;
        // A drive mean m moves dc_u by m sum(s) / sum(s^2), s the offset's shape.
        let shape = coilscope_core::chain::offset_behind(n, fu, fs);
        let gain = shape.iter().sum::<f64>() / shape.iter().map(|v| v * v).sum::<f64>();
        power.sqrt() / n as f64 * gain.abs()
    }
    /// The current the model must match: behind coupling and delay, less the basis.
    ///
    /// The basis comes off before the delay, as the card added offset and hum before the
    /// record was read: behind the inverted coupling an offset is a ramp that ends at up to
    /// 1.7x the current's peak (1 % offset, 4.7 Hz), and delaying it by FFT rings at the
    /// record's ends where the zero padding cuts it (taken off after the delay, that ringing
    /// stayed in the residual).
    pub fn target(&self, th_c: &[f64]) -> Vec<f64> {
        let key = th_c.iter().map(|v| v.to_bits()).collect();
        let tau = self.values(th_c)[0];
        self.targets
            .get_or_compute(key, || self.targets_delayed(th_c, &[tau]).pop().expect("one delay, one target"))
            .as_ref()
            .clone()
    }
    /// [`ChainSetup::target`] at `th_c` with the delay (samples) taken as each of `taus`
    /// instead (the delay's Jacobian column): the current behind the coupling, less the
    /// basis, once, then delayed by each ([`coilscope_core::chain::delays`]). The same values
    /// to the last bit as `target` of `th_c` with each delay.
    pub(super) fn targets_delayed(&self, th_c: &[f64], taus: &[f64]) -> Vec<Vec<f64>> {
        let fi = self.values(th_c)[2];
        let mut t = coilscope_core::chain::hp_inverse(&self.i_rec, fi, self.terms.fs);
        let c = &th_c[self.basis_index()..];
        for (ck, (_, b)) in c.iter().zip(&self.basis) {
            if *ck != 0.0 {
                for (v, bv) in t.iter_mut().zip(b) {
                    *v -= ck * bv;
                }
            }
        }
        coilscope_core::chain::delays(&t, &taus.iter().map(|&tau| -tau).collect::<Vec<f64>>())
    }
    /// The basis signals' spectra for a delay of `samples` ([`ChainSetup::basis_spectra`]),
    /// computed on `threads` workers when first asked for or when the padding changes.
    pub(super) fn basis_delayer(
        &self,
        samples: f64,
        threads: usize,
    ) -> std::sync::Arc<Vec<coilscope_core::chain::DelaySpectrum>> {
        let pad = coilscope_core::chain::delay_pad(samples);
        let mut kept = self.basis_spectra.lock().expect("basis spectra");
        if kept.as_ref().is_none_or(|v| v.first().is_some_and(|s| s.pad != pad)) {
            *kept = Some(std::sync::Arc::new(parallel_map(self.basis.len(), threads, |k| {
                coilscope_core::chain::DelaySpectrum::new(&self.basis[k].1, pad)
            })));
        }
        kept.clone().expect("just computed")
    }

    /// The chain's theta at the linear fit's estimate, the offset and ramp by least squares
    /// on the current behind the chain (the driver's current has neither), hum at 0.
    pub fn theta0(&self, est: &[f64; 3]) -> Vec<f64> {
        let on = self.terms.on();
        let mut th: Vec<f64> = (0..3).filter(|&k| on[k]).map(|k| est[k]).collect();
        if self.dc_u_free {
            // A free dc_u starts at the projection (voltage_behind).
            th.push(coilscope_core::chain::voltage_behind(&self.u_rec, est[1], self.terms.fs).1 / self.u_unit);
        }
        let nc = th.len();
        th.resize(self.n(), 0.0);
        let t = self.target(&th);
        let (b0, b1) = (&self.basis[0].1, &self.basis[1].1);
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
        let m = nalgebra::Matrix2::new(dot(b0, b0), dot(b0, b1), dot(b1, b0), dot(b1, b1));
        if let Some(inv) = m.try_inverse() {
            let c = inv * nalgebra::Vector2::new(dot(b0, &t), dot(b1, &t));
            th[nc] = c[0];
            th[nc + 1] = c[1];
        }
        th
    }
}

//! Tests of the integrators, each against a slow reference.

use super::*;

struct Decay {
    lambda: f64,
}
impl Dynamics<f64, 1> for Decay {
    fn deriv(&self, y: &[f64; 1], u: f64) -> [f64; 1] {
        [-self.lambda * y[0] + u]
    }
}

/// `[x, v, i, i2]`: a stiff RL network (`a`, 1/s) driven by `u`, and a spring-mass
/// system the current pushes (`f = g i`), with a cubic spring to make it nonlinear.
struct Network {
    a: [[f64; 2]; 2],
    g: f64,
    k3: f64,
}
impl<D: DualNum<Primitive = f64> + Copy> Dynamics<D, 4> for Network {
    fn deriv(&self, y: &[D; 4], u: D) -> [D; 4] {
        let [x, v, i, i2] = *y;
        let a = &self.a;
        [
            v,
            i * self.g - x * 4.0e4 - x * x * x * self.k3 - v * 20.0,
            i * a[0][0] + i2 * a[0][1] + u,
            i * a[1][0] + i2 * a[1][1],
        ]
    }
}
impl<D: DualNum<Primitive = f64> + Copy> Electrical<D, 4> for Network {
    fn electrical(&self, _: &[D; 4]) -> [[D; 2]; 2] {
        std::array::from_fn(|r| std::array::from_fn(|c| D::from(self.a[r][c])))
    }
    fn input(&self, _: &[D; 4]) -> D {
        D::one()
    }
}

fn reference(sys: &Network, y0: [f64; 4], t: f64, u: &dyn Fn(f64) -> f64) -> [f64; 4] {
    let n = 200_000;
    let h = t / n as f64;
    let mut y = y0;
    for k in 0..n {
        let t0 = k as f64 * h;
        y = rk4_step(sys, &y, h, u(t0), u(t0 + 0.5 * h), u(t0 + h));
    }
    y
}

/// A microspeaker-like network: eigenvalues about -4.7e5 and -0.9e5 /s.
const STIFF: [[f64; 2]; 2] = [[-3.2e5, 6.7e4], [1.3e5, -1.3e5]];

#[test]
fn an_exponential_step_integrates_a_stiff_network_exactly() {
    // Constant drive, no coupling to the mechanics (g = 0): the currents' solution is
    // e^{Ah} y + A^-1 (e^{Ah} - I) b u, which the method reproduces at any step.
    let sys = Network { a: STIFF, g: 0.0, k3: 0.0 };
    let y0 = [0.0, 0.0, 0.3, -0.1];
    let h = 1.0 / 48000.0; // |lambda| h = 10
    let exact = reference(&sys, y0, h, &|_| 2.0e5);
    let k = EtdCoefficients::new(&sys.electrical(&y0), h);
    let y = etd4_step(&sys, &y0, &k, [2.0e5; 3], None);
    for j in 2..4 {
        assert!((y[j] - exact[j]).abs() < 1e-12 * exact[j].abs().max(1.0), "state {j}: {} vs {}", y[j], exact[j]);
    }
    // RK4 with one step is unstable there (|lambda| h = 10 > 2.78).
    let r = rk4_step(&sys, &y0, h, 2.0e5, 2.0e5, 2.0e5);
    assert!((r[2] - exact[2]).abs() > 1.0, "{}", r[2]);
}

/// `phi_k(M)` of a 2 x 2 matrix by its Taylor series `sum_j M^j / (j + k)!` (200 terms):
/// slow, and obviously the definition.
fn slow_phi(m: [[f64; 2]; 2], k: usize) -> [[f64; 2]; 2] {
    let mul = |x: [[f64; 2]; 2], y: [[f64; 2]; 2]| -> [[f64; 2]; 2] {
        std::array::from_fn(|r| std::array::from_fn(|c| x[r][0] * y[0][c] + x[r][1] * y[1][c]))
    };
    let mut sum = [[0.0; 2]; 2];
    let mut power = [[1.0, 0.0], [0.0, 1.0]];
    let mut fact: f64 = (1..=k).map(|v| v as f64).product();
    for j in 0..200 {
        for r in 0..2 {
            for c in 0..2 {
                sum[r][c] += power[r][c] / fact;
            }
        }
        power = mul(power, m);
        fact *= (j + k + 1) as f64;
    }
    sum
}

/// The coefficients held as pairs `p I + q A` are Hochbruck and
/// Ostermann's matrices (Eq. 5.19) computed from the slow series of each `phi_j(c h A)`,
/// for a microspeaker's network (`|lambda| h` = 10, the closed forms) and a woofer's
/// (0.3, the series).
#[test]
fn pairs_are_the_matrix_coefficients() {
    let h = 1.0 / 48000.0;
    for (a, tol) in [(STIFF, 1e-8), ([[-1.2e4, 2.0e3], [3.0e3, -3.0e3]], 1e-12)] {
        let k = EtdCoefficients::new(&a, h);
        let scaled = |c: f64| -> [[f64; 2]; 2] { std::array::from_fn(|r| std::array::from_fn(|j| a[r][j] * c * h)) };
        let ph = |j: usize, c: f64| slow_phi(scaled(c), j);
        let comb = |terms: &[([[f64; 2]; 2], f64)], scale: f64| -> [[f64; 2]; 2] {
            std::array::from_fn(|r| {
                std::array::from_fn(|c| scale * terms.iter().map(|(m, w)| m[r][c] * w).sum::<f64>())
            })
        };
        let a52 = comb(&[(ph(2, 0.5), 0.5), (ph(3, 1.0), -1.0), (ph(2, 1.0), 0.25), (ph(3, 0.5), -0.5)], 1.0);
        let a54 = comb(&[(ph(2, 0.5), 0.25), (a52, -1.0)], 1.0);
        let a51 = comb(&[(ph(1, 0.5), 0.5), (a52, -2.0), (a54, -1.0)], 1.0);
        let cases: [(&str, &Pair<f64>, [[f64; 2]; 2]); 13] = [
            ("e5", &k.e5, ph(0, 0.5)),
            ("e1", &k.e1, ph(0, 1.0)),
            ("a21", &k.a21, comb(&[(ph(1, 0.5), 0.5)], h)),
            ("a31", &k.a31, comb(&[(ph(1, 0.5), 0.5), (ph(2, 0.5), -1.0)], h)),
            ("a32", &k.a32, comb(&[(ph(2, 0.5), 1.0)], h)),
            ("a41", &k.a41, comb(&[(ph(1, 1.0), 1.0), (ph(2, 1.0), -2.0)], h)),
            ("a42", &k.a42, comb(&[(ph(2, 1.0), 1.0)], h)),
            ("a51", &k.a51, comb(&[(a51, 1.0)], h)),
            ("a52", &k.a52, comb(&[(a52, 1.0)], h)),
            ("a54", &k.a54, comb(&[(a54, 1.0)], h)),
            ("b1", &k.b1, comb(&[(ph(1, 1.0), 1.0), (ph(2, 1.0), -3.0), (ph(3, 1.0), 4.0)], h)),
            ("b4", &k.b4, comb(&[(ph(2, 1.0), -1.0), (ph(3, 1.0), 4.0)], h)),
            ("b5", &k.b5, comb(&[(ph(2, 1.0), 4.0), (ph(3, 1.0), -8.0)], h)),
        ];
        for (name, pair, want) in cases {
            let scale = want.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
            for r in 0..2 {
                for c in 0..2 {
                    let got = if r == c { pair.p } else { 0.0 } + pair.q * a[r][c];
                    assert!(
                        (got - want[r][c]).abs() <= tol * scale,
                        "{name}[{r}][{c}]: {got:e} vs {:e} (|A h| {:.1})",
                        want[r][c],
                        a[0][0].abs() * h
                    );
                }
            }
        }
    }
}

/// With two steps or more per sample the exponential method takes the drive exactly, as
/// the quartic through five points of each step (its own, at quarter steps): a stiff
/// network (`|lambda| h` = 5 per step) under a quartic drive comes out exact, where the
/// method's own quadrature (one step per sample, the drive in `N`) misses by the
/// drive's cubic and quartic parts.
#[test]
fn the_exponential_method_takes_a_quartic_drive_exactly() {
    let sys = Network { a: STIFF, g: 0.0, k3: 0.0 };
    let y0 = [0.0, 0.0, 0.3, -0.1];
    let dt = 1.0 / 48000.0;
    let u = |t: f64| {
        let s = t / dt;
        2.0e5 * (1.0 - 0.7 * s + 1.9 * s * s - 2.3 * s * s * s + 1.1 * s * s * s * s)
    };
    let exact = reference(&sys, y0, dt, &u);
    for n in [2usize, 3, 5] {
        let pts: Vec<f64> = (0..=4 * n).map(|j| u(j as f64 * dt / (4 * n) as f64)).collect();
        let y = etd4_sample(&sys, &y0, dt, &pts);
        for j in 2..4 {
            assert!(
                (y[j] - exact[j]).abs() < 1e-10 * exact[j].abs().max(1.0),
                "{n} steps, state {j}: {} vs {}",
                y[j],
                exact[j]
            );
        }
    }
    let pts: Vec<f64> = (0..=2).map(|j| u(j as f64 * dt / 2.0)).collect();
    let one = etd4_sample(&sys, &y0, dt, &pts);
    assert!((one[2] - exact[2]).abs() > 1e-4 * exact[2].abs(), "one step: {} vs {}", one[2], exact[2]);
}

/// The current's exponential method takes the current's decay and a
/// quartic drive exactly: a woofer's current equation alone (`|c| h` = 0.6 per sample, no
/// coupling) under a quartic drive comes out exact at one step per sample, where RK4
/// (one sub-step, the drive at three points) misses by the decay's and the drive's
/// higher terms.
#[test]
fn the_current_exponential_method_takes_the_decay_and_a_quartic_drive_exactly() {
    let sys = Network { a: [[-2.9e4, 0.0], [0.0, 0.0]], g: 0.0, k3: 0.0 };
    let y0 = [0.0, 0.0, 0.3, -0.1];
    let dt = 1.0 / 48000.0;
    let u = |t: f64| {
        let s = t / dt;
        2.0e3 * (1.0 - 0.7 * s + 1.9 * s * s - 2.3 * s * s * s + 1.1 * s * s * s * s)
    };
    let exact = reference(&sys, y0, dt, &u);
    for n in [1usize, 2] {
        let pts: Vec<f64> = (0..=4 * n).map(|j| u(j as f64 * dt / (4 * n) as f64)).collect();
        let y = etdc_sample(&sys, &y0, dt, &pts);
        assert!((y[2] - exact[2]).abs() < 1e-12 * exact[2].abs(), "{n} steps: {} vs {}", y[2], exact[2]);
        assert_eq!(y[3], y0[3]);
    }
    let rk = rk4_sample(&sys, &y0, dt, &[u(0.0), u(0.5 * dt), u(dt)]);
    assert!((rk[2] - exact[2]).abs() > 1e-5 * exact[2].abs(), "RK4: {} vs {}", rk[2], exact[2]);
}

/// Relative errors (the larger of x's and i's) at 2 ms of 192, 384 and 768 steps of
/// `step(sys, y, h, [u0, um, u1])` on the stiff network coupled to a nonlinear spring-mass
/// system under a smooth two-tone drive (192 steps: 10.4 us, `|lambda| h` = 4.9, half a
/// sample at 48 kHz), against a tiny-step RK4 reference.
fn coupled_errors(step: impl Fn(&Network, &[f64; 4], f64, [f64; 3]) -> [f64; 4]) -> [f64; 3] {
    let sys = Network { a: STIFF, g: 3.0e3, k3: 2.0e9 };
    let u = |t: f64| {
        4.0e4 * (2.0 * std::f64::consts::PI * 700.0 * t).sin() + 1.0e4 * (2.0 * std::f64::consts::PI * 2300.0 * t).cos()
    };
    let t_end = 2.0e-3;
    let y0 = [1e-4, 0.0, 0.0, 0.0];
    let exact = reference(&sys, y0, t_end, &u);
    [192, 384, 768].map(|n: usize| {
        let h = t_end / n as f64;
        let mut y = y0;
        for s in 0..n {
            let t0 = s as f64 * h;
            y = step(&sys, &y, h, [u(t0), u(t0 + 0.5 * h), u(t0 + h)]);
        }
        ((y[0] - exact[0]) / exact[0]).abs().max(((y[2] - exact[2]) / exact[2]).abs())
    })
}

#[test]
fn the_exponential_method_is_fourth_order_on_the_coupled_system() {
    // A smooth drive and the nonlinear mechanics: halving h divides the error by ~16
    // even though |lambda| h stays far above RK4's stability limit.
    let [e1, e2, e3] =
        coupled_errors(|sys, y, h, u| etd4_step(sys, y, &EtdCoefficients::new(&sys.electrical(y), h), u, None));
    assert!(e2 < 1e-5, "{e2:.3e}");
    let (r1, r2) = (e1 / e2, e2 / e3);
    assert!(r1 > 11.0 && r2 > 13.0, "error ratios {r1:.1}, {r2:.1} ({e1:.2e}, {e2:.2e}, {e3:.2e})");
}

/// The exponential midpoint rule ([`etd2_step`], the stiff drivers' search Jacobians)
/// integrates the network exactly under a drive quadratic in time (its drive terms), at
/// `|lambda| h` = 10; on the coupled nonlinear system it is second order.
#[test]
fn the_exponential_midpoint_rule_is_exact_on_the_network_and_second_order() {
    let sys = Network { a: STIFF, g: 0.0, k3: 0.0 };
    let y0 = [0.0, 0.0, 0.3, -0.1];
    let h = 1.0 / 48000.0;
    let u = |t: f64| 2.0e5 + 3.0e9 * t - 4.0e13 * t * t;
    let exact = reference(&sys, y0, h, &u);
    let k = Etd2Coefficients::new(&sys.electrical(&y0), h);
    let y = etd2_step(&sys, &y0, &k, 1.0, u(0.0), u(0.5 * h), u(h));
    for j in 2..4 {
        assert!((y[j] - exact[j]).abs() < 1e-11 * exact[j].abs().max(1.0), "state {j}: {} vs {}", y[j], exact[j]);
    }
    let [e1, e2, e3] = coupled_errors(|sys, y, h, [u0, um, u1]| {
        etd2_step(sys, y, &Etd2Coefficients::new(&sys.electrical(y), h), 1.0, u0, um, u1)
    });
    assert!(e1 < 1e-3, "{e1:.3e}");
    let (r1, r2) = (e1 / e2, e2 / e3);
    assert!(r1 > 3.0 && r2 > 3.5, "error ratios {r1:.1}, {r2:.1} ({e1:.2e}, {e2:.2e}, {e3:.2e})");
}

/// `[x, v, i, i2, -, -, i3]` (the currents where [`crate::model::ExtModel`] keeps them):
/// a stiff 3 x 3 RL network (`a`, 1/s; the LR-3 branch's current `i3`) driven by `u`,
/// and the spring-mass system the current pushes, as [`Network`].
struct Network3<D> {
    a: [[D; 3]; 3],
    g: f64,
    k3: f64,
}
impl<D: DualNum<Primitive = f64> + Copy> Dynamics<D, 7> for Network3<D> {
    fn deriv(&self, y: &[D; 7], u: D) -> [D; 7] {
        let [x, v, i, i2, _, _, i3] = *y;
        let a = &self.a;
        let z = D::zero();
        [
            v,
            i * self.g - x * 4.0e4 - x * x * x * self.k3 - v * 20.0,
            a[0][0] * i + a[0][1] * i2 + a[0][2] * i3 + u,
            a[1][0] * i + a[1][1] * i2 + a[1][2] * i3,
            z,
            z,
            a[2][0] * i + a[2][1] * i2 + a[2][2] * i3,
        ]
    }
}
impl<D: DualNum<Primitive = f64> + Copy> Electrical<D, 7> for Network3<D> {
    fn electrical(&self, _: &[D; 7]) -> [[D; 2]; 2] {
        unreachable!("the 3 x 3 network is taken")
    }
    fn network3(&self, _: &[D; 7]) -> Option<[[D; 3]; 3]> {
        Some(self.a)
    }
    fn input(&self, _: &[D; 7]) -> D {
        D::one()
    }
}

/// `-L^-1 R` of a microspeaker with an LR-3 branch (Le 30 uH, L2 15 uH, L3 5 uH, Re 7.5,
/// R2 2, R3 `r3` ohm): eigenvalues about -7e5, -3.5e5 and -0.6e5 /s with `r3` = 3, so
/// `|lambda| h` up to 15 at 48 kHz.
fn lr3_network<D: DualNum<Primitive = f64> + Copy>(r3: D) -> [[D; 3]; 3] {
    let (le, l2, l3, re, r2) = (30e-6, 15e-6, 5e-6, 7.5, 2.0);
    let z = D::zero();
    [
        [-(r3 + (re + r2)) / le, D::from(r2 / le), r3 / le],
        [D::from(r2 / l2), D::from(-r2 / l2), z],
        [r3 / l3, z, -r3 / l3],
    ]
}

fn reference3<D: DualNum<Primitive = f64> + Copy>(
    sys: &Network3<D>,
    y0: [D; 7],
    t: f64,
    u: &dyn Fn(f64) -> f64,
) -> [D; 7] {
    let n = 200_000;
    let h = t / n as f64;
    let mut y = y0;
    for k in 0..n {
        let t0 = k as f64 * h;
        y = rk4_step(sys, &y, h, D::from(u(t0)), D::from(u(t0 + 0.5 * h)), D::from(u(t0 + h)));
    }
    y
}

/// The three eigenvalues of an LR-3 network's matrix are the roots
/// of its characteristic polynomial (to 1e-12 of the largest), in order, with the trace
/// and the determinant theirs, and their dual parts the roots' derivatives (central
/// differences); also with two branches of the same time constant and with a vanishing
/// one (R3 1e-6 ohm), where two roots nearly meet.
#[test]
fn the_lr3_networks_eigenvalues_are_its_characteristic_roots() {
    for r3 in [3.0, 0.5, 1e-6] {
        for (name, a) in [
            ("microspeaker", lr3_network(Dual64::from(r3).derivative())),
            ("equal corners", {
                let mut a = lr3_network(Dual64::from(r3).derivative());
                // L3 = L2 R3 / R2: the branches' time constants equal.
                let g = a[1][0];
                a[2][0] = g;
                a[2][2] = -g;
                a
            }),
        ] {
            let mu = net::eigenvalues3(&a);
            let af: [[f64; 3]; 3] = std::array::from_fn(|r| std::array::from_fn(|c| a[r][c].re));
            let big = mu.iter().fold(0.0f64, |m, v| m.max(v.re.abs()));
            assert!(mu[0].re >= mu[1].re && mu[1].re >= mu[2].re, "{name} {r3}: order {mu:?}");
            let tr = af[0][0] + af[1][1] + af[2][2];
            assert!((mu.iter().map(|v| v.re).sum::<f64>() - tr).abs() < 1e-12 * big, "{name} {r3}: trace");
            let det = af[0][0] * (af[1][1] * af[2][2] - af[1][2] * af[2][1])
                - af[0][1] * (af[1][0] * af[2][2] - af[1][2] * af[2][0])
                + af[0][2] * (af[1][0] * af[2][1] - af[1][1] * af[2][0]);
            assert!((mu.iter().map(|v| v.re).product::<f64>() - det).abs() < 1e-9 * det.abs(), "{name} {r3}: det");
            // The derivatives d mu / d R3 against central differences of the f64 roots.
            let roots = |r: f64| {
                let mut m = lr3_network(r);
                if name == "equal corners" {
                    let g = m[1][0];
                    m[2][0] = g;
                    m[2][2] = -g;
                }
                net::eigenvalues3(&m)
            };
            let d = 1e-6 * r3;
            let (hi, lo) = (roots(r3 + d), roots(r3 - d));
            for k in 0..3 {
                let fd = (hi[k] - lo[k]) / (2.0 * d);
                let scale = (big / r3).max(fd.abs());
                assert!((mu[k].eps - fd).abs() < 1e-4 * scale, "{name} {r3}: d mu{k}/dR3 {} vs {fd}", mu[k].eps);
            }
        }
    }
}

/// With an LR-3 branch the exponential method integrates the 3 x 3
/// network of `i`, `i2` and `i3` exactly (a constant drive, no mechanics: `|lambda| h` =
/// 15, where one RK4 step diverges), and takes a quartic drive exactly at two steps or
/// more, as the 2 x 2 network's tests above; the exponential midpoint rule (a stiff
/// driver's search Jacobians) too, under a drive quadratic in time.
#[test]
fn an_exponential_step_integrates_a_stiff_lr3_network_exactly() {
    let sys = Network3 { a: lr3_network(3.0), g: 0.0, k3: 0.0 };
    let y0 = [0.0, 0.0, 0.3, -0.1, 0.0, 0.0, 0.2];
    let dt = 1.0 / 48000.0;
    let states = [2, 3, 6];
    let check = |y: &[f64; 7], exact: &[f64; 7], tol: f64, what: &str| {
        for j in states {
            assert!(
                (y[j] - exact[j]).abs() < tol * exact[j].abs().max(1.0),
                "{what}, state {j}: {} vs {}",
                y[j],
                exact[j]
            );
        }
    };
    let exact = reference3(&sys, y0, dt, &|_| 2.0e5);
    check(&etd4_sample(&sys, &y0, dt, &[2.0e5; 3]), &exact, 1e-12, "one step, constant drive");
    let r = rk4_step(&sys, &y0, dt, 2.0e5, 2.0e5, 2.0e5);
    assert!((r[2] - exact[2]).abs() > 1.0, "one RK4 step: {}", r[2]);
    let u = |t: f64| {
        let s = t / dt;
        2.0e5 * (1.0 - 0.7 * s + 1.9 * s * s - 2.3 * s * s * s + 1.1 * s * s * s * s)
    };
    let exact = reference3(&sys, y0, dt, &u);
    for n in [2usize, 3, 5] {
        let pts: Vec<f64> = (0..=4 * n).map(|j| u(j as f64 * dt / (4 * n) as f64)).collect();
        check(&etd4_sample(&sys, &y0, dt, &pts), &exact, 1e-10, &format!("{n} steps, quartic drive"));
    }
    let q = |t: f64| 2.0e5 + 3.0e9 * t - 4.0e13 * t * t;
    let exact = reference3(&sys, y0, dt, &q);
    check(
        &etd2_sample(&sys, &y0, dt, &[q(0.0), q(0.5 * dt), q(dt)]),
        &exact,
        1e-11,
        "exponential midpoint, quadratic drive",
    );
}

/// On the LR-3 network coupled to the nonlinear mechanics the
/// exponential method stays fourth order (`|lambda| h` from 7.5 down to 1.9), the
/// exponential midpoint rule second order; and dual numbers through a sample's steps
/// carry the sensitivity to R3 (against central differences), through the eigenvalues'
/// derivatives.
#[test]
fn the_exponential_method_is_fourth_order_with_an_lr3_branch_and_carries_its_sensitivity() {
    let sys = Network3 { a: lr3_network(3.0), g: 3.0e3, k3: 2.0e9 };
    let u = |t: f64| {
        4.0e4 * (2.0 * std::f64::consts::PI * 700.0 * t).sin() + 1.0e4 * (2.0 * std::f64::consts::PI * 2300.0 * t).cos()
    };
    let t_end = 2.0e-3;
    let y0 = [1e-4, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
    let exact = reference3(&sys, y0, t_end, &u);
    let errors = |sample: &dyn Fn(&[f64; 7], f64, &[f64]) -> [f64; 7], pts: usize| {
        [192usize, 384, 768, 1536].map(|n| {
            let h = t_end / n as f64;
            let mut y = y0;
            for s in 0..n {
                let t0 = s as f64 * h;
                let p: Vec<f64> = (0..pts).map(|j| u(t0 + h * j as f64 / (pts - 1) as f64)).collect();
                y = sample(&y, h, &p);
            }
            ((y[0] - exact[0]) / exact[0])
                .abs()
                .max(((y[2] - exact[2]) / exact[2]).abs())
                .max(((y[6] - exact[6]) / exact[6]).abs())
        })
    };
    let [e1, e2, e3, e4] = errors(&|y, h, p| etd4_sample(&sys, y, h, p), 3);
    // (Measured: 7.4e-5, 8.5e-6, 6.8e-7, 4.6e-8: ratios 8.6, 12.5, 14.9 as |lambda| h
    // falls from 7.3 to 0.9, the 2 x 2 network's fastest mode being half as fast.)
    assert!(e2 < 1e-5, "{e2:.3e}");
    assert!(e1 / e2 > 7.0 && e2 / e3 > 11.0 && e3 / e4 > 13.0, "exponential: {e1:.2e}, {e2:.2e}, {e3:.2e}, {e4:.2e}");
    let [m1, m2, m3, m4] = errors(&|y, h, p| etd2_sample(&sys, y, h, p), 3);
    assert!(
        m1 < 1e-3 && m1 / m2 > 3.0 && m2 / m3 > 3.5 && m3 / m4 > 3.5,
        "exponential midpoint: {m1:.2e}, {m2:.2e}, {m3:.2e}, {m4:.2e}"
    );
    // d(state)/dR3 over ten samples of two steps.
    let dt = 1.0 / 48000.0;
    let run = |r3: Dual64| {
        let sys = Network3 { a: lr3_network(r3), g: 3.0e3, k3: 2.0e9 };
        let mut y: [Dual64; 7] = [Dual64::from(0.0); 7];
        for m in 0..10 {
            let pts: Vec<Dual64> = (0..=8).map(|j| Dual64::from(u((m as f64 + j as f64 / 8.0) * dt))).collect();
            y = etd4_sample(&sys, &y, dt, &pts);
        }
        y
    };
    let exact = run(Dual64::from(3.0).derivative());
    let d = 1e-5;
    let (hi, lo) = (run(Dual64::from(3.0 + d)), run(Dual64::from(3.0 - d)));
    for j in [0, 2, 3, 6] {
        let fd = (hi[j].re - lo[j].re) / (2.0 * d);
        assert!((exact[j].eps - fd).abs() < 1e-5 * fd.abs(), "state {j}: {} vs {fd}", exact[j].eps);
    }
}

#[test]
fn the_scalar_phi_functions_agree_across_their_two_evaluations() {
    // The series (|z| < 0.5) and the closed forms meet without a jump, and match
    // phi_k(z) = sum_j z^j / (j + k)! computed slowly.
    for z in [-0.5f64 - 1e-12, -0.5 + 1e-12, 0.4999999, 0.5000001, -0.2, 1e-9, -3.0, -40.0] {
        let (p, p4): ([f64; 6], [f64; 4]) = (phis(z), phis(z));
        for k in 0..4 {
            assert!((p4[k] - p[k]).abs() <= 1e-15 * p[k].abs(), "phi_{k}({z}): {} vs {}", p4[k], p[k]);
        }
        let slow = |k: usize| {
            if z.abs() > 1.0 {
                // phi_k from its definition in exact-enough arithmetic for large |z|.
                let mut v = z.exp();
                let mut f = 1.0;
                for j in 0..k {
                    v = (v - 1.0 / f) / z;
                    f *= (j + 1) as f64;
                }
                v
            } else {
                let mut sum = 0.0;
                let mut f: f64 = (1..=k).map(|v| v as f64).product();
                for j in 0..40 {
                    sum += z.powi(j) / f;
                    f *= (j as usize + k + 1) as f64;
                }
                sum
            }
        };
        // phi_4 and phi_5 by the recurrence just above |z| = 0.5 lose digits (see phis).
        for k in 0..6 {
            let tol = if k < 4 { 1e-14 } else { 1e-11 };
            assert!((p[k] - slow(k)).abs() < tol * slow(k).abs().max(1e-3), "phi_{k}({z}) = {} vs {}", p[k], slow(k));
        }
    }
}

#[test]
fn dual_numbers_carry_the_exponential_steps_sensitivity() {
    // d y(t) / d a00 through ten exponential steps equals a central difference.
    use num_dual::Dual64;
    let run = |d: Dual64| -> Dual64 {
        struct P(Dual64);
        impl Dynamics<Dual64, 4> for P {
            fn deriv(&self, y: &[Dual64; 4], u: Dual64) -> [Dual64; 4] {
                let sys = Network { a: STIFF, g: 3.0e3, k3: 2.0e9 };
                let mut d = sys.deriv(y, u);
                d[2] += (self.0 - STIFF[0][0]) * y[2];
                d
            }
        }
        impl Electrical<Dual64, 4> for P {
            fn electrical(&self, _: &[Dual64; 4]) -> [[Dual64; 2]; 2] {
                [[self.0, Dual64::from(STIFF[0][1])], [Dual64::from(STIFF[1][0]), Dual64::from(STIFF[1][1])]]
            }
            fn input(&self, _: &[Dual64; 4]) -> Dual64 {
                Dual64::from(1.0)
            }
        }
        let sys = P(d);
        let mut y = [Dual64::from(1e-4), Dual64::from(0.0), Dual64::from(0.1), Dual64::from(0.0)];
        let h = 1.0 / 48000.0;
        for s in 0..10 {
            let u = Dual64::from(3.0e4 * (s as f64 * 0.7).sin());
            let k = EtdCoefficients::new(&sys.electrical(&y), h);
            y = etd4_step(&sys, &y, &k, [u; 3], None);
        }
        y[0]
    };
    let a = STIFF[0][0];
    let exact = run(Dual64::from(a).derivative()).eps;
    let step = 1.0;
    let fd = (run(Dual64::from(a + step)).re - run(Dual64::from(a - step)).re) / (2.0 * step);
    assert!((exact - fd).abs() < 1e-6 * fd.abs(), "{exact} vs {fd}");
    assert!(exact.abs() > 0.0);
}

#[test]
fn steppers_take_the_cheaper_scheme_with_an_lr3_branch_in_the_network() {
    let fs = 48000.0;
    // A woofer (SB17: |lambda| / fs = 0.83): RK4 with 2 sub-steps, 1 in the Jacobian.
    let woofer = Rates::stiff(0.83 * fs);
    let (r, j) = Stepper::for_fit(woofer, fs);
    assert_eq!((r.scheme, r.n(), j.scheme, j.n()), (Scheme::Rk4, 2, Scheme::Rk4, 1));
    // A slow coil (|lambda| / fs = 0.25) keeps 2; SB17 at 96 kHz too.
    assert_eq!(Stepper::for_rates(Rates::stiff(0.25 * fs), fs).n(), 2);
    assert_eq!(Stepper::for_rates(woofer, 2.0 * fs).n(), 2);
    // The microspeaker (|lambda| / fs = 10.4): 3 exponential steps in a simulation, 2 in
    // a fit's model runs (FIT_EXP_STIFF_LIMIT), 1 in the Jacobian; the steps' points: the
    // quartic's five per step, the one step's three...
    let micro = Rates::stiff(10.4 * fs);
    let sim = Stepper::for_rates(micro, fs);
    assert_eq!((sim.scheme, sim.n(), sim.points()), (Scheme::Exponential, 3, 13));
    let (r, j) = Stepper::for_fit(micro, fs);
    assert_eq!(
        (r.scheme, r.n(), r.points(), j.scheme, j.n(), j.points()),
        (Scheme::Exponential, 2, 9, Scheme::Exponential, 1, 3)
    );
    // (up to |lambda| / fs = 12 in a fit, then 3).
    assert_eq!(Stepper::for_fit(Rates::stiff(12.0 * fs), fs).0.n(), 2);
    assert_eq!(Stepper::for_fit(Rates::stiff(12.1 * fs), fs).0.n(), 3);
    // A search stage's Jacobian: the midpoint rule for woofers, the exponential midpoint
    // rule for the stiff ones (RK4 between the two limits).
    for (rates, scheme) in
        [(woofer, Scheme::Midpoint), (Rates::stiff(1.2 * fs), Scheme::Rk4), (micro, Scheme::ExpMidpoint)]
    {
        let s = Stepper::for_search_jacobian(rates, fs);
        assert_eq!(s.scheme, scheme, "{rates:?}");
        assert_eq!(s.n(), if scheme == Scheme::Midpoint { 1 } else { Stepper::for_fit(rates, fs).1.n() });
    }
    // A set with an LR-3 branch: in the exponential method's network, it sets no
    // exponential steps (the microspeaker keeps its 3 and 2, 1 in the Jacobian), and
    // counts in RK4's.
    let with_lr3 = Rates { stiff: 10.4 * fs, lr3: 15.0 * fs };
    let (r, j) = Stepper::for_fit(with_lr3, fs);
    assert_eq!(
        (exp_steps_for(with_lr3, fs), r.scheme, r.n(), j.scheme, j.n()),
        (3, Scheme::Exponential, 2, Scheme::Exponential, 1)
    );
    assert_eq!(substeps_for(with_lr3.total(), fs), 51);
    // A woofer's keeps RK4 (2 sub-steps against 2 exponential steps) until the branch
    // needs 5 RK4 sub-steps.
    assert_eq!(Stepper::for_rates(Rates { stiff: 0.83 * fs, lr3: 0.5 * fs }, fs).scheme, Scheme::Rk4);
    assert_eq!(Stepper::for_rates(Rates { stiff: 0.83 * fs, lr3: 1.5 * fs }, fs).scheme, Scheme::Exponential);
}

#[test]
fn the_midpoint_rule_is_second_order_and_stable_below_2() {
    // y' = -y + u: halving h divides the error by ~4.
    let sys = Decay { lambda: 1.0 };
    let err = |n: usize| {
        let h = 1.0 / n as f64;
        let mut y = [1.0];
        for _ in 0..n {
            y = midpoint_sample(&sys, &y, h, &[0.0; 3]);
        }
        (y[0] - (-1.0f64).exp()).abs()
    };
    let (e1, e2) = (err(20), err(40));
    assert!((e1 / e2 - 4.0).abs() < 0.3, "ratio {}", e1 / e2);
    // The stiff mode at |lambda| h = 1.9 decays, at 2.1 grows.
    for (z, decays) in [(1.9, true), (2.1, false)] {
        let mut y = [1.0];
        for _ in 0..200 {
            y = midpoint_sample(&Decay { lambda: z }, &y, 1.0, &[0.0; 3]);
        }
        assert_eq!(y[0].abs() < 1.0, decays, "|lambda| h = {z}: {}", y[0]);
    }
}

#[test]
fn rk4_is_fourth_order() {
    // y' = -y, exact exp(-t): halving h divides the error by ~16.
    let sys = Decay { lambda: 1.0 };
    let err = |n: usize| {
        let h = 1.0 / n as f64;
        let mut y = [1.0];
        for _ in 0..n {
            y = rk4_step(&sys, &y, h, 0.0, 0.0, 0.0);
        }
        (y[0] - (-1.0f64).exp()).abs()
    };
    let ratio = err(10) / err(20);
    assert!(ratio > 14.0 && ratio < 18.0, "{ratio}");
}

#[test]
fn substeps_keep_the_fastest_mode_inside_the_accuracy_limit() {
    // A microspeaker with Le/(Re+R2) = 3 us at 48 kHz.
    let n = substeps_for(1.0 / 3e-6, 48000.0);
    assert!(n >= 14, "{n}");
    let h = 1.0 / 48000.0 / n as f64;
    assert!(h / 3e-6 <= STIFF_LIMIT + 1e-12);
    assert_eq!(substeps_for(1000.0, 48000.0), MIN_SUBSTEPS);
    // Stable and accurate: step response of the 3 us pole equals 1 - exp(-t/tau).
    let sys = Decay { lambda: 1.0 / 3e-6 };
    let mut y = [0.0];
    let pts = vec![1.0 / 3e-6; 2 * n + 1];
    for _ in 0..3 {
        y = rk4_sample(&sys, &y, 1.0 / 48000.0, &pts);
    }
    let exact = 1.0 - (-3.0 / 48000.0 / 3e-6f64).exp();
    assert!((y[0] - exact).abs() < 1e-6, "{} vs {}", y[0], exact);
}

#[test]
fn interpolation_reproduces_band_limited_sines() {
    let fs = 48000.0;
    let it = Interpolator::new(4);
    let mut pts = vec![0.0; 9];
    for (f, tol) in [(50.0, 1e-6), (1000.0, 1e-6), (8000.0, 1e-6), (16000.0, 1e-6), (20000.0, 0.03)] {
        let u: Vec<f64> = (0..2000).map(|k| (2.0 * std::f64::consts::PI * f * k as f64 / fs + 0.3).sin()).collect();
        let mut worst: f64 = 0.0;
        for m in 100..1900 {
            it.fill(&u, m, &mut pts);
            for (j, p) in pts.iter().enumerate() {
                let t = (m as f64 + j as f64 / 8.0) / fs;
                let exact = (2.0 * std::f64::consts::PI * f * t + 0.3).sin();
                worst = worst.max((p - exact).abs());
            }
        }
        assert!(worst < tol, "{f} Hz: {worst}");
    }
}

#[test]
fn interpolation_is_exact_at_samples_and_treats_outside_as_silence() {
    let it = Interpolator::new(3);
    let u = [0.0, 1.0, -2.0, 0.5];
    let mut pts = vec![0.0; 7];
    it.fill(&u, 1, &mut pts);
    assert_eq!(pts[0], 1.0);
    assert_eq!(pts[6], -2.0);
    it.fill(&u, 3, &mut pts);
    assert_eq!(pts[6], 0.0);
    // Interior points equal a direct kernel sum (the slow reference).
    let direct: f64 = (0..4).map(|k| u[k] * kernel(1.5 - k as f64)).sum::<f64>();
    it.fill(&u, 1, &mut pts);
    let norm: f64 = (-20..20).map(|k| kernel(0.5 - k as f64)).sum();
    assert!((pts[3] - direct / norm).abs() < 1e-12);
}

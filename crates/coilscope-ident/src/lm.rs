//! Levenberg-Marquardt as a pure state transition: [`lm_step`] takes the state and returns
//! the next one; callers loop and hand each state to their observers (progress, logs).

use nalgebra::{DMatrix, DVector};

/// What a least-squares problem provides: residuals and their exact Jacobian.
pub trait Problem {
    /// Residual vector `r(theta)` (length m) and Jacobian `dr/dtheta` (m x n).
    fn residual_jacobian(&self, theta: &[f64]) -> (DVector<f64>, DMatrix<f64>);
    fn residual(&self, theta: &[f64]) -> DVector<f64> {
        self.residual_jacobian(theta).0
    }
}

/// One iteration's state.
#[derive(Clone, Debug)]
pub struct LmState {
    pub theta: Vec<f64>,
    /// `1/2 |r|^2`.
    pub cost: f64,
    pub lambda: f64,
    pub iteration: usize,
    /// Relative cost decrease of the last accepted step.
    pub last_decrease: f64,
    pub converged: bool,
}

impl LmState {
    pub fn new<P: Problem>(p: &P, theta: Vec<f64>) -> Self {
        let cost = 0.5 * p.residual(&theta).norm_squared();
        LmState { theta, cost, lambda: 1e-3, iteration: 0, last_decrease: f64::INFINITY, converged: false }
    }
}

/// One LM iteration (tries damping until a step lowers the cost, at most 20 times).
pub fn lm_step<P: Problem>(p: &P, s: &LmState) -> LmState {
    let (r, j) = p.residual_jacobian(&s.theta);
    let a = j.tr_mul(&j);
    let g = j.tr_mul(&r);
    let mut lambda = s.lambda;
    for _ in 0..20 {
        let mut damped = a.clone();
        for k in 0..damped.nrows() {
            damped[(k, k)] += lambda * a[(k, k)].max(1e-30);
        }
        if let Some(ch) = damped.cholesky() {
            let delta = ch.solve(&(-&g));
            let theta: Vec<f64> = s.theta.iter().zip(delta.iter()).map(|(t, d)| t + d).collect();
            let cost = 0.5 * p.residual(&theta).norm_squared();
            if cost.is_finite() && cost < s.cost {
                let dec = (s.cost - cost) / s.cost.max(1e-300);
                let step = delta.amax();
                return LmState {
                    theta,
                    cost,
                    lambda: (lambda / 3.0).max(1e-12),
                    iteration: s.iteration + 1,
                    last_decrease: dec,
                    converged: dec < 1e-12 || step < 1e-10,
                };
            }
        }
        lambda *= 4.0;
    }
    LmState { lambda, iteration: s.iteration + 1, converged: true, last_decrease: 0.0, ..s.clone() }
}

/// Covariance of theta: `sigma^2 (J^T J)^-1` with `sigma^2 = |r|^2 / (m - n)`.
pub fn covariance<P: Problem>(p: &P, theta: &[f64]) -> Option<DMatrix<f64>> {
    let (r, j) = p.residual_jacobian(theta);
    let (m, n) = (j.nrows(), j.ncols());
    if m <= n {
        return None;
    }
    let s2 = r.norm_squared() / (m - n) as f64;
    j.tr_mul(&j).try_inverse().map(|inv| inv * s2)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Fit y = a exp(b t) to exact data.
    struct Exp {
        t: Vec<f64>,
        y: Vec<f64>,
    }
    impl Problem for Exp {
        fn residual_jacobian(&self, th: &[f64]) -> (DVector<f64>, DMatrix<f64>) {
            let m = self.t.len();
            let r = DVector::from_fn(m, |k, _| th[0] * (th[1] * self.t[k]).exp() - self.y[k]);
            let j = DMatrix::from_fn(m, 2, |k, c| {
                let e = (th[1] * self.t[k]).exp();
                if c == 0 { e } else { th[0] * self.t[k] * e }
            });
            (r, j)
        }
    }

    #[test]
    fn converges_on_a_nonlinear_problem_from_far_away() {
        let t: Vec<f64> = (0..50).map(|k| k as f64 * 0.05).collect();
        let y = t.iter().map(|t| 2.5 * (-1.3 * t).exp()).collect();
        let p = Exp { t, y };
        let mut s = LmState::new(&p, vec![1.0, 0.5]);
        while !s.converged && s.iteration < 200 {
            s = lm_step(&p, &s);
        }
        assert!((s.theta[0] - 2.5).abs() < 1e-8 && (s.theta[1] + 1.3).abs() < 1e-8, "{:?}", s.theta);
    }
}

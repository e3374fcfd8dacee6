//! One step of a bisection integrator: solve tar(∂S/∂p(h,p), p) = μ for p by Newton, then
//! μ' = sou(∂S/∂p(h,p), p).

use nalgebra::{Matrix3, Vector3};

use crate::dual::{Dual1, Scalar};
use crate::error::{CoreError, StepFailure};
use crate::generating::{GeneratingFunction, Workspace};
use crate::groupoid::Chart;

/// Newton settings. The defaults converge to round-off, so the Casimir is kept to round-off.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NewtonOptions {
    /// Stop once the Newton update satisfies |δ|∞ ≤ tol · max(|p|∞, 1e-300). Quadratic
    /// convergence leaves the error after that update near |δ|², far below round-off.
    pub tol: f64,
    /// Iteration cap; exceeding it is a step failure.
    pub max_iter: u32,
}

impl Default for NewtonOptions {
    fn default() -> Self {
        NewtonOptions {
            tol: 1e-12,
            max_iter: 50,
        }
    }
}

impl NewtonOptions {
    pub fn validated(tol: f64, max_iter: u32) -> Result<Self, CoreError> {
        if !(tol.is_finite() && tol > 0.0 && tol < 1.0) {
            return Err(CoreError::Invalid(format!(
                "tol must lie in (0, 1), got {tol}"
            )));
        }
        if max_iter == 0 {
            return Err(CoreError::Invalid("max_iter must be at least 1".into()));
        }
        Ok(NewtonOptions { tol, max_iter })
    }
}

/// What one successful step cost and how well it solved its equation.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StepStats {
    /// Newton updates taken.
    pub iterations: u32,
    /// |tar(∂S/∂p(h,p), p) − μ|∞ at the accepted p.
    pub residual: f64,
}

/// A map μ ↦ μ' that advances one step of size h. Implemented by every integrator so a rollout
/// is written once.
pub trait StepMap: Sync {
    type Workspace: Send;
    fn workspace(&self) -> Self::Workspace;
    /// Advances `mu` in place.
    fn step(
        &self,
        h: f64,
        mu: &mut [f64; 3],
        ws: &mut Self::Workspace,
    ) -> Result<StepStats, StepFailure>;
}

/// The bisection integrator of a generating function in a chart.
#[derive(Clone, Debug)]
pub struct BisectionStepper {
    pub generating: GeneratingFunction,
    pub chart: Chart,
    pub newton: NewtonOptions,
}

/// F(p) = tar(∂S/∂p(h,p), p) − μ and its Jacobian dF/dp.
#[inline]
fn residual(
    st: &BisectionStepper,
    h: f64,
    mu: &[f64; 3],
    p: &[f64; 3],
    ws: &mut Workspace,
) -> Result<([f64; 3], Matrix3<f64>), StepFailure> {
    let jet = st.generating.jet(h, p, ws);
    if !jet.is_finite() {
        return Err(StepFailure::NonFinite);
    }
    let (g, hs) = (jet.grad(), jet.hess());
    // x(p) = ∇S(p) carries the Hessian as its derivative; p carries the identity.
    let x: [Dual1; 3] = std::array::from_fn(|i| Dual1 { v: g[i], g: hs[i] });
    let pd: [Dual1; 3] = std::array::from_fn(|i| Dual1::var(p[i], i));
    let t = st.chart.tar(&x, &pd)?;
    let f = [t[0].v - mu[0], t[1].v - mu[1], t[2].v - mu[2]];
    let j = Matrix3::from_fn(|r, c| t[r].g[c]);
    Ok((f, j))
}

fn max_abs(a: &[f64; 3]) -> f64 {
    a[0].abs().max(a[1].abs()).max(a[2].abs())
}

impl StepMap for BisectionStepper {
    type Workspace = Workspace;

    fn workspace(&self) -> Workspace {
        self.generating.workspace()
    }

    fn step(
        &self,
        h: f64,
        mu: &mut [f64; 3],
        ws: &mut Workspace,
    ) -> Result<StepStats, StepFailure> {
        let target = *mu;
        let mut p = target;
        let mut iterations = 0;
        let mut done = false;
        loop {
            if done {
                // Converged: x at the final p needs the gradient of S only, not its Hessian.
                let g = self.generating.gradient(h, &p, ws);
                if !g.is_finite() {
                    return Err(StepFailure::NonFinite);
                }
                let x = g.g;
                let t = self.chart.tar(&x, &p)?;
                let f = [t[0] - target[0], t[1] - target[1], t[2] - target[2]];
                let out = self.chart.sou(&x, &p)?;
                if !out.iter().all(|v| v.is_finite()) {
                    return Err(StepFailure::NonFinite);
                }
                *mu = out;
                return Ok(StepStats {
                    iterations,
                    residual: max_abs(&f),
                });
            }
            let (f, j) = residual(self, h, &target, &p, ws)?;
            if iterations >= self.newton.max_iter {
                return Err(StepFailure::NotConverged);
            }
            let delta = j
                .lu()
                .solve(&Vector3::new(-f[0], -f[1], -f[2]))
                .ok_or(StepFailure::SingularJacobian)?;
            if !delta.iter().all(|d| d.is_finite()) {
                return Err(StepFailure::SingularJacobian);
            }
            for i in 0..3 {
                p[i] += delta[i];
            }
            iterations += 1;
            done = delta.amax() <= self.newton.tol * max_abs(&p).max(1e-300);
        }
    }
}

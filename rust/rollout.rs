//! Batches of long rollouts, one trajectory per rayon task.
//!
//! Trajectories are independent, so the result is bit-identical whatever the thread count.

use rayon::prelude::*;

use crate::error::{CoreError, StepFailure};
use crate::stepper::StepMap;

/// Per-trajectory diagnostics of a rollout.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrajectoryInfo {
    /// Every step succeeded.
    pub converged: bool,
    /// Index of the step that failed (from state k to k+1), or −1.
    pub failed_step: i64,
    /// Why it failed, if it did.
    pub failure: Option<StepFailure>,
    /// Newton updates summed over the trajectory.
    pub newton_iterations: u64,
    /// Most Newton updates in any one step.
    pub max_newton_iterations: u32,
    /// Largest accepted Newton residual |tar(∂S/∂p, p) − μ|∞ over the steps.
    pub max_residual: f64,
}

impl Default for TrajectoryInfo {
    fn default() -> Self {
        TrajectoryInfo {
            converged: true,
            failed_step: -1,
            failure: None,
            newton_iterations: 0,
            max_newton_iterations: 0,
            max_residual: 0.0,
        }
    }
}

/// Number of stored states: steps 0, every, 2·every, … ≤ n_steps.
pub fn n_records(n_steps: usize, every: usize) -> usize {
    n_steps / every + 1
}

/// Checks the scalar arguments of a rollout.
pub fn check_arguments(h: f64, every: usize) -> Result<(), CoreError> {
    if !(h.is_finite() && h > 0.0) {
        return Err(CoreError::Invalid(format!(
            "h must be a finite number > 0, got {h}"
        )));
    }
    if every == 0 {
        return Err(CoreError::Invalid("every must be at least 1".into()));
    }
    Ok(())
}

/// Advances one trajectory, writing its records into `out` (n_records × 3).
fn run_one<S: StepMap>(
    stepper: &S,
    ws: &mut S::Workspace,
    mu0: [f64; 3],
    h: f64,
    n_steps: usize,
    every: usize,
    out: &mut [f64],
) -> TrajectoryInfo {
    let mut info = TrajectoryInfo::default();
    let mut mu = mu0;
    out[..3].copy_from_slice(&mu);
    for k in 0..n_steps {
        match stepper.step(h, &mut mu, ws) {
            Ok(stats) => {
                info.newton_iterations += u64::from(stats.iterations);
                info.max_newton_iterations = info.max_newton_iterations.max(stats.iterations);
                info.max_residual = info.max_residual.max(stats.residual);
            }
            Err(failure) => {
                // The trajectory stops here: later records are NaN, never stale values.
                info.converged = false;
                info.failed_step = k as i64;
                info.failure = Some(failure);
                let next = (k + 1).div_ceil(every);
                out[3 * next..].fill(f64::NAN);
                return info;
            }
        }
        if (k + 1) % every == 0 {
            let r = 3 * ((k + 1) / every);
            out[r..r + 3].copy_from_slice(&mu);
        }
    }
    info
}

/// Rolls out every initial state for `n_steps` steps of size `h`, keeping every `every`-th state.
///
/// `out` has length n · n_records(n_steps, every) · 3, laid out as (n, n_records, 3).
pub fn rollout<S: StepMap>(
    stepper: &S,
    mu0: &[[f64; 3]],
    h: f64,
    n_steps: usize,
    every: usize,
    out: &mut [f64],
) -> Result<Vec<TrajectoryInfo>, CoreError> {
    check_arguments(h, every)?;
    let row = 3 * n_records(n_steps, every);
    if out.len() != mu0.len() * row {
        return Err(CoreError::Invalid(format!(
            "output buffer holds {} numbers, {} needed",
            out.len(),
            mu0.len() * row
        )));
    }
    if let Some(bad) = mu0.iter().position(|m| !m.iter().all(|v| v.is_finite())) {
        return Err(CoreError::Invalid(format!(
            "initial state {bad} is not finite"
        )));
    }
    Ok(out
        .par_chunks_mut(row)
        .zip(mu0.par_iter())
        .map_init(
            || stepper.workspace(),
            |ws, (o, &m)| run_one(stepper, ws, m, h, n_steps, every, o),
        )
        .collect())
}

//! Classical baseline integrators: RK4 and the implicit midpoint rule for any Lie–Poisson
//! system, the free rigid body's splittings and discrete Moser–Veselov, and the heavy top's
//! kinetic/potential splitting.
//!
//! They are not bisection methods, but implement [`StepMap`] like [`BisectionStepper`], so one
//! [`rollout`] drives them all and timings compare like for like. None allocates per step.
//!
//! Rigid body (so(3)*):
//!
//! | method | struct | order | Poisson |
//! |---|---|---|---|
//! | `rk4` | [`Rk4`] | 4 | no |
//! | `midpoint` | [`ImplicitMidpoint`] | 2 | yes (quadratic H: keeps C and H up to Newton tolerance) |
//! | `splitting` | [`Splitting`] (Strang) | 2 | yes |
//! | `splitting4` | [`Splitting4`] (Suzuki, 5 Strang stages) | 4 | yes |
//! | `dmv` | [`MoserVeselov`] | 2 | yes (keeps C and H to round-off) |
//! | `splitting_casimir` | [`CasimirSplitting`] | 2 | yes |
//!
//! Any Lie–Poisson system ([`LieMethod`]): `rk4` and `midpoint` (Poisson for quadratic H), and
//! for the heavy top `splitting` ([`HeavyTopSplitting`], order 2, Poisson).
//!
//! [`BisectionStepper`]: crate::stepper::BisectionStepper
//! [`StepMap`]: crate::step::StepMap
//! [`rollout`]: crate::rollout::rollout

mod heavy_top;
mod methods;
mod rigid_body;

pub use heavy_top::{HeavyTop, HeavyTopSplitting};
pub use methods::{ImplicitMidpoint, LieMethod, LieStepper, Rk4};
pub use rigid_body::{
    rollout_classical, CasimirSplitting, ClassicalMethod, ClassicalStepper, MoserVeselov,
    RigidBody, Splitting, Splitting4, SplittingComposition,
};

use crate::error::{CoreError, StepFailure};
use crate::step::StepStats;

#[inline]
pub(super) fn axpy<const N: usize>(a: f64, x: &[f64; N], y: &[f64; N]) -> [f64; N] {
    std::array::from_fn(|i| y[i] + a * x[i])
}

#[inline]
pub(crate) fn max_abs<const N: usize>(a: &[f64; N]) -> f64 {
    a.iter().fold(0.0, |m: f64, v| m.max(v.abs()))
}

/// The stats of an explicit step, or NonFinite if it overflowed.
#[inline]
pub(super) fn explicit_result<const N: usize>(mu: &[f64; N]) -> Result<StepStats, StepFailure> {
    if mu.iter().all(|v| v.is_finite()) {
        Ok(StepStats::default())
    } else {
        Err(StepFailure::NonFinite)
    }
}

/// The method of `all` called `name`, or an error listing the valid names.
pub(super) fn by_name<M: Copy>(
    all: &[M],
    name_of: fn(M) -> &'static str,
    name: &str,
    context: &str,
) -> Result<M, CoreError> {
    all.iter()
        .copied()
        .find(|&m| name_of(m) == name)
        .ok_or_else(|| {
            let names: Vec<_> = all.iter().map(|&m| name_of(m)).collect();
            CoreError::Invalid(format!(
                "unknown classical integrator {name:?}{context}; valid names: {}",
                names.join(", ")
            ))
        })
}

#[cfg(test)]
mod tests;

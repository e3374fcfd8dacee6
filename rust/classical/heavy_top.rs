//! The heavy top on se(3)*, and its kinetic/potential splitting.

use super::rigid_body::{cross, rotate_about_by};
use super::{explicit_result, RigidBody};
use crate::error::{CoreError, StepFailure};
use crate::step::{StepMap, StepStats};
use crate::trig;

/// The heavy top on se(3)*, μ = (M, Γ), H = ½ Σ Mᵢ²/Iᵢ + mgl χ·Γ:
/// Ṁ = M × Ω + mgl Γ × χ, Γ̇ = Γ × Ω with Ω = M/I.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HeavyTop {
    pub body: RigidBody,
    /// mgl · χ: the weight times the centre of mass in the body frame.
    pub torque_arm: [f64; 3],
}

impl HeavyTop {
    pub fn new(inertia: [f64; 3], mgl: f64, com: [f64; 3]) -> Result<Self, CoreError> {
        if !(mgl.is_finite() && com.iter().all(|v| v.is_finite())) {
            return Err(CoreError::Invalid(format!(
                "mgl and the centre of mass must be finite, got {mgl} and {com:?}"
            )));
        }
        Ok(HeavyTop {
            body: RigidBody::new(inertia)?,
            torque_arm: com.map(|c| mgl * c),
        })
    }

    /// Exact flow for time t of Hᵢ = Mᵢ²/(2Iᵢ): M and Γ turn about eᵢ by the same angle.
    #[inline]
    pub(crate) fn axis_flow(&self, i: usize, t: f64, mu: &mut [f64; 6]) {
        let sc = trig::sin_cos(t * mu[i] * self.body.inv[i]);
        let (m, g) = mu.split_at_mut(3);
        rotate_about_by(i, sc, m);
        rotate_about_by(i, sc, g);
    }

    /// Exact flow for time t of the potential mgl χ·Γ: Γ fixed, M += t mgl Γ × χ.
    #[inline]
    pub(crate) fn potential_flow(&self, t: f64, mu: &mut [f64; 6]) {
        let g = [mu[3], mu[4], mu[5]];
        let d = cross(&g, &self.torque_arm);
        for i in 0..3 {
            mu[i] += t * d[i];
        }
    }
}

/// Strang splitting of the heavy top into its kinetic and potential parts, order 2:
/// V(h/2) ∘ K(h) ∘ V(h/2), with the kinetic flow K itself the rigid body's Strang splitting
/// over the three axes. Every sub-flow is exact, so the step is a Poisson map and keeps both
/// Casimirs |Γ|² and M·Γ to round-off.
#[derive(Clone, Copy, Debug)]
pub struct HeavyTopSplitting {
    pub top: HeavyTop,
}

impl StepMap<6> for HeavyTopSplitting {
    type Workspace = ();

    fn workspace(&self) {}

    fn step(&self, h: f64, mu: &mut [f64; 6], _: &mut ()) -> Result<StepStats, StepFailure> {
        let top = &self.top;
        top.potential_flow(0.5 * h, mu);
        top.axis_flow(0, 0.5 * h, mu);
        top.axis_flow(1, 0.5 * h, mu);
        top.axis_flow(2, h, mu);
        top.axis_flow(1, 0.5 * h, mu);
        top.axis_flow(0, 0.5 * h, mu);
        top.potential_flow(0.5 * h, mu);
        explicit_result(mu)
    }
}

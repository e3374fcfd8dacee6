//! The methods for any vector field (RK4, the implicit midpoint rule) and the classical
//! integrators of a general Lie–Poisson system by name ([`LieMethod`]).

use nalgebra::{Const, DimMin};

use super::{axpy, by_name, explicit_result, max_abs, HeavyTop, HeavyTopSplitting};
use crate::error::{CoreError, StepFailure};
use crate::lane_field::MidpointSolve;
use crate::step::{NewtonOptions, StepMap, StepStats};
use crate::straight_line::LieField;
use crate::structures::lie_poisson::{LiePoisson, VectorField};

/// Classical explicit Runge–Kutta of order 4. Not Poisson: C and H drift.
#[derive(Clone, Debug)]
pub struct Rk4<F> {
    pub system: F,
}

impl<const N: usize, F: VectorField<N>> StepMap<N> for Rk4<F> {
    type Workspace = ();

    fn workspace(&self) {}

    fn step(&self, h: f64, mu: &mut [f64; N], _: &mut ()) -> Result<StepStats, StepFailure> {
        let f = |m: &[f64; N]| self.system.field(m);
        let k1 = f(mu);
        let k2 = f(&axpy(0.5 * h, &k1, mu));
        let k3 = f(&axpy(0.5 * h, &k2, mu));
        let k4 = f(&axpy(h, &k3, mu));
        for i in 0..N {
            mu[i] += h / 6.0 * (k1[i] + 2.0 * (k2[i] + k3[i]) + k4[i]);
        }
        explicit_result(mu)
    }
}

/// Implicit midpoint μ' = μ + h f((μ + μ')/2), order 2.
///
/// It keeps every quadratic invariant: for the rigid body C = |μ|² and H, up to the Newton
/// tolerance, and for any Lie–Poisson system its quadratic Casimirs (a Poisson map when H is
/// quadratic). Newton solves for the midpoint m = μ + (h/2) f(m) with the exact Jacobian
/// I − (h/2) ∂f/∂μ(m).
#[derive(Clone, Debug)]
pub struct ImplicitMidpoint<F> {
    pub system: F,
    pub newton: NewtonOptions,
}

impl<const N: usize, F: VectorField<N> + MidpointSolve<N>> StepMap<N> for ImplicitMidpoint<F>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    type Workspace = ();

    fn workspace(&self) {}

    fn step(&self, h: f64, mu: &mut [f64; N], _: &mut ()) -> Result<StepStats, StepFailure> {
        let body = &self.system;
        let mu0 = *mu;
        let half = 0.5 * h;
        // Start at the explicit Euler midpoint (one Newton update fewer than starting at μ),
        // refined by the field's fixed-point sweeps: the lanes' predictor on one lane.
        let mut m = body.midpoint_predictor(half, &mu0);
        let mut iterations = 0;
        loop {
            if iterations >= self.newton.max_iter {
                return Err(StepFailure::NotConverged);
            }
            let fm = body.field(&m);
            let r: [f64; N] = std::array::from_fn(|i| m[i] - mu0[i] - half * fm[i]);
            let delta = body.midpoint_update(half, &m, &r)?;
            for i in 0..N {
                m[i] += delta[i];
            }
            iterations += 1;
            if max_abs(&delta) <= self.newton.tol * max_abs(&m).max(1e-300) {
                break;
            }
        }
        let fm = body.field(&m);
        let residual = max_abs::<N>(&std::array::from_fn(|i| m[i] - mu0[i] - half * fm[i]));
        // μ + h f(m) rather than 2m − μ: the increment carries the rounding, not μ.
        *mu = axpy(h, &fm, &mu0);
        if !mu.iter().all(|v| v.is_finite()) {
            return Err(StepFailure::NonFinite);
        }
        Ok(StepStats {
            iterations,
            residual,
        })
    }
}

/// The classical integrators of a general Lie–Poisson system, by name.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LieMethod {
    Rk4,
    Midpoint,
    /// The heavy top's kinetic/potential splitting; needs [`HeavyTop`] parameters.
    Splitting,
}

impl LieMethod {
    pub const ALL: [LieMethod; 3] = [LieMethod::Rk4, LieMethod::Midpoint, LieMethod::Splitting];

    pub fn name(self) -> &'static str {
        match self {
            LieMethod::Rk4 => "rk4",
            LieMethod::Midpoint => "midpoint",
            LieMethod::Splitting => "splitting",
        }
    }

    pub fn from_name(name: &str) -> Result<Self, CoreError> {
        by_name(&Self::ALL, Self::name, name, " for a Lie–Poisson system")
    }
}

/// A classical integrator of a Lie–Poisson system chosen at run time.
#[derive(Clone, Debug)]
pub enum LieStepper<const N: usize> {
    Rk4(Rk4<LieField<N>>),
    Midpoint(ImplicitMidpoint<LieField<N>>),
    /// Only for N = 6 (the heavy top); built by [`LieStepper::new`] alone.
    HeavyTop(HeavyTopSplitting),
}

impl<const N: usize> LieStepper<N> {
    /// The integrator `method` for `system`; `heavy_top` carries the parameters the splitting
    /// needs (it must describe the same system).
    pub fn new(
        method: LieMethod,
        system: LiePoisson<N>,
        heavy_top: Option<HeavyTop>,
        newton: NewtonOptions,
    ) -> Result<Self, CoreError> {
        // The steppers evaluate a recognised pattern's straight-line field, else the system
        // compiled to its sparsity.
        let system = LieField::new(&system);
        Ok(match method {
            LieMethod::Rk4 => LieStepper::Rk4(Rk4 { system }),
            LieMethod::Midpoint => LieStepper::Midpoint(ImplicitMidpoint { system, newton }),
            LieMethod::Splitting => {
                match heavy_top {
                    Some(top) if N == 6 => LieStepper::HeavyTop(HeavyTopSplitting { top }),
                    _ => return Err(CoreError::Invalid(
                        "the splitting integrator is defined for the rigid body and the heavy top \
                         only"
                            .into(),
                    )),
                }
            }
        })
    }
}

impl<const N: usize> StepMap<N> for LieStepper<N>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    type Workspace = ();

    fn workspace(&self) {}

    #[inline]
    fn step(&self, h: f64, mu: &mut [f64; N], ws: &mut ()) -> Result<StepStats, StepFailure> {
        match self {
            LieStepper::Rk4(s) => s.step(h, mu, ws),
            LieStepper::Midpoint(s) => s.step(h, mu, ws),
            LieStepper::HeavyTop(s) => match <&mut [f64; 6]>::try_from(&mut mu[..]) {
                Ok(m) => s.step(h, m, ws),
                Err(_) => Err(StepFailure::NonFinite),
            },
        }
    }
}

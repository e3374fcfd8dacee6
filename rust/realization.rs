//! A realization gives the bisection equation; a generating function gives the Lagrangian
//! bisection. The Newton stepper of [`RealizationStepper`] needs nothing else, so it steps every
//! Poisson structure the same way: the Lie-algebra groupoids ([`Groupoid`], base coordinate p ∈
//! g*, fibre x ∈ g) and the log-canonical one ([`crate::structures::LogCanonical`], base q = ln x,
//! fibre P).
//!
//! One step of size h from μ: solve tar(∂S/∂p(h, p), p) = μ for p, then μ' = sou(∂S/∂p, p),
//! formed from μ where the realization can ([`Realization::sou_after_solve`]), so that Newton's
//! residual does not reach the Casimirs.
//! On the Lie-algebra groupoid with a [`GeneratingFunction`], a step of [`RealizationStepper`] is
//! the same sequence of floating-point operations as one of
//! [`crate::stepper::BisectionStepper`] with full Newton on one trajectory, so the two are
//! bit-identical there (tested).

use nalgebra::{Const, DimMin};

use crate::dual::{Dual1, Jet2, Scalar};
use crate::error::StepFailure;
use crate::generating::{GeneratingFunction, Workspace};
use crate::step::{Inverse, NewtonOptions, StepMap, StepResult, StepStats};
use crate::structures::lie_groupoid::Groupoid;

/// The source and target maps of a symplectic realization in canonical coordinates (x fibre,
/// p base): sou is the Poisson map (β), tar the anti-Poisson one (α), and sou(0, p) = tar(0, p)
/// = p. Generic over the scalar so that Newton gets the Jacobian from dual numbers.
pub trait Realization<const N: usize>: Sync {
    fn sou<T: Scalar>(&self, x: &[T; N], p: &[T; N]) -> Result<[T; N], StepFailure>;
    fn tar<T: Scalar>(&self, x: &[T; N], p: &[T; N]) -> Result<[T; N], StepFailure>;
    /// The step's new state from the converged (x, p) and the state it solved for
    /// (tar(x, p) = target up to Newton's residual): sou(x, p) by default. A realization where
    /// sou is a map of x alone applied to tar (sou = tar − c x on the log-canonical groupoid,
    /// sou = g(x) · tar on a Lie groupoid) overrides it to apply that map to `target`, which
    /// leaves the residual out of the step: the Casimirs are then kept whatever it is.
    #[inline]
    fn sou_after_solve(
        &self,
        x: &[f64; N],
        p: &[f64; N],
        _target: &[f64; N],
    ) -> Result<[f64; N], StepFailure> {
        self.sou(x, p)
    }
}

impl<const N: usize> Realization<N> for Groupoid<N> {
    #[inline]
    fn sou<T: Scalar>(&self, x: &[T; N], p: &[T; N]) -> Result<[T; N], StepFailure> {
        Groupoid::sou(self, x, p)
    }
    #[inline]
    fn tar<T: Scalar>(&self, x: &[T; N], p: &[T; N]) -> Result<[T; N], StepFailure> {
        Groupoid::tar(self, x, p)
    }
    /// sou(x, p) = g(x) · tar(x, p) for the coadjoint action of the chart's group element g(x),
    /// so the new state is g(x) · μ ([`Groupoid::coadjoint`]): on μ's own coadjoint orbit,
    /// every Casimir kept up to the rounding of that one evaluation, whatever Newton's residual.
    /// sou(x, p) at Newton's last iterate carried C(tar(x, p)) = C(μ + residual) instead, and
    /// simplified Newton's residual (up to its tolerance) has the same sign from step to step:
    /// a drift of the Casimirs linear in the number of steps.
    #[inline]
    fn sou_after_solve(
        &self,
        x: &[f64; N],
        _p: &[f64; N],
        target: &[f64; N],
    ) -> Result<[f64; N], StepFailure> {
        self.coadjoint(x, target)
    }
}

/// A generating function S(t, p) as the Newton stepper sees it: its p-jet (value, gradient,
/// Hessian) and its p-gradient at fixed t.
pub trait Generating<const N: usize>: Sync {
    type Workspace: Send;
    fn workspace(&self) -> Self::Workspace;
    fn jet(&self, t: f64, p: &[f64; N], ws: &mut Self::Workspace) -> Jet2<N>;
    /// ∂S/∂p in `.g` (the value is not used).
    fn gradient(&self, t: f64, p: &[f64; N], ws: &mut Self::Workspace) -> Dual1<N>;
}

impl<const N: usize> Generating<N> for GeneratingFunction<N> {
    type Workspace = Workspace<N>;
    fn workspace(&self) -> Workspace<N> {
        GeneratingFunction::workspace(self)
    }
    fn jet(&self, t: f64, p: &[f64; N], ws: &mut Workspace<N>) -> Jet2<N> {
        GeneratingFunction::jet(self, t, p, ws)
    }
    fn gradient(&self, t: f64, p: &[f64; N], ws: &mut Workspace<N>) -> Dual1<N> {
        GeneratingFunction::gradient(self, t, p, ws)
    }
}

/// The bisection integrator of a generating function `G` on a realization `R`, full Newton,
/// one trajectory at a time.
#[derive(Clone, Debug)]
pub struct RealizationStepper<const N: usize, R, G> {
    pub generating: G,
    pub realization: R,
    pub newton: NewtonOptions,
    /// Newton stops once |δ|∞ ≤ tol · max(|p|∞, scale_floor): 1e-300 (relative) reproduces
    /// [`crate::stepper::BisectionStepper`]; 1 suits a base coordinate that is a logarithm,
    /// where a relative tolerance on q near 0 would ask for more than round-off.
    pub scale_floor: f64,
}

fn max_abs<const N: usize>(a: &[f64; N]) -> f64 {
    a.iter().fold(0.0, |m: f64, v| m.max(v.abs()))
}

impl<const N: usize, R: Realization<N>, G: Generating<N>> RealizationStepper<N, R, G>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    /// One Newton update of p for tar(∂S/∂p(h,p), p) = target from the jet of S at p.
    /// Returns whether |δ|∞ ≤ tol · max(|p|∞, scale_floor).
    #[inline]
    fn newton_update(
        &self,
        jet: &Jet2<N>,
        target: &[f64; N],
        p: &mut [f64; N],
        iterations: &mut u32,
    ) -> Result<bool, StepFailure> {
        if !jet.is_finite() {
            return Err(StepFailure::NonFinite);
        }
        let (g, hs) = (jet.grad(), jet.hess());
        // x(p) = ∇S(p) carries the Hessian as its derivative; p carries the identity.
        let x: [Dual1<N>; N] = std::array::from_fn(|i| Dual1 { v: g[i], g: hs[i] });
        let pd: [Dual1<N>; N] = std::array::from_fn(|i| Dual1::var(p[i], i));
        let t = self.realization.tar(&x, &pd)?;
        if *iterations >= self.newton.max_iter {
            return Err(StepFailure::NotConverged);
        }
        // The stepper's explicit inverse (the same numbers as BisectionStepper's updates).
        let inv = Inverse::new(&t.map(|ti| ti.g))?;
        let f: [f64; N] = std::array::from_fn(|i| target[i] - t[i].v);
        let delta = inv.apply(&f);
        if !delta.iter().all(|d| d.is_finite()) {
            return Err(StepFailure::SingularJacobian);
        }
        for (pi, d) in p.iter_mut().zip(delta.iter()) {
            *pi += d;
        }
        *iterations += 1;
        Ok(max_abs(&delta) <= self.newton.tol * max_abs(p).max(self.scale_floor))
    }
}

impl<const N: usize, R: Realization<N>, G: Generating<N>> StepMap<N> for RealizationStepper<N, R, G>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    type Workspace = G::Workspace;

    fn workspace(&self) -> G::Workspace {
        self.generating.workspace()
    }

    fn step(&self, h: f64, mu: &mut [f64; N], ws: &mut G::Workspace) -> StepResult {
        let target = *mu;
        let mut p = target;
        let mut iterations = 0;
        loop {
            let jet = self.generating.jet(h, &p, ws);
            if self.newton_update(&jet, &target, &mut p, &mut iterations)? {
                break;
            }
        }
        let grad = self.generating.gradient(h, &p, ws);
        if !grad.is_finite() {
            return Err(StepFailure::NonFinite);
        }
        let x = grad.g;
        let t = self.realization.tar(&x, &p)?;
        let f: [f64; N] = std::array::from_fn(|i| t[i] - target[i]);
        let out = self.realization.sou_after_solve(&x, &p, &target)?;
        if !out.iter().all(|v| v.is_finite()) {
            return Err(StepFailure::NonFinite);
        }
        *mu = out;
        Ok(StepStats {
            iterations,
            residual: max_abs(&f),
        })
    }
}

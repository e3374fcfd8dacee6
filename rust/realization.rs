//! A realization gives the bisection equation; a generating function gives the Lagrangian
//! bisection. The Newton solve here ([`Newton`]) needs nothing else, so the one bisection
//! stepper ([`crate::stepper::BisectionStepper`]) steps every Poisson structure the same way:
//! the Lie-algebra groupoids ([`Groupoid`], base coordinate p ∈ g*, fibre x ∈ g), the
//! log-canonical one ([`crate::structures::LogCanonical`], base q = ln x, fibre P) and the
//! order-n realizations of polynomial bivectors.
//!
//! One step of size h from μ: solve tar(∂S/∂p(h, p), p) = μ for p, then μ' = sou(∂S/∂p, p),
//! formed from μ where the realization can ([`Realization::sou_after_solve`]), so that Newton's
//! residual does not reach the Casimirs. A generating function ([`Generating`]) may evaluate
//! several momenta at once ([`Generating::jets`]); the stepper then solves that many Newton
//! systems in lockstep, each with the updates of the one-trajectory solve.

use nalgebra::{Const, DimMin};

use crate::dual::{Dual1, Jet2, Scalar};
use crate::error::StepFailure;
use crate::generating::{
    GeneratingFunction, LaneRow, Mlp, NetworkLanes, Polynomial, Workspace, MAX_BATCH,
};
use crate::step::{Inverse, StepResult, StepStats, SIMPLIFIED_RATE};
pub use crate::structures::lie_groupoid::LaneChart;
use crate::structures::lie_groupoid::{Chart, Groupoid, LieAlgebra};

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
    /// Whether [`Realization::predict`] gives Newton a start (then the solve evaluates
    /// x₀ = ∂S/∂p at p = μ once more per step).
    #[inline]
    fn predicts(&self) -> bool {
        false
    }
    /// A start for Newton closer to the solution than the state `target` itself, from
    /// x₀ = ∂S/∂p(h, target); None: start at `target`.
    #[inline]
    fn predict(&self, _x0: &[f64; N], _target: &[f64; N]) -> Option<[f64; N]> {
        None
    }
    /// The closed-form lane chart this realization is, if any: None (the generic dual-number
    /// solve) unless a lane solver exists for it.
    #[inline]
    fn lane_chart(&self) -> Option<LaneChart> {
        None
    }
    /// The Lie algebra of a Lie groupoid's chart ([`LaneChart::ExpSeries`] sums its series);
    /// None for any other realization.
    #[inline]
    fn lie_algebra(&self) -> Option<&LieAlgebra<N>> {
        None
    }
}

/// Largest |x₀|² at which [`Realization::predict`] is used on a Lie groupoid: beyond it (a step
/// far too large for the series, h = 5 say) the first-order start can throw Newton past the exp
/// chart's singular angle that a start from μ avoids (the rule of the so(3) lanes' predictor).
const PREDICT_MAX_S: f64 = 1.0;

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
    /// [`Groupoid::lane_chart`]: so(3) in either chart, se(3) in the exponential one.
    #[inline]
    fn lane_chart(&self) -> Option<LaneChart> {
        Groupoid::lane_chart(self)
    }
    #[inline]
    fn lie_algebra(&self) -> Option<&LieAlgebra<N>> {
        Some(&self.algebra)
    }
    #[inline]
    fn predicts(&self) -> bool {
        true
    }
    /// tar(x, p) = p + ½ ad_xᵀ p + O(|x|²) in every chart, so p₀ = μ − ½ ad_{x₀}ᵀ μ is O(h²)
    /// from the solution where μ itself is O(h) away (x₀ = O(h)): Newton's first error, and
    /// simplified Newton's contraction with it, shrink by a power of h. In the Cayley chart
    /// p₀ also takes tar's quadratic term, ¼ x₀ (x₀·μ) (p₀ = 2μ − tar(x₀, μ)); in the exponential
    /// one the whole chart predicts no better (`benches/newton_predictors.py`). Only where
    /// |x₀|² ≤ [`PREDICT_MAX_S`] and p₀ is finite.
    #[inline]
    fn predict(&self, x0: &[f64; N], target: &[f64; N]) -> Option<[f64; N]> {
        let s: f64 = x0.iter().map(|v| v * v).sum();
        // A NaN x₀ predicts nothing either.
        if s.is_nan() || s > PREDICT_MAX_S {
            return None;
        }
        let a = self.algebra.ad_transpose_apply(x0, target);
        let mut p0: [f64; N] = std::array::from_fn(|i| target[i] - 0.5 * a[i]);
        if self.chart == Chart::Cayley {
            // The Cayley chart's quadratic term too (p₀ = 2μ − tar(x₀, μ)), as the so(3) lanes.
            let along = 0.25 * x0.iter().zip(target).fold(0.0, |s, (a, b)| s + a * b);
            for i in 0..N {
                p0[i] -= x0[i] * along;
            }
        }
        p0.iter().all(|v| v.is_finite()).then_some(p0)
    }
}

/// A generating function S(t, p) as the Newton stepper sees it: its p-jet (value, gradient,
/// Hessian) and its p-gradient at fixed t, one momentum at a time or [`Self::batch`] at once.
pub trait Generating<const N: usize>: Sync {
    type Workspace: Send;
    fn workspace(&self) -> Self::Workspace;
    /// Bytes one workspace takes (the rollout makes one per thread).
    fn workspace_bytes(&self) -> usize {
        0
    }
    fn jet(&self, t: f64, p: &[f64; N], ws: &mut Self::Workspace) -> Jet2<N>;
    /// ∂S/∂p in `.g` (the value is not used).
    fn gradient(&self, t: f64, p: &[f64; N], ws: &mut Self::Workspace) -> Dual1<N>;
    /// Momenta per batched evaluation ([`Self::jets`], [`Self::gradients`]); 1: the stepper
    /// solves one trajectory at a time.
    fn batch(&self) -> usize {
        1
    }
    /// `out[j]` = the jet at `p[j]`, for at most [`crate::generating::MAX_BATCH`] momenta.
    fn jets(&self, t: f64, p: &[[f64; N]], out: &mut [Jet2<N>], ws: &mut Self::Workspace) {
        for (o, q) in out.iter_mut().zip(p) {
            *o = self.jet(t, q, ws);
        }
    }
    /// `out[j]` = the gradient at `p[j]`, for at most [`crate::generating::MAX_BATCH`] momenta.
    fn gradients(&self, t: f64, p: &[[f64; N]], out: &mut [Dual1<N>], ws: &mut Self::Workspace) {
        for (o, q) in out.iter_mut().zip(p) {
            *o = self.gradient(t, q, ws);
        }
    }
    /// S as a polynomial in (t, p) alone, where it is one: the so(3) lane solver's input
    /// ([`crate::lanes_bisection`]), and the sign that a batched step has the bits of the
    /// one-trajectory step (the lanes evaluate a polynomial bit for bit as the scalar code).
    fn polynomial(&self) -> Option<&Polynomial<N>> {
        None
    }
    /// S as the lane Newton solvers take it: its polynomial part and its network term, where S
    /// is a polynomial, or a polynomial plus a network narrow enough for the lanes
    /// ([`crate::generating::NETWORK_LANES_MAX_WIDTH`]); None keeps the batched path.
    fn lane_parts(&self) -> Option<(&Polynomial<N>, Option<NetworkLanes<'_>>)> {
        self.polynomial().map(|p| (p, None))
    }
    /// The lane network term's scratch in a workspace (empty where there is none).
    fn lane_scratch<'w>(&self, _ws: &'w mut Self::Workspace) -> &'w mut [LaneRow] {
        &mut []
    }
}

impl<const N: usize> Generating<N> for GeneratingFunction<N> {
    type Workspace = Workspace<N>;
    fn workspace(&self) -> Workspace<N> {
        GeneratingFunction::workspace(self)
    }
    fn workspace_bytes(&self) -> usize {
        Workspace::bytes(self)
    }
    fn jet(&self, t: f64, p: &[f64; N], ws: &mut Workspace<N>) -> Jet2<N> {
        GeneratingFunction::jet(self, t, p, ws)
    }
    fn gradient(&self, t: f64, p: &[f64; N], ws: &mut Workspace<N>) -> Dual1<N> {
        GeneratingFunction::gradient(self, t, p, ws)
    }
    fn batch(&self) -> usize {
        batch_size(self.mlp.as_ref())
    }
    /// The MLP's layers as matrix–matrix products over the batch, the polynomial in lanes.
    fn jets(&self, t: f64, p: &[[f64; N]], out: &mut [Jet2<N>], ws: &mut Workspace<N>) {
        GeneratingFunction::jets(self, t, p, out, ws);
    }
    /// The MLP in reverse mode: fewer flops, the same numbers to round-off.
    fn gradients(&self, t: f64, p: &[[f64; N]], out: &mut [Dual1<N>], ws: &mut Workspace<N>) {
        self.gradients_reverse(t, p, out, ws);
    }
    fn polynomial(&self) -> Option<&Polynomial<N>> {
        self.mlp.is_none().then_some(&self.polynomial)
    }
    fn lane_parts(&self) -> Option<(&Polynomial<N>, Option<NetworkLanes<'_>>)> {
        match self.mlp {
            None => Some((&self.polynomial, None)),
            Some(_) => Some((&self.polynomial, Some(self.network_lanes()?))),
        }
    }
    fn lane_scratch<'w>(&self, ws: &'w mut Workspace<N>) -> &'w mut [LaneRow] {
        &mut ws.lanes
    }
}

/// Trajectories per batched Newton solve: enough columns (10 per trajectory) for the kernel's
/// register blocks, few enough that a k-block of activations stays in L2.
const BISECTION_BATCH: usize = 16;

/// Below this many MLP parameters a step is dominated by the per-trajectory work (polynomial,
/// chart, 3×3 solve), and batching only adds gathering. The 121-parameter default model is
/// about 2× faster batched (its tanh rows in SIMD lanes, its polynomial in lanes: see
/// docs/performance_bisection.md), the 253,501-parameter paper-sized one 2.5×.
const BATCH_MIN_PARAMETERS: usize = 100;

/// Trajectories per lockstep solve of a polynomial S (no MLP): its jets are evaluated in SIMD
/// lanes across them ([`crate::generating::polynomial_lanes`]), each lane bit-identical to the
/// scalar evaluation, so the batched step equals the one-trajectory step bit for bit.
const POLYNOMIAL_BATCH: usize = MAX_BATCH;

/// Trajectories per batched solve for a generating function whose MLP is `mlp`:
/// [`POLYNOMIAL_BATCH`] without an MLP, [`BISECTION_BATCH`] for MLPs of
/// [`BATCH_MIN_PARAMETERS`] or more, else 1 (one at a time).
pub fn batch_size(mlp: Option<&Mlp>) -> usize {
    match mlp {
        None => POLYNOMIAL_BATCH,
        Some(m) if m.n_parameters() >= BATCH_MIN_PARAMETERS => BISECTION_BATCH,
        Some(_) => 1,
    }
}

fn max_abs<const N: usize>(a: &[f64; N]) -> f64 {
    a.iter().fold(0.0, |m: f64, v| m.max(v.abs()))
}

/// The Newton solve of a bisection step, as [`crate::stepper::BisectionStepper`] runs it one
/// trajectory at a time or in lockstep: tar(∂S/∂p(h, p), p) = μ for p, then μ' from the realization. The Jacobian is
/// inverted once per refresh ([`Inverse`]); simplified Newton keeps it while the updates contract
/// by [`SIMPLIFIED_RATE`] or better, full Newton refreshes it every update.
pub(crate) struct Newton<'a, const N: usize, R> {
    pub realization: &'a R,
    pub tol: f64,
    pub max_iter: u32,
    pub simplified: bool,
    /// Newton stops once |δ|∞ ≤ tol · max(|p|∞, scale_floor).
    pub scale_floor: f64,
    /// Start from the realization's prediction ([`Realization::predict`]) where it has one.
    pub predict: bool,
}

impl<const N: usize, R: Realization<N>> Newton<'_, N, R>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    /// One trajectory's step: Newton from p = μ (or the realization's prediction from it),
    /// then μ' at the converged p.
    #[inline]
    pub(crate) fn step<G: Generating<N>>(
        &self,
        generating: &G,
        h: f64,
        mu: &mut [f64; N],
        ws: &mut G::Workspace,
    ) -> StepResult {
        let target = *mu;
        let mut p = target;
        if self.predict && self.realization.predicts() {
            let x0 = generating.gradient(h, &target, ws);
            if let Some(p0) = self.realization.predict(&x0.g, &target) {
                p = p0;
            }
        }
        let mut iterations = 0;
        let mut factors = None;
        let (mut refresh, mut last) = (true, f64::INFINITY);
        loop {
            let (converged, size) = if refresh {
                let jet = generating.jet(h, &p, ws);
                self.newton_update(&jet, &target, &mut p, &mut iterations, &mut factors)?
            } else {
                let g = generating.gradient(h, &p, ws);
                self.simplified_update(&g, &target, &mut p, &mut iterations, &factors)?
            };
            if converged {
                // x at the final p needs the gradient of S only, not its Hessian.
                let g = generating.gradient(h, &p, ws);
                return self.finish(&g, &target, &p, iterations, mu);
            }
            refresh = !self.simplified || size > SIMPLIFIED_RATE * last;
            last = size;
        }
    }

    /// One Newton update of p for tar(∂S/∂p(h,p), p) = μ from the jet of S at p, keeping its
    /// Jacobian's factors. Returns whether the update met the tolerance and |δ|∞.
    #[inline]
    pub(crate) fn newton_update(
        &self,
        jet: &Jet2<N>,
        target: &[f64; N],
        p: &mut [f64; N],
        iterations: &mut u32,
        factors: &mut Option<Inverse<N>>,
    ) -> Result<(bool, f64), StepFailure> {
        if !jet.is_finite() {
            return Err(StepFailure::NonFinite);
        }
        let (g, hs) = (jet.grad(), jet.hess());
        // x(p) = ∇S(p) carries the Hessian as its derivative; p carries the identity.
        let x: [Dual1<N>; N] = std::array::from_fn(|i| Dual1 { v: g[i], g: hs[i] });
        let pd: [Dual1<N>; N] = std::array::from_fn(|i| Dual1::var(p[i], i));
        let t = self.realization.tar(&x, &pd)?;
        // The cap is checked before the inverse, as before the LU factors.
        if *iterations >= self.max_iter {
            return Err(StepFailure::NotConverged);
        }
        let inv = factors.insert(Inverse::new(&t.map(|ti| ti.g))?);
        self.update(&t.map(|ti| ti.v), inv, target, p, iterations)
    }

    /// One simplified-Newton update of p from ∂S/∂p at p and a kept Jacobian.
    /// Returns whether it met the tolerance and |δ|∞.
    #[inline]
    pub(crate) fn simplified_update(
        &self,
        grad: &Dual1<N>,
        target: &[f64; N],
        p: &mut [f64; N],
        iterations: &mut u32,
        factors: &Option<Inverse<N>>,
    ) -> Result<(bool, f64), StepFailure> {
        if !grad.is_finite() {
            return Err(StepFailure::NonFinite);
        }
        // A simplified update always follows a full one, which kept the inverse.
        let inv = factors.as_ref().ok_or(StepFailure::SingularJacobian)?;
        let t = self.realization.tar(&grad.g, p)?;
        self.update(&t, inv, target, p, iterations)
    }

    /// p += δ with J δ = μ − tar(x, p), given tar(x, p) at the current p, unless the iteration
    /// cap is reached. Returns whether |δ|∞ ≤ tol · max(|p|∞, scale_floor), and |δ|∞.
    #[inline]
    fn update(
        &self,
        tar: &[f64; N],
        inv: &Inverse<N>,
        target: &[f64; N],
        p: &mut [f64; N],
        iterations: &mut u32,
    ) -> Result<(bool, f64), StepFailure> {
        if *iterations >= self.max_iter {
            return Err(StepFailure::NotConverged);
        }
        let f: [f64; N] = std::array::from_fn(|i| target[i] - tar[i]);
        let delta = inv.apply(&f);
        if !delta.iter().all(|d| d.is_finite()) {
            return Err(StepFailure::SingularJacobian);
        }
        for (pi, d) in p.iter_mut().zip(delta.iter()) {
            *pi += d;
        }
        *iterations += 1;
        let size = max_abs(&delta);
        Ok((size <= self.tol * max_abs(p).max(self.scale_floor), size))
    }

    /// μ' = sou(∂S/∂p, p) at the converged p, from the gradient of S there, as the realization
    /// forms it from μ ([`Realization::sou_after_solve`]); the residual of the solved equation
    /// goes into the stats.
    #[inline]
    pub(crate) fn finish(
        &self,
        grad: &Dual1<N>,
        target: &[f64; N],
        p: &[f64; N],
        iterations: u32,
        mu: &mut [f64; N],
    ) -> StepResult {
        if !grad.is_finite() {
            return Err(StepFailure::NonFinite);
        }
        let x = grad.g;
        let t = self.realization.tar(&x, p)?;
        let f: [f64; N] = std::array::from_fn(|i| t[i] - target[i]);
        let out = self.realization.sou_after_solve(&x, p, target)?;
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

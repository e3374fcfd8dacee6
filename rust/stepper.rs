//! One step of a bisection integrator: solve tar(∂S/∂p(h,p), p) = μ for p by Newton, then
//! μ' = sou(∂S/∂p(h,p), p), formed from μ by the realization
//! ([`Realization::sou_after_solve`]: on a Lie groupoid, the coadjoint action of the chart's
//! group element on μ, which keeps the Casimirs whatever Newton's residual). Generic over the
//! dimension N and over the realization that gives sou and tar ([`Realization`]: the
//! Lie-algebra groupoid by default, or the log-canonical one);
//! the Newton Jacobian is inverted once per refresh (closed form for N = 3, nalgebra's LU
//! otherwise), so every update, simplified or not, is one matrix–vector product.

use nalgebra::{Const, DimMin};

use crate::dual::{Dual1, Jet2};
use crate::error::StepFailure;
use crate::generating::{GeneratingFunction, Mlp, Workspace, MAX_BATCH};
use crate::isa::Isa;
use crate::lanes_bisection::{so3_newton_steps, So3Newton};
use crate::realization::{Newton, Realization};
use crate::step::step_each;
pub use crate::step::{
    adjugate3, inverse3, Inverse, NewtonOptions, StepMap, StepResult, StepStats, SIMPLIFIED_RATE,
};
use crate::structures::lie_groupoid::{Chart, Groupoid};

/// Whether a realization is an so(3) chart, where the bisection stepper solves a polynomial S's
/// Newton systems with the chart's closed-form Jacobian in SIMD lanes
/// ([`crate::lanes_bisection`]). Kept out of [`Realization`], which every structure implements:
/// only the Lie groupoid answers, any other realization takes the default with an empty impl.
pub trait So3Lanes<const N: usize> {
    /// The so(3) chart this realization is, if it is one.
    fn so3_chart(&self) -> Option<Chart> {
        None
    }
}

impl<const N: usize> So3Lanes<N> for Groupoid<N> {
    fn so3_chart(&self) -> Option<Chart> {
        (N == 3 && self.algebra.is_so3()).then_some(self.chart)
    }
}

/// Whether the so(3) lane solver starts from the explicit predictor (see
/// [`crate::lanes_bisection::So3Newton::predict`]).
const PREDICT: bool = true;

/// The bisection integrator of a generating function on a realization: a chart of the
/// Lie-algebra groupoid by default.
#[derive(Clone, Debug)]
pub struct BisectionStepper<const N: usize, R = Groupoid<N>> {
    pub generating: GeneratingFunction<N>,
    pub groupoid: R,
    pub newton: NewtonOptions,
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
/// scalar evaluation, so the batched step equals [`StepMap::step`] bit for bit.
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

impl<const N: usize, R: Realization<N> + So3Lanes<N>> BisectionStepper<N, R>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    /// The lane solver, where it applies: a polynomial S (no MLP) on an so(3) chart with
    /// simplified Newton. Full Newton keeps the generic dual-number path, bit-identical to
    /// [`crate::realization::RealizationStepper`].
    fn so3_lanes(&self) -> Option<So3Newton<'_, N>> {
        if N != 3 || !self.newton.simplified || self.generating.mlp.is_some() {
            return None;
        }
        Some(So3Newton {
            poly: &self.generating.polynomial,
            chart: self.groupoid.so3_chart()?,
            tol: self.newton.tol,
            max_iter: self.newton.max_iter,
            predict: PREDICT,
        })
    }

    /// The Newton solve with this stepper's settings (the floor of the relative tolerance at
    /// 1e-300, as good as none).
    #[inline]
    fn solver(&self) -> Newton<'_, N, R> {
        Newton {
            realization: &self.groupoid,
            tol: self.newton.tol,
            max_iter: self.newton.max_iter,
            simplified: self.newton.simplified,
            scale_floor: 1e-300,
        }
    }

    /// [`StepMap::step`] by the generic path (dual-number Jacobian, explicit inverse), whatever
    /// the realization and S: the reference the lane solver is tested against.
    pub fn step_generic(&self, h: f64, mu: &mut [f64; N], ws: &mut Workspace<N>) -> StepResult {
        self.solver().step(&self.generating, h, mu, ws)
    }
}

impl<const N: usize, R: Realization<N> + So3Lanes<N>> StepMap<N> for BisectionStepper<N, R>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    type Workspace = Workspace<N>;

    fn workspace(&self) -> Workspace<N> {
        self.generating.workspace()
    }

    fn workspace_bytes(&self) -> usize {
        Workspace::bytes(&self.generating)
    }

    /// One trajectory's Newton solve: the same updates as [`StepMap::step_batch`] (full Newton
    /// refreshes the Jacobian every update; simplified Newton keeps the first one's factors
    /// while the updates contract by [`SIMPLIFIED_RATE`] or better, needing ∂S/∂p only).
    ///
    /// A polynomial S on an so(3) chart with simplified Newton takes the lane solver with one
    /// lane: the bits of its lane in any block of [`StepMap::step_batch`].
    fn step(&self, h: f64, mu: &mut [f64; N], ws: &mut Workspace<N>) -> StepResult {
        if let Some(sys) = self.so3_lanes() {
            let mut result = [Err(StepFailure::NotConverged)];
            so3_newton_steps(
                &sys,
                Isa::detect(),
                h,
                std::slice::from_mut(mu),
                &[true],
                &mut result,
            );
            return result[0];
        }
        self.step_generic(h, mu, ws)
    }

    fn batch(&self) -> usize {
        batch_size(self.generating.mlp.as_ref())
    }

    /// The Newton solves of the batch in lockstep: each round evaluates S at the momenta still
    /// iterating in batched passes (the jet where a Jacobian is needed, else ∂S/∂p in reverse
    /// mode), and a trajectory leaves once it has converged.
    fn step_batch(
        &self,
        h: f64,
        mu: &mut [[f64; N]],
        live: &[bool],
        results: &mut [StepResult],
        ws: &mut Workspace<N>,
    ) {
        if let Some(sys) = self.so3_lanes() {
            return so3_newton_steps(&sys, Isa::detect(), h, mu, live, results);
        }
        // A polynomial S gives the same bits in lockstep lanes and one at a time, so a chunk too
        // small to fill the lanes takes the cheaper path (a rollout of one state, say).
        let few = self.generating.mlp.is_none() && live.iter().filter(|&&l| l).count() <= 2;
        if self.batch() == 1 || few {
            return step_each(self, h, mu, live, results, ws);
        }
        // The scratch below is sized at compile time: a chunk of a few trajectories (a rollout
        // of one state) takes small arrays instead of zeroing 32 trajectories' worth per step.
        if mu.len() <= FEW {
            self.lockstep::<FEW>(h, mu, live, results, ws);
        } else {
            self.lockstep::<MAX_BATCH>(h, mu, live, results, ws);
        }
    }
}

/// Chunks of at most this many trajectories take the small lockstep scratch.
const FEW: usize = 4;

impl<const N: usize, R: Realization<N> + So3Lanes<N>> BisectionStepper<N, R>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    /// [`StepMap::step_batch`]'s lockstep solve with scratch for `CAP` ≥ `mu.len()`
    /// trajectories (the same operations whatever `CAP`).
    fn lockstep<const CAP: usize>(
        &self,
        h: f64,
        mu: &mut [[f64; N]],
        live: &[bool],
        results: &mut [StepResult],
        ws: &mut Workspace<N>,
    ) {
        let n = mu.len();
        assert!(n <= CAP && CAP <= MAX_BATCH, "batch of {n} trajectories");
        let solver = self.solver();
        let mut p = [[0.0; N]; CAP];
        let mut iterations = [0u32; CAP];
        let mut factors: [Option<Inverse<N>>; CAP] = [None; CAP];
        // Whether the next update needs a fresh Jacobian, and the size of the last update.
        let mut refresh = [true; CAP];
        let mut last = [f64::INFINITY; CAP];
        // Indices of the trajectories still iterating, and of those converged.
        let (mut active, mut n_active) = ([0usize; CAP], 0);
        let (mut done, mut n_done) = ([0usize; CAP], 0);
        for i in (0..n).filter(|&i| live[i]) {
            p[i] = mu[i];
            active[n_active] = i;
            n_active += 1;
        }
        // Gathered momenta of the jet and gradient passes, their results and their owners.
        let (mut pj, mut jets, mut jet_of) = ([[0.0; N]; CAP], [Jet2::default(); CAP], [0; CAP]);
        let (mut pg, mut grads, mut grad_of) = ([[0.0; N]; CAP], [Dual1::default(); CAP], [0; CAP]);
        while n_active > 0 {
            let (mut nj, mut ng) = (0, 0);
            for &i in &active[..n_active] {
                if refresh[i] {
                    (pj[nj], jet_of[nj]) = (p[i], i);
                    nj += 1;
                } else {
                    (pg[ng], grad_of[ng]) = (p[i], i);
                    ng += 1;
                }
            }
            if nj > 0 {
                self.generating.jets(h, &pj[..nj], &mut jets[..nj], ws);
            }
            if ng > 0 {
                self.generating
                    .gradients_reverse(h, &pg[..ng], &mut grads[..ng], ws);
            }
            let mut still = 0;
            let mut settle = |i: usize, update: Result<(bool, f64), StepFailure>| match update {
                Err(e) => results[i] = Err(e),
                Ok((true, _)) => {
                    done[n_done] = i;
                    n_done += 1;
                }
                Ok((false, size)) => {
                    // Full Newton refreshes every time; simplified Newton only when an update
                    // contracted too little.
                    refresh[i] = !self.newton.simplified || size > SIMPLIFIED_RATE * last[i];
                    last[i] = size;
                    active[still] = i;
                    still += 1;
                }
            };
            for (jet, &i) in jets.iter().zip(&jet_of[..nj]) {
                let target = mu[i];
                let update = solver.newton_update(
                    jet,
                    &target,
                    &mut p[i],
                    &mut iterations[i],
                    &mut factors[i],
                );
                settle(i, update);
            }
            for (g, &i) in grads.iter().zip(&grad_of[..ng]) {
                let target = mu[i];
                let update = solver.simplified_update(
                    g,
                    &target,
                    &mut p[i],
                    &mut iterations[i],
                    &factors[i],
                );
                settle(i, update);
            }
            n_active = still;
        }
        if n_done == 0 {
            return;
        }
        for (q, &i) in pg.iter_mut().zip(&done[..n_done]) {
            *q = p[i];
        }
        self.generating
            .gradients_reverse(h, &pg[..n_done], &mut grads[..n_done], ws);
        for (g, &i) in grads.iter().zip(&done[..n_done]) {
            let target = mu[i];
            results[i] = solver.finish(g, &target, &p[i], iterations[i], &mut mu[i]);
        }
    }
}

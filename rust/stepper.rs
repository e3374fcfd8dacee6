//! The bisection integrator, one for every Poisson structure: solve tar(∂S/∂p(h,p), p) = μ for
//! p by Newton, then μ' = sou(∂S/∂p(h,p), p), formed from μ by the realization
//! ([`Realization::sou_after_solve`]: on a Lie groupoid, the coadjoint action of the chart's
//! group element on μ, which keeps the Casimirs whatever Newton's residual). Generic over the
//! dimension N, the realization that gives sou and tar ([`Realization`]: a Lie-algebra
//! groupoid by default, the log-canonical one, an order-n realization of a polynomial bivector)
//! and the generating function ([`Generating`]: Taylor terms plus an MLP by default, an
//! exponential polynomial, jets of an expression H). The Newton Jacobian is inverted once per
//! refresh (closed form for N = 3, nalgebra's LU otherwise), so every update, simplified or not,
//! is one matrix–vector product. A generating function that evaluates several momenta at once
//! has its Newton systems solved in lockstep; on an so(3) or se(3) chart, a polynomial S, or one
//! plus a network narrow enough ([`Generating::lane_parts`]), in SIMD lanes.

use nalgebra::{Const, DimMin};

use crate::dual::{Dual1, Jet2};
use crate::error::StepFailure;
use crate::generating::{GeneratingFunction, MAX_BATCH};
use crate::isa::Isa;
use crate::lanes_bisection::{so3_newton_steps, So3Newton};
use crate::lanes_bisection_exp::chart_newton_steps;
use crate::lanes_bisection_se3::{Se3Chart, Se3Newton};
use crate::lanes_bisection_series::{SeriesChart, SeriesNewton};
use crate::realization::{Generating, LaneChart, Newton, Realization};
use crate::step::step_each;
pub use crate::step::{
    adjugate3, inverse3, Inverse, NewtonOptions, StepMap, StepResult, StepStats, SIMPLIFIED_RATE,
};
use crate::structures::lie_groupoid::Groupoid;

/// Whether the so(3) lane solver starts from the explicit predictor (see
/// [`crate::lanes_bisection::So3Newton::predict`]).
const PREDICT: bool = true;

/// Newton's stopping floor of [`BisectionStepper::new`]: |δ|∞ ≤ tol · max(|p|∞, 1e-300), a
/// relative tolerance (the floor as good as none).
pub const RELATIVE_FLOOR: f64 = 1e-300;

/// The bisection integrator of a generating function `G` on a realization `R`: by default a
/// [`GeneratingFunction`] on a chart of the Lie-algebra groupoid.
#[derive(Clone, Debug)]
pub struct BisectionStepper<const N: usize, R = Groupoid<N>, G = GeneratingFunction<N>> {
    pub generating: G,
    pub realization: R,
    pub newton: NewtonOptions,
    /// Newton stops once |δ|∞ ≤ tol · max(|p|∞, scale_floor): [`RELATIVE_FLOOR`] on g*; 1 where
    /// the base coordinate is a logarithm or near 0 (log-canonical, order-n realizations), where
    /// a relative tolerance would ask for more than round-off.
    pub scale_floor: f64,
}

impl<const N: usize, R, G> BisectionStepper<N, R, G> {
    /// Newton as `newton` says, stopping on a relative tolerance ([`RELATIVE_FLOOR`]).
    pub fn new(generating: G, realization: R, newton: NewtonOptions) -> Self {
        BisectionStepper {
            generating,
            realization,
            newton,
            scale_floor: RELATIVE_FLOOR,
        }
    }

    /// Full Newton whatever `newton.simplified` says, stopping once
    /// |δ|∞ ≤ tol · max(|p|∞, 1): the settings of the log-canonical groupoid (base q = ln x) and
    /// of the order-n realizations, whose steps are validated with them.
    pub fn unit_scale(generating: G, realization: R, newton: NewtonOptions) -> Self {
        BisectionStepper {
            generating,
            realization,
            newton: NewtonOptions {
                simplified: false,
                ..newton
            },
            scale_floor: 1.0,
        }
    }
}

impl<const N: usize, R: Realization<N>, G: Generating<N>> BisectionStepper<N, R, G>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    /// The so(3) lane solver, where it applies: a polynomial S, or one plus a network term that
    /// fits the lanes ([`Generating::lane_parts`]), on a chart the realization names
    /// ([`Realization::lane_chart`]), with simplified Newton and the relative tolerance. Full
    /// Newton keeps the generic dual-number path.
    fn so3_lanes(&self) -> Option<So3Newton<'_, N>> {
        if N != 3 || !self.newton.simplified || self.scale_floor != RELATIVE_FLOOR {
            return None;
        }
        let Some(LaneChart::So3(chart)) = self.realization.lane_chart() else {
            return None;
        };
        let (poly, network) = self.generating.lane_parts()?;
        Some(So3Newton {
            poly,
            network,
            chart,
            tol: self.newton.tol,
            max_iter: self.newton.max_iter,
            predict: PREDICT,
        })
    }

    /// The se(3) lane solver, where it applies: S as [`Self::so3_lanes`] takes it, on se(3)'s
    /// exponential chart, with simplified Newton and the relative tolerance (as [`Self::so3_lanes`]).
    fn se3_lanes(&self) -> Option<Se3Newton<'_, N>> {
        if N != 6 || !self.newton.simplified || self.scale_floor != RELATIVE_FLOOR {
            return None;
        }
        if self.realization.lane_chart() != Some(LaneChart::Se3Exp) {
            return None;
        }
        let (poly, network) = self.generating.lane_parts()?;
        Some(Se3Newton {
            poly,
            network,
            chart: Se3Chart,
            tol: self.newton.tol,
            max_iter: self.newton.max_iter,
            predict: PREDICT,
        })
    }

    /// The series lane solver, where it applies: S as [`Self::so3_lanes`] takes it, on the
    /// exponential chart of any other Lie algebra ([`LaneChart::ExpSeries`]), with simplified
    /// Newton and the relative tolerance (as [`Self::so3_lanes`]).
    fn series_lanes(&self) -> Option<SeriesNewton<'_, N>> {
        if !self.newton.simplified || self.scale_floor != RELATIVE_FLOOR {
            return None;
        }
        if self.realization.lane_chart() != Some(LaneChart::ExpSeries) {
            return None;
        }
        let algebra = self.realization.lie_algebra()?;
        let (poly, network) = self.generating.lane_parts()?;
        Some(SeriesNewton {
            poly,
            network,
            chart: SeriesChart { algebra },
            tol: self.newton.tol,
            max_iter: self.newton.max_iter,
            predict: PREDICT,
        })
    }

    /// The Newton solve with this stepper's settings.
    #[inline]
    fn solver(&self) -> Newton<'_, N, R> {
        Newton {
            realization: &self.realization,
            tol: self.newton.tol,
            max_iter: self.newton.max_iter,
            simplified: self.newton.simplified,
            scale_floor: self.scale_floor,
            predict: true,
        }
    }

    /// [`StepMap::step`] by the generic path (dual-number Jacobian, explicit inverse), whatever
    /// the realization and S, started from μ (no prediction): the reference the lane solver and
    /// the predicted start are tested against.
    pub fn step_generic(&self, h: f64, mu: &mut [f64; N], ws: &mut G::Workspace) -> StepResult {
        let solver = Newton {
            predict: false,
            ..self.solver()
        };
        solver.step(&self.generating, h, mu, ws)
    }
}

impl<const N: usize, R: Realization<N>, G: Generating<N>> StepMap<N> for BisectionStepper<N, R, G>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    type Workspace = G::Workspace;

    fn workspace(&self) -> G::Workspace {
        self.generating.workspace()
    }

    fn workspace_bytes(&self) -> usize {
        self.generating.workspace_bytes()
    }

    /// One trajectory's Newton solve: the same updates as [`StepMap::step_batch`] (full Newton
    /// refreshes the Jacobian every update; simplified Newton keeps the first one's factors
    /// while the updates contract by [`SIMPLIFIED_RATE`] or better, needing ∂S/∂p only).
    ///
    /// S on a Lie algebra's chart with simplified Newton, where it fits the lanes
    /// ([`Generating::lane_parts`]), takes the lane solver with one lane: the bits of its lane
    /// in any block of [`StepMap::step_batch`].
    fn step(&self, h: f64, mu: &mut [f64; N], ws: &mut G::Workspace) -> StepResult {
        let mut result = [Err(StepFailure::NotConverged)];
        if let Some(sys) = self.so3_lanes() {
            let one = std::slice::from_mut(mu);
            let buf = self.generating.lane_scratch(ws);
            so3_newton_steps(&sys, Isa::detect(), buf, h, one, &[true], &mut result);
            return result[0];
        }
        if let Some(sys) = self.se3_lanes() {
            let one = std::slice::from_mut(mu);
            let buf = self.generating.lane_scratch(ws);
            chart_newton_steps(&sys, Isa::detect(), buf, h, one, &[true], &mut result);
            return result[0];
        }
        if let Some(sys) = self.series_lanes() {
            let one = std::slice::from_mut(mu);
            let buf = self.generating.lane_scratch(ws);
            chart_newton_steps(&sys, Isa::detect(), buf, h, one, &[true], &mut result);
            return result[0];
        }
        self.solver().step(&self.generating, h, mu, ws)
    }

    fn batch(&self) -> usize {
        self.generating.batch()
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
        ws: &mut G::Workspace,
    ) {
        if let Some(sys) = self.so3_lanes() {
            let buf = self.generating.lane_scratch(ws);
            return so3_newton_steps(&sys, Isa::detect(), buf, h, mu, live, results);
        }
        if let Some(sys) = self.se3_lanes() {
            let buf = self.generating.lane_scratch(ws);
            return chart_newton_steps(&sys, Isa::detect(), buf, h, mu, live, results);
        }
        if let Some(sys) = self.series_lanes() {
            let buf = self.generating.lane_scratch(ws);
            return chart_newton_steps(&sys, Isa::detect(), buf, h, mu, live, results);
        }
        // A polynomial S gives the same bits in lockstep lanes and one at a time, so a chunk too
        // small to fill the lanes takes the cheaper path (a rollout of one state, say).
        let few =
            self.generating.polynomial().is_some() && live.iter().filter(|&&l| l).count() <= 2;
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

impl<const N: usize, R: Realization<N>, G: Generating<N>> BisectionStepper<N, R, G>
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
        ws: &mut G::Workspace,
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
        if solver.predict && self.realization.predicts() && n_active > 0 {
            // The one-trajectory step's start (Newton::step), from the same gradients.
            for (q, &i) in pg.iter_mut().zip(&active[..n_active]) {
                *q = mu[i];
            }
            self.generating
                .gradients(h, &pg[..n_active], &mut grads[..n_active], ws);
            for (g, &i) in grads.iter().zip(&active[..n_active]) {
                if let Some(p0) = self.realization.predict(&g.g, &mu[i]) {
                    p[i] = p0;
                }
            }
        }
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
                    .gradients(h, &pg[..ng], &mut grads[..ng], ws);
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
            .gradients(h, &pg[..n_done], &mut grads[..n_done], ws);
        for (g, &i) in grads.iter().zip(&done[..n_done]) {
            let target = mu[i];
            results[i] = solver.finish(g, &target, &p[i], iterations[i], &mut mu[i]);
        }
    }
}

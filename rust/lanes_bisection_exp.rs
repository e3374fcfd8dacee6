//! The simplified-Newton bisection solve of S in SIMD lanes on a Lie algebra's exponential chart,
//! one solver for every chart that implements [`ExpChartLanes`]: se(3)'s closed form
//! ([`crate::lanes_bisection_se3`]) and any algebra's Bernoulli series
//! ([`crate::lanes_bisection_series`]). A block of trajectories in lockstep, each lane
//! bit-identical to the one-lane solve (the one-trajectory step):
//!
//! - Newton started from the first-order p₁ = μ − ½ A(x₀) μ (x₀: the gradient of S's t¹ … t³
//!   terms at μ) and a few fixed-point steps from there, ∇S linearized at μ
//!   ([`second_order_start`]);
//! - each round tar(x, p) with x = ∇S(p), and on a Jacobian refresh its exact p-Jacobian
//!   J = ∂tar/∂p + ∂tar/∂x · Hess S, inverted by Gauss–Jordan lane by lane ([`inverse_lanes`]);
//! - the new state e^{−A(x)} μ by the chart's coadjoint action, on μ's coadjoint orbit whatever
//!   Newton's residual.
//!
//! so(3) keeps its own solver ([`crate::lanes_bisection`]): its Cayley chart, its 3×3 inverse by
//! cofactors and its own second-order start (`so3_start`).

// Index loops over lanes, coordinates and matrix entries read as the formulas they evaluate.
#![allow(clippy::needless_range_loop)]

use std::array::from_fn;

use crate::error::StepFailure;
use crate::generating::polynomial_lanes::{jet_lanes_into, JetLanes, Scratch};
use crate::generating::LaneRow;
use crate::isa::Isa;
use crate::lanes_bisection::{
    evaluate, finite_probe, inverse_lanes, lane_newton_steps, load_block, round_probes,
    ChartNewton, LaneSolve, Progress, PREDICT_MAX_S, V,
};
use crate::step::{StepResult, StepStats};

/// A Lie algebra's exponential chart on g* in lanes, as [`ChartNewton`]'s solve needs it. Every
/// method works lane by lane: a lane's numbers never depend on another lane's.
pub(crate) trait ExpChartLanes<const N: usize> {
    /// A(x) q with A = ad_xᵀ, and with `twice` also A(x)² q (else zeros), lane by lane. On every
    /// exponential chart tar(x, p) = p + ½ A(x) p + A(x)² p / 12 + O(|x|⁴) (the Bernoulli
    /// series: B₁ = −½, B₂/2! = 1/12), which Newton's start reads.
    fn turns<const L: usize>(
        &self,
        x: &[V<L>; N],
        q: &[V<L>; N],
        twice: bool,
    ) -> ([V<L>; N], [V<L>; N]);

    /// tar(x, p) on the lanes in `live`, and with `hess` (S's Hessian, symmetric) also its exact
    /// p-Jacobian into `jac` (left alone without it), J[r][k] = ∂tar_r/∂p_k. Per lane the
    /// chart's failure, if any, and the size the second-order start is judged by (kept where it
    /// is at most [`PREDICT_MAX_S`]).
    fn tar<const L: usize>(
        &self,
        x: &[V<L>; N],
        p: &[V<L>; N],
        hess: Option<&[[V<L>; N]; N]>,
        jac: &mut [[V<L>; N]; N],
        live: &[bool; L],
    ) -> ([V<L>; N], [Option<StepFailure>; L], V<L>);

    /// μ' = e^{−A(x)} μ on the lanes in `live`; per lane the failure, if any.
    fn coadjoint<const L: usize>(
        &self,
        x: &[V<L>; N],
        mu: &[V<L>; N],
        live: &[bool; L],
    ) -> ([V<L>; N], [Option<StepFailure>; L]);
}

/// Fixed-point steps of Newton's start on an exponential chart: 3 take the heavy top's Taylor
/// K = 3 / 5 at h = 0.1 from 3.00 to 2.00 Newton updates a step (1 leaves 3.00, 2 leave 2.39;
/// `benches/newton_predictors.py`'s replay).
pub(crate) const START_STEPS: usize = 3;

/// Newton's start and the lanes that take it. From two passes at μ, the gradient x₀ of S's t¹ …
/// t³ terms and the Hessian of its t¹, t² terms (no network, no t⁴ … terms), the first-order
/// p = μ − ½ A(x₀) μ and then [`START_STEPS`] steps of the fixed-point iteration
/// p ← p + μ − tar(x̃, p), with tar to second order, p ← μ − ½ A(x̃) p − A(x̃)² p / 12, and
/// x̃ = x₀ + Hess · (p − μ), ∇S(p) linearized at μ (a t³ term's Hessian times p − μ is O(h⁴)).
/// Each step costs a few products, where a gradient pass and a chart evaluation at p would
/// cost about a Newton update. On the heavy top the t³ terms' gradient and the third step
/// matter: with S's t¹, t² terms alone the steps stall where update 1 moves 1.6e-5 (3.00
/// updates), with them it moves 7e-7 (2.00). Taken where |x₀|², |x̃|² ≤ [`PREDICT_MAX_S`] (the
/// expansion meaningful) and the start is finite.
// Out of line: once a block, and inlined it moved the learned heavy top's network Hessian in
// the block's frame (1.9× its step).
#[inline(never)]
pub(crate) fn second_order_start<const N: usize, const L: usize, C: ExpChartLanes<N>>(
    sys: &ChartNewton<'_, N, C>,
    t: f64,
    pl: &[[f64; L]; N],
    mu: &[V<L>; N],
    scratch: &mut Scratch<N, L>,
    jet: &mut JetLanes<N, L>,
) -> ([V<L>; N], [bool; L]) {
    jet_lanes_into::<N, L, true, 2>(sys.poly, t, pl, scratch, jet);
    let hess: [[V<L>; N]; N] = from_fn(|a| from_fn(|b| V(jet.h[a.min(b)][a.max(b)])));
    jet_lanes_into::<N, L, false, 3>(sys.poly, t, pl, scratch, jet);
    let x0: [V<L>; N] = from_fn(|i| V(jet.g[i]));
    let (a0, _) = sys.chart.turns(&x0, mu, false);
    let mut p: [V<L>; N] = from_fn(|i| mu[i] - a0[i].scale(0.5));
    let square = |x: &[V<L>; N]| x.iter().fold(V::splat(0.0), |a, v| a + *v * *v);
    let mut largest = square(&x0);
    for _ in 0..START_STEPS {
        let mut xt = x0;
        for a in 0..N {
            for b in 0..N {
                xt[a] = xt[a] + hess[a][b] * (p[b] - mu[b]);
            }
        }
        let (a1, a2) = sys.chart.turns(&xt, &p, true);
        p = from_fn(|i| mu[i] - a1[i].scale(0.5) - a2[i].scale(1.0 / 12.0));
        largest = largest.max(square(&xt));
    }
    let probe = finite_probe(p);
    let keep = from_fn(|l| largest.0[l] <= PREDICT_MAX_S && probe.0[l] == 0.0);
    (p, keep)
}

/// One step of at most L trajectories (`mu.len()` ≤ L; those with `live` false are left alone)
/// by simplified Newton in lanes: the rule of the generic one-trajectory step (refresh the
/// Jacobian while updates contract by less than
/// [`SIMPLIFIED_RATE`](crate::step::SIMPLIFIED_RATE), stop once
/// |δ|∞ ≤ tol · max(|p|∞, 1e-300)) and its failures in its order, lane by lane. A lane that
/// converged or failed is frozen; the block runs until every lane has.
// Out of line in debug builds: inlined there, every local of every instantiation keeps its
// own slot in the dispatching frames, and a test thread's stack overflowed.
#[cfg_attr(not(debug_assertions), inline(always))]
#[cfg_attr(debug_assertions, inline(never))]
fn chart_block<const N: usize, const L: usize, C: ExpChartLanes<N>>(
    sys: &ChartNewton<'_, N, C>,
    buf: &mut [LaneRow],
    t: f64,
    mu: &mut [[f64; N]],
    live: &[bool],
    results: &mut [StepResult],
) {
    let n = mu.len();
    debug_assert!(n <= L);
    let (mut pl, active) = load_block::<N, L>(mu, live);
    let target: [V<L>; N] = from_fn(|i| V(pl[i]));
    let mut p = target;
    let net = sys.network.as_ref();
    let mut scratch = Scratch::<N, L>::new();
    let mut jet = JetLanes {
        v: [0.0; L],
        g: [[0.0; L]; N],
        h: [[[0.0; L]; N]; N],
    };
    // The kept inverse per lane, and this round's Hessian, Jacobian and inverse.
    let zero = [[V::splat(0.0); N]; N];
    let (mut inv, mut h, mut jac, mut fresh) = (zero, zero, zero, zero);
    if sys.predict {
        let (p0, keep) = second_order_start(sys, t, &pl, &target, &mut scratch, &mut jet);
        for i in 0..N {
            p[i] = p[i].blend(&keep, p0[i]);
        }
    }
    let mut progress = Progress::new(active);
    // x = ∇S at each converged lane's p from its last update, x + Hess S · δ with the Hessian
    // of the lane's last refresh (off by O(|δ| · |p − p_refresh| + |δ|²), far below a rounding
    // at |δ| ≤ tol·|p|; the gradient pass at the solution saved).
    let mut xs: [V<L>; N] = [V::splat(0.0); N];
    while progress.running() {
        let hess = progress.jacobian_wanted();
        for i in 0..N {
            pl[i] = p[i].0;
        }
        if hess {
            evaluate::<N, L, true>(sys.poly, net, t, &pl, &mut scratch, buf, &mut jet);
        } else {
            evaluate::<N, L, false>(sys.poly, net, t, &pl, &mut scratch, buf, &mut jet);
        }
        let mut x = target;
        for i in 0..N {
            x[i] = V(jet.g[i]);
        }
        if hess {
            // Only the refreshing lanes take the new Hessian: `h` is each lane's Hessian of its
            // own last refresh, which the first-order x at the solution needs (another lane's
            // refresh must not change a lane's bits).
            let take: [bool; L] = from_fn(|l| progress.active[l] && progress.refresh[l]);
            for a in 0..N {
                for b in 0..N {
                    h[a][b] = h[a][b].blend(&take, V(jet.h[a.min(b)][a.max(b)]));
                }
            }
        }
        let (tar, chart, _) = sys
            .chart
            .tar(&x, &p, hess.then_some(&h), &mut jac, &progress.active);
        let ok = if hess {
            inverse_lanes(&jac, &mut fresh)
        } else {
            [false; L]
        };
        let (probe, hess_probe) = round_probes(&jet.v, &x, &h, hess);
        // `take`: the lanes whose fresh inverse is taken this round.
        let (go, take) = progress.judge(
            &probe,
            &hess_probe,
            |l| chart[l],
            sys.max_iter,
            |l| ok[l],
            results,
        );
        if take.contains(&true) {
            for r in 0..N {
                for k in 0..N {
                    inv[r][k] = inv[r][k].blend(&take, fresh[r][k]);
                }
            }
        }
        // δ = J⁻¹ (μ − tar), each component summed in column order.
        let mut f = tar;
        for i in 0..N {
            f[i] = target[i] - tar[i];
        }
        let mut delta = f;
        for r in 0..N {
            let mut acc = inv[r][0] * f[0];
            for k in 1..N {
                acc = acc + inv[r][k] * f[k];
            }
            delta[r] = acc;
        }
        progress.update(&go, &mut p, &delta, sys.tol, results);
        let newly: [bool; L] = from_fn(|l| go[l] && progress.converged[l]);
        if newly.contains(&true) {
            for a in 0..N {
                let mut acc = x[a];
                for b in 0..N {
                    acc = acc + h[a][b] * delta[b];
                }
                xs[a] = xs[a].blend(&newly, acc);
            }
        }
    }
    if !progress.converged.contains(&true) {
        return;
    }
    // μ' = e^{−A(x)} μ with x = ∇S(p) at the converged p (sou(x, p) up to Newton's residual,
    // which the coadjoint action leaves out); the residual of the solved equation into the
    // stats.
    let x = xs;
    let done = progress.converged;
    let (tar, chart, _) = sys.chart.tar(&x, &p, None, &mut jac, &done);
    let (next, moved) = sys.chart.coadjoint(&x, &target, &done);
    let x_probe = finite_probe(x);
    for l in (0..n).filter(|&l| done[l]) {
        results[l] = if x_probe.0[l] != 0.0 {
            Err(StepFailure::NonFinite)
        } else if let Some(e) = chart[l].or(moved[l]) {
            Err(e)
        } else {
            let mut residual = 0.0f64;
            for i in 0..N {
                mu[l][i] = next[i].0[l];
                residual = residual.max((tar[i].0[l] - target[i].0[l]).abs());
            }
            Ok(StepStats {
                iterations: progress.iterations[l],
                residual,
            })
        };
    }
}

impl<const N: usize, C: ExpChartLanes<N>> LaneSolve<N> for ChartNewton<'_, N, C> {
    #[inline(always)]
    fn block<const L: usize>(
        &self,
        buf: &mut [LaneRow],
        t: f64,
        mu: &mut [[f64; N]],
        live: &[bool],
        results: &mut [StepResult],
    ) {
        chart_block::<N, L, C>(self, buf, t, mu, live, results);
    }
}

/// One simplified-Newton bisection step of every `mu[j]` with `live[j]` on the chart of `sys`:
/// [`lane_newton_steps`] of [`ChartNewton`].
pub(crate) fn chart_newton_steps<const N: usize, C: ExpChartLanes<N>>(
    sys: &ChartNewton<'_, N, C>,
    isa: Isa,
    buf: &mut [LaneRow],
    t: f64,
    mu: &mut [[f64; N]],
    live: &[bool],
    results: &mut [StepResult],
) {
    lane_newton_steps(sys, isa, buf, t, mu, live, results);
}

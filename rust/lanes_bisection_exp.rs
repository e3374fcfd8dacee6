//! The simplified-Newton bisection solve of S in SIMD lanes on a Lie algebra's exponential chart,
//! one solver for every chart that implements [`ExpChartLanes`]: se(3)'s closed form
//! ([`crate::lanes_bisection_se3`]) and any algebra's Bernoulli series
//! ([`crate::lanes_bisection_series`]). A block of trajectories in lockstep, each lane
//! bit-identical to the one-lane solve (the one-trajectory step):
//!
//! - Newton started second order: the first-order p₁ = μ − ½ A(x₀) μ (x₀: the gradient of S's
//!   t¹ and t² terms at μ) and one fixed-point step from there, ∇S linearized at μ;
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
    /// Whether the chart's blocks run compiled for AVX-512 where the CPU has it
    /// ([`LaneSolve::avx512`]); by default up to [`crate::isa::AVX512_MAX_DIM`] coordinates.
    const AVX512: bool = N <= crate::isa::AVX512_MAX_DIM;

    /// A(x) q with A = ad_xᵀ, lane by lane. On every exponential chart
    /// tar(x, p) = p + ½ A(x) p + A(x)² p / 12 + O(|x|⁴) (the Bernoulli series: B₁ = −½,
    /// B₂/2! = 1/12), which Newton's start reads.
    fn turn<const L: usize>(&self, x: &[V<L>; N], q: &[V<L>; N]) -> [V<L>; N];

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

/// Newton's start, O(h³) from the solution, and the lanes that take it: from one jet of S's t¹
/// and t² terms at μ with its Hessian (x₀ and Hess; no network, no t³ … terms), the first-order
/// p₁ = μ − ½ A(x₀) μ and one fixed-point step p₀ = p₁ + μ − tar(x̃, p₁) with tar to second
/// order, p₀ = μ − ½ A(x̃) p₁ − A(x̃)² p₁ / 12, and x̃ = x₀ + Hess · (p₁ − μ) = ∇S(p₁) + O(h³)
/// (the Hessian at μ standing in for a gradient pass and a chart evaluation at p₁: the same
/// 3.00 updates a step on the heavy top as with them, `benches/newton_predictors.py`). Taken
/// where |x₀|², |x̃|² ≤ [`PREDICT_MAX_S`] (the expansion meaningful) and p₀ is finite.
///
/// Tried and not kept (`benches/step_costs.py`, docs/performance.md): three such steps from the
/// gradient of S's t¹ … t³ terms take the heavy top's Taylor K = 3 / 5 to 2.02 updates a step
/// but 1.18× / 1.04× its time (the t³ gradient is most of S at K = 3); three steps without the
/// t³ terms, 2.77 updates and 1.26× / 1.18×.
// Out of line: inlined into the block it made the learned heavy top's step 1.9× slower while
// the network Hessian summed its entries through memory; with those sums in registers, inlined
// it read 0.98–1.01× on the heavy top's steps (no gain). Out of line it runs without the
// block's `avx2,fma` code generation, which one step can afford.
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
    let x0: [V<L>; N] = from_fn(|i| V(jet.g[i]));
    let a0 = sys.chart.turn(&x0, mu);
    let p1: [V<L>; N] = from_fn(|i| mu[i] - a0[i].scale(0.5));
    let mut xt = x0;
    for a in 0..N {
        for b in 0..N {
            xt[a] = xt[a] + V(jet.h[a.min(b)][a.max(b)]) * (p1[b] - mu[b]);
        }
    }
    let a1 = sys.chart.turn(&xt, &p1);
    let a2 = sys.chart.turn(&xt, &a1);
    let p0: [V<L>; N] = from_fn(|i| mu[i] - a1[i].scale(0.5) - a2[i].scale(1.0 / 12.0));
    let square = |x: &[V<L>; N]| x.iter().fold(V::splat(0.0), |a, v| a + *v * *v);
    let (s0, st) = (square(&x0), square(&xt));
    let probe = finite_probe(p0);
    let keep =
        from_fn(|l| s0.0[l] <= PREDICT_MAX_S && st.0[l] <= PREDICT_MAX_S && probe.0[l] == 0.0);
    (p0, keep)
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
    fn avx512(&self) -> bool {
        C::AVX512
    }

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

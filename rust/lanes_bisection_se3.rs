//! The se(3) Newton solve of a polynomial S in SIMD lanes: the heavy top's Taylor-HJ bisection
//! step for a block of trajectories in lockstep, each lane bit-identical to the one-trajectory
//! step. What [`crate::lanes_bisection`] does on so(3), on se(3)'s exponential chart in closed
//! form (the groupoid's `se3_chart`):
//!
//! - tar(x, p) in lanes with the scalar chart's operations, so its values are the scalar chart's
//!   bits; its exact p-Jacobian J = ∂T/∂p + ∂T/∂x · Hess S in forward mode, six tangents per
//!   lane (x carries the Hessian's rows, p the identity);
//! - J⁻¹ by Gauss–Jordan with partial pivoting, the pivot rows chosen and swapped lane by lane;
//! - Newton started from p₀ = μ − ½ ad_{x₀}ᵀ μ (x₀: the gradient of S's terms linear in t);
//! - the new state g(x)·μ by the closed-form coadjoint action (`se3_coadjoint`), lane by lane.

// Index loops over lanes, coordinates and matrix entries read as the formulas they evaluate.
#![allow(clippy::needless_range_loop)]

use std::array::from_fn;
use std::ops::{Add, Mul, Sub};

use crate::error::StepFailure;
use crate::generating::polynomial_lanes::{jet_lanes_into, JetLanes, Scratch};
use crate::generating::{LaneRow, NetworkLanes, Polynomial};
use crate::isa::Isa;
use crate::lanes_bisection::{
    evaluate, finite_probe, inverse_lanes, lane_newton_steps, load_block, round_probes, LaneSolve,
    Progress, D, PREDICT_MAX_S, V,
};
use crate::step::{StepResult, StepStats};
use crate::structures::lie_groupoid::{
    exp_chart_coefficient_derivatives_to, exp_chart_coefficient_to, se3_coadjoint, C_SERIES,
    EXP_CHART_MAX_ANGLE,
};

type V6<const L: usize> = [V<L>; 6];
type M6<const L: usize> = [[V<L>; 6]; 6];

/// What the chart is evaluated on: lane values ([`V`]) or lane values with their derivatives
/// along the six p-directions ([`D`]).
trait Lane<const L: usize>:
    Copy + Add<Output = Self> + Sub<Output = Self> + Mul<Output = Self>
{
    fn times(self, c: f64) -> Self;
    /// f(s), from f's values and s-derivatives at s's values.
    fn chain(s: &Self, f: V<L>, df: V<L>) -> Self;
}

impl<const L: usize> Lane<L> for V<L> {
    #[inline(always)]
    fn times(self, c: f64) -> Self {
        self.scale(c)
    }
    #[inline(always)]
    fn chain(_: &Self, f: V<L>, _: V<L>) -> Self {
        f
    }
}

/// L values with their derivatives along the six p-directions.
type D6<const L: usize> = D<L, 6>;

impl<const L: usize> Lane<L> for D6<L> {
    #[inline(always)]
    fn times(self, c: f64) -> Self {
        D::times(self, c)
    }
    #[inline(always)]
    fn chain(s: &Self, f: V<L>, df: V<L>) -> Self {
        let mut r = *s;
        r.v = f;
        for k in 0..6 {
            r.d[k] = df * s.d[k];
        }
        r
    }
}

/// The same products in the same order as the groupoid's `cross`.
#[inline(always)]
fn cross<const L: usize, T: Lane<L>>(a: &[T; 3], b: &[T; 3]) -> [T; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[inline(always)]
fn dot<const L: usize, T: Lane<L>>(a: &[T; 3], b: &[T; 3]) -> T {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// c(s), c'(s) and, when `second`, c''(s) of the exponential chart at s = |ω|², lane by lane:
/// the groupoid's `exp_chart_coefficient_to` / `exp_chart_coefficient_derivatives_to` (the
/// same Horner chains below s = 1, summed in lanes; their closed forms lane by lane above).
#[inline(always)]
fn chart_coefficients<const L: usize>(s: V<L>, second: bool) -> (V<L>, V<L>, V<L>) {
    let zero = V::splat(0.0);
    let (mut c, mut c1, mut c2) = (zero, zero, zero);
    for (n, &a) in C_SERIES.iter().enumerate().rev() {
        let nf = n as f64;
        c = c * s + V::splat(a);
        if n >= 1 {
            c1 = c1 * s + V::splat(nf * a);
        }
        if second && n >= 2 {
            c2 = c2 * s + V::splat(nf * (nf - 1.0) * a);
        }
    }
    for l in 0..L {
        if s.0[l] >= 1.0 {
            c.0[l] = exp_chart_coefficient_to(s.0[l], 0).0;
            let (d1, d2, _) = exp_chart_coefficient_derivatives_to(s.0[l], u8::from(second));
            (c1.0[l], c2.0[l]) = (d1, d2);
        }
    }
    (c, c1, c2)
}

/// tar(x, p) of se(3)'s exponential chart, x = (ω, v), p = (p_R, p_T), given c = c(|ω|²) and
/// c₁ = c'(|ω|²): the groupoid's `se3_chart` with sign −1, operation for operation.
#[inline(always)]
fn tar<const L: usize, T: Lane<L>>(x: &[T; 6], p: &[T; 6], c: T, c1: T) -> [T; 6] {
    let w = [x[0], x[1], x[2]];
    let v = [x[3], x[4], x[5]];
    let pr = [p[0], p[1], p[2]];
    let pt = [p[3], p[4], p[5]];
    let half = -0.5;
    let (wpr, wpt, vpt) = (cross(&w, &pr), cross(&w, &pt), cross(&v, &pt));
    let (wwpr, wwpt) = (cross(&w, &wpr), cross(&w, &wpt));
    let (vwpt, wvpt) = (cross(&v, &wpt), cross(&w, &vpt));
    let k = dot(&w, &v).times(2.0) * c1;
    let mut out = *p;
    for i in 0..3 {
        let d = vpt[i].times(half) + k * wwpt[i] + c * (vwpt[i] + wvpt[i]);
        out[i] = pr[i] + wpr[i].times(half) + c * wwpr[i] + d;
        out[3 + i] = pt[i] + wpt[i].times(half) + c * wwpt[i];
    }
    out
}

/// tar(x, p) of se(3)'s exponential chart in lanes (the scalar chart's bits) and |ω|²; with
/// `hess` (S's Hessian, symmetric) also the exact p-Jacobian of tar(∇S(p), p) into `jac`,
/// J[r][k] = ∂tar_r/∂p_k (left alone without it).
#[inline(always)]
pub(crate) fn se3_tar_lanes<const L: usize>(
    x: &V6<L>,
    p: &V6<L>,
    hess: Option<&M6<L>>,
    jac: &mut M6<L>,
) -> (V6<L>, V<L>) {
    let w = [x[0], x[1], x[2]];
    let s = dot(&w, &w);
    let (c, c1, c2) = chart_coefficients(s, hess.is_some());
    let Some(h) = hess else {
        return (tar(x, p, c, c1), s);
    };
    let (zero, one) = (V::splat(0.0), V::splat(1.0));
    // ∂x_i/∂p_k = Hess S[i][k]; ∂p_i/∂p_k = δ_ik.
    let mut xd = [D {
        v: zero,
        d: [zero; 6],
    }; 6];
    let mut pd = xd;
    for i in 0..6 {
        xd[i].v = x[i];
        xd[i].d = h[i];
        pd[i].v = p[i];
        pd[i].d[i] = one;
    }
    let wd = [xd[0], xd[1], xd[2]];
    let sd = dot(&wd, &wd);
    let t = tar(&xd, &pd, D::chain(&sd, c, c1), D::chain(&sd, c1, c2));
    let mut value = *p;
    for r in 0..6 {
        value[r] = t[r].v;
        jac[r] = t[r].d;
    }
    (value, s)
}

/// What the lane Newton solve of S on se(3) needs: S's polynomial part (N = 6) and network term
/// if it has one, and the simplified-Newton settings.
pub(crate) struct Se3Newton<'a, const N: usize> {
    pub poly: &'a Polynomial<N>,
    pub network: Option<NetworkLanes<'a>>,
    pub tol: f64,
    pub max_iter: u32,
    /// Start Newton from p₀ = μ − ½ ad_{x₀}ᵀ μ (x₀: the t-linear terms' gradient at μ) and one
    /// fixed-point step from there, instead of μ, where |x₀|² ≤ [`PREDICT_MAX_S`].
    pub predict: bool,
}

/// One step of at most L trajectories (`mu.len()` ≤ L; those with `live` false are left alone)
/// by simplified Newton in lanes: the rule and the failures of the generic one-trajectory step
/// (refresh the Jacobian while updates contract by less than
/// [`SIMPLIFIED_RATE`](crate::step::SIMPLIFIED_RATE), stop once
/// |δ|∞ ≤ tol · max(|p|∞, 1e-300)), lane by lane. A lane that converged or failed is frozen; the
/// block runs until every lane has.
// Out of line in debug builds: inlined there, every local of every instantiation keeps its
// own slot in the dispatching frames, and a test thread's stack overflowed.
#[cfg_attr(not(debug_assertions), inline(always))]
#[cfg_attr(debug_assertions, inline(never))]
fn se3_block<const N: usize, const L: usize>(
    sys: &Se3Newton<'_, N>,
    buf: &mut [LaneRow],
    t: f64,
    mu: &mut [[f64; N]],
    live: &[bool],
    results: &mut [StepResult],
) {
    let n = mu.len();
    debug_assert!(N == 6 && n <= L);
    let (mut pl, active) = load_block::<N, L>(mu, live);
    let target: V6<L> = from_fn(|i| V(pl[i]));
    let mut p = target;
    let net = sys.network.as_ref();
    let mut scratch = Scratch::<N, L>::new();
    let mut jet = JetLanes {
        v: [0.0; L],
        g: [[0.0; L]; N],
        h: [[[0.0; L]; N]; N],
    };
    if sys.predict {
        // tar(x, p) = p − ½ (ω×p_R + v×p_T, ω×p_T) + O(|x|²), so p₀ = μ + ½ (ω₀×M + v₀×Γ,
        // ω₀×Γ) is O(h²) from the solution where μ is O(h) (the groupoid's `predict`).
        jet_lanes_into::<N, L, false, 1>(sys.poly, t, &pl, &mut scratch, &mut jet);
        let x0: V6<L> = from_fn(|i| V(jet.g[i]));
        let (w, v) = ([x0[0], x0[1], x0[2]], [x0[3], x0[4], x0[5]]);
        let (m, g) = (
            [target[0], target[1], target[2]],
            [target[3], target[4], target[5]],
        );
        let (wm, vg, wg) = (cross(&w, &m), cross(&v, &g), cross(&w, &g));
        let p0: V6<L> = from_fn(|i| {
            let turn = if i < 3 { wm[i] + vg[i] } else { wg[i - 3] };
            target[i] + turn.scale(0.5)
        });
        let s0 = x0.iter().fold(V::splat(0.0), |a, v| a + *v * *v);
        let probe = finite_probe(p0);
        let near: [bool; L] = from_fn(|l| s0.0[l] <= PREDICT_MAX_S && probe.0[l] == 0.0);
        for i in 0..6 {
            p[i] = p[i].blend(&near, p0[i]);
        }
        {
            // Second order: one fixed-point step p ← p + μ − tar(x, p) with x the gradient of
            // S's t¹ and t² terms at p₀ (no network, no t³ … terms; on g* the Taylor S has no
            // t² term) leaves an O(h³) error: 3.67 → 3.00 updates a step on the heavy top
            // (`benches/newton_predictors.py`), 0.82× its step's time. Kept where p₀ was,
            // |ω|² ≤ PREDICT_MAX_S and the new start is finite. Not on so(3): there it saved
            // an update (2.97 → 2.00) but cost more than the cheap 3×3 update it saved
            // (1.05–1.35× the step's time, measured).
            for i in 0..N {
                pl[i] = p[i].0;
            }
            jet_lanes_into::<N, L, false, 2>(sys.poly, t, &pl, &mut scratch, &mut jet);
            let xa: V6<L> = from_fn(|i| V(jet.g[i]));
            let mut unused: M6<L> = [[V::splat(0.0); 6]; 6];
            let (tar, sa) = se3_tar_lanes(&xa, &p, None, &mut unused);
            let p1: V6<L> = from_fn(|i| p[i] + (target[i] - tar[i]));
            let probe = finite_probe(p1);
            let keep: [bool; L] =
                from_fn(|l| near[l] && sa.0[l] <= PREDICT_MAX_S && probe.0[l] == 0.0);
            for i in 0..6 {
                p[i] = p[i].blend(&keep, p1[i]);
            }
        }
    }
    let mut progress = Progress::new(active);
    // The kept inverse per lane, and this round's Hessian, Jacobian and inverse.
    let mut inv: M6<L> = [[V::splat(0.0); 6]; 6];
    let (mut h, mut jac, mut fresh) = (inv, inv, inv);
    // x = ∇S at each converged lane's p from its last update, x + Hess S · δ with the Hessian
    // of the lane's last refresh (as on so(3): off by far less than a rounding at
    // |δ| ≤ tol·|p|, and the gradient pass at the solution saved).
    let mut xs: V6<L> = [V::splat(0.0); 6];
    let max_s = EXP_CHART_MAX_ANGLE * EXP_CHART_MAX_ANGLE;
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
        for i in 0..6 {
            x[i] = V(jet.g[i]);
        }
        if hess {
            // Only the refreshing lanes take the new Hessian: `h` is each lane's Hessian of its
            // own last refresh (the others' Jacobians this round are not used), which the
            // first-order x at the solution needs (another lane's refresh must not change a
            // lane's bits).
            let mut take = [false; L];
            for l in 0..L {
                take[l] = progress.active[l] && progress.refresh[l];
            }
            for a in 0..6 {
                for b in 0..6 {
                    h[a][b] = h[a][b].blend(&take, V(jet.h[a.min(b)][a.max(b)]));
                }
            }
        }
        let (tar, s) = se3_tar_lanes(&x, &p, hess.then_some(&h), &mut jac);
        let ok = if hess {
            inverse_lanes(&jac, &mut fresh)
        } else {
            [false; L]
        };
        let (probe, hess_probe) = round_probes(&jet.v, &x, &h, hess);
        let mut go = [false; L];
        // The lanes whose fresh inverse is taken this round.
        let mut take = [false; L];
        for l in 0..L {
            if !progress.active[l] {
                continue;
            }
            let refresh = progress.refresh[l];
            let finite = probe.0[l] == 0.0 && (!refresh || hess_probe.0[l] == 0.0);
            let failure = if !finite {
                Some(StepFailure::NonFinite)
            } else if s.0[l] >= max_s {
                Some(StepFailure::ChartSingular)
            } else if progress.iterations[l] >= sys.max_iter {
                Some(StepFailure::NotConverged)
            } else if refresh {
                if ok[l] {
                    take[l] = true;
                    None
                } else {
                    Some(StepFailure::SingularJacobian)
                }
            } else {
                None
            };
            progress.settle(l, failure, &mut go, results);
        }
        if take.contains(&true) {
            for r in 0..6 {
                for c in 0..6 {
                    inv[r][c] = inv[r][c].blend(&take, fresh[r][c]);
                }
            }
        }
        // δ = J⁻¹ (μ − tar), each component summed in column order.
        let mut f = tar;
        for i in 0..6 {
            f[i] = target[i] - tar[i];
        }
        let mut delta = f;
        for r in 0..6 {
            let mut acc = inv[r][0] * f[0];
            for c in 1..6 {
                acc = acc + inv[r][c] * f[c];
            }
            delta[r] = acc;
        }
        progress.update(&go, &mut p, &delta, sys.tol, results);
        let mut newly = [false; L];
        for l in 0..L {
            newly[l] = go[l] && progress.converged[l];
        }
        if newly.contains(&true) {
            for a in 0..6 {
                let mut acc = x[a];
                for b in 0..6 {
                    acc = acc + h[a][b] * delta[b];
                }
                for l in 0..L {
                    xs[a].0[l] = if newly[l] { acc.0[l] } else { xs[a].0[l] };
                }
            }
        }
    }
    if !progress.converged.iter().any(|&c| c) {
        return;
    }
    // μ' = g(x)·μ with x = ∇S(p) at the converged p (sou(x, p) up to Newton's residual, which
    // the coadjoint action leaves out); the residual of the solved equation into the stats.
    let x = xs;
    let (tar, s) = se3_tar_lanes(&x, &p, None, &mut jac);
    for l in (0..n).filter(|&l| progress.converged[l]) {
        let xl: [f64; 6] = from_fn(|i| x[i].0[l]);
        let ml: [f64; 6] = from_fn(|i| target[i].0[l]);
        results[l] = if !xl.iter().all(|v| v.is_finite()) {
            Err(StepFailure::NonFinite)
        } else if s.0[l] >= max_s {
            Err(StepFailure::ChartSingular)
        } else {
            se3_coadjoint(&xl, &ml).map(|next| {
                mu[l][..6].copy_from_slice(&next);
                StepStats {
                    iterations: progress.iterations[l],
                    residual: (0..6).fold(0.0f64, |m, i| m.max((tar[i].0[l] - ml[i]).abs())),
                }
            })
        };
    }
}

impl<const N: usize> LaneSolve<N> for Se3Newton<'_, N> {
    #[inline(always)]
    fn block<const L: usize>(
        &self,
        buf: &mut [LaneRow],
        t: f64,
        mu: &mut [[f64; N]],
        live: &[bool],
        results: &mut [StepResult],
    ) {
        se3_block::<N, L>(self, buf, t, mu, live, results);
    }
}

/// One simplified-Newton bisection step of every `mu[j]` with `live[j]` on se(3)'s exponential
/// chart (N must be 6): [`lane_newton_steps`] of [`Se3Newton`].
pub(crate) fn se3_newton_steps<const N: usize>(
    sys: &Se3Newton<'_, N>,
    isa: Isa,
    buf: &mut [LaneRow],
    t: f64,
    mu: &mut [[f64; N]],
    live: &[bool],
    results: &mut [StepResult],
) {
    assert!(N == 6, "se(3) lanes need N = 6");
    lane_newton_steps(sys, isa, buf, t, mu, live, results);
}

//! The Newton solve of S in SIMD lanes on the exponential chart of any Lie algebra, by its
//! Bernoulli series: the Taylor-HJ (or learned) bisection step on g* for every algebra without a
//! closed-form chart (so(3) and se(3) have theirs: [`crate::lanes_bisection`],
//! [`crate::lanes_bisection_se3`]), among them the central extensions that carry the affine
//! brackets. A block of trajectories in lockstep, each lane bit-identical to the one-lane solve
//! (the one-trajectory step):
//!
//! - tar(x, p) = Σ (Bₙ/n!) (−A)ⁿ p with A = ad_xᵀ, in lanes; each lane stops where the groupoid's
//!   scalar series stops (two consecutive non-zero terms below 1e-17 of the sum), judged on the
//!   values, so a lane's term count is its own whatever the block and whether the Jacobian is
//!   wanted;
//! - its exact p-Jacobian J = ∂tar/∂p + ∂tar/∂x · Hess S in forward mode (N tangents a lane: x
//!   carries the Hessian's rows, p the identity), summed to the values' term count;
//! - J⁻¹ by Gauss–Jordan with partial pivoting lane by lane ([`inverse_lanes`]);
//! - Newton started from p₀ = μ − ½ A(x₀) μ (x₀: the gradient of S's terms linear in t), the
//!   groupoid's first-order predictor, and one fixed-point step from there (as on se(3));
//! - the new state e^{−A(x)} μ in lanes ([`LieAlgebra::exp_coadjoint`]'s rule, each lane its own
//!   term count), on μ's coadjoint orbit whatever Newton's residual.

// Index loops over lanes, coordinates and matrix entries read as the formulas they evaluate.
#![allow(clippy::needless_range_loop)]

use std::array::from_fn;
use std::ops::{Add, Mul};

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
    bernoulli_over_factorial, LieAlgebra, COADJOINT_TAIL, MAX_SERIES_TERMS,
};

/// What the series is summed on: lane values ([`V`]) or lane values with their derivatives
/// along the N p-directions ([`D`]).
trait Lane<const L: usize>: Copy + Add<Output = Self> + Mul<Output = Self> {
    fn zero() -> Self;
    fn value(&self) -> V<L>;
    fn times(self, c: f64) -> Self;
    fn blend(self, take: &[bool; L], a: Self) -> Self;
}

impl<const L: usize> Lane<L> for V<L> {
    #[inline(always)]
    fn zero() -> Self {
        V::splat(0.0)
    }
    #[inline(always)]
    fn value(&self) -> V<L> {
        *self
    }
    #[inline(always)]
    fn times(self, c: f64) -> Self {
        self.scale(c)
    }
    #[inline(always)]
    fn blend(self, take: &[bool; L], a: Self) -> Self {
        V::blend(self, take, a)
    }
}

impl<const L: usize, const K: usize> Lane<L> for D<L, K> {
    #[inline(always)]
    fn zero() -> Self {
        D::constant(V::splat(0.0))
    }
    #[inline(always)]
    fn value(&self) -> V<L> {
        self.v
    }
    #[inline(always)]
    fn times(self, c: f64) -> Self {
        D::times(self, c)
    }
    #[inline(always)]
    fn blend(self, take: &[bool; L], a: Self) -> Self {
        D::blend(self, take, a)
    }
}

/// A = ad_xᵀ, A[j][k] = Σ_i c[i][j][k] x_i (zero constants skipped), and which entries the
/// constants leave structurally zero (`false`: skipped by [`apply`]).
#[inline(always)]
fn ad_transpose<const N: usize, const L: usize, T: Lane<L>>(
    c: &[[[f64; N]; N]; N],
    x: &[T; N],
) -> ([[T; N]; N], [[bool; N]; N]) {
    let mut a = [[T::zero(); N]; N];
    let mut used = [[false; N]; N];
    for i in 0..N {
        for j in 0..N {
            for k in 0..N {
                let cijk = c[i][j][k];
                if cijk != 0.0 {
                    a[j][k] = a[j][k] + x[i].times(cijk);
                    used[j][k] = true;
                }
            }
        }
    }
    (a, used)
}

/// A v over A's structurally non-zero entries, each component summed in column order. (Loops,
/// not `array::from_fn`: its closures over lane vectors were left out of line, and their
/// results copied through memory.)
#[inline(always)]
fn apply<const N: usize, const L: usize, T: Lane<L>>(
    a: &[[T; N]; N],
    used: &[[bool; N]; N],
    v: &[T; N],
) -> [T; N] {
    let mut out = [T::zero(); N];
    for j in 0..N {
        let mut s = T::zero();
        for k in 0..N {
            if used[j][k] {
                s = s + a[j][k] * v[k];
            }
        }
        out[j] = s;
    }
    out
}

/// max_i |v_i| lane by lane, on the values.
#[inline(always)]
fn size<const N: usize, const L: usize, T: Lane<L>>(v: &[T; N]) -> V<L> {
    v.iter().fold(V::splat(0.0), |m, t| m.max(t.value().abs()))
}

/// tar(x, p) = Σ (Bₙ/n!) (−A)ⁿ p, A = ad_xᵀ, on the lanes in `live` (the others are left at
/// p), and per lane why it has none: NonFinite where a term is not finite (a NaN too, which the
/// scalar series' sizes skip), ChartSingular where
/// [`MAX_SERIES_TERMS`] terms do not reach round-off (the chart's singular angle, or beyond).
/// Each lane sums until two consecutive non-zero terms are at most 1e-17 of its sum (values).
#[inline(always)]
fn tar_series<const N: usize, const L: usize, T: Lane<L>>(
    c: &[[[f64; N]; N]; N],
    x: &[T; N],
    p: &[T; N],
    live: &[bool; L],
) -> ([T; N], [Option<StepFailure>; L]) {
    let b = bernoulli_over_factorial();
    let (a, used) = ad_transpose(c, x);
    let mut term = *p;
    let mut out = *p;
    let mut running = *live;
    let mut small = [0u8; L];
    let mut failed = [None; L];
    for (n, &bn) in b.iter().enumerate().skip(1) {
        if !running.contains(&true) {
            break;
        }
        term = apply(&a, &used, &term);
        if bn == 0.0 {
            continue;
        }
        // The target map's sign: (−A)ⁿ is −Aⁿ for odd n.
        let coef = if n % 2 == 1 { -bn } else { bn };
        for i in 0..N {
            out[i] = out[i].blend(&running, out[i] + term[i].times(coef));
        }
        let (t, o) = (size(&term), size(&out));
        let probe = finite_probe(term.iter().map(|v| v.value()));
        for l in 0..L {
            if !running[l] {
                continue;
            }
            let t = t.0[l] * bn.abs();
            if !t.is_finite() || probe.0[l] != 0.0 {
                failed[l] = Some(StepFailure::NonFinite);
                running[l] = false;
            } else if t <= 1e-17 * o.0[l] {
                small[l] += 1;
                running[l] = small[l] < 2;
            } else {
                small[l] = 0;
            }
        }
    }
    for l in 0..L {
        if running[l] {
            failed[l] = Some(StepFailure::ChartSingular);
        }
    }
    (out, failed)
}

/// tar(x, p) on the lanes in `live`, and with `hess` (S's Hessian, symmetric) also its exact
/// p-Jacobian into `jac` (left alone without it), J[r][k] = ∂tar_r/∂p_k; per lane the failure
/// of [`tar_series`].
#[inline(always)]
pub(crate) fn series_tar_lanes<const N: usize, const L: usize>(
    algebra: &LieAlgebra<N>,
    x: &[V<L>; N],
    p: &[V<L>; N],
    hess: Option<&[[V<L>; N]; N]>,
    jac: &mut [[V<L>; N]; N],
    live: &[bool; L],
) -> ([V<L>; N], [Option<StepFailure>; L]) {
    let c = algebra.structure_constants();
    let Some(h) = hess else {
        return tar_series(c, x, p, live);
    };
    // ∂x_i/∂p_k = Hess S[i][k]; ∂p_i/∂p_k = δ_ik.
    let mut xd = [D::constant(V::splat(0.0)); N];
    let mut pd = xd;
    for i in 0..N {
        xd[i] = D { v: x[i], d: h[i] };
        pd[i] = D::constant(p[i]);
        pd[i].d[i] = V::splat(1.0);
    }
    let (t, failed) = tar_series(c, &xd, &pd, live);
    let mut value = *p;
    for r in 0..N {
        jac[r] = t[r].d;
        value[r] = t[r].v;
    }
    (value, failed)
}

/// e^{−A} μ with A = ad_xᵀ on the lanes in `live`, the rule of [`LieAlgebra::exp_coadjoint`] in
/// lanes: each lane's term count K from its own ρ = ‖A‖∞ (the terms past K below
/// [`COADJOINT_TAIL`] · e^ρ), then Horner from the innermost term, w = μ − (A w)/n for
/// n = K … 2 (a lane whose K is below n keeps w = μ) and μ − A w. Per lane the failure, if any:
/// ChartSingular where K would pass [`MAX_SERIES_TERMS`], NonFinite where ρ or the result is
/// not finite.
#[inline(always)]
pub(crate) fn coadjoint_lanes<const N: usize, const L: usize>(
    c: &[[[f64; N]; N]; N],
    x: &[V<L>; N],
    mu: &[V<L>; N],
    live: &[bool; L],
) -> ([V<L>; N], [Option<StepFailure>; L]) {
    let (a, used) = ad_transpose(c, x);
    let mut rho = V::splat(0.0);
    for j in 0..N {
        let mut row = V::splat(0.0);
        for k in 0..N {
            if used[j][k] {
                row = row + a[j][k].abs();
            }
        }
        rho = rho.max(row);
    }
    let mut failed = [None; L];
    let mut terms = [0usize; L];
    let mut most = 0;
    for l in 0..L {
        if !live[l] {
            continue;
        }
        let r = rho.0[l];
        if !r.is_finite() {
            failed[l] = Some(StepFailure::NonFinite);
            continue;
        }
        let (mut k, mut bound) = (0, 1.0f64);
        while bound > COADJOINT_TAIL && k <= MAX_SERIES_TERMS {
            k += 1;
            bound *= r / k as f64;
        }
        if k > MAX_SERIES_TERMS {
            failed[l] = Some(StepFailure::ChartSingular);
        } else {
            terms[l] = k;
            most = most.max(k);
        }
    }
    let mut w = *mu;
    for n in (2..=most).rev() {
        let inner: [bool; L] = from_fn(|l| n <= terms[l]);
        let aw = apply(&a, &used, &w);
        let nf = V::splat(n as f64);
        for i in 0..N {
            w[i] = w[i].blend(&inner, mu[i] - aw[i].zip(nf, |a, b| a / b));
        }
    }
    let aw = apply(&a, &used, &w);
    let mut out = *mu;
    for i in 0..N {
        out[i] = mu[i] - aw[i];
    }
    let probe = finite_probe(out);
    for l in 0..L {
        if live[l] && failed[l].is_none() && probe.0[l] != 0.0 {
            failed[l] = Some(StepFailure::NonFinite);
        }
    }
    (out, failed)
}

/// What the lane Newton solve of S on a Lie algebra's exponential chart needs: S's polynomial
/// part and network term if it has one, the algebra, and the simplified-Newton settings.
pub(crate) struct SeriesNewton<'a, const N: usize> {
    pub poly: &'a Polynomial<N>,
    pub network: Option<NetworkLanes<'a>>,
    pub algebra: &'a LieAlgebra<N>,
    pub tol: f64,
    pub max_iter: u32,
    /// Start Newton from p₀ = μ − ½ A(x₀) μ (x₀: the t-linear terms' gradient at μ) and one
    /// fixed-point step from there instead of μ, where |x₀|² ≤ [`PREDICT_MAX_S`] and p₀ is
    /// finite.
    pub predict: bool,
}

/// One step of at most L trajectories (`mu.len()` ≤ L; those with `live` false are left alone)
/// by simplified Newton in lanes: the rule of the generic one-trajectory step (refresh the
/// Jacobian while updates contract by less than
/// [`SIMPLIFIED_RATE`](crate::step::SIMPLIFIED_RATE), stop once
/// |δ|∞ ≤ tol · max(|p|∞, 1e-300)), lane by lane. A lane that converged or failed is frozen; the
/// block runs until every lane has.
// Out of line in debug builds: inlined there, every local of every instantiation keeps its
// own slot in the dispatching frames, and a test thread's stack overflowed.
#[cfg_attr(not(debug_assertions), inline(always))]
#[cfg_attr(debug_assertions, inline(never))]
fn series_block<const N: usize, const L: usize>(
    sys: &SeriesNewton<'_, N>,
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
    let c = sys.algebra.structure_constants();
    let mut scratch = Scratch::<N, L>::new();
    let mut jet = JetLanes {
        v: [0.0; L],
        g: [[0.0; L]; N],
        h: [[[0.0; L]; N]; N],
    };
    if sys.predict {
        // tar(x, p) = p + ½ A p + O(|x|²), so p₀ = μ − ½ A(x₀) μ is O(h²) from the solution
        // where μ is O(h) away (the groupoid's `predict`).
        jet_lanes_into::<N, L, false, 1>(sys.poly, t, &pl, &mut scratch, &mut jet);
        let x0: [V<L>; N] = from_fn(|i| V(jet.g[i]));
        let (a, used) = ad_transpose(c, &x0);
        let turn = apply(&a, &used, &target);
        let p0: [V<L>; N] = from_fn(|i| target[i] - turn[i].scale(0.5));
        let s0 = x0.iter().fold(V::splat(0.0), |a, v| a + *v * *v);
        let probe = finite_probe(p0);
        let near: [bool; L] = from_fn(|l| s0.0[l] <= PREDICT_MAX_S && probe.0[l] == 0.0);
        for i in 0..N {
            p[i] = p[i].blend(&near, p0[i]);
        }
        // Second order, as on se(3): one fixed-point step p ← p + μ − tar(x, p) with x the
        // gradient of S's t¹ and t² terms at p₀ leaves an O(h³) error. Kept where p₀ was, |x|²
        // ≤ PREDICT_MAX_S, the series summed and the new start is finite.
        for i in 0..N {
            pl[i] = p[i].0;
        }
        jet_lanes_into::<N, L, false, 2>(sys.poly, t, &pl, &mut scratch, &mut jet);
        let xa: [V<L>; N] = from_fn(|i| V(jet.g[i]));
        let sa = xa.iter().fold(V::splat(0.0), |a, v| a + *v * *v);
        let (tar, chart) = tar_series(c, &xa, &p, &near);
        let p1: [V<L>; N] = from_fn(|i| p[i] + (target[i] - tar[i]));
        let probe = finite_probe(p1);
        let keep: [bool; L] = from_fn(|l| {
            near[l] && sa.0[l] <= PREDICT_MAX_S && chart[l].is_none() && probe.0[l] == 0.0
        });
        for i in 0..N {
            p[i] = p[i].blend(&keep, p1[i]);
        }
    }
    let mut progress = Progress::new(active);
    // The kept inverse per lane, and this round's Hessian, Jacobian and inverse.
    let zero = [[V::splat(0.0); N]; N];
    let (mut inv, mut h, mut jac, mut fresh) = (zero, zero, zero, zero);
    // x = ∇S at each converged lane's p from its last update, x + Hess S · δ with the Hessian
    // of the lane's last refresh (as on so(3) and se(3)).
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
            // Only the refreshing lanes take the new Hessian (another lane's refresh must not
            // change a lane's bits).
            let take: [bool; L] = from_fn(|l| progress.active[l] && progress.refresh[l]);
            for a in 0..N {
                for b in 0..N {
                    h[a][b] = h[a][b].blend(&take, V(jet.h[a.min(b)][a.max(b)]));
                }
            }
        }
        let (tar, chart) = series_tar_lanes(
            sys.algebra,
            &x,
            &p,
            hess.then_some(&h),
            &mut jac,
            &progress.active,
        );
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
            } else if chart[l].is_some() {
                chart[l]
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
    let (tar, chart) = series_tar_lanes(sys.algebra, &x, &p, None, &mut jac, &done);
    let (next, moved) = coadjoint_lanes(c, &x, &target, &done);
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

impl<const N: usize> LaneSolve<N> for SeriesNewton<'_, N> {
    #[inline(always)]
    fn block<const L: usize>(
        &self,
        buf: &mut [LaneRow],
        t: f64,
        mu: &mut [[f64; N]],
        live: &[bool],
        results: &mut [StepResult],
    ) {
        series_block::<N, L>(self, buf, t, mu, live, results);
    }
}

/// One simplified-Newton bisection step of every `mu[j]` with `live[j]` on the exponential chart
/// of `sys.algebra` by its series: [`lane_newton_steps`] of [`SeriesNewton`].
pub(crate) fn series_newton_steps<const N: usize>(
    sys: &SeriesNewton<'_, N>,
    isa: Isa,
    buf: &mut [LaneRow],
    t: f64,
    mu: &mut [[f64; N]],
    live: &[bool],
    results: &mut [StepResult],
) {
    lane_newton_steps(sys, isa, buf, t, mu, live, results);
}

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
//! - A(x) q = ad_xᵀ q in lanes, for Newton's second-order start;
//! - the new state e^{−A(x)} μ in lanes ([`LieAlgebra::exp_coadjoint`]'s rule, each lane its own
//!   term count), on μ's coadjoint orbit whatever Newton's residual.
//!
//! The Newton solve around it is [`crate::lanes_bisection_exp`]'s, shared with se(3)'s closed
//! form.

// Index loops over lanes, coordinates and matrix entries read as the formulas they evaluate.
#![allow(clippy::needless_range_loop)]

use std::array::from_fn;
use std::ops::{Add, Mul};

use crate::error::StepFailure;
use crate::lanes_bisection::ChartNewton;
use crate::lanes_bisection::{finite_probe, D, V};
use crate::lanes_bisection_exp::ExpChartLanes;
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
        // Every lane still summing (the rule until the first one stops): no blend.
        if running.contains(&false) {
            for i in 0..N {
                out[i] = out[i].blend(&running, out[i] + term[i].times(coef));
            }
        } else {
            for i in 0..N {
                out[i] = out[i] + term[i].times(coef);
            }
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

/// A Lie algebra's exponential chart by its series, for [`ChartNewton`]'s solve.
pub(crate) struct SeriesChart<'a, const N: usize> {
    pub algebra: &'a LieAlgebra<N>,
}

/// The lane Newton solve of S on a Lie algebra's exponential chart by its series: S's
/// polynomial part and network term if it has one, the algebra, and the simplified-Newton
/// settings.
pub(crate) type SeriesNewton<'a, const N: usize> = ChartNewton<'a, N, SeriesChart<'a, N>>;

impl<const N: usize> ExpChartLanes<N> for SeriesChart<'_, N> {
    /// Up to four coordinates: the affine system's central extension (N = 4) took 0.88× / 0.91×
    /// its AVX2 time at Taylor K = 3 / 5 (`benches/step_costs.py --system affine`, the same
    /// build otherwise). At N ≥ 5 the lane solves lost (see [`crate::isa::AVX512_MAX_DIM`]).
    const AVX512: bool = N <= 4;

    #[inline(always)]
    fn turn<const L: usize>(&self, x: &[V<L>; N], q: &[V<L>; N]) -> [V<L>; N] {
        let (a, used) = ad_transpose(self.algebra.structure_constants(), x);
        apply(&a, &used, q)
    }

    /// [`series_tar_lanes`]; the size is |x|².
    // Out of line in debug builds, as the block is (a debug frame keeps every local).
    #[cfg_attr(not(debug_assertions), inline(always))]
    #[cfg_attr(debug_assertions, inline(never))]
    fn tar<const L: usize>(
        &self,
        x: &[V<L>; N],
        p: &[V<L>; N],
        hess: Option<&[[V<L>; N]; N]>,
        jac: &mut [[V<L>; N]; N],
        live: &[bool; L],
    ) -> ([V<L>; N], [Option<StepFailure>; L], V<L>) {
        let (value, failed) = series_tar_lanes(self.algebra, x, p, hess, jac, live);
        let size = x.iter().fold(V::splat(0.0), |a, v| a + *v * *v);
        (value, failed, size)
    }

    /// [`coadjoint_lanes`].
    // Out of line in debug builds, as the block is (a debug frame keeps every local).
    #[cfg_attr(not(debug_assertions), inline(always))]
    #[cfg_attr(debug_assertions, inline(never))]
    fn coadjoint<const L: usize>(
        &self,
        x: &[V<L>; N],
        mu: &[V<L>; N],
        live: &[bool; L],
    ) -> ([V<L>; N], [Option<StepFailure>; L]) {
        coadjoint_lanes(self.algebra.structure_constants(), x, mu, live)
    }
}

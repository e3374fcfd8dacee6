//! The se(3) Newton solve of a polynomial S in SIMD lanes: the heavy top's Taylor-HJ bisection
//! step for a block of trajectories in lockstep, each lane bit-identical to the one-trajectory
//! step. What [`crate::lanes_bisection`] does on so(3), on se(3)'s exponential chart in closed
//! form (the groupoid's `se3_chart`):
//!
//! - tar(x, p) in lanes with the scalar chart's operations, so its values are the scalar chart's
//!   bits; its exact p-Jacobian J = ∂T/∂p + ∂T/∂x · Hess S in forward mode, six tangents per
//!   lane (x carries the Hessian's rows, p the identity);
//! - A(x) q = ad_xᵀ q in closed form, for Newton's second-order start;
//! - the new state g(x)·μ by the closed-form coadjoint action (`se3_coadjoint`), lane by lane.
//!
//! The Newton solve around it is [`crate::lanes_bisection_exp`]'s, shared with every other
//! algebra's chart.

// Index loops over lanes, coordinates and matrix entries read as the formulas they evaluate.
#![allow(clippy::needless_range_loop)]

use std::array::from_fn;
use std::ops::{Add, Mul, Sub};

use crate::error::StepFailure;
use crate::lanes_bisection::ChartNewton;
use crate::lanes_bisection::{D, V};
use crate::lanes_bisection_exp::ExpChartLanes;
use crate::structures::lie_groupoid::{
    exp_chart_coefficient_derivatives_to, exp_chart_coefficient_to, se3_coadjoint, C_SERIES,
    EXP_CHART_MAX_ANGLE,
};

type V6<const L: usize> = [V<L>; 6];

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
/// J[r][k] = ∂tar_r/∂p_k (left alone without it). N must be 6 (generic so that the lane solver
/// passes its arrays as they are, without copies).
#[inline(always)]
pub(crate) fn se3_tar_lanes<const N: usize, const L: usize>(
    x: &[V<L>; N],
    p: &[V<L>; N],
    hess: Option<&[[V<L>; N]; N]>,
    jac: &mut [[V<L>; N]; N],
) -> ([V<L>; N], V<L>) {
    debug_assert!(N == 6);
    let x6: V6<L> = [x[0], x[1], x[2], x[3], x[4], x[5]];
    let p6: V6<L> = [p[0], p[1], p[2], p[3], p[4], p[5]];
    let w = [x[0], x[1], x[2]];
    let s = dot(&w, &w);
    let (c, c1, c2) = chart_coefficients(s, hess.is_some());
    let mut value = *p;
    let Some(h) = hess else {
        value[..6].copy_from_slice(&tar(&x6, &p6, c, c1));
        return (value, s);
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
        for k in 0..6 {
            xd[i].d[k] = h[i][k];
        }
        pd[i].v = p[i];
        pd[i].d[i] = one;
    }
    let wd = [xd[0], xd[1], xd[2]];
    let sd = dot(&wd, &wd);
    let t = tar(&xd, &pd, D::chain(&sd, c, c1), D::chain(&sd, c1, c2));
    for r in 0..6 {
        value[r] = t[r].v;
        jac[r][..6].copy_from_slice(&t[r].d);
    }
    (value, s)
}

/// se(3)'s exponential chart in closed form, for [`ChartNewton`]'s solve (N must be 6).
pub(crate) struct Se3Chart;

/// The lane Newton solve of S on se(3): S's polynomial part (N = 6) and network term if it has
/// one, and the simplified-Newton settings.
pub(crate) type Se3Newton<'a, const N: usize> = ChartNewton<'a, N, Se3Chart>;

impl<const N: usize> ExpChartLanes<N> for Se3Chart {
    /// A(x) q = ad_xᵀ q = −(ω×q_R + v×q_T, ω×q_T) on se(3)*.
    #[inline(always)]
    fn turn<const L: usize>(&self, x: &[V<L>; N], q: &[V<L>; N]) -> [V<L>; N] {
        let (w, v) = ([x[0], x[1], x[2]], [x[3], x[4], x[5]]);
        let (qr, qt) = ([q[0], q[1], q[2]], [q[3], q[4], q[5]]);
        let (wr, vt, wt) = (cross(&w, &qr), cross(&v, &qt), cross(&w, &qt));
        let mut out = *q;
        for i in 0..3 {
            out[i] = V::splat(0.0) - (wr[i] + vt[i]);
            out[3 + i] = V::splat(0.0) - wt[i];
        }
        out
    }

    /// [`se3_tar_lanes`] on every lane; ChartSingular where |ω|² reaches the chart's singular
    /// angle; the size is |ω|².
    // Out of line in debug builds, as the block is (a debug frame keeps every local).
    #[cfg_attr(not(debug_assertions), inline(always))]
    #[cfg_attr(debug_assertions, inline(never))]
    fn tar<const L: usize>(
        &self,
        x: &[V<L>; N],
        p: &[V<L>; N],
        hess: Option<&[[V<L>; N]; N]>,
        jac: &mut [[V<L>; N]; N],
        _live: &[bool; L],
    ) -> ([V<L>; N], [Option<StepFailure>; L], V<L>) {
        let (value, s) = se3_tar_lanes(x, p, hess, jac);
        let max_s = EXP_CHART_MAX_ANGLE * EXP_CHART_MAX_ANGLE;
        let mut failed = [None; L];
        for l in 0..L {
            if s.0[l] >= max_s {
                failed[l] = Some(StepFailure::ChartSingular);
            }
        }
        (value, failed, s)
    }

    /// The closed-form coadjoint action ([`se3_coadjoint`]), lane by lane.
    // Out of line in debug builds, as the block is (a debug frame keeps every local).
    #[cfg_attr(not(debug_assertions), inline(always))]
    #[cfg_attr(debug_assertions, inline(never))]
    fn coadjoint<const L: usize>(
        &self,
        x: &[V<L>; N],
        mu: &[V<L>; N],
        live: &[bool; L],
    ) -> ([V<L>; N], [Option<StepFailure>; L]) {
        let mut out = *mu;
        let mut failed = [None; L];
        for l in (0..L).filter(|&l| live[l]) {
            let xl: [f64; 6] = from_fn(|i| x[i].0[l]);
            let ml: [f64; 6] = from_fn(|i| mu[i].0[l]);
            match se3_coadjoint(&xl, &ml) {
                Ok(next) => {
                    for i in 0..6 {
                        out[i].0[l] = next[i];
                    }
                }
                Err(e) => failed[l] = Some(e),
            }
        }
        (out, failed)
    }
}

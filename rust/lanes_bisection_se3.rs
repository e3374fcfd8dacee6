//! The se(3) Newton solve of a polynomial S in SIMD lanes: the heavy top's Taylor-HJ bisection
//! step for a block of trajectories in lockstep, each lane bit-identical to the one-trajectory
//! step. What [`crate::lanes_bisection`] does on so(3), on se(3)'s exponential chart in closed
//! form (the groupoid's `se3_chart`):
//!
//! - tar(x, p) in lanes with the scalar chart's operations, so its values are the scalar chart's
//!   bits; its exact p-Jacobian J = ∂T/∂p + ∂T/∂x · Hess S from both derivatives in closed
//!   3×3 blocks (`tar_derivatives`);
//! - A(x) q = ad_xᵀ q in closed form, for Newton's second-order start;
//! - the new state g(x)·μ by the closed-form coadjoint action (`se3_coadjoint`), lane by lane.
//!
//! The Newton solve around it is [`crate::lanes_bisection_exp`]'s, shared with every other
//! algebra's chart.

// Index loops over lanes, coordinates and matrix entries read as the formulas they evaluate.
#![allow(clippy::needless_range_loop)]

use std::array::from_fn;

use crate::error::StepFailure;
use crate::lanes_bisection::ChartNewton;
use crate::lanes_bisection::V;
use crate::lanes_bisection_exp::ExpChartLanes;
use crate::structures::lie_groupoid::{
    exp_chart_coefficient_derivatives_to, exp_chart_coefficient_to, se3_coadjoint, C_SERIES,
    EXP_CHART_MAX_ANGLE,
};

type V6<const L: usize> = [V<L>; 6];

/// The same products in the same order as the groupoid's `cross`.
#[inline(always)]
fn cross<const L: usize>(a: &[V<L>; 3], b: &[V<L>; 3]) -> [V<L>; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[inline(always)]
fn dot<const L: usize>(a: &[V<L>; 3], b: &[V<L>; 3]) -> V<L> {
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
fn tar<const L: usize>(x: &V6<L>, p: &V6<L>, c: V<L>, c1: V<L>) -> V6<L> {
    let w = [x[0], x[1], x[2]];
    let v = [x[3], x[4], x[5]];
    let pr = [p[0], p[1], p[2]];
    let pt = [p[3], p[4], p[5]];
    let half = -0.5;
    let (wpr, wpt, vpt) = (cross(&w, &pr), cross(&w, &pt), cross(&v, &pt));
    let (wwpr, wwpt) = (cross(&w, &wpr), cross(&w, &wpt));
    let (vwpt, wvpt) = (cross(&v, &wpt), cross(&w, &vpt));
    let k = dot(&w, &v).scale(2.0) * c1;
    let mut out = *p;
    for i in 0..3 {
        let d = vpt[i].scale(half) + k * wwpt[i] + c * (vwpt[i] + wvpt[i]);
        out[i] = pr[i] + wpr[i].scale(half) + c * wwpr[i] + d;
        out[3 + i] = pt[i] + wpt[i].scale(half) + c * wwpt[i];
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
    value[..6].copy_from_slice(&tar(&x6, &p6, c, c1));
    let Some(h) = hess else {
        return (value, s);
    };
    let m = tar_derivatives(&x6, &p6, c, c1, c2);
    // J = B(x) + ∂ₓ tar · Hess S, with B(x) = ∂tar/∂p = [[B₀, B_RT], [0, B₀]] and
    // ∂ₓ tar = [[A_Rω, A_Rv], [A_Tω, 0]] (`tar_derivatives`), each sum in column order.
    for r in 0..6 {
        for k in 0..6 {
            let mut acc = m.b[r][k];
            for a in 0..6 {
                if r >= 3 && a >= 3 {
                    break;
                }
                acc = acc + m.a[r][a] * h[a][k];
            }
            jac[r][k] = acc;
        }
    }
    (value, s)
}

type M3<const L: usize> = [[V<L>; 3]; 3];

/// ∂tar/∂p (`b`) and ∂tar/∂x (`a`, its lower right block zero) of se(3)'s exponential chart at
/// (x, p), x = (ω, v), c, c₁, c₂ = c, c', c'' at s = |ω|². tar is linear in p,
///
///   tar_R = p_R − ½ ω×p_R + c ω×(ω×p_R) − ½ v×p_T + k ω×(ω×p_T) + c (v×(ω×p_T) + ω×(v×p_T)),
///   tar_T = p_T − ½ ω×p_T + c ω×(ω×p_T),   k = 2 (ω·v) c₁,
///
/// so ∂tar/∂p = [[B₀, B_RT], [0, B₀]] with B₀ = I − ½[ω]× + c[ω]×² and
/// B_RT = −½[v]× + k[ω]×² + c(ω vᵀ + v ωᵀ − 2(ω·v) I); with G(q) = ∂(ω×(ω×q))/∂ω =
/// (ω·q) I + ω qᵀ − 2 q ωᵀ, ∂c/∂ω = 2c₁ωᵀ, ∂k/∂ω = 2c₁vᵀ + 4(ω·v)c₂ωᵀ, ∂k/∂v = 2c₁ωᵀ:
///
///   A_Tω = ½[p_T]× + c G(p_T) + (ω×(ω×p_T)) 2c₁ωᵀ,
///   A_Rω = ½[p_R]× + c G(p_R) + k G(p_T) + u 2c₁ωᵀ + (ω×(ω×p_T)) ∂k/∂ω
///          − c (p_T vᵀ − (v·p_T) I) − c [v×p_T]×,   u = ω×(ω×p_R) + v×(ω×p_T) + ω×(v×p_T),
///   A_Rv = ½[p_T]× + (ω×(ω×p_T)) 2c₁ωᵀ − c [ω×p_T]× − c (p_T ωᵀ − (ω·p_T) I).
///
/// About half the operations of six forward-mode tangents through every cross product.
/// `tests/se3_lanes.rs` checks J against the dual-number derivative of the scalar chart.
#[inline(always)]
fn tar_derivatives<const L: usize>(
    x: &V6<L>,
    p: &V6<L>,
    c: V<L>,
    c1: V<L>,
    c2: V<L>,
) -> ChartDerivatives<L> {
    let zero = V::splat(0.0);
    let w = [x[0], x[1], x[2]];
    let v = [x[3], x[4], x[5]];
    let pr = [p[0], p[1], p[2]];
    let pt = [p[3], p[4], p[5]];
    let wv = dot(&w, &v);
    let k = wv.scale(2.0) * c1;
    let s = dot(&w, &w);
    let ww = square_skew(&w, s);
    let (wpr, wpt, vpt) = (cross(&w, &pr), cross(&w, &pt), cross(&v, &pt));
    let (wwpr, wwpt) = (cross(&w, &wpr), cross(&w, &wpt));
    let (vwpt, wvpt) = (cross(&v, &wpt), cross(&w, &vpt));
    let (wpr_dot, wpt_dot, vpt_dot) = (dot(&w, &pr), dot(&w, &pt), dot(&v, &pt));
    let c1w2 = [
        (w[0] * c1).scale(2.0),
        (w[1] * c1).scale(2.0),
        (w[2] * c1).scale(2.0),
    ];
    let dk_dw: [V<L>; 3] = {
        let f = wv * c2;
        let mut d = [zero; 3];
        for j in 0..3 {
            d[j] = (v[j] * c1).scale(2.0) + (f * w[j]).scale(4.0);
        }
        d
    };
    let mut out = ChartDerivatives {
        b: [[zero; 6]; 6],
        a: [[zero; 6]; 6],
    };
    for i in 0..3 {
        let u = wwpr[i] + vwpt[i] + wvpt[i];
        for j in 0..3 {
            let id = if i == j { V::splat(1.0) } else { zero };
            let half_w = skew_entry(&w, i, j).scale(0.5);
            let b0 = id - half_w + c * ww[i][j];
            out.b[i][j] = b0;
            out.b[3 + i][3 + j] = b0;
            let sym = w[i] * v[j] + v[i] * w[j] - id * wv.scale(2.0);
            out.b[i][3 + j] = ww[i][j] * k + c * sym - skew_entry(&v, i, j).scale(0.5);
            let g_pr = id * wpr_dot + w[i] * pr[j] - (pr[i] * w[j]).scale(2.0);
            let g_pt = id * wpt_dot + w[i] * pt[j] - (pt[i] * w[j]).scale(2.0);
            let half_pt = skew_entry(&pt, i, j).scale(0.5);
            out.a[3 + i][j] = half_pt + c * g_pt + wwpt[i] * c1w2[j];
            out.a[i][j] = skew_entry(&pr, i, j).scale(0.5)
                + c * g_pr
                + k * g_pt
                + u * c1w2[j]
                + wwpt[i] * dk_dw[j]
                - c * (pt[i] * v[j] - id * vpt_dot)
                - c * skew_entry(&vpt, i, j);
            out.a[i][3 + j] = half_pt + wwpt[i] * c1w2[j]
                - c * skew_entry(&wpt, i, j)
                - c * (pt[i] * w[j] - id * wpt_dot);
        }
    }
    out
}

/// [`tar_derivatives`]' result: ∂tar/∂p and ∂tar/∂x, 6×6 each.
struct ChartDerivatives<const L: usize> {
    b: [[V<L>; 6]; 6],
    a: [[V<L>; 6]; 6],
}

/// Entry (i, j) of [a]×, the matrix of q ↦ a × q.
#[inline(always)]
fn skew_entry<const L: usize>(a: &[V<L>; 3], i: usize, j: usize) -> V<L> {
    match (i, j) {
        (0, 1) => V::splat(0.0) - a[2],
        (0, 2) => a[1],
        (1, 0) => a[2],
        (1, 2) => V::splat(0.0) - a[0],
        (2, 0) => V::splat(0.0) - a[1],
        (2, 1) => a[0],
        _ => V::splat(0.0),
    }
}

/// [ω]×² = ω ωᵀ − |ω|² I, `s` = |ω|².
#[inline(always)]
fn square_skew<const L: usize>(w: &[V<L>; 3], s: V<L>) -> M3<L> {
    let mut m = [[V::splat(0.0); 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            m[i][j] = w[i] * w[j];
        }
        m[i][i] = m[i][i] - s;
    }
    m
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

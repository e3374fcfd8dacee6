//! The so(3) Newton solve of S in SIMD lanes: the bisection step of a Taylor-HJ integrator (a
//! polynomial S) or of a learned one (a polynomial plus a network term,
//! [`crate::generating::NetworkLanes`]) on an so(3) chart, for a block of trajectories in
//! lockstep, each lane bit-identical to the one-lane step.

// Index loops over lanes and coordinates read as the formulas they evaluate.
#![allow(clippy::needless_range_loop)]

use crate::error::StepFailure;
use crate::generating::polynomial_lanes::{jet_lanes_into, JetLanes, Scratch, SCALAR_AT_MOST};
pub use crate::generating::polynomial_lanes::{polynomial_gradients, polynomial_jets};
use crate::generating::{LaneRow, NetworkLanes, Polynomial};
use crate::isa::{Isa, LANES};
use crate::step::{StepResult, StepStats, SIMPLIFIED_RATE};
use crate::structures::lie_groupoid::{
    exp_chart_coefficient_to, Chart, COS_SERIES, C_SERIES, EXP_CHART_MAX_ANGLE, SIN_SERIES,
};

/// L numbers, one per lane; every operation acts lane by lane (one SIMD instruction per 4 lanes
/// with AVX2). Plain multiplies and adds only, never contracted: lane l of any L gives the same
/// bits, so one trajectory (L = 1) and a block (L = [`LANES`]) agree exactly.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct V<const L: usize>(pub [f64; L]);

impl<const L: usize> V<L> {
    #[inline(always)]
    pub(crate) fn splat(x: f64) -> Self {
        V([x; L])
    }
    #[inline(always)]
    pub(crate) fn zip(self, o: Self, f: impl Fn(f64, f64) -> f64) -> Self {
        let mut r = self;
        for l in 0..L {
            r.0[l] = f(self.0[l], o.0[l]);
        }
        r
    }
    #[inline(always)]
    pub(crate) fn scale(self, c: f64) -> Self {
        let mut r = self;
        for l in 0..L {
            r.0[l] = self.0[l] * c;
        }
        r
    }
    /// `a` on the lanes where `take` holds, `self` elsewhere: a blend, where writing the lanes
    /// one at a time and then reading the vector back stalls on store forwarding.
    #[inline(always)]
    pub(crate) fn blend(self, take: &[bool; L], a: Self) -> Self {
        let mut r = self;
        for l in 0..L {
            r.0[l] = if take[l] { a.0[l] } else { self.0[l] };
        }
        r
    }
    /// a − a: 0 for a finite a, NaN for ±∞ and NaN. A sum of such probes is 0 exactly where
    /// every term is finite (NaN survives any sum), so one vector sum checks many numbers.
    #[inline(always)]
    // a − a on purpose: it is the probe.
    #[allow(clippy::eq_op)]
    pub(crate) fn finite_probe(self) -> Self {
        self - self
    }
    /// |a| lane by lane.
    #[inline(always)]
    pub(crate) fn abs(self) -> Self {
        let mut r = self;
        for l in 0..L {
            r.0[l] = self.0[l].abs();
        }
        r
    }
    /// f64::max lane by lane.
    #[inline(always)]
    pub(crate) fn max(self, o: Self) -> Self {
        self.zip(o, f64::max)
    }
}

/// A Newton round's finiteness checks as vector sums: (S and ∇S, the Hessian where `hess`,
/// else 0), each lane 0 exactly where those numbers are finite on it.
#[inline(always)]
pub(crate) fn round_probes<const D: usize, const L: usize>(
    value: &[f64; L],
    x: &[V<L>; D],
    h: &[[V<L>; D]; D],
    hess: bool,
) -> (V<L>, V<L>) {
    let probe = finite_probe(x) + V(*value).finite_probe();
    let hess_probe = if hess { matrix_probe(h) } else { V::splat(0.0) };
    (probe, hess_probe)
}

/// The sum of the [`V::finite_probe`]s of `vs`: lane l is 0 exactly where every `vs[k]` is
/// finite on lane l.
#[inline(always)]
pub(crate) fn finite_probe<const L: usize, B: std::borrow::Borrow<V<L>>>(
    vs: impl IntoIterator<Item = B>,
) -> V<L> {
    vs.into_iter()
        .fold(V::splat(0.0), |acc, v| acc + v.borrow().finite_probe())
}

/// [`finite_probe`] of a matrix's entries in row order, in plain loops: through
/// `iter().flatten()` the sum was an out-of-line call (2 % of the heavy top's Taylor step and
/// of the rigid body's).
#[inline(always)]
pub(crate) fn matrix_probe<const R: usize, const C: usize, const L: usize>(
    m: &[[V<L>; C]; R],
) -> V<L> {
    let mut acc = V::splat(0.0);
    for row in m {
        for v in row {
            acc = acc + v.finite_probe();
        }
    }
    acc
}

impl<const L: usize> std::ops::Add for V<L> {
    type Output = Self;
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        self.zip(o, |a, b| a + b)
    }
}

impl<const L: usize> std::ops::Sub for V<L> {
    type Output = Self;
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        self.zip(o, |a, b| a - b)
    }
}

impl<const L: usize> std::ops::Mul for V<L> {
    type Output = Self;
    #[inline(always)]
    fn mul(self, o: Self) -> Self {
        self.zip(o, |a, b| a * b)
    }
}

/// L values and their derivatives along K directions (forward mode). The values take the
/// operations [`V`] takes, so they are its bits.
#[derive(Clone, Copy)]
pub(crate) struct D<const L: usize, const K: usize> {
    pub v: V<L>,
    pub d: [V<L>; K],
}

impl<const L: usize, const K: usize> D<L, K> {
    /// A constant: `v` with derivative 0.
    #[inline(always)]
    pub(crate) fn constant(v: V<L>) -> Self {
        D {
            v,
            d: [V::splat(0.0); K],
        }
    }
    #[inline(always)]
    pub(crate) fn times(self, c: f64) -> Self {
        let mut r = self;
        r.v = self.v.scale(c);
        for k in 0..K {
            r.d[k] = self.d[k].scale(c);
        }
        r
    }
    /// `a` on the lanes where `take` holds (value and derivatives), `self` elsewhere.
    #[inline(always)]
    pub(crate) fn blend(self, take: &[bool; L], a: Self) -> Self {
        let mut r = self;
        r.v = self.v.blend(take, a.v);
        for k in 0..K {
            r.d[k] = self.d[k].blend(take, a.d[k]);
        }
        r
    }
}

impl<const L: usize, const K: usize> std::ops::Add for D<L, K> {
    type Output = Self;
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        let mut r = self;
        r.v = self.v + o.v;
        for k in 0..K {
            r.d[k] = self.d[k] + o.d[k];
        }
        r
    }
}

impl<const L: usize, const K: usize> std::ops::Sub for D<L, K> {
    type Output = Self;
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        let mut r = self;
        r.v = self.v - o.v;
        for k in 0..K {
            r.d[k] = self.d[k] - o.d[k];
        }
        r
    }
}

impl<const L: usize, const K: usize> std::ops::Mul for D<L, K> {
    type Output = Self;
    #[inline(always)]
    fn mul(self, o: Self) -> Self {
        let mut r = self;
        r.v = self.v * o.v;
        for k in 0..K {
            r.d[k] = self.d[k] * o.v + self.v * o.d[k];
        }
        r
    }
}

/// The inverse of an N×N matrix lane by lane, by Gauss–Jordan with partial pivoting (each lane
/// picks and swaps its own pivot rows), and per lane whether every pivot was non-zero and the
/// inverse finite. `m` is reduced in `a` while `inv` (starting at I) takes the same row
/// operations.
#[inline(always)]
pub(crate) fn inverse_lanes<const N: usize, const L: usize>(
    m: &[[V<L>; N]; N],
    inv: &mut [[V<L>; N]; N],
) -> [bool; L] {
    let (zero, one) = (V::splat(0.0), V::splat(1.0));
    let mut a = *m;
    for r in 0..N {
        inv[r] = [zero; N];
        inv[r][r] = one;
    }
    let mut ok = [true; L];
    for col in 0..N {
        // Rows above `col` are pivot rows; below it, columns before `col` are already zero.
        // Each lane's pivot row (the first of the largest |a[r][col]|), searched in vectors;
        // the rows are swapped lane by lane, and only where a lane's pivot moved (J ≈ I in a
        // Newton solve of small steps: rarely).
        let mut largest = a[col][col].abs();
        let mut pivot_row = [col; L];
        for r in col + 1..N {
            let size = a[r][col].abs();
            let larger: [bool; L] = std::array::from_fn(|l| size.0[l] > largest.0[l]);
            largest = largest.blend(&larger, size);
            for l in 0..L {
                pivot_row[l] = if larger[l] { r } else { pivot_row[l] };
            }
        }
        for l in 0..L {
            let best = pivot_row[l];
            if best != col {
                for j in col..N {
                    let t = a[best][j].0[l];
                    a[best][j].0[l] = a[col][j].0[l];
                    a[col][j].0[l] = t;
                }
                for j in 0..N {
                    let t = inv[best][j].0[l];
                    inv[best][j].0[l] = inv[col][j].0[l];
                    inv[col][j].0[l] = t;
                }
            }
        }
        let pivot = a[col][col];
        for l in 0..L {
            ok[l] &= pivot.0[l] != 0.0 && pivot.0[l].is_finite();
        }
        let r = one.zip(pivot, |a, b| a / b);
        for j in col + 1..N {
            a[col][j] = a[col][j] * r;
        }
        for j in 0..N {
            inv[col][j] = inv[col][j] * r;
        }
        for row in 0..N {
            if row != col {
                let f = a[row][col];
                for j in col + 1..N {
                    a[row][j] = a[row][j] - f * a[col][j];
                }
                for j in 0..N {
                    inv[row][j] = inv[row][j] - f * inv[col][j];
                }
            }
        }
    }
    let probe = matrix_probe(inv);
    for l in 0..L {
        ok[l] &= probe.0[l] == 0.0;
    }
    ok
}

type V3<const L: usize> = [V<L>; 3];
type M3<const L: usize> = [[V<L>; 3]; 3];

/// `[e(0), e(1), e(2)]` with the index bound to 0, 1, 2, written out in place. Not a helper
/// taking a closure: a closure the compiler leaves out of line is compiled without the block's
/// target features (the profile found SSE2 code for a 3×3 inverse and for the charts' vectors
/// inside the AVX-512 block). Exported for the benches' hand-written steps.
#[doc(hidden)]
#[macro_export]
macro_rules! v3 {
    (|$i:ident| $e:expr) => {
        [
            {
                let $i = 0;
                $e
            },
            {
                let $i = 1;
                $e
            },
            {
                let $i = 2;
                $e
            },
        ]
    };
}

/// The 3×3 matrix with entries `e(r, c)`, written out in place as `v3!` does.
#[doc(hidden)]
#[macro_export]
macro_rules! m3 {
    (|$r:ident, $c:ident| $e:expr) => {
        [
            $crate::v3!(|$c| {
                let $r = 0;
                $e
            }),
            $crate::v3!(|$c| {
                let $r = 1;
                $e
            }),
            $crate::v3!(|$c| {
                let $r = 2;
                $e
            }),
        ]
    };
}

/// The same products in the same order as the chart's (groupoid::cross).
#[inline(always)]
fn cross<const L: usize>(a: &V3<L>, b: &V3<L>) -> V3<L> {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[inline(always)]
fn dot<const L: usize>(a: &V3<L>, b: &V3<L>) -> V<L> {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// tar (`sign` = −1) or sou (+1) of an so(3) chart in lanes, with the exact p-Jacobian of
/// tar(∇S(p), p) when `hess` (the Hessian of S, symmetric) is given. Also returns |x|².
///
/// The values are the chart's own operations ([`Chart::tar`] / [`Chart::sou`] in f64), bit for
/// bit. With x = ∇S, w = x·p, s = |x|² and, for the exponential chart, c = c(s), c' = dc/ds,
/// u = x×(x×p) = x w − s p:
/// - Cayley, T = p − ½ x×p + ¼ x w: ∂T/∂p = I − ½ x̂ + ¼ x xᵀ, ∂T/∂x = ½ p̂ + ¼ (x pᵀ + w I);
/// - exp, T = p − ½ x×p + c u: ∂T/∂p = (1 − c s) I − ½ x̂ + c x xᵀ,
///   ∂T/∂x = ½ p̂ + c (x pᵀ + w I) + (2c' u − 2c p) xᵀ;
///
/// and J = ∂T/∂p + ∂T/∂x · Hess S. Lanes with s ≥ 1 take c and c' from the scalar closed form
/// (the series is summed for s < 1 only, as in the chart).
#[inline(always)]
pub(crate) fn so3_chart_lanes<const L: usize>(
    chart: Chart,
    sign: f64,
    x: &V3<L>,
    p: &V3<L>,
    hess: Option<&M3<L>>,
) -> (V3<L>, V<L>, Option<M3<L>>) {
    let xp = cross(x, p);
    let s = dot(x, x);
    let half = v3!(|i| xp[i].scale(0.5 * sign));
    let (t, c, dc, u) = match chart {
        Chart::Cayley => {
            let q = dot(x, p).scale(0.25);
            let t = v3!(|i| p[i] + half[i] + x[i] * q);
            (t, V::splat(0.25), V::splat(0.0), [V::splat(0.0); 3])
        }
        Chart::Exp => {
            let order = if hess.is_some() { 1 } else { 0 };
            // groupoid::exp_chart_coefficient_to's series, lane by lane.
            let (mut c, mut dc) = (V::splat(0.0), V::splat(0.0));
            for (n, &a) in C_SERIES.iter().enumerate().rev() {
                c = c * s + V::splat(a);
                if order >= 1 && n >= 1 {
                    dc = dc * s + V::splat(n as f64 * a);
                }
            }
            for l in 0..L {
                if s.0[l] >= 1.0 {
                    let (a, b, _) = exp_chart_coefficient_to(s.0[l], order);
                    (c.0[l], dc.0[l]) = (a, b);
                }
            }
            let u = cross(x, &xp);
            let t = v3!(|i| p[i] + half[i] + c * u[i]);
            (t, c, dc, u)
        }
    };
    let Some(h) = hess else {
        return (t, s, None);
    };
    let (zero, one) = (V::splat(0.0), V::splat(1.0));
    let w = dot(x, p);
    // The exponential chart's extra terms: −c s on the diagonal of ∂T/∂p, v xᵀ in ∂T/∂x.
    let (diag, v) = match chart {
        Chart::Cayley => (one, [zero; 3]),
        Chart::Exp => {
            let two_dc = dc.scale(2.0);
            let two_c = c.scale(2.0);
            (one - c * s, v3!(|i| two_dc * u[i] - two_c * p[i]))
        }
    };
    // ∂T/∂p = diag I − ½ x̂ + c x xᵀ, with x̂ = [[0, −x₂, x₁], [x₂, 0, −x₀], [−x₁, x₀, 0]].
    let hx = v3!(|i| x[i].scale(0.5));
    let mut jp = m3!(|r, k| c * x[r] * x[k]);
    jp[0][1] = jp[0][1] + hx[2];
    jp[0][2] = jp[0][2] - hx[1];
    jp[1][0] = jp[1][0] - hx[2];
    jp[1][2] = jp[1][2] + hx[0];
    jp[2][0] = jp[2][0] + hx[1];
    jp[2][1] = jp[2][1] - hx[0];
    for i in 0..3 {
        jp[i][i] = jp[i][i] + diag;
    }
    // ∂T/∂x = ½ p̂ + c (x pᵀ + w I) + v xᵀ.
    let hp = v3!(|i| p[i].scale(0.5));
    let mut a = m3!(|r, k| c * x[r] * p[k] + v[r] * x[k]);
    a[0][1] = a[0][1] - hp[2];
    a[0][2] = a[0][2] + hp[1];
    a[1][0] = a[1][0] + hp[2];
    a[1][2] = a[1][2] - hp[0];
    a[2][0] = a[2][0] - hp[1];
    a[2][1] = a[2][1] + hp[0];
    let cw = c * w;
    for i in 0..3 {
        a[i][i] = a[i][i] + cw;
    }
    let j = m3!(|r, k| jp[r][k] + a[r][0] * h[0][k] + a[r][1] * h[1][k] + a[r][2] * h[2][k]);
    (t, s, Some(j))
}

/// [`Chart::rotate`] in lanes, bit for bit: R(x) μ = μ + (a x×μ + b x×(x×μ)), with the
/// coefficients at s = |x|² (given) from [`Chart::rotation_coefficients`]; the exponential
/// chart's series is summed in lanes below s = 1, its closed form taken lane by lane above.
#[inline(always)]
pub(crate) fn so3_rotate_lanes<const L: usize>(
    chart: Chart,
    x: &V3<L>,
    mu: &V3<L>,
    s: V<L>,
) -> V3<L> {
    let (a, b) = match chart {
        Chart::Cayley => {
            let r = V::splat(1.0).zip(V::splat(1.0) + s.scale(0.25), |a, b| a / b);
            (r, r.scale(0.5))
        }
        Chart::Exp => {
            let (mut a, mut b) = (V::splat(0.0), V::splat(0.0));
            for (&u, &v) in SIN_SERIES.iter().zip(&COS_SERIES).rev() {
                a = a * s + V::splat(u);
                b = b * s + V::splat(v);
            }
            for l in 0..L {
                if s.0[l] >= 1.0 {
                    (a.0[l], b.0[l]) = chart.rotation_coefficients(s.0[l]);
                }
            }
            (a, b)
        }
    };
    let xm = cross(x, mu);
    let xxm = cross(x, &xm);
    v3!(|i| mu[i] + (a * xm[i] + b * xxm[i]))
}

/// The cofactor inverse of [`crate::stepper::inverse3`] lane by lane (the same operations), and
/// the determinant.
#[inline(always)]
fn inverse3_lanes<const L: usize>(m: &M3<L>) -> (M3<L>, V<L>) {
    let (adj, det) = crate::step::adjugate3(m);
    let r = V::splat(1.0).zip(det, |a, b| a / b);
    (m3!(|i, j| adj[i][j] * r), det)
}

/// Largest |x₀|² at which the Newton predictor is used (see [`So3Newton::predict`]).
pub(crate) const PREDICT_MAX_S: f64 = 1.0;

/// What a lane Newton solve of S needs: S's polynomial part and network term if it has one,
/// the chart (so(3)'s [`Chart`] here; any [`crate::lanes_bisection_exp::ExpChartLanes`] for the
/// exponential-chart solver) and the simplified-Newton settings.
pub(crate) struct ChartNewton<'a, const N: usize, C> {
    pub poly: &'a Polynomial<N>,
    pub network: Option<NetworkLanes<'a>>,
    pub chart: C,
    pub tol: f64,
    pub max_iter: u32,
    /// Start Newton from a predicted p₀ instead of μ, where |x₀|² ≤ [`PREDICT_MAX_S`] (x₀: the
    /// gradient of S's cheap terms at μ): a second-order start from one jet of those terms with
    /// its Hessian, so(3)'s in either chart (`so3_start`), every other algebra's exponential
    /// chart's from tar's second-order part (`lanes_bisection_exp::second_order_start`).
    pub predict: bool,
}

/// The so(3) lane solve: S on N = 3 in either so(3) chart.
pub(crate) type So3Newton<'a, const N: usize> = ChartNewton<'a, N, Chart>;

/// The jets of S = P + network term (the Hessian only when `HESS`) at a block's momenta into
/// `jet`; `buf` is the network term's scratch ([`NetworkLanes::add_jet_lanes`]).
#[inline(always)]
pub(crate) fn evaluate<const N: usize, const L: usize, const HESS: bool>(
    poly: &Polynomial<N>,
    network: Option<&NetworkLanes<'_>>,
    t: f64,
    p: &[[f64; L]; N],
    scratch: &mut Scratch<N, L>,
    buf: &mut [LaneRow],
    jet: &mut JetLanes<N, L>,
) {
    evaluate_polynomial::<N, L, HESS>(poly, t, p, scratch, jet);
    if let Some(net) = network {
        net.add_jet_lanes::<N, L, HESS>(t, p, buf, jet);
    }
}

/// The polynomial part of [`evaluate`]. One lane takes the scalar [`Polynomial::jet`] /
/// [`Polynomial::gradient`]: the same bits as a lane of a block (see [`jet_lanes_into`]),
/// without storing every factor to memory as the lane code does.
#[inline(always)]
fn evaluate_polynomial<const N: usize, const L: usize, const HESS: bool>(
    poly: &Polynomial<N>,
    t: f64,
    p: &[[f64; L]; N],
    scratch: &mut Scratch<N, L>,
    jet: &mut JetLanes<N, L>,
) {
    if L != 1 {
        return jet_lanes_into::<N, L, HESS, 0>(poly, t, p, scratch, jet);
    }
    let q: [f64; N] = std::array::from_fn(|i| p[i][0]);
    if HESS {
        let j = poly.jet(t, &q);
        jet.v[0] = j.v;
        let packed = j.packed();
        let mut k = 0;
        for a in 0..N {
            jet.g[a][0] = j.g[a];
            for b in a..N {
                jet.h[a][b][0] = packed[k];
                k += 1;
            }
        }
    } else {
        let d = poly.gradient(t, &q);
        jet.v[0] = d.v;
        for a in 0..N {
            jet.g[a][0] = d.g[a];
        }
    }
}

/// x = ∇S and, when `HESS`, the full symmetric Hessian, from a block's jets (N = 3).
#[inline(always)]
fn gradient_and_hessian<const N: usize, const L: usize>(jet: &JetLanes<N, L>) -> (V3<L>, M3<L>) {
    let x = [V(jet.g[0]), V(jet.g[1]), V(jet.g[2])];
    let h = m3!(|a, b| V(jet.h[a.min(b)][a.max(b)]));
    (x, h)
}

/// so(3)'s Newton start, O(h³) from the solution, and |x₀|²: from one jet of S's cheap terms at
/// μ with its Hessian (x₀ and Hess), a first-order start p₁ and then one fixed-point step
/// p₀ = p₁ + μ − tar(x̃, p₁) with x̃ = x₀ + Hess · (p₁ − μ) = ∇S(p₁) + O(h³) (the Hessian at μ
/// standing in for a gradient pass at p₁). The step contracts p₁'s error by O(h), so both
/// constants count: the rigid body's Taylor K = 3 at h = 0.1 takes 2 updates a step from p₀ in
/// either chart, 3 from p₁ (`benches/newton_predictors.py`).
///
/// - Exponential chart (`EXP`): S's t¹ and t² terms (S₂ = 0 there), p₁ = μ + ½ x₀ × μ, and
///   tar's quadratic coefficient taken at c(0) = 1/12 (c(s) − c(0) = O(h²) is O(h⁴) here):
///   p₀ = μ + ½ x̃ × p₁ − x̃ × (x̃ × p₁)/12.
/// - Cayley: tar(x, p) = p − ½ x×p + ¼ x (x·p) is exactly quadratic in x, and both of its
///   large parts enter: p₁ = 2μ − tar(x₀, μ) (from μ + ½ x₀ × μ alone, whose O(h²) error is
///   about 35× the exponential chart's, 2.78 updates a step) and S's t³ terms in the jet (its S₃
///   is 10–20× the exponential chart's; left out, 2.78 as well). p₀ = μ + ½ x̃ × p₁ −
///   ¼ x̃ (x̃·p₁).
#[inline(always)]
pub(crate) fn so3_start<const N: usize, const L: usize, const EXP: bool>(
    poly: &Polynomial<N>,
    t: f64,
    pl: &[[f64; L]; N],
    mu: &V3<L>,
    scratch: &mut Scratch<N, L>,
    jet: &mut JetLanes<N, L>,
) -> (V3<L>, V<L>) {
    if EXP {
        jet_lanes_into::<N, L, true, 2>(poly, t, pl, scratch, jet);
    } else {
        jet_lanes_into::<N, L, true, 3>(poly, t, pl, scratch, jet);
    }
    let (x0, h0) = gradient_and_hessian(jet);
    let turn = cross(&x0, mu);
    let p1 = if EXP {
        v3!(|i| mu[i] + turn[i].scale(0.5))
    } else {
        let along = dot(&x0, mu).scale(0.25);
        v3!(|i| mu[i] + turn[i].scale(0.5) - x0[i] * along)
    };
    let d = v3!(|i| p1[i] - mu[i]);
    let xt = v3!(|a| x0[a] + (h0[a][0] * d[0] + h0[a][1] * d[1] + h0[a][2] * d[2]));
    let turn = cross(&xt, &p1);
    let p0 = if EXP {
        let twice = cross(&xt, &turn);
        v3!(|i| mu[i] + turn[i].scale(0.5) - twice[i].scale(C_SERIES[0]))
    } else {
        let along = dot(&xt, &p1).scale(0.25);
        v3!(|i| mu[i] + turn[i].scale(0.5) - xt[i] * along)
    };
    (p0, dot(&x0, &x0))
}

/// Simplified Newton's bookkeeping for a block, lane by lane (the rule of the generic
/// one-trajectory step): which lanes still iterate, which take a fresh Jacobian next, the last
/// update's size, the update counts and which lanes converged.
pub(crate) struct Progress<const L: usize> {
    pub active: [bool; L],
    pub refresh: [bool; L],
    last: [f64; L],
    pub iterations: [u32; L],
    pub converged: [bool; L],
}

impl<const L: usize> Progress<L> {
    /// Every lane in `active` iterates, starting with a fresh Jacobian.
    #[inline(always)]
    pub(crate) fn new(active: [bool; L]) -> Self {
        Progress {
            active,
            refresh: [true; L],
            last: [f64::INFINITY; L],
            iterations: [0; L],
            converged: [false; L],
        }
    }

    #[inline(always)]
    pub(crate) fn running(&self) -> bool {
        self.active.iter().any(|&a| a)
    }

    /// Whether a lane still iterating needs a fresh Jacobian this round.
    #[inline(always)]
    pub(crate) fn jacobian_wanted(&self) -> bool {
        (0..L).any(|l| self.active[l] && self.refresh[l])
    }

    /// This round's verdict on every active lane l, in the one-trajectory step's order:
    /// NonFinite where S's jet is not finite (`probe`; on a refresh `hess_probe` too), the
    /// chart's own failure (`chart(l)`), NotConverged after `max_iter` updates,
    /// SingularJacobian where a refreshing lane's fresh inverse is unusable (`inverted(l)`
    /// false). A lane that fails stops with its failure in `results`. Returns the lanes that
    /// take this round's update and, of those, the ones that take the fresh inverse. (`chart`
    /// and `inverted` are asked only where the verdict needs them: the so(3) rounds are short
    /// enough that whole arrays of them cost 3–7 % of a step.)
    #[inline(always)]
    pub(crate) fn judge(
        &mut self,
        probe: &V<L>,
        hess_probe: &V<L>,
        chart: impl Fn(usize) -> Option<StepFailure>,
        max_iter: u32,
        inverted: impl Fn(usize) -> bool,
        results: &mut [StepResult],
    ) -> ([bool; L], [bool; L]) {
        let mut go = [false; L];
        let mut take = [false; L];
        for l in 0..L {
            if !self.active[l] {
                continue;
            }
            let refresh = self.refresh[l];
            let finite = probe.0[l] == 0.0 && (!refresh || hess_probe.0[l] == 0.0);
            let failure = if !finite {
                Some(StepFailure::NonFinite)
            } else if let Some(e) = chart(l) {
                Some(e)
            } else if self.iterations[l] >= max_iter {
                Some(StepFailure::NotConverged)
            } else if refresh && !inverted(l) {
                Some(StepFailure::SingularJacobian)
            } else {
                take[l] = refresh;
                None
            };
            match failure {
                Some(e) => {
                    results[l] = Err(e);
                    self.active[l] = false;
                }
                None => go[l] = true,
            }
        }
        (go, take)
    }

    /// p += δ on the lanes in `go`: a δ that is not finite fails with SingularJacobian; a lane
    /// converges once |δ|∞ ≤ tol · max(|p|∞, 1e-300), else takes a fresh Jacobian next round
    /// where the update contracted by less than [`SIMPLIFIED_RATE`]. The sums, sizes and
    /// blends run on whole vectors; only the verdicts are taken lane by lane.
    #[inline(always)]
    pub(crate) fn update<const D: usize>(
        &mut self,
        go: &[bool; L],
        p: &mut [V<L>; D],
        delta: &[V<L>; D],
        tol: f64,
        results: &mut [StepResult],
    ) {
        let probe = finite_probe(delta);
        let mut take = *go;
        for l in 0..L {
            if go[l] && probe.0[l] != 0.0 {
                results[l] = Err(StepFailure::SingularJacobian);
                self.active[l] = false;
                take[l] = false;
            }
        }
        for i in 0..D {
            p[i] = p[i].blend(&take, p[i] + delta[i]);
        }
        let (size, pmax) = sizes(delta, p);
        for l in 0..L {
            if !take[l] {
                continue;
            }
            let size = size.0[l];
            self.iterations[l] += 1;
            if converged(size, pmax.0[l], tol) {
                self.converged[l] = true;
                self.active[l] = false;
            } else {
                self.refresh[l] = size > SIMPLIFIED_RATE * self.last[l];
                self.last[l] = size;
            }
        }
    }
}

/// An update's size |δ|∞ and the updated |p|∞, lane by lane.
#[inline(always)]
fn sizes<const D: usize, const L: usize>(delta: &[V<L>; D], p: &[V<L>; D]) -> (V<L>, V<L>) {
    let (mut size, mut pmax) = (V::splat(0.0), V::splat(0.0));
    for i in 0..D {
        size = size.max(delta[i].abs());
        pmax = pmax.max(p[i].abs());
    }
    (size, pmax)
}

/// Newton's stop rule, the one-trajectory step's: |δ|∞ ≤ tol · max(|p|∞, 1e-300).
#[inline(always)]
fn converged(size: f64, pmax: f64, tol: f64) -> bool {
    size <= tol * pmax.max(1e-300)
}

/// A block's states as lanes (`pl[i][j]` = `mu[j][i]`, zero past `mu.len()`) and which lanes
/// are live.
#[inline(always)]
pub(crate) fn load_block<const N: usize, const L: usize>(
    mu: &[[f64; N]],
    live: &[bool],
) -> ([[f64; L]; N], [bool; L]) {
    // Built in place by `from_fn`: a zeroed array filled after was a `memset` and a `memmove`
    // call each block (3 % of the heavy top's Taylor step).
    let n = mu.len();
    let pl = std::array::from_fn(|i| std::array::from_fn(|j| if j < n { mu[j][i] } else { 0.0 }));
    let active = std::array::from_fn(|j| j < n && live[j]);
    (pl, active)
}

/// One step of at most L trajectories (`mu.len()` ≤ L; those with `live` false are left alone)
/// by simplified Newton in lanes: the same rule as [`crate::stepper::BisectionStepper`]'s
/// (refresh the Jacobian while updates contract by less than [`SIMPLIFIED_RATE`], stop once
/// |δ|∞ ≤ tol · max(|p|∞, 1e-300)) and the same failures in the same order, lane by lane. A
/// lane that converged or failed is frozen; the block runs until every lane has. `EXP`: the
/// chart is the exponential one (else Cayley), as `sys.chart` says.
// Out of line in debug builds: inlined there, every local of every instantiation keeps its
// own slot in the dispatching frames, and a test thread's stack overflowed.
#[cfg_attr(not(debug_assertions), inline(always))]
#[cfg_attr(debug_assertions, inline(never))]
fn so3_block<const N: usize, const L: usize, const EXP: bool>(
    sys: &So3Newton<'_, N>,
    buf: &mut [LaneRow],
    t: f64,
    mu: &mut [[f64; N]],
    live: &[bool],
    results: &mut [StepResult],
) {
    let n = mu.len();
    debug_assert!(N == 3 && n <= L && EXP == (sys.chart == Chart::Exp));
    let chart = if EXP { Chart::Exp } else { Chart::Cayley };
    let (mut pl, active) = load_block::<N, L>(mu, live);
    let target: V3<L> = [V(pl[0]), V(pl[1]), V(pl[2])];
    let mut p = target;
    let net = sys.network.as_ref();
    let mut scratch = Scratch::<N, L>::new();
    let mut jet = JetLanes {
        v: [0.0; L],
        g: [[0.0; L]; N],
        h: [[[0.0; L]; N]; N],
    };
    // Every lane live and started from the prediction: the block may take its first two
    // rounds straight through (`so3_two_rounds`).
    let mut started = false;
    if sys.predict {
        // tar(x, p) = p − ½ x×p + O(|x|²) in both charts, so p₁ = μ + ½ x₀ × μ (x₀ the
        // gradient of S's cheap terms at μ) is O(h²) from the solution where μ is O(h), and one
        // fixed-point step from it O(h³) (`so3_start`). Simplified Newton's contraction is
        // proportional to that first error: 2 updates a step where p₁ takes 3.
        let (p0, s0) = so3_start::<N, L, EXP>(sys.poly, t, &pl, &target, &mut scratch, &mut jet);
        // Only where the expansion is meaningful: at |x₀| > 1 rad (a step far too large for
        // the series, h = 5 say) the predictor can throw Newton past the exp chart's singular
        // angle that a start from μ avoids.
        let probe = finite_probe(p0);
        let keep: [bool; L] =
            std::array::from_fn(|l| s0.0[l] <= PREDICT_MAX_S && probe.0[l] == 0.0);
        for i in 0..3 {
            p[i] = p[i].blend(&keep, p0[i]);
        }
        started = n == L && active.iter().chain(&keep).all(|&k| k);
    }
    let mut progress = Progress::new(active);
    let mut inv: M3<L> = [[V::splat(0.0); 3]; 3];
    // x = ∇S at each converged lane's p, to first order from its last update: x + Hess S · δ
    // with the Hessian of the lane's last refresh (the current one after a refresh, at most a
    // few simplified updates old otherwise), off by O(|δ| · |p − p_refresh| + |δ|²), far below a
    // rounding at |δ| ≤ tol·|p|; it saves the gradient pass at the solution.
    let mut xs: V3<L> = [V::splat(0.0); 3];
    let mut hk: M3<L> = [[V::splat(0.0); 3]; 3];
    let max_s = EXP_CHART_MAX_ANGLE * EXP_CHART_MAX_ANGLE;
    #[cfg(test)]
    if L > 1 && !started {
        two_rounds_tally::count(0);
    }
    // Blocks only: the one-lane solve stays on the loop, the reference each lane of a block is
    // tested against (`two_rounds_straight_through_end_as_the_loop_does`).
    if started && L > 1 && sys.max_iter >= 2 {
        let rounds = so3_two_rounds::<N, L, EXP>(sys, buf, t, &p, &target, &mut scratch, &mut jet);
        #[cfg(test)]
        let taken = rounds.is_some();
        if let Some(state) = rounds {
            Rounds {
                p,
                inv,
                hk,
                xs,
                progress,
            } = state;
        }
        #[cfg(test)]
        two_rounds_tally::count(match (taken, progress.running()) {
            (false, _) => 1,
            (true, true) => 2,
            (true, false) => 3,
        });
    }
    while progress.running() {
        let hess = progress.jacobian_wanted();
        for i in 0..3 {
            pl[i] = p[i].0;
        }
        if hess {
            evaluate::<N, L, true>(sys.poly, net, t, &pl, &mut scratch, buf, &mut jet);
        } else {
            evaluate::<N, L, false>(sys.poly, net, t, &pl, &mut scratch, buf, &mut jet);
        }
        let (x, h) = gradient_and_hessian(&jet);
        let (tar, s, jac) = so3_chart_lanes(chart, -1.0, &x, &p, hess.then_some(&h));
        // Matches, not `Option::map`: a closure left out of line is compiled without the
        // block's target features (it was: SSE2 code for the whole 3×3 inverse).
        #[allow(clippy::manual_map)]
        let fresh = match &jac {
            Some(j) => Some(inverse3_lanes(j)),
            None => None,
        };
        let (probe, hess_probe) = round_probes(&jet.v, &x, &h, hess);
        #[allow(clippy::manual_map)]
        let fresh_probe = match &fresh {
            Some((fi, det)) => Some(matrix_probe(fi) + det.finite_probe()),
            None => None,
        };
        let chart = |l: usize| (EXP && s.0[l] >= max_s).then_some(StepFailure::ChartSingular);
        let inverted = |l: usize| match (&fresh, &fresh_probe) {
            (Some((_, det)), Some(fp)) => det.0[l] != 0.0 && fp.0[l] == 0.0,
            _ => false,
        };
        // `take`: the lanes whose fresh inverse is taken this round.
        let (go, take) =
            progress.judge(&probe, &hess_probe, chart, sys.max_iter, inverted, results);
        if let Some((fi, _)) = &fresh {
            for r in 0..3 {
                for c in 0..3 {
                    inv[r][c] = inv[r][c].blend(&take, fi[r][c]);
                }
            }
            // Each lane's own last Hessian: the one of its last refresh (a block evaluates the
            // Hessian for every lane when one of them refreshes; a lane's bits must not see
            // that).
            for a in 0..3 {
                for b in 0..3 {
                    hk[a][b] = hk[a][b].blend(&take, h[a][b]);
                }
            }
        }
        // δ = J⁻¹ (μ − tar), each component summed in column order (Inverse::apply).
        let f = v3!(|i| target[i] - tar[i]);
        let delta = v3!(|r| inv[r][0] * f[0] + inv[r][1] * f[1] + inv[r][2] * f[2]);
        progress.update(&go, &mut p, &delta, sys.tol, results);
        let step = v3!(|a| hk[a][0] * delta[0] + hk[a][1] * delta[1] + hk[a][2] * delta[2]);
        let newly: [bool; L] = std::array::from_fn(|l| go[l] && progress.converged[l]);
        for a in 0..3 {
            xs[a] = xs[a].blend(&newly, x[a] + step[a]);
        }
    }
    if !progress.converged.iter().any(|&c| c) {
        return;
    }
    // μ' = R(x) μ with x = ∇S(p) at the converged p (= sou(x, p) up to the residual, which
    // R(x) μ leaves out: see Groupoid::coadjoint); the residual of the solved equation.
    let x = xs;
    let (tar, s, _) = so3_chart_lanes(chart, -1.0, &x, &p, None);
    let next = so3_rotate_lanes(chart, &x, &target, s);
    for l in (0..n).filter(|&l| progress.converged[l]) {
        results[l] = if !(0..3).all(|i| x[i].0[l].is_finite()) {
            Err(StepFailure::NonFinite)
        } else if EXP && s.0[l] >= max_s {
            Err(StepFailure::ChartSingular)
        } else if !(0..3).all(|i| next[i].0[l].is_finite()) {
            Err(StepFailure::NonFinite)
        } else {
            let residual = (0..3).fold(0.0f64, |m, i| m.max((tar[i].0[l] - target[i].0[l]).abs()));
            for i in 0..3 {
                mu[l][i] = next[i].0[l];
            }
            Ok(StepStats {
                iterations: progress.iterations[l],
                residual,
            })
        };
    }
}

/// How so(3) blocks of several lanes ran on this thread (tests only): the loop alone (not every
/// lane live and started from the prediction), [`so3_two_rounds`] declined (the loop from the
/// start), handed on (the loop went on for some lanes), finished (every lane converged).
#[cfg(test)]
pub(crate) mod two_rounds_tally {
    use std::cell::Cell;
    thread_local! {
        static TALLY: Cell<[u64; 4]> = const { Cell::new([0; 4]) };
    }
    pub(crate) fn count(outcome: usize) {
        TALLY.with(|t| {
            let mut v = t.get();
            v[outcome] += 1;
            t.set(v);
        });
    }
    /// The tally so far, and zero from here on.
    pub(crate) fn take() -> [u64; 4] {
        TALLY.with(|t| t.replace([0; 4]))
    }
}

/// The state of [`so3_block`]'s Newton loop between rounds.
struct Rounds<const L: usize> {
    p: V3<L>,
    inv: M3<L>,
    hk: M3<L>,
    xs: V3<L>,
    progress: Progress<L>,
}

/// [`so3_block`]'s first two rounds on a block whose every lane is live and starts from the
/// prediction, straight through: a fresh Jacobian, then a simplified update, each lane's
/// verdicts taken at the end as vector tests instead of round by round. Where every lane took
/// both updates as the loop would (finite, in the chart, invertible, not converged after the
/// first: the loop's rule then refreshes no Jacobian for the second, whose contraction is
/// against an infinite `last`), the loop's state after its second round is returned, made by
/// the same operations in the same order, so with the same bits; the loop goes on from there
/// for the lanes that have not converged. Otherwise None, and the loop runs from the start. The rigid body's Taylor steps take two updates a step
/// (`benches/step_costs.py`), so most blocks end here.
#[inline(always)]
fn so3_two_rounds<const N: usize, const L: usize, const EXP: bool>(
    sys: &So3Newton<'_, N>,
    buf: &mut [LaneRow],
    t: f64,
    p0: &V3<L>,
    target: &V3<L>,
    scratch: &mut Scratch<N, L>,
    jet: &mut JetLanes<N, L>,
) -> Option<Rounds<L>> {
    let chart = if EXP { Chart::Exp } else { Chart::Cayley };
    let net = sys.network.as_ref();
    let max_s = EXP_CHART_MAX_ANGLE * EXP_CHART_MAX_ANGLE;
    let mut pl = [[0.0; L]; N];
    for i in 0..3 {
        pl[i] = p0[i].0;
    }
    // Round 1: S's jet with its Hessian, the chart's Jacobian and its inverse.
    evaluate::<N, L, true>(sys.poly, net, t, &pl, scratch, buf, jet);
    let (x1, h1) = gradient_and_hessian(jet);
    let (tar1, s1, jac) = so3_chart_lanes(chart, -1.0, &x1, p0, Some(&h1));
    let jac = jac?;
    let (fi, det) = inverse3_lanes(&jac);
    let (probe, hess_probe) = round_probes(&jet.v, &x1, &h1, true);
    let fresh_probe = matrix_probe(&fi) + det.finite_probe();
    let f = v3!(|i| target[i] - tar1[i]);
    let d1 = v3!(|r| fi[r][0] * f[0] + fi[r][1] * f[1] + fi[r][2] * f[2]);
    let p1 = v3!(|i| p0[i] + d1[i]);
    let (size1, pmax1) = sizes(&d1, &p1);
    // Every probe 0 and every determinant non-zero, each lane in the chart and still moving
    // (Progress::judge's and Progress::update's verdicts, all passed).
    let probes = probe + hess_probe + fresh_probe + finite_probe(d1);
    for l in 0..L {
        let bad = probes.0[l] != 0.0 || det.0[l] == 0.0 || (EXP && s1.0[l] >= max_s);
        if bad || converged(size1.0[l], pmax1.0[l], sys.tol) {
            return None;
        }
    }
    // Round 2: the gradient only, the kept inverse.
    for i in 0..3 {
        pl[i] = p1[i].0;
    }
    evaluate::<N, L, false>(sys.poly, net, t, &pl, scratch, buf, jet);
    let x2 = [V(jet.g[0]), V(jet.g[1]), V(jet.g[2])];
    let (tar2, s2, _) = so3_chart_lanes(chart, -1.0, &x2, &p1, None);
    let f = v3!(|i| target[i] - tar2[i]);
    let d2 = v3!(|r| fi[r][0] * f[0] + fi[r][1] * f[1] + fi[r][2] * f[2]);
    let p2 = v3!(|i| p1[i] + d2[i]);
    let (size2, pmax2) = sizes(&d2, &p2);
    let probes = finite_probe(x2) + V(jet.v).finite_probe() + finite_probe(d2);
    for l in 0..L {
        if probes.0[l] != 0.0 || (EXP && s2.0[l] >= max_s) {
            return None;
        }
    }
    let step = v3!(|a| h1[a][0] * d2[0] + h1[a][1] * d2[1] + h1[a][2] * d2[2]);
    let done: [bool; L] = std::array::from_fn(|l| converged(size2.0[l], pmax2.0[l], sys.tol));
    let mut progress = Progress::new([true; L]);
    for l in 0..L {
        progress.iterations[l] = 2;
        progress.converged[l] = done[l];
        progress.active[l] = !done[l];
        progress.refresh[l] = !done[l] && size2.0[l] > SIMPLIFIED_RATE * size1.0[l];
        progress.last[l] = if done[l] { size1.0[l] } else { size2.0[l] };
    }
    Some(Rounds {
        p: p2,
        inv: fi,
        hk: h1,
        xs: v3!(|a| V::splat(0.0).blend(&done, x2[a] + step[a])),
        progress,
    })
}

/// A Newton solve in lanes: one step of a block of at most L trajectories, every lane with the
/// bits of its one-lane solve ([`So3Newton`]; [`ChartNewton`] on any
/// [`crate::lanes_bisection_exp::ExpChartLanes`]).
pub(crate) trait LaneSolve<const N: usize> {
    /// Whether blocks run compiled for AVX-512 where the CPU has it ([`Isa::is_avx512`]):
    /// eight lanes are then one register. By default up to [`crate::isa::AVX512_MAX_DIM`]
    /// coordinates (the solves there took 0.86–0.97× their AVX2 time); a solver measured to
    /// lose says false.
    fn avx512(&self) -> bool {
        N <= crate::isa::AVX512_MAX_DIM
    }

    /// One step of `mu` (at most L states; those with `live` false left alone) into `results`.
    fn block<const L: usize>(
        &self,
        buf: &mut [LaneRow],
        t: f64,
        mu: &mut [[f64; N]],
        live: &[bool],
        results: &mut [StepResult],
    );
}

impl<const N: usize> LaneSolve<N> for So3Newton<'_, N> {
    /// The exponential chart's Taylor steps took 0.90–0.96× their AVX2 time and a network's
    /// 0.89–0.91×; the Cayley chart's Taylor steps 1.03–1.07×, so they stay on AVX2.
    fn avx512(&self) -> bool {
        self.chart == Chart::Exp || self.network.is_some()
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
        // One instantiation per chart: each block's code then holds its own chart only (with
        // the chart a run-time value, the exponential chart's start made the Cayley chart's
        // block 1.16× slower with the same operations). The network stays a run-time option:
        // one instantiation per S with and without it read 0.96–1.04× on the Taylor steps and
        // 1.07× on the learned `default`.
        match self.chart {
            Chart::Exp => so3_block::<N, L, true>(self, buf, t, mu, live, results),
            Chart::Cayley => so3_block::<N, L, false>(self, buf, t, mu, live, results),
        }
    }
}

/// [`LaneSolve::block`] over a chunk: blocks of [`LANES`] trajectories, or one trajectory at a
/// time (L = 1, the same bits) where a block has at most [`SCALAR_AT_MOST`] live ones, compiled
/// for `isa` too.
#[inline(always)]
fn solve_chunk<const N: usize, S: LaneSolve<N>>(
    sys: &S,
    isa: Isa,
    buf: &mut [LaneRow],
    t: f64,
    mu: &mut [[f64; N]],
    live: &[bool],
    results: &mut [StepResult],
) {
    for ((m, lv), r) in mu
        .chunks_mut(LANES)
        .zip(live.chunks(LANES))
        .zip(results.chunks_mut(LANES))
    {
        if lv.iter().filter(|&&l| l).count() <= SCALAR_AT_MOST {
            for j in (0..m.len()).filter(|&j| lv[j]) {
                #[cfg(target_arch = "x86_64")]
                if isa.is_avx2() {
                    // SAFETY: `isa` claims AVX2 and FMA only where run-time detection found both.
                    unsafe { solve_one_avx2(sys, buf, t, &mut m[j], &mut r[j]) };
                    continue;
                }
                solve_one(sys, buf, t, &mut m[j], &mut r[j]);
            }
        } else {
            sys.block::<LANES>(buf, t, m, lv, r);
        }
    }
}

/// A function stepping one trajectory: [`LaneSolve::block`] with one lane, compiled on its own
/// (scalar code gains nothing from the block's vector registers, and a separate function keeps
/// its registers to itself), under the attributes given.
macro_rules! one_lane_solver {
    ($(#[$attr:meta])* $name:ident) => {
        $(#[$attr])*
        #[inline(never)]
        fn $name<const N: usize, S: LaneSolve<N>>(
            sys: &S,
            buf: &mut [LaneRow],
            t: f64,
            mu: &mut [f64; N],
            result: &mut StepResult,
        ) {
            sys.block::<1>(
                buf,
                t,
                std::slice::from_mut(mu),
                &[true],
                std::slice::from_mut(result),
            );
        }
    };
}

one_lane_solver!(solve_one);
one_lane_solver!(
    /// `solve_one` compiled for AVX2 and FMA: the lane networks' fused multiply-adds are one
    /// instruction each here, where the portable build calls the C library's `fma`.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    solve_one_avx2
);

/// [`solve_chunk`] compiled for the CPU features `$features`: callable only behind the
/// [`Isa`] proof that detection found them.
macro_rules! solve_chunk_for {
    ($name:ident, $features:literal) => {
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = $features)]
        fn $name<const N: usize, S: LaneSolve<N>>(
            sys: &S,
            isa: Isa,
            buf: &mut [LaneRow],
            t: f64,
            mu: &mut [[f64; N]],
            live: &[bool],
            results: &mut [StepResult],
        ) {
            solve_chunk(sys, isa, buf, t, mu, live, results);
        }
    };
}

solve_chunk_for!(solve_chunk_avx2, "avx2,fma");
solve_chunk_for!(solve_chunk_avx512, "avx512f,avx512vl,avx2,fma");

/// One step of every `mu[j]` with `live[j]` by the lane solver `sys`, compiled for `isa`;
/// `results[j]` as [`crate::stepper::StepMap::step`] reports it. Lane j's bits depend neither on
/// the other lanes, nor on the block size, nor on `isa`. `buf`: the network term's scratch
/// (empty for a polynomial S).
pub(crate) fn lane_newton_steps<const N: usize, S: LaneSolve<N>>(
    sys: &S,
    isa: Isa,
    buf: &mut [LaneRow],
    t: f64,
    mu: &mut [[f64; N]],
    live: &[bool],
    results: &mut [StepResult],
) {
    assert!(
        live.len() == mu.len() && results.len() == mu.len(),
        "one flag and one result per state"
    );
    #[cfg(target_arch = "x86_64")]
    if isa.is_avx512() && sys.avx512() {
        // SAFETY: an `Isa` claims AVX-512 (F, VL) with AVX2 and FMA only where run-time
        // detection found all four (its fields are private: safe code cannot forge it).
        unsafe { solve_chunk_avx512(sys, isa, buf, t, mu, live, results) };
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if isa.is_avx2() {
        // SAFETY: an `Isa` claims AVX2 only where run-time detection found AVX2 and FMA (its
        // field is private: safe code cannot forge it).
        unsafe { solve_chunk_avx2(sys, isa, buf, t, mu, live, results) };
        return;
    }
    solve_chunk(sys, isa, buf, t, mu, live, results);
}

/// One simplified-Newton bisection step of every `mu[j]` with `live[j]` on an so(3) chart (N
/// must be 3): [`lane_newton_steps`] of [`So3Newton`].
pub(crate) fn so3_newton_steps<const N: usize>(
    sys: &So3Newton<'_, N>,
    isa: Isa,
    buf: &mut [LaneRow],
    t: f64,
    mu: &mut [[f64; N]],
    live: &[bool],
    results: &mut [StepResult],
) {
    assert!(N == 3, "so(3) lanes need N = 3");
    lane_newton_steps(sys, isa, buf, t, mu, live, results);
}

//! The symplectic groupoid T*G ⇉ g* of a Lie algebra g in a chart of G near the identity.
//!
//! Coordinates are (x, p) ∈ g × g* ≅ R^N × R^N; units are x = 0, where sou = tar = p.
//! - so(3) (the rigid body) has two closed-form charts, Cayley and exponential. `sou` is the
//!   spatial momentum, `tar` the body one, and |sou(x,p)| = |tar(x,p)|.
//! - Any other algebra uses the exponential chart, with A = ad_xᵀ:
//!   sou(x,p) = (ad_x/(e^{ad_x} − 1))ᵀ p = Σ (Bₙ/n!) Aⁿ p and
//!   tar(x,p) = (ad_x/(1 − e^{−ad_x}))ᵀ p = Σ (Bₙ/n!) (−A)ⁿ p, summed as series (ad_x is
//!   singular, so never as a quotient). Both lie on one coadjoint orbit, which is why every
//!   bisection map keeps every Casimir whatever the generating function is.
//!
//! Indeed sou(x, p) = g(x) · tar(x, p) for the coadjoint action of the chart's group element
//! g(x) (e^{−A} in the exponential chart, a rotation on so(3): [`Groupoid::coadjoint`]), so a
//! step that solved tar(x, p) = μ takes g(x) · μ as its new state: exactly on μ's orbit,
//! whatever the residual of the solve.

// Index loops over small fixed-size vectors and matrices read as the formulas they implement.
#![allow(clippy::needless_range_loop)]

use std::sync::OnceLock;

use crate::dual::Scalar;
use crate::error::{CoreError, StepFailure};

/// A chart of G near the identity. Cayley exists for so(3) only.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Chart {
    /// Cayley transform: polynomial, no trigonometry.
    Cayley,
    /// Exponential map: singular at |x| = 2π.
    Exp,
}

/// A groupoid whose chart the SIMD lane solvers have in closed form
/// ([`crate::realization::Realization::lane_chart`]): the stepper picks its lane solver by this
/// value, never by the realization's type.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LaneChart {
    /// so(3)'s groupoid in the given chart ([`crate::lanes_bisection`]).
    So3(Chart),
    /// se(3)'s groupoid in the exponential chart ([`crate::lanes_bisection_se3`]).
    Se3Exp,
    /// Any other algebra's groupoid in the exponential chart, by its Bernoulli series
    /// ([`crate::lanes_bisection_series`]; the constants from
    /// [`crate::realization::Realization::lie_algebra`]).
    ExpSeries,
}

/// Largest |x| the exponential chart accepts: c(θ) has a pole at 2π.
pub const EXP_CHART_MAX_ANGLE: f64 = 2.0 * std::f64::consts::PI - 0.1;

/// Taylor coefficients of c(θ) = (1 − (θ/2)cot(θ/2))/θ² in s = θ²: |B₂ₙ|/(2n)!.
pub const C_SERIES: [f64; 12] = [
    1.0 / 12.0,
    1.0 / 720.0,
    1.0 / 30240.0,
    1.0 / 1209600.0,
    1.0 / 47900160.0,
    691.0 / 1307674368000.0,
    1.0 / 74724249600.0,
    3617.0 / 10670622842880000.0,
    43867.0 / 5109094217170944000.0,
    174611.0 / 802857662698291200000.0,
    77683.0 / 14101100039391805440000.0,
    236364091.0 / 1693824136731743669452800000.0,
];

/// c(s), c'(s), c''(s) for s = θ², the coefficient of x×(x×p) in the exponential chart.
#[cfg(test)]
fn exp_chart_coefficient(s: f64) -> (f64, f64, f64) {
    exp_chart_coefficient_to(s, 2)
}

/// [`exp_chart_coefficient`] up to the derivative `order` (0, 1 or 2); the derivatives beyond
/// it are returned as 0 and cost nothing. Each returned number has the bits of the full
/// evaluation: the Horner chains and closed forms are the same, only the unused ones are skipped.
#[inline(always)]
pub(crate) fn exp_chart_coefficient_to(s: f64, order: u8) -> (f64, f64, f64) {
    if s < 1.0 {
        // Series (radius 4π²): the closed form cancels catastrophically near 0.
        let (mut c, mut dc, mut d2c) = (0.0, 0.0, 0.0);
        for (n, &a) in C_SERIES.iter().enumerate().rev() {
            let n = n as f64;
            c = c * s + a;
            if order >= 1 && n >= 1.0 {
                dc = dc * s + n * a;
            }
            if order >= 2 && n >= 2.0 {
                d2c = d2c * s + n * (n - 1.0) * a;
            }
        }
        return (c, dc, d2c);
    }
    let th = s.sqrt();
    let (sn, cs) = (0.5 * th).sin_cos();
    let cot = cs / sn;
    let c = 1.0 / s - cot / (2.0 * th);
    if order == 0 {
        return (c, 0.0, 0.0);
    }
    let csc2 = 1.0 / (sn * sn);
    let c_th = -2.0 / (s * th) + cot / (2.0 * s) + csc2 / (4.0 * th);
    if order == 1 {
        return (c, c_th / (2.0 * th), 0.0);
    }
    let c_thth = 6.0 / (s * s) - cot / (s * th) - csc2 / (2.0 * s) - csc2 * cot / (4.0 * th);
    (c, c_th / (2.0 * th), (c_thth - c_th / th) / (4.0 * s))
}

/// c'(s), c''(s) and c'''(s) of [`exp_chart_coefficient_to`]'s c, up to the derivative `order`
/// of c' (0, 1 or 2; the rest returned as 0): the coefficient the se(3) chart's translation
/// block carries ([`se3_chart`]). Series below s = 1, as c's; above, the θ-derivatives of the
/// closed form taken to s = θ².
#[inline(always)]
pub(crate) fn exp_chart_coefficient_derivatives_to(s: f64, order: u8) -> (f64, f64, f64) {
    if s < 1.0 {
        let (mut d1, mut d2, mut d3) = (0.0, 0.0, 0.0);
        for (n, &a) in C_SERIES.iter().enumerate().rev() {
            let n = n as f64;
            if n >= 1.0 {
                d1 = d1 * s + n * a;
            }
            if order >= 1 && n >= 2.0 {
                d2 = d2 * s + n * (n - 1.0) * a;
            }
            if order >= 2 && n >= 3.0 {
                d3 = d3 * s + n * (n - 1.0) * (n - 2.0) * a;
            }
        }
        return (d1, d2, d3);
    }
    let th = s.sqrt();
    let (sn, cs) = (0.5 * th).sin_cos();
    let cot = cs / sn;
    let csc2 = 1.0 / (sn * sn);
    let c_th = -2.0 / (s * th) + cot / (2.0 * s) + csc2 / (4.0 * th);
    let d1 = c_th / (2.0 * th);
    if order == 0 {
        return (d1, 0.0, 0.0);
    }
    let c_thth = 6.0 / (s * s) - cot / (s * th) - csc2 / (2.0 * s) - csc2 * cot / (4.0 * th);
    let d2 = (c_thth - c_th / th) / (4.0 * s);
    if order == 1 {
        return (d1, d2, 0.0);
    }
    let c_ththth = -24.0 / (s * s * th)
        + 3.0 * cot / (s * s)
        + 1.5 * csc2 / (s * th)
        + 0.75 * csc2 * cot / s
        + (csc2 * cot * cot + 0.5 * csc2 * csc2) / (4.0 * th);
    (
        d1,
        d2,
        (c_ththth - 3.0 * c_thth / th + 3.0 * c_th / s) / (8.0 * s * th),
    )
}

/// (−1)ⁿ/(2n+1)! and (−1)ⁿ/(2n+2)!, n = 0 … 9: the series of sin θ/θ and (1 − cos θ)/θ² in
/// s = θ², summed below s = 1 (the tenth terms are below 2e-20 there).
pub const SIN_SERIES: [f64; 10] = [
    1.0,
    -1.0 / 6.0,
    1.0 / 120.0,
    -1.0 / 5040.0,
    1.0 / 362880.0,
    -1.0 / 39916800.0,
    1.0 / 6227020800.0,
    -1.0 / 1307674368000.0,
    1.0 / 355687428096000.0,
    -1.0 / 121645100408832000.0,
];
pub const COS_SERIES: [f64; 10] = [
    1.0 / 2.0,
    -1.0 / 24.0,
    1.0 / 720.0,
    -1.0 / 40320.0,
    1.0 / 3628800.0,
    -1.0 / 479001600.0,
    1.0 / 87178291200.0,
    -1.0 / 20922789888000.0,
    1.0 / 6402373705728000.0,
    -1.0 / 2432902008176640000.0,
];

/// (sin θ/θ, (1 − cos θ)/θ²) at s = θ²: Rodrigues' coefficients of exp(x̂). Series below s = 1,
/// half-angle closed forms above (2 sin(θ/2) cos(θ/2)/θ and 2 sin²(θ/2)/θ², which do not cancel
/// near θ = 2π as 1 − cos θ would).
#[inline(always)]
pub(crate) fn rodrigues_coefficients(s: f64) -> (f64, f64) {
    if s < 1.0 {
        let (mut a, mut b) = (0.0, 0.0);
        for (&u, &v) in SIN_SERIES.iter().zip(&COS_SERIES).rev() {
            a = a * s + u;
            b = b * s + v;
        }
        return (a, b);
    }
    let th = s.sqrt();
    let (sn, cs) = (0.5 * th).sin_cos();
    (2.0 * sn * cs / th, 2.0 * sn * sn / s)
}

/// The s-derivatives (a'(s), b'(s)) of [`rodrigues_coefficients`]: series below s = 1, the
/// half-angle closed forms above (a = sin θ/θ, b = 2 sin²(θ/2)/θ², θ = √s).
#[inline(always)]
pub(crate) fn rodrigues_derivatives(s: f64) -> (f64, f64) {
    if s < 1.0 {
        let (mut a, mut b) = (0.0, 0.0);
        for (n, (&u, &v)) in SIN_SERIES.iter().zip(&COS_SERIES).enumerate().rev() {
            if n == 0 {
                break;
            }
            let n = n as f64;
            a = a * s + n * u;
            b = b * s + n * v;
        }
        return (a, b);
    }
    let th = s.sqrt();
    let (sn, cs) = (0.5 * th).sin_cos();
    // d/dθ (sin θ/θ) = (θ cos θ − sin θ)/θ², d/dθ (2 sin²(θ/2)/θ²) = (θ sin θ − 4 sin²(θ/2))/θ³,
    // and d/ds = d/dθ / (2θ).
    let (sin, cos) = (2.0 * sn * cs, cs * cs - sn * sn);
    (
        (th * cos - sin) / (2.0 * s * th),
        (th * sin - 4.0 * sn * sn) / (2.0 * s * s),
    )
}

/// The se(3) exponential chart in closed form: sou (`sign` = +1) or tar (−1) of x = (ω, v) ∈
/// se(3) at p = (p_R, p_T) ∈ se(3)*. ad_xᵀ is block upper triangular, [[W(ω), W(v)], [0,
/// W(ω)]] with W(y) so(3)'s ad_yᵀ, so the Bernoulli series f(ad_xᵀ) is [[f(W(ω)),
/// Df(W(ω))[W(v)]], [0, f(W(ω))]]: so(3)'s chart on each block, plus its derivative along v,
///
///   Df[v] q = ±½ v×q + 2c'(|ω|²)(ω·v) ω×(ω×q) + c(|ω|²)(v×(ω×q) + ω×(v×q)).
///
/// The map of [`Groupoid::exp_series`] (its singular set |ω| ≥ 2π included: the eigenvalues of
/// ad_x are ω's), without its 20-odd dense 6×6 products.
#[inline(always)]
fn se3_chart<T: Scalar>(x: &[T; 6], p: &[T; 6], sign: f64) -> Result<[T; 6], StepFailure> {
    let w = [x[0], x[1], x[2]];
    let v = [x[3], x[4], x[5]];
    let pr = [p[0], p[1], p[2]];
    let pt = [p[3], p[4], p[5]];
    let s = dot(&w, &w);
    if s.value() >= EXP_CHART_MAX_ANGLE * EXP_CHART_MAX_ANGLE {
        return Err(StepFailure::ChartSingular);
    }
    let (c, dc, d2c) = exp_chart_coefficient_to(s.value(), T::ORDER);
    let (e1, e2, e3) = exp_chart_coefficient_derivatives_to(s.value(), T::ORDER);
    let c = s.chain(c, dc, d2c);
    let c1 = s.chain(e1, e2, e3);
    let half = 0.5 * sign;
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
    Ok(out)
}

/// The coadjoint action of exp(x), x = (ω, v) ∈ se(3), on μ = (M, Γ) in closed form:
/// e^{−ad_xᵀ} = [[E, DE[v]], [0, E]] with E q = q + a ω×q + b ω×(ω×q) (Rodrigues, so(3)'s
/// [`Chart::rotate`]) and DE[v] its derivative along v. Keeps |Γ|² and M·Γ up to rounding, as a
/// rotation keeps |μ|² on so(3)*: the corrections are added to μ last.
#[inline(always)]
pub(crate) fn se3_coadjoint(x: &[f64; 6], mu: &[f64; 6]) -> Result<[f64; 6], StepFailure> {
    let w = [x[0], x[1], x[2]];
    let v = [x[3], x[4], x[5]];
    let m = [mu[0], mu[1], mu[2]];
    let g = [mu[3], mu[4], mu[5]];
    let s = dot(&w, &w);
    if s >= EXP_CHART_MAX_ANGLE * EXP_CHART_MAX_ANGLE {
        return Err(StepFailure::ChartSingular);
    }
    let (a, b) = rodrigues_coefficients(s);
    let (da, db) = rodrigues_derivatives(s);
    let k = 2.0 * dot(&w, &v);
    let (wm, wg, vg) = (cross(&w, &m), cross(&w, &g), cross(&v, &g));
    let (wwm, wwg) = (cross(&w, &wm), cross(&w, &wg));
    let (vwg, wvg) = (cross(&v, &wg), cross(&w, &vg));
    let mut out = [0.0; 6];
    for i in 0..3 {
        let d = k * da * wg[i] + a * vg[i] + k * db * wwg[i] + b * (vwg[i] + wvg[i]);
        out[i] = m[i] + ((a * wm[i] + b * wwm[i]) + d);
        out[3 + i] = g[i] + (a * wg[i] + b * wwg[i]);
    }
    if !out.iter().all(|v| v.is_finite()) {
        return Err(StepFailure::NonFinite);
    }
    Ok(out)
}

#[inline(always)]
fn cross<T: Scalar>(a: &[T; 3], b: &[T; 3]) -> [T; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[inline(always)]
fn dot<T: Scalar>(a: &[T; 3], b: &[T; 3]) -> T {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

impl Chart {
    pub fn name(self) -> &'static str {
        match self {
            Chart::Cayley => "cayley",
            Chart::Exp => "exp",
        }
    }

    pub fn from_name(name: &str) -> Option<Chart> {
        match name {
            "cayley" => Some(Chart::Cayley),
            "exp" => Some(Chart::Exp),
            _ => None,
        }
    }

    /// The so(3) closed forms: sou(x,p) when `sign = +1`, tar(x,p) when `sign = −1`; the two
    /// differ only in the sign of the ½ x×p term.
    #[inline(always)]
    fn apply_so3<T: Scalar>(
        self,
        x: &[T; 3],
        p: &[T; 3],
        sign: f64,
    ) -> Result<[T; 3], StepFailure> {
        let xp = cross(x, p);
        let mut out = [p[0], p[1], p[2]];
        match self {
            Chart::Cayley => {
                // p ± ½ x×p + ¼ x (x·p)
                let q = dot(x, p).scale(0.25);
                for i in 0..3 {
                    out[i] = out[i] + xp[i].scale(0.5 * sign) + x[i] * q;
                }
            }
            Chart::Exp => {
                // p ± ½ x×p + c(|x|²) x×(x×p)
                let s = dot(x, x);
                if s.value() >= EXP_CHART_MAX_ANGLE * EXP_CHART_MAX_ANGLE {
                    return Err(StepFailure::ChartSingular);
                }
                let (c, dc, d2c) = exp_chart_coefficient_to(s.value(), T::ORDER);
                let c = s.chain(c, dc, d2c);
                let xxp = cross(x, &xp);
                for i in 0..3 {
                    out[i] = out[i] + xp[i].scale(0.5 * sign) + c * xxp[i];
                }
            }
        }
        Ok(out)
    }

    /// The rotation of this chart's group element g(x) applied to μ: sou(x, p) = R(x) tar(x, p)
    /// for every (x, p), so R(x) μ is the new state of a step that solved tar(x, p) = μ, on the
    /// sphere |μ| whatever the residual of the solve. Cayley: R = I + (x̂ + ½ x̂²)/(1 + |x|²/4);
    /// exp: Rodrigues, R = I + (sin θ/θ) x̂ + ((1 − cos θ)/θ²) x̂², θ = |x|.
    #[inline(always)]
    pub fn rotate(self, x: &[f64; 3], mu: &[f64; 3]) -> Result<[f64; 3], StepFailure> {
        let s = dot(x, x);
        if self == Chart::Exp && s >= EXP_CHART_MAX_ANGLE * EXP_CHART_MAX_ANGLE {
            return Err(StepFailure::ChartSingular);
        }
        let (a, b) = self.rotation_coefficients(s);
        let xm = cross(x, mu);
        let xxm = cross(x, &xm);
        Ok(std::array::from_fn(|i| mu[i] + (a * xm[i] + b * xxm[i])))
    }

    /// The coefficients (a, b) of [`Chart::rotate`], R = I + a x̂ + b x̂², at s = |x|².
    #[inline(always)]
    pub(crate) fn rotation_coefficients(self, s: f64) -> (f64, f64) {
        match self {
            Chart::Cayley => {
                let r = 1.0 / (1.0 + 0.25 * s);
                (r, 0.5 * r)
            }
            Chart::Exp => rodrigues_coefficients(s),
        }
    }

    /// Source map of so(3)*: the spatial momentum of the covector with coordinates (x, p).
    pub fn sou<T: Scalar>(self, x: &[T; 3], p: &[T; 3]) -> Result<[T; 3], StepFailure> {
        self.apply_so3(x, p, 1.0)
    }

    /// Target map of so(3)*: the body momentum of the covector with coordinates (x, p).
    pub fn tar<T: Scalar>(self, x: &[T; 3], p: &[T; 3]) -> Result<[T; 3], StepFailure> {
        self.apply_so3(x, p, -1.0)
    }
}

/// Most terms of the Bernoulli series summed before a step is refused as beyond the chart: the
/// terms shrink like (ρ/2π)ⁿ for ρ the spectral radius of ad_x, so this reaches round-off up to
/// ρ ≈ 0.85 · 2π.
pub const MAX_SERIES_TERMS: usize = 240;

/// Relative size below which [`Groupoid::coadjoint`] drops the tail of the exponential series:
/// far below round-off, so that the neglected terms (the same smooth function of the state at
/// every step) add up to nothing over 10⁹ steps.
pub(crate) const COADJOINT_TAIL: f64 = 1e-26;

/// Bₙ/n! for n = 0 … MAX_SERIES_TERMS (B₁ = −½, odd n > 1 vanish). B₂ₖ/(2k)! =
/// (−1)^{k+1} 2ζ(2k)/(2π)^{2k}; the first twelve are exact ratios (as in C_SERIES).
pub(crate) fn bernoulli_over_factorial() -> &'static [f64; MAX_SERIES_TERMS + 1] {
    static TABLE: OnceLock<[f64; MAX_SERIES_TERMS + 1]> = OnceLock::new();
    TABLE.get_or_init(|| {
        let mut b = [0.0; MAX_SERIES_TERMS + 1];
        b[0] = 1.0;
        b[1] = -0.5;
        let two_pi = 2.0 * std::f64::consts::PI;
        for k in 1..=MAX_SERIES_TERMS / 2 {
            let magnitude = match C_SERIES.get(k - 1) {
                Some(&c) => c,
                None => {
                    let zeta: f64 = (1..=12).map(|m| f64::from(m).powi(-2 * k as i32)).sum();
                    2.0 * zeta / two_pi.powi(2 * k as i32)
                }
            };
            b[2 * k] = if k % 2 == 1 { magnitude } else { -magnitude };
        }
        b
    })
}

/// A Lie algebra of dimension N by its structure constants, [e_i, e_j] = Σ_k c[i][j][k] e_k.
#[derive(Clone, Debug, PartialEq)]
pub struct LieAlgebra<const N: usize> {
    c: [[[f64; N]; N]; N],
    /// c is exactly the Levi-Civita symbol: so(3), with its closed-form charts.
    so3: bool,
    /// c is exactly [`LieAlgebra::se3`]'s: the exponential chart and the coadjoint action in
    /// closed form ([`se3_chart`], [`se3_coadjoint`]).
    se3: bool,
}

/// se(3)'s structure constants in the basis (R₁, R₂, R₃, T₁, T₂, T₃) (see [`LieAlgebra::se3`]).
fn se3_constant(i: usize, j: usize, k: usize) -> f64 {
    match (i < 3, j < 3, k < 3) {
        (true, true, true) => levi_civita(i, j, k),
        (true, false, false) => levi_civita(i, j - 3, k - 3),
        (false, true, false) => -levi_civita(j, i - 3, k - 3),
        _ => 0.0,
    }
}

impl LieAlgebra<6> {
    /// se(3) in the basis (R₁, R₂, R₃, T₁, T₂, T₃): [R_i, R_j] = ε_ijk R_k,
    /// [R_i, T_j] = ε_ijk T_k, [T_i, T_j] = 0 (the heavy top's algebra, μ = (M, Γ)).
    pub fn se3() -> Self {
        let c: [[[f64; 6]; 6]; 6] = std::array::from_fn(|i| {
            std::array::from_fn(|j| std::array::from_fn(|k| se3_constant(i, j, k)))
        });
        // Antisymmetric and Jacobi by construction: `new` cannot refuse it.
        match LieAlgebra::new(c) {
            Ok(a) => a,
            Err(_) => unreachable!("se(3) is a Lie algebra"),
        }
    }
}

impl<const N: usize> LieAlgebra<N> {
    /// Checks that every entry is finite, antisymmetry and the Jacobi identity, to a tolerance
    /// relative to max |c| (above 1). Both checks run on c / max(max |c|, 1), so the Jacobi sums
    /// (quadratic in c) cannot overflow and turn the check off, however large the constants.
    pub fn new(c: [[[f64; N]; N]; N]) -> Result<Self, CoreError> {
        let invalid = |m: String| Err(CoreError::Invalid(m));
        for i in 0..N {
            for j in 0..N {
                for k in 0..N {
                    if !c[i][j][k].is_finite() {
                        return invalid(format!(
                            "structure constants must be finite: c[{i},{j},{k}] = {}",
                            c[i][j][k]
                        ));
                    }
                }
            }
        }
        let scale = c
            .iter()
            .flatten()
            .flatten()
            .fold(0.0f64, |m, v| m.max(v.abs()))
            .max(1.0);
        // Finite entries of size at most 1: every sum below is finite, so `>` cannot miss a NaN.
        let u: [[[f64; N]; N]; N] = c.map(|a| a.map(|b| b.map(|v| v / scale)));
        let tol = 1e-12;
        for i in 0..N {
            for j in 0..N {
                for k in 0..N {
                    if (u[i][j][k] + u[j][i][k]).abs() > tol {
                        return invalid(format!(
                            "structure constants are not antisymmetric (c[i,j,k] = -c[j,i,k] \
                             fails): c[{i},{j},{k}] = {} but c[{j},{i},{k}] = {}",
                            c[i][j][k], c[j][i][k]
                        ));
                    }
                }
            }
        }
        // Jacobi: Σ_l c[i][j][l] c[l][k][m] + cyclic = 0, on the scaled constants.
        for i in 0..N {
            for j in 0..N {
                for k in 0..N {
                    for m in 0..N {
                        let s: f64 = (0..N)
                            .map(|l| {
                                u[i][j][l] * u[l][k][m]
                                    + u[j][k][l] * u[l][i][m]
                                    + u[k][i][l] * u[l][j][m]
                            })
                            .sum();
                        if s.abs() > tol {
                            return invalid(format!(
                                "structure constants violate the Jacobi identity at \
                                 (e{i}, e{j}, e{k}), component {m}: {:e}",
                                s * scale * scale
                            ));
                        }
                    }
                }
            }
        }
        let so3 = N == 3
            && (0..3).all(|i| (0..3).all(|j| (0..3).all(|k| c[i][j][k] == levi_civita(i, j, k))));
        let se3 = N == 6
            && (0..6).all(|i| (0..6).all(|j| (0..6).all(|k| c[i][j][k] == se3_constant(i, j, k))));
        Ok(LieAlgebra { c, so3, se3 })
    }

    /// so(3) when N = 3 (c = ε); an error for other N.
    pub fn so3() -> Result<Self, CoreError> {
        if N != 3 {
            return Err(CoreError::Invalid(format!(
                "so(3) has dimension 3, not {N}"
            )));
        }
        let mut c = [[[0.0; N]; N]; N];
        for (i, ci) in c.iter_mut().enumerate() {
            for (j, cij) in ci.iter_mut().enumerate() {
                for (k, v) in cij.iter_mut().enumerate() {
                    *v = levi_civita(i, j, k);
                }
            }
        }
        LieAlgebra::new(c)
    }

    pub fn structure_constants(&self) -> &[[[f64; N]; N]; N] {
        &self.c
    }

    pub fn is_so3(&self) -> bool {
        self.so3
    }

    /// Whether c is exactly [`LieAlgebra::se3`]'s (the closed-form chart applies).
    pub fn is_se3(&self) -> bool {
        self.se3
    }

    /// A v with A = ad_xᵀ: (A v)_j = Σ_{i,k} c[i][j][k] x_i v_k.
    #[inline]
    pub fn ad_transpose_apply<T: Scalar>(&self, x: &[T; N], v: &[T; N]) -> [T; N] {
        let a = self.ad_transpose(x);
        apply(&a, v)
    }

    /// e^{−A} μ with A = ad_xᵀ (the coadjoint action of exp(x) on μ), summed as Σ (−A)ⁿ μ / n!
    /// until the tail is below round-off: [`Groupoid::coadjoint`] on an algebra without a
    /// closed form.
    pub fn exp_coadjoint(&self, x: &[f64; N], mu: &[f64; N]) -> Result<[f64; N], StepFailure> {
        let a = self.ad_transpose(x);
        // ρ = ‖A‖∞ bounds ‖Aⁿ‖∞ by ρⁿ: the terms past K, Σ_{n>K} ρⁿ/n!, stay below
        // COADJOINT_TAIL · e^ρ relative to |μ|∞ once ρ^{K+1}/(K+1)! is.
        let rho = a
            .iter()
            .map(|row| row.iter().map(|v| v.abs()).sum::<f64>())
            .fold(0.0f64, f64::max);
        if !rho.is_finite() {
            return Err(StepFailure::NonFinite);
        }
        let mut k = 0;
        let mut bound = 1.0;
        while bound > COADJOINT_TAIL {
            k += 1;
            if k > MAX_SERIES_TERMS {
                return Err(StepFailure::ChartSingular);
            }
            bound *= rho / k as f64;
        }
        // Horner from the innermost term: w = μ, then w = μ − (A w)/n for n = K … 2, and
        // μ − A w. Every addition adds a correction far above μ's last bit, so its rounding has
        // no sign: summing the terms one after another from the largest would drop the sub-ulp
        // tail of every component the same way at every step, a bias on the Casimirs. (A
        // division, not a product by a rounded 1/n, for the same reason.)
        let mut w = *mu;
        for n in (2..=k).rev() {
            let n = n as f64;
            let aw = apply(&a, &w);
            w = std::array::from_fn(|i| mu[i] - aw[i] / n);
        }
        let out = {
            let aw = apply(&a, &w);
            std::array::from_fn(|i| mu[i] - aw[i])
        };
        if !out.iter().all(|v: &f64| v.is_finite()) {
            return Err(StepFailure::NonFinite);
        }
        Ok(out)
    }

    /// The matrix ad_xᵀ, (ad_xᵀ)_{jk} = Σ_i c[i][j][k] x_i.
    #[inline]
    fn ad_transpose<T: Scalar>(&self, x: &[T; N]) -> [[T; N]; N] {
        let mut a = [[T::cst(0.0); N]; N];
        for (i, xi) in x.iter().enumerate() {
            for j in 0..N {
                for k in 0..N {
                    let c = self.c[i][j][k];
                    if c != 0.0 {
                        a[j][k] = xi.mul_add(c, a[j][k]);
                    }
                }
            }
        }
        a
    }
}

fn levi_civita(i: usize, j: usize, k: usize) -> f64 {
    match (i, j, k) {
        (0, 1, 2) | (1, 2, 0) | (2, 0, 1) => 1.0,
        (0, 2, 1) | (2, 1, 0) | (1, 0, 2) => -1.0,
        _ => 0.0,
    }
}

#[inline(always)]
fn apply<T: Scalar, const N: usize>(a: &[[T; N]; N], v: &[T; N]) -> [T; N] {
    std::array::from_fn(|j| {
        let mut s = a[j][0] * v[0];
        for k in 1..N {
            s = s + a[j][k] * v[k];
        }
        s
    })
}

/// The groupoid T*G ⇉ g* in a chart: the source and target maps a bisection step needs.
#[derive(Clone, Debug, PartialEq)]
pub struct Groupoid<const N: usize> {
    pub algebra: LieAlgebra<N>,
    pub chart: Chart,
}

impl<const N: usize> Groupoid<N> {
    /// The lane solver's chart this groupoid is: so(3) in either chart and se(3) in the
    /// exponential one in closed form, any other algebra's exponential chart (the only chart it
    /// has) by its series.
    pub fn lane_chart(&self) -> Option<LaneChart> {
        if N == 3 && self.algebra.is_so3() {
            Some(LaneChart::So3(self.chart))
        } else if N == 6 && self.algebra.is_se3() && self.chart == Chart::Exp {
            Some(LaneChart::Se3Exp)
        } else if self.chart == Chart::Exp {
            Some(LaneChart::ExpSeries)
        } else {
            None
        }
    }

    /// The Cayley chart exists for so(3) only.
    pub fn new(algebra: LieAlgebra<N>, chart: Chart) -> Result<Self, CoreError> {
        if chart == Chart::Cayley && !algebra.is_so3() {
            return Err(CoreError::Invalid(
                "the Cayley chart is available for so(3) only; use the exp chart".into(),
            ));
        }
        Ok(Groupoid { algebra, chart })
    }

    /// so(3) in `chart` (N must be 3).
    pub fn so3(chart: Chart) -> Result<Self, CoreError> {
        Groupoid::new(LieAlgebra::so3()?, chart)
    }

    #[inline(always)]
    fn apply<T: Scalar>(&self, x: &[T; N], p: &[T; N], sign: f64) -> Result<[T; N], StepFailure> {
        if self.algebra.so3 {
            // N = 3 here; the conversions compile away.
            if let (Ok(x3), Ok(p3)) = (<&[T; 3]>::try_from(&x[..]), <&[T; 3]>::try_from(&p[..])) {
                let s = self.chart.apply_so3(x3, p3, sign)?;
                let mut out = *p;
                out.copy_from_slice(&s);
                return Ok(out);
            }
        }
        if self.algebra.se3 {
            // N = 6 here, and the chart is exp (Cayley is refused for any algebra but so(3)).
            if let (Ok(x6), Ok(p6)) = (<&[T; 6]>::try_from(&x[..]), <&[T; 6]>::try_from(&p[..])) {
                let s = se3_chart(x6, p6, sign)?;
                let mut out = *p;
                out.copy_from_slice(&s);
                return Ok(out);
            }
        }
        self.exp_series(x, p, sign)
    }

    /// Σ (Bₙ/n!) (sign · A)ⁿ p with A = ad_xᵀ, until two consecutive non-zero terms are below
    /// round-off in every component (value and derivatives).
    #[inline]
    pub(crate) fn exp_series<T: Scalar>(
        &self,
        x: &[T; N],
        p: &[T; N],
        sign: f64,
    ) -> Result<[T; N], StepFailure> {
        let b = bernoulli_over_factorial();
        let a = self.algebra.ad_transpose(x);
        let size = |v: &[T; N]| v.iter().fold(0.0f64, |m, t| m.max(t.max_abs()));
        let mut term = *p;
        let mut out = *p;
        let mut small = 0;
        for (n, &bn) in b.iter().enumerate().skip(1) {
            term = apply(&a, &term);
            if bn == 0.0 {
                continue;
            }
            let c = if n % 2 == 1 { sign * bn } else { bn };
            for (o, t) in out.iter_mut().zip(&term) {
                *o = t.mul_add(c, *o);
            }
            let t = size(&term) * bn.abs();
            if !t.is_finite() {
                return Err(StepFailure::NonFinite);
            }
            if t <= 1e-17 * size(&out) {
                small += 1;
                if small == 2 {
                    return Ok(out);
                }
            } else {
                small = 0;
            }
        }
        Err(StepFailure::ChartSingular)
    }

    /// The coadjoint action of the chart's group element g(x) on μ: sou(x, p) = coadjoint(x,
    /// tar(x, p)) for every (x, p). It maps μ onto its own coadjoint orbit, so every Casimir of
    /// the result is μ's up to the rounding of this evaluation (which has no sign), whatever x.
    /// so(3): the chart's rotation ([`Chart::rotate`]); any other algebra (exponential chart):
    /// e^{−A} μ with A = ad_xᵀ, summed as Σ (−A)ⁿ μ / n! until two consecutive non-zero terms are
    /// below round-off.
    pub fn coadjoint(&self, x: &[f64; N], mu: &[f64; N]) -> Result<[f64; N], StepFailure> {
        if self.algebra.so3 {
            if let (Ok(x3), Ok(m3)) = (
                <&[f64; 3]>::try_from(&x[..]),
                <&[f64; 3]>::try_from(&mu[..]),
            ) {
                let r = self.chart.rotate(x3, m3)?;
                let mut out = *mu;
                out.copy_from_slice(&r);
                return Ok(out);
            }
        }
        if self.algebra.se3 {
            if let (Ok(x6), Ok(m6)) = (
                <&[f64; 6]>::try_from(&x[..]),
                <&[f64; 6]>::try_from(&mu[..]),
            ) {
                let r = se3_coadjoint(x6, m6)?;
                let mut out = *mu;
                out.copy_from_slice(&r);
                return Ok(out);
            }
        }
        self.algebra.exp_coadjoint(x, mu)
    }

    /// Source map: the momentum sou(x, p) ∈ g*.
    pub fn sou<T: Scalar>(&self, x: &[T; N], p: &[T; N]) -> Result<[T; N], StepFailure> {
        self.apply(x, p, 1.0)
    }

    /// Target map: the momentum tar(x, p) ∈ g*.
    pub fn tar<T: Scalar>(&self, x: &[T; N], p: &[T; N]) -> Result<[T; N], StepFailure> {
        self.apply(x, p, -1.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dual::Dual1;

    fn norm(a: &[f64; 3]) -> f64 {
        dot(a, a).sqrt()
    }

    #[test]
    fn algebra_check_refuses_nan_and_keeps_jacobi_for_huge_constants() {
        let mut c = [[[0.0; 3]; 3]; 3];
        for (i, j, k) in [(0, 1, 2), (1, 2, 0), (2, 0, 1)] {
            c[i][j][k] = 1.0;
            c[j][i][k] = -1.0;
        }
        let mut nan = c;
        nan[0][0][0] = f64::NAN;
        assert!(LieAlgebra::<3>::new(nan).is_err());
        // so(3) scaled by 1e200 is a Lie algebra; adding a non-Jacobi entry of that size is not.
        let big = c.map(|a| a.map(|b| b.map(|v| v * 1e200)));
        assert!(LieAlgebra::<3>::new(big).is_ok());
        let mut bad = big;
        bad[0][1][0] = 1e200;
        bad[1][0][0] = -1e200;
        assert!(LieAlgebra::<3>::new(bad).is_err());
    }

    #[test]
    fn units_are_the_identity() {
        let p = [0.3, -1.2, 2.0];
        for chart in [Chart::Cayley, Chart::Exp] {
            assert_eq!(chart.sou(&[0.0; 3], &p).unwrap(), p);
            assert_eq!(chart.tar(&[0.0; 3], &p).unwrap(), p);
        }
    }

    #[test]
    fn source_and_target_have_equal_norms() {
        let p = [0.3, -1.2, 2.0];
        for chart in [Chart::Cayley, Chart::Exp] {
            for x in [[0.01, 0.02, -0.03], [0.4, -0.9, 0.3], [1.5, 2.0, -2.5]] {
                let (s, t) = (chart.sou(&x, &p).unwrap(), chart.tar(&x, &p).unwrap());
                assert!(
                    (norm(&s) - norm(&t)).abs() < 1e-14 * norm(&p),
                    "{chart:?} {x:?}"
                );
            }
        }
    }

    #[test]
    fn series_and_closed_form_agree_at_the_switch() {
        let (a, da, d2a) = exp_chart_coefficient(1.0 - 1e-12);
        let (b, db, d2b) = exp_chart_coefficient(1.0 + 1e-12);
        assert!((a - b).abs() < 1e-14);
        assert!((da - db).abs() < 1e-12);
        assert!((d2a - d2b).abs() < 1e-9);
        // θ = π: c = 1/π².
        let (c, _, _) = exp_chart_coefficient(std::f64::consts::PI.powi(2));
        assert!((c - 1.0 / std::f64::consts::PI.powi(2)).abs() < 1e-15);
    }

    /// The closed-form derivative of c against the series one on either side of the switch:
    /// they are independent formulas.
    #[test]
    fn exp_chart_jacobian_matches_dual_derivative_of_components() {
        let x = [0.5, -0.4, 0.9];
        let p = [1.0, 2.0, -0.5];
        let xd: [Dual1<3>; 3] = [
            Dual1::var(x[0], 0),
            Dual1::var(x[1], 1),
            Dual1::var(x[2], 2),
        ];
        let pd = p.map(Dual1::cst);
        let s = Chart::Exp.sou(&xd, &pd).unwrap();
        // Compare with a second independent evaluation: central differences on exact arithmetic
        // are not exact, so use a tight step and a loose-enough bound only as a sanity check.
        let h = 1e-6;
        for j in 0..3 {
            let mut xp = x;
            let mut xm = x;
            xp[j] += h;
            xm[j] -= h;
            let sp = Chart::Exp.sou(&xp, &p).unwrap();
            let sm = Chart::Exp.sou(&xm, &p).unwrap();
            for i in 0..3 {
                let fd = (sp[i] - sm[i]) / (2.0 * h);
                assert!((s[i].g[j] - fd).abs() < 1e-8, "d sou_{i}/d x_{j}");
            }
        }
    }

    /// The value-only and first-order evaluations give the full one's numbers bit for bit, on
    /// both sides of the switch from the series to the closed form.
    #[test]
    fn truncated_chart_coefficient_equals_the_full_one() {
        let mut s = 1e-6;
        while s < 38.0 {
            let (c, dc, d2c) = exp_chart_coefficient(s);
            assert_eq!(exp_chart_coefficient_to(s, 0), (c, 0.0, 0.0), "s = {s}");
            assert_eq!(exp_chart_coefficient_to(s, 1), (c, dc, 0.0), "s = {s}");
            assert_eq!(exp_chart_coefficient_to(s, 2), (c, dc, d2c), "s = {s}");
            s *= 1.07;
        }
        // The chart in f64 keeps the value of its Dual1 evaluation.
        let (x, p) = ([0.9, -1.1, 0.7], [1.0, 2.0, -0.5]);
        let xd = x.map(Dual1::<3>::cst);
        let pd = p.map(Dual1::<3>::cst);
        let (a, b) = (
            Chart::Exp.tar(&x, &p).unwrap(),
            Chart::Exp.tar(&xd, &pd).unwrap(),
        );
        assert_eq!(a, b.map(|v| v.v));
    }

    /// se(3) with its closed forms turned off: the Bernoulli and exponential series of any
    /// algebra, the independent oracle of [`se3_chart`] and [`se3_coadjoint`].
    fn se3_by_series() -> Groupoid<6> {
        let closed = LieAlgebra::se3();
        assert!(closed.se3 && !closed.so3);
        let algebra = LieAlgebra {
            c: closed.c,
            so3: false,
            se3: false,
        };
        Groupoid {
            algebra,
            chart: Chart::Exp,
        }
    }

    /// Seeded (x, p) pairs with |ω| from 1e-4 to 6 (across the switch s = 1 and near the pole).
    fn se3_points() -> Vec<([f64; 6], [f64; 6])> {
        let mut state = 0x9e37_79b9_7f4a_7c15_u64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        };
        let mut out = Vec::new();
        for &r in &[1e-4, 0.05, 0.3, 0.99, 1.01, 2.0, 3.5, 5.0, 6.0] {
            for _ in 0..4 {
                let w: [f64; 3] = std::array::from_fn(|_| next());
                let n = norm(&w);
                let x = [
                    w[0] / n * r,
                    w[1] / n * r,
                    w[2] / n * r,
                    next(),
                    next(),
                    next(),
                ];
                out.push((x, std::array::from_fn(|_| 2.0 * next())));
            }
        }
        out
    }

    #[test]
    fn se3_chart_in_closed_form_is_the_bernoulli_series_with_its_derivatives() {
        let closed = Groupoid::new(LieAlgebra::se3(), Chart::Exp).unwrap();
        let series = se3_by_series();
        for (x, p) in se3_points() {
            // Derivatives in all twelve inputs: x and p.
            let xd: [Dual1<12>; 6] = std::array::from_fn(|i| Dual1::var(x[i], i));
            let pd: [Dual1<12>; 6] = std::array::from_fn(|i| Dual1::var(p[i], 6 + i));
            // The series' own rounding grows with |ω| (a sum of terms up to e^{|ω|} in size).
            let scale = (1.0 + norm(&[x[0], x[1], x[2]])).powi(4);
            for sign in [1.0, -1.0] {
                let a = closed.apply(&xd, &pd, sign).unwrap();
                // The series converges too slowly near its radius |ω| = 2π to be summed there;
                // sou = Ad*(tar) checks the closed form out to 6 (the coadjoint test).
                let Ok(b) = series.apply(&xd, &pd, sign) else {
                    assert!(norm(&[x[0], x[1], x[2]]) > 4.0, "{x:?}");
                    continue;
                };
                for i in 0..6 {
                    let (u, w) = (a[i].v, b[i].v);
                    assert!((u - w).abs() <= 1e-14 * scale, "{x:?} {sign} {i}: {u} {w}");
                    for j in 0..12 {
                        let (u, w) = (a[i].g[j], b[i].g[j]);
                        assert!((u - w).abs() <= 1e-13 * scale, "{x:?} d{i}/d{j}: {u} {w}");
                    }
                }
                // f64 keeps the Dual1 evaluation's value.
                assert_eq!(closed.apply(&x, &p, sign).unwrap(), a.map(|v| v.v));
            }
        }
        let x = [0.0, 0.0, 2.0 * std::f64::consts::PI, 1.0, 0.0, 0.0];
        assert_eq!(closed.sou(&x, &[1.0; 6]), Err(StepFailure::ChartSingular));
        assert_eq!(
            closed.coadjoint(&x, &[1.0; 6]),
            Err(StepFailure::ChartSingular)
        );
    }

    #[test]
    fn se3_coadjoint_in_closed_form_is_the_series_and_keeps_both_casimirs() {
        let closed = Groupoid::new(LieAlgebra::se3(), Chart::Exp).unwrap();
        let series = se3_by_series();
        let gg = |m: &[f64; 6]| m[3] * m[3] + m[4] * m[4] + m[5] * m[5];
        let mg = |m: &[f64; 6]| m[0] * m[3] + m[1] * m[4] + m[2] * m[5];
        for (x, mu) in se3_points() {
            let a = closed.coadjoint(&x, &mu).unwrap();
            let b = series.coadjoint(&x, &mu).unwrap();
            let size = (1.0 + x.iter().map(|v| v.abs()).sum::<f64>()).powi(2);
            for i in 0..6 {
                assert!(
                    (a[i] - b[i]).abs() <= 1e-14 * size,
                    "{x:?} {i}: {} {}",
                    a[i],
                    b[i]
                );
            }
            assert!((gg(&a) - gg(&mu)).abs() <= 1e-14 * size, "{x:?} |Γ|²");
            assert!((mg(&a) - mg(&mu)).abs() <= 1e-14 * size, "{x:?} M·Γ");
            // sou(x, p) = coadjoint(x, tar(x, p)) on the closed forms too.
            let t = closed.tar(&x, &mu).unwrap();
            let (s, c) = (
                closed.sou(&x, &mu).unwrap(),
                closed.coadjoint(&x, &t).unwrap(),
            );
            for i in 0..6 {
                assert!(
                    (s[i] - c[i]).abs() <= 1e-13 * size,
                    "{x:?} sou = Ad* tar, {i}"
                );
            }
        }
    }

    /// The derivative coefficients against central differences of the lower ones (independent
    /// formulas: series below s = 1, closed forms above), across the switch.
    #[test]
    fn chart_and_rodrigues_derivative_coefficients_are_the_derivatives() {
        for &s in &[1e-3, 0.2, 0.7, 0.999, 1.001, 1.5, 4.0, 10.0, 25.0, 37.0] {
            let e: f64 = 1e-5 * f64::max(s, 0.01);
            let (d1, d2, d3) = exp_chart_coefficient_derivatives_to(s, 2);
            let (cp, dp, d2p) = exp_chart_coefficient_to(s + e, 2);
            let (cm, dm, d2m) = exp_chart_coefficient_to(s - e, 2);
            let (_, dc, d2c) = exp_chart_coefficient_to(s, 2);
            assert_eq!((d1, d2), (dc, d2c), "s = {s}");
            let rel = |a: f64, b: f64| (a - b).abs() / b.abs().max(1e-3);
            assert!(
                rel((cp - cm) / (2.0 * e), d1) < 1e-7,
                "first derivative at {s}"
            );
            assert!(
                rel((dp - dm) / (2.0 * e), d2) < 1e-6,
                "second derivative at {s}"
            );
            assert!(
                rel((d2p - d2m) / (2.0 * e), d3) < 1e-5,
                "third derivative at {s}"
            );
            let (da, db) = rodrigues_derivatives(s);
            let (ap, bp) = rodrigues_coefficients(s + e);
            let (am, bm) = rodrigues_coefficients(s - e);
            assert!(rel((ap - am) / (2.0 * e), da) < 1e-7, "a' at {s}");
            assert!(rel((bp - bm) / (2.0 * e), db) < 1e-7, "b' at {s}");
        }
    }

    #[test]
    fn exp_chart_refuses_the_singular_angle() {
        let x = [0.0, 0.0, 2.0 * std::f64::consts::PI];
        assert_eq!(
            Chart::Exp.sou(&x, &[1.0, 0.0, 0.0]),
            Err(StepFailure::ChartSingular)
        );
    }
}

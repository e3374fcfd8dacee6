//! The log-canonical structure c as a realization (the linear groupoid in q = ln x), and a
//! system on it: c with a log-polynomial Hamiltonian.

// Index loops over small fixed-size vectors and matrices read as the formulas they implement.
#![allow(clippy::needless_range_loop)]

use super::pow_lanes;
use crate::dual::Scalar;
use crate::error::{CoreError, StepFailure};
use crate::realization::Realization;

/// The structure matrix c of π_ij = c_ij x_i x_j: finite and antisymmetric.
#[derive(Clone, Debug, PartialEq)]
pub struct LogCanonical<const N: usize> {
    c: [[f64; N]; N],
}

impl<const N: usize> LogCanonical<N> {
    pub fn new(c: [[f64; N]; N]) -> Result<Self, CoreError> {
        for i in 0..N {
            for j in 0..N {
                if !c[i][j].is_finite() || c[i][j] != -c[j][i] {
                    return Err(CoreError::Invalid(format!(
                        "c must be finite and antisymmetric: c[{i}][{j}] = {}, c[{j}][{i}] = {}",
                        c[i][j], c[j][i]
                    )));
                }
            }
        }
        Ok(LogCanonical { c })
    }

    pub fn c(&self) -> &[[f64; N]; N] {
        &self.c
    }

    /// q ± ½ c P.
    #[inline(always)]
    fn shift<T: Scalar>(&self, x: &[T; N], p: &[T; N], sign: f64) -> [T; N] {
        std::array::from_fn(|i| {
            let mut acc = p[i];
            for j in 0..N {
                if self.c[i][j] != 0.0 {
                    acc.add_scaled(&x[j], 0.5 * sign * self.c[i][j]);
                }
            }
            acc
        })
    }
}

/// In log coordinates: fibre x = P, base p = q.
impl<const N: usize> Realization<N> for LogCanonical<N> {
    #[inline]
    fn sou<T: Scalar>(&self, x: &[T; N], p: &[T; N]) -> Result<[T; N], StepFailure> {
        Ok(self.shift(x, p, -1.0))
    }
    #[inline]
    fn tar<T: Scalar>(&self, x: &[T; N], p: &[T; N]) -> Result<[T; N], StepFailure> {
        Ok(self.shift(x, p, 1.0))
    }
    /// sou = tar − c P, so q_{k+1} = q_k − c P: k·q is kept for every k with kᵀc = 0 whatever
    /// Newton's residual (which sou(P, q) would carry into the Casimirs, one-sided from step to
    /// step).
    #[inline]
    fn sou_after_solve(
        &self,
        x: &[f64; N],
        _p: &[f64; N],
        target: &[f64; N],
    ) -> Result<[f64; N], StepFailure> {
        Ok(std::array::from_fn(|i| {
            let mut acc = target[i];
            for j in 0..N {
                acc -= self.c[i][j] * x[j];
            }
            acc
        }))
    }
    #[inline]
    fn predicts(&self) -> bool {
        true
    }
    /// tar(x, p) = p + ½ c x exactly, and x = ∂S/∂p = O(h): p₀ = q_k − ½ c x₀ with
    /// x₀ = ∂S/∂p(h, q_k) is O(h²) from the solution where q_k is O(h) away, which saves
    /// Newton about one update a step for one gradient of S. Only where the shift is at most
    /// [`PREDICT_MAX_SHIFT`] in every coordinate (a step far too large for the series can
    /// otherwise throw the start where e^p overflows) and p₀ is finite.
    /// (The lane solve computes the same start with its own multiply-adds.)
    #[inline]
    fn predict(&self, x0: &[f64; N], target: &[f64; N]) -> Option<[f64; N]> {
        let mut p0 = *target;
        for i in 0..N {
            let mut shift = 0.0;
            for k in 0..N {
                shift += 0.5 * self.c[i][k] * x0[k];
            }
            // A NaN shift fails the comparison and predicts nothing.
            if shift.is_nan() || shift.abs() > PREDICT_MAX_SHIFT {
                return None;
            }
            p0[i] -= shift;
        }
        p0.iter().all(|v| v.is_finite()).then_some(p0)
    }
}

/// Largest |p₀ − q_k| (in ln x: a factor e in x) at which [`Realization::predict`] starts the
/// log-canonical Newton solve.
pub const PREDICT_MAX_SHIFT: f64 = 1.0;

/// A log-canonical system: the structure c and H = Σ_m a_m x^{e_m} − Σ_i b_i ln x_i
/// (exponents ≥ 0), ẋ_i = x_i Σ_j c_ij (x_j ∂H/∂x_j) = x_i Σ_j c_ij (Σ_m a_m e_mj x^{e_m} − b_j).
#[derive(Clone, Debug, PartialEq)]
pub struct LogSystem<const N: usize> {
    pub structure: LogCanonical<N>,
    terms: Vec<([u32; N], f64)>,
    pub(super) b: [f64; N],
    /// a where H = Σ a_i x_i − b_i ln x_i, one linear term a variable (Lotka–Volterra's form):
    /// RK4's field is then straight-line code ([`linear_field_lanes`]).
    linear: Option<[f64; N]>,
}

/// a where `terms` are exactly one a_i x_i for every variable i (in any order), else None.
fn linear_coefficients<const N: usize>(terms: &[([u32; N], f64)]) -> Option<[f64; N]> {
    let mut a = [None; N];
    for (e, c) in terms {
        let mut nonzero = e.iter().enumerate().filter(|(_, &k)| k > 0);
        let (i, &k) = nonzero.next()?;
        if k != 1 || nonzero.next().is_some() || a[i].replace(*c).is_some() {
            return None;
        }
    }
    let mut out = [0.0; N];
    for (o, v) in out.iter_mut().zip(a) {
        *o = v?;
    }
    Some(out)
}

/// Largest exponent of a Hamiltonian monomial.
pub const MAX_HAMILTONIAN_EXPONENT: u32 = 16;

impl<const N: usize> LogSystem<N> {
    pub fn new(
        structure: LogCanonical<N>,
        terms: Vec<([u32; N], f64)>,
        b: [f64; N],
    ) -> Result<Self, CoreError> {
        if let Some((e, a)) = terms.iter().find(|(e, a)| {
            !a.is_finite()
                || e.iter().any(|&k| k > MAX_HAMILTONIAN_EXPONENT)
                || e.iter().all(|&k| k == 0)
        }) {
            return Err(CoreError::Invalid(format!(
                "Hamiltonian term {a} x^{e:?} needs a finite coefficient and exponents in \
                 0..={MAX_HAMILTONIAN_EXPONENT}, not all zero"
            )));
        }
        if b.iter().any(|v| !v.is_finite()) {
            return Err(CoreError::Invalid("b must be finite".into()));
        }
        let linear = linear_coefficients(&terms);
        Ok(LogSystem {
            structure,
            terms,
            b,
            linear,
        })
    }

    /// x_j ∂H/∂x_j = ∂H/∂q_j, a polynomial in x.
    #[inline]
    fn log_gradient<T: Scalar>(&self, x: &[T; N]) -> [T; N] {
        let mut g: [T; N] = std::array::from_fn(|j| T::cst(-self.b[j]));
        for (e, a) in &self.terms {
            let mut m = T::cst(*a);
            for i in 0..N {
                if e[i] > 0 {
                    m = m * x[i].powi(e[i] as i32);
                }
            }
            for j in 0..N {
                if e[j] > 0 {
                    g[j].add_scaled(&m, f64::from(e[j]));
                }
            }
        }
        g
    }

    /// ẋ = π(x)∇H(x), for any scalar.
    pub fn vector_field<T: Scalar>(&self, x: &[T; N]) -> [T; N] {
        let g = self.log_gradient(x);
        let c = self.structure.c();
        std::array::from_fn(|i| {
            let mut acc = T::cst(0.0);
            for j in 0..N {
                if c[i][j] != 0.0 {
                    acc.add_scaled(&g[j], c[i][j]);
                }
            }
            x[i] * acc
        })
    }

    /// [`LogSystem::vector_field`] at L states, lane by lane: the explicit steppers' field
    /// (RK4 takes it for one trajectory too, with L = 1, so every lane has the scalar bits).
    #[inline(always)]
    pub(super) fn field_lanes<const L: usize>(&self, x: &[[f64; L]; N], out: &mut [[f64; L]; N]) {
        let mut g: [[f64; L]; N] = std::array::from_fn(|j| [-self.b[j]; L]);
        for (e, a) in &self.terms {
            add_monomial_gradient(&mut g, e, &monomial_lanes(e, *a, x));
        }
        for i in 0..N {
            let acc = self.c_row_lanes(i, &g);
            for l in 0..L {
                out[i][l] = x[i][l] * acc[l];
            }
        }
    }

    /// The coefficients a of a linear H, Σ a_i x_i − b_i ln x_i with one term a variable
    /// ([`linear_field_lanes`]), if H is one.
    #[inline(always)]
    pub fn linear(&self) -> Option<&[f64; N]> {
        self.linear.as_ref()
    }

    /// ∂f/∂x at L states (`out[i][k][l]`), lane by lane in closed form: with g_j = x_j ∂H/∂x_j,
    /// ∂f_i/∂x_k = δ_ik (c g)_i + x_i Σ_j c_ij ∂g_j/∂x_k and ∂g_j/∂x_k = Σ_m a_m e_mj e_mk
    /// x^{e_m − 1_k}.
    #[inline(always)]
    pub(super) fn jacobian_in_lanes<const L: usize>(
        &self,
        x: &[[f64; L]; N],
        out: &mut [[[f64; L]; N]; N],
    ) {
        let mut g: [[f64; L]; N] = std::array::from_fn(|j| [-self.b[j]; L]);
        // dg[k][j] = ∂g_j/∂x_k.
        let mut dg = [[[0.0; L]; N]; N];
        for (e, a) in &self.terms {
            add_monomial_gradient(&mut g, e, &monomial_lanes(e, *a, x));
            for k in (0..N).filter(|&k| e[k] > 0) {
                // a e_k x^{e − 1_k}, without dividing by x_k (which may be 0).
                let mut lowered = *e;
                lowered[k] -= 1;
                let d = monomial_lanes(&lowered, *a * f64::from(e[k]), x);
                add_monomial_gradient(&mut dg[k], e, &d);
            }
        }
        for i in 0..N {
            for k in 0..N {
                let acc = self.c_row_lanes(i, &dg[k]);
                for l in 0..L {
                    out[i][k][l] = x[i][l] * acc[l];
                }
            }
            let cg = self.c_row_lanes(i, &g);
            for l in 0..L {
                out[i][i][l] += cg[l];
            }
        }
    }

    /// (c v)_i at L lanes, the zero entries of c skipped.
    #[inline(always)]
    fn c_row_lanes<const L: usize>(&self, i: usize, v: &[[f64; L]; N]) -> [f64; L] {
        let c = self.structure.c();
        let mut acc = [0.0; L];
        for j in 0..N {
            if c[i][j] != 0.0 {
                for l in 0..L {
                    acc[l] += v[j][l] * c[i][j];
                }
            }
        }
        acc
    }

    /// H' of the one-variable parts: the flow of H_i(q_i) = Σ_{m ∈ i} a_m e^{e_mi q_i} − b_i q_i
    /// is q_j += t c_ji H_i'(q_i) (q_i fixed since c_ii = 0). None unless H is separable (every
    /// monomial in one variable).
    pub(super) fn separable(&self) -> Option<Vec<(usize, u32, f64)>> {
        let mut parts = Vec::with_capacity(self.terms.len());
        for (e, a) in &self.terms {
            let vars: Vec<usize> = (0..N).filter(|&i| e[i] > 0).collect();
            if vars.len() != 1 {
                return None;
            }
            parts.push((vars[0], e[vars[0]], *a));
        }
        Some(parts)
    }
}

/// [`LogSystem::field_lanes`] for H = Σ a_i x_i − b_i ln x_i on the bracket c: g_j = a_j x_j −
/// b_j and ẋ_i = x_i Σ_j c_ij g_j, straight-line code (no loop over terms, no branch), so that
/// RK4 can step it by lane ([`crate::lane_field::rk4_by_lane`]). The terms' operations: g_j is
/// −b_j + (a_j x_j) · 1 there, the same number. The zero entries of c are multiplied, not
/// skipped; they add ±0 to the sum, which moves nothing but the sign of an exactly zero
/// component (then x_i · 0), and no state: x + h·(±0) is x.
#[inline(always)]
pub(super) fn linear_field_lanes<const N: usize, const L: usize>(
    a: &[f64; N],
    b: &[f64; N],
    c: &[[f64; N]; N],
    x: &[[f64; L]; N],
    out: &mut [[f64; L]; N],
) {
    let g: [[f64; L]; N] = std::array::from_fn(|j| std::array::from_fn(|l| -b[j] + a[j] * x[j][l]));
    for i in 0..N {
        let mut acc = [0.0; L];
        for j in 0..N {
            for l in 0..L {
                acc[l] += g[j][l] * c[i][j];
            }
        }
        for l in 0..L {
            out[i][l] = x[i][l] * acc[l];
        }
    }
}

/// a · x^e at L lanes.
#[inline(always)]
fn monomial_lanes<const N: usize, const L: usize>(
    e: &[u32; N],
    a: f64,
    x: &[[f64; L]; N],
) -> [f64; L] {
    let mut m = [a; L];
    for i in 0..N {
        if e[i] > 0 {
            let power = pow_lanes(&x[i], e[i]);
            for l in 0..L {
                m[l] *= power[l];
            }
        }
    }
    m
}

/// g_j += e_j · m for every j with e_j > 0 (x_j ∂/∂x_j of a monomial m = a x^e).
#[inline(always)]
fn add_monomial_gradient<const N: usize, const L: usize>(
    g: &mut [[f64; L]; N],
    e: &[u32; N],
    m: &[f64; L],
) {
    for j in 0..N {
        if e[j] > 0 {
            let ej = f64::from(e[j]);
            for l in 0..L {
                g[j][l] += m[l] * ej;
            }
        }
    }
}

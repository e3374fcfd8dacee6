//! Lie–Poisson systems: a Lie algebra g by its structure constants and a polynomial
//! Hamiltonian H on g*. In the convention of the rigid body (μ̇ = μ × ∇H on so(3)*),
//! μ̇_j = Σ_{i,k} c[i][j][k] ∂H/∂μ_i μ_k, i.e. μ̇ = ad*_{∇H} μ with A = ad_{∇H}ᵀ: μ̇ = A μ.

// Index loops over lanes and coordinates read as the formulas they evaluate.
#![allow(clippy::needless_range_loop)]

use nalgebra::SMatrix;

use crate::dual::{Dual1, Scalar};
use crate::error::CoreError;
use crate::structures::lie_groupoid::LieAlgebra;

/// Largest exponent a Hamiltonian monomial may carry.
pub const MAX_HAMILTONIAN_DEGREE: u32 = 16;

/// A polynomial H(μ) = Σ c · μ₁^e₁ ⋯ μ_N^e_N.
#[derive(Clone, Debug, PartialEq)]
pub struct Hamiltonian<const N: usize> {
    terms: Vec<([u32; N], f64)>,
}

impl<const N: usize> Hamiltonian<N> {
    /// Checks that every coefficient is finite and every exponent at most
    /// [`MAX_HAMILTONIAN_DEGREE`].
    pub fn new(terms: Vec<([u32; N], f64)>) -> Result<Self, CoreError> {
        if let Some((e, c)) = terms.iter().find(|(_, c)| !c.is_finite()) {
            return Err(CoreError::Invalid(format!(
                "Hamiltonian coefficient {c} of the monomial {e:?} is not finite"
            )));
        }
        if let Some((e, _)) = terms
            .iter()
            .find(|(e, _)| e.iter().any(|&k| k > MAX_HAMILTONIAN_DEGREE))
        {
            return Err(CoreError::Invalid(format!(
                "Hamiltonian monomial {e:?} has an exponent over {MAX_HAMILTONIAN_DEGREE}"
            )));
        }
        Ok(Hamiltonian { terms })
    }

    pub fn terms(&self) -> &[([u32; N], f64)] {
        &self.terms
    }

    /// H(μ) for any scalar type.
    pub fn value<T: Scalar>(&self, mu: &[T; N]) -> T {
        let mut h = T::cst(0.0);
        for (e, c) in &self.terms {
            let mut m = T::cst(*c);
            for (x, &k) in mu.iter().zip(e) {
                if k > 0 {
                    m = m * x.powi(k as i32);
                }
            }
            h = h + m;
        }
        h
    }

    /// ∇H(μ), exactly, for any scalar type: each monomial differentiated in closed form.
    pub fn gradient<T: Scalar>(&self, mu: &[T; N]) -> [T; N] {
        let mut g = [T::cst(0.0); N];
        for (e, c) in &self.terms {
            for (i, gi) in g.iter_mut().enumerate() {
                if e[i] == 0 {
                    continue;
                }
                let mut m = T::cst(*c * f64::from(e[i]));
                for (l, (x, &k)) in mu.iter().zip(e).enumerate() {
                    let k = if l == i { k - 1 } else { k };
                    if k > 0 {
                        m = m * x.powi(k as i32);
                    }
                }
                *gi = *gi + m;
            }
        }
        g
    }
}

/// A right-hand side μ̇ = f(μ) with its Jacobian, for the classical integrators.
pub trait VectorField<const N: usize>: Sync {
    fn field(&self, mu: &[f64; N]) -> [f64; N];
    /// ∂f/∂μ, exactly.
    fn jacobian(&self, mu: &[f64; N]) -> SMatrix<f64, N, N>;
    /// The local rate (1/time) at which the flow turns and stretches near μ: a step of size h
    /// resolves the motion only while h · rate is well below a quarter turn. The default is
    /// ‖∂f/∂μ‖_F, a cheap upper bound of the spectral norm of the local linearisation; a
    /// Lie–Poisson system takes the larger of it and its rotation rate ‖ad_{∇H}‖_F/√2 (see
    /// [`lie_poisson_rate`]).
    fn step_rate(&self, mu: &[f64; N]) -> f64 {
        self.jacobian(mu).norm()
    }
}

/// h · [`VectorField::step_rate`] at each state: the angle a step of size h turns it by.
/// Deterministic per state; NaN where the rate overflows to a non-number.
pub fn step_angles<const N: usize, F: VectorField<N>>(
    field: &F,
    mu: &[[f64; N]],
    h: f64,
    out: &mut [f64],
) {
    for (o, m) in out.iter_mut().zip(mu) {
        *o = h * field.step_rate(m);
    }
}

/// The local rate of a Lie–Poisson field μ̇ = A μ, A = ad_{∇H(μ)}ᵀ, with Jacobian
/// J = A + (ξ ↦ ad*_ξ μ) ∘ Hess H(μ): max(‖A‖_F/√2, ‖J‖_F).
///
/// ‖A‖_F/√2 measures the rate at which μ turns along its coadjoint orbit: it is exactly
/// ‖A‖₂ = |ω| on so(3), an upper bound of ‖A‖₂ wherever A is skew (singular values in pairs:
/// compact algebras in an orthonormal basis), and within √(N/2) of it otherwise; an exact
/// ‖A‖₂ ([`spectral_norm`]) costs ten times as much for N = 6. The rotation misses how fast ∇H
/// itself changes, which the Hessian term of J carries: a quartic H on so(3) can turn μ by
/// 0.85 rad a step while J's norm is 8× larger, and every fixed-step method is then O(1) wrong.
/// ‖J‖_F bounds J's spectral norm from above at the cost of N² multiplications. For a quadratic
/// H (the rigid body) the two terms of J partly cancel and ‖J‖_F stays below |ω|, so the rule
/// there is unchanged.
pub fn lie_poisson_rate<const N: usize>(a: &[[f64; N]; N], jacobian_frobenius: f64) -> f64 {
    let rotation = a.iter().flatten().map(|v| v * v).sum::<f64>() * 0.5;
    rotation.sqrt().max(jacobian_frobenius)
}

/// ‖A‖₂ = √λ_max(AᵀA), by cyclic Jacobi rotations of the symmetric AᵀA (N ≤ MAX_DIM, a few
/// sweeps). No allocation. The oracle for [`lie_poisson_rate`]'s bound.
pub fn spectral_norm<const N: usize>(a: &[[f64; N]; N]) -> f64 {
    let mut m = [[0.0f64; N]; N];
    for i in 0..N {
        for j in 0..N {
            m[i][j] = (0..N).map(|k| a[k][i] * a[k][j]).sum();
        }
    }
    let scale = (0..N).map(|i| m[i][i]).fold(0.0f64, f64::max);
    if !(scale.is_finite() && scale > 0.0) {
        return scale.sqrt();
    }
    for _sweep in 0..32 {
        let off: f64 = (0..N)
            .flat_map(|i| (0..N).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| m[i][j] * m[i][j])
            .sum();
        // Off-diagonal mass below 1e-12 of the largest entry moves the eigenvalues by its square
        // over the gap: far below what a step-size rule needs (and round-off keeps the sweeps
        // from going much lower).
        if off <= 1e-24 * scale * scale {
            break;
        }
        for p in 0..N {
            for q in p + 1..N {
                if m[p][q] == 0.0 {
                    continue;
                }
                let theta = (m[q][q] - m[p][p]) / (2.0 * m[p][q]);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..N {
                    let (mkp, mkq) = (m[k][p], m[k][q]);
                    m[k][p] = c * mkp - s * mkq;
                    m[k][q] = s * mkp + c * mkq;
                }
                for k in 0..N {
                    let (mpk, mqk) = (m[p][k], m[q][k]);
                    m[p][k] = c * mpk - s * mqk;
                    m[q][k] = s * mpk + c * mqk;
                }
            }
        }
    }
    (0..N).map(|i| m[i][i]).fold(0.0f64, f64::max).sqrt()
}

/// A Lie–Poisson system on g*: an algebra and a Hamiltonian.
#[derive(Clone, Debug, PartialEq)]
pub struct LiePoisson<const N: usize> {
    pub algebra: LieAlgebra<N>,
    pub hamiltonian: Hamiltonian<N>,
}

impl<const N: usize> LiePoisson<N> {
    /// μ̇ = ad_{∇H}ᵀ μ for any scalar type.
    pub fn field_generic<T: Scalar>(&self, mu: &[T; N]) -> [T; N] {
        let g = self.hamiltonian.gradient(mu);
        self.algebra.ad_transpose_apply(&g, mu)
    }
}

impl LiePoisson<6> {
    /// The heavy top on se(3)*: H = ½ Σ Mᵢ²/Iᵢ + mgl χ·Γ, with `mgl_chi` = mgl χ (its zero
    /// entries give no term).
    pub fn heavy_top(inertia: [f64; 3], mgl_chi: [f64; 3]) -> Result<Self, CoreError> {
        let mut terms = Vec::new();
        terms
            .try_reserve_exact(6)
            .map_err(|_| CoreError::Invalid("no memory for 6 terms".into()))?;
        for i in 0..3 {
            let mut e = [0; 6];
            e[i] = 2;
            terms.push((e, 0.5 / inertia[i]));
        }
        for i in (0..3).filter(|&i| mgl_chi[i] != 0.0) {
            let mut e = [0; 6];
            e[3 + i] = 1;
            terms.push((e, mgl_chi[i]));
        }
        Ok(LiePoisson {
            algebra: LieAlgebra::se3(),
            hamiltonian: Hamiltonian::new(terms)?,
        })
    }
}

impl<const N: usize> LiePoisson<N> {
    /// The system compiled to its sparsity (see [`CompiledLiePoisson`]).
    pub fn compile(&self) -> CompiledLiePoisson<N> {
        CompiledLiePoisson::new(self)
    }
}

impl<const N: usize> VectorField<N> for LiePoisson<N> {
    fn field(&self, mu: &[f64; N]) -> [f64; N] {
        self.field_generic(mu)
    }

    fn step_rate(&self, mu: &[f64; N]) -> f64 {
        let g = self.hamiltonian.gradient(mu);
        let c = self.algebra.structure_constants();
        let a: [[f64; N]; N] = std::array::from_fn(|j| {
            std::array::from_fn(|k| (0..N).map(|i| c[i][j][k] * g[i]).sum())
        });
        lie_poisson_rate(&a, self.jacobian(mu).norm())
    }

    fn jacobian(&self, mu: &[f64; N]) -> SMatrix<f64, N, N> {
        let md: [Dual1<N>; N] = std::array::from_fn(|i| Dual1::var(mu[i], i));
        let f = self.field_generic(&md);
        SMatrix::from_fn(|r, c| f[r].g[c])
    }
}

/// Largest power of one coordinate a compiled Hamiltonian tabulates.
const MAX_POWER: usize = MAX_HAMILTONIAN_DEGREE as usize;

/// One product c · Π μ_v^p of a derivative of H, added into slot `out` (a gradient component,
/// or a Hessian entry i·N + m); its factors (v, p ≥ 1) are `factors[start..end]`.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Product {
    out: usize,
    coeff: f64,
    start: usize,
    end: usize,
}

/// A Lie–Poisson system compiled to its sparsity: the field μ̇_j = Σ c[i][j][k] ∂ᵢH μ_k, its
/// Jacobian and ∇H evaluated from the nonzero structure constants and the monomials of ∇H and
/// Hess H only, with integer powers read from a per-state table built by repeated
/// multiplication (no N³ loop, no `powi`).
///
/// The products are summed in the order of the monomials and of the structure constants, so
/// the result is deterministic; it differs from the dense [`LiePoisson`] (the oracle) by
/// rounding only, a few ulps of the largest term (see the tests).
#[derive(Clone, Debug, PartialEq)]
pub struct CompiledLiePoisson<const N: usize> {
    /// The nonzero c[i][j][k] as (i, j, k, c).
    bracket: Vec<(usize, usize, usize, f64)>,
    grad: Vec<Product>,
    hess: Vec<Product>,
    factors: Vec<(usize, usize)>,
    /// Highest power of each coordinate any product needs.
    max_power: [usize; N],
    /// Highest power of one coordinate in a product of ∇H.
    grad_degree: usize,
    /// bracket[row_end[j − 1]..row_end[j]] are the entries of component j.
    row_end: [usize; N],
    /// The field's terms, ordered by j: the bracket without the entries whose ∂ᵢH vanishes
    /// identically, and with a constant ∂ᵢH folded into the coefficient (the heavy top's
    /// mgl χ: 4 of its 18 entries dropped, 2 folded).
    field_terms: Vec<FieldTerm>,
    /// field_terms[field_row_end[j − 1]..field_row_end[j]] are the terms of component j.
    field_row_end: [usize; N],
    /// The products of ∇H whose component depends on μ (the field needs no others).
    field_grad: Vec<Product>,
}

/// One term of the compiled field, μ̇_j += w μ_k: w = c ∂ᵢH(μ) for `grad: Some(i)`, or the
/// constant w = c for `grad: None`, where c already holds c[i][j][k] ∂ᵢH computed as the
/// scalar path computes it, so (c ∂ᵢH) μ_k has the same bits as c · ∂ᵢH · μ_k.
#[derive(Clone, Copy, Debug, PartialEq)]
struct FieldTerm {
    grad: Option<usize>,
    k: usize,
    c: f64,
}

impl<const N: usize> CompiledLiePoisson<N> {
    pub fn new(system: &LiePoisson<N>) -> Self {
        let c = system.algebra.structure_constants();
        let mut bracket = Vec::new();
        for j in 0..N {
            for i in 0..N {
                for k in 0..N {
                    if c[i][j][k] != 0.0 {
                        bracket.push((i, j, k, c[i][j][k]));
                    }
                }
            }
        }
        let (mut grad, mut hess, mut factors) = (Vec::new(), Vec::new(), Vec::new());
        let mut max_power = [0usize; N];
        let mut push = |list: &mut Vec<Product>, out: usize, coeff: f64, e: &[u32; N]| {
            if coeff == 0.0 {
                return;
            }
            let start = factors.len();
            for (v, &p) in e.iter().enumerate() {
                if p > 0 {
                    factors.push((v, p as usize));
                    max_power[v] = max_power[v].max(p as usize);
                }
            }
            list.push(Product {
                out,
                coeff,
                start,
                end: factors.len(),
            });
        };
        for (e, coeff) in system.hamiltonian.terms() {
            for l in 0..N {
                if e[l] == 0 {
                    continue;
                }
                let mut d = *e;
                d[l] -= 1;
                push(&mut grad, l, coeff * f64::from(e[l]), &d);
                for m in l..N {
                    if d[m] == 0 {
                        continue;
                    }
                    let mut dd = d;
                    dd[m] -= 1;
                    push(
                        &mut hess,
                        l * N + m,
                        coeff * f64::from(e[l]) * f64::from(d[m]),
                        &dd,
                    );
                }
            }
        }
        let grad_degree = grad
            .iter()
            .flat_map(|t| factors[t.start..t.end].iter().map(|&(_, p)| p))
            .max()
            .unwrap_or(0);
        let row_end = std::array::from_fn(|j| bracket.iter().filter(|e| e.1 <= j).count());
        // ∂ᵢH is constant when every product of component i has no factor; its value is the
        // sum of their coefficients in order, from 0, as `gradient` sums them.
        let mut constant = [true; N];
        let mut value = [0.0; N];
        let mut present = [false; N];
        for t in &grad {
            present[t.out] = true;
            constant[t.out] &= t.start == t.end;
            value[t.out] += t.coeff;
        }
        let mut field_terms = Vec::new();
        for &(i, _, k, c) in &bracket {
            if !present[i] {
                continue;
            }
            field_terms.push(if constant[i] {
                FieldTerm {
                    grad: None,
                    k,
                    c: c * value[i],
                }
            } else {
                FieldTerm {
                    grad: Some(i),
                    k,
                    c,
                }
            });
        }
        let field_row_end =
            std::array::from_fn(|j| bracket.iter().filter(|e| e.1 <= j && present[e.0]).count());
        let field_grad = grad.iter().filter(|t| !constant[t.out]).copied().collect();
        CompiledLiePoisson {
            field_terms,
            field_row_end,
            field_grad,
            row_end,
            bracket,
            grad,
            hess,
            factors,
            max_power,
            grad_degree,
        }
    }

    /// The nonzero structure constants (i, j, k, c), ordered by j.
    pub fn bracket(&self) -> &[(usize, usize, usize, f64)] {
        &self.bracket
    }

    /// μ_v^p for p ≤ max_power[v], by repeated multiplication.
    #[inline(always)]
    fn powers(&self, mu: &[f64; N]) -> [[f64; MAX_POWER + 1]; N] {
        let mut pw = [[1.0; MAX_POWER + 1]; N];
        for v in 0..N {
            for p in 1..=self.max_power[v] {
                pw[v][p] = pw[v][p - 1] * mu[v];
            }
        }
        pw
    }

    /// Σ of `products`, each c · Π pow(v, p), into its slot of `out`.
    #[inline(always)]
    fn sum_products<const M: usize>(
        &self,
        products: &[Product],
        pow: impl Fn(usize, usize) -> f64,
        out: &mut [f64; M],
    ) {
        for t in products {
            let mut v = t.coeff;
            for &(var, p) in &self.factors[t.start..t.end] {
                v *= pow(var, p);
            }
            out[t.out] += v;
        }
    }

    /// ∇H(μ). A quadratic H needs no power table (every factor is a coordinate itself).
    #[inline]
    pub fn gradient(&self, mu: &[f64; N]) -> [f64; N] {
        let mut g = [0.0; N];
        if self.needs_powers() {
            let pw = self.powers(mu);
            self.sum_products(&self.grad, |v, p| pw[v][p], &mut g);
        } else {
            self.sum_products(&self.grad, |v, _| mu[v], &mut g);
        }
        g
    }

    /// Whether some factor of ∇H is a power above 1.
    #[inline(always)]
    fn needs_powers(&self) -> bool {
        self.grad_degree > 1
    }

    /// Hess H(μ), symmetric.
    fn hessian(&self, mu: &[f64; N]) -> [[f64; N]; N] {
        let pw = self.powers(mu);
        let mut hm = [[0.0; N]; N];
        for t in &self.hess {
            let (l, m) = (t.out / N, t.out % N);
            let mut v = t.coeff;
            for &(var, p) in &self.factors[t.start..t.end] {
                v *= pw[var][p];
            }
            hm[l][m] += v;
            if l != m {
                hm[m][l] += v;
            }
        }
        hm
    }

    /// The rotation part A = ad_{∇H}ᵀ, A[j][k] = Σᵢ c[i][j][k] ∂ᵢH.
    fn rotation(&self, g: &[f64; N]) -> [[f64; N]; N] {
        let mut a = [[0.0; N]; N];
        for &(i, j, k, c) in &self.bracket {
            a[j][k] += c * g[i];
        }
        a
    }
}

impl<const N: usize> VectorField<N> for CompiledLiePoisson<N> {
    /// Σ over the compiled field terms, component by component (the lanes' order).
    #[inline]
    fn field(&self, mu: &[f64; N]) -> [f64; N] {
        let mut g = [0.0; N];
        if self.needs_powers() {
            let pw = self.powers(mu);
            self.sum_products(&self.field_grad, |v, p| pw[v][p], &mut g);
        } else {
            self.sum_products(&self.field_grad, |v, _| mu[v], &mut g);
        }
        let mut f = [0.0; N];
        let mut start = 0;
        for j in 0..N {
            for t in &self.field_terms[start..self.field_row_end[j]] {
                f[j] += match t.grad {
                    Some(i) => t.c * g[i] * mu[t.k],
                    None => t.c * mu[t.k],
                };
            }
            start = self.field_row_end[j];
        }
        f
    }

    /// J[j][m] = Σ c[i][j][k] (∂ᵢH δ_km + ∂ᵢ∂_mH μ_k).
    fn jacobian(&self, mu: &[f64; N]) -> SMatrix<f64, N, N> {
        let g = self.gradient(mu);
        let hm = self.hessian(mu);
        let mut j = self.rotation(&g);
        for &(i, r, k, c) in &self.bracket {
            let w = c * mu[k];
            for m in 0..N {
                j[r][m] += w * hm[i][m];
            }
        }
        SMatrix::from_fn(|r, m| j[r][m])
    }

    fn step_rate(&self, mu: &[f64; N]) -> f64 {
        let a = self.rotation(&self.gradient(mu));
        lie_poisson_rate(&a, self.jacobian(mu).norm())
    }
}

/// Evaluation of a compiled system on a block of L states at once (structure of arrays).
impl<const N: usize> CompiledLiePoisson<N> {
    /// The field at L states, lane by lane with the same operations in the same order as
    /// [`VectorField::field`]: each lane equals the scalar path bit for bit.
    #[inline(always)]
    pub fn field_lanes<const L: usize>(&self, mu: &[[f64; L]; N], out: &mut [[f64; L]; N]) {
        let mut g = [[0.0; L]; N];
        if self.needs_powers() {
            let mut pw = [[[1.0; L]; MAX_POWER + 1]; N];
            for v in 0..N {
                for p in 1..=self.max_power[v] {
                    for l in 0..L {
                        pw[v][p][l] = pw[v][p - 1][l] * mu[v][l];
                    }
                }
            }
            self.gradient_lanes(|v, p| &pw[v][p], &mut g);
        } else {
            self.gradient_lanes(|v, _| &mu[v], &mut g);
        }
        // Component by component, accumulated in registers (the same sums, in the same order,
        // as the scalar path's); a structure constant ±1 multiplies exactly, so it is skipped.
        let mut start = 0;
        for j in 0..N {
            let mut acc = [0.0; L];
            for t in &self.field_terms[start..self.field_row_end[j]] {
                let (c, k) = (t.c, t.k);
                match t.grad {
                    Some(i) if c == 1.0 => {
                        for l in 0..L {
                            acc[l] += g[i][l] * mu[k][l];
                        }
                    }
                    Some(i) if c == -1.0 => {
                        for l in 0..L {
                            acc[l] += -g[i][l] * mu[k][l];
                        }
                    }
                    Some(i) => {
                        for l in 0..L {
                            acc[l] += c * g[i][l] * mu[k][l];
                        }
                    }
                    None => {
                        for l in 0..L {
                            acc[l] += c * mu[k][l];
                        }
                    }
                }
            }
            out[j] = acc;
            start = self.field_row_end[j];
        }
    }

    #[inline(always)]
    fn gradient_lanes<'a, const L: usize>(
        &self,
        pow: impl Fn(usize, usize) -> &'a [f64; L],
        g: &mut [[f64; L]; N],
    ) {
        for t in &self.field_grad {
            let mut x = [t.coeff; L];
            for &(var, p) in &self.factors[t.start..t.end] {
                let y = pow(var, p);
                for l in 0..L {
                    x[l] *= y[l];
                }
            }
            for l in 0..L {
                g[t.out][l] += x[l];
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn so3_field_is_mu_cross_grad_h() {
        let inv = [1.0 / 1.5, 1.0 / 2.0, 1.0 / 2.5];
        let h = Hamiltonian::new(vec![
            ([2, 0, 0], 0.5 * inv[0]),
            ([0, 2, 0], 0.5 * inv[1]),
            ([0, 0, 2], 0.5 * inv[2]),
        ])
        .unwrap();
        let sys = LiePoisson {
            algebra: LieAlgebra::so3().unwrap(),
            hamiltonian: h,
        };
        let mu = [0.3, -1.2, 2.0];
        let w = [mu[0] * inv[0], mu[1] * inv[1], mu[2] * inv[2]];
        let expect = [
            mu[1] * w[2] - mu[2] * w[1],
            mu[2] * w[0] - mu[0] * w[2],
            mu[0] * w[1] - mu[1] * w[0],
        ];
        let f = sys.field(&mu);
        for i in 0..3 {
            assert!((f[i] - expect[i]).abs() < 1e-15, "{f:?} {expect:?}");
        }
        // The Jacobian against central differences of the field (an independent path).
        let j = sys.jacobian(&mu);
        for c in 0..3 {
            let (mut a, mut b) = (mu, mu);
            a[c] += 1e-6;
            b[c] -= 1e-6;
            let (fa, fb) = (sys.field(&a), sys.field(&b));
            for r in 0..3 {
                assert!((j[(r, c)] - (fa[r] - fb[r]) / 2e-6).abs() < 1e-8);
            }
        }
    }

    /// The heavy top's field drops the 4 bracket entries of Γ₁, Γ₂ (∂H ≡ 0) and folds mgl
    /// into the 2 of Γ₃ (∂H constant), and still equals the full bracket sum bit for bit.
    #[test]
    fn compiled_field_drops_zero_and_folds_constant_gradients() {
        let sys = LiePoisson::heavy_top([1.0, 1.5, 2.0], [0.0, 0.0, 0.981])
            .unwrap()
            .compile();
        assert_eq!(sys.bracket.len(), 18);
        assert_eq!(sys.field_terms.len(), 14);
        assert_eq!(
            sys.field_terms.iter().filter(|t| t.grad.is_none()).count(),
            2
        );
        for mu in [
            [0.3, -1.2, 2.0, 0.6, 0.0, -0.8],
            [1e-3, 4.0, -2.5, -0.1, 0.99, 0.1],
        ] {
            let g = sys.gradient(&mu);
            let mut full = [0.0; 6];
            for &(i, j, k, c) in &sys.bracket {
                full[j] += c * g[i] * mu[k];
            }
            assert_eq!(sys.field(&mu), full);
        }
    }

    #[test]
    fn bad_hamiltonians_are_refused() {
        assert!(Hamiltonian::<3>::new(vec![([1, 0, 0], f64::NAN)]).is_err());
        assert!(Hamiltonian::<3>::new(vec![([99, 0, 0], 1.0)]).is_err());
    }
}

//! Lie–Poisson systems: a Lie algebra g by its structure constants and a polynomial
//! Hamiltonian H on g*. In the convention of the rigid body (μ̇ = μ × ∇H on so(3)*),
//! μ̇_j = Σ_{i,k} c[i][j][k] ∂H/∂μ_i μ_k, i.e. μ̇ = ad*_{∇H} μ with A = ad_{∇H}ᵀ: μ̇ = A μ.

use nalgebra::SMatrix;

use crate::dual::{Dual1, Scalar};
use crate::error::CoreError;
use crate::groupoid::LieAlgebra;

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

impl<const N: usize> VectorField<N> for LiePoisson<N> {
    fn field(&self, mu: &[f64; N]) -> [f64; N] {
        self.field_generic(mu)
    }

    fn jacobian(&self, mu: &[f64; N]) -> SMatrix<f64, N, N> {
        let md: [Dual1<N>; N] = std::array::from_fn(|i| Dual1::var(mu[i], i));
        let f = self.field_generic(&md);
        SMatrix::from_fn(|r, c| f[r].g[c])
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

    #[test]
    fn bad_hamiltonians_are_refused() {
        assert!(Hamiltonian::<3>::new(vec![([1, 0, 0], f64::NAN)]).is_err());
        assert!(Hamiltonian::<3>::new(vec![([99, 0, 0], 1.0)]).is_err());
    }
}

//! Any polynomial bivector π(x) through an approximate symplectic realization of order n.
//!
//! The realization and the Taylor-HJ series are derived symbolically at construction time (in
//! Python, with sympy); the core receives their coefficients: the maps α and β as polynomials in
//! (fibre p, base x), and S(t, x) as a polynomial in (t, x). A step is then the same Newton
//! bisection as on every other realization ([`RealizationStepper`]): solve α(∇S(h, x), x) = x_k
//! for x and return β(∇S(h, x), x). Derivatives come from evaluating the same polynomials on
//! dual numbers, so they are exact.

use crate::dual::{Dual1, Jet2, Scalar};
use crate::error::{CoreError, StepFailure};
use crate::realization::{Generating, Realization, RealizationStepper};

/// Largest exponent of one variable in a term.
pub const MAX_EXPONENT: u32 = 64;
/// Largest dimension: the evaluation buffers hold 2 · MAX_DIM variables.
pub const MAX_DIM: usize = 10;

/// Σ_k c_k Π_i v_i^{e_ki}: a sparse polynomial in `vars` variables, exponents row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct SparsePolynomial {
    vars: usize,
    coeffs: Vec<f64>,
    exponents: Vec<u8>,
}

impl SparsePolynomial {
    /// `exponents`: `coeffs.len()` rows of `vars` exponents in 0..=[`MAX_EXPONENT`]; the
    /// coefficients must be finite. Fallible allocation.
    pub fn new(vars: usize, coeffs: &[f64], exponents: &[u32]) -> Result<Self, CoreError> {
        if vars == 0 || vars > 2 * MAX_DIM + 1 {
            return Err(CoreError::Invalid(format!(
                "a polynomial needs 1..={} variables, got {vars}",
                2 * MAX_DIM + 1
            )));
        }
        if exponents.len() != coeffs.len() * vars {
            return Err(CoreError::Invalid(format!(
                "{} coefficients need {} exponents ({vars} a term), got {}",
                coeffs.len(),
                coeffs.len() * vars,
                exponents.len()
            )));
        }
        if let Some(k) = coeffs.iter().position(|c| !c.is_finite()) {
            return Err(CoreError::Invalid(format!(
                "coefficient {k} is not finite: {}",
                coeffs[k]
            )));
        }
        if let Some(k) = exponents.iter().position(|&e| e > MAX_EXPONENT) {
            return Err(CoreError::Invalid(format!(
                "exponent {} of term {} is over {MAX_EXPONENT}",
                exponents[k],
                k / vars
            )));
        }
        let mut c = Vec::new();
        c.try_reserve_exact(coeffs.len())
            .map_err(|_| CoreError::Invalid("too many polynomial terms".into()))?;
        c.extend_from_slice(coeffs);
        let mut e = Vec::new();
        e.try_reserve_exact(exponents.len())
            .map_err(|_| CoreError::Invalid("too many polynomial terms".into()))?;
        e.extend(exponents.iter().map(|&v| v as u8));
        Ok(SparsePolynomial {
            vars,
            coeffs: c,
            exponents: e,
        })
    }

    pub fn vars(&self) -> usize {
        self.vars
    }

    /// The polynomial at `v` (at least `vars` values), any scalar: powers by repeated
    /// multiplication, so f64, duals and jets all get exact results and derivatives.
    #[inline]
    pub fn eval<T: Scalar>(&self, v: &[T]) -> T {
        let mut sum = T::cst(0.0);
        for (c, row) in self
            .coeffs
            .iter()
            .zip(self.exponents.chunks_exact(self.vars))
        {
            let mut term = T::cst(*c);
            for (x, &e) in v.iter().zip(row) {
                for _ in 0..e {
                    term = term * *x;
                }
            }
            sum = sum + term;
        }
        sum
    }
}

/// An approximate symplectic realization in canonical coordinates: sou = β and tar = α, each
/// N polynomials in (fibre, base), 2N variables.
#[derive(Clone, Debug, PartialEq)]
pub struct PolynomialRealization<const N: usize> {
    sou: Vec<SparsePolynomial>,
    tar: Vec<SparsePolynomial>,
}

impl<const N: usize> PolynomialRealization<N> {
    pub fn new(sou: Vec<SparsePolynomial>, tar: Vec<SparsePolynomial>) -> Result<Self, CoreError> {
        if N > MAX_DIM {
            return Err(CoreError::Invalid(format!(
                "dimension {N} is over {MAX_DIM}"
            )));
        }
        for (name, maps) in [("sou", &sou), ("tar", &tar)] {
            if maps.len() != N || maps.iter().any(|m| m.vars() != 2 * N) {
                return Err(CoreError::Invalid(format!(
                    "{name} must be {N} polynomials in {} variables (fibre, base)",
                    2 * N
                )));
            }
        }
        Ok(PolynomialRealization { sou, tar })
    }

    #[inline]
    fn apply<T: Scalar>(
        maps: &[SparsePolynomial],
        x: &[T; N],
        p: &[T; N],
    ) -> Result<[T; N], StepFailure> {
        let mut v = [T::cst(0.0); 2 * MAX_DIM];
        v[..N].copy_from_slice(x);
        v[N..2 * N].copy_from_slice(p);
        let out: [T; N] = std::array::from_fn(|i| maps[i].eval(&v[..2 * N]));
        if out.iter().all(|o| o.value().is_finite()) {
            Ok(out)
        } else {
            Err(StepFailure::NonFinite)
        }
    }
}

impl<const N: usize> Realization<N> for PolynomialRealization<N> {
    #[inline]
    fn sou<T: Scalar>(&self, x: &[T; N], p: &[T; N]) -> Result<[T; N], StepFailure> {
        Self::apply(&self.sou, x, p)
    }
    #[inline]
    fn tar<T: Scalar>(&self, x: &[T; N], p: &[T; N]) -> Result<[T; N], StepFailure> {
        Self::apply(&self.tar, x, p)
    }
}

/// S(t, p) as a polynomial in (t, p): N + 1 variables, t first.
#[derive(Clone, Debug, PartialEq)]
pub struct PolynomialGenerating<const N: usize> {
    s: SparsePolynomial,
}

impl<const N: usize> PolynomialGenerating<N> {
    pub fn new(s: SparsePolynomial) -> Result<Self, CoreError> {
        if N > MAX_DIM || s.vars() != N + 1 {
            return Err(CoreError::Invalid(format!(
                "S must be a polynomial in {} variables (t, then the {N} coordinates)",
                N + 1
            )));
        }
        Ok(PolynomialGenerating { s })
    }
}

impl<const N: usize> Generating<N> for PolynomialGenerating<N> {
    type Workspace = ();
    fn workspace(&self) {}
    fn jet(&self, t: f64, p: &[f64; N], _: &mut ()) -> Jet2<N> {
        let mut v = [Jet2::<N>::cst(0.0); MAX_DIM + 1];
        v[0] = Jet2::cst(t);
        for i in 0..N {
            v[i + 1] = Jet2::var(p[i], i);
        }
        self.s.eval(&v[..N + 1])
    }
    fn gradient(&self, t: f64, p: &[f64; N], _: &mut ()) -> Dual1<N> {
        let mut v = [Dual1::<N>::cst(0.0); MAX_DIM + 1];
        v[0] = Dual1::cst(t);
        for i in 0..N {
            v[i + 1] = Dual1::var(p[i], i);
        }
        self.s.eval(&v[..N + 1])
    }
}

/// Taylor-HJ on an approximate realization of a polynomial bivector.
pub type PolynomialBisection<const N: usize> =
    RealizationStepper<N, PolynomialRealization<N>, PolynomialGenerating<N>>;

//! Any polynomial bivector π(x) through an approximate symplectic realization of order n.
//!
//! The realization and the Taylor-HJ series are derived symbolically at construction time (in
//! Python, with sympy); the core receives their coefficients: the maps α and β as polynomials in
//! (fibre p, base x), and S(t, x) as a polynomial in (t, x). A step is then the same Newton
//! bisection as on every other realization ([`BisectionStepper`]): solve α(∇S(h, x), x) = x_k
//! for x and return β(∇S(h, x), x). Derivatives come from evaluating the same polynomials on
//! dual numbers, so they are exact; the rollouts step in SIMD lanes instead, on the derivative
//! polynomials ([`super::polynomial_lanes`]).

use crate::dual::{Dual1, Jet2, Scalar};
use crate::error::{CoreError, StepFailure};
use crate::generating::{GeneratingFunction, Mlp, MlpInputs, Polynomial, Workspace};
use crate::lane_field::LaneField;
use crate::realization::{Generating, Realization};
use crate::stepper::BisectionStepper;
use crate::stepper::NewtonOptions;
use crate::structures::lie_poisson::VectorField;
use nalgebra::SMatrix;

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

    /// The terms: (coefficient, exponents of each variable).
    pub fn terms(&self) -> impl Iterator<Item = (f64, &[u8])> {
        self.coeffs
            .iter()
            .copied()
            .zip(self.exponents.chunks_exact(self.vars))
    }

    /// The polynomial at L points at once (`v[i][l]`: variable i of lane l), with the same
    /// operations in the same order as [`Self::eval`] on f64, so every lane gets its bits.
    #[inline]
    pub fn eval_lanes<const L: usize>(&self, v: &[[f64; L]]) -> [f64; L] {
        self.sum_lanes(v, 0, |c, _| c)
    }

    /// The polynomial at (t, `rest`) for L points at once, t the first variable and one plain
    /// number: each term's c·tᵉ in f64 (as [`Self::eval_after_constant`] forms it), then the
    /// powers of the other variables lane by lane, by repeated multiplication.
    #[inline]
    pub fn eval_lanes_after_t<const L: usize>(&self, t: f64, rest: &[[f64; L]]) -> [f64; L] {
        self.sum_lanes(rest, 1, |c, row| times_powers(c, &[t], &row[..1]))
    }

    /// Σ_k head_k · Π_i v_i^{e_k,skip+i} at L points: each term's `head(c, exponents)` times
    /// the powers of the variables from `skip` on, by repeated multiplication left to right.
    #[inline(always)]
    fn sum_lanes<const L: usize>(
        &self,
        v: &[[f64; L]],
        skip: usize,
        head: impl Fn(f64, &[u8]) -> f64,
    ) -> [f64; L] {
        let mut sum = [0.0; L];
        for (c, row) in self.terms() {
            let mut term = [head(c, row); L];
            for (x, &e) in v.iter().zip(&row[skip..]) {
                for _ in 0..e {
                    for l in 0..L {
                        term[l] *= x[l];
                    }
                }
            }
            for l in 0..L {
                sum[l] += term[l];
            }
        }
        sum
    }

    /// ∂/∂v_var, exactly: each term with a positive exponent e of v_var becomes c·e times the
    /// same powers with e − 1 (the others drop out). Fallible allocation.
    pub fn derivative(&self, var: usize) -> Result<Self, CoreError> {
        let rows = self.terms().filter(|(_, row)| row[var] > 0).count();
        let mut coeffs = Vec::new();
        let mut exponents = Vec::new();
        coeffs
            .try_reserve_exact(rows)
            .map_err(|_| CoreError::Invalid("too many polynomial terms".into()))?;
        exponents
            .try_reserve_exact(rows * self.vars)
            .map_err(|_| CoreError::Invalid("too many polynomial terms".into()))?;
        for (c, row) in self.terms().filter(|(_, row)| row[var] > 0) {
            coeffs.push(c * f64::from(row[var]));
            exponents.extend(
                row.iter()
                    .enumerate()
                    .map(|(i, &e)| u32::from(e) - u32::from(i == var)),
            );
        }
        SparsePolynomial::new(self.vars, &coeffs, &exponents)
    }

    /// The polynomial at `v` (at least `vars` values), any scalar: powers by repeated
    /// multiplication, so f64, duals and jets all get exact results and derivatives.
    #[inline]
    pub fn eval<T: Scalar>(&self, v: &[T]) -> T {
        self.terms().fold(T::cst(0.0), |sum, (c, row)| {
            sum + times_powers(T::cst(c), v, row)
        })
    }

    /// [`Self::eval`] at (t, `rest`), t the first variable and a plain number: each term's
    /// c·tᵉ multiplied in f64 before its first product of jets. For t = +0 or t > 0 and a
    /// finite c·tᵉ, `eval`'s products of constant jets give the value c·tᵉ with derivatives
    /// (+0)·t + c·(+0) = +0, which is `T::cst(c·tᵉ)`: the same bits for fewer jet products.
    /// Any other t, and a term whose c·tᵉ is not finite, take `eval`'s products.
    #[inline]
    pub fn eval_after_constant<T: Scalar>(&self, t: f64, rest: &[T]) -> T {
        let positive = t > 0.0 || t.to_bits() == 0;
        self.terms().fold(T::cst(0.0), |sum, (c, row)| {
            let ct = times_powers(c, &[t], &row[..1]);
            let head = if positive && ct.is_finite() {
                T::cst(ct)
            } else {
                times_powers(T::cst(c), &[T::cst(t)], &row[..1])
            };
            sum + times_powers(head, rest, &row[1..])
        })
    }
}

/// `term · Π_i v_i^{row_i}`, each power by repeated multiplication, left to right: the
/// products of [`SparsePolynomial::eval`] for any scalar.
#[inline(always)]
fn times_powers<T: Scalar>(mut term: T, v: &[T], row: &[u8]) -> T {
    for (x, &e) in v.iter().zip(row) {
        for _ in 0..e {
            term = term * *x;
        }
    }
    term
}

/// A polynomial vector field ẋ_i = f_i(x), f = π∇H of a polynomial bivector and Hamiltonian
/// (expanded by sympy): the right-hand side of the classical baselines (RK4 and the implicit
/// midpoint rule, in SIMD lanes), with the exact Jacobian from dual numbers.
#[derive(Clone, Debug, PartialEq)]
pub struct PolynomialField<const N: usize> {
    f: Vec<SparsePolynomial>,
}

impl<const N: usize> PolynomialField<N> {
    /// N polynomials in N variables.
    pub fn new(f: Vec<SparsePolynomial>) -> Result<Self, CoreError> {
        if f.len() != N || f.iter().any(|p| p.vars() != N) {
            return Err(CoreError::Invalid(format!(
                "a vector field in dimension {N} needs {N} polynomials in {N} variables"
            )));
        }
        Ok(PolynomialField { f })
    }
}

impl<const N: usize> VectorField<N> for PolynomialField<N> {
    #[inline]
    fn field(&self, x: &[f64; N]) -> [f64; N] {
        std::array::from_fn(|i| self.f[i].eval(x))
    }

    fn jacobian(&self, x: &[f64; N]) -> SMatrix<f64, N, N> {
        let d: [Dual1<N>; N] = std::array::from_fn(|i| Dual1::var(x[i], i));
        let rows: [Dual1<N>; N] = std::array::from_fn(|i| self.f[i].eval(&d));
        SMatrix::from_fn(|r, c| rows[r].g[c])
    }
}

/// The field in lanes by [`SparsePolynomial::eval_lanes`] (the same bits as
/// [`VectorField::field`]); the Jacobian lane by lane through dual numbers.
impl<const N: usize> LaneField<N> for PolynomialField<N> {
    #[inline(always)]
    fn field_lanes<const L: usize>(&self, x: &[[f64; L]; N], out: &mut [[f64; L]; N]) {
        for (row, f) in out.iter_mut().zip(&self.f) {
            *row = f.eval_lanes(x);
        }
    }

    #[inline(always)]
    fn jacobian_lanes<const L: usize>(
        &self,
        x: &[[f64; L]; N],
        out: &mut [[[f64; L]; N]; N],
    ) -> bool {
        crate::straight_line::jacobian_lanes_by(x, out, |m| {
            let j = VectorField::jacobian(self, m);
            std::array::from_fn(|r| std::array::from_fn(|c| j[(r, c)]))
        })
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

impl<const N: usize> PolynomialRealization<N> {
    /// β's and α's N polynomials in (fibre, base).
    pub fn maps(&self) -> (&[SparsePolynomial], &[SparsePolynomial]) {
        (&self.sou, &self.tar)
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

impl<const N: usize> PolynomialGenerating<N> {
    /// S as a polynomial in (t, x), t first.
    pub fn as_polynomial(&self) -> &SparsePolynomial {
        &self.s
    }
}

impl<const N: usize> Generating<N> for PolynomialGenerating<N> {
    type Workspace = ();
    fn workspace(&self) {}
    fn jet(&self, t: f64, p: &[f64; N], _: &mut ()) -> Jet2<N> {
        let v: [Jet2<N>; N] = std::array::from_fn(|i| Jet2::var(p[i], i));
        self.s.eval_after_constant(t, &v)
    }
    fn gradient(&self, t: f64, p: &[f64; N], _: &mut ()) -> Dual1<N> {
        let v: [Dual1<N>; N] = std::array::from_fn(|i| Dual1::var(p[i], i));
        self.s.eval_after_constant(t, &v)
    }
}

/// Taylor-HJ on an approximate realization of a polynomial bivector.
pub type PolynomialBisection<const N: usize> =
    BisectionStepper<N, PolynomialRealization<N>, PolynomialGenerating<N>>;

/// A learned generating function on an approximate realization: the exact Taylor-HJ terms as a
/// polynomial in (t, x) ([`PolynomialGenerating`]) plus t^m · N(t, x), the network term of a
/// [`GeneratingFunction`] with plain inputs (t, x) and no polynomial part. Both derivatives are
/// exact: the Taylor terms evaluated on jets, forward-mode duals through the MLP.
#[derive(Clone, Debug, PartialEq)]
pub struct LearnedPolynomial<const N: usize> {
    pub taylor: PolynomialGenerating<N>,
    pub network: GeneratingFunction<N>,
}

impl<const N: usize> LearnedPolynomial<N> {
    /// Refuses a network part with polynomial terms of its own (the Taylor terms live in
    /// `taylor`, so a second polynomial would be counted twice).
    pub fn new(
        taylor: PolynomialGenerating<N>,
        network: GeneratingFunction<N>,
    ) -> Result<Self, CoreError> {
        if !network.polynomial.terms().is_empty() {
            return Err(CoreError::Invalid(
                "the network part of a learned polynomial-realization generating function must \
                 hold no polynomial terms (the Taylor terms are given separately)"
                    .into(),
            ));
        }
        Ok(LearnedPolynomial { taylor, network })
    }
}

impl<const N: usize> Generating<N> for LearnedPolynomial<N> {
    type Workspace = Workspace<N>;
    fn workspace(&self) -> Workspace<N> {
        self.network.workspace()
    }
    fn jet(&self, t: f64, p: &[f64; N], ws: &mut Workspace<N>) -> Jet2<N> {
        Generating::jet(&self.taylor, t, p, &mut ()) + self.network.jet(t, p, ws)
    }
    fn gradient(&self, t: f64, p: &[f64; N], ws: &mut Workspace<N>) -> Dual1<N> {
        let taylor = Generating::gradient(&self.taylor, t, p, &mut ());
        let net = self.network.gradient(t, p, ws);
        Dual1 {
            v: taylor.v + net.v,
            g: std::array::from_fn(|i| taylor.g[i] + net.g[i]),
        }
    }
}

/// The learned bisection integrator on an approximate realization of a polynomial bivector.
pub type LearnedPolynomialBisection<const N: usize> =
    BisectionStepper<N, PolynomialRealization<N>, LearnedPolynomial<N>>;

/// A learned model on an approximate realization, of any dimension `dim` ≤ [`MAX_DIM`]: the maps
/// β (sou) and α (tar) as `dim` polynomials each in (fibre, base), the Taylor terms S(t, x) as
/// one polynomial in (t, x), and the network t^m · N(t, x). [`Self::stepper`] builds the
/// `dim`-dimensional (monomorphised) integrator; every check runs in [`Self::new`].
#[derive(Clone, Debug)]
pub struct LearnedPolynomialModel {
    pub dim: usize,
    sou: Vec<SparsePolynomial>,
    tar: Vec<SparsePolynomial>,
    taylor: SparsePolynomial,
    pub mlp: Option<Mlp>,
    pub mlp_power: u32,
}

impl LearnedPolynomialModel {
    pub fn new(
        dim: usize,
        sou: Vec<SparsePolynomial>,
        tar: Vec<SparsePolynomial>,
        taylor: SparsePolynomial,
        mlp: Option<Mlp>,
        mlp_power: u32,
    ) -> Result<Self, CoreError> {
        if !(1..=MAX_DIM).contains(&dim) {
            return Err(CoreError::Invalid(format!(
                "dimension {dim} is outside 1..={MAX_DIM}"
            )));
        }
        if mlp.is_some() && !(1..=64).contains(&mlp_power) {
            return Err(CoreError::Invalid(format!(
                "mlp_power must be in 1..=64, got {mlp_power}"
            )));
        }
        let model = LearnedPolynomialModel {
            dim,
            sou,
            tar,
            taylor,
            mlp,
            mlp_power,
        };
        crate::with_dim!(dim, N => {
            model.stepper::<N>(NewtonOptions::default())?;
        }, return Err(CoreError::Invalid(format!("dimension {dim} is outside 1..={MAX_DIM}"))));
        Ok(model)
    }

    fn check_dim<const N: usize>(&self) -> Result<(), CoreError> {
        if N != self.dim {
            return Err(CoreError::Invalid(format!(
                "the model has dimension {}, not {N}",
                self.dim
            )));
        }
        Ok(())
    }

    /// The generating function, for N = `self.dim`.
    pub fn generating<const N: usize>(&self) -> Result<LearnedPolynomial<N>, CoreError> {
        self.check_dim::<N>()?;
        let network = GeneratingFunction::new(
            Polynomial::default(),
            self.mlp.clone(),
            self.mlp_power.max(1),
            MlpInputs::Plain,
        )?;
        LearnedPolynomial::new(PolynomialGenerating::new(self.taylor.clone())?, network)
    }

    /// The integrator (Newton stops once |δ|∞ ≤ tol · max(|x|∞, 1)), for N = `self.dim`.
    pub fn stepper<const N: usize>(
        &self,
        newton: NewtonOptions,
    ) -> Result<LearnedPolynomialBisection<N>, CoreError> {
        Ok(LearnedPolynomialBisection::unit_scale(
            self.generating::<N>()?,
            PolynomialRealization::new(self.sou.clone(), self.tar.clone())?,
            newton,
        ))
    }

    /// Terms of the Taylor part.
    pub fn n_taylor_terms(&self) -> usize {
        self.taylor.coeffs.len()
    }
}

#[cfg(test)]
mod learned_tests {
    //! The learned generating function on a realization: its jet is the sum of its parts, and
    //! a model with a zero network steps exactly as the Taylor integrator does.

    use super::*;
    use crate::generating::Layer;
    use crate::stepper::StepMap;

    /// A fixed tanh MLP R^{1+3} → R, one hidden layer of 5 (weights from a sine pattern),
    /// its last layer scaled by `gain`.
    fn mlp(gain: f64) -> Mlp {
        let w0: Vec<f64> = (0..20).map(|k| 0.7 * (1.3 * k as f64).sin()).collect();
        let b0: Vec<f64> = (0..5).map(|k| 0.2 * (0.9 * k as f64).cos()).collect();
        let w1: Vec<f64> = (0..5)
            .map(|k| gain * (2.1 * k as f64 + 0.3).sin())
            .collect();
        Mlp::new(vec![
            Layer::new(4, 5, w0, b0).unwrap(),
            Layer::new(5, 1, w1, vec![0.1 * gain]).unwrap(),
        ])
        .unwrap()
    }

    /// so(3) (π = x̂, linear) at order 1: β = x − ½ x × p... written as polynomials in
    /// (p, x): β_i = x_i − ½ ε_ijk x_k p_j, α with +½; S = −t |x|²/2.
    fn model(gain: f64) -> LearnedPolynomialModel {
        let eps = |i: usize, j: usize, k: usize| -> f64 {
            match (i, j, k) {
                (0, 1, 2) | (1, 2, 0) | (2, 0, 1) => 1.0,
                (0, 2, 1) | (2, 1, 0) | (1, 0, 2) => -1.0,
                _ => 0.0,
            }
        };
        let maps = |sign: f64| -> Vec<SparsePolynomial> {
            (0..3)
                .map(|i| {
                    let mut coeffs = vec![1.0];
                    let mut exps = vec![0u32; 6];
                    exps[3 + i] = 1;
                    for j in 0..3 {
                        for k in 0..3 {
                            let e = eps(i, j, k);
                            if e != 0.0 {
                                coeffs.push(sign * 0.5 * e);
                                let mut row = vec![0u32; 6];
                                row[j] = 1;
                                row[3 + k] = 1;
                                exps.extend(row);
                            }
                        }
                    }
                    SparsePolynomial::new(6, &coeffs, &exps).unwrap()
                })
                .collect()
        };
        let s = SparsePolynomial::new(
            4,
            &[-0.5, -0.5, -0.5],
            &[1, 2, 0, 0, 1, 0, 2, 0, 1, 0, 0, 2],
        )
        .unwrap();
        LearnedPolynomialModel::new(3, maps(-1.0), maps(1.0), s, Some(mlp(gain)), 3).unwrap()
    }

    #[test]
    fn jet_is_the_sum_of_the_taylor_and_network_jets() {
        let s = model(0.5).generating::<3>().unwrap();
        let mut ws = Generating::workspace(&s);
        let x = [0.2, -0.4, 0.7];
        let jet = Generating::jet(&s, 0.1, &x, &mut ws);
        let sum = Generating::jet(&s.taylor, 0.1, &x, &mut ()) + s.network.jet(0.1, &x, &mut ws);
        assert_eq!(jet, sum);
        let grad = Generating::gradient(&s, 0.1, &x, &mut ws);
        for i in 0..3 {
            assert!((grad.g[i] - jet.g[i]).abs() <= 1e-15);
        }
    }

    #[test]
    fn zero_network_steps_as_the_taylor_integrator() {
        let learned = model(0.0).stepper::<3>(NewtonOptions::default()).unwrap();
        let taylor = PolynomialBisection::<3>::unit_scale(
            learned.generating.taylor.clone(),
            learned.realization.clone(),
            NewtonOptions::default(),
        );
        let (mut a, mut b) = ([0.3, 0.5, -0.4], [0.3, 0.5, -0.4]);
        let mut ws = learned.workspace();
        for _ in 0..20 {
            learned.step(0.1, &mut a, &mut ws).unwrap();
            taylor.step(0.1, &mut b, &mut ()).unwrap();
        }
        for i in 0..3 {
            assert!((a[i] - b[i]).abs() <= 1e-14, "{a:?} vs {b:?}");
        }
    }

    #[test]
    fn bad_models_are_refused() {
        let m = model(0.5);
        let err = LearnedPolynomialModel::new(
            3,
            m.sou.clone(),
            m.tar.clone(),
            m.taylor.clone(),
            m.mlp.clone(),
            0,
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("mlp_power"), "{err}");
        let err = LearnedPolynomialModel::new(
            2,
            m.sou.clone(),
            m.tar.clone(),
            m.taylor.clone(),
            m.mlp.clone(),
            3,
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("inputs") || err.contains("variables"), "{err}");
    }
}

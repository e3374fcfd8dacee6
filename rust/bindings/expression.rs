//! Hamiltonians given as expressions: their jets, their vector field on a polynomial bivector,
//! and Taylor-HJ by jets on a polynomial realization or a Lie algebra.

use numpy::ndarray::{Array1, Array2, Array3, Ix1, Ix2, Ix3};
use numpy::{
    IntoPyArray, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods,
};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use super::polynomial::{component_polynomials, indexed_polynomials, polynomial, term_table};
use super::rollout::run_rollout;
use super::{check_output_bytes, detached, dim_error, states, Array};

use crate::distance_sum::{DistanceSum, MAX_POINT_DIM};
use crate::dual::Jet2;
use crate::error::CoreError;
use crate::expression::Expression;
use crate::jet_hj::{JetGenerating, LieSource, PolynomialSource, SeriesSource};
use crate::lanes::Lanes;
use crate::rollout::PerStep;
use crate::stepper::NewtonOptions;
use crate::structures::bivector::{DistanceField, HamiltonianField};
use crate::structures::lie_groupoid::LieAlgebra;
use crate::structures::lie_poisson::VectorField;
use crate::structures::point_vortices::PointVortices;
use crate::structures::PolynomialRealization;
use crate::with_dim;

/// An expression tape from its table (see [`crate::expression::Expression::from_table`]).
pub(super) fn expression(
    vars: usize,
    code: &PyReadonlyArray1<'_, i64>,
    a: &PyReadonlyArray1<'_, i64>,
    b: &PyReadonlyArray1<'_, i64>,
    c: &PyReadonlyArray1<'_, f64>,
) -> PyResult<Expression> {
    let (code, a, b, c) = (code.as_array(), a.as_array(), b.as_array(), c.as_array());
    let slice = |v: &numpy::ndarray::ArrayView1<'_, i64>| v.iter().copied().collect::<Vec<i64>>();
    let cs: Vec<f64> = c.iter().copied().collect();
    Expression::from_table(vars, &slice(&code), &slice(&a), &slice(&b), &cs)
        .map_err(|e| PyValueError::new_err(format!("hamiltonian: {e}")))
}

/// H, ∇H and ∇²H of an expression at each row of `x` (n, vars), exactly (forward mode).
#[pyfunction]
pub(super) fn expression_jets<'py>(
    py: Python<'py>,
    code: PyReadonlyArray1<'py, i64>,
    a: PyReadonlyArray1<'py, i64>,
    b: PyReadonlyArray1<'py, i64>,
    c: PyReadonlyArray1<'py, f64>,
    x: PyReadonlyArray2<'py, f64>,
) -> PyResult<(Array<'py, Ix1>, Array<'py, Ix2>, Array<'py, Ix3>)> {
    let dim = x.shape()[1];
    let n = x.shape()[0];
    check_output_bytes(n.saturating_mul(1 + dim + dim * dim), 0)?;
    with_dim!(dim, N => {
        let e = expression(N, &code, &a, &b, &c)?;
        let rows = states::<N>(&x, "x")?;
        let jets = detached(py, || {
            let mut out = Vec::new();
            out.try_reserve_exact(rows.len())
                .map_err(|_| CoreError::Memory("the jets".into()))?;
            out.extend(rows.iter().map(|r| {
                let d: [Jet2<N>; N] = std::array::from_fn(|i| Jet2::var(r[i], i));
                e.eval(&d)
            }));
            Ok(out)
        })?;
        let value = Array1::from_iter(jets.iter().map(|j| j.v));
        let grad = Array2::from_shape_fn((n, N), |(k, i)| jets[k].g[i]);
        let hess = Array3::from_shape_fn((n, N, N), |(k, i, j)| jets[k].hess()[i][j]);
        Ok((value.into_pyarray(py), grad.into_pyarray(py), hess.into_pyarray(py)))
    }, Err(dim_error(dim)))
}

/// ẋ = π(x) ∇H(x) at each row of `x` (n, N): H an expression, π's upper triangle (π_ij,
/// i < j, row by row) a term table (index, coeffs, exponents (M, N)).
#[pyfunction]
#[pyo3(signature = (code, a, b, c, upper_index, upper_coeffs, upper_exponents, x, program=None, distances=None))]
#[allow(clippy::too_many_arguments)]
pub(super) fn hamiltonian_field<'py>(
    py: Python<'py>,
    code: PyReadonlyArray1<'py, i64>,
    a: PyReadonlyArray1<'py, i64>,
    b: PyReadonlyArray1<'py, i64>,
    c: PyReadonlyArray1<'py, f64>,
    upper_index: PyReadonlyArray1<'py, i64>,
    upper_coeffs: PyReadonlyArray1<'py, f64>,
    upper_exponents: PyReadonlyArray2<'py, i64>,
    x: PyReadonlyArray2<'py, f64>,
    program: Option<FieldProgram<'py>>,
    distances: Option<DistanceTable<'py>>,
) -> PyResult<Array<'py, Ix2>> {
    let dim = x.shape()[1];
    let n = x.shape()[0];
    check_output_bytes(n.saturating_mul(dim), 0)?;
    with_dim!(dim, N => {
        let field = field_of::<N>(&code, &a, &b, &c, &upper_index, &upper_coeffs, &upper_exponents, program.as_ref(), distances.as_ref())?;
        let rows = states::<N>(&x, "x")?;
        let out = detached(py, || {
            let mut out = Vec::new();
            out.try_reserve_exact(rows.len())
                .map_err(|_| CoreError::Memory("the field".into()))?;
            out.extend(rows.iter().map(|r| field.field(r)));
            Ok(out)
        })?;
        Ok(Array2::from_shape_fn((n, N), |(k, i)| out[k][i]).into_pyarray(py))
    }, Err(dim_error(dim)))
}

/// A vector field's program: (code, a, b, c, outputs), as an expression's table plus the
/// registers of the N outputs.
pub(super) type FieldProgram<'py> = (
    PyReadonlyArray1<'py, i64>,
    PyReadonlyArray1<'py, i64>,
    PyReadonlyArray1<'py, i64>,
    PyReadonlyArray1<'py, f64>,
    PyReadonlyArray1<'py, i64>,
);

/// H as a sum over distances ([`DistanceSum`]): (radial (K,), weight (K,), power (K,), dims
/// (K,), first (K, 3), second (K, 3)) per term, and the polynomial rest as a term table
/// (coeffs (M,), exponents (M, N)).
pub(super) type DistanceTable<'py> = (
    PyReadonlyArray1<'py, i64>,
    PyReadonlyArray1<'py, f64>,
    PyReadonlyArray1<'py, f64>,
    PyReadonlyArray1<'py, i64>,
    PyReadonlyArray2<'py, i64>,
    PyReadonlyArray2<'py, i64>,
    PyReadonlyArray1<'py, f64>,
    PyReadonlyArray2<'py, i64>,
);

/// The [`DistanceSum`] of a table, every shape and entry checked (errors name `distances` and
/// the field).
fn distance_sum<const N: usize>(t: &DistanceTable<'_>) -> PyResult<DistanceSum> {
    let (radial, weight, power, dims, first, second, coeffs, exponents) = t;
    let k = radial.len();
    let points =
        |a: &PyReadonlyArray2<'_, i64>, what: &str| -> PyResult<Vec<[i64; MAX_POINT_DIM]>> {
            let v = a.as_array();
            if v.shape() != [k, MAX_POINT_DIM] {
                return Err(PyValueError::new_err(format!(
                    "distances: {what} must have shape ({k}, {MAX_POINT_DIM}), got {:?}",
                    v.shape()
                )));
            }
            Ok(v.outer_iter()
                .map(|row| std::array::from_fn(|j| row[j]))
                .collect())
        };
    let (first, second) = (points(first, "first")?, points(second, "second")?);
    let (co, ex) = term_table("distances: the polynomial", coeffs, exponents, N)?;
    let rest = if co.is_empty() {
        None
    } else {
        let rows: Vec<usize> = (0..co.len()).collect();
        Some(polynomial("distances: the polynomial", &co, &ex, &rows, N)?)
    };
    let slice_i = |a: &PyReadonlyArray1<'_, i64>| a.as_array().iter().copied().collect::<Vec<_>>();
    let slice_f = |a: &PyReadonlyArray1<'_, f64>| a.as_array().iter().copied().collect::<Vec<_>>();
    DistanceSum::new(
        N,
        &slice_i(radial),
        &slice_f(weight),
        &slice_f(power),
        &slice_i(dims),
        &first,
        &second,
        rest,
    )
    .map_err(|e| PyValueError::new_err(format!("distances: {e}")))
}

#[allow(clippy::too_many_arguments)]
pub(super) fn field_of<const N: usize>(
    code: &PyReadonlyArray1<'_, i64>,
    a: &PyReadonlyArray1<'_, i64>,
    b: &PyReadonlyArray1<'_, i64>,
    c: &PyReadonlyArray1<'_, f64>,
    upper_index: &PyReadonlyArray1<'_, i64>,
    upper_coeffs: &PyReadonlyArray1<'_, f64>,
    upper_exponents: &PyReadonlyArray2<'_, i64>,
    program: Option<&FieldProgram<'_>>,
    distances: Option<&DistanceTable<'_>>,
) -> PyResult<HamiltonianField<N>> {
    let e = expression(N, code, a, b, c)?;
    let program = match program {
        None => None,
        Some((pc, pa, pb, pcc, po)) => {
            let v =
                |x: &PyReadonlyArray1<'_, i64>| x.as_array().iter().copied().collect::<Vec<i64>>();
            let consts: Vec<f64> = pcc.as_array().iter().copied().collect();
            Some(
                Expression::program(N, &v(pc), &v(pa), &v(pb), &consts, &v(po))
                    .map_err(|e| PyValueError::new_err(format!("field program: {e}")))?,
            )
        }
    };
    let upper = indexed_polynomials(
        "bivector",
        upper_index,
        upper_coeffs,
        upper_exponents,
        N * (N - 1) / 2,
        N,
    )?;
    let distances = distances.map(distance_sum::<N>).transpose()?;
    Ok(HamiltonianField::<N>::new(upper, e, program, distances)?)
}

/// Rolls out "rk4" or "midpoint" on ẋ = π(x) ∇H(x) (arguments as [`hamiltonian_field`]) from
/// each row of `x0` (n, N), in SIMD lanes; the midpoint's Newton stops at |δ|∞ ≤ tol ·
/// max(|m|∞, 1e-300).
#[pyfunction]
#[pyo3(signature = (name, code, a, b, c, upper_index, upper_coeffs, upper_exponents, x0, h, n_steps, every=1, tol=1e-13, max_iter=50, program=None, distances=None))]
#[allow(clippy::too_many_arguments)]
pub(super) fn rollout_hamiltonian_field<'py>(
    py: Python<'py>,
    name: &str,
    code: PyReadonlyArray1<'py, i64>,
    a: PyReadonlyArray1<'py, i64>,
    b: PyReadonlyArray1<'py, i64>,
    c: PyReadonlyArray1<'py, f64>,
    upper_index: PyReadonlyArray1<'py, i64>,
    upper_coeffs: PyReadonlyArray1<'py, f64>,
    upper_exponents: PyReadonlyArray2<'py, i64>,
    x0: PyReadonlyArray2<'py, f64>,
    h: f64,
    n_steps: usize,
    every: usize,
    tol: f64,
    max_iter: u32,
    program: Option<FieldProgram<'py>>,
    distances: Option<DistanceTable<'py>>,
) -> PyResult<(Array<'py, Ix3>, Bound<'py, PyDict>)> {
    let newton = NewtonOptions::validated(tol, max_iter)?;
    let dim = x0.shape()[1];
    with_dim!(dim, N => {
        let field = field_of::<N>(&code, &a, &b, &c, &upper_index, &upper_coeffs, &upper_exponents, program.as_ref(), distances.as_ref())?;
        let x0 = states::<N>(&x0, "x0")?;
        match name {
            "rk4" if field.has_distances() => match PointVortices::new(field) {
                Ok(vortices) => {
                    let rk4 = crate::classical::Rk4 { system: vortices };
                    run_rollout(py, &Lanes::new(&rk4), &x0, h, n_steps, every, None)
                }
                Err(field) => {
                    let rk4 = crate::classical::Rk4 { system: DistanceField::new(field)? };
                    run_rollout(py, &Lanes::new(&rk4), &x0, h, n_steps, every, None)
                }
            },
            "rk4" => {
                let rk4 = crate::classical::Rk4 { system: field };
                run_rollout(py, &Lanes::new(&rk4), &x0, h, n_steps, every, None)
            }
            "midpoint" => {
                let midpoint = crate::classical::ImplicitMidpoint { system: field, newton };
                run_rollout(py, &Lanes::new(&midpoint), &x0, h, n_steps, every, None)
            }
            other => Err(PyValueError::new_err(format!(
                "unknown integrator {other:?} for an expression Hamiltonian; valid: rk4, midpoint"
            ))),
        }
    }, Err(dim_error(dim)))
}

/// Runs the jet Taylor-HJ stepper of `generating` on `realization` after checking that its
/// workspaces (one per thread) fit.
#[allow(clippy::too_many_arguments)]
pub(super) fn run_jets<'py, const N: usize, R, S>(
    py: Python<'py>,
    generating: JetGenerating<N, S>,
    realization: R,
    newton: NewtonOptions,
    x0: &[[f64; N]],
    h: f64,
    n_steps: usize,
    every: usize,
) -> PyResult<(Array<'py, Ix3>, Bound<'py, PyDict>)>
where
    R: crate::realization::Realization<N> + 'static,
    S: SeriesSource<N>,
    nalgebra::Const<N>: nalgebra::DimMin<nalgebra::Const<N>, Output = nalgebra::Const<N>>,
{
    let threads = rayon::current_num_threads().max(1);
    check_output_bytes(0, generating.workspace_bytes().saturating_mul(threads))?;
    let stepper = crate::stepper::BisectionStepper::unit_scale(generating, realization, newton);
    run_rollout(py, &PerStep(&stepper), x0, h, n_steps, every, None)
}

/// Rolls out Taylor-HJ of order `order` by jets for an expression H on the realization given by
/// polynomial maps sou (β) and tar (α), N polynomials each in (p, x) (as
/// `rollout_polynomial_realization`), from each row of `x0` (n, N).
#[pyfunction]
#[pyo3(signature = (code, a, b, c, hamiltonian_vars, order, sou_index, sou_coeffs, sou_exponents, tar_index, tar_coeffs, tar_exponents, x0, h, n_steps, every=1, tol=1e-13, max_iter=50))]
#[allow(clippy::too_many_arguments)]
pub(super) fn rollout_jets_polynomial<'py>(
    py: Python<'py>,
    code: PyReadonlyArray1<'py, i64>,
    a: PyReadonlyArray1<'py, i64>,
    b: PyReadonlyArray1<'py, i64>,
    c: PyReadonlyArray1<'py, f64>,
    hamiltonian_vars: usize,
    order: usize,
    sou_index: PyReadonlyArray1<'py, i64>,
    sou_coeffs: PyReadonlyArray1<'py, f64>,
    sou_exponents: PyReadonlyArray2<'py, i64>,
    tar_index: PyReadonlyArray1<'py, i64>,
    tar_coeffs: PyReadonlyArray1<'py, f64>,
    tar_exponents: PyReadonlyArray2<'py, i64>,
    x0: PyReadonlyArray2<'py, f64>,
    h: f64,
    n_steps: usize,
    every: usize,
    tol: f64,
    max_iter: u32,
) -> PyResult<(Array<'py, Ix3>, Bound<'py, PyDict>)> {
    let newton = NewtonOptions::validated(tol, max_iter)?;
    let dim = x0.shape()[1];
    with_dim!(dim, N => {
        let e = expression(hamiltonian_vars, &code, &a, &b, &c)?;
        let sou = component_polynomials::<N>("sou", &sou_index, &sou_coeffs, &sou_exponents, 2 * N)?;
        let tar = component_polynomials::<N>("tar", &tar_index, &tar_coeffs, &tar_exponents, 2 * N)?;
        let generating = JetGenerating::<N, _>::new(e, PolynomialSource::<N>::new(sou.clone())?, order)?;
        let realization = PolynomialRealization::<N>::new(sou, tar)?;
        let x0 = states::<N>(&x0, "x0")?;
        run_jets(py, generating, realization, newton, &x0, h, n_steps, every)
    }, Err(dim_error(dim)))
}

/// Rolls out Taylor-HJ of order `order` by jets for an expression H of the first
/// `hamiltonian_vars` coordinates on the exact groupoid of the Lie algebra with structure
/// constants `c_lie` (N, N, N), in the exponential chart, from each row of `x0` (n, N).
#[pyfunction]
#[pyo3(signature = (code, a, b, c, hamiltonian_vars, order, c_lie, x0, h, n_steps, every=1, tol=1e-13, max_iter=50))]
#[allow(clippy::too_many_arguments)]
pub(super) fn rollout_jets_lie<'py>(
    py: Python<'py>,
    code: PyReadonlyArray1<'py, i64>,
    a: PyReadonlyArray1<'py, i64>,
    b: PyReadonlyArray1<'py, i64>,
    c: PyReadonlyArray1<'py, f64>,
    hamiltonian_vars: usize,
    order: usize,
    c_lie: PyReadonlyArray3<'py, f64>,
    x0: PyReadonlyArray2<'py, f64>,
    h: f64,
    n_steps: usize,
    every: usize,
    tol: f64,
    max_iter: u32,
) -> PyResult<(Array<'py, Ix3>, Bound<'py, PyDict>)> {
    let newton = NewtonOptions::validated(tol, max_iter)?;
    let dim = x0.shape()[1];
    with_dim!(dim, N => {
        if c_lie.shape() != [N, N, N] {
            return Err(PyValueError::new_err(format!(
                "c_lie must have shape ({N}, {N}, {N}), got {:?}",
                c_lie.shape()
            )));
        }
        let cl = c_lie.as_array();
        let constants: [[[f64; N]; N]; N] =
            std::array::from_fn(|i| std::array::from_fn(|j| std::array::from_fn(|k| cl[[i, j, k]])));
        let e = expression(hamiltonian_vars, &code, &a, &b, &c)?;
        let algebra = LieAlgebra::<N>::new(constants)?;
        let groupoid = crate::structures::lie_groupoid::Groupoid::new(
            algebra,
            crate::structures::lie_groupoid::Chart::Exp,
        )?;
        let generating = JetGenerating::<N, _>::new(e, LieSource::<N>::new(&constants), order)?;
        let x0 = states::<N>(&x0, "x0")?;
        run_jets(py, generating, groupoid, newton, &x0, h, n_steps, every)
    }, Err(dim_error(dim)))
}

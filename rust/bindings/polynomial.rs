//! Any polynomial bivector: Taylor-HJ bisection on an approximate realization whose maps and
//! generating function arrive as polynomial coefficients, and the classical baselines on its
//! field.

use numpy::ndarray::Ix3;
use numpy::{PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::{PyMemoryError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use super::rollout::run_rollout;
use super::{dim_error, rows_match, states, Array};

use crate::lanes::Lanes;
use crate::stepper::NewtonOptions;
use crate::structures::{
    PolynomialBisection, PolynomialField, PolynomialGenerating, PolynomialLanes,
    PolynomialRealization, SparsePolynomial,
};
use crate::with_dim;

/// One polynomial in `vars` variables from the rows `rows` of a term table.
pub(super) fn polynomial(
    what: &str,
    coeffs: &numpy::ndarray::ArrayView1<'_, f64>,
    exponents: &numpy::ndarray::ArrayView2<'_, i64>,
    rows: &[usize],
    vars: usize,
) -> PyResult<SparsePolynomial> {
    let mut e = Vec::new();
    e.try_reserve_exact(rows.len() * vars)
        .map_err(|_| PyMemoryError::new_err("too many polynomial terms"))?;
    for &k in rows {
        for v in 0..vars {
            let value = exponents[[k, v]];
            e.push(u32::try_from(value).map_err(|_| {
                PyValueError::new_err(format!(
                    "{what} exponents[{k}, {v}] = {value} must not be negative"
                ))
            })?);
        }
    }
    let c: Vec<f64> = rows.iter().map(|&k| coeffs[k]).collect();
    SparsePolynomial::new(vars, &c, &e)
        .map_err(|err| PyValueError::new_err(format!("{what}: {err}")))
}

/// Checks a term table: `coeffs` (M,), `exponents` (M, vars).
pub(super) fn term_table<'a>(
    what: &str,
    coeffs: &'a PyReadonlyArray1<'_, f64>,
    exponents: &'a PyReadonlyArray2<'_, i64>,
    vars: usize,
) -> PyResult<(
    numpy::ndarray::ArrayView1<'a, f64>,
    numpy::ndarray::ArrayView2<'a, i64>,
)> {
    let (co, ex) = (coeffs.as_array(), exponents.as_array());
    rows_match(&format!("{what} exponents"), ex.shape()[0], co.len())?;
    if ex.shape()[1] != vars {
        return Err(PyValueError::new_err(format!(
            "{what} exponents must have {vars} columns, got {}",
            ex.shape()[1]
        )));
    }
    Ok((co, ex))
}

/// N polynomials in 2N variables from one term table: term m adds coeffs[m] · v^exponents[m]
/// to component index[m].
pub(super) fn component_polynomials<const N: usize>(
    what: &str,
    index: &PyReadonlyArray1<'_, i64>,
    coeffs: &PyReadonlyArray1<'_, f64>,
    exponents: &PyReadonlyArray2<'_, i64>,
    vars: usize,
) -> PyResult<Vec<SparsePolynomial>> {
    indexed_polynomials(what, index, coeffs, exponents, N, vars)
}

/// `count` polynomials in `vars` variables from one term table: term m adds
/// coeffs[m] · v^exponents[m] to polynomial index[m].
pub(super) fn indexed_polynomials(
    what: &str,
    index: &PyReadonlyArray1<'_, i64>,
    coeffs: &PyReadonlyArray1<'_, f64>,
    exponents: &PyReadonlyArray2<'_, i64>,
    count: usize,
    vars: usize,
) -> PyResult<Vec<SparsePolynomial>> {
    let (co, ex) = term_table(what, coeffs, exponents, vars)?;
    let ix = index.as_array();
    rows_match(&format!("{what} index"), ix.len(), co.len())?;
    if let Some(k) = (0..ix.len()).find(|&k| !(0..count as i64).contains(&ix[k])) {
        return Err(PyValueError::new_err(format!(
            "{what} index[{k}] = {} is outside 0..{count}",
            ix[k]
        )));
    }
    let mut out = Vec::new();
    out.try_reserve_exact(count)
        .map_err(|_| PyMemoryError::new_err("too many polynomials"))?;
    for target in 0..count {
        let rows: Vec<usize> = (0..ix.len()).filter(|&k| ix[k] == target as i64).collect();
        out.push(polynomial(
            &format!("{what}[{target}]"),
            &co,
            &ex,
            &rows,
            vars,
        )?);
    }
    Ok(out)
}

/// Rolls out Taylor-HJ on an approximate realization of a polynomial bivector, from each row of
/// `x0` (n, N). β (sou) and α (tar) are N polynomials each in (p, x) (2N variables: the fibre p
/// then the base x), given as term tables (index: which component, coeffs, exponents (M, 2N));
/// S(t, x) is one polynomial in (t, x) (exponents (K, N + 1)). A step solves
/// α(∇S(h, x), x) = x_k for x by Newton (|δ|∞ ≤ tol · max(|x|∞, 1)) and returns
/// β(∇S(h, x), x).
#[pyfunction]
#[pyo3(signature = (sou_index, sou_coeffs, sou_exponents, tar_index, tar_coeffs, tar_exponents, s_coeffs, s_exponents, x0, h, n_steps, every=1, tol=1e-13, max_iter=50))]
#[allow(clippy::too_many_arguments)]
pub(super) fn rollout_polynomial_realization<'py>(
    py: Python<'py>,
    sou_index: PyReadonlyArray1<'py, i64>,
    sou_coeffs: PyReadonlyArray1<'py, f64>,
    sou_exponents: PyReadonlyArray2<'py, i64>,
    tar_index: PyReadonlyArray1<'py, i64>,
    tar_coeffs: PyReadonlyArray1<'py, f64>,
    tar_exponents: PyReadonlyArray2<'py, i64>,
    s_coeffs: PyReadonlyArray1<'py, f64>,
    s_exponents: PyReadonlyArray2<'py, i64>,
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
        let sou = component_polynomials::<N>("sou", &sou_index, &sou_coeffs, &sou_exponents, 2 * N)?;
        let tar = component_polynomials::<N>("tar", &tar_index, &tar_coeffs, &tar_exponents, 2 * N)?;
        let (co, ex) = term_table("S", &s_coeffs, &s_exponents, N + 1)?;
        let all: Vec<usize> = (0..co.len()).collect();
        let s = polynomial("S", &co, &ex, &all, N + 1)?;
        let stepper = PolynomialBisection::<N>::unit_scale(
            PolynomialGenerating::new(s)?,
            PolynomialRealization::new(sou, tar)?,
            newton,
        );
        // The Newton systems solved in SIMD lanes (every lane the scalar bits).
        let lanes = PolynomialLanes::new(&stepper)?;
        let x0 = states::<N>(&x0, "x0")?;
        run_rollout(py, &Lanes::new(&lanes), &x0, h, n_steps, every, None)
    }, Err(dim_error(dim)))
}

/// Rolls out a classical baseline of a polynomial vector field ẋ_i = f_i(x) (the components as
/// one term table: index (which component), coeffs, exponents (M, N)) from each row of `x0`
/// (n, N): "rk4", or "midpoint" (Newton on the midpoint m with the exact Jacobian, |δ|∞ ≤
/// tol · max(|m|∞, 1e-300)),
/// stepped in SIMD lanes.
#[pyfunction]
#[pyo3(signature = (name, index, coeffs, exponents, x0, h, n_steps, every=1, tol=1e-13, max_iter=50))]
#[allow(clippy::too_many_arguments)]
pub(super) fn rollout_polynomial_field<'py>(
    py: Python<'py>,
    name: &str,
    index: PyReadonlyArray1<'py, i64>,
    coeffs: PyReadonlyArray1<'py, f64>,
    exponents: PyReadonlyArray2<'py, i64>,
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
        let f = component_polynomials::<N>("f", &index, &coeffs, &exponents, N)?;
        let field = PolynomialField::<N>::new(f)?;
        let x0 = states::<N>(&x0, "x0")?;
        match name {
            "rk4" => {
                let rk4 = crate::classical::Rk4 { system: field };
                run_rollout(py, &Lanes::new(&rk4), &x0, h, n_steps, every, None)
            }
            "midpoint" => {
                let midpoint = crate::classical::ImplicitMidpoint { system: field, newton };
                run_rollout(py, &Lanes::new(&midpoint), &x0, h, n_steps, every, None)
            }
            other => Err(PyValueError::new_err(format!(
                "unknown polynomial-field integrator {other:?}; valid: rk4, midpoint"
            ))),
        }
    }, Err(dim_error(dim)))
}

//! Log-canonical structures π_ij = c_ij x_i x_j (Lotka–Volterra): Taylor-HJ bisection on the
//! exact groupoid and the classical baselines.

use numpy::ndarray::Ix3;
use numpy::{PyReadonlyArray1, PyReadonlyArray2, PyReadwriteArrayDyn, PyUntypedArrayMethods};
use pyo3::exceptions::{PyMemoryError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use super::rollout::run_rollout;
use super::{detached, dim_error, polynomial_terms, rows_match, states, Array};

use crate::lanes::Lanes;
use crate::rollout::PerStep;
use crate::stepper::NewtonOptions;
use crate::structures::{
    ExpMonomial, ExpPolynomial, LogBisection, LogCanonical, LogClassical, LogMethod, LogSystem,
    OrthantChecked,
};
use crate::with_dim;

/// `x ← ln x` elementwise, in place, by libm: the states' change of coordinates into q = ln x.
/// NumPy's log and exp dispatch on the CPU (an AVX-512 kernel where there is one) and differ
/// from libm in the last bit on some arguments, so a rollout converted by them would not keep
/// its bits from one machine to the next; libm's are the ones the scalar steps use.
#[pyfunction]
pub(super) fn log_in_place(py: Python<'_>, mut x: PyReadwriteArrayDyn<'_, f64>) -> PyResult<()> {
    let values = x
        .as_slice_mut()
        .map_err(|_| PyValueError::new_err("x must be a C-contiguous float64 array"))?;
    detached(py, || {
        values.iter_mut().for_each(|v| *v = v.ln());
        Ok(())
    })
}

/// `q ← e^q` elementwise, in place, by libm: the rollouts' states back from q = ln x (see
/// [`log_in_place`]).
#[pyfunction]
pub(super) fn exp_in_place(py: Python<'_>, mut q: PyReadwriteArrayDyn<'_, f64>) -> PyResult<()> {
    let values = q
        .as_slice_mut()
        .map_err(|_| PyValueError::new_err("q must be a C-contiguous float64 array"))?;
    detached(py, || {
        values.iter_mut().for_each(|v| *v = v.exp());
        Ok(())
    })
}

/// The (N, N) structure matrix c as a checked [`LogCanonical`].
pub(super) fn log_structure<const N: usize>(
    c: &PyReadonlyArray2<'_, f64>,
) -> PyResult<LogCanonical<N>> {
    let c = c.as_array();
    if c.shape() != [N, N] {
        return Err(PyValueError::new_err(format!(
            "c must have shape ({N}, {N}), got {:?}",
            c.shape()
        )));
    }
    Ok(LogCanonical::new(std::array::from_fn(|i| {
        std::array::from_fn(|j| c[[i, j]])
    }))?)
}

/// Rolls out the bisection integrator of the generating function
/// S(t, q) = Σ_m coeffs[m] t^t_powers[m] e^{exponents[m]·q} + t · linear·q on the log-canonical
/// groupoid of `c` (N, N), from each row of `q0` (n, N), in q = ln x: solve
/// q + ½ c ∇S(q) = q_k, then q_{k+1} = q − ½ c ∇S(q). Newton stops once
/// |δ|∞ ≤ tol · max(|q|∞, 1). A step whose e^q leaves the float64 orthant fails (code 5 or 3).
///
/// Returns the trajectories in q (n, n_steps // every + 1, N) and a dict of per-trajectory
/// arrays. Ctrl-C interrupts it (KeyboardInterrupt) within about SEGMENT_SECONDS.
#[pyfunction]
#[pyo3(signature = (c, t_powers, exponents, coeffs, linear, q0, h, n_steps, every=1, tol=1e-12, max_iter=50))]
#[allow(clippy::too_many_arguments)]
pub(super) fn rollout_log_canonical<'py>(
    py: Python<'py>,
    c: PyReadonlyArray2<'py, f64>,
    t_powers: PyReadonlyArray1<'py, i64>,
    exponents: PyReadonlyArray2<'py, i64>,
    coeffs: PyReadonlyArray1<'py, f64>,
    linear: PyReadonlyArray1<'py, f64>,
    q0: PyReadonlyArray2<'py, f64>,
    h: f64,
    n_steps: usize,
    every: usize,
    tol: f64,
    max_iter: u32,
) -> PyResult<(Array<'py, Ix3>, Bound<'py, PyDict>)> {
    let newton = NewtonOptions::validated(tol, max_iter)?;
    let dim = c.shape()[0];
    let m = coeffs.shape()[0];
    rows_match("t_powers", t_powers.shape()[0], m)?;
    rows_match("exponents", exponents.shape()[0], m)?;
    with_dim!(dim, N => {
        let realization = log_structure::<N>(&c)?;
        let (tp, ex, co, lin) = (
            t_powers.as_array(),
            exponents.as_array(),
            coeffs.as_array(),
            linear.as_array(),
        );
        if ex.shape()[1] != N || lin.len() != N {
            return Err(PyValueError::new_err(format!(
                "exponents must have shape (M, {N}) and linear shape ({N},), got {:?} and {:?}",
                ex.shape(),
                lin.shape()
            )));
        }
        let mut terms = Vec::new();
        terms.try_reserve_exact(m).map_err(|_| PyMemoryError::new_err("too many terms"))?;
        for k in 0..m {
            let t_power = u32::try_from(tp[k])
                .ok()
                .filter(|&t| t <= 64)
                .ok_or_else(|| PyValueError::new_err(format!("t_powers[{k}] = {} is outside 0..=64", tp[k])))?;
            let mut exps = [0i32; N];
            for i in 0..N {
                exps[i] = i32::try_from(ex[[k, i]]).map_err(|_| {
                    PyValueError::new_err(format!("exponents[{k}, {i}] = {} is too large", ex[[k, i]]))
                })?;
            }
            terms.push(ExpMonomial { t_power, exponents: exps, coeff: co[k] });
        }
        let generating = ExpPolynomial::new(terms, std::array::from_fn(|i| lin[i]))?;
        let stepper = OrthantChecked(LogBisection::<N>::unit_scale(generating, realization, newton));
        let q0 = states::<N>(&q0, "q0")?;
        // The Newton systems solved in SIMD lanes (every lane the scalar bits).
        run_rollout(py, &Lanes::new(&stepper.0.lanes()), &q0, h, n_steps, every, None)
    }, Err(dim_error(dim)))
}

/// Rolls out the classical integrator `name` of the log-canonical system with structure `c`
/// (N, N) and H = Σ_m coeffs[m] x^powers[m] − Σ_i b_i ln x_i (powers int64 (M, N) ≥ 0), from
/// each row of `s0` (n, N): "rk4" and "midpoint" step x, "log_splitting" (Strang, order 2) and
/// "log_splitting4" (Suzuki, order 4) step q = ln x through the exact flows of the one-variable
/// parts of H (which must be separable). A step that leaves the open positive orthant fails with
/// code 5 ("left the domain").
#[pyfunction]
#[pyo3(signature = (name, c, powers, coeffs, b, s0, h, n_steps, every=1, tol=1e-12, max_iter=50))]
#[allow(clippy::too_many_arguments)]
pub(super) fn rollout_log_classical<'py>(
    py: Python<'py>,
    name: &str,
    c: PyReadonlyArray2<'py, f64>,
    powers: PyReadonlyArray2<'py, i64>,
    coeffs: PyReadonlyArray1<'py, f64>,
    b: PyReadonlyArray1<'py, f64>,
    s0: PyReadonlyArray2<'py, f64>,
    h: f64,
    n_steps: usize,
    every: usize,
    tol: f64,
    max_iter: u32,
) -> PyResult<(Array<'py, Ix3>, Bound<'py, PyDict>)> {
    let method = LogMethod::from_name(name)?;
    let newton = NewtonOptions::validated(tol, max_iter)?;
    let dim = c.shape()[0];
    rows_match("powers", powers.shape()[0], coeffs.shape()[0])?;
    with_dim!(dim, N => {
        let structure = log_structure::<N>(&c)?;
        let (pw, co, bb) = (powers.as_array(), coeffs.as_array(), b.as_array());
        if pw.shape()[1] != N || bb.len() != N {
            return Err(PyValueError::new_err(format!(
                "powers must have shape (M, {N}) and b shape ({N},), got {:?} and {:?}",
                pw.shape(),
                bb.shape()
            )));
        }
        let terms = polynomial_terms::<N>(pw, co)?;
        let system = LogSystem::new(structure, terms, std::array::from_fn(|i| bb[i]))?;
        let stepper = LogClassical::new(method, system, newton)?;
        let s0 = states::<N>(&s0, "s0")?;
        // Every method steps blocks of trajectories in SIMD lanes (the same bits).
        if let Some(midpoint) = stepper.midpoint_in_lanes() {
            return run_rollout(py, &Lanes::new(&midpoint), &s0, h, n_steps, every, None);
        }
        match stepper.explicit() {
            Some(explicit) => run_rollout(py, &Lanes::new(&explicit), &s0, h, n_steps, every, None),
            None => run_rollout(py, &PerStep(&stepper), &s0, h, n_steps, every, None),
        }
    }, Err(dim_error(dim)))
}

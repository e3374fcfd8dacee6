//! Lie–Poisson systems: the rigid body's and any system's classical baselines, and the step
//! angles a rollout reports.

use numpy::ndarray::{Array1, Ix1, Ix3};
use numpy::{
    IntoPyArray, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyMemoryError, PyValueError};
use pyo3::prelude::*;

use super::rollout::{angles_of, run_rollout_lazy};
use super::{
    check_output_bytes, detached, dim_error, initial_states, polynomial_terms, states, Array,
};

use crate::classical::{
    ClassicalMethod, ClassicalStepper, HeavyTop, LieMethod, LieStepper, RigidBody,
};
use crate::lanes::Lanes;
use crate::stepper::NewtonOptions;
use crate::straight_line::LieField;
use crate::structures::lie_groupoid::LieAlgebra;
use crate::structures::lie_poisson::{Hamiltonian, LiePoisson};
use crate::with_dim;

/// Rolls out the classical integrator `name` (rk4, midpoint, splitting, splitting4, dmv) for the
/// rigid body with principal moments `inertia` from each row of `mu0` (n, 3). `tol` and
/// `max_iter` set the Newton solve of the implicit methods (midpoint, dmv).
///
/// Returns the trajectories (n, n_steps // every + 1, 3) and a dict of per-trajectory arrays.
/// Ctrl-C interrupts it (KeyboardInterrupt) within about SEGMENT_SECONDS.
#[pyfunction]
#[pyo3(signature = (name, inertia, mu0, h, n_steps, every=1, tol=1e-12, max_iter=50, lazy=false))]
#[allow(clippy::too_many_arguments)]
pub(super) fn rollout_classical<'py>(
    py: Python<'py>,
    name: &str,
    inertia: [f64; 3],
    mu0: &Bound<'py, PyAny>,
    h: f64,
    n_steps: usize,
    every: usize,
    tol: f64,
    max_iter: u32,
    lazy: bool,
) -> PyResult<Option<(Array<'py, Ix3>, Bound<'py, PyAny>)>> {
    let method = ClassicalMethod::from_name(name)?;
    let body = RigidBody::new(inertia)?;
    let Some(mu0) = initial_states::<3>(mu0, "mu0")? else {
        return Ok(None);
    };
    let newton = NewtonOptions::validated(tol, max_iter)?;
    let angles = |m: &[[f64; 3]], o: &mut [f64]| angles_of(&body, h, m, o);
    // One arm per stepper type: the kernel is monomorphised for each.
    macro_rules! lanes {
        ($s:expr) => {
            run_rollout_lazy(py, &Lanes::new(&$s), &mu0, h, n_steps, every, Some(&angles))?
        };
    }
    let (traj, diagnostics) = match method.stepper(body, newton) {
        // Every method in SIMD lanes (rust/lanes.rs, rust/lanes_splitting.rs).
        ClassicalStepper::Rk4(s) => lanes!(s),
        ClassicalStepper::Midpoint(s) => lanes!(s),
        ClassicalStepper::Splitting(s) => lanes!(s),
        ClassicalStepper::Splitting4(s) => lanes!(s),
        ClassicalStepper::Dmv(s) => lanes!(s),
        ClassicalStepper::CasimirSplitting(s) => lanes!(s),
    };
    Ok(Some((traj, diagnostics.into_python(py, lazy)?)))
}

/// Heavy-top parameters for the splitting integrator: (inertia, mgl, centre of mass).
pub(super) type HeavyTopParameters = ([f64; 3], f64, [f64; 3]);

/// Rolls out the classical integrator `name` (rk4, midpoint; splitting for the heavy top) of
/// the Lie–Poisson system with structure constants `c` (N, N, N) and polynomial Hamiltonian
/// Σ coeffs[m] Π μ_i^powers[m, i] (powers int64 (M, N), coeffs (M,)), from each row of `mu0`
/// (n, N). `heavy_top` = (inertia, mgl, com) selects the heavy top's splitting.
#[pyfunction]
#[pyo3(signature = (name, c, powers, coeffs, mu0, h, n_steps, every=1, tol=1e-12, max_iter=50, heavy_top=None, lazy=false))]
#[allow(clippy::too_many_arguments)]
pub(super) fn rollout_lie_poisson<'py>(
    py: Python<'py>,
    name: &str,
    c: PyReadonlyArray3<'py, f64>,
    powers: PyReadonlyArray2<'py, i64>,
    coeffs: PyReadonlyArray1<'py, f64>,
    mu0: &Bound<'py, PyAny>,
    h: f64,
    n_steps: usize,
    every: usize,
    tol: f64,
    max_iter: u32,
    heavy_top: Option<HeavyTopParameters>,
    lazy: bool,
) -> PyResult<Option<(Array<'py, Ix3>, Bound<'py, PyAny>)>> {
    let method = LieMethod::from_name(name)?;
    let newton = NewtonOptions::validated(tol, max_iter)?;
    let shape = c.shape();
    let dim = shape[0];
    if shape[1] != dim || shape[2] != dim {
        return Err(PyValueError::new_err(format!(
            "structure constants must have shape (N, N, N), got {shape:?}"
        )));
    }
    if powers.shape()[1] != dim || powers.shape()[0] != coeffs.shape()[0] {
        return Err(PyValueError::new_err(format!(
            "the Hamiltonian needs powers of shape (M, {dim}) and coeffs of shape (M,), got {:?} \
             and {:?}",
            powers.shape(),
            coeffs.shape()
        )));
    }
    let top = heavy_top
        .map(|(i, mgl, com)| HeavyTop::new(i, mgl, com))
        .transpose()?;
    let (c, powers, coeffs) = (c.as_array(), powers.as_array(), coeffs.as_array());
    with_dim!(dim, N => {
        let algebra = LieAlgebra::<N>::new(std::array::from_fn(|i| {
            std::array::from_fn(|j| std::array::from_fn(|k| c[[i, j, k]]))
        }))?;
        let mut terms = Vec::with_capacity(coeffs.len());
        for (row, &coeff) in powers.rows().into_iter().zip(coeffs.iter()) {
            if let Some(&bad) = row.iter().find(|&&e| !(0..=64).contains(&e)) {
                return Err(PyValueError::new_err(format!(
                    "Hamiltonian exponent {bad} is outside 0..=64"
                )));
            }
            terms.push((std::array::from_fn(|i| row[i] as u32), coeff));
        }
        let system = LiePoisson { algebra, hamiltonian: Hamiltonian::new(terms)? };
        // The step check's rate from the field the steppers use (straight-line where the
        // system matches a pattern: a third of the compiled field's cost on the heavy top).
        let field = LieField::new(&system);
        let angles = |m: &[[f64; N]], o: &mut [f64]| angles_of(&field, h, m, o);
        let stepper = LieStepper::new(method, system, top, newton)?;
        let Some(mu0) = initial_states::<N>(mu0, "mu0")? else {
            return Ok(None);
        };
        let (traj, diagnostics) = match &stepper {
            // Every method in SIMD lanes (the splitting in rust/lanes_splitting.rs).
            LieStepper::Rk4(rk4) => {
                run_rollout_lazy(py, &Lanes::new(rk4), &mu0, h, n_steps, every, Some(&angles))?
            }
            LieStepper::Midpoint(mid) => {
                run_rollout_lazy(py, &Lanes::new(mid), &mu0, h, n_steps, every, Some(&angles))?
            }
            LieStepper::HeavyTop(top) => {
                run_rollout_lazy(py, &Lanes::new(top), &mu0, h, n_steps, every, Some(&angles))?
            }
        };
        Ok(Some((traj, diagnostics.into_python(py, lazy)?)))
    }, Err(dim_error(dim)))
}

/// h × the local rate at each row of `mu` (n, N) for the Lie–Poisson system with structure
/// constants `c` (N, N, N) and polynomial Hamiltonian Σ coeffs[m] Π μ_i^powers[m, i]: the angle
/// a step of size h turns each state by, max(‖ad_∇H‖_F/√2, ‖∂f/∂μ‖_F) · h. Returns (n,) float64.
#[pyfunction]
pub(super) fn step_angles<'py>(
    py: Python<'py>,
    c: PyReadonlyArray3<'py, f64>,
    powers: PyReadonlyArray2<'py, i64>,
    coeffs: PyReadonlyArray1<'py, f64>,
    mu: PyReadonlyArray2<'py, f64>,
    h: f64,
) -> PyResult<Array<'py, Ix1>> {
    if !(h.is_finite() && h > 0.0) {
        return Err(PyValueError::new_err(format!(
            "h must be a finite number > 0, got {h}"
        )));
    }
    let dim = c.shape()[0];
    with_dim!(dim, N => {
        let system = lie_poisson_system::<N>(&c, &powers, &coeffs)?.compile();
        let mu = states::<N>(&mu, "mu")?;
        check_output_bytes(mu.len(), 0)?;
        let mut out = Vec::new();
        out.try_reserve_exact(mu.len())
            .map_err(|_| PyMemoryError::new_err("cannot allocate the step angles"))?;
        out.resize(mu.len(), f64::NAN);
        detached(py, || {
            angles_of(&system, h, &mu, &mut out);
            Ok(())
        })?;
        Ok(Array1::from_vec(out).into_pyarray(py))
    }, Err(dim_error(dim)))
}

/// The Lie–Poisson system of structure constants `c` (N, N, N) and the polynomial Hamiltonian
/// Σ coeffs[m] Π μ_i^powers[m, i] (powers int64 (M, N), coeffs (M,)), checked.
pub(super) fn lie_poisson_system<const N: usize>(
    c: &PyReadonlyArray3<'_, f64>,
    powers: &PyReadonlyArray2<'_, i64>,
    coeffs: &PyReadonlyArray1<'_, f64>,
) -> PyResult<LiePoisson<N>> {
    let shape = c.shape();
    if shape != [N, N, N] {
        return Err(PyValueError::new_err(format!(
            "structure constants must have shape (N, N, N), got {shape:?}"
        )));
    }
    if powers.shape()[1] != N || powers.shape()[0] != coeffs.shape()[0] {
        return Err(PyValueError::new_err(format!(
            "the Hamiltonian needs powers of shape (M, {N}) and coeffs of shape (M,), got {:?} \
             and {:?}",
            powers.shape(),
            coeffs.shape()
        )));
    }
    let (c, powers, coeffs) = (c.as_array(), powers.as_array(), coeffs.as_array());
    let algebra = LieAlgebra::<N>::new(std::array::from_fn(|i| {
        std::array::from_fn(|j| std::array::from_fn(|k| c[[i, j, k]]))
    }))?;
    Ok(LiePoisson {
        algebra,
        hamiltonian: Hamiltonian::new(polynomial_terms::<N>(powers, coeffs)?)?,
    })
}

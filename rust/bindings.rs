//! Python bindings: the only module that knows about pyo3. It checks shapes, releases the GIL
//! around batch work and turns core errors into Python exceptions.

use std::path::PathBuf;
use std::time::Instant;

use numpy::ndarray::{Array1, Array2, Array3, Ix1, Ix2, Ix3};
use numpy::{IntoPyArray, PyArray, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::{
    PyFileNotFoundError, PyMemoryError, PyOSError, PyRuntimeError, PyValueError,
};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::classical::{ClassicalMethod, RigidBody};
use crate::error::CoreError;
use crate::model::{Model, FORMAT};
use crate::rollout::{n_records, Rollout, TrajectoryInfo};
use crate::stepper::{batch_size, NewtonOptions, StepMap};

impl From<CoreError> for PyErr {
    fn from(e: CoreError) -> PyErr {
        match e {
            CoreError::NotFound(_) => PyFileNotFoundError::new_err(e.to_string()),
            CoreError::Io(_) => PyOSError::new_err(e.to_string()),
            CoreError::Format(_) | CoreError::Invalid(_) => PyValueError::new_err(e.to_string()),
        }
    }
}

/// A float64 NumPy array owned by Python.
type Array<'py, D> = Bound<'py, PyArray<f64, D>>;

/// Largest trajectory array a call may allocate (16 GiB of float64).
const MAX_OUTPUT_BYTES: usize = 16 << 30;

/// Runs `f` with the GIL released; a panic becomes a RuntimeError instead of crossing into Python.
fn detached<T: Send>(
    py: Python<'_>,
    f: impl FnOnce() -> Result<T, CoreError> + Send,
) -> PyResult<T> {
    py.detach(|| std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)))
        .map_err(|_| PyRuntimeError::new_err("internal error in the poisson_rs core (panic)"))?
        .map_err(PyErr::from)
}

/// An (n, 3) float64 array as rows of 3; the caller has made it C-contiguous.
fn states(a: &PyReadonlyArray2<'_, f64>, what: &str) -> PyResult<Vec<[f64; 3]>> {
    let shape = a.shape();
    if shape[1] != 3 {
        return Err(PyValueError::new_err(format!(
            "{what} must have shape (n, 3), got ({}, {})",
            shape[0], shape[1]
        )));
    }
    let view = a.as_array();
    Ok(view
        .rows()
        .into_iter()
        .map(|r| [r[0], r[1], r[2]])
        .collect())
}

/// A generating function loaded from a model file.
#[pyclass(name = "Model", module = "poisson_rs._core", frozen)]
struct PyModel {
    inner: Model,
}

#[pymethods]
impl PyModel {
    /// Loads a model file. Raises FileNotFoundError or ValueError.
    #[staticmethod]
    fn load(py: Python<'_>, path: PathBuf) -> PyResult<Self> {
        let inner = detached(py, || Model::from_file(&path))?;
        Ok(PyModel { inner })
    }

    /// Parses the bytes of a model file. Raises ValueError.
    #[staticmethod]
    fn from_bytes(py: Python<'_>, data: Vec<u8>) -> PyResult<Self> {
        let inner = detached(py, || Model::from_bytes(&data))?;
        Ok(PyModel { inner })
    }

    /// The file's metadata, as strings.
    #[getter]
    fn metadata<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        for (k, v) in &self.inner.metadata {
            d.set_item(k, v)?;
        }
        Ok(d)
    }

    #[getter]
    fn chart(&self) -> &'static str {
        self.inner.chart.name()
    }

    #[getter]
    fn mlp_power(&self) -> u32 {
        self.inner.generating.mlp_power
    }

    /// Hidden layer widths of the MLP (empty without one).
    #[getter]
    fn widths(&self) -> Vec<usize> {
        self.inner
            .generating
            .mlp
            .as_ref()
            .map_or_else(Vec::new, |m| {
                m.layers[..m.layers.len() - 1]
                    .iter()
                    .map(|l| l.n_out)
                    .collect()
            })
    }

    #[getter]
    fn n_parameters(&self) -> usize {
        self.inner
            .generating
            .mlp
            .as_ref()
            .map_or(0, |m| m.n_parameters())
    }

    /// Trajectories a rollout solves together in batched passes (1: one at a time).
    #[getter]
    fn batch(&self) -> usize {
        batch_size(&self.inner.generating)
    }

    #[getter]
    fn n_polynomial_terms(&self) -> usize {
        self.inner.generating.polynomial.terms.len()
    }

    /// S, ∂S/∂p and ∂²S/∂p² at time t for p of shape (n, 3): arrays (n,), (n, 3), (n, 3, 3).
    fn derivatives<'py>(
        &self,
        py: Python<'py>,
        t: f64,
        p: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(Array<'py, Ix1>, Array<'py, Ix2>, Array<'py, Ix3>)> {
        let p = states(&p, "p")?;
        let g = &self.inner.generating;
        let (s, grad, hess) = detached(py, || {
            let mut ws = g.workspace();
            let n = p.len();
            let (mut s, mut grad, mut hess) = (
                Vec::with_capacity(n),
                Vec::with_capacity(3 * n),
                Vec::with_capacity(9 * n),
            );
            for q in &p {
                let jet = g.jet(t, q, &mut ws);
                s.push(jet.0[0]);
                grad.extend(jet.grad());
                hess.extend(jet.hess().iter().flatten());
            }
            Ok((s, grad, hess))
        })?;
        let n = p.len();
        let shape_err = |e: numpy::ndarray::ShapeError| PyRuntimeError::new_err(e.to_string());
        Ok((
            Array1::from_vec(s).into_pyarray(py),
            Array2::from_shape_vec((n, 3), grad)
                .map_err(shape_err)?
                .into_pyarray(py),
            Array3::from_shape_vec((n, 3, 3), hess)
                .map_err(shape_err)?
                .into_pyarray(py),
        ))
    }

    /// S and ∂S/∂t at (t, p) for p of shape (n, 3): arrays (n,), (n,).
    fn time_derivative<'py>(
        &self,
        py: Python<'py>,
        t: f64,
        p: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(Array<'py, Ix1>, Array<'py, Ix1>)> {
        let p = states(&p, "p")?;
        let g = &self.inner.generating;
        let (s, dt): (Vec<f64>, Vec<f64>) = detached(py, || {
            let mut ws = g.workspace();
            Ok(p.iter()
                .map(|q| g.value_and_time_derivative(t, q, &mut ws))
                .unzip())
        })?;
        Ok((
            Array1::from_vec(s).into_pyarray(py),
            Array1::from_vec(dt).into_pyarray(py),
        ))
    }

    fn __repr__(&self) -> String {
        format!(
            "Model(chart={:?}, polynomial_terms={}, mlp_parameters={}, mlp_power={})",
            self.inner.chart.name(),
            self.n_polynomial_terms(),
            self.n_parameters(),
            self.inner.generating.mlp_power
        )
    }
}

fn info_dict<'py>(py: Python<'py>, info: &[TrajectoryInfo]) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    let col = |f: &dyn Fn(&TrajectoryInfo) -> f64| Array1::from_iter(info.iter().map(f));
    d.set_item(
        "converged",
        Array1::from_iter(info.iter().map(|i| i.converged)).into_pyarray(py),
    )?;
    d.set_item(
        "failed_step",
        Array1::from_iter(info.iter().map(|i| i.failed_step)).into_pyarray(py),
    )?;
    d.set_item(
        "failure_code",
        Array1::from_iter(info.iter().map(|i| i.failure.map_or(0, |f| f.code()))).into_pyarray(py),
    )?;
    d.set_item(
        "newton_iterations",
        Array1::from_iter(info.iter().map(|i| i.newton_iterations)).into_pyarray(py),
    )?;
    d.set_item(
        "max_newton_iterations",
        Array1::from_iter(info.iter().map(|i| i.max_newton_iterations)).into_pyarray(py),
    )?;
    d.set_item("max_residual", col(&|i| i.max_residual).into_pyarray(py))?;
    Ok(d)
}

/// Records per trajectory and numbers in the (n, records, 3) output of a rollout; refuses
/// outputs over MAX_OUTPUT_BYTES before anything is allocated.
fn output_size(n: usize, n_steps: usize, every: usize) -> PyResult<(usize, usize)> {
    if every == 0 {
        return Err(PyValueError::new_err("every must be at least 1"));
    }
    let records = n_records(n_steps, every);
    let len = n
        .checked_mul(records)
        .and_then(|x| x.checked_mul(3))
        .filter(|&x| x.saturating_mul(8) <= MAX_OUTPUT_BYTES)
        .ok_or_else(|| {
            PyMemoryError::new_err(format!(
                "the output ({n} trajectories x {records} states x 3) exceeds {} GiB; \
                 raise `every` or split the batch",
                MAX_OUTPUT_BYTES >> 30
            ))
        })?;
    Ok((records, len))
}

/// Wall-clock time a rollout segment aims at: Ctrl-C is noticed within about this long (plus one
/// step of every trajectory, the smallest segment).
const SEGMENT_SECONDS: f64 = 0.05;

/// Trajectory-steps in the first segment, before its duration is known.
const FIRST_SEGMENT_WORK: usize = 1 << 12;

/// Runs a rollout of `stepper` into a new (n, records, 3) array, in segments with the GIL
/// released. Between segments it re-attaches and calls `py.check_signals()`, so Ctrl-C raises
/// KeyboardInterrupt within about SEGMENT_SECONDS instead of at the end. Segment sizes adapt to
/// the measured speed; the result does not depend on them (see [`Rollout`]).
fn run_rollout<'py, S: StepMap>(
    py: Python<'py>,
    stepper: &S,
    mu0: &[[f64; 3]],
    h: f64,
    n_steps: usize,
    every: usize,
) -> PyResult<(Array<'py, Ix3>, Bound<'py, PyDict>)> {
    // Refuses an oversized output before anything is allocated, and one the system cannot
    // give with MemoryError rather than the abort of a failed infallible allocation.
    let (records, len) = output_size(mu0.len(), n_steps, every)?;
    let mut out: Vec<f64> = Vec::new();
    out.try_reserve_exact(len).map_err(|_| {
        PyMemoryError::new_err(format!(
            "cannot allocate the output ({} trajectories x {records} states x 3 float64, \
             {:.1} GiB); raise `every` or split the batch",
            mu0.len(),
            (len as f64) * 8.0 / f64::from(1u32 << 30)
        ))
    })?;
    let mut rollout = detached(py, || {
        out.resize(len, 0.0);
        Rollout::start(mu0, h, n_steps, every, &mut out)
    })?;
    let mut segment = (FIRST_SEGMENT_WORK / mu0.len().max(1)).max(1);
    while !rollout.is_finished() {
        let start = Instant::now();
        detached(py, || rollout.advance(stepper, segment, &mut out))?;
        py.check_signals()?;
        // Rescale towards SEGMENT_SECONDS, growing at most 8× at a time so that a segment
        // timed while the machine was briefly idle cannot overshoot by much.
        let seconds = start.elapsed().as_secs_f64();
        let factor = if seconds > 0.0 {
            (SEGMENT_SECONDS / seconds).min(8.0)
        } else {
            8.0
        };
        segment = ((segment as f64 * factor) as usize).max(1);
    }
    let info = rollout.into_info();
    let traj = Array3::from_shape_vec((mu0.len(), records, 3), out)
        .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
    Ok((traj.into_pyarray(py), info_dict(py, &info)?))
}

/// Rolls out the bisection integrator of `model` from each row of `mu0` (n, 3). `simplified`
/// lets batched steps reuse the Newton Jacobian (see `NewtonOptions::simplified`).
///
/// Returns the trajectories (n, n_steps // every + 1, 3) and a dict of per-trajectory arrays.
/// Ctrl-C interrupts it (KeyboardInterrupt) within about SEGMENT_SECONDS.
#[pyfunction]
#[pyo3(signature = (model, mu0, h, n_steps, every=1, tol=1e-12, max_iter=50, simplified=true))]
#[allow(clippy::too_many_arguments)]
fn rollout_model<'py>(
    py: Python<'py>,
    model: &PyModel,
    mu0: PyReadonlyArray2<'py, f64>,
    h: f64,
    n_steps: usize,
    every: usize,
    tol: f64,
    max_iter: u32,
    simplified: bool,
) -> PyResult<(Array<'py, Ix3>, Bound<'py, PyDict>)> {
    let mu0 = states(&mu0, "mu0")?;
    let newton = NewtonOptions {
        simplified,
        ..NewtonOptions::validated(tol, max_iter)?
    };
    let stepper = model.inner.stepper(newton);
    run_rollout(py, &stepper, &mu0, h, n_steps, every)
}

/// Rolls out the classical integrator `name` (rk4, midpoint, splitting, splitting4, dmv) for the
/// rigid body with principal moments `inertia` from each row of `mu0` (n, 3). `tol` and
/// `max_iter` set the Newton solve of the implicit methods (midpoint, dmv).
///
/// Returns the trajectories (n, n_steps // every + 1, 3) and a dict of per-trajectory arrays.
/// Ctrl-C interrupts it (KeyboardInterrupt) within about SEGMENT_SECONDS.
#[pyfunction]
#[pyo3(signature = (name, inertia, mu0, h, n_steps, every=1, tol=1e-12, max_iter=50))]
#[allow(clippy::too_many_arguments)]
fn rollout_classical<'py>(
    py: Python<'py>,
    name: &str,
    inertia: [f64; 3],
    mu0: PyReadonlyArray2<'py, f64>,
    h: f64,
    n_steps: usize,
    every: usize,
    tol: f64,
    max_iter: u32,
) -> PyResult<(Array<'py, Ix3>, Bound<'py, PyDict>)> {
    let method = ClassicalMethod::from_name(name)?;
    let body = RigidBody::new(inertia)?;
    let mu0 = states(&mu0, "mu0")?;
    let newton = NewtonOptions::validated(tol, max_iter)?;
    let stepper = method.stepper(body, newton);
    run_rollout(py, &stepper, &mu0, h, n_steps, every)
}

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyModel>()?;
    m.add_function(wrap_pyfunction!(rollout_model, m)?)?;
    m.add_function(wrap_pyfunction!(rollout_classical, m)?)?;
    m.add("MODEL_FORMAT", FORMAT)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}

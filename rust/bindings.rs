//! Python bindings: the only module that knows about pyo3. It checks shapes, releases the GIL
//! around batch work and turns core errors into Python exceptions.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use numpy::ndarray::{Array1, Array2, Array3, Ix1, Ix2, Ix3};
use numpy::{
    IntoPyArray, PyArray, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3,
    PyUntypedArrayMethods,
};
use pyo3::exceptions::{
    PyFileNotFoundError, PyMemoryError, PyOSError, PyRuntimeError, PyValueError,
};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyFloat, PyInt, PyList};

use crate::classical::{
    ClassicalMethod, ClassicalStepper, HeavyTop, LieMethod, LieStepper, RigidBody,
};
use crate::dual::Jet2;
use crate::error::CoreError;
use crate::expression::Expression;
use crate::generating::Workspace;
use crate::jet_hj::{JetGenerating, LieSource, PolynomialSource, SeriesSource};
use crate::lanes::Lanes;
use crate::memory::try_with_capacity;
use crate::model::{LogModel, Model, FORMAT};
use crate::realization::Generating;
use crate::rollout::{n_records, ChunkKernel, PerStep, Rollout, TrajectoryInfo};
use crate::stepper::{batch_size, NewtonOptions};
use crate::straight_line::LieField;
use crate::structures::bivector::HamiltonianField;
use crate::structures::lie_groupoid::LieAlgebra;
use crate::structures::lie_poisson::{self, Hamiltonian, LiePoisson, VectorField};
use crate::{with_dim, MAX_DIM};

impl From<CoreError> for PyErr {
    fn from(e: CoreError) -> PyErr {
        match e {
            CoreError::NotFound(_) => PyFileNotFoundError::new_err(e.to_string()),
            CoreError::Io(_) => PyOSError::new_err(e.to_string()),
            CoreError::Format(_) | CoreError::Invalid(_) => PyValueError::new_err(e.to_string()),
            CoreError::Memory(_) => PyMemoryError::new_err(e.to_string()),
        }
    }
}

/// A float64 NumPy array owned by Python.
type Array<'py, D> = Bound<'py, PyArray<f64, D>>;

/// Below this many bytes a call skips reading the memory limits: a file read costs more
/// than the whole of a small call, and no machine this runs on lacks 1 MiB.
const SMALL_CALL_BYTES: usize = 1 << 20;

/// Refuses, with MemoryError, a call whose output of `numbers` float64 plus `extra` bytes of
/// working memory would not fit in the memory this process can use now (the least of
/// MemAvailable, RLIMIT_AS and the cgroup limit, see [`crate::memory`]); before anything is
/// allocated.
fn check_output_bytes(numbers: usize, extra: usize) -> PyResult<()> {
    let need = numbers.saturating_mul(8).saturating_add(extra);
    if need <= SMALL_CALL_BYTES {
        return Ok(());
    }
    crate::memory::check_fits(
        need,
        "this call (output and working memory)",
        "raise `every` or split the batch",
    )?;
    Ok(())
}

/// Runs `f` with the GIL released; a panic becomes a RuntimeError instead of crossing into Python.
fn detached<T: Send>(
    py: Python<'_>,
    f: impl FnOnce() -> Result<T, CoreError> + Send,
) -> PyResult<T> {
    py.detach(|| std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)))
        .map_err(|payload| {
            // Memory refused where no Result could carry it (a workspace inside the pool).
            match crate::memory::out_of_memory(&*payload) {
                Some(oom) => PyMemoryError::new_err(oom.message.clone()),
                None => PyRuntimeError::new_err("internal error in the poisson_rs core (panic)"),
            }
        })?
        .map_err(PyErr::from)
}

/// An (n, N) float64 array as rows of N.
fn states<const N: usize>(a: &PyReadonlyArray2<'_, f64>, what: &str) -> PyResult<Vec<[f64; N]>> {
    let shape = a.shape();
    if shape[1] != N {
        return Err(PyValueError::new_err(format!(
            "{what} must have shape (n, {N}), got ({}, {})",
            shape[0], shape[1]
        )));
    }
    let mut rows = Vec::new();
    rows.try_reserve_exact(shape[0])
        .map_err(|_| PyMemoryError::new_err(format!("cannot allocate {} states", shape[0])))?;
    rows.extend(
        a.as_array()
            .rows()
            .into_iter()
            .map(|r| std::array::from_fn(|i| r[i])),
    );
    Ok(rows)
}

/// [`states`], with ValueError for a state that holds NaN or ±∞ (the check `integrate()` leaves
/// to the core on its fast path; worded as its own).
fn finite_states<const N: usize>(
    a: &PyReadonlyArray2<'_, f64>,
    what: &str,
) -> PyResult<Vec<[f64; N]>> {
    let rows = states::<N>(a, what)?;
    if let Some(bad) = rows.iter().position(|m| !m.iter().all(|v| v.is_finite())) {
        return Err(PyValueError::new_err(format!(
            "{what} holds NaN or infinite values (state {bad})"
        )));
    }
    Ok(rows)
}

/// The initial states of a rollout: an (n, N) float64 array, or a Python list of exactly N
/// plain numbers (`float`, or `int` within int64; not `bool`), one state, read without NumPy
/// (converting a short list to an array costs more than a one-step rollout). Ok(None) for any
/// other list: the caller converts it (and names what is wrong with it). Non-finite states are
/// a ValueError either way.
fn initial_states<const N: usize>(
    mu0: &Bound<'_, PyAny>,
    what: &str,
) -> PyResult<Option<Vec<[f64; N]>>> {
    let Ok(list) = mu0.cast::<PyList>() else {
        let array: PyReadonlyArray2<'_, f64> = mu0.extract()?;
        return finite_states::<N>(&array, what).map(Some);
    };
    if list.len() != N {
        return Ok(None);
    }
    let mut state = [0.0; N];
    for (x, item) in state.iter_mut().zip(list.iter()) {
        *x = if item.is_exact_instance_of::<PyFloat>() {
            item.extract::<f64>()?
        } else if item.is_exact_instance_of::<PyInt>() {
            // As NumPy casts an int64 array (round to nearest); a larger int is an object
            // array there, refused with its dtype named.
            match item.extract::<i64>() {
                Ok(v) => v as f64,
                Err(_) => return Ok(None),
            }
        } else {
            return Ok(None);
        };
    }
    if !state.iter().all(|v| v.is_finite()) {
        return Err(PyValueError::new_err(format!(
            "{what} holds NaN or infinite values (state 0)"
        )));
    }
    Ok(Some(vec![state]))
}

fn dim_error(dim: usize) -> PyErr {
    PyValueError::new_err(format!("dimension {dim} is not supported (1 to {MAX_DIM})"))
}

/// Set in a child process after fork(): rayon's thread pool does not survive a fork (its
/// threads are gone but its state says they exist, so a parallel rollout would wait forever).
/// A forked child runs its rollouts on the calling thread instead; the result is the same bit
/// for bit, since chunks never depend on the thread count.
static FORKED: AtomicBool = AtomicBool::new(false);

/// Called by `os.register_at_fork(after_in_child=...)`.
#[pyfunction]
fn _after_fork_in_child() {
    FORKED.store(true, Ordering::SeqCst);
}

/// Whether rollouts in this process run serially (a forked child).
#[pyfunction]
fn serial_rollouts() -> bool {
    FORKED.load(Ordering::SeqCst)
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
    fn from_bytes(py: Python<'_>, data: &[u8]) -> PyResult<Self> {
        let inner = detached(py, || Model::from_bytes(data))?;
        Ok(PyModel { inner })
    }

    /// The dimension N of the model's Lie algebra (3 for the rigid body).
    #[getter]
    fn dim(&self) -> usize {
        self.inner.dim
    }

    /// The structure constants c[i, j, k] of the model's algebra, shape (N, N, N).
    #[getter]
    fn structure_constants<'py>(&self, py: Python<'py>) -> PyResult<Array<'py, Ix3>> {
        let n = self.inner.dim;
        Array3::from_shape_vec((n, n, n), self.inner.structure_constants.clone())
            .map(|a| a.into_pyarray(py))
            .map_err(|e| PyRuntimeError::new_err(e.to_string()))
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
        self.inner.mlp_power
    }

    /// Hidden layer widths of the MLP (empty without one).
    #[getter]
    fn widths(&self) -> Vec<usize> {
        self.inner.mlp.as_ref().map_or_else(Vec::new, |m| {
            m.layers[..m.layers.len() - 1]
                .iter()
                .map(|l| l.n_out)
                .collect()
        })
    }

    #[getter]
    fn n_parameters(&self) -> usize {
        self.inner.mlp.as_ref().map_or(0, |m| m.n_parameters())
    }

    /// Trajectories a rollout solves together in batched passes (1: one at a time).
    #[getter]
    fn batch(&self) -> usize {
        batch_size(self.inner.mlp.as_ref())
    }

    #[getter]
    fn n_polynomial_terms(&self) -> usize {
        self.inner.n_polynomial_terms()
    }

    /// S, ∂S/∂p and ∂²S/∂p² at time t for p of shape (n, N): arrays (n,), (n, N), (n, N, N).
    fn derivatives<'py>(
        &self,
        py: Python<'py>,
        t: f64,
        p: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(Array<'py, Ix1>, Array<'py, Ix2>, Array<'py, Ix3>)> {
        with_dim!(self.inner.dim, N => {
            let p = states::<N>(&p, "p")?;
            let g = self.inner.generating::<N>()?;
            jets_at(py, &g, &g, t, &p)
        }, Err(dim_error(self.inner.dim)))
    }

    /// S and ∂S/∂t at (t, p) for p of shape (n, N): arrays (n,), (n,).
    fn time_derivative<'py>(
        &self,
        py: Python<'py>,
        t: f64,
        p: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(Array<'py, Ix1>, Array<'py, Ix1>)> {
        with_dim!(self.inner.dim, N => self.time_derivative_n::<N>(py, t, p), Err(dim_error(self.inner.dim)))
    }

    fn __repr__(&self) -> String {
        format!(
            "Model(dim={}, chart={:?}, polynomial_terms={}, mlp_parameters={}, mlp_power={})",
            self.inner.dim,
            self.inner.chart.name(),
            self.n_polynomial_terms(),
            self.n_parameters(),
            self.inner.mlp_power
        )
    }
}

impl PyModel {
    fn time_derivative_n<'py, const N: usize>(
        &self,
        py: Python<'py>,
        t: f64,
        p: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(Array<'py, Ix1>, Array<'py, Ix1>)> {
        let p = states::<N>(&p, "p")?;
        let g = self.inner.generating::<N>()?;
        check_output_bytes(p.len().saturating_mul(2), Workspace::bytes(&g))?;
        let (s, dt) = detached(py, || {
            let mut ws = g.try_workspace()?;
            let mut s = try_with_capacity(p.len(), "the output S")?;
            let mut dt = try_with_capacity(p.len(), "the output dS/dt")?;
            for q in &p {
                let (v, d) = g.value_and_time_derivative(t, q, &mut ws);
                s.push(v);
                dt.push(d);
            }
            Ok((s, dt))
        })?;
        Ok((
            Array1::from_vec(s).into_pyarray(py),
            Array1::from_vec(dt).into_pyarray(py),
        ))
    }
}

/// The per-trajectory diagnostics as a dict of (n,) arrays; `step_angle` (h × the local rate
/// at each initial state, see [`VectorField::step_rate`]) where the rollout knows its system.
fn info_dict<'py>(
    py: Python<'py>,
    info: &[TrajectoryInfo],
    step_angle: Option<Vec<f64>>,
) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    if let Some(a) = step_angle {
        d.set_item("step_angle", Array1::from_vec(a).into_pyarray(py))?;
    }
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

/// A rollout's per-trajectory diagnostics, kept in Rust until asked for: `summary()` gives
/// what `integrate()` needs to warn (a few numbers, no arrays), `arrays()` the dict of (n,)
/// arrays of `RolloutInfo`. Building seven NumPy arrays and a dict costs more than a one-step
/// rollout of one state, and most calls never look at them.
#[pyclass(name = "RolloutDiagnostics", module = "poisson_rs._core", frozen)]
struct PyDiagnostics {
    info: Vec<TrajectoryInfo>,
    step_angle: Option<Vec<f64>>,
}

#[pymethods]
impl PyDiagnostics {
    /// (n_failed, first_failed, its failed_step, its failure_code, max_angle, argmax_angle):
    /// the trajectories that failed, the first of them (−1 if none) with its step and code,
    /// and the largest step angle ignoring NaN with its index (NaN and −1 where every angle is
    /// NaN or none was computed).
    fn summary(&self) -> (usize, i64, i64, i8, f64, i64) {
        let mut n_failed = 0;
        let mut first: Option<usize> = None;
        for (k, i) in self.info.iter().enumerate() {
            if !i.converged {
                n_failed += 1;
                first.get_or_insert(k);
            }
        }
        let (step, code) = first.map_or((-1, 0), |k| {
            let i = &self.info[k];
            (i.failed_step, i.failure.map_or(0, |f| f.code()))
        });
        let (mut top, mut worst) = (f64::NAN, -1i64);
        for (k, &a) in self.step_angle.iter().flatten().enumerate() {
            // The first largest, as NumPy's nanargmax.
            if a > top || (top.is_nan() && !a.is_nan()) {
                top = a;
                worst = k as i64;
            }
        }
        (
            n_failed,
            first.map_or(-1, |k| k as i64),
            step,
            code,
            top,
            worst,
        )
    }

    /// The diagnostics as a dict of (n,) arrays (the fields of `RolloutInfo` but out_of_domain).
    fn arrays<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        info_dict(py, &self.info, self.step_angle.clone())
    }

    fn __len__(&self) -> usize {
        self.info.len()
    }
}

impl PyDiagnostics {
    /// Itself (`lazy`) or the dict of its arrays.
    fn into_python(self, py: Python<'_>, lazy: bool) -> PyResult<Bound<'_, PyAny>> {
        if lazy {
            Ok(Bound::new(py, self)?.into_any())
        } else {
            Ok(self.arrays(py)?.into_any())
        }
    }
}

/// Records per trajectory and numbers in the (n, records, N) output of a rollout, and a check
/// that the output, the rollout's own state and every thread's workspace fit in memory.
fn output_size<const N: usize>(
    n: usize,
    n_steps: usize,
    every: usize,
    workspace_bytes: usize,
) -> PyResult<(usize, usize)> {
    if every == 0 {
        return Err(PyValueError::new_err("every must be at least 1"));
    }
    let records = n_records(n_steps, every);
    let len = n
        .checked_mul(records)
        .and_then(|x| x.checked_mul(N))
        .ok_or_else(|| {
            PyMemoryError::new_err(format!(
                "the output ({n} trajectories x {records} states x {N}) is too large to index; \
                 raise `every` or split the batch"
            ))
        })?;
    let threads = if FORKED.load(Ordering::SeqCst) {
        1
    } else {
        rayon::current_num_threads() + 1
    };
    // Per trajectory: its current state, its diagnostics, and the returned diagnostic arrays.
    let per_trajectory = 8 * N + std::mem::size_of::<TrajectoryInfo>() + 7 * 8;
    let extra = n
        .saturating_mul(per_trajectory)
        .saturating_add(threads.saturating_mul(workspace_bytes));
    check_output_bytes(len, extra)?;
    Ok((records, len))
}

/// Writes the step angle of each state into the slice beside it.
type StepAngles<'a, const N: usize> = dyn Fn(&[[f64; N]], &mut [f64]) + Sync + 'a;

/// Wall-clock time a rollout segment aims at: Ctrl-C is noticed within about this long (plus one
/// step of one chunk of trajectories, the smallest segment).
const SEGMENT_SECONDS: f64 = 0.05;

/// Runs a rollout with `kernel` into a new (n, records, N) array, in segments with the GIL
/// released. Between segments it re-attaches and calls `py.check_signals()`, so Ctrl-C raises
/// KeyboardInterrupt within about SEGMENT_SECONDS instead of at the end.
///
/// Segments are sized by work (trajectory-steps), not by steps: the batch is taken in blocks
/// of consecutive trajectories, and a segment advances one block by as many steps as the work
/// allows, so a segment's length does not grow with the batch. The first segment is one step of
/// one chunk, whatever the model costs; the work per segment is then rescaled from the measured
/// speed. A block of a single chunk runs on the calling thread (no hand-off to the pool). The
/// result does not depend on the blocks or segments (see [`Rollout`]).
///
/// `angles` computes the step angle of each initial state (see [`info_dict`]).
#[allow(clippy::too_many_arguments)]
fn run_rollout<'py, const N: usize, K: ChunkKernel<N>>(
    py: Python<'py>,
    kernel: &K,
    mu0: &[[f64; N]],
    h: f64,
    n_steps: usize,
    every: usize,
    angles: Option<&StepAngles<'_, N>>,
) -> PyResult<(Array<'py, Ix3>, Bound<'py, PyDict>)> {
    let (traj, diagnostics) = run_rollout_lazy(py, kernel, mu0, h, n_steps, every, angles)?;
    Ok((traj, diagnostics.arrays(py)?))
}

/// [`run_rollout`] with the diagnostics left in Rust ([`PyDiagnostics`]).
#[allow(clippy::too_many_arguments)]
fn run_rollout_lazy<'py, const N: usize, K: ChunkKernel<N>>(
    py: Python<'py>,
    kernel: &K,
    mu0: &[[f64; N]],
    h: f64,
    n_steps: usize,
    every: usize,
    angles: Option<&StepAngles<'_, N>>,
) -> PyResult<(Array<'py, Ix3>, PyDiagnostics)> {
    // Refuses what cannot fit before anything is allocated, and an allocation the system
    // refuses anyway becomes MemoryError rather than the abort of an infallible allocation.
    let n = mu0.len();
    let (records, len) = output_size::<N>(n, n_steps, every, kernel.workspace_bytes())?;
    let alloc_error = || {
        PyMemoryError::new_err(format!(
            "cannot allocate the output ({n} trajectories x {records} states x {N} float64, \
             {:.1} GiB); raise `every` or split the batch",
            (len as f64) * 8.0 / f64::from(1u32 << 30)
        ))
    };
    let mut out: Vec<f64> = Vec::new();
    out.try_reserve_exact(len).map_err(|_| alloc_error())?;
    let mut info: Vec<TrajectoryInfo> = Vec::new();
    info.try_reserve_exact(n).map_err(|_| alloc_error())?;
    let mut step_angle: Option<Vec<f64>> = None;
    if let Some(f) = angles {
        let mut a = Vec::new();
        a.try_reserve_exact(n).map_err(|_| alloc_error())?;
        a.resize(n, f64::NAN);
        detached(py, || {
            f(mu0, &mut a);
            Ok(())
        })?;
        step_angle = Some(a);
    }
    let serial = FORKED.load(Ordering::SeqCst);
    // Every trajectory's row of the output, and the block's rows to the end of the batch.
    let row = records * N;
    let chunk = kernel.chunk().max(1);
    let mut work = chunk as f64;
    let mut done = 0;
    out.resize(len, 0.0);
    while done < n {
        // Whole chunks, so the chunks (and the batched solves) are those of one big block.
        let rows = ((work as usize).div_ceil(chunk) * chunk)
            .max(chunk)
            .min(n - done);
        let out_block = &mut out[done * row..(done + rows) * row];
        let mut rollout = detached(py, || {
            Rollout::start(&mu0[done..done + rows], h, n_steps, every, out_block)
        })?;
        while !rollout.is_finished() {
            let start = Instant::now();
            let steps = ((work / rows as f64) as usize).max(1);
            detached(py, || {
                rollout.advance_kernel(kernel, steps, out_block, !serial)
            })?;
            py.check_signals()?;
            // Rescale towards SEGMENT_SECONDS, growing at most 8× at a time so that a segment
            // timed while the machine was briefly idle cannot overshoot by much.
            let seconds = start.elapsed().as_secs_f64();
            let factor = if seconds > 0.0 {
                (SEGMENT_SECONDS / seconds).min(8.0)
            } else {
                8.0
            };
            work = (steps as f64 * rows as f64 * factor).max(chunk as f64);
        }
        info.extend_from_slice(rollout.info());
        done += rows;
    }
    let traj = Array3::from_shape_vec((n, records, N), out)
        .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
    Ok((traj.into_pyarray(py), PyDiagnostics { info, step_angle }))
}

/// The step angles of `mu` under `field`, in parallel for large batches (each state's angle
/// is computed alone, so the result does not depend on the threads).
fn angles_of<const N: usize, F: VectorField<N>>(
    field: &F,
    h: f64,
    mu: &[[f64; N]],
    out: &mut [f64],
) {
    use rayon::prelude::*;
    const CHUNK: usize = 4096;
    if mu.len() > CHUNK && !FORKED.load(Ordering::SeqCst) {
        out.par_chunks_mut(CHUNK)
            .zip(mu.par_chunks(CHUNK))
            .for_each(|(o, m)| lie_poisson::step_angles(field, m, h, o));
    } else {
        lie_poisson::step_angles(field, mu, h, out);
    }
}

/// Rolls out the bisection integrator of `model` from each row of `mu0` (n, N). `simplified`
/// lets batched steps reuse the Newton Jacobian (see `NewtonOptions::simplified`).
///
/// Returns the trajectories (n, n_steps // every + 1, N) and a dict of per-trajectory arrays.
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
    let newton = NewtonOptions {
        simplified,
        ..NewtonOptions::validated(tol, max_iter)?
    };
    with_dim!(model.inner.dim, N => {
        let mu0 = states::<N>(&mu0, "mu0")?;
        let stepper = model.inner.stepper::<N>(newton)?;
        run_rollout(py, &PerStep(&stepper), &mu0, h, n_steps, every, None)
    }, Err(dim_error(model.inner.dim)))
}

/// Rolls out the classical integrator `name` (rk4, midpoint, splitting, splitting4, dmv) for the
/// rigid body with principal moments `inertia` from each row of `mu0` (n, 3). `tol` and
/// `max_iter` set the Newton solve of the implicit methods (midpoint, dmv).
///
/// Returns the trajectories (n, n_steps // every + 1, 3) and a dict of per-trajectory arrays.
/// Ctrl-C interrupts it (KeyboardInterrupt) within about SEGMENT_SECONDS.
#[pyfunction]
#[pyo3(signature = (name, inertia, mu0, h, n_steps, every=1, tol=1e-12, max_iter=50, lazy=false))]
#[allow(clippy::too_many_arguments)]
fn rollout_classical<'py>(
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
type HeavyTopParameters = ([f64; 3], f64, [f64; 3]);

/// Rolls out the classical integrator `name` (rk4, midpoint; splitting for the heavy top) of
/// the Lie–Poisson system with structure constants `c` (N, N, N) and polynomial Hamiltonian
/// Σ coeffs[m] Π μ_i^powers[m, i] (powers int64 (M, N), coeffs (M,)), from each row of `mu0`
/// (n, N). `heavy_top` = (inertia, mgl, com) selects the heavy top's splitting.
#[pyfunction]
#[pyo3(signature = (name, c, powers, coeffs, mu0, h, n_steps, every=1, tol=1e-12, max_iter=50, heavy_top=None, lazy=false))]
#[allow(clippy::too_many_arguments)]
fn rollout_lie_poisson<'py>(
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

// ---------------------------------------------------------------------------------------------
// Log-canonical structures π_ij = c_ij x_i x_j (Lotka–Volterra): Taylor-HJ bisection on the
// exact groupoid and the classical baselines.
// ---------------------------------------------------------------------------------------------

use crate::structures::{
    ExpMonomial, ExpPolynomial, LogBisection, LogCanonical, LogClassical, LogMethod, LogSystem,
    OrthantChecked,
};

/// The (N, N) structure matrix c as a checked [`LogCanonical`].
fn log_structure<const N: usize>(c: &PyReadonlyArray2<'_, f64>) -> PyResult<LogCanonical<N>> {
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

/// Checks that `what` has `n` rows.
fn rows_match(what: &str, got: usize, n: usize) -> PyResult<()> {
    if got != n {
        return Err(PyValueError::new_err(format!(
            "{what} has {got} rows, {n} expected (one per term)"
        )));
    }
    Ok(())
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
fn rollout_log_canonical<'py>(
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
        let stepper: OrthantChecked<LogBisection<N>> = OrthantChecked(LogBisection {
            generating,
            realization,
            newton,
            scale_floor: 1.0,
        });
        let q0 = states::<N>(&q0, "q0")?;
        // N = 2 and 3 solve their Newton systems in SIMD lanes (every lane the scalar bits).
        match stepper.0.lanes() {
            Some(lanes) => run_rollout(py, &Lanes::new(&lanes), &q0, h, n_steps, every, None),
            None => run_rollout(py, &PerStep(&stepper), &q0, h, n_steps, every, None),
        }
    }, Err(dim_error(dim)))
}

/// S, ∇S and ∇²S at time t for each of `x`, for any S whose network part is `network` (its
/// workspace and the outputs counted, then allocated fallibly, before the GIL is released: a
/// refusal is MemoryError, never an abort): arrays (n,), (n, N), (n, N, N).
fn jets_at<'py, const N: usize, G: Generating<N, Workspace = Workspace<N>>>(
    py: Python<'py>,
    g: &G,
    network: &crate::generating::GeneratingFunction<N>,
    t: f64,
    x: &[[f64; N]],
) -> PyResult<(Array<'py, Ix1>, Array<'py, Ix2>, Array<'py, Ix3>)> {
    let n = x.len();
    check_output_bytes(n.saturating_mul(1 + N + N * N), Workspace::bytes(network))?;
    let (s, grad, hess) = detached(py, || {
        let mut ws = network.try_workspace()?;
        let (mut s, mut grad, mut hess) = (
            try_with_capacity(n, "the output S")?,
            try_with_capacity(N * n, "the output dS/dx")?,
            try_with_capacity(N * N * n, "the output d2S/dx2")?,
        );
        for xi in x {
            let jet = g.jet(t, xi, &mut ws);
            s.push(jet.v);
            grad.extend(jet.grad());
            hess.extend(jet.hess().iter().flatten());
        }
        Ok((s, grad, hess))
    })?;
    let shape_err = |e: numpy::ndarray::ShapeError| PyRuntimeError::new_err(e.to_string());
    Ok((
        Array1::from_vec(s).into_pyarray(py),
        Array2::from_shape_vec((n, N), grad)
            .map_err(shape_err)?
            .into_pyarray(py),
        Array3::from_shape_vec((n, N, N), hess)
            .map_err(shape_err)?
            .into_pyarray(py),
    ))
}

/// A learned generating function of a log-canonical structure π_ij = c_ij x_i x_j, loaded from
/// a model file whose metadata says `structure = log_canonical`: S(t, q) = exact Taylor terms
/// + t^m · MLP(t, q) in q = ln x, stepped on the exact groupoid (every monomial Casimir kept to
/// round-off, whatever the network learned).
#[pyclass(name = "LogCanonicalModel", module = "poisson_rs._core", frozen)]
struct PyLogModel {
    inner: LogModel,
}

#[pymethods]
impl PyLogModel {
    /// Loads a log-canonical model file. Raises FileNotFoundError or ValueError.
    #[staticmethod]
    fn load(py: Python<'_>, path: PathBuf) -> PyResult<Self> {
        let inner = detached(py, || LogModel::from_file(&path))?;
        Ok(PyLogModel { inner })
    }

    /// Parses the bytes of a log-canonical model file. Raises ValueError.
    #[staticmethod]
    fn from_bytes(py: Python<'_>, data: &[u8]) -> PyResult<Self> {
        let inner = detached(py, || LogModel::from_bytes(data))?;
        Ok(PyLogModel { inner })
    }

    /// The dimension N (number of species).
    #[getter]
    fn dim(&self) -> usize {
        self.inner.dim
    }

    /// The structure matrix c, shape (N, N).
    #[getter]
    fn c<'py>(&self, py: Python<'py>) -> PyResult<Array<'py, Ix2>> {
        let n = self.inner.dim;
        Array2::from_shape_vec((n, n), self.inner.c.clone())
            .map(|a| a.into_pyarray(py))
            .map_err(|e| PyRuntimeError::new_err(e.to_string()))
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
    fn mlp_power(&self) -> u32 {
        self.inner.mlp_power
    }

    #[getter]
    fn n_parameters(&self) -> usize {
        self.inner.mlp.as_ref().map_or(0, |m| m.n_parameters())
    }

    #[getter]
    fn n_polynomial_terms(&self) -> usize {
        self.inner.n_polynomial_terms()
    }

    /// S, ∂S/∂q and ∂²S/∂q² at time t for q of shape (n, N): arrays (n,), (n, N), (n, N, N).
    fn derivatives<'py>(
        &self,
        py: Python<'py>,
        t: f64,
        q: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(Array<'py, Ix1>, Array<'py, Ix2>, Array<'py, Ix3>)> {
        with_dim!(self.inner.dim, N => {
            let q = states::<N>(&q, "q")?;
            let g = self.inner.generating::<N>()?;
            jets_at(py, &g, &g.network, t, &q)
        }, Err(dim_error(self.inner.dim)))
    }

    /// Rolls out the model's bisection integrator from each row of `q0` (n, N), in q = ln x:
    /// solve q + ½ c ∇S(h, q) = q_k by Newton (|δ|∞ ≤ tol · max(|q|∞, 1)), then
    /// q_{k+1} = q − ½ c ∇S(h, q). A step whose e^q leaves the float64 orthant fails (code 5
    /// or 3). Returns the trajectories in q (n, n_steps // every + 1, N) and a dict of
    /// per-trajectory arrays. Ctrl-C interrupts it (KeyboardInterrupt).
    #[pyo3(signature = (q0, h, n_steps, every=1, tol=1e-12, max_iter=50))]
    #[allow(clippy::too_many_arguments)]
    fn rollout<'py>(
        &self,
        py: Python<'py>,
        q0: PyReadonlyArray2<'py, f64>,
        h: f64,
        n_steps: usize,
        every: usize,
        tol: f64,
        max_iter: u32,
    ) -> PyResult<(Array<'py, Ix3>, Bound<'py, PyDict>)> {
        let newton = NewtonOptions::validated(tol, max_iter)?;
        with_dim!(self.inner.dim, N => {
            let stepper = self.inner.stepper::<N>(newton)?;
            let q0 = finite_states::<N>(&q0, "q0")?;
            run_rollout(py, &PerStep(&stepper), &q0, h, n_steps, every, None)
        }, Err(dim_error(self.inner.dim)))
    }

    fn __repr__(&self) -> String {
        format!(
            "LogCanonicalModel(dim={}, polynomial_terms={}, mlp_parameters={}, mlp_power={})",
            self.inner.dim,
            self.n_polynomial_terms(),
            self.n_parameters(),
            self.inner.mlp_power
        )
    }
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
fn rollout_log_classical<'py>(
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
        // The explicit methods step blocks of trajectories in SIMD lanes (the same bits).
        match stepper.explicit() {
            Some(explicit) => run_rollout(py, &Lanes::new(&explicit), &s0, h, n_steps, every, None),
            None => run_rollout(py, &PerStep(&stepper), &s0, h, n_steps, every, None),
        }
    }, Err(dim_error(dim)))
}

// ---------------------------------------------------------------------------------------------
// Any polynomial bivector: Taylor-HJ bisection on an approximate realization whose maps and
// generating function arrive as polynomial coefficients.
// ---------------------------------------------------------------------------------------------

use crate::generating::{Layer, Mlp};
use crate::structures::{
    LearnedPolynomialModel, PolynomialBisection, PolynomialField, PolynomialGenerating,
    PolynomialRealization, SparsePolynomial,
};

/// One polynomial in `vars` variables from the rows `rows` of a term table.
fn polynomial(
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
fn term_table<'a>(
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
fn component_polynomials<const N: usize>(
    what: &str,
    index: &PyReadonlyArray1<'_, i64>,
    coeffs: &PyReadonlyArray1<'_, f64>,
    exponents: &PyReadonlyArray2<'_, i64>,
    vars: usize,
) -> PyResult<Vec<SparsePolynomial>> {
    let (co, ex) = term_table(what, coeffs, exponents, vars)?;
    let ix = index.as_array();
    rows_match(&format!("{what} index"), ix.len(), co.len())?;
    if let Some(k) = (0..ix.len()).find(|&k| !(0..N as i64).contains(&ix[k])) {
        return Err(PyValueError::new_err(format!(
            "{what} index[{k}] = {} is outside 0..{N}",
            ix[k]
        )));
    }
    let mut out = Vec::new();
    out.try_reserve_exact(N)
        .map_err(|_| PyMemoryError::new_err("too many polynomials"))?;
    for target in 0..N {
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
fn rollout_polynomial_realization<'py>(
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
        let stepper: PolynomialBisection<N> = PolynomialBisection {
            generating: PolynomialGenerating::new(s)?,
            realization: PolynomialRealization::new(sou, tar)?,
            newton,
            scale_floor: 1.0,
        };
        let x0 = states::<N>(&x0, "x0")?;
        run_rollout(py, &PerStep(&stepper), &x0, h, n_steps, every, None)
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
fn rollout_polynomial_field<'py>(
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

/// A learned generating function on an approximate realization of a polynomial bivector:
/// S(t, x) = exact Taylor-HJ terms + t^m · MLP(t, x), stepped by the same Newton bisection as
/// `rollout_polynomial_realization`. Built from the term tables (as there) and the MLP's layers
/// (`weights[i]` (out, in), `biases[i]` (out,), inputs (t, x), tanh after every layer but the
/// last, one output; empty lists: no network).
#[pyclass(name = "LearnedPolynomialModel", module = "poisson_rs._core", frozen)]
struct PyLearnedPolynomialModel {
    inner: LearnedPolynomialModel,
}

#[pymethods]
impl PyLearnedPolynomialModel {
    #[new]
    #[pyo3(signature = (sou_index, sou_coeffs, sou_exponents, tar_index, tar_coeffs, tar_exponents, s_coeffs, s_exponents, weights, biases, mlp_power))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        sou_index: PyReadonlyArray1<'_, i64>,
        sou_coeffs: PyReadonlyArray1<'_, f64>,
        sou_exponents: PyReadonlyArray2<'_, i64>,
        tar_index: PyReadonlyArray1<'_, i64>,
        tar_coeffs: PyReadonlyArray1<'_, f64>,
        tar_exponents: PyReadonlyArray2<'_, i64>,
        s_coeffs: PyReadonlyArray1<'_, f64>,
        s_exponents: PyReadonlyArray2<'_, i64>,
        weights: Vec<PyReadonlyArray2<'_, f64>>,
        biases: Vec<PyReadonlyArray1<'_, f64>>,
        mlp_power: u32,
    ) -> PyResult<Self> {
        let dim = s_exponents.shape()[1].saturating_sub(1);
        rows_match("biases", biases.len(), weights.len())?;
        let mut layers = Vec::new();
        layers
            .try_reserve_exact(weights.len())
            .map_err(|_| PyMemoryError::new_err("too many layers"))?;
        for (i, (w, b)) in weights.iter().zip(&biases).enumerate() {
            let (ws, bs) = (w.shape(), b.shape());
            if bs[0] != ws[0] {
                return Err(PyValueError::new_err(format!(
                    "layer {i}: weight shape {ws:?} and bias shape {bs:?} do not match (out, in) \
                     and (out,)"
                )));
            }
            let wv: Vec<f64> = w.as_array().iter().copied().collect();
            let bv: Vec<f64> = b.as_array().iter().copied().collect();
            layers.push(Layer::new(ws[1], ws[0], wv, bv)?);
        }
        let mlp = if layers.is_empty() {
            None
        } else {
            Some(Mlp::new(layers)?)
        };
        let inner = with_dim!(dim, N => {
            let sou = component_polynomials::<N>("sou", &sou_index, &sou_coeffs, &sou_exponents, 2 * N)?;
            let tar = component_polynomials::<N>("tar", &tar_index, &tar_coeffs, &tar_exponents, 2 * N)?;
            let (co, ex) = term_table("S", &s_coeffs, &s_exponents, N + 1)?;
            let all: Vec<usize> = (0..co.len()).collect();
            let s = polynomial("S", &co, &ex, &all, N + 1)?;
            LearnedPolynomialModel::new(N, sou, tar, s, mlp, mlp_power)?
        }, return Err(dim_error(dim)));
        Ok(PyLearnedPolynomialModel { inner })
    }

    /// The dimension N.
    #[getter]
    fn dim(&self) -> usize {
        self.inner.dim
    }

    #[getter]
    fn mlp_power(&self) -> u32 {
        self.inner.mlp_power
    }

    #[getter]
    fn n_parameters(&self) -> usize {
        self.inner.mlp.as_ref().map_or(0, |m| m.n_parameters())
    }

    #[getter]
    fn n_taylor_terms(&self) -> usize {
        self.inner.n_taylor_terms()
    }

    /// S, ∂S/∂x and ∂²S/∂x² at time t for x of shape (n, N): arrays (n,), (n, N), (n, N, N).
    fn derivatives<'py>(
        &self,
        py: Python<'py>,
        t: f64,
        x: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(Array<'py, Ix1>, Array<'py, Ix2>, Array<'py, Ix3>)> {
        with_dim!(self.inner.dim, N => {
            let x = states::<N>(&x, "x")?;
            let g = self.inner.generating::<N>()?;
            jets_at(py, &g, &g.network, t, &x)
        }, Err(dim_error(self.inner.dim)))
    }

    /// Rolls out the learned bisection integrator from each row of `x0` (n, N): solve
    /// α(∇S(h, x), x) = x_k by Newton (|δ|∞ ≤ tol · max(|x|∞, 1)), then x_{k+1} = β(∇S(h, x), x).
    /// Returns the trajectories (n, n_steps // every + 1, N) and a dict of per-trajectory
    /// arrays. Ctrl-C interrupts it (KeyboardInterrupt).
    #[pyo3(signature = (x0, h, n_steps, every=1, tol=1e-13, max_iter=50))]
    #[allow(clippy::too_many_arguments)]
    fn rollout<'py>(
        &self,
        py: Python<'py>,
        x0: PyReadonlyArray2<'py, f64>,
        h: f64,
        n_steps: usize,
        every: usize,
        tol: f64,
        max_iter: u32,
    ) -> PyResult<(Array<'py, Ix3>, Bound<'py, PyDict>)> {
        let newton = NewtonOptions::validated(tol, max_iter)?;
        with_dim!(self.inner.dim, N => {
            let stepper = self.inner.stepper::<N>(newton)?;
            let x0 = states::<N>(&x0, "x0")?;
            run_rollout(py, &PerStep(&stepper), &x0, h, n_steps, every, None)
        }, Err(dim_error(self.inner.dim)))
    }

    fn __repr__(&self) -> String {
        format!(
            "LearnedPolynomialModel(dim={}, taylor_terms={}, mlp_parameters={}, mlp_power={})",
            self.inner.dim,
            self.n_taylor_terms(),
            self.n_parameters(),
            self.inner.mlp_power
        )
    }
}

/// h × the local rate at each row of `mu` (n, N) for the Lie–Poisson system with structure
/// constants `c` (N, N, N) and polynomial Hamiltonian Σ coeffs[m] Π μ_i^powers[m, i]: the angle
/// a step of size h turns each state by, max(‖ad_∇H‖_F/√2, ‖∂f/∂μ‖_F) · h. Returns (n,) float64.
#[pyfunction]
fn step_angles<'py>(
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
fn lie_poisson_system<const N: usize>(
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

/// The monomials Σ coeffs[m] Π x_i^powers[m, i] of a Hamiltonian (powers (M, N), already checked
/// to have N columns and M rows), each exponent in 0..=64; the term list allocated fallibly.
fn polynomial_terms<const N: usize>(
    powers: numpy::ndarray::ArrayView2<'_, i64>,
    coeffs: numpy::ndarray::ArrayView1<'_, f64>,
) -> PyResult<Vec<([u32; N], f64)>> {
    let mut terms = Vec::new();
    terms
        .try_reserve_exact(coeffs.len())
        .map_err(|_| PyMemoryError::new_err("cannot allocate the Hamiltonian's terms"))?;
    for (row, &coeff) in powers.rows().into_iter().zip(coeffs.iter()) {
        if let Some(&bad) = row.iter().find(|&&e| !(0..=64).contains(&e)) {
            return Err(PyValueError::new_err(format!(
                "Hamiltonian exponent {bad} is outside 0..=64"
            )));
        }
        terms.push((std::array::from_fn(|i| row[i] as u32), coeff));
    }
    Ok(terms)
}

/// An expression tape from its table (see [`crate::expression::Expression::from_table`]).
fn expression(
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

/// `count` polynomials in `vars` variables from one term table: term m adds
/// coeffs[m] · v^exponents[m] to polynomial index[m].
fn indexed_polynomials(
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

/// H, ∇H and ∇²H of an expression at each row of `x` (n, vars), exactly (forward mode).
#[pyfunction]
fn expression_jets<'py>(
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
#[pyo3(signature = (code, a, b, c, upper_index, upper_coeffs, upper_exponents, x, program=None))]
#[allow(clippy::too_many_arguments)]
fn hamiltonian_field<'py>(
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
) -> PyResult<Array<'py, Ix2>> {
    let dim = x.shape()[1];
    let n = x.shape()[0];
    check_output_bytes(n.saturating_mul(dim), 0)?;
    with_dim!(dim, N => {
        let field = field_of::<N>(&code, &a, &b, &c, &upper_index, &upper_coeffs, &upper_exponents, program.as_ref())?;
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
type FieldProgram<'py> = (
    PyReadonlyArray1<'py, i64>,
    PyReadonlyArray1<'py, i64>,
    PyReadonlyArray1<'py, i64>,
    PyReadonlyArray1<'py, f64>,
    PyReadonlyArray1<'py, i64>,
);

#[allow(clippy::too_many_arguments)]
fn field_of<const N: usize>(
    code: &PyReadonlyArray1<'_, i64>,
    a: &PyReadonlyArray1<'_, i64>,
    b: &PyReadonlyArray1<'_, i64>,
    c: &PyReadonlyArray1<'_, f64>,
    upper_index: &PyReadonlyArray1<'_, i64>,
    upper_coeffs: &PyReadonlyArray1<'_, f64>,
    upper_exponents: &PyReadonlyArray2<'_, i64>,
    program: Option<&FieldProgram<'_>>,
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
    Ok(HamiltonianField::<N>::new(upper, e, program)?)
}

/// Rolls out "rk4" or "midpoint" on ẋ = π(x) ∇H(x) (arguments as [`hamiltonian_field`]) from
/// each row of `x0` (n, N), in SIMD lanes; the midpoint's Newton stops at |δ|∞ ≤ tol ·
/// max(|m|∞, 1e-300).
#[pyfunction]
#[pyo3(signature = (name, code, a, b, c, upper_index, upper_coeffs, upper_exponents, x0, h, n_steps, every=1, tol=1e-13, max_iter=50, program=None))]
#[allow(clippy::too_many_arguments)]
fn rollout_hamiltonian_field<'py>(
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
) -> PyResult<(Array<'py, Ix3>, Bound<'py, PyDict>)> {
    let newton = NewtonOptions::validated(tol, max_iter)?;
    let dim = x0.shape()[1];
    with_dim!(dim, N => {
        let field = field_of::<N>(&code, &a, &b, &c, &upper_index, &upper_coeffs, &upper_exponents, program.as_ref())?;
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
                "unknown integrator {other:?} for an expression Hamiltonian; valid: rk4, midpoint"
            ))),
        }
    }, Err(dim_error(dim)))
}

/// Runs the jet Taylor-HJ stepper of `generating` on `realization` after checking that its
/// workspaces (one per thread) fit.
#[allow(clippy::too_many_arguments)]
fn run_jets<'py, const N: usize, R, S>(
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
    R: crate::realization::Realization<N>,
    S: SeriesSource<N>,
    nalgebra::Const<N>: nalgebra::DimMin<nalgebra::Const<N>, Output = nalgebra::Const<N>>,
{
    let threads = rayon::current_num_threads().max(1);
    check_output_bytes(0, generating.workspace_bytes().saturating_mul(threads))?;
    let stepper = crate::realization::RealizationStepper {
        generating,
        realization,
        newton,
        scale_floor: 1.0,
    };
    run_rollout(py, &PerStep(&stepper), x0, h, n_steps, every, None)
}

/// Rolls out Taylor-HJ of order `order` by jets for an expression H on the realization given by
/// polynomial maps sou (β) and tar (α), N polynomials each in (p, x) (as
/// `rollout_polynomial_realization`), from each row of `x0` (n, N).
#[pyfunction]
#[pyo3(signature = (code, a, b, c, hamiltonian_vars, order, sou_index, sou_coeffs, sou_exponents, tar_index, tar_coeffs, tar_exponents, x0, h, n_steps, every=1, tol=1e-13, max_iter=50))]
#[allow(clippy::too_many_arguments)]
fn rollout_jets_polynomial<'py>(
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
fn rollout_jets_lie<'py>(
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

/// Bytes this process can still take (the least of MemAvailable, what RLIMIT_AS leaves and
/// what the cgroup's limit leaves), or None where none can be read: the estimate every call of
/// the core checks its plan against, for the work Python does itself.
#[pyfunction]
fn usable_memory() -> Option<usize> {
    crate::memory::usable_bytes()
}

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyModel>()?;
    m.add_class::<PyDiagnostics>()?;
    m.add_class::<PyLogModel>()?;
    m.add_class::<PyLearnedPolynomialModel>()?;
    m.add_function(wrap_pyfunction!(rollout_model, m)?)?;
    m.add_function(wrap_pyfunction!(rollout_classical, m)?)?;
    m.add_function(wrap_pyfunction!(rollout_lie_poisson, m)?)?;
    m.add_function(wrap_pyfunction!(step_angles, m)?)?;
    m.add_function(wrap_pyfunction!(_after_fork_in_child, m)?)?;
    m.add_function(wrap_pyfunction!(serial_rollouts, m)?)?;
    m.add_function(wrap_pyfunction!(rollout_log_canonical, m)?)?;
    m.add_function(wrap_pyfunction!(rollout_polynomial_field, m)?)?;
    m.add_function(wrap_pyfunction!(rollout_log_classical, m)?)?;
    m.add_function(wrap_pyfunction!(rollout_polynomial_realization, m)?)?;
    m.add_function(wrap_pyfunction!(expression_jets, m)?)?;
    m.add_function(wrap_pyfunction!(usable_memory, m)?)?;
    m.add_function(wrap_pyfunction!(hamiltonian_field, m)?)?;
    m.add_function(wrap_pyfunction!(rollout_hamiltonian_field, m)?)?;
    m.add_function(wrap_pyfunction!(rollout_jets_polynomial, m)?)?;
    m.add_function(wrap_pyfunction!(rollout_jets_lie, m)?)?;
    m.add("MAX_DIM", MAX_DIM)?;
    m.add("MODEL_FORMAT", FORMAT)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}

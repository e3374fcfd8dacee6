//! Python bindings: the only module that knows about pyo3. It checks shapes, releases the GIL
//! around batch work and turns core errors into Python exceptions.
//!
//! One file per area: [`rollout`] (the driver every call shares), [`models`] (the learned-model
//! classes), [`lie_poisson`], [`log_canonical`], [`polynomial`] and [`expression`]; the shared
//! argument checks, the error conversion and the module itself here.

mod expression;
mod lie_poisson;
mod log_canonical;
mod models;
mod polynomial;
mod rollout;

use std::sync::atomic::{AtomicBool, Ordering};

use numpy::{PyArray, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::{
    PyFileNotFoundError, PyMemoryError, PyOSError, PyRuntimeError, PyValueError,
};
use pyo3::prelude::*;
use pyo3::types::{PyFloat, PyInt, PyList};

use expression::{
    expression_jets, hamiltonian_field, rollout_hamiltonian_field, rollout_jets_lie,
    rollout_jets_polynomial,
};
use lie_poisson::{rollout_classical, rollout_lie_poisson, step_angles};
use log_canonical::{exp_in_place, log_in_place, rollout_log_canonical, rollout_log_classical};
use models::{rollout_model, PyLearnedModel, PyModel};
use polynomial::{rollout_polynomial_field, rollout_polynomial_realization};
use rollout::PyDiagnostics;

use crate::error::CoreError;
use crate::model::FORMAT;
use crate::MAX_DIM;

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

/// Checks that `what` has `n` rows.
fn rows_match(what: &str, got: usize, n: usize) -> PyResult<()> {
    if got != n {
        return Err(PyValueError::new_err(format!(
            "{what} has {got} rows, {n} expected (one per term)"
        )));
    }
    Ok(())
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
    m.add_class::<PyLearnedModel>()?;
    m.add_function(wrap_pyfunction!(rollout_model, m)?)?;
    m.add_function(wrap_pyfunction!(rollout_classical, m)?)?;
    m.add_function(wrap_pyfunction!(rollout_lie_poisson, m)?)?;
    m.add_function(wrap_pyfunction!(step_angles, m)?)?;
    m.add_function(wrap_pyfunction!(_after_fork_in_child, m)?)?;
    m.add_function(wrap_pyfunction!(serial_rollouts, m)?)?;
    m.add_function(wrap_pyfunction!(rollout_log_canonical, m)?)?;
    m.add_function(wrap_pyfunction!(log_in_place, m)?)?;
    m.add_function(wrap_pyfunction!(exp_in_place, m)?)?;
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

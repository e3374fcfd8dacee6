//! The rollout driver every binding shares: output arrays sized and checked before any work,
//! the GIL released around the batch, and the diagnostics handed back ([`PyDiagnostics`]).

use std::sync::atomic::Ordering;
use std::time::Instant;

use numpy::ndarray::{Array1, Array3, Ix3};
use numpy::IntoPyArray;
use pyo3::exceptions::{PyMemoryError, PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use super::{check_output_bytes, detached, Array, FORKED};

use crate::rollout::{n_records, ChunkKernel, Rollout, TrajectoryInfo};
use crate::structures::lie_poisson::{self, VectorField};

/// The per-trajectory diagnostics as a dict of (n,) arrays; `step_angle` (h × the local rate
/// at each initial state, see [`VectorField::step_rate`]) where the rollout knows its system.
pub(super) fn info_dict<'py>(
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
pub(super) struct PyDiagnostics {
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
    pub(super) fn into_python(self, py: Python<'_>, lazy: bool) -> PyResult<Bound<'_, PyAny>> {
        if lazy {
            Ok(Bound::new(py, self)?.into_any())
        } else {
            Ok(self.arrays(py)?.into_any())
        }
    }
}

/// Records per trajectory and numbers in the (n, records, N) output of a rollout, and a check
/// that the output, the rollout's own state and every thread's workspace fit in memory.
pub(super) fn output_size<const N: usize>(
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
pub(super) type StepAngles<'a, const N: usize> = dyn Fn(&[[f64; N]], &mut [f64]) + Sync + 'a;

/// Wall-clock time a rollout segment aims at: Ctrl-C is noticed within about this long (plus one
/// step of one chunk of trajectories, the smallest segment).
pub(super) const SEGMENT_SECONDS: f64 = 0.05;

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
pub(super) fn run_rollout<'py, const N: usize, K: ChunkKernel<N>>(
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
pub(super) fn run_rollout_lazy<'py, const N: usize, K: ChunkKernel<N>>(
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
pub(super) fn angles_of<const N: usize, F: VectorField<N>>(
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

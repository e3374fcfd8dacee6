//! Batches of long rollouts, a fixed chunk of trajectories per rayon task, in segments of steps.
//!
//! Trajectories are independent, so the result is bit-identical whatever the thread count; a
//! trajectory's state is carried exactly between segments, so it is bit-identical whatever the
//! segmentation too. How a chunk is advanced is a [`ChunkKernel`]: one step of every trajectory
//! at a time for any [`StepMap`] ([`PerStep`]), or blocks of SIMD lanes kept in registers over
//! many steps ([`crate::lanes::Lanes`]).

use rayon::prelude::*;

use crate::error::{CoreError, StepFailure};
use crate::generating::MAX_BATCH;
use crate::step::{StepMap, StepResult, StepStats};

/// Per-trajectory diagnostics of a rollout.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrajectoryInfo {
    /// Every step succeeded.
    pub converged: bool,
    /// Index of the step that failed (from state k to k+1), or −1.
    pub failed_step: i64,
    /// Why it failed, if it did.
    pub failure: Option<StepFailure>,
    /// Newton updates summed over the trajectory.
    pub newton_iterations: u64,
    /// Most Newton updates in any one step.
    pub max_newton_iterations: u32,
    /// Largest accepted Newton residual |tar(∂S/∂p, p) − μ|∞ over the steps.
    pub max_residual: f64,
}

impl TrajectoryInfo {
    /// Counts one successful step's Newton updates and residual.
    #[inline(always)]
    pub(crate) fn count(&mut self, stats: StepStats) {
        self.newton_iterations += u64::from(stats.iterations);
        self.max_newton_iterations = self.max_newton_iterations.max(stats.iterations);
        self.max_residual = self.max_residual.max(stats.residual);
    }
}

impl Default for TrajectoryInfo {
    fn default() -> Self {
        TrajectoryInfo {
            converged: true,
            failed_step: -1,
            failure: None,
            newton_iterations: 0,
            max_newton_iterations: 0,
            max_residual: 0.0,
        }
    }
}

/// Number of stored states: steps 0, every, 2·every, … ≤ n_steps.
pub fn n_records(n_steps: usize, every: usize) -> usize {
    // Saturates rather than overflowing: a count that large fails the buffer-size checks.
    (n_steps / every.max(1)).saturating_add(1)
}

/// Checks the scalar arguments of a rollout.
pub fn check_arguments(h: f64, every: usize) -> Result<(), CoreError> {
    if !(h.is_finite() && h > 0.0) {
        return Err(CoreError::Invalid(format!(
            "h must be a finite number > 0, got {h}"
        )));
    }
    if every == 0 {
        return Err(CoreError::Invalid("every must be at least 1".into()));
    }
    Ok(())
}

/// Numbers per trajectory (N per stored state) and the check that `out` holds
/// (n, n_records, N).
fn check_buffer<const N: usize>(
    n: usize,
    n_steps: usize,
    every: usize,
    out: &[f64],
) -> Result<usize, CoreError> {
    let row = n_records(n_steps, every)
        .checked_mul(N)
        .ok_or_else(|| CoreError::Invalid(format!("{n_steps} steps overflow the record count")))?;
    if Some(out.len()) != n.checked_mul(row) {
        return Err(CoreError::Invalid(format!(
            "output buffer holds {} numbers, {} needed",
            out.len(),
            n.saturating_mul(row)
        )));
    }
    Ok(row)
}

/// One chunk of a rollout: its output rows, its states and its diagnostics.
type Chunk<'a, const N: usize> = (
    (&'a mut [f64], &'a mut [[f64; N]]),
    &'a mut [TrajectoryInfo],
);

/// A batch rollout that can be advanced a segment of steps at a time.
///
/// It carries each trajectory's current state and [`TrajectoryInfo`] between segments and writes
/// records at their global indices, so any split into segments gives results bit-identical to
/// one segment of all the steps (each trajectory sees the same sequence of `step` calls). The
/// bindings use this to return to Python between segments and notice Ctrl-C.
#[derive(Clone, Debug)]
pub struct Rollout<const N: usize> {
    h: f64,
    n_steps: usize,
    every: usize,
    /// Steps taken so far by every live trajectory.
    steps_done: usize,
    mu: Vec<[f64; N]>,
    info: Vec<TrajectoryInfo>,
}

impl<const N: usize> Rollout<N> {
    /// Checks the arguments and writes the initial states into record 0 of `out`
    /// (length n · n_records(n_steps, every) · N, laid out as (n, n_records, N)).
    pub fn start(
        mu0: &[[f64; N]],
        h: f64,
        n_steps: usize,
        every: usize,
        out: &mut [f64],
    ) -> Result<Self, CoreError> {
        check_arguments(h, every)?;
        let row = check_buffer::<N>(mu0.len(), n_steps, every, out)?;
        if let Some(bad) = mu0.iter().position(|m| !m.iter().all(|v| v.is_finite())) {
            return Err(CoreError::Invalid(format!(
                "initial state {bad} is not finite"
            )));
        }
        for (o, m) in out.chunks_exact_mut(row).zip(mu0) {
            o[..N].copy_from_slice(m);
        }
        Ok(Rollout {
            h,
            n_steps,
            every,
            steps_done: 0,
            mu: mu0.to_vec(),
            info: vec![TrajectoryInfo::default(); mu0.len()],
        })
    }

    /// Steps taken so far (by every trajectory that has not failed).
    pub fn steps_done(&self) -> usize {
        self.steps_done
    }

    /// Whether all `n_steps` steps have been taken.
    pub fn is_finished(&self) -> bool {
        self.steps_done == self.n_steps
    }

    /// Advances every live trajectory by up to `max_steps` steps (fewer at the end), writing the
    /// records that fall in this segment into `out` (the buffer given to [`Rollout::start`]).
    /// Returns the number of steps taken.
    pub fn advance<S: StepMap<N>>(
        &mut self,
        stepper: &S,
        max_steps: usize,
        out: &mut [f64],
    ) -> Result<usize, CoreError> {
        self.advance_with(stepper, max_steps, out, true)
    }

    /// [`Rollout::advance`], on rayon's pool when `parallel`, else on the calling thread (as in
    /// a forked child, where the pool's threads are gone). The chunks are the same either way,
    /// so the result is bit-identical.
    pub fn advance_with<S: StepMap<N>>(
        &mut self,
        stepper: &S,
        max_steps: usize,
        out: &mut [f64],
        parallel: bool,
    ) -> Result<usize, CoreError> {
        self.advance_kernel(&PerStep(stepper), max_steps, out, parallel)
    }

    /// [`Rollout::advance_with`] for any [`ChunkKernel`]. A rollout of a single chunk runs on
    /// the calling thread whatever `parallel` says: handing it to the pool costs more than it
    /// could gain.
    pub fn advance_kernel<K: ChunkKernel<N>>(
        &mut self,
        kernel: &K,
        max_steps: usize,
        out: &mut [f64],
        parallel: bool,
    ) -> Result<usize, CoreError> {
        let row = check_buffer::<N>(self.mu.len(), self.n_steps, self.every, out)?;
        let steps = max_steps.min(self.n_steps - self.steps_done);
        let (h, every, first) = (self.h, self.every, self.steps_done);
        if steps > 0 && !self.mu.is_empty() {
            // Fixed chunks of `batch` consecutive trajectories: which trajectories share a
            // batched solve never depends on the thread count.
            let batch = kernel.chunk().max(1);
            let chunk = |ws: &mut K::Workspace, ((o, mu), info): Chunk<'_, N>| {
                kernel.advance_chunk(ws, mu, info, h, first..first + steps, every, o);
            };
            if parallel && self.mu.len() > batch {
                out.par_chunks_mut(row * batch)
                    .zip(self.mu.par_chunks_mut(batch))
                    .zip(self.info.par_chunks_mut(batch))
                    .for_each_init(|| kernel.workspace(), chunk);
            } else {
                let mut ws = kernel.workspace();
                out.chunks_mut(row * batch)
                    .zip(self.mu.chunks_mut(batch))
                    .zip(self.info.chunks_mut(batch))
                    .for_each(|c| chunk(&mut ws, c));
            }
        }
        self.steps_done += steps;
        Ok(steps)
    }

    /// The current state of every trajectory (the last one reached where a step failed).
    pub fn states(&self) -> &[[f64; N]] {
        &self.mu
    }

    /// The per-trajectory diagnostics (final once [`Rollout::is_finished`]).
    pub fn info(&self) -> &[TrajectoryInfo] {
        &self.info
    }

    pub fn into_info(self) -> Vec<TrajectoryInfo> {
        self.info
    }
}

/// How a [`Rollout`] advances a chunk of consecutive trajectories over a range of steps. The
/// chunks are fixed by position (never by the thread count), and a kernel must give every
/// trajectory the same result whatever chunk it sits in.
pub trait ChunkKernel<const N: usize>: Sync {
    type Workspace: Send;
    fn workspace(&self) -> Self::Workspace;
    /// Bytes one workspace takes (the rollout makes one per thread).
    fn workspace_bytes(&self) -> usize {
        0
    }
    /// Trajectories per chunk.
    fn chunk(&self) -> usize;
    /// Takes the global steps `steps` (state k → k+1 for k in the range) of the trajectories
    /// `mu`, updating `info` and writing their records into their rows of `out` (n_records × N
    /// each). After a failed step a trajectory's later records are NaN.
    #[allow(clippy::too_many_arguments)]
    fn advance_chunk(
        &self,
        ws: &mut Self::Workspace,
        mu: &mut [[f64; N]],
        info: &mut [TrajectoryInfo],
        h: f64,
        steps: std::ops::Range<usize>,
        every: usize,
        out: &mut [f64],
    );
}

/// Any [`StepMap`] as a [`ChunkKernel`]: one step of every trajectory of the chunk at a time,
/// chunks of [`StepMap::batch`] trajectories.
pub struct PerStep<'a, S>(pub &'a S);

impl<const N: usize, S: StepMap<N>> ChunkKernel<N> for PerStep<'_, S> {
    type Workspace = S::Workspace;

    fn workspace(&self) -> S::Workspace {
        self.0.workspace()
    }

    fn workspace_bytes(&self) -> usize {
        self.0.workspace_bytes()
    }

    fn chunk(&self) -> usize {
        self.0.batch().clamp(1, MAX_BATCH)
    }

    fn advance_chunk(
        &self,
        ws: &mut S::Workspace,
        mu: &mut [[f64; N]],
        info: &mut [TrajectoryInfo],
        h: f64,
        steps: std::ops::Range<usize>,
        every: usize,
        out: &mut [f64],
    ) {
        advance_chunk(self.0, ws, mu, info, h, steps, every, out);
    }
}

/// The record global step k (state k → k+1) writes, if any: state k + 1 is kept where
/// `every` divides it. Computed once a step for a whole block, not once a trajectory (an
/// integer division costs about as much as the rest of [`record_step`]).
#[inline(always)]
pub(crate) fn record_of(k: usize, every: usize) -> Option<usize> {
    (k + 1).is_multiple_of(every).then(|| (k + 1) / every)
}

/// Records the outcome of global step k (state k → k+1) of one trajectory: its diagnostics, and
/// its new state `mu` in record `record` ([`record_of`]) if it is kept, or NaN in every later
/// record if the step failed. `o` is the trajectory's row of the output. Returns whether the
/// trajectory is still live.
#[inline]
pub(crate) fn record_step<const N: usize>(
    result: StepResult,
    k: usize,
    every: usize,
    record: Option<usize>,
    mu: &[f64; N],
    info: &mut TrajectoryInfo,
    o: &mut [f64],
) -> bool {
    match result {
        Ok(stats) => {
            info.count(stats);
            if let Some(r) = record {
                o[N * r..N * r + N].copy_from_slice(mu);
            }
            true
        }
        Err(failure) => {
            // The trajectory stops here: later records are NaN, never stale values.
            info.converged = false;
            info.failed_step = k as i64;
            info.failure = Some(failure);
            let next = (k + 1).div_ceil(every);
            o[N * next..].fill(f64::NAN);
            false
        }
    }
}

/// Takes the global steps `steps` (state k → k+1 for k in the range) of a chunk of
/// trajectories, writing their records into their rows of `out` (n_records × N each).
#[allow(clippy::too_many_arguments)]
fn advance_chunk<const N: usize, S: StepMap<N>>(
    stepper: &S,
    ws: &mut S::Workspace,
    mu: &mut [[f64; N]],
    info: &mut [TrajectoryInfo],
    h: f64,
    steps: std::ops::Range<usize>,
    every: usize,
    out: &mut [f64],
) {
    let n = mu.len();
    let row = out.len() / n;
    let mut live = [false; MAX_BATCH];
    let mut results: [StepResult; MAX_BATCH] = [Ok(StepStats::default()); MAX_BATCH];
    for (l, i) in live.iter_mut().zip(info.iter()) {
        *l = i.converged;
    }
    for k in steps {
        if !live[..n].contains(&true) {
            return;
        }
        stepper.step_batch(h, mu, &live[..n], &mut results[..n], ws);
        let record = record_of(k, every);
        for i in 0..n {
            if !live[i] {
                continue;
            }
            let o = &mut out[i * row..(i + 1) * row];
            live[i] = record_step(results[i], k, every, record, &mu[i], &mut info[i], o);
        }
    }
}

/// Rolls out every initial state for `n_steps` steps of size `h`, keeping every `every`-th state:
/// a [`Rollout`] advanced in one segment.
///
/// `out` has length n · n_records(n_steps, every) · N, laid out as (n, n_records, N).
pub fn rollout<const N: usize, S: StepMap<N>>(
    stepper: &S,
    mu0: &[[f64; N]],
    h: f64,
    n_steps: usize,
    every: usize,
    out: &mut [f64],
) -> Result<Vec<TrajectoryInfo>, CoreError> {
    let mut r = Rollout::start(mu0, h, n_steps, every, out)?;
    r.advance(stepper, n_steps, out)?;
    Ok(r.into_info())
}

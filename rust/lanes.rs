//! Batch-SIMD classical steppers: trajectories in structure-of-arrays blocks of [`LANES`]
//! lanes, kept in registers over a whole segment of steps, one instruction advancing every lane.
//!
//! A system plugs in by implementing one trait, [`LaneField`] (its vector field at L states at
//! once); [`Rk4`] then runs on it through [`Lanes`], the rollout kernel. The scalar steppers of
//! [`crate::classical`] stay the oracle.
//!
//! **Bit identity.** A lane performs exactly the scalar path's operations in the same order
//! (plain multiplies and adds: Rust never contracts `a * b + c` into an FMA), so every lane equals
//! the scalar [`crate::stepper::StepMap::step`] bit for bit, on every dispatch path, for any
//! chunking, padding and thread count. The tests check all of it.
//!
//! **Dispatch.** The block loop is compiled for the baseline x86-64 (SSE2, two lanes per
//! instruction), behind `#[target_feature(enable = "avx2,fma")]` for AVX2 (four lanes per
//! instruction) and behind `#[target_feature(enable = "avx512f,avx512vl,avx2,fma")]` (eight):
//! blocks of [`PAIRED_LANES`] where [`LaneStepper::avx512_paired`] says so (at any N; stepped
//! lane by lane where [`LaneStepper::avx512_by_lane`] says so), blocks of [`LANES`] where
//! [`LaneStepper::AVX512`] does (by default N ≤ 3), a wide stepper's blocks of
//! [`WIDE512_LANES`] where there are more than [`WIDE_LANES`] trajectories, chosen once at run
//! time with
//! `is_x86_feature_detected!` ([`Isa::detect`]). `std::arch` needs no dependency and no
//! `unsafe` beyond the call of the feature-gated function.

// Index loops over lanes and coordinates read as the formulas they evaluate.
#![allow(clippy::needless_range_loop)]

use nalgebra::{Const, DimMin};

use crate::classical::{ImplicitMidpoint, RigidBody, Rk4};
use crate::error::StepFailure;
pub use crate::isa::{Isa, AVX512_MAX_DIM, LANES};
pub use crate::lane_field::{
    midpoint_predictor_lanes, midpoint_update_lanes, rk4_by_lane, rk4_with, AtStates, FieldAt,
    LaneField, MidpointSolve,
};
use crate::rollout::{record_of, record_step, ChunkKernel, TrajectoryInfo};
use crate::step::{NewtonOptions, StepResult, StepStats};
use crate::straight_line::{sized_mut, LieField, Se3QuadraticLinear, So3Quadratic};
use crate::structures::lie_poisson::{CompiledLiePoisson, VectorField};

/// Trajectories per rollout chunk (a multiple of [`WIDE512_LANES`]).
pub const LANE_CHUNK: usize = 8 * LANES;

/// Lanes of a wide block ([`LaneStepper::WIDE`]).
pub const WIDE_LANES: usize = 4 * LANES;

/// Lanes of a wide block compiled for AVX-512, for blocks of more than [`WIDE_LANES`]
/// trajectories where the CPU has it: an interpreted field's instruction spreads its dispatch
/// over twice the lanes, in half the vector instructions a lane (measured on the extended
/// pendulum's RK4: 0.80× the time of AVX2 blocks of 32, where AVX-512 at 32 lanes read 0.96×
/// and AVX2 at 64 lanes 0.98×).
pub const WIDE512_LANES: usize = 8 * LANES;

/// Lanes of a paired AVX-512 block ([`LaneStepper::avx512_paired`]): two registers a
/// coordinate.
pub const PAIRED_LANES: usize = 2 * LANES;

impl<const N: usize> LaneField<N> for CompiledLiePoisson<N> {
    #[inline(always)]
    fn field_lanes<const L: usize>(&self, mu: &[[f64; L]; N], out: &mut [[f64; L]; N]) {
        CompiledLiePoisson::field_lanes(self, mu, out);
    }

    /// Each lane's exact Jacobian from the scalar sparse formula (it has no straight-line form
    /// for an arbitrary algebra), so that the midpoint's solve runs lane-wide.
    #[inline(always)]
    fn jacobian_lanes<const L: usize>(
        &self,
        mu: &[[f64; L]; N],
        out: &mut [[[f64; L]; N]; N],
    ) -> bool {
        crate::straight_line::jacobian_lanes_by(mu, out, |m| {
            let j = VectorField::jacobian(self, m);
            std::array::from_fn(|r| std::array::from_fn(|c| j[(r, c)]))
        })
    }
}

impl LaneField<3> for RigidBody {
    /// Measured: RK4 in blocks of 16 took 0.55× the time of blocks of 8.
    const AVX512_PAIRED: bool = true;

    /// Those blocks by lane: lane-inner, the block took 1.3 ns a step built by `cargo build`
    /// (no LTO beside the rlib) and 4.2–4.4 ns in the wheel's cdylib-only build while the
    /// profile had thin LTO (lane shuffles and stack stores in its loop; by lane it compiles
    /// well in both; docs/performance.md, "The build the benches time").
    const AVX512_BY_LANE: bool = true;

    #[inline(always)]
    fn rk4_step_by_lane<const L: usize>(&self, h: f64, mu: &mut [[f64; L]; 3]) {
        crate::straight_line::weighted_cross_rk4_by_lane(self.inverse_inertia(), h, mu);
    }

    /// μ × (μ/I), as [`RigidBody::vector_field`].
    #[inline(always)]
    fn field_lanes<const L: usize>(&self, mu: &[[f64; L]; 3], out: &mut [[f64; L]; 3]) {
        crate::straight_line::weighted_cross_lanes(&self.inverse_inertia(), mu, out);
    }

    /// As for [`So3Quadratic`](crate::straight_line::So3Quadratic): 9 flops a sweep.
    const MIDPOINT_SWEEPS: u32 = crate::straight_line::SO3_MIDPOINT_SWEEPS;

    /// The so(3) pattern kernel's Jacobian (the rigid body is that pattern with a = 1/I), so
    /// the midpoint rule solves its Newton systems lane-wide.
    #[inline(always)]
    fn jacobian_lanes<const L: usize>(
        &self,
        mu: &[[f64; L]; 3],
        out: &mut [[[f64; L]; 3]; 3],
    ) -> bool {
        self.pattern().jacobian_lanes(mu, out)
    }
}

/// A stepper that advances a block of L states by one step. Explicit steppers cannot fail
/// except by overflow, which [`Lanes`] detects after each step; implicit ones set
/// [`LaneStepper::REPORTS`] and give each lane its own outcome.
pub trait LaneStepper<const N: usize>: Sync {
    /// Whether [`LaneStepper::step_lanes_reporting`] gives per-lane outcomes (Newton counts,
    /// residuals, failures) that the block loop must record after every step.
    const REPORTS: bool = false;

    /// Whether blocks of [`WIDE_LANES`] trajectories pay (rather than [`LANES`]; of
    /// [`WIDE512_LANES`] on AVX-512): for work whose cost per instruction does not grow with the
    /// lanes (an interpreted program's dispatch). A block of at most [`LANES`] live trajectories
    /// stays narrow.
    const WIDE: bool = false;

    /// Whether the stepper has a domain beyond finite states (the block loop then asks
    /// [`LaneStepper::maybe_outside_lanes`] after every step).
    const CHECKS_DOMAIN: bool = false;

    /// Whether a block of at most [`LANES`] trajectories runs compiled for AVX-512 where the CPU
    /// has it ([`Isa::is_avx512`]): eight lanes are then one register, and a kernel whose block
    /// fits the 32 registers runs with fewer instructions. By default up to [`AVX512_MAX_DIM`]
    /// coordinates, where it was measured to pay; a stepper measured to lose there says false.
    /// (Longer blocks follow [`LaneStepper::avx512_paired`].) The same operations either way,
    /// so the same bits.
    const AVX512: bool = N <= AVX512_MAX_DIM;

    /// Whether blocks of more than [`LANES`] trajectories run compiled for AVX-512 in blocks of
    /// [`PAIRED_LANES`], two registers a coordinate, at any N (whatever
    /// [`LaneStepper::AVX512`] says). A step is a chain of dependent operations; two independent
    /// chains interleaved hide each other's latency, as two AVX2 registers a coordinate do at
    /// [`LANES`]. At N ≥ 5, where blocks of 8 lost to the compiler's shuffles, paired blocks
    /// gain for most steppers; where the doubled block spills out of the registers it costs
    /// more, so a stepper says so where measured to pay (docs/performance.md: the rigid body's
    /// RK4, splittings and DMV, the heavy top's midpoint rule and splitting, the log-canonical
    /// splittings, midpoint rule at N ≥ 3 and Taylor steps, the polynomial realization's Taylor
    /// steps). A method, so that a stepper with a run-time variant can answer for each.
    #[inline(always)]
    fn avx512_paired(&self) -> bool {
        false
    }

    /// Whether this stepper's paired AVX-512 blocks step lane by lane, the loop over lanes
    /// outermost ([`rk4_by_lane`]): for a straight-line step, which by lane is one vector
    /// instruction an operation where the lane-inner form packs coordinates into parts of
    /// registers. Implies [`LaneStepper::avx512_paired`]. A block of [`PAIRED_LANES`] is always
    /// an AVX-512 block, so the step tells them apart by L.
    #[inline(always)]
    fn avx512_by_lane(&self) -> bool {
        false
    }

    /// Whether the block loop's finiteness probe (Σ x·0 over each lane's coordinates, after
    /// every step) runs lane by lane in a block of [`PAIRED_LANES`], rather than coordinate by
    /// coordinate. The same sums; which order compiles to vector code depends on the step before
    /// it (measured): after Lotka–Volterra's by-lane RK4 the coordinate-by-coordinate sums of 16
    /// lanes compiled to shuffles (a quarter of its time), after the rigid body's lane-inner
    /// RK4 the lane-by-lane ones did (1.28–1.6× its time).
    const PROBE_BY_LANE: bool = false;

    /// Flags the lanes that may have left the domain: a cheap test over all lanes that may
    /// flag too many (never too few); each flagged lane then gets [`LaneStepper::domain`].
    #[inline(always)]
    fn maybe_outside_lanes<const L: usize>(&self, _mu: &[[f64; L]; N], _flag: &mut [bool; L]) {}

    /// The scalar step's own check of one state after a step (non-finite states included).
    #[inline(always)]
    fn domain(&self, _state: &[f64; N]) -> Result<(), StepFailure> {
        Ok(())
    }

    /// Advances every lane. An implementation defines this or
    /// [`LaneStepper::step_lanes_reporting`] (each defaults to the other): the default runs
    /// the reporting step with every lane live and drops the outcomes.
    #[inline(always)]
    fn step_lanes<const L: usize>(&self, h: f64, mu: &mut [[f64; L]; N]) {
        let mut result = [Ok(StepStats::default()); L];
        self.step_lanes_reporting(h, mu, &[true; L], &mut result);
    }

    /// Advances the `live` lanes, writing each one's outcome into `result` (a lane that fails
    /// holds what the scalar step leaves in its state). Explicit steppers report success and
    /// leave the overflow check to the block loop.
    #[inline(always)]
    fn step_lanes_reporting<const L: usize>(
        &self,
        h: f64,
        mu: &mut [[f64; L]; N],
        _live: &[bool; L],
        result: &mut [StepResult; L],
    ) {
        self.step_lanes(h, mu);
        result.fill(Ok(StepStats::default()));
    }
}

impl<const N: usize, F: LaneField<N>> LaneStepper<N> for Rk4<F> {
    const WIDE: bool = F::WIDE;
    const AVX512: bool = F::AVX512;
    const PROBE_BY_LANE: bool = F::AVX512_BY_LANE;

    #[inline(always)]
    fn avx512_paired(&self) -> bool {
        F::AVX512_PAIRED
    }

    #[inline(always)]
    fn avx512_by_lane(&self) -> bool {
        F::AVX512_BY_LANE
    }

    #[inline(always)]
    fn step_lanes<const L: usize>(&self, h: f64, mu: &mut [[f64; L]; N]) {
        rk4_lanes(&self.system, h, mu);
    }
}

/// One [`Rk4`] step of the field `f` at L states: the same operations as the scalar step, lane
/// by lane; in an AVX-512 paired block of a field that asks for it, the loop over lanes
/// outermost ([`rk4_by_lane`]).
#[inline(always)]
fn rk4_lanes<const N: usize, const L: usize, F: LaneField<N>>(
    f: &F,
    h: f64,
    mu: &mut [[f64; L]; N],
) {
    // A block of PAIRED_LANES is always an AVX-512 block (`Lanes::advance_chunk`).
    if F::AVX512_BY_LANE && L == PAIRED_LANES {
        f.rk4_step_by_lane(h, mu);
    } else {
        rk4_with(f, h, mu);
    }
}

impl<const N: usize, F: LaneField<N> + VectorField<N>> LaneStepper<N> for ImplicitMidpoint<F>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    const REPORTS: bool = true;

    #[inline(always)]
    fn step_lanes_reporting<const L: usize>(
        &self,
        h: f64,
        mu: &mut [[f64; L]; N],
        live: &[bool; L],
        result: &mut [StepResult; L],
    ) {
        midpoint_lanes(&self.system, &self.newton, h, mu, live, result);
    }
}

/// The scalar [`ImplicitMidpoint`] step of the field `f` lane by lane: the predictor
/// ([`midpoint_predictor_lanes`]), the field (and so the residual), the update and the
/// convergence test for the whole block at once; the Newton solve lane-wide where the field has
/// one ([`LaneField::solve_midpoint_lanes`]), else
/// (and in the lanes that need pivoting) each unconverged lane's exact Jacobian and LU solve by
/// the scalar functions on that lane's values (the same bits). A lane that converges is frozen
/// while the others iterate; one that fails stops with the scalar path's failure alone.
#[inline(always)]
fn midpoint_lanes<const N: usize, const L: usize, F: LaneField<N> + VectorField<N>>(
    f: &F,
    newton: &NewtonOptions,
    h: f64,
    mu: &mut [[f64; L]; N],
    live: &[bool; L],
    result: &mut [StepResult; L],
) where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    let mu0 = *mu;
    let half = 0.5 * h;
    let mut fm = [[0.0; L]; N];
    let mut m = [[0.0; L]; N];
    midpoint_predictor_lanes(f, half, &mu0, &mut m);
    // `active`: still iterating; `done`: converged. Every active lane has taken the same
    // number of updates, so one counter serves them all.
    let mut active = *live;
    let mut done = [false; L];
    let mut iterations = [0u32; L];
    let mut count = 0u32;
    while active.contains(&true) {
        if count >= newton.max_iter {
            for l in 0..L {
                if active[l] {
                    result[l] = Err(StepFailure::NotConverged);
                    active[l] = false;
                }
            }
            break;
        }
        f.field_lanes(&m, &mut fm);
        count += 1;
        let mut r = [[0.0; L]; N];
        for i in 0..N {
            for l in 0..L {
                r[i][l] = m[i][l] - mu0[i][l] - half * fm[i][l];
            }
        }
        // All lanes at once where the field has a lane-wide Jacobian; the others lane by lane.
        let mut wide = [[0.0; L]; N];
        let mut solved = [false; L];
        f.solve_midpoint_lanes(half, &m, &r, &mut wide, &mut solved);
        // The lanes the lane-wide solve left (all of them for a field without one): the
        // pivoted LU one by one, or its failure.
        for l in 0..L {
            if !active[l] || solved[l] {
                continue;
            }
            let ml: [f64; N] = std::array::from_fn(|i| m[i][l]);
            let rl: [f64; N] = std::array::from_fn(|i| r[i][l]);
            match f.midpoint_update(half, &ml, &rl) {
                Ok(d) => {
                    for i in 0..N {
                        wide[i][l] = d[i];
                    }
                }
                Err(e) => {
                    result[l] = Err(e);
                    active[l] = false;
                }
            }
        }
        // m += δ in the active lanes and the scalar step's test |δ|∞ ≤ tol·max(|m|∞, 1e-300),
        // for all lanes at once (the maxima folded in the scalar `max_abs`'s order).
        // Every lane active (the rule) needs no choice per entry in a block of two registers a
        // coordinate: see [`midpoint_predictor_lanes`] for what one costs there.
        let (dmax, mmax) = if L > LANES && !active.contains(&false) {
            add_update::<N, L, true>(&mut m, &wide, &active)
        } else {
            add_update::<N, L, false>(&mut m, &wide, &active)
        };
        for l in 0..L {
            if active[l] && dmax[l] <= newton.tol * mmax[l].max(1e-300) {
                active[l] = false;
                done[l] = true;
                iterations[l] = count;
            }
        }
    }
    f.field_lanes(&m, &mut fm);
    // The scalar step's residual (its `max_abs`, folded in the same order) and μ + h f(m), for
    // all lanes at once; only the converged lanes keep them (every lane converged, the rule,
    // needs no choice per entry in a block of two registers a coordinate).
    let (residual, finite) = if L > LANES && !done.contains(&false) {
        finish_midpoint::<N, L, true>(h, &mu0, &m, &fm, &done, mu)
    } else {
        finish_midpoint::<N, L, false>(h, &mu0, &m, &fm, &done, mu)
    };
    for l in 0..L {
        if done[l] {
            result[l] = if finite[l] {
                Ok(StepStats {
                    iterations: iterations[l],
                    residual: residual[l],
                })
            } else {
                Err(StepFailure::NonFinite)
            };
        }
    }
}

/// m += δ in the lanes `active` (in every lane where `ALL`: the same numbers without a choice
/// per entry) and the maxima |δ|∞ and |m|∞ of each lane, folded in the scalar `max_abs`'s order.
#[inline(always)]
fn add_update<const N: usize, const L: usize, const ALL: bool>(
    m: &mut [[f64; L]; N],
    delta: &[[f64; L]; N],
    active: &[bool; L],
) -> ([f64; L], [f64; L]) {
    let (mut dmax, mut mmax) = ([0.0f64; L], [0.0f64; L]);
    for i in 0..N {
        for l in 0..L {
            m[i][l] = if ALL || active[l] {
                m[i][l] + delta[i][l]
            } else {
                m[i][l]
            };
            dmax[l] = dmax[l].max(delta[i][l].abs());
            mmax[l] = mmax[l].max(m[i][l].abs());
        }
    }
    (dmax, mmax)
}

/// The midpoint step's end at m: μ = μ₀ + h f(m) in the lanes `done` (every lane where `ALL`),
/// and each lane's residual |m − μ₀ − ½h f(m)|∞ (the scalar `max_abs`'s order) and whether its
/// new state is finite.
#[inline(always)]
fn finish_midpoint<const N: usize, const L: usize, const ALL: bool>(
    h: f64,
    mu0: &[[f64; L]; N],
    m: &[[f64; L]; N],
    fm: &[[f64; L]; N],
    done: &[bool; L],
    mu: &mut [[f64; L]; N],
) -> ([f64; L], [bool; L]) {
    let half = 0.5 * h;
    let mut residual = [0.0f64; L];
    let mut finite = [true; L];
    for i in 0..N {
        for l in 0..L {
            let r = m[i][l] - mu0[i][l] - half * fm[i][l];
            residual[l] = residual[l].max(r.abs());
            let next = mu0[i][l] + h * fm[i][l];
            finite[l] &= next.is_finite();
            mu[i][l] = if ALL || done[l] { next } else { mu[i][l] };
        }
    }
    (residual, finite)
}

/// The heavy top and the rigid body as a Lie–Poisson system: the variant of [`LieField`] is
/// matched once a step, then its own RK4 runs (a straight-line kernel, or the compiled field).
impl<const N: usize> LaneStepper<N> for Rk4<LieField<N>> {
    /// The variant's own [`LaneField::AVX512_PAIRED`].
    #[inline(always)]
    fn avx512_paired(&self) -> bool {
        match self.system {
            LieField::Compiled(_) => <CompiledLiePoisson<N> as LaneField<N>>::AVX512_PAIRED,
            LieField::So3(_) => <So3Quadratic as LaneField<3>>::AVX512_PAIRED,
            LieField::Se3(_) => <Se3QuadraticLinear as LaneField<6>>::AVX512_PAIRED,
        }
    }

    /// The variant's own [`LaneField::AVX512_BY_LANE`].
    #[inline(always)]
    fn avx512_by_lane(&self) -> bool {
        match self.system {
            LieField::Compiled(_) => <CompiledLiePoisson<N> as LaneField<N>>::AVX512_BY_LANE,
            LieField::So3(_) => <So3Quadratic as LaneField<3>>::AVX512_BY_LANE,
            LieField::Se3(_) => <Se3QuadraticLinear as LaneField<6>>::AVX512_BY_LANE,
        }
    }

    #[inline(always)]
    fn step_lanes<const L: usize>(&self, h: f64, mu: &mut [[f64; L]; N]) {
        match &self.system {
            LieField::Compiled(f) => rk4_lanes(f, h, mu),
            LieField::So3(f) => match sized_mut::<_, N, 3>(mu) {
                Some(m) => rk4_lanes(f, h, m),
                // Unreachable: the variant is built for N = 3 only (NaN fails the lanes).
                None => *mu = [[f64::NAN; L]; N],
            },
            LieField::Se3(f) => match sized_mut::<_, N, 6>(mu) {
                Some(m) => rk4_lanes(f, h, m),
                None => *mu = [[f64::NAN; L]; N],
            },
        }
    }
}

/// As for [`Rk4`]: the variant matched once a step, then its own masked Newton lanes.
impl<const N: usize> LaneStepper<N> for ImplicitMidpoint<LieField<N>>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    const REPORTS: bool = true;

    /// The se(3) kernel's: 0.62× the time of AVX2 blocks (the so(3) one read 0.93×, noise).
    #[inline(always)]
    fn avx512_paired(&self) -> bool {
        matches!(self.system, LieField::Se3(_))
    }

    #[inline(always)]
    fn step_lanes_reporting<const L: usize>(
        &self,
        h: f64,
        mu: &mut [[f64; L]; N],
        live: &[bool; L],
        result: &mut [StepResult; L],
    ) {
        let newton = &self.newton;
        // A `match`, not `Option::map` with a closure: a closure left out of line would be
        // compiled without the caller's AVX2 (it ran the heavy top's Newton lanes in SSE2).
        let done = match &self.system {
            LieField::Compiled(f) => {
                midpoint_lanes(f, newton, h, mu, live, result);
                true
            }
            LieField::So3(f) => match sized_mut::<_, N, 3>(mu) {
                Some(m) => {
                    midpoint_lanes::<3, L, _>(f, newton, h, m, live, result);
                    true
                }
                None => false,
            },
            LieField::Se3(f) => match sized_mut::<_, N, 6>(mu) {
                Some(m) => {
                    midpoint_lanes::<6, L, _>(f, newton, h, m, live, result);
                    true
                }
                None => false,
            },
        };
        if !done {
            // Unreachable: a pattern variant is built for its own dimension only.
            result.fill(Err(StepFailure::NonFinite));
        }
    }
}

/// A [`LaneStepper`] as a rollout [`ChunkKernel`]: chunks of [`LANE_CHUNK`] trajectories, each
/// advanced in blocks of [`LANES`] (the last block padded with zero states, whose lanes are
/// ignored), the block loop compiled for `isa`.
pub struct Lanes<'a, S> {
    pub stepper: &'a S,
    pub isa: Isa,
}

impl<'a, S> Lanes<'a, S> {
    /// The kernel for the widest instruction set this CPU runs.
    pub fn new(stepper: &'a S) -> Self {
        Lanes {
            stepper,
            isa: Isa::detect(),
        }
    }
}

/// One block's view of its trajectories: states, diagnostics and output rows.
struct Block<'a, const N: usize> {
    mu: &'a mut [[f64; N]],
    info: &'a mut [TrajectoryInfo],
    out: &'a mut [f64],
    row: usize,
}

impl<const N: usize, S: LaneStepper<N>> ChunkKernel<N> for Lanes<'_, S> {
    type Workspace = ();

    fn workspace(&self) {}

    fn chunk(&self) -> usize {
        LANE_CHUNK
    }

    fn advance_chunk(
        &self,
        _: &mut (),
        mu: &mut [[f64; N]],
        info: &mut [TrajectoryInfo],
        h: f64,
        steps: std::ops::Range<usize>,
        every: usize,
        out: &mut [f64],
    ) {
        if mu.is_empty() {
            return;
        }
        let row = out.len() / mu.len();
        // Blocks of more than LANES trajectories run paired AVX-512 where the stepper asks (at
        // any N); blocks of at most LANES run AVX-512 where `S::AVX512` says, else AVX2. A wide
        // stepper's blocks of more than WIDE_LANES run AVX-512 blocks of WIDE512_LANES where the
        // CPU has it, its other blocks of more than LANES AVX2 blocks of WIDE_LANES.
        let isa512 = !S::WIDE && self.isa.is_avx512();
        let paired = isa512 && (self.stepper.avx512_paired() || self.stepper.avx512_by_lane());
        let single = isa512 && S::AVX512;
        let wide512 = S::WIDE && self.isa.is_avx512();
        let width = if wide512 {
            WIDE512_LANES
        } else if S::WIDE {
            WIDE_LANES
        } else if paired {
            PAIRED_LANES
        } else {
            LANES
        };
        for ((m, i), o) in mu
            .chunks_mut(width)
            .zip(info.chunks_mut(width))
            .zip(out.chunks_mut(row * width))
        {
            let block = Block {
                mu: m,
                info: i,
                out: o,
                row,
            };
            // The block loop `$f` at `$lanes` lanes; every path passes the same arguments.
            macro_rules! advance {
                ($f:ident, $lanes:expr) => {
                    $f::<N, { $lanes }, S>(self.stepper, h, steps.clone(), every, block)
                };
            }
            if block.mu.len() == 1 {
                // A lone trajectory: a block of one lane does the same arithmetic (bit for bit)
                // without carrying seven idle ones.
                advance!(advance_block, 1);
                continue;
            }
            let wide = S::WIDE && block.mu.len() > LANES;
            #[cfg(target_arch = "x86_64")]
            if wide512 && block.mu.len() > WIDE_LANES {
                // SAFETY: as below, an `Isa` that claims AVX-512.
                unsafe { advance!(advance_block_avx512, WIDE512_LANES) };
                continue;
            }
            #[cfg(target_arch = "x86_64")]
            if (paired && block.mu.len() > LANES) || single {
                // SAFETY: an `Isa` claims AVX-512 only where run-time detection found AVX-512 F
                // and VL, AVX2 and FMA (its fields are private: safe code cannot forge it).
                unsafe {
                    if paired && block.mu.len() > LANES {
                        advance!(advance_block_avx512, PAIRED_LANES)
                    } else {
                        advance!(advance_block_avx512, LANES)
                    }
                };
                continue;
            }
            #[cfg(target_arch = "x86_64")]
            if self.isa.is_avx2() {
                // SAFETY: an `Isa` claims AVX2 only where run-time detection found AVX2 and FMA
                // (its field is private: safe code cannot forge it).
                unsafe {
                    if wide {
                        advance!(advance_block_avx2, WIDE_LANES)
                    } else {
                        advance!(advance_block_avx2, LANES)
                    }
                };
                continue;
            }
            if wide {
                advance!(advance_block, WIDE_LANES);
            } else {
                advance!(advance_block, LANES);
            }
        }
    }
}

/// [`advance_block`] compiled for the CPU features `$features`: callable only behind the
/// [`Isa`] proof that this CPU has them.
macro_rules! advance_block_for {
    ($name:ident, $features:literal) => {
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = $features)]
        unsafe fn $name<const N: usize, const L: usize, S: LaneStepper<N>>(
            stepper: &S,
            h: f64,
            steps: std::ops::Range<usize>,
            every: usize,
            block: Block<'_, N>,
        ) {
            advance_block::<N, L, S>(stepper, h, steps, every, block);
        }
    };
}

advance_block_for!(advance_block_avx2, "avx2,fma");
advance_block_for!(advance_block_avx512, "avx512f,avx512vl,avx2,fma");

/// Loads up to L trajectories into lanes, takes the steps, records and checks each lane after
/// every step, and stores the live lanes back.
#[inline(always)]
fn advance_block<const N: usize, const L: usize, S: LaneStepper<N>>(
    stepper: &S,
    h: f64,
    steps: std::ops::Range<usize>,
    every: usize,
    block: Block<'_, N>,
) {
    let Block { mu, info, out, row } = block;
    let n = mu.len();
    let mut lanes = [[0.0; L]; N];
    let mut live = [false; L];
    for (l, (m, i)) in mu.iter().zip(info.iter()).enumerate() {
        live[l] = i.converged;
        for c in 0..N {
            lanes[c][l] = m[c];
        }
    }
    if !live.contains(&true) {
        return;
    }
    for k in steps {
        if S::REPORTS {
            let mut result = [Ok(StepStats::default()); L];
            stepper.step_lanes_reporting(h, &mut lanes, &live, &mut result);
            let record = record_of(k, every);
            for l in 0..n {
                if !live[l] {
                    continue;
                }
                // A step that succeeded between records only counts its updates: no state
                // gathered from the lanes, no call (the two took 6 % of a profile's samples of the
                // heavy top's midpoint rollout).
                if let (Ok(stats), None) = (result[l], record) {
                    info[l].count(stats);
                    continue;
                }
                let state: [f64; N] = std::array::from_fn(|c| lanes[c][l]);
                if result[l].is_err() {
                    mu[l] = state;
                }
                let o = &mut out[l * row..(l + 1) * row];
                live[l] = record_step(result[l], k, every, record, &state, &mut info[l], o);
            }
            if !live.contains(&true) {
                return;
            }
            continue;
        }
        stepper.step_lanes(h, &mut lanes);
        // x · 0 is 0 for finite x and NaN for ±∞ and NaN: one multiply-add per coordinate.
        // The same sums in either order ([`LaneStepper::PROBE_BY_LANE`]).
        let mut probe = [0.0; L];
        if S::PROBE_BY_LANE && L == PAIRED_LANES {
            for l in 0..L {
                for c in 0..N {
                    probe[l] += lanes[c][l] * 0.0;
                }
            }
        } else {
            for c in 0..N {
                for l in 0..L {
                    probe[l] += lanes[c][l] * 0.0;
                }
            }
        }
        let all_finite = probe.iter().all(|p| *p == 0.0);
        let mut flagged = [false; L];
        let mut inside = true;
        if S::CHECKS_DOMAIN {
            stepper.maybe_outside_lanes(&lanes, &mut flagged);
            // Padding lanes (zero states) may be flagged; only live ones count.
            inside = !(0..n).any(|l| live[l] && flagged[l]);
        }
        let record = record_of(k, every);
        if record.is_none() && all_finite && inside {
            continue;
        }
        for l in 0..n {
            if !live[l] {
                continue;
            }
            let state: [f64; N] = std::array::from_fn(|c| lanes[c][l]);
            let result = if probe[l] != 0.0 {
                Err(StepFailure::NonFinite)
            } else if flagged[l] {
                stepper.domain(&state).map(|()| StepStats::default())
            } else {
                Ok(StepStats::default())
            };
            if result.is_err() {
                mu[l] = state;
            }
            let o = &mut out[l * row..(l + 1) * row];
            live[l] = record_step(result, k, every, record, &state, &mut info[l], o);
        }
        if !live.contains(&true) {
            return;
        }
    }
    for l in 0..n {
        if live[l] {
            mu[l] = std::array::from_fn(|c| lanes[c][l]);
        }
    }
}

/// δ = J⁻¹ f at L lanes: by cofactors for N ≤ 3, by Gaussian elimination with partial pivoting
/// above ([`solve_pivoted_lanes`]); `ok[l]` is false where J is singular (det 0 or a zero
/// pivot) or not finite.
#[inline(always)]
pub(crate) fn solve_small_lanes<const N: usize, const L: usize>(
    j: &[[[f64; L]; N]; N],
    f: &[[f64; L]; N],
    delta: &mut [[f64; L]; N],
    ok: &mut [bool; L],
) {
    if N > 3 {
        return solve_pivoted_lanes(j, f, delta, ok);
    }
    for l in 0..L {
        let m: [[f64; N]; N] = std::array::from_fn(|r| std::array::from_fn(|c| j[r][c][l]));
        let (adj, det): ([[f64; N]; N], f64) = if N == 1 {
            (
                std::array::from_fn(|_| std::array::from_fn(|_| 1.0)),
                m[0][0],
            )
        } else if N == 2 {
            let adj = [[m[1][1], -m[0][1]], [-m[1][0], m[0][0]]];
            (
                std::array::from_fn(|r| std::array::from_fn(|c| adj[r][c])),
                m[0][0] * m[1][1] - m[0][1] * m[1][0],
            )
        } else {
            let m3: [[f64; 3]; 3] = std::array::from_fn(|r| std::array::from_fn(|c| m[r][c]));
            let (adj, det) = crate::step::adjugate3(&m3);
            (
                std::array::from_fn(|r| std::array::from_fn(|c| adj[r][c])),
                det,
            )
        };
        ok[l] = det != 0.0 && det.is_finite();
        let r = 1.0 / det;
        for a in 0..N {
            let mut acc = 0.0;
            for b in 0..N {
                acc += adj[a][b] * f[b][l];
            }
            delta[a][l] = acc * r;
        }
    }
}

/// δ = J⁻¹ f at L lanes by Gaussian elimination with partial pivoting, each lane choosing and
/// swapping its own pivot rows (so a lane's bits depend on no other lane), then back
/// substitution; `ok[l]` is false where a pivot is 0 or not finite.
#[inline(always)]
pub(crate) fn solve_pivoted_lanes<const N: usize, const L: usize>(
    j: &[[[f64; L]; N]; N],
    f: &[[f64; L]; N],
    delta: &mut [[f64; L]; N],
    ok: &mut [bool; L],
) {
    let (mut a, mut b) = (*j, *f);
    *ok = [true; L];
    for col in 0..N {
        for l in 0..L {
            let mut best = col;
            for r in col + 1..N {
                if a[r][col][l].abs() > a[best][col][l].abs() {
                    best = r;
                }
            }
            if best != col {
                for k in col..N {
                    let t = a[best][k][l];
                    a[best][k][l] = a[col][k][l];
                    a[col][k][l] = t;
                }
                let t = b[best][l];
                b[best][l] = b[col][l];
                b[col][l] = t;
            }
            let pivot = a[col][col][l];
            ok[l] &= pivot != 0.0 && pivot.is_finite();
        }
        for row in col + 1..N {
            let mut factor = [0.0; L];
            for l in 0..L {
                factor[l] = a[row][col][l] / a[col][col][l];
            }
            for k in col + 1..N {
                for l in 0..L {
                    a[row][k][l] -= factor[l] * a[col][k][l];
                }
            }
            for l in 0..L {
                b[row][l] -= factor[l] * b[col][l];
            }
        }
    }
    for row in (0..N).rev() {
        let mut acc = b[row];
        for k in row + 1..N {
            for l in 0..L {
                acc[l] -= a[row][k][l] * delta[k][l];
            }
        }
        for l in 0..L {
            delta[row][l] = acc[l] / a[row][row][l];
        }
    }
}

/// Full Newton's rule for one lane of a lane solve (the log-canonical and the order-n
/// realization steps), the generic step's order of failures: derivatives not finite →
/// NonFinite, the update cap → NotConverged, J singular or δ not finite → SingularJacobian.
pub(crate) struct FullNewton {
    pub tol: f64,
    pub max_iter: u32,
    /// Newton stops once |δ|∞ ≤ tol · max(|p|∞, floor).
    pub floor: f64,
}

impl FullNewton {
    /// Lane l fails (its result written, `active` cleared) or takes p += δ and counts the
    /// update; returns whether it converged with it (then `active` is cleared too).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn settle<const N: usize, const L: usize>(
        &self,
        l: usize,
        finite: bool,
        solvable: bool,
        delta: &[[f64; L]; N],
        p: &mut [[f64; L]; N],
        iterations: &mut [u32; L],
        active: &mut [bool; L],
        result: &mut [StepResult; L],
    ) -> bool {
        let failure = if !finite {
            Some(StepFailure::NonFinite)
        } else if iterations[l] >= self.max_iter {
            Some(StepFailure::NotConverged)
        } else if !solvable || !(0..N).all(|a| delta[a][l].is_finite()) {
            Some(StepFailure::SingularJacobian)
        } else {
            None
        };
        if let Some(failure) = failure {
            result[l] = Err(failure);
            active[l] = false;
            return false;
        }
        let (mut dmax, mut pmax) = (0.0f64, 0.0f64);
        for a in 0..N {
            p[a][l] += delta[a][l];
            dmax = dmax.max(delta[a][l].abs());
            pmax = pmax.max(p[a][l].abs());
        }
        iterations[l] += 1;
        let done = dmax <= self.tol * pmax.max(self.floor);
        if done {
            active[l] = false;
        }
        done
    }
}

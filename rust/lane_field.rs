//! A vector field in SIMD lanes ([`LaneField`]) and the implicit midpoint's Newton update on it
//! ([`MidpointSolve`]), for one state or a block: the interface between a system's field and the
//! classical steppers, scalar ([`crate::classical`]) or in lanes ([`crate::lanes`]).

// Index loops over lanes and coordinates read as the formulas they evaluate.
#![allow(clippy::needless_range_loop)]

use nalgebra::{Const, DimMin, SMatrix, SVector};

use crate::error::StepFailure;
use crate::structures::lie_poisson::VectorField;

/// A vector field evaluated on a block of L states at once.
///
/// `mu[i][l]` is coordinate i of lane l. An implementation must give each lane the same number,
/// bit for bit, as the system's scalar field (the same operations in the same order), and no
/// lane may depend on another: that is what keeps results independent of the chunking.
pub trait LaneField<const N: usize>: Sync {
    /// Whether RK4 on this field runs in wide blocks ([`crate::lanes::WIDE_LANES`]
    /// trajectories): true for a field interpreted instruction by instruction (an expression's
    /// program), whose dispatch per instruction is then spread over four times the lanes.
    const WIDE: bool = false;

    /// Whether RK4 on this field runs its blocks compiled for AVX-512 where the CPU has it
    /// ([`crate::lanes::LaneStepper::AVX512`], whose default by dimension this follows).
    const AVX512: bool = N <= crate::isa::AVX512_MAX_DIM;

    /// Whether RK4 on this field runs AVX-512 blocks of two registers a coordinate
    /// ([`crate::lanes::LaneStepper::avx512_paired`]).
    const AVX512_PAIRED: bool = false;

    /// Whether RK4 on this field steps its AVX-512 blocks of [`crate::lanes::PAIRED_LANES`]
    /// lane by lane ([`LaneField::rk4_step_by_lane`]; [`crate::lanes::LaneStepper::avx512_by_lane`]).
    /// For a field whose [`LaneField::field_lanes`] is straight-line code with no branch.
    const AVX512_BY_LANE: bool = false;

    /// One RK4 step at L states by lane ([`rk4_by_lane`]), for [`LaneField::AVX512_BY_LANE`].
    /// A field overrides it to run on a copy of its constants (read through `self`, they are
    /// loaded again in every lane, since the compiler cannot tell them apart from the block it
    /// stores to, and the loop stays scalar) and to match any variant outside the loop.
    #[inline(always)]
    fn rk4_step_by_lane<const L: usize>(&self, h: f64, mu: &mut [[f64; L]; N])
    where
        Self: Sized,
    {
        rk4_by_lane::<N, L, 1, Self>(self, h, mu);
    }

    fn field_lanes<const L: usize>(&self, mu: &[[f64; L]; N], out: &mut [[f64; L]; N]);

    /// ∂f/∂μ at L states (`out[r][c][l]`), where the field provides it (in straight-line form,
    /// or lane by lane from its scalar formula); then the implicit midpoint solves its Newton
    /// systems for all lanes at once ([`midpoint_update_lanes`]). The default has none and
    /// returns false.
    #[inline(always)]
    fn jacobian_lanes<const L: usize>(
        &self,
        _mu: &[[f64; L]; N],
        _out: &mut [[[f64; L]; N]; N],
    ) -> bool {
        false
    }

    /// Fixed-point sweeps m ← μ + half·f(m) the implicit midpoint takes after its Euler
    /// predictor ([`midpoint_predictor_lanes`]). Each sweep costs one field evaluation and, where
    /// half·‖∂f/∂μ‖ is small, gains about a digit: worth it where a field evaluation is cheap
    /// next to a Newton update (a straight-line kernel), so that Newton needs one update fewer.
    const MIDPOINT_SWEEPS: u32 = 0;

    /// The implicit midpoint's Newton updates at L states, as [`midpoint_update_lanes`]
    /// specifies them (δ in every lane, `solved[l]` where lane l's δ is to be kept, false where
    /// the field has no lane-wide solve). The default is [`midpoint_update_lanes`]; a field with
    /// a structured Jacobian may solve by its blocks instead. The scalar step runs it with
    /// L = 1 ([`MidpointSolve`]), so its choice and bits must not depend on the other lanes.
    #[inline(always)]
    fn solve_midpoint_lanes<const L: usize>(
        &self,
        half: f64,
        m: &[[f64; L]; N],
        r: &[[f64; L]; N],
        delta: &mut [[f64; L]; N],
        solved: &mut [bool; L],
    ) -> bool
    where
        Self: Sized,
    {
        midpoint_update_lanes(self, half, m, r, delta, solved)
    }
}

/// A field at L states as the RK4 kernels call it: every [`LaneField`], or a kernel at K states
/// bound to copies of its constants ([`AtStates`]). A trait, not a closure: a closure left
/// out of line is compiled without the caller's target features (an interpreted field's RK4
/// ran 1.09–1.14× slower through one).
pub trait FieldAt<const N: usize, const L: usize> {
    fn field_at(&self, y: &[[f64; L]; N], out: &mut [[f64; L]; N]);
}

impl<const N: usize, const L: usize, F: LaneField<N>> FieldAt<N, L> for F {
    #[inline(always)]
    fn field_at(&self, y: &[[f64; L]; N], out: &mut [[f64; L]; N]) {
        self.field_lanes(y, out);
    }
}

/// A straight-line kernel at K states, `(y, out)`, as a [`FieldAt`] for [`rk4_by_lane`].
pub struct AtStates<const K: usize, C>(pub C);

impl<const N: usize, const K: usize, C: Fn(&[[f64; K]; N], &mut [[f64; K]; N])> FieldAt<N, K>
    for AtStates<K, C>
{
    #[inline(always)]
    fn field_at(&self, y: &[[f64; K]; N], out: &mut [[f64; K]; N]) {
        (self.0)(y, out);
    }
}

/// One RK4 step of `f` at L states: the same operations as the scalar step, lane by lane
/// (k₁ = f(μ), k₂ = f(μ + ½h k₁), k₃ = f(μ + ½h k₂), k₄ = f(μ + h k₃), μ += h/6 (k₁ + 2(k₂ +
/// k₃) + k₄)).
#[inline(always)]
pub fn rk4_with<const N: usize, const L: usize, F: FieldAt<N, L>>(
    f: &F,
    h: f64,
    mu: &mut [[f64; L]; N],
) {
    let (mut k1, mut k2, mut k3, mut k4) =
        ([[0.0; L]; N], [[0.0; L]; N], [[0.0; L]; N], [[0.0; L]; N]);
    let mut y = [[0.0; L]; N];
    let (half, sixth) = (0.5 * h, h / 6.0);
    f.field_at(mu, &mut k1);
    axpy_lanes(half, &k1, mu, &mut y);
    f.field_at(&y, &mut k2);
    axpy_lanes(half, &k2, mu, &mut y);
    f.field_at(&y, &mut k3);
    axpy_lanes(h, &k3, mu, &mut y);
    f.field_at(&y, &mut k4);
    for i in 0..N {
        for l in 0..L {
            mu[i][l] += sixth * (k1[i][l] + 2.0 * (k2[i][l] + k3[i][l]) + k4[i][l]);
        }
    }
}

/// [`rk4_with`] at L states with the loop over lanes outermost: each lane runs the scalar
/// step's code (`f` at K states, lanes l, l + L/K, …, each its own chain of operations), and the
/// compiler vectorises that loop across lanes, one register a coordinate. The same operations,
/// so the same bits. For AVX-512 blocks of a field whose lane-inner form the compiler packs
/// badly: at N = 6 it packs pairs of coordinates into 128-bit halves (the heavy top's RK4 took
/// 3.7× its AVX2 time), where this form is one vector instruction an operation. `f` must be
/// straight-line code (a branch in it keeps the loop scalar) on constants the loop holds in
/// registers (copies, [`AtStates`]).
///
/// K = 2 puts twice the independent work in flight, for a step whose one chain is
/// latency-bound (the point vortices' divisions: 0.72× the time of K = 1); a field with many
/// coordinates and no division runs out of registers that way (the heavy top's RK4 took 1.1×
/// its time). Where K does not divide L, each of the last lanes runs as K copies of itself.
#[inline(always)]
pub fn rk4_by_lane<const N: usize, const L: usize, const K: usize, F: FieldAt<N, K>>(
    f: &F,
    h: f64,
    mu: &mut [[f64; L]; N],
) {
    by_lane::<N, L, K, _>(&Rk4Step(f), h, mu);
}

/// One explicit step of size h at K states: what [`by_lane`] runs lane by lane. A trait, not a
/// closure, for the reason [`FieldAt`] is one (through a closure the heavy top's RK4 by lane
/// ran 16× slower: its lane loop no longer vectorised).
pub trait StepAt<const N: usize, const K: usize> {
    fn step_at(&self, h: f64, y: &mut [[f64; K]; N]);
}

/// [`rk4_with`] of a field, as a [`StepAt`].
pub struct Rk4Step<'a, F>(pub &'a F);

impl<const N: usize, const K: usize, F: FieldAt<N, K>> StepAt<N, K> for Rk4Step<'_, F> {
    #[inline(always)]
    fn step_at(&self, h: f64, y: &mut [[f64; K]; N]) {
        rk4_with(self.0, h, y);
    }
}

/// `step` at L states with the loop over lanes outermost: lanes l, l + L/K, … gathered,
/// stepped and scattered back; where K does not divide L, each of the last lanes runs as K
/// copies of itself. Each lane runs the step's operations, so it has the bits of the step at
/// one state. The form of [`rk4_by_lane`], for any explicit step written at K states.
#[inline(always)]
pub fn by_lane<const N: usize, const L: usize, const K: usize, S: StepAt<N, K>>(
    step: &S,
    h: f64,
    mu: &mut [[f64; L]; N],
) {
    let stride = L / K;
    for l in 0..stride {
        let mut some: [[f64; K]; N] =
            std::array::from_fn(|i| std::array::from_fn(|j| mu[i][l + j * stride]));
        step.step_at(h, &mut some);
        for i in 0..N {
            for j in 0..K {
                mu[i][l + j * stride] = some[i][j];
            }
        }
    }
    for l in stride * K..L {
        let mut copies: [[f64; K]; N] = std::array::from_fn(|i| [mu[i][l]; K]);
        step.step_at(h, &mut copies);
        for i in 0..N {
            mu[i][l] = copies[i][0];
        }
    }
}

/// out = y + a·x, lane by lane (the scalar `axpy`).
#[inline(always)]
pub(crate) fn axpy_lanes<const L: usize, const N: usize>(
    a: f64,
    x: &[[f64; L]; N],
    y: &[[f64; L]; N],
    out: &mut [[f64; L]; N],
) {
    for i in 0..N {
        for l in 0..L {
            out[i][l] = y[i][l] + a * x[i][l];
        }
    }
}

/// The implicit midpoint's starting point `m` at the L states `mu0`: the Euler midpoint
/// μ + half·f(μ), then [`LaneField::MIDPOINT_SWEEPS`] fixed-point sweeps m ← μ + half·f(m).
/// A lane keeps a sweep only while the sweeps contract there (the sweep moves it by less, in
/// the 1-norm, than the previous one did; false for NaN or ∞): where half·∂f/∂μ is too large
/// for the fixed point to converge the lane stays at its last contracting iterate, and Newton
/// starts from there. The scalar step runs this with L = 1 ([`MidpointSolve`]).
#[inline(always)]
pub fn midpoint_predictor_lanes<const N: usize, const L: usize, F: LaneField<N>>(
    f: &F,
    half: f64,
    mu0: &[[f64; L]; N],
    m: &mut [[f64; L]; N],
) {
    let mut fm = [[0.0; L]; N];
    f.field_lanes(mu0, &mut fm);
    for i in 0..N {
        for l in 0..L {
            m[i][l] = mu0[i][l] + half * fm[i][l];
        }
    }
    let sweeps = F::MIDPOINT_SWEEPS;
    if sweeps == 0 {
        return;
    }
    // The 1-norm (a sum, unlike `f64::max`, propagates NaN) of the last move.
    let mut last = [0.0; L];
    for i in 0..N {
        for l in 0..L {
            last[l] += (m[i][l] - mu0[i][l]).abs();
        }
    }
    let mut go = [true; L];
    for _ in 0..sweeps {
        f.field_lanes(m, &mut fm);
        let mut next = [[0.0; L]; N];
        let mut moved = [0.0; L];
        for i in 0..N {
            for l in 0..L {
                next[i][l] = mu0[i][l] + half * fm[i][l];
                moved[l] += (next[i][l] - m[i][l]).abs();
            }
        }
        for l in 0..L {
            go[l] &= moved[l] < last[l];
        }
        last = moved;
        // Where every lane takes the sweep (the rule, not the exception), a copy: in a block of
        // two registers a coordinate (more than `LANES`) the lane-by-lane choice compiles to
        // one masked scalar move an entry (11 % of a profile's samples of the heavy top's
        // midpoint rollout); in a block of one register it is one blend, and such branches
        // cost more than they saved (in the Newton update and the step's end they took
        // Lotka–Volterra's N = 2 midpoint to 1.12–1.30× its time).
        if L > crate::isa::LANES && !go.contains(&false) {
            *m = next;
            continue;
        }
        for i in 0..N {
            for l in 0..L {
                m[i][l] = if go[l] { next[i][l] } else { m[i][l] };
            }
        }
        if !go.contains(&true) {
            break;
        }
    }
}

/// The implicit midpoint's Newton updates (I − half J(m)) δ = −r at L states at once, for a field
/// with a lane-wide Jacobian ([`LaneField::jacobian_lanes`]; returns false for one without):
/// Gaussian elimination without pivoting in every lane, kept (`solved[l]`) where the lane's
/// matrix is strictly diagonally dominant by rows (then no pivot vanishes and none is needed:
/// the Schur complements stay dominant) and δ is finite. The other lanes take the LU with
/// pivoting one by one. The scalar step of such a field runs this with L = 1
/// ([`MidpointSolve`]), so a lane's choice and bits are its scalar step's.
#[inline(always)]
pub fn midpoint_update_lanes<const N: usize, const L: usize, F: LaneField<N>>(
    f: &F,
    half: f64,
    m: &[[f64; L]; N],
    r: &[[f64; L]; N],
    delta: &mut [[f64; L]; N],
    solved: &mut [bool; L],
) -> bool {
    let mut a = [[[0.0; L]; N]; N];
    if !f.jacobian_lanes(m, &mut a) {
        return false;
    }
    for i in 0..N {
        for j in 0..N {
            let d = if i == j { 1.0 } else { 0.0 };
            for l in 0..L {
                a[i][j][l] = d - half * a[i][j][l];
            }
        }
    }
    let mut ok = [true; L];
    for i in 0..N {
        let mut off = [0.0; L];
        for j in 0..N {
            if j != i {
                for l in 0..L {
                    off[l] += a[i][j][l].abs();
                }
            }
        }
        for l in 0..L {
            // False for a NaN anywhere in the row.
            ok[l] &= a[i][i][l].abs() > off[l];
        }
    }
    let mut b = [[0.0; L]; N];
    for i in 0..N {
        for l in 0..L {
            b[i][l] = -r[i][l];
        }
    }
    let mut inv = [[0.0; L]; N];
    for k in 0..N {
        for l in 0..L {
            inv[k][l] = 1.0 / a[k][k][l];
        }
        for i in k + 1..N {
            let mut p = [0.0; L];
            for l in 0..L {
                p[l] = a[i][k][l] * inv[k][l];
            }
            for j in k + 1..N {
                for l in 0..L {
                    a[i][j][l] -= p[l] * a[k][j][l];
                }
            }
            for l in 0..L {
                b[i][l] -= p[l] * b[k][l];
            }
        }
    }
    for k in (0..N).rev() {
        let mut s = b[k];
        for j in k + 1..N {
            for l in 0..L {
                s[l] -= a[k][j][l] * delta[j][l];
            }
        }
        for l in 0..L {
            delta[k][l] = s[l] * inv[k][l];
        }
    }
    for l in 0..L {
        solved[l] = ok[l] && (0..N).all(|i| delta[i][l].is_finite());
    }
    true
}

/// The implicit midpoint's Newton update at the midpoint `m` with residual `r`: δ solving
/// (I − half ∂f/∂μ(m)) δ = −r. Every lane field has it: [`LaneField::solve_midpoint_lanes`]
/// on one lane, or where that lane needs pivoting (or the field has no lane-wide Jacobian) the
/// LU of the exact Jacobian, so the scalar step takes each lane's choice and bits. Its
/// predictor likewise is [`midpoint_predictor_lanes`] on one lane.
pub trait MidpointSolve<const N: usize> {
    /// The Newton iteration's starting point for the step from `mu0`
    /// ([`midpoint_predictor_lanes`] on one lane).
    fn midpoint_predictor(&self, half: f64, mu0: &[f64; N]) -> [f64; N];

    fn midpoint_update(
        &self,
        half: f64,
        m: &[f64; N],
        r: &[f64; N],
    ) -> Result<[f64; N], StepFailure>
    where
        Const<N>: DimMin<Const<N>, Output = Const<N>>;
}

impl<const N: usize, F: LaneField<N> + VectorField<N>> MidpointSolve<N> for F {
    #[inline(always)]
    fn midpoint_predictor(&self, half: f64, mu0: &[f64; N]) -> [f64; N] {
        let mut m = [[0.0; 1]; N];
        midpoint_predictor_lanes(self, half, &mu0.map(|v| [v]), &mut m);
        m.map(|v| v[0])
    }

    #[inline(always)]
    fn midpoint_update(
        &self,
        half: f64,
        m: &[f64; N],
        r: &[f64; N],
    ) -> Result<[f64; N], StepFailure>
    where
        Const<N>: DimMin<Const<N>, Output = Const<N>>,
    {
        let mut delta = [[0.0; 1]; N];
        let mut solved = [false];
        self.solve_midpoint_lanes(
            half,
            &m.map(|v| [v]),
            &r.map(|v| [v]),
            &mut delta,
            &mut solved,
        );
        if solved[0] {
            Ok(delta.map(|v| v[0]))
        } else {
            newton_update(SMatrix::identity() - half * self.jacobian(m), r)
        }
    }
}

/// Solves J δ = −f for a Newton update; a singular or overflowing solve is a step failure.
#[inline]
pub(crate) fn newton_update<const N: usize>(
    j: SMatrix<f64, N, N>,
    f: &[f64; N],
) -> Result<[f64; N], StepFailure>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    let d = j
        .lu()
        .solve(&SVector::<f64, N>::from_fn(|i, _| -f[i]))
        .ok_or(StepFailure::SingularJacobian)?;
    if !d.iter().all(|v| v.is_finite()) {
        return Err(StepFailure::SingularJacobian);
    }
    Ok(std::array::from_fn(|i| d[i]))
}

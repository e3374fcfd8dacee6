//! The step map every integrator implements ([`StepMap`]), what one step reports
//! ([`StepStats`], [`StepResult`]), Newton's settings ([`NewtonOptions`]) and the explicit
//! inverse its updates share ([`Inverse`]): the bottom layer that steppers, realizations and the
//! rollout all build on, so none of them needs another's module for these.

use nalgebra::{Const, DimMin, SMatrix};

use crate::error::{CoreError, StepFailure};

/// Newton settings. The defaults converge to round-off, so the Casimir is kept to round-off.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NewtonOptions {
    /// Stop once the Newton update satisfies |δ|∞ ≤ tol · max(|p|∞, 1e-300). Quadratic
    /// convergence leaves the error after that update near |δ|², far below round-off.
    pub tol: f64,
    /// Iteration cap; exceeding it is a step failure.
    pub max_iter: u32,
    /// Batched steps (large MLPs, see [`StepMap::batch`]) reuse the Jacobian of the first
    /// update (simplified Newton), refreshing it when an update shrinks by less than
    /// [`SIMPLIFIED_RATE`]: later updates need ∂S/∂p only, 4 flops per weight in reverse mode
    /// against 20 for the value, gradient and Hessian. About 1.4× faster per step on a
    /// paper-sized MLP, for one more (cheap) update per step; the result agrees with full
    /// Newton to the tolerance.
    pub simplified: bool,
}

/// Slowest contraction |δₖ| / |δₖ₋₁| simplified Newton accepts before it refreshes the Jacobian.
pub const SIMPLIFIED_RATE: f64 = 0.25;

impl Default for NewtonOptions {
    fn default() -> Self {
        NewtonOptions {
            tol: 1e-12,
            max_iter: 50,
            simplified: true,
        }
    }
}

impl NewtonOptions {
    /// Checked options, with simplified Newton on.
    pub fn validated(tol: f64, max_iter: u32) -> Result<Self, CoreError> {
        if !(tol.is_finite() && tol > 0.0 && tol < 1.0) {
            return Err(CoreError::Invalid(format!(
                "tol must lie in (0, 1), got {tol}"
            )));
        }
        if max_iter == 0 {
            return Err(CoreError::Invalid("max_iter must be at least 1".into()));
        }
        Ok(NewtonOptions {
            tol,
            max_iter,
            ..Default::default()
        })
    }
}

/// What one successful step cost and how well it solved its equation.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StepStats {
    /// Newton updates taken.
    pub iterations: u32,
    /// |tar(∂S/∂p(h,p), p) − μ|∞ at the accepted p.
    pub residual: f64,
}

/// The outcome of one step of one trajectory.
pub type StepResult = Result<StepStats, StepFailure>;

/// A map μ ↦ μ' that advances one step of size h. Implemented by every integrator so a rollout
/// is written once.
pub trait StepMap<const N: usize>: Sync {
    type Workspace: Send;
    fn workspace(&self) -> Self::Workspace;
    /// Bytes one workspace takes (the rollout makes one per thread).
    fn workspace_bytes(&self) -> usize {
        0
    }
    /// Advances `mu` in place.
    fn step(&self, h: f64, mu: &mut [f64; N], ws: &mut Self::Workspace) -> StepResult;

    /// Trajectories a rollout hands to [`StepMap::step_batch`] together (at most
    /// [`MAX_BATCH`](crate::generating::MAX_BATCH)); the chunks are fixed by position, never by
    /// the thread count.
    fn batch(&self) -> usize {
        1
    }

    /// Advances every `mu[i]` with `live[i]` by one step, writing `results[i]`; the others are
    /// left alone. The default takes them one at a time.
    fn step_batch(
        &self,
        h: f64,
        mu: &mut [[f64; N]],
        live: &[bool],
        results: &mut [StepResult],
        ws: &mut Self::Workspace,
    ) {
        step_each(self, h, mu, live, results, ws);
    }
}

/// [`StepMap::step_batch`] one trajectory at a time.
pub(crate) fn step_each<const N: usize, S: StepMap<N> + ?Sized>(
    stepper: &S,
    h: f64,
    mu: &mut [[f64; N]],
    live: &[bool],
    results: &mut [StepResult],
    ws: &mut S::Workspace,
) {
    for ((m, &l), r) in mu.iter_mut().zip(live).zip(results.iter_mut()) {
        if l {
            *r = stepper.step(h, m, ws);
        }
    }
}

/// The explicit inverse of a Newton Jacobian, kept between updates: simplified Newton reuses
/// it, and every update is a matrix–vector product instead of a triangular solve.
///
/// The Jacobians here are near the identity (I + O(h)), where δ = J⁻¹ f is as accurate as an LU
/// solve (tested against nalgebra's on random well- and ill-conditioned matrices), and a 3×3
/// cofactor inverse costs about what one LU factorisation did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Inverse<const N: usize>(pub [[f64; N]; N]);

/// The adjugate of a 3×3 matrix (its transposed cofactors) and its determinant, expanded along
/// the first row: straight-line code for one number (`f64`) or a SIMD block of lanes, the same
/// operations either way, so every 3×3 solve of the package (the bisection Newton, DMV, their
/// lanes) has one definition.
#[inline(always)]
pub fn adjugate3<T>(m: &[[T; 3]; 3]) -> ([[T; 3]; 3], T)
where
    T: Copy + std::ops::Add<Output = T> + std::ops::Sub<Output = T> + std::ops::Mul<Output = T>,
{
    let c00 = m[1][1] * m[2][2] - m[1][2] * m[2][1];
    let c01 = m[1][2] * m[2][0] - m[1][0] * m[2][2];
    let c02 = m[1][0] * m[2][1] - m[1][1] * m[2][0];
    let det = m[0][0] * c00 + m[0][1] * c01 + m[0][2] * c02;
    let adj = [
        [
            c00,
            m[0][2] * m[2][1] - m[0][1] * m[2][2],
            m[0][1] * m[1][2] - m[0][2] * m[1][1],
        ],
        [
            c01,
            m[0][0] * m[2][2] - m[0][2] * m[2][0],
            m[0][2] * m[1][0] - m[0][0] * m[1][2],
        ],
        [
            c02,
            m[0][1] * m[2][0] - m[0][0] * m[2][1],
            m[0][0] * m[1][1] - m[0][1] * m[1][0],
        ],
    ];
    (adj, det)
}

/// The inverse of a 3×3 matrix by cofactors (adjugate over the determinant); None where the
/// determinant is 0 or not finite, or an entry of the inverse is not finite.
#[inline(always)]
pub fn inverse3(m: &[[f64; 3]; 3]) -> Option<[[f64; 3]; 3]> {
    let (adj, det) = adjugate3(m);
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let r = 1.0 / det;
    let inv = adj.map(|row| row.map(|v| v * r));
    inv.iter().flatten().all(|v| v.is_finite()).then_some(inv)
}

impl<const N: usize> Inverse<N>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    /// The inverse of `j` (row-major), or [`StepFailure::SingularJacobian`] where `j` is
    /// singular or the inverse is not finite. N = 3 takes the cofactor formula, other N
    /// nalgebra's LU with partial pivoting.
    #[inline]
    pub fn new(j: &[[f64; N]; N]) -> Result<Self, StepFailure> {
        let mut out = [[0.0; N]; N];
        if N == 3 {
            let m: [[f64; 3]; 3] = std::array::from_fn(|r| std::array::from_fn(|c| j[r][c]));
            let inv = inverse3(&m).ok_or(StepFailure::SingularJacobian)?;
            for (o, i) in out.iter_mut().zip(&inv) {
                o.copy_from_slice(i);
            }
            return Ok(Inverse(out));
        }
        let inv = SMatrix::<f64, N, N>::from_fn(|r, c| j[r][c])
            .lu()
            .try_inverse()
            .ok_or(StepFailure::SingularJacobian)?;
        for (r, o) in out.iter_mut().enumerate() {
            for (c, v) in o.iter_mut().enumerate() {
                *v = inv[(r, c)];
            }
        }
        if !out.iter().flatten().all(|v| v.is_finite()) {
            return Err(StepFailure::SingularJacobian);
        }
        Ok(Inverse(out))
    }
}

impl<const N: usize> Inverse<N> {
    /// J⁻¹ f, each component summed in column order.
    #[inline(always)]
    pub fn apply(&self, f: &[f64; N]) -> [f64; N] {
        std::array::from_fn(|r| {
            let row = &self.0[r];
            let mut s = row[0] * f[0];
            for c in 1..N {
                s += row[c] * f[c];
            }
            s
        })
    }
}

//! Straight-line Lie–Poisson fields for patterns recognised from a system's data.
//!
//! [`CompiledLiePoisson`] evaluates any algebra from its nonzero structure constants, but each of
//! its terms loads its operands by run-time index, so the coordinates cannot stay in registers.
//! Two patterns are common enough to deserve code of their own, and are recognised from the
//! structure constants and the Hamiltonian's monomials, never from a name:
//!
//! | pattern | structure constants | Hamiltonian | field | flops |
//! |---|---|---|---|---|
//! | [`So3Quadratic`] | exactly ε (so(3)) | ½ Σ aᵢ μᵢ² | μ × (a∘μ) | 12 |
//! | [`Se3QuadraticLinear`] | exactly [`crate::structures::lie_groupoid::LieAlgebra::se3`] | ½ Σ aᵢ Mᵢ² + Σ bᵢ Γᵢ | Ṁ = M × Ω + Γ × b, Γ̇ = Γ × Ω, Ω = a∘M | 21 for b = 0, 25 for one bᵢ ≠ 0, 33 for several |
//!
//! Constant monomials and zero coefficients are ignored; any other monomial (a cross term, a
//! cubic, Γ², a linear term in M) or any other structure constant falls back to the compiled
//! field ([`LieField::new`]). The free rigid body and the heavy top with its centre of mass on
//! any axis match, and so does any user's system of the same form.
//!
//! **Bits.** Each kernel's scalar field is its lane code with one lane, so every lane equals the
//! scalar path bit for bit (see [`crate::lanes`]). Against [`CompiledLiePoisson`] and the dense
//! [`crate::structures::lie_poisson::LiePoisson`] a kernel differs by rounding only (tested to a few ulps of the
//! sum of the absolute terms); for one nonzero bᵢ and one monomial per aᵢ it even performs the
//! compiled field's operations.
//!
//! **A new pattern** is a struct implementing [`VectorField`] and [`LaneField`], and one arm of
//! [`LieField`].

// Index loops over lanes and coordinates read as the formulas they evaluate.
#![allow(clippy::needless_range_loop)]

use nalgebra::{Const, DimMin, SMatrix};

use crate::error::StepFailure;
use crate::lane_field::{rk4_by_lane, AtStates, LaneField, MidpointSolve};
use crate::structures::lie_poisson::{
    lie_poisson_rate, CompiledLiePoisson, Hamiltonian, LiePoisson, VectorField,
};

/// μ × (a∘μ) at L states: the rigid body's kernel (a = 1/I), 6 multiplications a lane.
/// Component i is μ_j (a_k μ_k) − μ_k (a_j μ_j) = (a_k − a_j) μ_j μ_k for (i, j, k) cyclic,
/// taken in that factored form ([`weight_differences`] once a call): 9 multiplications and 3
/// subtractions become 6 multiplications, and an RK4 step, bound by the CPU's two multiply
/// ports, takes 39 instead of 51.
#[inline(always)]
pub fn weighted_cross_lanes<const L: usize>(
    a: &[f64; 3],
    mu: &[[f64; L]; 3],
    out: &mut [[f64; L]; 3],
) {
    let d = weight_differences(a);
    for l in 0..L {
        let (m0, m1, m2) = (mu[0][l], mu[1][l], mu[2][l]);
        out[0][l] = d[0] * (m1 * m2);
        out[1][l] = d[1] * (m2 * m0);
        out[2][l] = d[2] * (m0 * m1);
    }
}

/// One RK4 step of μ × (a∘μ) at L states by lane ([`rk4_by_lane`]), on the copy `a` (read
/// through a field's `self`, the constants would be loaded again in every lane): the by-lane RK4
/// of the rigid body's field and of [`So3Quadratic`].
#[inline(always)]
pub(crate) fn weighted_cross_rk4_by_lane<const L: usize>(
    a: [f64; 3],
    h: f64,
    mu: &mut [[f64; L]; 3],
) {
    let f =
        AtStates::<1, _>(|y: &[[f64; 1]; 3], o: &mut [[f64; 1]; 3]| weighted_cross_lanes(&a, y, o));
    rk4_by_lane(&f, h, mu);
}

/// (a₂ − a₁, a₀ − a₂, a₁ − a₀): the factors of μ × (a∘μ) ([`weighted_cross_lanes`]).
#[inline(always)]
pub fn weight_differences(a: &[f64; 3]) -> [f64; 3] {
    [a[2] - a[1], a[0] - a[2], a[1] - a[0]]
}

/// The matrix of v ↦ x × v, row-major.
#[inline(always)]
fn hat(x: &[f64; 3]) -> [[f64; 3]; 3] {
    [[0.0, -x[2], x[1]], [x[2], 0.0, -x[0]], [-x[1], x[0], 0.0]]
}

/// so(3)* with H = ½ Σ aᵢ μᵢ² (any real aᵢ): μ̇ = μ × (a∘μ).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct So3Quadratic {
    /// aᵢ = ∂²H/∂μᵢ².
    pub a: [f64; 3],
}

impl So3Quadratic {
    /// ∂f/∂μ = `[μ]× diag(a) − [a∘μ]×`, row-major.
    #[inline(always)]
    pub fn jacobian_array(&self, mu: &[f64; 3]) -> [[f64; 3]; 3] {
        let w = [mu[0] * self.a[0], mu[1] * self.a[1], mu[2] * self.a[2]];
        let (hm, hw) = (hat(mu), hat(&w));
        std::array::from_fn(|r| std::array::from_fn(|c| hm[r][c] * self.a[c] - hw[r][c]))
    }
}

/// The midpoint's fixed-point sweeps for μ × (a∘μ) ([`LaneField::MIDPOINT_SWEEPS`]): a sweep
/// (9 flops) costs a small fraction of a Newton update, and on the rigid body at h = 0.1 two
/// bring the Euler midpoint close enough for 2 updates, not 3.
pub(crate) const SO3_MIDPOINT_SWEEPS: u32 = 2;

impl LaneField<3> for So3Quadratic {
    /// As the rigid body's (the same kernel): RK4 in blocks of 16 took 0.55× the time of
    /// blocks of 8.
    const AVX512_PAIRED: bool = true;

    /// By lane, as the rigid body's ([`crate::classical::RigidBody`]'s `LaneField`): the
    /// lane-inner block compiled well in `cargo build` and badly in the wheel's cdylib-only
    /// build while the profile had thin LTO (docs/performance.md).
    const AVX512_BY_LANE: bool = true;

    #[inline(always)]
    fn rk4_step_by_lane<const L: usize>(&self, h: f64, mu: &mut [[f64; L]; 3]) {
        weighted_cross_rk4_by_lane(self.a, h, mu);
    }

    #[inline(always)]
    fn field_lanes<const L: usize>(&self, mu: &[[f64; L]; 3], out: &mut [[f64; L]; 3]) {
        weighted_cross_lanes(&self.a, mu, out);
    }

    const MIDPOINT_SWEEPS: u32 = SO3_MIDPOINT_SWEEPS;

    #[inline(always)]
    fn jacobian_lanes<const L: usize>(
        &self,
        mu: &[[f64; L]; 3],
        out: &mut [[[f64; L]; 3]; 3],
    ) -> bool {
        jacobian_lanes_by(mu, out, |m| self.jacobian_array(m))
    }
}

/// The Jacobian `jac` of each lane's state, stored lane-wise (`out[r][c][l]`).
#[inline(always)]
pub(crate) fn jacobian_lanes_by<const N: usize, const L: usize>(
    mu: &[[f64; L]; N],
    out: &mut [[[f64; L]; N]; N],
    jac: impl Fn(&[f64; N]) -> [[f64; N]; N],
) -> bool {
    for l in 0..L {
        let j = jac(&std::array::from_fn(|i| mu[i][l]));
        for r in 0..N {
            for c in 0..N {
                out[r][c][l] = j[r][c];
            }
        }
    }
    true
}

/// A lane field evaluated at one state: its lane code with one lane, so the scalar path and
/// every lane agree bit for bit.
#[inline(always)]
fn one_lane_field<const N: usize, F: LaneField<N>>(f: &F, mu: &[f64; N]) -> [f64; N] {
    let mut out = [[0.0; 1]; N];
    f.field_lanes(&mu.map(|v| [v]), &mut out);
    out.map(|v| v[0])
}

/// A row-major array as an nalgebra matrix.
#[inline(always)]
fn matrix<const N: usize>(j: &[[f64; N]; N]) -> SMatrix<f64, N, N> {
    SMatrix::from_fn(|r, c| j[r][c])
}

impl VectorField<3> for So3Quadratic {
    /// The lane code with one lane (the same bits).
    #[inline]
    fn field(&self, mu: &[f64; 3]) -> [f64; 3] {
        one_lane_field(self, mu)
    }

    #[inline]
    fn jacobian(&self, mu: &[f64; 3]) -> SMatrix<f64, 3, 3> {
        matrix(&self.jacobian_array(mu))
    }

    /// A = `−[ω]×`, ω = a∘μ (see [`lie_poisson_rate`]).
    fn step_rate(&self, mu: &[f64; 3]) -> f64 {
        let w = [mu[0] * self.a[0], mu[1] * self.a[1], mu[2] * self.a[2]];
        let a = hat(&w).map(|row| row.map(|v| -v));
        lie_poisson_rate(&a, self.jacobian(mu).norm())
    }
}

/// The linear part b of the Hamiltonian, stored by its nonzero components so that the field
/// skips the zero ones: Γ × b costs 4 flops for one axis, 9 in general.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Torque {
    /// b = 0: Γ is carried along by the rotation only.
    Zero,
    /// b = (b₀, 0, 0).
    X(f64),
    /// b = (0, b₁, 0).
    Y(f64),
    /// b = (0, 0, b₂).
    Z(f64),
    /// Two or three bᵢ ≠ 0.
    General([f64; 3]),
}

impl Torque {
    /// The pattern of b.
    pub fn new(b: [f64; 3]) -> Self {
        match b.map(|v| v != 0.0) {
            [false, false, false] => Torque::Zero,
            [true, false, false] => Torque::X(b[0]),
            [false, true, false] => Torque::Y(b[1]),
            [false, false, true] => Torque::Z(b[2]),
            _ => Torque::General(b),
        }
    }

    /// b as a vector.
    pub fn vector(&self) -> [f64; 3] {
        match *self {
            Torque::Zero => [0.0; 3],
            Torque::X(b) => [b, 0.0, 0.0],
            Torque::Y(b) => [0.0, b, 0.0],
            Torque::Z(b) => [0.0, 0.0, b],
            Torque::General(b) => b,
        }
    }
}

/// Evaluates `$body` with `$t` bound to the closure (g, d) ↦ d += g × b for the torque's
/// pattern: one arm per pattern, so that each is its own straight-line code with b's zeros
/// skipped (x · 0 cannot be folded away: it is NaN for x = ∞).
macro_rules! with_torque {
    ($torque:expr, $t:ident => $body:expr) => {
        match $torque {
            Torque::Zero => {
                let $t = |_: [f64; 3], _: &mut [f64; 3]| {};
                $body
            }
            // g × b e₀ = (0, g₂ b, −g₁ b).
            Torque::X(b) => {
                let $t = |g: [f64; 3], d: &mut [f64; 3]| {
                    d[1] += g[2] * b;
                    d[2] -= g[1] * b;
                };
                $body
            }
            // g × b e₁ = (−g₂ b, 0, g₀ b).
            Torque::Y(b) => {
                let $t = |g: [f64; 3], d: &mut [f64; 3]| {
                    d[0] -= g[2] * b;
                    d[2] += g[0] * b;
                };
                $body
            }
            // g × b e₂ = (g₁ b, −g₀ b, 0).
            Torque::Z(b) => {
                let $t = |g: [f64; 3], d: &mut [f64; 3]| {
                    d[0] += g[1] * b;
                    d[1] -= g[0] * b;
                };
                $body
            }
            Torque::General(b) => {
                let $t = |g: [f64; 3], d: &mut [f64; 3]| {
                    d[0] += g[1] * b[2] - g[2] * b[1];
                    d[1] += g[2] * b[0] - g[0] * b[2];
                    d[2] += g[0] * b[1] - g[1] * b[0];
                };
                $body
            }
        }
    };
}

/// se(3)* = (M, Γ) with H = ½ Σ aᵢ Mᵢ² + Σ bᵢ Γᵢ (any real aᵢ, bᵢ): the heavy top and any
/// system of its form. Ṁ = M × Ω + Γ × b, Γ̇ = Γ × Ω, Ω = a∘M.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Se3QuadraticLinear {
    /// aᵢ = ∂²H/∂Mᵢ².
    pub a: [f64; 3],
    /// bᵢ = ∂H/∂Γᵢ (for the heavy top mgl χ).
    pub torque: Torque,
}

/// The se(3) field at L states, with Γ × b added by `torque(Γ, Ṁ)` (a closure per pattern of b,
/// so each pattern is its own straight-line loop).
#[inline(always)]
fn se3_lanes<const L: usize>(
    a: &[f64; 3],
    mu: &[[f64; L]; 6],
    out: &mut [[f64; L]; 6],
    torque: impl Fn([f64; 3], &mut [f64; 3]),
) {
    for l in 0..L {
        let (m0, m1, m2) = (mu[0][l], mu[1][l], mu[2][l]);
        let (g0, g1, g2) = (mu[3][l], mu[4][l], mu[5][l]);
        let (w0, w1, w2) = (m0 * a[0], m1 * a[1], m2 * a[2]);
        let mut d = [m1 * w2 - m2 * w1, m2 * w0 - m0 * w2, m0 * w1 - m1 * w0];
        torque([g0, g1, g2], &mut d);
        out[0][l] = d[0];
        out[1][l] = d[1];
        out[2][l] = d[2];
        out[3][l] = g1 * w2 - g2 * w1;
        out[4][l] = g2 * w0 - g0 * w2;
        out[5][l] = g0 * w1 - g1 * w0;
    }
}

impl LaneField<6> for Se3QuadraticLinear {
    #[inline(always)]
    fn field_lanes<const L: usize>(&self, mu: &[[f64; L]; 6], out: &mut [[f64; L]; 6]) {
        with_torque!(self.torque, t => se3_lanes(&self.a, mu, out, t))
    }

    /// Straight-line for each pattern of b (measured: the heavy top's RK4 at 0.30× its time in
    /// AVX2 blocks, where lane-inner AVX-512 took 3.7×).
    const AVX512_BY_LANE: bool = true;

    /// The torque's pattern matched once, outside the loop over lanes (a branch inside keeps
    /// it scalar).
    #[inline(always)]
    fn rk4_step_by_lane<const L: usize>(&self, h: f64, mu: &mut [[f64; L]; 6]) {
        let a = self.a;
        with_torque!(self.torque, t => {
            let f = AtStates::<1, _>(|y: &[[f64; 1]; 6], o: &mut [[f64; 1]; 6]| se3_lanes(&a, y, o, t));
            rk4_by_lane(&f, h, mu);
        })
    }

    /// Four sweeps: a field evaluation (about 30 flops) costs a fraction of a Newton update, and
    /// on the heavy top at h = 0.1 they bring every bench state's Euler midpoint close enough
    /// for 2 updates, not 3 (two sweeps leave a block's slowest lane at 3, six start to reach 1
    /// in some lanes only: both cost more).
    const MIDPOINT_SWEEPS: u32 = 4;

    /// By the blocks of the Jacobian ([`se3_midpoint_lanes`]), not the dense elimination.
    #[inline(always)]
    fn solve_midpoint_lanes<const L: usize>(
        &self,
        half: f64,
        m: &[[f64; L]; 6],
        r: &[[f64; L]; 6],
        delta: &mut [[f64; L]; 6],
        solved: &mut [bool; L],
    ) -> bool {
        with_torque!(self.torque, t => se3_midpoint_lanes(&self.a, half, m, r, delta, solved, t));
        true
    }

    /// [`Se3QuadraticLinear::jacobian_array`] entry by entry, each a loop over the lanes (its
    /// zeros and the constant block `−[b]×` stored as such).
    #[inline(always)]
    fn jacobian_lanes<const L: usize>(
        &self,
        mu: &[[f64; L]; 6],
        out: &mut [[[f64; L]; 6]; 6],
    ) -> bool {
        let [a0, a1, a2] = self.a;
        let b = self.torque.vector();
        for l in 0..L {
            let (m0, m1, m2) = (mu[0][l], mu[1][l], mu[2][l]);
            let (g0, g1, g2) = (mu[3][l], mu[4][l], mu[5][l]);
            let (w0, w1, w2) = (m0 * a0, m1 * a1, m2 * a2);
            // [M]× diag(a) − [Ω]×.
            out[0][0][l] = 0.0;
            out[0][1][l] = w2 - m2 * a1;
            out[0][2][l] = m1 * a2 - w1;
            out[1][0][l] = m2 * a0 - w2;
            out[1][1][l] = 0.0;
            out[1][2][l] = w0 - m0 * a2;
            out[2][0][l] = w1 - m1 * a0;
            out[2][1][l] = m0 * a1 - w0;
            out[2][2][l] = 0.0;
            // −[b]×.
            out[0][3][l] = 0.0;
            out[0][4][l] = b[2];
            out[0][5][l] = -b[1];
            out[1][3][l] = -b[2];
            out[1][4][l] = 0.0;
            out[1][5][l] = b[0];
            out[2][3][l] = b[1];
            out[2][4][l] = -b[0];
            out[2][5][l] = 0.0;
            // [Γ]× diag(a).
            out[3][0][l] = 0.0;
            out[3][1][l] = -g2 * a1;
            out[3][2][l] = g1 * a2;
            out[4][0][l] = g2 * a0;
            out[4][1][l] = 0.0;
            out[4][2][l] = -g0 * a2;
            out[5][0][l] = -g1 * a0;
            out[5][1][l] = g0 * a1;
            out[5][2][l] = 0.0;
            // −[Ω]×.
            out[3][3][l] = 0.0;
            out[3][4][l] = w2;
            out[3][5][l] = -w1;
            out[4][3][l] = -w2;
            out[4][4][l] = 0.0;
            out[4][5][l] = w0;
            out[5][3][l] = w1;
            out[5][4][l] = -w0;
            out[5][5][l] = 0.0;
        }
        true
    }
}

/// The midpoint's Newton update (I − s J) δ = −r (s = `half`) of the se(3) field at L states,
/// by the blocks of J = `[[ [M]× diag(a) − [Ω]×, −[b]× ], [ [Γ]× diag(a), −[Ω]× ]]`, with the
/// torque's cross product `torque` ((g, d) ↦ d += g × b, as in [`se3_lanes`]).
///
/// Writing δ = (x, y) and −r = (p, q): the lower-right block A₂₂ = I + s[Ω]× is normal with
/// eigenvalues 1 and 1 ± i s|Ω|, so it is always invertible and ‖A₂₂⁻¹‖₂ ≤ 1 (eliminating y
/// first never amplifies anything), with the closed form A₂₂⁻¹ = P̃ / (1 + |u|²),
/// P̃ = I − [u]× + u uᵀ, u = sΩ. What remains for x is the 3 × 3 Schur complement
/// S = I − s J₁₁ + s² [b]× A₂₂⁻¹ [Γ]× diag(a) with right side p' = p − s b × A₂₂⁻¹ q, solved by
/// elimination without pivoting; then y = A₂₂⁻¹ (q + s Γ × (a∘x)). A lane is kept
/// (`solved[l]`) where S is strictly diagonally dominant by rows (then no pivot vanishes and
/// none is needed) and δ is finite; the others are left to the pivoted LU of the full 6 × 6.
/// About 150 flops and 4 divisions a lane, against some 300 and 6 for the dense elimination.
#[inline(always)]
fn se3_midpoint_lanes<const L: usize>(
    a: &[f64; 3],
    half: f64,
    mu: &[[f64; L]; 6],
    r: &[[f64; L]; 6],
    delta: &mut [[f64; L]; 6],
    solved: &mut [bool; L],
    torque: impl Fn([f64; 3], &mut [f64; 3]),
) {
    let s = half;
    let ss = s * s;
    for l in 0..L {
        let (m0, m1, m2) = (mu[0][l], mu[1][l], mu[2][l]);
        let g = [mu[3][l], mu[4][l], mu[5][l]];
        let (w0, w1, w2) = (m0 * a[0], m1 * a[1], m2 * a[2]);
        // I − s J₁₁, J₁₁ = [M]× diag(a) − [Ω]× (its diagonal is zero).
        let mut sc = [
            [1.0, -(s * (w2 - m2 * a[1])), -(s * (m1 * a[2] - w1))],
            [-(s * (m2 * a[0] - w2)), 1.0, -(s * (w0 - m0 * a[2]))],
            [-(s * (w1 - m1 * a[0])), -(s * (m0 * a[1] - w0)), 1.0],
        ];
        // A₂₂⁻¹ = inv · P̃, by rows.
        let u = [s * w0, s * w1, s * w2];
        let inv = 1.0 / (1.0 + (u[0] * u[0] + u[1] * u[1] + u[2] * u[2]));
        let pt = [
            [1.0 + u[0] * u[0], u[2] + u[0] * u[1], u[0] * u[2] - u[1]],
            [u[1] * u[0] - u[2], 1.0 + u[1] * u[1], u[0] + u[1] * u[2]],
            [u[1] + u[2] * u[0], u[2] * u[1] - u[0], 1.0 + u[2] * u[2]],
        ];
        // Row k of P̃ [Γ]× diag(a) is (P̃ₖ × Γ)∘a; [b]× of it, column by column, is b × column
        // = −(column × b): the torque's closure on the column scaled by −s² inv (the rows the
        // torque does not touch are never computed).
        let mut c = [[0.0; 3]; 3];
        for k in 0..3 {
            let p = &pt[k];
            c[k] = [
                (p[1] * g[2] - p[2] * g[1]) * a[0],
                (p[2] * g[0] - p[0] * g[2]) * a[1],
                (p[0] * g[1] - p[1] * g[0]) * a[2],
            ];
        }
        let k = -ss * inv;
        for j in 0..3 {
            let mut col = [sc[0][j], sc[1][j], sc[2][j]];
            torque([k * c[0][j], k * c[1][j], k * c[2][j]], &mut col);
            for i in 0..3 {
                sc[i][j] = col[i];
            }
        }
        let q = [-r[3][l], -r[4][l], -r[5][l]];
        let pq = [
            pt[0][0] * q[0] + pt[0][1] * q[1] + pt[0][2] * q[2],
            pt[1][0] * q[0] + pt[1][1] * q[1] + pt[1][2] * q[2],
            pt[2][0] * q[0] + pt[2][1] * q[1] + pt[2][2] * q[2],
        ];
        // p' = p − s b × A₂₂⁻¹ q = p + (s inv P̃ q) × b.
        let mut p = [-r[0][l], -r[1][l], -r[2][l]];
        let si = s * inv;
        torque([si * pq[0], si * pq[1], si * pq[2]], &mut p);
        // Strict diagonal dominance by rows (false for a NaN anywhere in a row).
        let ok = (sc[0][0].abs() > sc[0][1].abs() + sc[0][2].abs())
            & (sc[1][1].abs() > sc[1][0].abs() + sc[1][2].abs())
            & (sc[2][2].abs() > sc[2][0].abs() + sc[2][1].abs());
        // Elimination without pivoting, then back substitution.
        let i0 = 1.0 / sc[0][0];
        let (f1, f2) = (sc[1][0] * i0, sc[2][0] * i0);
        let (s11, s12, p1) = (
            sc[1][1] - f1 * sc[0][1],
            sc[1][2] - f1 * sc[0][2],
            p[1] - f1 * p[0],
        );
        let (s21, s22, p2) = (
            sc[2][1] - f2 * sc[0][1],
            sc[2][2] - f2 * sc[0][2],
            p[2] - f2 * p[0],
        );
        let i1 = 1.0 / s11;
        let f = s21 * i1;
        let x2 = (p2 - f * p1) / (s22 - f * s12);
        let x1 = (p1 - s12 * x2) * i1;
        let x0 = (p[0] - sc[0][1] * x1 - sc[0][2] * x2) * i0;
        // y = A₂₂⁻¹ (q + s Γ × (a∘x)).
        let (v0, v1, v2) = (x0 * a[0], x1 * a[1], x2 * a[2]);
        let z = [
            q[0] + s * (g[1] * v2 - g[2] * v1),
            q[1] + s * (g[2] * v0 - g[0] * v2),
            q[2] + s * (g[0] * v1 - g[1] * v0),
        ];
        let d = [
            x0,
            x1,
            x2,
            (pt[0][0] * z[0] + pt[0][1] * z[1] + pt[0][2] * z[2]) * inv,
            (pt[1][0] * z[0] + pt[1][1] * z[1] + pt[1][2] * z[2]) * inv,
            (pt[2][0] * z[0] + pt[2][1] * z[1] + pt[2][2] * z[2]) * inv,
        ];
        let mut finite = true;
        for i in 0..6 {
            delta[i][l] = d[i];
            finite &= d[i].is_finite();
        }
        solved[l] = ok && finite;
    }
}

impl Se3QuadraticLinear {
    /// ∂f/∂μ as a row-major array: `[[ [M]× diag(a) − [Ω]×, −[b]× ], [ [Γ]× diag(a), −[Ω]× ]]`.
    #[inline(always)]
    pub fn jacobian_array(&self, mu: &[f64; 6]) -> [[f64; 6]; 6] {
        let a = &self.a;
        let m = [mu[0], mu[1], mu[2]];
        let g = [mu[3], mu[4], mu[5]];
        let w = [m[0] * a[0], m[1] * a[1], m[2] * a[2]];
        let (hm, hg, hw, hb) = (hat(&m), hat(&g), hat(&w), hat(&self.torque.vector()));
        let mut j = [[0.0; 6]; 6];
        for r in 0..3 {
            for c in 0..3 {
                j[r][c] = hm[r][c] * a[c] - hw[r][c];
                j[r][3 + c] = -hb[r][c];
                j[3 + r][c] = hg[r][c] * a[c];
                j[3 + r][3 + c] = -hw[r][c];
            }
        }
        j
    }
}

impl VectorField<6> for Se3QuadraticLinear {
    /// The lane code with one lane (the same bits).
    #[inline]
    fn field(&self, mu: &[f64; 6]) -> [f64; 6] {
        one_lane_field(self, mu)
    }

    #[inline]
    fn jacobian(&self, mu: &[f64; 6]) -> SMatrix<f64, 6, 6> {
        matrix(&self.jacobian_array(mu))
    }

    /// A = ad_{∇H}ᵀ = `[[−[Ω]×, −[b]×], [0, −[Ω]×]]` (see [`lie_poisson_rate`]).
    fn step_rate(&self, mu: &[f64; 6]) -> f64 {
        let w = [mu[0] * self.a[0], mu[1] * self.a[1], mu[2] * self.a[2]];
        let (hw, hb) = (hat(&w), hat(&self.torque.vector()));
        let mut a = [[0.0; 6]; 6];
        for r in 0..3 {
            for c in 0..3 {
                a[r][c] = -hw[r][c];
                a[r][3 + c] = -hb[r][c];
                a[3 + r][3 + c] = -hw[r][c];
            }
        }
        lie_poisson_rate(&a, self.jacobian(mu).norm())
    }
}

/// The field a classical Lie–Poisson stepper evaluates: a recognised pattern's straight-line
/// kernel where the system matches one, else the system compiled to its sparsity.
///
/// It is deliberately not a [`LaneField`]: a match on the variant inside every field evaluation
/// cost the heavy top's RK4 lanes about 40 % (the kernels stop being one straight-line loop), so
/// [`crate::lanes`] steps `Rk4<LieField>` and `ImplicitMidpoint<LieField>` by matching once a
/// step and running the variant's own monomorphised stepper.
#[derive(Clone, Debug, PartialEq)]
pub enum LieField<const N: usize> {
    Compiled(CompiledLiePoisson<N>),
    /// Only for N = 3.
    So3(So3Quadratic),
    /// Only for N = 6.
    Se3(Se3QuadraticLinear),
}

/// The diagonal-quadratic and linear parts of H: `Some((a, b))` when every monomial with a
/// nonzero coefficient is a constant, a square μᵢ² with i < `squares`, or a single μᵢ with
/// i ≥ `squares`; aᵢ = 2 Σ c over the μᵢ² monomials, bᵢ = Σ c over the μᵢ ones.
fn quadratic_linear<const N: usize>(
    h: &Hamiltonian<N>,
    squares: usize,
) -> Option<([f64; N], [f64; N])> {
    let (mut sq, mut b) = ([0.0; N], [0.0; N]);
    for (e, c) in h.terms() {
        if *c == 0.0 || e.iter().all(|&k| k == 0) {
            continue;
        }
        let mut nonzero = e.iter().enumerate().filter(|(_, &k)| k > 0);
        let (i, &k) = nonzero.next()?;
        if nonzero.next().is_some() {
            return None;
        }
        match (i < squares, k) {
            (true, 2) => sq[i] += c,
            (false, 1) => b[i] += c,
            _ => return None,
        }
    }
    Some((sq.map(|s| 2.0 * s), b))
}

impl<const N: usize> LieField<N> {
    /// The straight-line kernel of the pattern `system` matches, or its compiled field.
    pub fn new(system: &LiePoisson<N>) -> Self {
        Self::recognise(system).unwrap_or_else(|| LieField::Compiled(system.compile()))
    }

    fn recognise(system: &LiePoisson<N>) -> Option<Self> {
        if N == 3 && system.algebra.is_so3() {
            let (a, _) = quadratic_linear(&system.hamiltonian, 3)?;
            return Some(LieField::So3(So3Quadratic {
                a: [a[0], a[1], a[2]],
            }));
        }
        if N == 6 && system.algebra.is_se3() {
            let (a, b) = quadratic_linear(&system.hamiltonian, 3)?;
            return Some(LieField::Se3(Se3QuadraticLinear {
                a: [a[0], a[1], a[2]],
                torque: Torque::new([b[3], b[4], b[5]]),
            }));
        }
        None
    }

    /// The name of the kernel in use (for benches and diagnostics).
    pub fn kernel_name(&self) -> &'static str {
        match self {
            LieField::Compiled(_) => "compiled",
            LieField::So3(_) => "so3-quadratic",
            LieField::Se3(_) => "se3-quadratic-linear",
        }
    }
}

/// `x` as an array of length M (the pattern's dimension; the variants are built only for it).
#[inline(always)]
pub(crate) fn sized<T, const N: usize, const M: usize>(x: &[T; N]) -> Option<&[T; M]> {
    <&[T; M]>::try_from(&x[..]).ok()
}

#[inline(always)]
pub(crate) fn sized_mut<T, const N: usize, const M: usize>(x: &mut [T; N]) -> Option<&mut [T; M]> {
    <&mut [T; M]>::try_from(&mut x[..]).ok()
}

/// A pattern kernel's N-vector evaluated as its M-vector (N = M by construction; NaN otherwise).
#[inline(always)]
fn via<const N: usize, const M: usize>(
    mu: &[f64; N],
    f: impl Fn(&[f64; M]) -> [f64; M],
) -> [f64; N] {
    let mut out = [f64::NAN; N];
    if let (Some(m), Some(o)) = (sized::<_, N, M>(mu), sized_mut::<_, N, M>(&mut out)) {
        *o = f(m);
    }
    out
}

impl<const N: usize> VectorField<N> for LieField<N> {
    #[inline]
    fn field(&self, mu: &[f64; N]) -> [f64; N] {
        match self {
            LieField::Compiled(f) => f.field(mu),
            LieField::So3(f) => via::<N, 3>(mu, |m| f.field(m)),
            LieField::Se3(f) => via::<N, 6>(mu, |m| f.field(m)),
        }
    }

    fn jacobian(&self, mu: &[f64; N]) -> SMatrix<f64, N, N> {
        let copy = |j: &[[f64; N]; N]| SMatrix::from_fn(|r, c| j[r][c]);
        match self {
            LieField::Compiled(f) => f.jacobian(mu),
            LieField::So3(f) => match sized::<_, N, 3>(mu) {
                Some(m) => {
                    let j = f.jacobian(m);
                    SMatrix::from_fn(|r, c| if r < 3 && c < 3 { j[(r, c)] } else { f64::NAN })
                }
                None => copy(&[[f64::NAN; N]; N]),
            },
            LieField::Se3(f) => match sized::<_, N, 6>(mu) {
                Some(m) => {
                    let j = f.jacobian_array(m);
                    SMatrix::from_fn(|r, c| if r < 6 && c < 6 { j[r][c] } else { f64::NAN })
                }
                None => copy(&[[f64::NAN; N]; N]),
            },
        }
    }

    fn step_rate(&self, mu: &[f64; N]) -> f64 {
        match self {
            LieField::Compiled(f) => f.step_rate(mu),
            LieField::So3(f) => sized::<_, N, 3>(mu).map_or(f64::NAN, |m| f.step_rate(m)),
            LieField::Se3(f) => sized::<_, N, 6>(mu).map_or(f64::NAN, |m| f.step_rate(m)),
        }
    }
}

/// The variant's own midpoint solve ([`LieField`] is matched here, not inside the solve).
impl<const N: usize> MidpointSolve<N> for LieField<N> {
    /// The variant's own predictor, as its lanes run it.
    fn midpoint_predictor(&self, half: f64, mu0: &[f64; N]) -> [f64; N] {
        match self {
            LieField::Compiled(f) => f.midpoint_predictor(half, mu0),
            LieField::So3(f) => via::<N, 3>(mu0, |m| f.midpoint_predictor(half, m)),
            LieField::Se3(f) => via::<N, 6>(mu0, |m| f.midpoint_predictor(half, m)),
        }
    }

    /// The variant's own update, as its lanes solve.
    fn midpoint_update(
        &self,
        half: f64,
        m: &[f64; N],
        r: &[f64; N],
    ) -> Result<[f64; N], StepFailure>
    where
        Const<N>: DimMin<Const<N>, Output = Const<N>>,
    {
        // Unreachable mismatches (a variant is built for its own dimension) fail the step.
        let wrong = Err(StepFailure::NonFinite);
        match self {
            LieField::Compiled(f) => f.midpoint_update(half, m, r),
            LieField::So3(f) => match (sized::<_, N, 3>(m), sized::<_, N, 3>(r)) {
                (Some(m), Some(r)) => MidpointSolve::<3>::midpoint_update(f, half, m, r)
                    .and_then(|d| sized::<_, 3, N>(&d).copied().ok_or(StepFailure::NonFinite)),
                _ => wrong,
            },
            LieField::Se3(f) => match (sized::<_, N, 6>(m), sized::<_, N, 6>(r)) {
                (Some(m), Some(r)) => MidpointSolve::<6>::midpoint_update(f, half, m, r)
                    .and_then(|d| sized::<_, 6, N>(&d).copied().ok_or(StepFailure::NonFinite)),
                _ => wrong,
            },
        }
    }
}

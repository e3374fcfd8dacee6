//! The free rigid body on so(3)*: its field, its splittings, discrete Moser–Veselov, and the
//! methods by name ([`ClassicalMethod`]).

use nalgebra::Matrix3;

use super::{by_name, explicit_result, max_abs, ImplicitMidpoint, Rk4};
use crate::error::{CoreError, StepFailure};
use crate::rollout::{rollout, TrajectoryInfo};
use crate::step::{NewtonOptions, StepMap, StepStats};
use crate::structures::lie_poisson::VectorField;
use crate::trig;

/// A free rigid body: principal moments of inertia I (any order, all finite and > 0).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RigidBody {
    pub(super) inertia: [f64; 3],
    pub(super) inv: [f64; 3],
}

impl RigidBody {
    pub fn new(inertia: [f64; 3]) -> Result<Self, CoreError> {
        if !inertia.iter().all(|&v| v.is_finite() && v > 0.0) {
            return Err(CoreError::Invalid(format!(
                "inertia must be 3 finite numbers > 0, got {inertia:?}"
            )));
        }
        Ok(RigidBody {
            inertia,
            inv: inertia.map(|v| 1.0 / v),
        })
    }

    pub fn inertia(&self) -> [f64; 3] {
        self.inertia
    }

    /// 1/Iᵢ, the factors of ω = μ/I.
    #[inline(always)]
    pub fn inverse_inertia(&self) -> [f64; 3] {
        self.inv
    }

    /// The body as the straight-line so(3) kernel with H = ½ Σ aᵢ μᵢ², a = 1/I.
    #[inline(always)]
    pub fn pattern(&self) -> crate::straight_line::So3Quadratic {
        crate::straight_line::So3Quadratic { a: self.inv }
    }

    /// H(μ) = ½ Σ μᵢ²/Iᵢ.
    pub fn hamiltonian(&self, mu: &[f64; 3]) -> f64 {
        0.5 * (0..3).map(|i| mu[i] * mu[i] * self.inv[i]).sum::<f64>()
    }

    /// Angular velocity ω = ∇H(μ) = μ/I.
    #[inline]
    pub fn velocity(&self, mu: &[f64; 3]) -> [f64; 3] {
        [
            mu[0] * self.inv[0],
            mu[1] * self.inv[1],
            mu[2] * self.inv[2],
        ]
    }

    /// Euler's equations μ̇ = μ × (μ/I), as (1/I_k − 1/I_j) μ_j μ_k for (i, j, k) cyclic: the
    /// lane kernel's operations ([`crate::straight_line::weighted_cross_lanes`]), so a scalar
    /// step and every lane agree bit for bit.
    #[inline]
    pub fn vector_field(&self, mu: &[f64; 3]) -> [f64; 3] {
        let d = crate::straight_line::weight_differences(&self.inv);
        [
            d[0] * (mu[1] * mu[2]),
            d[1] * (mu[2] * mu[0]),
            d[2] * (mu[0] * mu[1]),
        ]
    }

    /// Exact flow for time t of Hᵢ = μᵢ²/(2Iᵢ), in place.
    ///
    /// μ̇ = μ × ∇Hᵢ = ωᵢ μ × eᵢ with ωᵢ = μᵢ/Iᵢ constant, so for (i, a, b) cyclic
    /// μ̇_a = ωᵢ μ_b, μ̇_b = −ωᵢ μ_a: a rotation about eᵢ by the angle −t ωᵢ.
    #[inline]
    pub fn axis_flow(&self, i: usize, t: f64, mu: &mut [f64; 3]) {
        rotate_about(i, t * mu[i] * self.inv[i], mu);
    }
}

/// Turns the 3-vector `v` about eᵢ by the angle −`angle`: for (i, a, b) cyclic,
/// v_a ← cos·v_a + sin·v_b, v_b ← cos·v_b − sin·v_a. Every splitting's axis flow is this
/// rotation, with its own angle. sin and cos come from [`trig::sin_cos`], the branch-free
/// form that the SIMD lanes ([`crate::lanes_splitting`]) evaluate too, so a lane equals this
/// step bit for bit.
#[inline]
fn rotate_about(i: usize, angle: f64, v: &mut [f64]) {
    rotate_about_by(i, trig::sin_cos(angle), v);
}

/// [`rotate_about`] with (sin, cos) of the angle given.
#[inline]
pub(super) fn rotate_about_by(i: usize, (s, c): (f64, f64), v: &mut [f64]) {
    let (a, b) = ((i + 1) % 3, (i + 2) % 3);
    let (x, y) = (v[a], v[b]);
    v[a] = c * x + s * y;
    v[b] = c * y - s * x;
}

#[inline]
pub(super) fn cross(a: &[f64; 3], b: &[f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

impl VectorField<3> for RigidBody {
    #[inline]
    fn field(&self, mu: &[f64; 3]) -> [f64; 3] {
        self.vector_field(mu)
    }

    /// d/dμ [μ × (μ/I)] = [μ]× diag(1/I) − [μ/I]×, as the so(3) pattern kernel computes it
    /// (the same bits as its lanes).
    #[inline]
    fn jacobian(&self, mu: &[f64; 3]) -> Matrix3<f64> {
        self.pattern().jacobian(mu)
    }

    /// max(|ω|, ‖J‖_F): ‖ad_ω‖₂ = |ω| in closed form (see [`crate::structures::lie_poisson::lie_poisson_rate`]).
    fn step_rate(&self, mu: &[f64; 3]) -> f64 {
        let w = self.velocity(mu);
        let rotation = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt();
        rotation.max(self.jacobian(mu).norm())
    }
}

/// McLachlan's explicit Lie–Poisson splitting H = H₁ + H₂ + H₃, Hᵢ = μᵢ²/(2Iᵢ), composed of
/// N Strang steps S(τ) = H₁(τ/2) H₂(τ/2) H₃(τ) H₂(τ/2) H₁(τ/2) with τ = γⱼ h.
///
/// Each sub-flow is an exact rotation ([`RigidBody::axis_flow`]), so C is kept to round-off.
/// The H₁ half-flows that meet between stages are merged (flows of one Hamiltonian add up), so a
/// step costs 4N + 1 rotations.
#[derive(Clone, Copy, Debug)]
pub struct SplittingComposition<const N: usize> {
    pub body: RigidBody,
    /// Stage weights γⱼ (Σ γⱼ = 1, palindromic so the step is symmetric).
    pub weights: [f64; N],
}

/// Strang splitting, order 2: 5 rotations a step.
pub type Splitting = SplittingComposition<1>;

/// Suzuki's fractal 5-stage composition of the Strang step, order 4: 21 rotations a step.
pub type Splitting4 = SplittingComposition<5>;

impl Splitting {
    pub fn strang(body: RigidBody) -> Self {
        SplittingComposition {
            body,
            weights: [1.0],
        }
    }
}

impl Splitting4 {
    /// Weights (p, p, 1 − 4p, p, p), p = 1/(4 − 4^{1/3}). Chosen over Yoshida's triple jump
    /// (3 stages, 13 rotations): its leading error constant is several times smaller, for 21
    /// rotations instead of 13.
    pub fn suzuki(body: RigidBody) -> Self {
        let p = 1.0 / (4.0 - 4f64.cbrt());
        SplittingComposition {
            body,
            weights: [p, p, 1.0 - 4.0 * p, p, p],
        }
    }
}

impl<const N: usize> StepMap<3> for SplittingComposition<N> {
    type Workspace = ();

    fn workspace(&self) {}

    fn step(&self, h: f64, mu: &mut [f64; 3], _: &mut ()) -> Result<StepStats, StepFailure> {
        let body = &self.body;
        let mut pending = 0.5 * self.weights[0] * h;
        for (j, &g) in self.weights.iter().enumerate() {
            let tau = g * h;
            body.axis_flow(0, pending, mu);
            body.axis_flow(1, 0.5 * tau, mu);
            body.axis_flow(2, tau, mu);
            body.axis_flow(1, 0.5 * tau, mu);
            pending = 0.5 * tau + self.weights.get(j + 1).map_or(0.0, |&n| 0.5 * n * h);
        }
        body.axis_flow(0, pending, mu);
        explicit_result(mu)
    }
}

/// The rigid body's splitting with a Casimir split off first (Fassò 2003; McLachlan 1993):
/// H = C/(2I_r) + Σ_{i≠r} ½ aᵢ μᵢ², aᵢ = 1/Iᵢ − 1/I_r, C = |μ|². The Casimir's flow is the
/// identity, so a step is the Strang composition of the two remaining axis flows,
/// A_j(h/2) A_k(h) A_j(h/2), each an exact rotation with angular speed aᵢ μᵢ. The reference axis r
/// has the median 1/I, which makes the aᵢ as small as they can be: for a nearly symmetric body
/// they nearly vanish, and with them the splitting error, where the plain splitting's does not.
/// Order 2, 3 rotations a step, keeps C to round-off.
#[derive(Clone, Copy, Debug)]
pub struct CasimirSplitting {
    /// The two axes kept, and their coefficients aᵢ.
    axes: [usize; 2],
    coeff: [f64; 2],
}

impl CasimirSplitting {
    pub fn new(body: RigidBody) -> Self {
        let inv = body.inv;
        let mut order = [0, 1, 2];
        order.sort_by(|&a, &b| inv[a].total_cmp(&inv[b]));
        let r = order[1];
        let axes = [order[0], order[2]];
        CasimirSplitting {
            axes,
            coeff: axes.map(|i| inv[i] - inv[r]),
        }
    }

    /// The two axes kept and their coefficients aᵢ.
    #[inline(always)]
    pub(crate) fn axes_and_coefficients(&self) -> ([usize; 2], [f64; 2]) {
        (self.axes, self.coeff)
    }

    /// Exact flow for time t of ½ a μᵢ²: a rotation about eᵢ by the angle −t a μᵢ.
    #[inline]
    fn axis_flow(i: usize, a: f64, t: f64, mu: &mut [f64; 3]) {
        rotate_about(i, t * a * mu[i], mu);
    }
}

impl StepMap<3> for CasimirSplitting {
    type Workspace = ();

    fn workspace(&self) {}

    fn step(&self, h: f64, mu: &mut [f64; 3], _: &mut ()) -> Result<StepStats, StepFailure> {
        let ([j, k], [aj, ak]) = (self.axes, self.coeff);
        Self::axis_flow(j, aj, 0.5 * h, mu);
        Self::axis_flow(k, ak, h, mu);
        Self::axis_flow(j, aj, 0.5 * h, mu);
        explicit_result(mu)
    }
}

/// The discrete Moser–Veselov algorithm (Moser & Veselov 1991), order 2.
///
/// With J = diag(J) and Iᵢ = tr(J) − Jᵢ, the step solves h μ̂ = F J − J Fᵀ for F ∈ SO(3), then
/// μ' = Fᵀ μ. Writing F as the Cayley transform of y (quaternion (1, y)/√(1+|y|²)), the
/// equation becomes G(y) = 2(I∘y + (J∘y) × y) − h(1 + |y|²) μ = 0, solved by Newton from
/// y = hω/2. μ' is μ rotated, so C is kept to round-off; the map is integrable and keeps H
/// exactly as well (McLachlan & Zanna 2005), up to the Newton tolerance.
#[derive(Clone, Copy, Debug)]
pub struct MoserVeselov {
    pub body: RigidBody,
    pub newton: NewtonOptions,
    /// Jᵢ = (I₁ + I₂ + I₃)/2 − Iᵢ (may be ≤ 0 for bodies that break the triangle inequality;
    /// the equation for y does not need J > 0).
    j: [f64; 3],
}

impl MoserVeselov {
    pub fn new(body: RigidBody, newton: NewtonOptions) -> Self {
        let i = body.inertia;
        let half_trace = 0.5 * (i[0] + i[1] + i[2]);
        MoserVeselov {
            body,
            newton,
            j: i.map(|v| half_trace - v),
        }
    }
}

impl MoserVeselov {
    /// G(y) = 2(I∘y + (J∘y) × y) − h(1 + |y|²) μ for the step of size h from μ = `m`.
    #[inline(always)]
    pub(crate) fn residual(&self, h: f64, m: &[f64; 3], y: &[f64; 3]) -> [f64; 3] {
        let (inertia, jj) = (&self.body.inertia, &self.j);
        let jy = [jj[0] * y[0], jj[1] * y[1], jj[2] * y[2]];
        let c = cross(&jy, y);
        let s = h * (1.0 + y[0] * y[0] + y[1] * y[1] + y[2] * y[2]);
        std::array::from_fn(|i| 2.0 * (inertia[i] * y[i] + c[i]) - s * m[i])
    }

    /// The Newton update δ = −(dG/dy)⁻¹ G(y), unchecked (±∞ or NaN where the Jacobian is
    /// singular). dG/dy = 2(diag(I) − [y]× diag(J) + [J∘y]×) − 2h μ yᵀ, whose off-diagonal part
    /// is 2 y_k (J_a − J_b) for the pair (a, b) the entry couples; the 3×3 solve by cofactors
    /// (Cramer's rule), straight-line code that the SIMD lanes run lane-wide with the same bits.
    /// The Jacobian is 2 diag(I) plus O(h|μ|), well conditioned at any resolved step.
    #[inline(always)]
    pub(crate) fn newton_delta(&self, h: f64, m: &[f64; 3], y: &[f64; 3]) -> [f64; 3] {
        let g = self.residual(h, m, y);
        let (i, jj) = (&self.body.inertia, &self.j);
        let (d12, d20, d01) = (jj[1] - jj[2], jj[2] - jj[0], jj[0] - jj[1]);
        let a = [
            [i[0], y[2] * d12, y[1] * d12],
            [y[2] * d20, i[1], y[0] * d20],
            [y[1] * d01, y[0] * d01, i[2]],
        ];
        let th = 2.0 * h;
        let j: [[f64; 3]; 3] =
            std::array::from_fn(|r| std::array::from_fn(|k| 2.0 * a[r][k] - th * m[r] * y[k]));
        let (adj, det) = crate::step::adjugate3(&j);
        let scale = -1.0 / det;
        std::array::from_fn(|r| (adj[r][0] * g[0] + adj[r][1] * g[1] + adj[r][2] * g[2]) * scale)
    }

    /// The new state Fᵀ μ from the solution y, and the residual |F J − J Fᵀ − h μ̂| given
    /// g = G(y).
    #[inline(always)]
    pub(crate) fn finish(m: &[f64; 3], y: &[f64; 3], g: &[f64; 3]) -> ([f64; 3], f64) {
        let n2 = 1.0 + y[0] * y[0] + y[1] * y[1] + y[2] * y[2];
        // |F J − J Fᵀ − h μ̂| as a vector: G(y)/(1 + |y|²).
        let residual = max_abs(g) / n2;
        // Fᵀ μ = μ + 2(−y × μ + y × (y × μ))/(1 + |y|²).
        let ym = cross(y, m);
        let yym = cross(y, &ym);
        let s = 2.0 / n2;
        (
            std::array::from_fn(|i| m[i] + s * (yym[i] - ym[i])),
            residual,
        )
    }
}

impl StepMap<3> for MoserVeselov {
    type Workspace = ();

    fn workspace(&self) {}

    fn step(&self, h: f64, mu: &mut [f64; 3], _: &mut ()) -> Result<StepStats, StepFailure> {
        let m = *mu;
        let mut y = self.body.velocity(&m).map(|w| 0.5 * h * w);
        let mut iterations = 0;
        loop {
            if iterations >= self.newton.max_iter {
                return Err(StepFailure::NotConverged);
            }
            let delta = self.newton_delta(h, &m, &y);
            if !delta.iter().all(|v| v.is_finite()) {
                return Err(StepFailure::SingularJacobian);
            }
            for i in 0..3 {
                y[i] += delta[i];
            }
            iterations += 1;
            if max_abs(&delta) <= self.newton.tol * max_abs(&y).max(1e-300) {
                break;
            }
        }
        let (next, residual) = Self::finish(&m, &y, &self.residual(h, &m, &y));
        *mu = next;
        if !mu.iter().all(|v| v.is_finite()) {
            return Err(StepFailure::NonFinite);
        }
        Ok(StepStats {
            iterations,
            residual,
        })
    }
}

/// The classical integrators by name, for callers that choose at run time.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ClassicalMethod {
    Rk4,
    Midpoint,
    Splitting,
    Splitting4,
    Dmv,
    CasimirSplitting,
}

impl ClassicalMethod {
    pub const ALL: [ClassicalMethod; 6] = [
        ClassicalMethod::Rk4,
        ClassicalMethod::Midpoint,
        ClassicalMethod::Splitting,
        ClassicalMethod::Splitting4,
        ClassicalMethod::Dmv,
        ClassicalMethod::CasimirSplitting,
    ];

    pub fn name(self) -> &'static str {
        match self {
            ClassicalMethod::Rk4 => "rk4",
            ClassicalMethod::Midpoint => "midpoint",
            ClassicalMethod::Splitting => "splitting",
            ClassicalMethod::Splitting4 => "splitting4",
            ClassicalMethod::Dmv => "dmv",
            ClassicalMethod::CasimirSplitting => "splitting_casimir",
        }
    }

    pub fn from_name(name: &str) -> Result<Self, CoreError> {
        by_name(&Self::ALL, Self::name, name, "")
    }

    /// Order of accuracy.
    pub fn order(self) -> u32 {
        match self {
            ClassicalMethod::Rk4 | ClassicalMethod::Splitting4 => 4,
            _ => 2,
        }
    }

    /// Whether the step is a Poisson map (keeps C to round-off or Newton tolerance).
    pub fn is_poisson(self) -> bool {
        self != ClassicalMethod::Rk4
    }
}

/// A classical integrator chosen at run time (by name), itself a [`StepMap`].
#[derive(Clone, Debug)]
pub enum ClassicalStepper {
    Rk4(Rk4<RigidBody>),
    Midpoint(ImplicitMidpoint<RigidBody>),
    Splitting(Splitting),
    Splitting4(Splitting4),
    Dmv(MoserVeselov),
    CasimirSplitting(CasimirSplitting),
}

impl ClassicalMethod {
    /// The integrator for `body`; `newton` matters only for the implicit ones.
    pub fn stepper(self, body: RigidBody, newton: NewtonOptions) -> ClassicalStepper {
        match self {
            ClassicalMethod::Rk4 => ClassicalStepper::Rk4(Rk4 { system: body }),
            ClassicalMethod::Midpoint => ClassicalStepper::Midpoint(ImplicitMidpoint {
                system: body,
                newton,
            }),
            ClassicalMethod::Splitting => ClassicalStepper::Splitting(Splitting::strang(body)),
            ClassicalMethod::Splitting4 => ClassicalStepper::Splitting4(Splitting4::suzuki(body)),
            ClassicalMethod::Dmv => ClassicalStepper::Dmv(MoserVeselov::new(body, newton)),
            ClassicalMethod::CasimirSplitting => {
                ClassicalStepper::CasimirSplitting(CasimirSplitting::new(body))
            }
        }
    }
}

impl StepMap<3> for ClassicalStepper {
    type Workspace = ();

    fn workspace(&self) {}

    #[inline]
    fn step(&self, h: f64, mu: &mut [f64; 3], ws: &mut ()) -> Result<StepStats, StepFailure> {
        match self {
            ClassicalStepper::Rk4(s) => s.step(h, mu, ws),
            ClassicalStepper::Midpoint(s) => s.step(h, mu, ws),
            ClassicalStepper::Splitting(s) => s.step(h, mu, ws),
            ClassicalStepper::Splitting4(s) => s.step(h, mu, ws),
            ClassicalStepper::Dmv(s) => s.step(h, mu, ws),
            ClassicalStepper::CasimirSplitting(s) => s.step(h, mu, ws),
        }
    }
}

/// [`rollout`] with the named classical integrator; `newton` matters only for the implicit ones.
#[allow(clippy::too_many_arguments)]
pub fn rollout_classical(
    method: ClassicalMethod,
    body: RigidBody,
    newton: NewtonOptions,
    mu0: &[[f64; 3]],
    h: f64,
    n_steps: usize,
    every: usize,
    out: &mut [f64],
) -> Result<Vec<TrajectoryInfo>, CoreError> {
    rollout(&method.stepper(body, newton), mu0, h, n_steps, every, out)
}

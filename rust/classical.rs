//! Classical baseline integrators: RK4 and the implicit midpoint rule for any Lie–Poisson
//! system, the free rigid body's splittings and discrete Moser–Veselov, and the heavy top's
//! kinetic/potential splitting.
//!
//! They are not bisection methods, but implement [`StepMap`] like [`BisectionStepper`], so one
//! [`rollout`] drives them all and timings compare like for like. None allocates per step.
//!
//! Rigid body (so(3)*):
//!
//! | method | struct | order | Poisson |
//! |---|---|---|---|
//! | `rk4` | [`Rk4`] | 4 | no |
//! | `midpoint` | [`ImplicitMidpoint`] | 2 | yes (quadratic H: keeps C and H up to Newton tolerance) |
//! | `splitting` | [`Splitting`] (Strang) | 2 | yes |
//! | `splitting4` | [`Splitting4`] (Suzuki, 5 Strang stages) | 4 | yes |
//! | `dmv` | [`MoserVeselov`] | 2 | yes (keeps C and H to round-off) |
//! | `splitting_casimir` | [`CasimirSplitting`] | 2 | yes |
//!
//! Any Lie–Poisson system ([`LieMethod`]): `rk4` and `midpoint` (Poisson for quadratic H), and
//! for the heavy top `splitting` ([`HeavyTopSplitting`], order 2, Poisson).
//!
//! [`BisectionStepper`]: crate::stepper::BisectionStepper

use nalgebra::{Const, DimMin, Matrix3};

use crate::error::{CoreError, StepFailure};
use crate::lane_field::MidpointSolve;
use crate::rollout::{rollout, TrajectoryInfo};
use crate::step::{NewtonOptions, StepMap, StepStats};
use crate::straight_line::LieField;
use crate::structures::lie_poisson::{LiePoisson, VectorField};
use crate::trig;

/// A free rigid body: principal moments of inertia I (any order, all finite and > 0).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RigidBody {
    inertia: [f64; 3],
    inv: [f64; 3],
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

    /// Euler's equations μ̇ = μ × (μ/I).
    #[inline]
    pub fn vector_field(&self, mu: &[f64; 3]) -> [f64; 3] {
        cross(mu, &self.velocity(mu))
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
fn rotate_about_by(i: usize, (s, c): (f64, f64), v: &mut [f64]) {
    let (a, b) = ((i + 1) % 3, (i + 2) % 3);
    let (x, y) = (v[a], v[b]);
    v[a] = c * x + s * y;
    v[b] = c * y - s * x;
}

#[inline]
fn cross(a: &[f64; 3], b: &[f64; 3]) -> [f64; 3] {
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

#[inline]
fn axpy<const N: usize>(a: f64, x: &[f64; N], y: &[f64; N]) -> [f64; N] {
    std::array::from_fn(|i| y[i] + a * x[i])
}

#[inline]
pub(crate) fn max_abs<const N: usize>(a: &[f64; N]) -> f64 {
    a.iter().fold(0.0, |m: f64, v| m.max(v.abs()))
}

/// The stats of an explicit step, or NonFinite if it overflowed.
#[inline]
fn explicit_result<const N: usize>(mu: &[f64; N]) -> Result<StepStats, StepFailure> {
    if mu.iter().all(|v| v.is_finite()) {
        Ok(StepStats::default())
    } else {
        Err(StepFailure::NonFinite)
    }
}

/// Classical explicit Runge–Kutta of order 4. Not Poisson: C and H drift.
#[derive(Clone, Debug)]
pub struct Rk4<F> {
    pub system: F,
}

impl<const N: usize, F: VectorField<N>> StepMap<N> for Rk4<F> {
    type Workspace = ();

    fn workspace(&self) {}

    fn step(&self, h: f64, mu: &mut [f64; N], _: &mut ()) -> Result<StepStats, StepFailure> {
        let f = |m: &[f64; N]| self.system.field(m);
        let k1 = f(mu);
        let k2 = f(&axpy(0.5 * h, &k1, mu));
        let k3 = f(&axpy(0.5 * h, &k2, mu));
        let k4 = f(&axpy(h, &k3, mu));
        for i in 0..N {
            mu[i] += h / 6.0 * (k1[i] + 2.0 * (k2[i] + k3[i]) + k4[i]);
        }
        explicit_result(mu)
    }
}

/// Implicit midpoint μ' = μ + h f((μ + μ')/2), order 2.
///
/// It keeps every quadratic invariant: for the rigid body C = |μ|² and H, up to the Newton
/// tolerance, and for any Lie–Poisson system its quadratic Casimirs (a Poisson map when H is
/// quadratic). Newton solves for the midpoint m = μ + (h/2) f(m) with the exact Jacobian
/// I − (h/2) ∂f/∂μ(m).
#[derive(Clone, Debug)]
pub struct ImplicitMidpoint<F> {
    pub system: F,
    pub newton: NewtonOptions,
}

impl<const N: usize, F: VectorField<N> + MidpointSolve<N>> StepMap<N> for ImplicitMidpoint<F>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    type Workspace = ();

    fn workspace(&self) {}

    fn step(&self, h: f64, mu: &mut [f64; N], _: &mut ()) -> Result<StepStats, StepFailure> {
        let body = &self.system;
        let mu0 = *mu;
        let half = 0.5 * h;
        // Start at the explicit Euler midpoint: one Newton update fewer than starting at μ.
        let mut m = axpy(half, &body.field(&mu0), &mu0);
        let mut iterations = 0;
        loop {
            if iterations >= self.newton.max_iter {
                return Err(StepFailure::NotConverged);
            }
            let fm = body.field(&m);
            let r: [f64; N] = std::array::from_fn(|i| m[i] - mu0[i] - half * fm[i]);
            let delta = body.midpoint_update(half, &m, &r)?;
            for i in 0..N {
                m[i] += delta[i];
            }
            iterations += 1;
            if max_abs(&delta) <= self.newton.tol * max_abs(&m).max(1e-300) {
                break;
            }
        }
        let fm = body.field(&m);
        let residual = max_abs::<N>(&std::array::from_fn(|i| m[i] - mu0[i] - half * fm[i]));
        // μ + h f(m) rather than 2m − μ: the increment carries the rounding, not μ.
        *mu = axpy(h, &fm, &mu0);
        if !mu.iter().all(|v| v.is_finite()) {
            return Err(StepFailure::NonFinite);
        }
        Ok(StepStats {
            iterations,
            residual,
        })
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

/// The method of `all` called `name`, or an error listing the valid names.
fn by_name<M: Copy>(
    all: &[M],
    name_of: fn(M) -> &'static str,
    name: &str,
    context: &str,
) -> Result<M, CoreError> {
    all.iter()
        .copied()
        .find(|&m| name_of(m) == name)
        .ok_or_else(|| {
            let names: Vec<_> = all.iter().map(|&m| name_of(m)).collect();
            CoreError::Invalid(format!(
                "unknown classical integrator {name:?}{context}; valid names: {}",
                names.join(", ")
            ))
        })
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

/// The heavy top on se(3)*, μ = (M, Γ), H = ½ Σ Mᵢ²/Iᵢ + mgl χ·Γ:
/// Ṁ = M × Ω + mgl Γ × χ, Γ̇ = Γ × Ω with Ω = M/I.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HeavyTop {
    pub body: RigidBody,
    /// mgl · χ: the weight times the centre of mass in the body frame.
    pub torque_arm: [f64; 3],
}

impl HeavyTop {
    pub fn new(inertia: [f64; 3], mgl: f64, com: [f64; 3]) -> Result<Self, CoreError> {
        if !(mgl.is_finite() && com.iter().all(|v| v.is_finite())) {
            return Err(CoreError::Invalid(format!(
                "mgl and the centre of mass must be finite, got {mgl} and {com:?}"
            )));
        }
        Ok(HeavyTop {
            body: RigidBody::new(inertia)?,
            torque_arm: com.map(|c| mgl * c),
        })
    }

    /// Exact flow for time t of Hᵢ = Mᵢ²/(2Iᵢ): M and Γ turn about eᵢ by the same angle.
    #[inline]
    pub(crate) fn axis_flow(&self, i: usize, t: f64, mu: &mut [f64; 6]) {
        let sc = trig::sin_cos(t * mu[i] * self.body.inv[i]);
        let (m, g) = mu.split_at_mut(3);
        rotate_about_by(i, sc, m);
        rotate_about_by(i, sc, g);
    }

    /// Exact flow for time t of the potential mgl χ·Γ: Γ fixed, M += t mgl Γ × χ.
    #[inline]
    pub(crate) fn potential_flow(&self, t: f64, mu: &mut [f64; 6]) {
        let g = [mu[3], mu[4], mu[5]];
        let d = cross(&g, &self.torque_arm);
        for i in 0..3 {
            mu[i] += t * d[i];
        }
    }
}

/// Strang splitting of the heavy top into its kinetic and potential parts, order 2:
/// V(h/2) ∘ K(h) ∘ V(h/2), with the kinetic flow K itself the rigid body's Strang splitting
/// over the three axes. Every sub-flow is exact, so the step is a Poisson map and keeps both
/// Casimirs |Γ|² and M·Γ to round-off.
#[derive(Clone, Copy, Debug)]
pub struct HeavyTopSplitting {
    pub top: HeavyTop,
}

impl StepMap<6> for HeavyTopSplitting {
    type Workspace = ();

    fn workspace(&self) {}

    fn step(&self, h: f64, mu: &mut [f64; 6], _: &mut ()) -> Result<StepStats, StepFailure> {
        let top = &self.top;
        top.potential_flow(0.5 * h, mu);
        top.axis_flow(0, 0.5 * h, mu);
        top.axis_flow(1, 0.5 * h, mu);
        top.axis_flow(2, h, mu);
        top.axis_flow(1, 0.5 * h, mu);
        top.axis_flow(0, 0.5 * h, mu);
        top.potential_flow(0.5 * h, mu);
        explicit_result(mu)
    }
}

/// The classical integrators of a general Lie–Poisson system, by name.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LieMethod {
    Rk4,
    Midpoint,
    /// The heavy top's kinetic/potential splitting; needs [`HeavyTop`] parameters.
    Splitting,
}

impl LieMethod {
    pub const ALL: [LieMethod; 3] = [LieMethod::Rk4, LieMethod::Midpoint, LieMethod::Splitting];

    pub fn name(self) -> &'static str {
        match self {
            LieMethod::Rk4 => "rk4",
            LieMethod::Midpoint => "midpoint",
            LieMethod::Splitting => "splitting",
        }
    }

    pub fn from_name(name: &str) -> Result<Self, CoreError> {
        by_name(&Self::ALL, Self::name, name, " for a Lie–Poisson system")
    }
}

/// A classical integrator of a Lie–Poisson system chosen at run time.
#[derive(Clone, Debug)]
pub enum LieStepper<const N: usize> {
    Rk4(Rk4<LieField<N>>),
    Midpoint(ImplicitMidpoint<LieField<N>>),
    /// Only for N = 6 (the heavy top); built by [`LieStepper::new`] alone.
    HeavyTop(HeavyTopSplitting),
}

impl<const N: usize> LieStepper<N> {
    /// The integrator `method` for `system`; `heavy_top` carries the parameters the splitting
    /// needs (it must describe the same system).
    pub fn new(
        method: LieMethod,
        system: LiePoisson<N>,
        heavy_top: Option<HeavyTop>,
        newton: NewtonOptions,
    ) -> Result<Self, CoreError> {
        // The steppers evaluate a recognised pattern's straight-line field, else the system
        // compiled to its sparsity.
        let system = LieField::new(&system);
        Ok(match method {
            LieMethod::Rk4 => LieStepper::Rk4(Rk4 { system }),
            LieMethod::Midpoint => LieStepper::Midpoint(ImplicitMidpoint { system, newton }),
            LieMethod::Splitting => {
                match heavy_top {
                    Some(top) if N == 6 => LieStepper::HeavyTop(HeavyTopSplitting { top }),
                    _ => return Err(CoreError::Invalid(
                        "the splitting integrator is defined for the rigid body and the heavy top \
                         only"
                            .into(),
                    )),
                }
            }
        })
    }
}

impl<const N: usize> StepMap<N> for LieStepper<N>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    type Workspace = ();

    fn workspace(&self) {}

    #[inline]
    fn step(&self, h: f64, mu: &mut [f64; N], ws: &mut ()) -> Result<StepStats, StepFailure> {
        match self {
            LieStepper::Rk4(s) => s.step(h, mu, ws),
            LieStepper::Midpoint(s) => s.step(h, mu, ws),
            LieStepper::HeavyTop(s) => match <&mut [f64; 6]>::try_from(&mut mu[..]) {
                Ok(m) => s.step(h, m, ws),
                Err(_) => Err(StepFailure::NonFinite),
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const PAPER: [f64; 3] = [1.5, 2.0, 2.5];
    const STATES: [[f64; 3]; 4] = [
        [1.0, 1.0, 2.0],
        [3.0, 2.0, 0.0],
        [-0.7, 1.3, 0.4],
        [0.2, -2.1, 1.1],
    ];

    fn body(inertia: [f64; 3]) -> RigidBody {
        RigidBody::new(inertia).unwrap()
    }

    /// One step of size h, in place; panics on a failed step.
    type Step = Box<dyn Fn(f64, &mut [f64; 3])>;

    fn stepper(method: ClassicalMethod, body: RigidBody) -> Step {
        let newton = NewtonOptions::default();
        fn boxed<S: StepMap<3, Workspace = ()> + 'static>(s: S) -> Step {
            Box::new(move |h, mu| {
                s.step(h, mu, &mut ()).unwrap();
            })
        }
        match method {
            ClassicalMethod::Rk4 => boxed(Rk4 { system: body }),
            ClassicalMethod::Midpoint => boxed(ImplicitMidpoint {
                system: body,
                newton,
            }),
            ClassicalMethod::Splitting => boxed(Splitting::strang(body)),
            ClassicalMethod::Splitting4 => boxed(Splitting4::suzuki(body)),
            ClassicalMethod::Dmv => boxed(MoserVeselov::new(body, newton)),
            ClassicalMethod::CasimirSplitting => boxed(CasimirSplitting::new(body)),
        }
    }

    /// The flow over time t by `n` RK4 steps: the reference for local errors.
    fn fine(body: RigidBody, mu: [f64; 3], t: f64, n: usize) -> [f64; 3] {
        let rk = Rk4 { system: body };
        let mut m = mu;
        for _ in 0..n {
            rk.step(t / n as f64, &mut m, &mut ()).unwrap();
        }
        m
    }

    fn dist(a: &[f64; 3], b: &[f64; 3]) -> f64 {
        (0..3).map(|i| (a[i] - b[i]).powi(2)).sum::<f64>().sqrt()
    }

    fn casimir(mu: &[f64; 3]) -> f64 {
        mu.iter().map(|v| v * v).sum()
    }

    #[test]
    fn rejects_bad_inertia_and_names() {
        for bad in [
            [0.0, 1.0, 1.0],
            [1.0, -2.0, 1.0],
            [1.0, f64::NAN, 1.0],
            [f64::INFINITY; 3],
        ] {
            assert!(matches!(RigidBody::new(bad), Err(CoreError::Invalid(_))));
        }
        for m in ClassicalMethod::ALL {
            assert_eq!(ClassicalMethod::from_name(m.name()), Ok(m));
        }
        let err = ClassicalMethod::from_name("rk5").unwrap_err().to_string();
        assert!(err.contains("rk5") && err.contains("splitting4") && err.contains("dmv"));
    }

    #[test]
    fn axis_flow_signs_follow_mu_cross_grad_h() {
        // (φ_t(μ) − φ_{−t}(μ))/2t → μ × ∇Hᵢ = (μᵢ/Iᵢ) μ × eᵢ; a flipped sign would give its negative.
        let b = body([1.3, 0.7, 2.9]);
        let t = 1e-5;
        for mu in STATES {
            for i in 0..3 {
                let (mut fwd, mut bwd) = (mu, mu);
                b.axis_flow(i, t, &mut fwd);
                b.axis_flow(i, -t, &mut bwd);
                let mut e = [0.0; 3];
                e[i] = mu[i] / b.inertia[i];
                let want = cross(&mu, &e);
                for k in 0..3 {
                    let got = (fwd[k] - bwd[k]) / (2.0 * t);
                    assert!(
                        (got - want[k]).abs() <= 1e-7,
                        "axis {i}: {got} vs {}",
                        want[k]
                    );
                }
                // Hᵢ's flow keeps μᵢ and |μ|.
                assert_eq!(fwd[i], mu[i]);
                assert!((casimir(&fwd) / casimir(&mu) - 1.0).abs() <= 1e-15);
            }
        }
        // The three flows add up to the full vector field.
        for mu in STATES {
            let mut sum = [0.0; 3];
            for i in 0..3 {
                let (mut fwd, mut bwd) = (mu, mu);
                b.axis_flow(i, t, &mut fwd);
                b.axis_flow(i, -t, &mut bwd);
                for k in 0..3 {
                    sum[k] += (fwd[k] - bwd[k]) / (2.0 * t);
                }
            }
            assert!(dist(&sum, &b.vector_field(&mu)) <= 1e-7);
        }
    }

    #[test]
    fn rk4_matches_a_fine_rk4_reference() {
        let b = body(PAPER);
        for mu0 in STATES {
            // 50 steps of 0.1 against 5000 of 0.001: RK4's global error is ~h⁴.
            let coarse = fine(b, mu0, 5.0, 50);
            let reference = fine(b, mu0, 5.0, 5000);
            let err = dist(&coarse, &reference);
            assert!(err > 1e-9 && err < 1e-3, "err {err}");
        }
    }

    #[test]
    fn every_method_matches_the_exact_symmetric_top() {
        // I₁ = I₂: μ₃ is constant and (μ₁, μ₂) turns at Ω = μ₃(1/I₃ − 1/I₁), an oracle
        // independent of RK4.
        let inertia = [2.0, 2.0, 0.8];
        let b = body(inertia);
        let (h, n) = (0.01, 300);
        for method in ClassicalMethod::ALL {
            let step = stepper(method, b);
            for mu0 in STATES {
                let mut mu = mu0;
                for _ in 0..n {
                    step(h, &mut mu);
                }
                let angle = mu0[2] * (1.0 / inertia[2] - 1.0 / inertia[0]) * (h * n as f64);
                let (s, c) = angle.sin_cos();
                let exact = [mu0[0] * c + mu0[1] * s, mu0[1] * c - mu0[0] * s, mu0[2]];
                let err = dist(&mu, &exact);
                let bound = if method.order() == 4 { 1e-8 } else { 1e-3 };
                assert!(err <= bound, "{}: err {err}", method.name());
            }
        }
    }

    #[test]
    fn local_error_ratio_matches_the_order() {
        // A one-step error ~ C h^(p+1), so err(h)/err(h/2) ≈ 2^(p+1).
        for inertia in [PAPER, [0.9, 3.1, 1.7]] {
            let b = body(inertia);
            for method in ClassicalMethod::ALL {
                let step = stepper(method, b);
                for mu0 in STATES {
                    let err = |h: f64| {
                        let mut mu = mu0;
                        step(h, &mut mu);
                        dist(&mu, &fine(b, mu0, h, 200))
                    };
                    let h = match method {
                        ClassicalMethod::Rk4 => 0.08,
                        ClassicalMethod::Splitting4 => 0.03,
                        _ => 0.02,
                    };
                    let (e1, e2) = (err(h), err(0.5 * h));
                    let slope = (e1 / e2).log2();
                    let want = f64::from(method.order() + 1);
                    assert!(
                        (slope - want).abs() <= 0.3,
                        "{} {inertia:?} {mu0:?}: log2 ratio {slope:.2} (errors {e1:.2e}, {e2:.2e})",
                        method.name()
                    );
                }
            }
        }
    }

    #[test]
    fn poisson_methods_keep_the_casimir_and_rk4_does_not() {
        for inertia in [PAPER, [0.9, 3.1, 1.7]] {
            let b = body(inertia);
            for method in ClassicalMethod::ALL {
                let step = stepper(method, b);
                for mu0 in STATES {
                    let (mut mu, c0, h0) = (mu0, casimir(&mu0), b.hamiltonian(&mu0));
                    let (mut dc, mut dh) = (0.0f64, 0.0f64);
                    for _ in 0..10_000 {
                        step(0.1, &mut mu);
                        dc = dc.max((casimir(&mu) / c0 - 1.0).abs());
                        dh = dh.max((b.hamiltonian(&mu) / h0 - 1.0).abs());
                    }
                    let name = method.name();
                    if method.is_poisson() {
                        assert!(dc <= 1e-12, "{name}: Casimir drift {dc:e}");
                    } else {
                        assert!(dc > 1e-10, "{name}: Casimir drift {dc:e}");
                    }
                    // Midpoint and DMV keep H as well (up to Newton tolerance and round-off).
                    if matches!(method, ClassicalMethod::Midpoint | ClassicalMethod::Dmv) {
                        assert!(dh <= 1e-12, "{name}: energy drift {dh:e}");
                    }
                }
            }
        }
    }

    #[test]
    fn newton_reports_failures_and_zero_state_is_a_fixed_point() {
        let b = body(PAPER);
        let tight = NewtonOptions::validated(1e-12, 1).unwrap();
        let mut mu = [1.0, 1.0, 2.0];
        let r = ImplicitMidpoint {
            system: b,
            newton: tight,
        }
        .step(0.1, &mut mu, &mut ());
        assert_eq!(r, Err(StepFailure::NotConverged));
        let r = MoserVeselov::new(b, tight).step(0.1, &mut mu, &mut ());
        assert_eq!(r, Err(StepFailure::NotConverged));
        for method in ClassicalMethod::ALL {
            let mut zero = [0.0; 3];
            stepper(method, b)(0.1, &mut zero);
            assert_eq!(zero, [0.0; 3], "{}", method.name());
        }
        // A converged implicit step reports its iterations and a round-off residual.
        let mut mu = [1.0, 1.0, 2.0];
        let s = MoserVeselov::new(b, NewtonOptions::default())
            .step(0.1, &mut mu, &mut ())
            .unwrap();
        assert!(s.iterations >= 2 && s.residual <= 1e-14, "{s:?}");
    }

    #[test]
    fn rollout_by_name_matches_stepping() {
        let b = body(PAPER);
        let (h, n, every) = (0.1, 7, 3);
        for method in ClassicalMethod::ALL {
            let mut out = vec![0.0; STATES.len() * 3 * 3];
            let info = rollout_classical(
                method,
                b,
                NewtonOptions::default(),
                &STATES,
                h,
                n,
                every,
                &mut out,
            )
            .unwrap();
            assert!(info.iter().all(|i| i.converged));
            let step = stepper(method, b);
            for (k, mu0) in STATES.iter().enumerate() {
                let mut mu = *mu0;
                for _ in 0..6 {
                    step(h, &mut mu);
                }
                assert_eq!(&out[9 * k + 6..9 * k + 9], &mu[..], "{}", method.name());
            }
        }
    }
}

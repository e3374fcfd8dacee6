//! The classical integrators of a log-canonical system: RK4 and the implicit midpoint rule in
//! x, the exact splittings in q, and the orthant check of a stepper in q.

// Index loops over small fixed-size vectors and matrices read as the formulas they implement.
#![allow(clippy::needless_range_loop)]

use nalgebra::{Const, DimMin, SMatrix};

use super::structure::linear_field_lanes;
use super::{in_orthant, log_state_in_orthant, LogSystem};
use crate::classical::ImplicitMidpoint;
use crate::dual::Dual1;
use crate::error::{CoreError, StepFailure};
use crate::exp::{exp_lanes, EXP_MAX, EXP_MIN};
use crate::lane_field::{by_lane, FieldAt, LaneField, StepAt};
use crate::lanes::{LaneStepper, PAIRED_LANES};
use crate::step::{NewtonOptions, StepMap, StepResult, StepStats};
use crate::structures::lie_poisson::VectorField;

/// Classical integrators of a log-canonical system.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LogMethod {
    /// Explicit RK4 in x; order 4, not Poisson.
    Rk4,
    /// Implicit midpoint in x, Newton with the exact Jacobian; order 2, not Poisson.
    Midpoint,
    /// Strang composition of the exact one-variable flows in q: H₁(h/2)…H_{n−1}(h/2) H_n(h)
    /// H_{n−1}(h/2)…H₁(h/2); explicit, order 2, Poisson.
    Splitting,
    /// Suzuki's 5-stage composition (p, p, 1 − 4p, p, p) of that Strang step,
    /// p = 1/(4 − 4^{1/3}); explicit, order 4, Poisson.
    Splitting4,
}

impl LogMethod {
    pub fn from_name(name: &str) -> Result<Self, CoreError> {
        match name {
            "rk4" => Ok(LogMethod::Rk4),
            "midpoint" => Ok(LogMethod::Midpoint),
            "log_splitting" => Ok(LogMethod::Splitting),
            "log_splitting4" => Ok(LogMethod::Splitting4),
            _ => Err(CoreError::Invalid(format!(
                "unknown log-canonical integrator {name:?}; valid: rk4, midpoint, log_splitting, \
                 log_splitting4"
            ))),
        }
    }

    /// Whether the state is q = ln x (the splittings) rather than x.
    pub fn in_log(self) -> bool {
        matches!(self, LogMethod::Splitting | LogMethod::Splitting4)
    }
}

/// A classical stepper of a log-canonical system.
#[derive(Clone, Debug)]
pub struct LogClassical<const N: usize> {
    pub method: LogMethod,
    pub system: LogSystem<N>,
    pub newton: NewtonOptions,
    /// (variable, exponent, coefficient) of each monomial, for the splittings.
    parts: Vec<(usize, u32, f64)>,
}

/// Suzuki's weight p = 1/(4 − 4^{1/3}).
fn suzuki_p() -> f64 {
    1.0 / (4.0 - 4f64.powf(1.0 / 3.0))
}

/// The field in x of H = Σ a_i x_i − b_i ln x_i on the bracket c ([`linear_field_lanes`]),
/// on copies of its constants.
#[derive(Clone, Copy)]
struct LinearField<const N: usize> {
    a: [f64; N],
    b: [f64; N],
    c: [[f64; N]; N],
}

impl<const N: usize, const L: usize> FieldAt<N, L> for LinearField<N> {
    #[inline(always)]
    fn field_at(&self, y: &[[f64; L]; N], out: &mut [[f64; L]; N]) {
        linear_field_lanes(&self.a, &self.b, &self.c, y, out);
    }
}

/// [`rk4_in_x`] of a field, as a [`StepAt`] (for [`by_lane`]).
struct Rk4InX<'a, F>(&'a F);

impl<const N: usize, const K: usize, F: FieldAt<N, K>> StepAt<N, K> for Rk4InX<'_, F> {
    #[inline(always)]
    fn step_at(&self, h: f64, y: &mut [[f64; K]; N]) {
        rk4_in_x(self.0, h, y);
    }
}

/// RK4 in x on `field` at L states, lane by lane (the scalar step is L = 1).
#[inline(always)]
fn rk4_in_x<const N: usize, const L: usize, F: FieldAt<N, L>>(
    field: &F,
    h: f64,
    x: &mut [[f64; L]; N],
) {
    let f = |y: &[[f64; L]; N]| {
        let mut out = [[0.0; L]; N];
        field.field_at(y, &mut out);
        out
    };
    let at = |k: &[[f64; L]; N], w: f64| -> [[f64; L]; N] {
        std::array::from_fn(|i| std::array::from_fn(|l| x[i][l] + w * k[i][l]))
    };
    let k1 = f(x);
    let k2 = f(&at(&k1, 0.5 * h));
    let k3 = f(&at(&k2, 0.5 * h));
    let k4 = f(&at(&k3, h));
    for i in 0..N {
        for l in 0..L {
            x[i][l] += h / 6.0 * (k1[i][l] + 2.0 * k2[i][l] + 2.0 * k3[i][l] + k4[i][l]);
        }
    }
}

/// A stepper in q whose every step is checked to keep x = e^q in the open orthant (finite,
/// > 0 in float64): a step that leaves it is a failure, never a silent 0 or ∞.
#[derive(Clone, Debug)]
pub struct OrthantChecked<S>(pub S);

impl<const N: usize, S: StepMap<N>> StepMap<N> for OrthantChecked<S> {
    type Workspace = S::Workspace;
    fn workspace(&self) -> S::Workspace {
        self.0.workspace()
    }
    fn step(&self, h: f64, q: &mut [f64; N], ws: &mut S::Workspace) -> StepResult {
        let stats = self.0.step(h, q, ws)?;
        log_state_in_orthant(q)?;
        Ok(stats)
    }
}

impl<const N: usize> LogClassical<N>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    pub fn new(
        method: LogMethod,
        system: LogSystem<N>,
        newton: NewtonOptions,
    ) -> Result<Self, CoreError> {
        let parts = if method.in_log() {
            system.separable().ok_or_else(|| {
                CoreError::Invalid(
                    "the log splittings need a separable Hamiltonian (every monomial in one \
                     variable)"
                        .into(),
                )
            })?
        } else {
            Vec::new()
        };
        Ok(LogClassical {
            method,
            system,
            newton,
            parts,
        })
    }

    /// The exact flow of H_i for time t at L states: q_j += t c_ji H_i'(q_i).
    #[inline(always)]
    fn flow_lanes<const L: usize>(&self, i: usize, t: f64, q: &mut [[f64; L]; N]) {
        let mut d = [-self.system.b[i]; L];
        for &(v, e, a) in &self.parts {
            if v == i {
                let ef = f64::from(e);
                let arg: [f64; L] = std::array::from_fn(|l| ef * q[i][l]);
                let mut y = [0.0; L];
                exp_lanes(&arg, &mut y);
                for l in 0..L {
                    d[l] += a * ef * y[l];
                }
            }
        }
        let c = self.system.structure.c();
        for j in 0..N {
            let w = t * c[j][i];
            for l in 0..L {
                q[j][l] += w * d[l];
            }
        }
    }

    #[inline(always)]
    fn strang_lanes<const L: usize>(&self, h: f64, q: &mut [[f64; L]; N]) {
        for i in 0..N - 1 {
            self.flow_lanes(i, 0.5 * h, q);
        }
        self.flow_lanes(N - 1, h, q);
        for i in (0..N - 1).rev() {
            self.flow_lanes(i, 0.5 * h, q);
        }
    }

    /// RK4 in x. A linear H (Lotka–Volterra's form) takes the straight-line field, lane by
    /// lane, or by lane in a block of [`PAIRED_LANES`], which is always an AVX-512 block
    /// (`Lanes::advance_chunk`; `LogExplicit::avx512_by_lane`).
    #[inline(always)]
    fn rk4_lanes<const L: usize>(&self, h: f64, x: &mut [[f64; L]; N]) {
        let Some(a) = self.system.linear() else {
            rk4_in_x(&FieldInX(&self.system), h, x);
            return;
        };
        // A copy: the loop over lanes then reads registers. Read through `self`, the
        // coefficients were loaded again in every lane and the loop stayed scalar (the
        // compiler could not tell them apart from the block it stores to).
        let field = LinearField {
            a: *a,
            b: self.system.b,
            c: *self.system.structure.c(),
        };
        if L == PAIRED_LANES {
            by_lane::<N, L, 1, _>(&Rk4InX(&field), h, x);
        } else {
            rk4_in_x(&field, h, x);
        }
    }

    /// One step of an explicit method (RK4 or a log splitting) at L states, lane by lane; the
    /// scalar step is this with L = 1. The midpoint rule is not explicit: nothing is done.
    #[inline(always)]
    fn step_explicit_lanes<const L: usize>(&self, h: f64, s: &mut [[f64; L]; N]) {
        match self.method {
            LogMethod::Rk4 => self.rk4_lanes(h, s),
            LogMethod::Splitting => self.strang_lanes(h, s),
            LogMethod::Splitting4 => {
                let p = suzuki_p();
                for w in [p, p, 1.0 - 4.0 * p, p, p] {
                    self.strang_lanes(w * h, s);
                }
            }
            LogMethod::Midpoint => {}
        }
    }

    /// This stepper in SIMD lanes, for the explicit methods (None for the midpoint rule).
    pub fn explicit(&self) -> Option<LogExplicit<'_, N>> {
        (self.method != LogMethod::Midpoint).then_some(LogExplicit(self))
    }

    /// The scalar step's check: x in the open orthant, or q with e^q in it.
    fn domain(&self, s: &[f64; N]) -> Result<(), StepFailure> {
        if self.method.in_log() {
            log_state_in_orthant(s)
        } else {
            in_orthant(s)
        }
    }

    /// This stepper in SIMD lanes, for the implicit midpoint rule (None for the others).
    pub fn midpoint_in_lanes(&self) -> Option<LogMidpoint<'_, N>> {
        (self.method == LogMethod::Midpoint).then_some(LogMidpoint(self))
    }
}

impl<const N: usize> StepMap<N> for LogClassical<N>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    type Workspace = ();

    fn workspace(&self) {}

    fn step(&self, h: f64, s: &mut [f64; N], _: &mut ()) -> StepResult {
        let mut lane: [[f64; 1]; N] = s.map(|v| [v]);
        if let Some(midpoint) = self.midpoint_in_lanes() {
            // The midpoint rule on one lane (its own orthant check included).
            let mut result = [Ok(StepStats::default())];
            midpoint.step_lanes_reporting(h, &mut lane, &[true], &mut result);
            *s = lane.map(|v| v[0]);
            return result[0];
        }
        self.step_explicit_lanes(h, &mut lane);
        *s = lane.map(|v| v[0]);
        self.domain(s)?;
        Ok(StepStats::default())
    }
}

/// An explicit [`LogClassical`] (RK4 in x, or a log splitting in q) as a [`LaneStepper`]:
/// blocks of trajectories step in SIMD lanes, each lane with the scalar step's bits and its
/// orthant check.
pub struct LogExplicit<'a, const N: usize>(&'a LogClassical<N>);

impl<const N: usize> StepMap<N> for LogExplicit<'_, N>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    type Workspace = ();
    fn workspace(&self) {}
    fn step(&self, h: f64, s: &mut [f64; N], ws: &mut ()) -> StepResult {
        self.0.step(h, s, ws)
    }
}

impl<const N: usize> LaneStepper<N> for LogExplicit<'_, N>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    const CHECKS_DOMAIN: bool = true;
    /// Measured with RK4 by lane and with the paired splittings.
    const PROBE_BY_LANE: bool = true;

    /// Measured: the log splittings 0.44–0.70× the time of blocks of 8; RK4 in x lost
    /// (1.30–1.56×, its loop over H's terms spilling), so it keeps blocks of 8 unless by lane.
    #[inline(always)]
    fn avx512_paired(&self) -> bool {
        self.0.method.in_log()
    }

    /// RK4 in x on a linear H (Lotka–Volterra's form): its field is straight-line code.
    #[inline(always)]
    fn avx512_by_lane(&self) -> bool {
        self.0.method == LogMethod::Rk4 && self.0.system.linear().is_some()
    }

    #[inline(always)]
    fn step_lanes<const L: usize>(&self, h: f64, mu: &mut [[f64; L]; N]) {
        self.0.step_explicit_lanes(h, mu);
    }

    #[inline(always)]
    fn maybe_outside_lanes<const L: usize>(&self, mu: &[[f64; L]; N], flag: &mut [bool; L]) {
        // In q: e^q can reach 0 or ∞ only outside exp's vectorised range. In x: x ≤ 0 (NaN
        // flags too; the block loop has already sent non-finite lanes to NonFinite).
        // Lane by lane, the loop over lanes outermost (as the block loop's probe).
        let in_log = self.0.method.in_log();
        for l in 0..L {
            for coordinate in mu {
                let v = coordinate[l];
                flag[l] |= if in_log {
                    !(EXP_MIN..=EXP_MAX).contains(&v)
                } else {
                    v <= 0.0 || v.is_nan()
                };
            }
        }
    }

    fn domain(&self, state: &[f64; N]) -> Result<(), StepFailure> {
        self.0.domain(state)
    }
}

/// A log-canonical system's vector field in x, ẋ_i = x_i (c g(x))_i, as the classical steppers
/// take a field: in lanes (the scalar field is its one-lane case) with its Jacobian in closed
/// form lane by lane ([`LogSystem::jacobian_in_lanes`]), and exactly by dual numbers for a lane
/// that needs a pivoted solve.
#[derive(Clone, Copy)]
pub struct FieldInX<'a, const N: usize>(pub &'a LogSystem<N>);

impl<const N: usize> VectorField<N> for FieldInX<'_, N> {
    fn field(&self, x: &[f64; N]) -> [f64; N] {
        let mut out = [[0.0; 1]; N];
        self.0.field_lanes(&x.map(|v| [v]), &mut out);
        out.map(|v| v[0])
    }

    fn jacobian(&self, x: &[f64; N]) -> SMatrix<f64, N, N> {
        let d: [Dual1<N>; N] = std::array::from_fn(|i| Dual1::var(x[i], i));
        let f = self.0.vector_field(&d);
        SMatrix::from_fn(|r, c| f[r].g[c])
    }
}

impl<const N: usize> LaneField<N> for FieldInX<'_, N> {
    #[inline(always)]
    fn field_lanes<const L: usize>(&self, x: &[[f64; L]; N], out: &mut [[f64; L]; N]) {
        self.0.field_lanes(x, out);
    }

    #[inline(always)]
    fn jacobian_lanes<const L: usize>(
        &self,
        x: &[[f64; L]; N],
        out: &mut [[[f64; L]; N]; N],
    ) -> bool {
        self.0.jacobian_in_lanes(x, out);
        true
    }
}

/// The implicit midpoint rule in x of a [`LogClassical`] as a [`LaneStepper`]: the classical
/// midpoint's Newton solve on [`FieldInX`] lane by lane (the Euler-midpoint start, the
/// residual, the lane-wide solve, masked convergence), then each converged lane's orthant
/// check. The scalar step is this with one lane, so every lane has its bits.
pub struct LogMidpoint<'a, const N: usize>(&'a LogClassical<N>);

impl<const N: usize> StepMap<N> for LogMidpoint<'_, N>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    type Workspace = ();
    fn workspace(&self) {}
    fn step(&self, h: f64, s: &mut [f64; N], ws: &mut ()) -> StepResult {
        self.0.step(h, s, ws)
    }
}

impl<const N: usize> LaneStepper<N> for LogMidpoint<'_, N>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    const REPORTS: bool = true;

    /// Measured: paired blocks 0.84× (N = 3) and 0.78× (N = 5) the time of AVX2 blocks, but
    /// 1.32× at N = 2 (PNN's system, whose block AVX2 already holds in registers).
    #[inline(always)]
    fn avx512_paired(&self) -> bool {
        N >= 3
    }

    #[inline(always)]
    fn step_lanes_reporting<const L: usize>(
        &self,
        h: f64,
        x: &mut [[f64; L]; N],
        live: &[bool; L],
        result: &mut [StepResult; L],
    ) {
        let midpoint = ImplicitMidpoint {
            system: FieldInX(&self.0.system),
            newton: self.0.newton,
        };
        midpoint.step_lanes_reporting(h, x, live, result);
        for l in 0..L {
            if !live[l] || result[l].is_err() {
                continue;
            }
            let state: [f64; N] = std::array::from_fn(|i| x[i][l]);
            if let Err(e) = in_orthant(&state) {
                result[l] = Err(e);
            }
        }
    }
}

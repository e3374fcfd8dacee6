//! Log-canonical structures π_ij(x) = c_ij x_i x_j on the positive orthant.
//!
//! In q = ln x the bracket is the constant antisymmetric matrix c and the exact symplectic
//! groupoid is linear: with P_j = x_j p_j, sou = β(q, P) = q − ½ c P and tar = α(q, P) = q + ½ c P.
//! Hamiltonians are log-polynomials H = Σ_m a_m e^{e_m·q} − b·q, so every Hamilton–Jacobi Taylor
//! term S_k (k ≥ 2) is a polynomial in y = e^q ([`ExpPolynomial`]).
//!
//! Coordinates: the bisection stepper and the splittings work in q (a step never leaves the
//! orthant, only overflows); RK4 and the implicit midpoint rule work in x, where a step can leave
//! the orthant, which is a [`StepFailure::OutOfDomain`].

// Index loops over small fixed-size vectors and matrices read as the formulas they implement.
#![allow(clippy::needless_range_loop)]

use nalgebra::{Const, DimMin, SMatrix, SVector};

use crate::dual::{Dual1, Jet2, Scalar};
use crate::error::{CoreError, StepFailure};
use crate::exp::{exp_lanes, EXP_MAX, EXP_MIN};
use crate::generating::{GeneratingFunction, Workspace};
use crate::lanes::LaneStepper;
use crate::realization::{Generating, Realization, RealizationStepper};
use crate::step::{NewtonOptions, StepMap, StepResult, StepStats};
use crate::stepper::So3Lanes;

/// The structure matrix c of π_ij = c_ij x_i x_j: finite and antisymmetric.
#[derive(Clone, Debug, PartialEq)]
pub struct LogCanonical<const N: usize> {
    c: [[f64; N]; N],
}

impl<const N: usize> LogCanonical<N> {
    pub fn new(c: [[f64; N]; N]) -> Result<Self, CoreError> {
        for i in 0..N {
            for j in 0..N {
                if !c[i][j].is_finite() || c[i][j] != -c[j][i] {
                    return Err(CoreError::Invalid(format!(
                        "c must be finite and antisymmetric: c[{i}][{j}] = {}, c[{j}][{i}] = {}",
                        c[i][j], c[j][i]
                    )));
                }
            }
        }
        Ok(LogCanonical { c })
    }

    pub fn c(&self) -> &[[f64; N]; N] {
        &self.c
    }

    /// q ± ½ c P.
    #[inline(always)]
    fn shift<T: Scalar>(&self, x: &[T; N], p: &[T; N], sign: f64) -> [T; N] {
        std::array::from_fn(|i| {
            let mut acc = p[i];
            for j in 0..N {
                if self.c[i][j] != 0.0 {
                    acc.add_scaled(&x[j], 0.5 * sign * self.c[i][j]);
                }
            }
            acc
        })
    }
}

/// Not an so(3) chart: the bisection stepper takes its generic Newton path here.
impl<const N: usize> So3Lanes<N> for LogCanonical<N> {}

/// In log coordinates: fibre x = P, base p = q.
impl<const N: usize> Realization<N> for LogCanonical<N> {
    #[inline]
    fn sou<T: Scalar>(&self, x: &[T; N], p: &[T; N]) -> Result<[T; N], StepFailure> {
        Ok(self.shift(x, p, -1.0))
    }
    #[inline]
    fn tar<T: Scalar>(&self, x: &[T; N], p: &[T; N]) -> Result<[T; N], StepFailure> {
        Ok(self.shift(x, p, 1.0))
    }
    /// sou = tar − c P, so q_{k+1} = q_k − c P: k·q is kept for every k with kᵀc = 0 whatever
    /// Newton's residual (which sou(P, q) would carry into the Casimirs, one-sided from step to
    /// step).
    #[inline]
    fn sou_after_solve(
        &self,
        x: &[f64; N],
        _p: &[f64; N],
        target: &[f64; N],
    ) -> Result<[f64; N], StepFailure> {
        Ok(std::array::from_fn(|i| {
            let mut acc = target[i];
            for j in 0..N {
                acc -= self.c[i][j] * x[j];
            }
            acc
        }))
    }
}

/// One term c · t^k · e^{e·q} = c t^k y^e.
#[derive(Clone, Debug, PartialEq)]
pub struct ExpMonomial<const N: usize> {
    pub t_power: u32,
    pub exponents: [i32; N],
    pub coeff: f64,
}

/// S(t, q) = Σ c t^k y^e + t · (linear · q): the Taylor-HJ generating function of a log-canonical
/// system (the linear part is S₁'s −(−b·q)).
#[derive(Clone, Debug, PartialEq)]
pub struct ExpPolynomial<const N: usize> {
    terms: Vec<ExpMonomial<N>>,
    linear: [f64; N],
}

/// Largest |exponent| of a term.
pub const MAX_EXPONENT: i32 = 256;

impl<const N: usize> ExpPolynomial<N> {
    pub fn new(terms: Vec<ExpMonomial<N>>, linear: [f64; N]) -> Result<Self, CoreError> {
        if let Some(m) = terms
            .iter()
            .find(|m| !m.coeff.is_finite() || m.exponents.iter().any(|e| e.abs() > MAX_EXPONENT))
        {
            return Err(CoreError::Invalid(format!(
                "generating term {m:?} has a non-finite coefficient or an exponent over \
                 {MAX_EXPONENT}"
            )));
        }
        if linear.iter().any(|v| !v.is_finite()) {
            return Err(CoreError::Invalid("linear part must be finite".into()));
        }
        Ok(ExpPolynomial { terms, linear })
    }

    /// S(t, ·) at q with its q-gradient and q-Hessian, in closed form: ∂/∂q_i y^e = e_i y^e.
    pub fn jet_at(&self, t: f64, q: &[f64; N]) -> Jet2<N> {
        let y: [f64; N] = std::array::from_fn(|i| q[i].exp());
        let mut out = Jet2::<N>::default();
        for m in &self.terms {
            let mut w = m.coeff * t.powi(m.t_power as i32);
            for i in 0..N {
                if m.exponents[i] != 0 {
                    w *= y[i].powi(m.exponents[i]);
                }
            }
            out.v += w;
            let e = m.exponents.map(f64::from);
            for i in 0..N {
                out.g[i] += w * e[i];
            }
            let packed = out.packed_mut();
            let mut k = 0;
            for a in 0..N {
                for b in a..N {
                    packed[k] += w * e[a] * e[b];
                    k += 1;
                }
            }
        }
        for i in 0..N {
            out.v += t * self.linear[i] * q[i];
            out.g[i] += t * self.linear[i];
        }
        out
    }
}

impl<const N: usize> Generating<N> for ExpPolynomial<N> {
    type Workspace = ();
    fn workspace(&self) {}
    fn jet(&self, t: f64, p: &[f64; N], _: &mut ()) -> Jet2<N> {
        self.jet_at(t, p)
    }
    fn gradient(&self, t: f64, p: &[f64; N], _: &mut ()) -> Dual1<N> {
        let j = self.jet_at(t, p);
        Dual1 { v: j.v, g: j.g }
    }
}

/// A learned generating function on the log-canonical groupoid: exact Taylor terms
/// ([`ExpPolynomial`]) plus t^m · N(t, q), the network term of a [`GeneratingFunction`] with
/// plain inputs (t, q) and no polynomial part. Both derivatives are exact: closed form for the
/// Taylor terms, forward-mode duals through the MLP.
#[derive(Clone, Debug, PartialEq)]
pub struct LearnedExp<const N: usize> {
    pub taylor: ExpPolynomial<N>,
    pub network: GeneratingFunction<N>,
}

impl<const N: usize> LearnedExp<N> {
    /// Refuses a network part with polynomial terms of its own (they would be read as
    /// polynomials in q, not in y = e^q).
    pub fn new(
        taylor: ExpPolynomial<N>,
        network: GeneratingFunction<N>,
    ) -> Result<Self, CoreError> {
        if !network.polynomial.terms.is_empty() {
            return Err(CoreError::Invalid(
                "the network part of a log-canonical generating function must hold no \
                 polynomial terms (the Taylor terms are exponential monomials)"
                    .into(),
            ));
        }
        Ok(LearnedExp { taylor, network })
    }
}

impl<const N: usize> Generating<N> for LearnedExp<N> {
    type Workspace = Workspace<N>;
    fn workspace(&self) -> Workspace<N> {
        self.network.workspace()
    }
    fn jet(&self, t: f64, p: &[f64; N], ws: &mut Workspace<N>) -> Jet2<N> {
        self.taylor.jet_at(t, p) + self.network.jet(t, p, ws)
    }
    fn gradient(&self, t: f64, p: &[f64; N], ws: &mut Workspace<N>) -> Dual1<N> {
        let taylor = self.taylor.jet_at(t, p);
        let net = self.network.gradient(t, p, ws);
        Dual1 {
            v: taylor.v + net.v,
            g: std::array::from_fn(|i| taylor.g[i] + net.g[i]),
        }
    }
}

/// The learned bisection integrator of a log-canonical structure, state q = ln x.
pub type LearnedLogBisection<const N: usize> =
    RealizationStepper<N, LogCanonical<N>, LearnedExp<N>>;

/// A log-canonical system: the structure c and H = Σ_m a_m x^{e_m} − Σ_i b_i ln x_i
/// (exponents ≥ 0), ẋ_i = x_i Σ_j c_ij (x_j ∂H/∂x_j) = x_i Σ_j c_ij (Σ_m a_m e_mj x^{e_m} − b_j).
#[derive(Clone, Debug, PartialEq)]
pub struct LogSystem<const N: usize> {
    pub structure: LogCanonical<N>,
    terms: Vec<([u32; N], f64)>,
    b: [f64; N],
}

/// Largest exponent of a Hamiltonian monomial.
pub const MAX_HAMILTONIAN_EXPONENT: u32 = 16;

impl<const N: usize> LogSystem<N> {
    pub fn new(
        structure: LogCanonical<N>,
        terms: Vec<([u32; N], f64)>,
        b: [f64; N],
    ) -> Result<Self, CoreError> {
        if let Some((e, a)) = terms.iter().find(|(e, a)| {
            !a.is_finite()
                || e.iter().any(|&k| k > MAX_HAMILTONIAN_EXPONENT)
                || e.iter().all(|&k| k == 0)
        }) {
            return Err(CoreError::Invalid(format!(
                "Hamiltonian term {a} x^{e:?} needs a finite coefficient and exponents in \
                 0..={MAX_HAMILTONIAN_EXPONENT}, not all zero"
            )));
        }
        if b.iter().any(|v| !v.is_finite()) {
            return Err(CoreError::Invalid("b must be finite".into()));
        }
        Ok(LogSystem {
            structure,
            terms,
            b,
        })
    }

    /// x_j ∂H/∂x_j = ∂H/∂q_j, a polynomial in x.
    #[inline]
    fn log_gradient<T: Scalar>(&self, x: &[T; N]) -> [T; N] {
        let mut g: [T; N] = std::array::from_fn(|j| T::cst(-self.b[j]));
        for (e, a) in &self.terms {
            let mut m = T::cst(*a);
            for i in 0..N {
                if e[i] > 0 {
                    m = m * x[i].powi(e[i] as i32);
                }
            }
            for j in 0..N {
                if e[j] > 0 {
                    g[j].add_scaled(&m, f64::from(e[j]));
                }
            }
        }
        g
    }

    /// ẋ = π(x)∇H(x), for any scalar.
    pub fn vector_field<T: Scalar>(&self, x: &[T; N]) -> [T; N] {
        let g = self.log_gradient(x);
        let c = self.structure.c();
        std::array::from_fn(|i| {
            let mut acc = T::cst(0.0);
            for j in 0..N {
                if c[i][j] != 0.0 {
                    acc.add_scaled(&g[j], c[i][j]);
                }
            }
            x[i] * acc
        })
    }

    /// [`LogSystem::vector_field`] at L states, lane by lane: the explicit steppers' field
    /// (RK4 takes it for one trajectory too, with L = 1, so every lane has the scalar bits).
    #[inline(always)]
    fn field_lanes<const L: usize>(&self, x: &[[f64; L]; N], out: &mut [[f64; L]; N]) {
        let mut g: [[f64; L]; N] = std::array::from_fn(|j| [-self.b[j]; L]);
        for (e, a) in &self.terms {
            let mut m = [*a; L];
            for i in 0..N {
                if e[i] > 0 {
                    let power = pow_lanes(&x[i], e[i]);
                    for l in 0..L {
                        m[l] *= power[l];
                    }
                }
            }
            for j in 0..N {
                if e[j] > 0 {
                    let ej = f64::from(e[j]);
                    for l in 0..L {
                        g[j][l] += m[l] * ej;
                    }
                }
            }
        }
        let c = self.structure.c();
        for i in 0..N {
            let mut acc = [0.0; L];
            for j in 0..N {
                if c[i][j] != 0.0 {
                    for l in 0..L {
                        acc[l] += g[j][l] * c[i][j];
                    }
                }
            }
            for l in 0..L {
                out[i][l] = x[i][l] * acc[l];
            }
        }
    }

    /// H' of the one-variable parts: the flow of H_i(q_i) = Σ_{m ∈ i} a_m e^{e_mi q_i} − b_i q_i
    /// is q_j += t c_ji H_i'(q_i) (q_i fixed since c_ii = 0). None unless H is separable (every
    /// monomial in one variable).
    fn separable(&self) -> Option<Vec<(usize, u32, f64)>> {
        let mut parts = Vec::with_capacity(self.terms.len());
        for (e, a) in &self.terms {
            let vars: Vec<usize> = (0..N).filter(|&i| e[i] > 0).collect();
            if vars.len() != 1 {
                return None;
            }
            parts.push((vars[0], e[vars[0]], *a));
        }
        Some(parts)
    }
}

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

/// x^e at L lanes by binary powering: the same multiplications for every lane (e is the
/// term's, not the lane's), the loop over e's bits outside the lanes so that they vectorise.
#[inline(always)]
fn pow_lanes<const L: usize>(x: &[f64; L], mut e: u32) -> [f64; L] {
    let (mut base, mut acc) = (*x, [1.0; L]);
    loop {
        if e & 1 == 1 {
            for l in 0..L {
                acc[l] *= base[l];
            }
        }
        e >>= 1;
        if e == 0 {
            return acc;
        }
        for l in 0..L {
            base[l] *= base[l];
        }
    }
}

/// Powers y⁰ … y^POWER_TABLE of each coordinate of a generating function's evaluation, lane by
/// lane; larger exponents take [`pow_lanes`].
const POWER_TABLE: usize = 8;

/// Suzuki's weight p = 1/(4 − 4^{1/3}).
fn suzuki_p() -> f64 {
    1.0 / (4.0 - 4f64.powf(1.0 / 3.0))
}

fn in_orthant<const N: usize>(x: &[f64; N]) -> Result<(), StepFailure> {
    if x.iter().any(|v| !v.is_finite()) {
        Err(StepFailure::NonFinite)
    } else if x.iter().any(|&v| v <= 0.0) {
        Err(StepFailure::OutOfDomain)
    } else {
        Ok(())
    }
}

/// q must stay finite and x = e^q representable (neither 0 nor ∞).
fn log_state_in_orthant<const N: usize>(q: &[f64; N]) -> Result<(), StepFailure> {
    if q.iter().any(|v| !v.is_finite()) {
        return Err(StepFailure::NonFinite);
    }
    in_orthant(&q.map(f64::exp))
}

/// The Taylor-HJ (or any [`ExpPolynomial`]) bisection integrator of a log-canonical structure,
/// state q = ln x.
pub type LogBisection<const N: usize> = RealizationStepper<N, LogCanonical<N>, ExpPolynomial<N>>;

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

    #[inline(always)]
    fn rk4_lanes<const L: usize>(&self, h: f64, x: &mut [[f64; L]; N]) {
        let f = |y: &[[f64; L]; N]| {
            let mut out = [[0.0; L]; N];
            self.system.field_lanes(y, &mut out);
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

    /// z = x + h f((x + z)/2) by Newton from z = x + h f(x).
    fn midpoint(&self, h: f64, x: &mut [f64; N]) -> StepResult {
        let x0 = *x;
        let f0 = self.system.vector_field(&x0);
        let mut z: [f64; N] = std::array::from_fn(|i| x0[i] + h * f0[i]);
        let mut iterations = 0;
        loop {
            if iterations >= self.newton.max_iter {
                return Err(StepFailure::NotConverged);
            }
            let m: [Dual1<N>; N] = std::array::from_fn(|i| {
                let mut d = Dual1::var(0.5 * (x0[i] + z[i]), i);
                d.g[i] = 0.5;
                d
            });
            let fm = self.system.vector_field(&m);
            let jac =
                SMatrix::<f64, N, N>::from_fn(|r, c| f64::from(u8::from(r == c)) - h * fm[r].g[c]);
            let res = SVector::<f64, N>::from_fn(|i, _| x0[i] + h * fm[i].v - z[i]);
            let delta = jac.lu().solve(&res).ok_or(StepFailure::SingularJacobian)?;
            if !delta.iter().all(|d| d.is_finite()) {
                return Err(StepFailure::NonFinite);
            }
            for i in 0..N {
                z[i] += delta[i];
            }
            iterations += 1;
            let scale = z.iter().fold(0.0f64, |a, v| a.max(v.abs())).max(1e-300);
            if delta.amax() <= self.newton.tol * scale {
                let fm = self
                    .system
                    .vector_field(&std::array::from_fn(|i| 0.5 * (x0[i] + z[i])));
                let residual = (0..N)
                    .map(|i| (x0[i] + h * fm[i] - z[i]).abs())
                    .fold(0.0, f64::max);
                *x = z;
                return Ok(StepStats {
                    iterations,
                    residual,
                });
            }
        }
    }
}

impl<const N: usize> StepMap<N> for LogClassical<N>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    type Workspace = ();

    fn workspace(&self) {}

    fn step(&self, h: f64, s: &mut [f64; N], _: &mut ()) -> StepResult {
        let mut stats = StepStats::default();
        if self.method == LogMethod::Midpoint {
            stats = self.midpoint(h, s)?;
        } else {
            let mut lane: [[f64; 1]; N] = s.map(|v| [v]);
            self.step_explicit_lanes(h, &mut lane);
            *s = lane.map(|v| v[0]);
        }
        self.domain(s)?;
        Ok(stats)
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

    #[inline(always)]
    fn step_lanes<const L: usize>(&self, h: f64, mu: &mut [[f64; L]; N]) {
        self.0.step_explicit_lanes(h, mu);
    }

    #[inline(always)]
    fn maybe_outside_lanes<const L: usize>(&self, mu: &[[f64; L]; N], flag: &mut [bool; L]) {
        // In q: e^q can reach 0 or ∞ only outside exp's vectorised range. In x: x ≤ 0 (NaN
        // flags too; the block loop has already sent non-finite lanes to NonFinite).
        let in_log = self.0.method.in_log();
        for coordinate in mu {
            for l in 0..L {
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

// ---------------------------------------------------------------------------------------------
// Taylor-HJ in SIMD lanes
// ---------------------------------------------------------------------------------------------

impl<const N: usize> ExpPolynomial<N> {
    /// ∇S(t, ·) at L points q, and with `HESS` its Hessian (`hs[a][b][l]`, both triangles),
    /// lane by lane: y = e^q once per coordinate, each term's y^e by binary powering.
    #[inline(always)]
    fn derivatives_lanes<const L: usize, const HESS: bool>(
        &self,
        t: f64,
        t_powers: &[f64; T_POWERS],
        q: &[[f64; L]; N],
        g: &mut [[f64; L]; N],
        hs: &mut [[[f64; L]; N]; N],
    ) {
        // pw[i][k] = y_i^k for k ≤ POWER_TABLE, y = e^q, by successive products.
        let mut pw = [[[1.0; L]; POWER_TABLE + 1]; N];
        for i in 0..N {
            exp_lanes(&q[i], &mut pw[i][1]);
            for k in 2..=POWER_TABLE {
                for l in 0..L {
                    pw[i][k][l] = pw[i][k - 1][l] * pw[i][1][l];
                }
            }
        }
        *g = [[0.0; L]; N];
        if HESS {
            *hs = [[[0.0; L]; N]; N];
        }
        for m in &self.terms {
            let tk = t_powers
                .get(m.t_power as usize)
                .copied()
                .unwrap_or_else(|| t.powi(m.t_power as i32));
            let mut w = [m.coeff * tk; L];
            for i in 0..N {
                // The exponent is the term's, not the lane's: one loop per case, so no lane
                // divides for a positive exponent.
                let e = m.exponents[i];
                let k = e.unsigned_abs() as usize;
                if e == 0 {
                    continue;
                }
                let power = if k <= POWER_TABLE {
                    pw[i][k]
                } else {
                    pow_lanes(&pw[i][1], e.unsigned_abs())
                };
                if e > 0 {
                    for l in 0..L {
                        w[l] *= power[l];
                    }
                } else {
                    for l in 0..L {
                        w[l] *= 1.0 / power[l];
                    }
                }
            }
            let e = m.exponents.map(f64::from);
            for a in 0..N {
                if e[a] == 0.0 {
                    continue;
                }
                for l in 0..L {
                    g[a][l] += w[l] * e[a];
                }
                if HESS {
                    for b in a..N {
                        let eab = e[a] * e[b];
                        if eab != 0.0 {
                            for l in 0..L {
                                hs[a][b][l] += w[l] * eab;
                            }
                        }
                    }
                }
            }
        }
        for i in 0..N {
            let lt = t * self.linear[i];
            for l in 0..L {
                g[i][l] += lt;
            }
        }
        if HESS {
            for a in 0..N {
                for b in 0..a {
                    hs[a][b] = hs[b][a];
                }
            }
        }
    }
}

/// t⁰ … t^(T_POWERS − 1), computed once a step (larger powers of t take `powi`).
const T_POWERS: usize = 16;

/// The table of powers of t that [`ExpPolynomial::derivatives_lanes`] reads.
#[inline(always)]
fn t_power_table(t: f64) -> [f64; T_POWERS] {
    let mut table = [1.0; T_POWERS];
    for k in 1..T_POWERS {
        table[k] = table[k - 1] * t;
    }
    table
}

/// δ = J⁻¹ f at L lanes by cofactors (N = 2 or 3); `ok[l]` is false where det J is 0 or not
/// finite.
#[inline(always)]
fn solve_small_lanes<const N: usize, const L: usize>(
    j: &[[[f64; L]; N]; N],
    f: &[[f64; L]; N],
    delta: &mut [[f64; L]; N],
    ok: &mut [bool; L],
) {
    debug_assert!(N == 2 || N == 3, "cofactor solves are for N = 2 and 3");
    for l in 0..L {
        let m: [[f64; N]; N] = std::array::from_fn(|r| std::array::from_fn(|c| j[r][c][l]));
        let (adj, det): ([[f64; N]; N], f64) = if N == 2 {
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

/// Taylor-HJ on the log-canonical groupoid ([`LogBisection`] of an [`ExpPolynomial`], with the
/// orthant check of [`OrthantChecked`]) in SIMD lanes, for N = 2 and 3: the Newton solve of
/// q + ½c∇S(q) = q_k runs lane by lane (exact gradient and Hessian of S from y = e^q, the
/// cofactor inverse of J = I + ½c∇²S, masked convergence), then q_{k+1} = q_k − c∇S(q) (the
/// same as q − ½c∇S(q) at the solution, and exactly Casimir-preserving at any iterate). The
/// scalar step is this with one lane, so every lane has the scalar bits.
pub struct LogTaylorLanes<'a, const N: usize>(&'a LogBisection<N>);

impl<const N: usize> LogBisection<N> {
    /// This stepper in SIMD lanes, for N = 2 and 3 (None otherwise).
    pub fn lanes(&self) -> Option<LogTaylorLanes<'_, N>> {
        (N == 2 || N == 3).then_some(LogTaylorLanes(self))
    }
}

impl<const N: usize> LaneStepper<N> for LogTaylorLanes<'_, N> {
    const REPORTS: bool = true;

    #[inline(always)]
    fn step_lanes_reporting<const L: usize>(
        &self,
        h: f64,
        mu: &mut [[f64; L]; N],
        live: &[bool; L],
        result: &mut [StepResult; L],
    ) {
        let s = self.0;
        let c = s.realization.c();
        let half_c: [[f64; N]; N] = std::array::from_fn(|i| c[i].map(|v| 0.5 * v));
        let (tol, max_iter) = (s.newton.tol, s.newton.max_iter);
        let t_powers = t_power_table(h);
        let target = *mu;
        let mut p = target;
        let mut active = *live;
        let mut converged = [false; L];
        let mut iterations = [0u32; L];
        let (mut g, mut hs) = ([[0.0; L]; N], [[[0.0; L]; N]; N]);
        while active.contains(&true) {
            s.generating
                .derivatives_lanes::<L, true>(h, &t_powers, &p, &mut g, &mut hs);
            // f = q_k − (q + ½c∇S), J = I + ½c∇²S.
            let mut f = [[0.0; L]; N];
            let mut j = [[[0.0; L]; N]; N];
            for i in 0..N {
                for l in 0..L {
                    let mut tar = p[i][l];
                    for k in 0..N {
                        tar += half_c[i][k] * g[k][l];
                    }
                    f[i][l] = target[i][l] - tar;
                }
                for r in 0..N {
                    for l in 0..L {
                        let mut acc = if i == r { 1.0 } else { 0.0 };
                        for k in 0..N {
                            acc += half_c[i][k] * hs[k][r][l];
                        }
                        j[i][r][l] = acc;
                    }
                }
            }
            let mut delta = [[0.0; L]; N];
            let mut solvable = [true; L];
            solve_small_lanes(&j, &f, &mut delta, &mut solvable);
            for l in 0..L {
                if !active[l] {
                    continue;
                }
                let finite =
                    (0..N).all(|a| g[a][l].is_finite() && (0..N).all(|b| hs[a][b][l].is_finite()));
                let failure = if !finite {
                    Some(StepFailure::NonFinite)
                } else if iterations[l] >= max_iter {
                    Some(StepFailure::NotConverged)
                } else if !solvable[l] || !(0..N).all(|a| delta[a][l].is_finite()) {
                    Some(StepFailure::SingularJacobian)
                } else {
                    None
                };
                if let Some(failure) = failure {
                    result[l] = Err(failure);
                    active[l] = false;
                    continue;
                }
                let (mut dmax, mut pmax) = (0.0f64, 0.0f64);
                for a in 0..N {
                    p[a][l] += delta[a][l];
                    dmax = dmax.max(delta[a][l].abs());
                    pmax = pmax.max(p[a][l].abs());
                }
                iterations[l] += 1;
                if dmax <= tol * pmax.max(s.scale_floor) {
                    active[l] = false;
                    converged[l] = true;
                }
            }
        }
        s.generating
            .derivatives_lanes::<L, false>(h, &t_powers, &p, &mut g, &mut hs);
        for l in 0..L {
            if !converged[l] {
                continue;
            }
            if !(0..N).all(|a| g[a][l].is_finite()) {
                result[l] = Err(StepFailure::NonFinite);
                continue;
            }
            let (gl, pl, tl): ([f64; N], [f64; N], [f64; N]) = (
                std::array::from_fn(|i| g[i][l]),
                std::array::from_fn(|i| p[i][l]),
                std::array::from_fn(|i| target[i][l]),
            );
            let mut residual = 0.0f64;
            for i in 0..N {
                let mut tar = pl[i];
                for k in 0..N {
                    tar += half_c[i][k] * gl[k];
                }
                residual = residual.max((tar - tl[i]).abs());
            }
            // q_k − c∇S rather than q − ½c∇S: Newton's residual stays out of the Casimirs.
            let out = match s.realization.sou_after_solve(&gl, &pl, &tl) {
                Ok(out) => out,
                Err(e) => {
                    result[l] = Err(e);
                    continue;
                }
            };
            for i in 0..N {
                mu[i][l] = out[i];
            }
            result[l] = log_state_in_orthant(&out).map(|()| StepStats {
                iterations: iterations[l],
                residual,
            });
        }
    }
}

impl<const N: usize> StepMap<N> for LogTaylorLanes<'_, N> {
    type Workspace = ();
    fn workspace(&self) {}
    fn step(&self, h: f64, q: &mut [f64; N], _: &mut ()) -> StepResult {
        let mut lane: [[f64; 1]; N] = q.map(|v| [v]);
        let mut result = [Ok(StepStats::default())];
        self.step_lanes_reporting(h, &mut lane, &[true], &mut result);
        *q = lane.map(|v| v[0]);
        result[0]
    }
}

#[cfg(test)]
mod learned_tests {
    //! The learned generating function and its model file: the jet is the sum of its parts, a
    //! random network keeps the monomial Casimir to round-off, and files of another or an
    //! unknown structure are refused by name.

    use std::collections::HashMap;

    use safetensors::tensor::TensorView;
    use safetensors::{serialize, Dtype};

    use super::*;
    use crate::generating::{Layer, Mlp, MlpInputs, Polynomial};
    use crate::model::{LogModel, Model, FORMAT};

    /// A fixed tanh MLP R^{1+3} → R with one hidden layer of 5 (weights from a sine pattern).
    fn mlp() -> Mlp {
        let w0: Vec<f64> = (0..20).map(|k| 0.7 * (1.3 * k as f64).sin()).collect();
        let b0: Vec<f64> = (0..5).map(|k| 0.2 * (0.9 * k as f64).cos()).collect();
        let w1: Vec<f64> = (0..5).map(|k| 0.5 * (2.1 * k as f64 + 0.3).sin()).collect();
        Mlp::new(vec![
            Layer::new(4, 5, w0, b0).unwrap(),
            Layer::new(5, 1, w1, vec![0.1]).unwrap(),
        ])
        .unwrap()
    }

    /// S = −t(x₁ + x₂ + x₃) + t b·q + t³ N(t, q) on the 3D structure with Casimir Σ q_i.
    fn learned() -> (LogCanonical<3>, LearnedExp<3>) {
        let c = [[0.0, 1.0, -1.0], [-1.0, 0.0, 1.0], [1.0, -1.0, 0.0]];
        let terms = (0..3)
            .map(|i| {
                let mut exponents = [0; 3];
                exponents[i] = 1;
                ExpMonomial {
                    t_power: 1,
                    exponents,
                    coeff: -1.0,
                }
            })
            .collect();
        let taylor = ExpPolynomial::new(terms, [1.0, 1.5, 2.0]).unwrap();
        let network =
            GeneratingFunction::new(Polynomial::default(), Some(mlp()), 3, MlpInputs::Plain)
                .unwrap();
        (
            LogCanonical::new(c).unwrap(),
            LearnedExp::new(taylor, network).unwrap(),
        )
    }

    #[test]
    fn jet_is_the_sum_of_the_taylor_and_network_jets() {
        let (_, s) = learned();
        let mut ws = Generating::workspace(&s);
        let q = [0.2, -0.4, 0.7];
        let jet = Generating::jet(&s, 0.1, &q, &mut ws);
        let sum = s.taylor.jet_at(0.1, &q) + s.network.jet(0.1, &q, &mut ws);
        assert_eq!(jet, sum);
        let grad = Generating::gradient(&s, 0.1, &q, &mut ws);
        for i in 0..3 {
            assert!((grad.g[i] - jet.g[i]).abs() <= 1e-15);
        }
    }

    #[test]
    fn random_network_keeps_the_casimir_to_round_off() {
        let (realization, generating) = learned();
        let stepper = OrthantChecked(LearnedLogBisection {
            generating,
            realization,
            newton: NewtonOptions::default(),
            scale_floor: 1.0,
        });
        let mut ws = stepper.workspace();
        let mut q = [0.1, -0.2, 0.3];
        let c0: f64 = q.iter().sum();
        for _ in 0..1000 {
            stepper.step(0.05, &mut q, &mut ws).unwrap();
        }
        assert!((q.iter().sum::<f64>() - c0).abs() <= 1e-12);
    }

    /// A log-canonical model file: the 2D structure, S = −t(x₁ + x₂) + t(1, 2)·q, and the
    /// given metadata.
    fn file(meta: &[(&str, &str)]) -> Vec<u8> {
        let f64s = |v: &[f64]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
        let c = f64s(&[0.0, 1.0, -1.0, 0.0]);
        let powers: Vec<u8> = [1i64, 1, 0, 1, 0, 1]
            .iter()
            .flat_map(|x| x.to_le_bytes())
            .collect();
        let coeffs = f64s(&[-1.0, -1.0]);
        let linear = f64s(&[1.0, 2.0]);
        let views = vec![
            (
                "structure.c",
                TensorView::new(Dtype::F64, vec![2, 2], &c).unwrap(),
            ),
            (
                "poly.powers",
                TensorView::new(Dtype::I64, vec![2, 3], &powers).unwrap(),
            ),
            (
                "poly.coeffs",
                TensorView::new(Dtype::F64, vec![2], &coeffs).unwrap(),
            ),
            (
                "poly.linear",
                TensorView::new(Dtype::F64, vec![2], &linear).unwrap(),
            ),
        ];
        let meta: HashMap<String, String> = meta
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect();
        serialize(views, Some(meta)).unwrap()
    }

    #[test]
    fn model_files_name_their_structure() {
        let good = file(&[("format", FORMAT), ("structure", "log_canonical")]);
        let model = LogModel::from_bytes(&good).unwrap();
        assert_eq!((model.dim, model.n_polynomial_terms()), (2, 2));
        let err = Model::from_bytes(&good).unwrap_err().to_string();
        assert!(err.contains("structure is 'log_canonical'"), "{err}");
        let odd = file(&[("format", FORMAT), ("structure", "nambu")]);
        let err = LogModel::from_bytes(&odd).unwrap_err().to_string();
        assert!(err.contains("unknown model structure 'nambu'"), "{err}");
        let none = file(&[("format", FORMAT)]);
        let err = LogModel::from_bytes(&none).unwrap_err().to_string();
        assert!(err.contains("'structure' is missing"), "{err}");
    }
}

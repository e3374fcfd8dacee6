//! Taylor-HJ on the log-canonical groupoid: generating functions that are polynomials in
//! y = e^q ([`ExpPolynomial`]), their bisection integrator, and its Newton solves in SIMD lanes.

// Index loops over small fixed-size vectors and matrices read as the formulas they implement.
#![allow(clippy::needless_range_loop)]

use super::{log_state_in_orthant, pow_lanes, LogCanonical, PREDICT_MAX_SHIFT};
use crate::dual::{Dual1, Jet2, Scalar};
use crate::error::{CoreError, StepFailure};
use crate::exp::exp_lanes;
use crate::generating::LaneRow;
use crate::lanes::{solve_small_lanes, FullNewton, LaneStepper};
use crate::memory::try_collect;
use crate::realization::{Generating, Realization};
use crate::step::{StepMap, StepResult, StepStats};
use crate::stepper::BisectionStepper;

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
    /// The terms compiled once for [`ExpPolynomial::taylor_lanes`]: each term's variables with a
    /// nonzero exponent, where every evaluation tested all N exponents and all N(N+1)/2 pairs.
    planned: Vec<PlannedExp<N>>,
    /// Each planned term's exponent of every coordinate, 0 where it lacks one, for the
    /// accumulation in registers; empty above [`DENSE_MAX_DIM`].
    dense_e: Vec<[f64; N]>,
    /// The largest |exponent| of each coordinate: the rows of the table of powers to build.
    max_power: [u32; N],
}

/// One term c t^k Π y_v^e_v as the lanes evaluate it: its `count` variables with a nonzero
/// exponent, in increasing order, with the exponent as a float and its size.
#[derive(Clone, Copy, Debug, PartialEq)]
struct PlannedExp<const N: usize> {
    t_power: u32,
    coeff: f64,
    count: usize,
    var: [usize; N],
    e: [f64; N],
    size: [u32; N],
}

/// Up to this N every term adds to all of ∇S and ∇²S (zeros included) in loops over N with
/// constant indices, so the accumulators stay in registers across the terms; with a term's own
/// variables as run-time indices they were stored and reloaded at every term, a chain through
/// memory that took a fifth of PNN's Taylor step. Adding w·0 = ±0 to a sum that started at +0
/// leaves its bits, so both ways give the same numbers. Above it the sparse sums stay: a 5-D
/// term has 2–3 of its 5 variables, and 15 Hessian sums of two registers each would not fit.
const DENSE_MAX_DIM: usize = 3;

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
        let mut max_power = [0u32; N];
        for m in &terms {
            for i in 0..N {
                max_power[i] = max_power[i].max(m.exponents[i].unsigned_abs());
            }
        }
        let planned = try_collect(
            terms.len(),
            terms.iter().map(|m| {
                let mut term = PlannedExp {
                    t_power: m.t_power,
                    coeff: m.coeff,
                    count: 0,
                    var: [0; N],
                    e: [0.0; N],
                    size: [0; N],
                };
                for (i, &e) in m.exponents.iter().enumerate() {
                    if e != 0 {
                        let j = term.count;
                        (term.var[j], term.e[j], term.size[j]) =
                            (i, f64::from(e), e.unsigned_abs());
                        term.count += 1;
                    }
                }
                term
            }),
            "the generating function's terms",
        )?;
        let dense_e = if N <= DENSE_MAX_DIM {
            try_collect(
                terms.len(),
                terms.iter().map(|m| m.exponents.map(f64::from)),
                "the generating function's terms",
            )?
        } else {
            Vec::new()
        };
        Ok(ExpPolynomial {
            terms,
            linear,
            planned,
            dense_e,
            max_power,
        })
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

/// The Taylor-HJ (or any [`ExpPolynomial`]) bisection integrator of a log-canonical structure,
/// state q = ln x.
pub type LogBisection<const N: usize> = BisectionStepper<N, LogCanonical<N>, ExpPolynomial<N>>;

/// Powers y⁰ … y^POWER_TABLE of each coordinate of a generating function's evaluation, lane by
/// lane; larger exponents take [`pow_lanes`].
const POWER_TABLE: usize = 8;

impl<const N: usize> ExpPolynomial<N> {
    /// ∇S(t, ·) at L points q, and with `HESS` its Hessian (`hs[a][b][l]`, both triangles),
    /// lane by lane: y = e^q once per coordinate, each term's y^e by binary powering.
    #[inline(always)]
    pub(crate) fn taylor_lanes<const L: usize, const HESS: bool>(
        &self,
        t: f64,
        t_powers: &[f64; T_POWERS],
        q: &[[f64; L]; N],
        g: &mut [[f64; L]; N],
        hs: &mut [[[f64; L]; N]; N],
    ) {
        self.taylor_lanes_by::<L, HESS>(N <= DENSE_MAX_DIM, t, t_powers, q, g, hs);
    }

    /// [`Self::taylor_lanes`] with the accumulation chosen: `dense` (honoured up to
    /// [`DENSE_MAX_DIM`]) adds every term to every entry in registers, else each term to its own
    /// entries (the same bits; a test holds both).
    #[inline(always)]
    pub(crate) fn taylor_lanes_by<const L: usize, const HESS: bool>(
        &self,
        dense: bool,
        t: f64,
        t_powers: &[f64; T_POWERS],
        q: &[[f64; L]; N],
        g: &mut [[f64; L]; N],
        hs: &mut [[[f64; L]; N]; N],
    ) {
        // pw[i][k] = y_i^k for k ≤ POWER_TABLE (and the largest |exponent| of coordinate i), y =
        // e^q, by successive products.
        let mut pw = [[[1.0; L]; POWER_TABLE + 1]; N];
        for i in 0..N {
            exp_lanes(&q[i], &mut pw[i][1]);
            for k in 2..=(self.max_power[i] as usize).min(POWER_TABLE) {
                for l in 0..L {
                    pw[i][k][l] = pw[i][k - 1][l] * pw[i][1][l];
                }
            }
        }
        *g = [[0.0; L]; N];
        if HESS {
            *hs = [[[0.0; L]; N]; N];
        }
        // `dense_e` is filled up to DENSE_MAX_DIM only.
        if dense && N <= DENSE_MAX_DIM {
            // Local sums, indexed by constants only: registers across the loop over terms.
            let mut ga = [[0.0; L]; N];
            let mut ha = [[[0.0; L]; N]; N];
            for (m, e) in self.planned.iter().zip(&self.dense_e) {
                // A constant term has no derivative (and its w·0 could be NaN at an overflow).
                if m.count == 0 {
                    continue;
                }
                let w = term_weight(m, m.coeff * t_power(t, t_powers, m.t_power), &pw);
                add_dense::<N, L, HESS>(e, &w, &mut ga, &mut ha);
            }
            *g = ga;
            if HESS {
                *hs = ha;
            }
        } else {
            for m in &self.planned {
                let c = m.coeff * t_power(t, t_powers, m.t_power);
                // A term in every variable takes loops over N with constant indices (unrolled);
                // the others loop over their own variables only. The same operations either way.
                if m.count == N {
                    add_term::<N, L, HESS, true>(m, c, &pw, g, hs);
                } else {
                    add_term::<N, L, HESS, false>(m, c, &pw, g, hs);
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

/// One term's w = c t^k Π y_v^e_v added to ∇S (and with `HESS` to ∇²S's upper triangle) in the
/// order of the scalar jet: the factors by increasing variable, ∂/∂q_a for each variable of the
/// term, ∂²/∂q_a∂q_b for each pair a ≤ b of them (the others add w·0, which the loop over all N
/// skipped too). `DENSE`: the term has every variable (`var[j]` = j).
#[inline(always)]
fn add_term<const N: usize, const L: usize, const HESS: bool, const DENSE: bool>(
    m: &PlannedExp<N>,
    c: f64,
    pw: &[[[f64; L]; POWER_TABLE + 1]; N],
    g: &mut [[f64; L]; N],
    hs: &mut [[[f64; L]; N]; N],
) {
    let count = if DENSE { N } else { m.count };
    let var = |j: usize| if DENSE { j } else { m.var[j] };
    // w in place (not through `term_weight`'s returned array: that took the 5-D Taylor K = 5
    // step to 1.2× its time).
    let mut w = [c; L];
    for j in 0..count {
        times_factor(&mut w, pw, var(j), m.size[j], m.e[j]);
    }
    for j in 0..count {
        let (a, ea) = (var(j), m.e[j]);
        for l in 0..L {
            g[a][l] += w[l] * ea;
        }
        if HESS {
            for jb in j..count {
                let eab = ea * m.e[jb];
                let b = var(jb);
                for l in 0..L {
                    hs[a][b][l] += w[l] * eab;
                }
            }
        }
    }
}

/// t^k from the step's table, `powi` past it.
#[inline(always)]
fn t_power(t: f64, t_powers: &[f64; T_POWERS], k: u32) -> f64 {
    t_powers
        .get(k as usize)
        .copied()
        .unwrap_or_else(|| t.powi(k as i32))
}

/// A term's w = c Π y_v^e_v at L points, the factors by increasing variable.
#[inline(always)]
fn term_weight<const N: usize, const L: usize>(
    m: &PlannedExp<N>,
    c: f64,
    pw: &[[[f64; L]; POWER_TABLE + 1]; N],
) -> [f64; L] {
    let mut w = [c; L];
    for j in 0..m.count {
        times_factor(&mut w, pw, m.var[j], m.size[j], m.e[j]);
    }
    w
}

/// w ·= y_i^e lane by lane (|e| = `size`), from the table of powers or by binary powering.
#[inline(always)]
fn times_factor<const N: usize, const L: usize>(
    w: &mut [f64; L],
    pw: &[[[f64; L]; POWER_TABLE + 1]; N],
    i: usize,
    size: u32,
    e: f64,
) {
    let power = if size as usize <= POWER_TABLE {
        pw[i][size as usize]
    } else {
        pow_lanes(&pw[i][1], size)
    };
    // The exponent is the term's, not the lane's: one loop per case, so no lane divides for a
    // positive exponent.
    if e > 0.0 {
        for l in 0..L {
            w[l] *= power[l];
        }
    } else {
        for l in 0..L {
            w[l] *= 1.0 / power[l];
        }
    }
}

/// w·e added to ∇S and w·e_a·e_b to ∇²S's upper triangle for every coordinate and pair (`e`
/// with its zeros): the sums of [`add_term`] with ±0 between them, the same bits.
#[inline(always)]
fn add_dense<const N: usize, const L: usize, const HESS: bool>(
    e: &[f64; N],
    w: &[f64; L],
    g: &mut [[f64; L]; N],
    hs: &mut [[[f64; L]; N]; N],
) {
    for a in 0..N {
        let ea = e[a];
        for l in 0..L {
            g[a][l] += w[l] * ea;
        }
        if HESS {
            for b in a..N {
                let eab = ea * e[b];
                for l in 0..L {
                    hs[a][b][l] += w[l] * eab;
                }
            }
        }
    }
}

/// t⁰ … t^(T_POWERS − 1), computed once a step (larger powers of t take `powi`).
pub(crate) const T_POWERS: usize = 16;

/// A generating function that the log-canonical lane solver evaluates: ∇S and, with `HESS`,
/// ∇²S (`hs`, both triangles) at L points q, lane by lane. An S with a network term
/// ([`Self::NETWORK`]) writes that term's Hessian to `hn` instead, and only with `NET_HESS`:
/// the solve takes it at its first update and keeps it.
pub trait LogLaneGenerating<const N: usize>: Generating<N> {
    /// Whether S has a network term (whose Hessian goes to `hn`).
    const NETWORK: bool = false;

    /// ∇S for the predicted start at L points q (`hs` and `hn` untouched): by default that of
    /// [`Self::derivatives_lanes`]; an S with a network term leaves it out.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn start_gradient_lanes<const L: usize>(
        &self,
        t: f64,
        t_powers: &[f64; T_POWERS],
        q: &[[f64; L]; N],
        buf: &mut [LaneRow],
        g: &mut [[f64; L]; N],
        hs: &mut [[[f64; L]; N]; N],
        hn: &mut [[[f64; L]; N]; N],
    ) {
        self.derivatives_lanes::<L, false, false>(t, t_powers, q, buf, g, hs, hn);
    }

    /// `buf`: scratch for a network term ([`crate::generating::NetworkLanes`]); nothing in it
    /// needs clearing.
    #[allow(clippy::too_many_arguments)]
    fn derivatives_lanes<const L: usize, const HESS: bool, const NET_HESS: bool>(
        &self,
        t: f64,
        t_powers: &[f64; T_POWERS],
        q: &[[f64; L]; N],
        buf: &mut [LaneRow],
        g: &mut [[f64; L]; N],
        hs: &mut [[[f64; L]; N]; N],
        hn: &mut [[[f64; L]; N]; N],
    );
}

impl<const N: usize> LogLaneGenerating<N> for ExpPolynomial<N> {
    #[inline(always)]
    fn derivatives_lanes<const L: usize, const HESS: bool, const NET_HESS: bool>(
        &self,
        t: f64,
        t_powers: &[f64; T_POWERS],
        q: &[[f64; L]; N],
        _: &mut [LaneRow],
        g: &mut [[f64; L]; N],
        hs: &mut [[[f64; L]; N]; N],
        _: &mut [[[f64; L]; N]; N],
    ) {
        self.taylor_lanes::<L, HESS>(t, t_powers, q, g, hs);
    }
}

/// The table of powers of t that [`ExpPolynomial::taylor_lanes`] reads.
#[inline(always)]
pub(crate) fn t_power_table(t: f64) -> [f64; T_POWERS] {
    let mut table = [1.0; T_POWERS];
    for k in 1..T_POWERS {
        table[k] = table[k - 1] * t;
    }
    table
}

/// Taylor-HJ on the log-canonical groupoid ([`LogBisection`] of an [`ExpPolynomial`], with the
/// orthant check of [`OrthantChecked`](super::OrthantChecked)) in SIMD lanes, for any N:
/// the Newton solve of q + ½c∇S(q) = q_k runs lane by lane from the predicted start
/// q_k − ½c∇S(q_k) (exact gradient and Hessian of S
/// from y = e^q, J = I + ½c∇²S solved by cofactors for N ≤ 3 and by pivoted elimination above,
/// masked convergence; ∇S at the solution from the last update's gradient and Hessian, to
/// O(|δ|²)), then q_{k+1} = q_k − c∇S(q) (the same as q − ½c∇S(q) at the solution, and exactly
/// Casimir-preserving at any iterate). The scalar step is this with one lane, so every lane has
/// the scalar bits.
pub struct LogTaylorLanes<'a, const N: usize>(&'a LogBisection<N>);

impl<const N: usize> LogBisection<N> {
    /// This stepper in SIMD lanes.
    pub fn lanes(&self) -> LogTaylorLanes<'_, N> {
        LogTaylorLanes(self)
    }
}

impl<const N: usize> LaneStepper<N> for LogTaylorLanes<'_, N> {
    /// Measured: 0.78–0.88× the AVX2 time at N = 3, but 1.05–1.11× at N = 2 (PNN's system,
    /// whose block AVX2 already holds in registers).
    const AVX512: bool = N == 3;
    const REPORTS: bool = true;

    /// Measured: at N = 3 0.74–0.82× the time of blocks of 8; at N = 2 and 5 0.83–0.91× the
    /// time of AVX2 blocks.
    #[inline(always)]
    fn avx512_paired(&self) -> bool {
        true
    }

    #[inline(always)]
    fn step_lanes_reporting<const L: usize>(
        &self,
        h: f64,
        mu: &mut [[f64; L]; N],
        live: &[bool; L],
        result: &mut [StepResult; L],
    ) {
        log_bisection_lanes(self.0, &mut [], h, mu, live, result);
    }
}

/// One bisection step of L trajectories of any [`LogLaneGenerating`] S in lanes (the solve of
/// [`LogTaylorLanes`]); `buf` is S's network scratch.
// Out of line in debug builds: inlined there, every local of every instantiation keeps its
// own slot in the dispatching frames, and a test thread's stack overflowed.
#[cfg_attr(not(debug_assertions), inline(always))]
#[cfg_attr(debug_assertions, inline(never))]
pub(super) fn log_bisection_lanes<const N: usize, const L: usize, G: LogLaneGenerating<N>>(
    s: &BisectionStepper<N, LogCanonical<N>, G>,
    buf: &mut [LaneRow],
    h: f64,
    mu: &mut [[f64; L]; N],
    live: &[bool; L],
    result: &mut [StepResult; L],
) {
    let c = s.realization.c();
    let half_c: [[f64; N]; N] = std::array::from_fn(|i| c[i].map(|v| 0.5 * v));
    let newton = FullNewton {
        tol: s.newton.tol,
        max_iter: s.newton.max_iter,
        floor: s.scale_floor,
    };
    let t_powers = t_power_table(h);
    let target = *mu;
    let mut p = target;
    let mut active = *live;
    let mut converged = [false; L];
    let mut iterations = [0u32; L];
    let (mut g, mut hs) = ([[0.0; L]; N], [[[0.0; L]; N]; N]);
    // A network term's Hessian, from the first update on: its term is t^m-small (2.5e-6 of J
    // for the shipped Lotka–Volterra model at h = 0.1) and moves by |∇³S|·|p − p₁| over the
    // updates after, so keeping it changes J by far less than Newton's own error there. A
    // later update then takes the network's gradient alone (`reverse_gradient`), not its
    // tangents.
    let mut hn = [[[0.0; L]; N]; N];
    let mut first = true;
    // ∇S at each converged lane's p.
    let mut x = [[0.0; L]; N];
    // The start q_k − ½c∇S(q_k) of Realization::predict, from one gradient pass of the Taylor
    // terms, with its rule: kept where every shift is at most PREDICT_MAX_SHIFT and finite. A
    // network term is left out of it: O(hᵐ), it would move the start by far less than the
    // start's own O(h²) error (by 4e-7 against 1.4e-3 for the shipped Lotka–Volterra model).
    s.generating
        .start_gradient_lanes::<L>(h, &t_powers, &target, buf, &mut g, &mut hs, &mut hn);
    let mut near = [true; L];
    for i in 0..N {
        for l in 0..L {
            let mut shift = 0.0;
            for k in 0..N {
                shift += half_c[i][k] * g[k][l];
            }
            p[i][l] = target[i][l] - shift;
            near[l] &= shift.abs() <= PREDICT_MAX_SHIFT && p[i][l].is_finite();
        }
    }
    for l in 0..L {
        if !near[l] {
            for i in 0..N {
                p[i][l] = target[i][l];
            }
        }
    }
    while active.contains(&true) {
        if G::NETWORK && first {
            s.generating.derivatives_lanes::<L, true, true>(
                h, &t_powers, &p, buf, &mut g, &mut hs, &mut hn,
            );
        } else {
            s.generating.derivatives_lanes::<L, true, false>(
                h, &t_powers, &p, buf, &mut g, &mut hs, &mut hn,
            );
        }
        first = false;
        if G::NETWORK {
            for a in 0..N {
                for b in 0..N {
                    for l in 0..L {
                        hs[a][b][l] += hn[a][b][l];
                    }
                }
            }
        }
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
        // ∇S and ∇²S finite, for all lanes at once: v·0 is 0 for a finite v and NaN for ±∞
        // and NaN, and NaN survives the sum (tested one lane at a time, it took 4 % of a
        // profile's samples of PNN's step).
        let mut probe = [0.0; L];
        for a in 0..N {
            for l in 0..L {
                probe[l] += g[a][l] * 0.0;
            }
            for b in 0..N {
                for l in 0..L {
                    probe[l] += hs[a][b][l] * 0.0;
                }
            }
        }
        for l in 0..L {
            if !active[l] {
                continue;
            }
            let finite = probe[l] == 0.0;
            if newton.settle(
                l,
                finite,
                solvable[l],
                &delta,
                &mut p,
                &mut iterations,
                &mut active,
                result,
            ) {
                converged[l] = true;
                // ∇S at the new p to first order, from the pass just made: off by
                // O(|δ|²) ≤ (tol·|p|)², far below a rounding, and one gradient pass saved.
                for a in 0..N {
                    let mut acc = g[a][l];
                    for b in 0..N {
                        acc += hs[a][b][l] * delta[b][l];
                    }
                    x[a][l] = acc;
                }
            }
        }
    }
    for l in 0..L {
        if !converged[l] {
            continue;
        }
        if !(0..N).all(|a| x[a][l].is_finite()) {
            result[l] = Err(StepFailure::NonFinite);
            continue;
        }
        let (gl, pl, tl): ([f64; N], [f64; N], [f64; N]) = (
            std::array::from_fn(|i| x[i][l]),
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

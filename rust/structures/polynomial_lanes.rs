//! Taylor-HJ on an approximate realization of a polynomial bivector in SIMD lanes: the step of
//! [`PolynomialBisection`] (full Newton on α(∇S(h, x), x) = x_k, then β) for a block of
//! trajectories in lockstep, one trajectory a lane.
//!
//! A Newton update takes two kinds of pass, both the sparse jets of
//! [`crate::generating::polynomial_lanes`] (tables of powers, the products of a term sharing
//! their prefixes): one jet of S(h, ·) gives ∇S and ∇²S, and one value-and-gradient pass of each
//! α_i in v = (p, x) gives α_i, ∂α_i/∂p and ∂α_i/∂x. It then forms
//! J = ∂α/∂x + ∂α/∂p · ∇²S and solves J δ = x_k − α by cofactors (N ≤ 3) or pivoted
//! elimination. The rules are the dual-number step's (start at x_k, |δ|∞ ≤ tol · max(|x|∞, 1),
//! the same failures in the same order, β at ∇S of the converged x), so the two agree to
//! round-off (tested); the scalar step is this one with one lane, so every lane has its bits.
//!
//! (Each derivative was a polynomial of its own before, 2N² + N(N + 3)/2 of them, each term's
//! powers by repeated multiplication: at the order-5 realization of the cubic Nambu bracket,
//! 596 derivative terms and 182 of α an update, where α's value-and-gradient passes take its
//! 182 once.)

// Index loops over lanes, coordinates and matrix entries read as the formulas they evaluate.
#![allow(clippy::needless_range_loop)]

use super::polynomial::{PolynomialBisection, SparsePolynomial};
use crate::error::{CoreError, StepFailure};
use crate::generating::polynomial_lanes::{
    jet_lanes_after_powers, jet_lanes_into, JetLanes, Scratch,
};
use crate::generating::{Monomial, Polynomial};
use crate::lanes::{solve_small_lanes, FullNewton, LaneStepper};
use crate::memory::try_collect;
use crate::step::{StepMap, StepResult, StepStats};

/// [`PolynomialBisection`] with S and α compiled for their jets, stepped in lanes; M = 2N, the
/// variables (p, x) of α (a const parameter of its own: `2 * N` cannot be one in generic code).
pub struct PolynomialLanes<'a, const N: usize, const M: usize> {
    stepper: &'a PolynomialBisection<N>,
    /// S(t, x): x's powers with t's (t is the first variable of the stored polynomial).
    s: Polynomial<N>,
    /// α_i in v = (p, x).
    tar: Vec<Polynomial<M>>,
    /// The largest exponent of each of v's variables over every α_i: the rows of the tables of
    /// powers that the N passes share.
    tar_max: [u32; M],
}

/// `poly`'s terms as monomials in `K` variables after `skip` leading ones, whose first exponent
/// (when `skip` is 1) is the power of t. Fallible allocation.
fn compiled<const K: usize>(
    poly: &SparsePolynomial,
    skip: usize,
    what: &str,
) -> Result<Polynomial<K>, CoreError> {
    if poly.vars() != skip + K {
        return Err(CoreError::Invalid(format!(
            "{what} must be a polynomial in {} variables, got {}",
            skip + K,
            poly.vars()
        )));
    }
    let terms = try_collect(
        poly.terms().count(),
        poly.terms().map(|(coeff, row)| {
            let mut p_powers = [0u32; K];
            for i in 0..K {
                p_powers[i] = u32::from(row[skip + i]);
            }
            Monomial {
                t_power: if skip == 1 { u32::from(row[0]) } else { 0 },
                p_powers,
                coeff,
            }
        }),
        what,
    )?;
    Polynomial::new(terms)
}

impl<'a, const N: usize, const M: usize> PolynomialLanes<'a, N, M> {
    /// The lane form of `stepper`: S and α compiled for their jets. `M` must be 2N.
    pub fn new(stepper: &'a PolynomialBisection<N>) -> Result<Self, CoreError> {
        if M != 2 * N {
            return Err(CoreError::Invalid(format!(
                "the lanes of a realization in dimension {N} take its maps in 2N = {} \
                 variables, not {M}",
                2 * N
            )));
        }
        let s = compiled::<N>(stepper.generating.as_polynomial(), 1, "S")?;
        let (_, maps) = stepper.realization.maps();
        let mut tar = Vec::new();
        tar.try_reserve_exact(N)
            .map_err(|_| CoreError::Invalid("too many polynomials".into()))?;
        let mut tar_max = [0u32; M];
        for map in maps {
            let poly = compiled::<M>(map, 0, "tar")?;
            for k in 0..M {
                tar_max[k] = tar_max[k].max(poly.plan().p_max[k]);
            }
            tar.push(poly);
        }
        Ok(PolynomialLanes {
            stepper,
            s,
            tar,
            tar_max,
        })
    }

    /// `maps` at (p, x) for L points (values only: β and α at the solution).
    #[inline(always)]
    fn apply<const L: usize>(
        maps: &[SparsePolynomial],
        p: &[[f64; L]; N],
        x: &[[f64; L]; N],
    ) -> [[f64; L]; N] {
        // (p, x) side by side, as one slice of 2N rows (no buffer of the largest size to clear).
        let v = [*p, *x];
        let v = v.as_flattened();
        let mut out = [[0.0; L]; N];
        for i in 0..N {
            out[i] = maps[i].eval_lanes(v);
        }
        out
    }
}

/// Whether every lane value of `rows` is finite, lane by lane.
#[inline(always)]
fn finite<const L: usize>(rows: &[[f64; L]]) -> [bool; L] {
    // x · 0 is 0 for a finite x and NaN for ±∞ and NaN (the block loop's probe in `lanes.rs`):
    // a sum in vectors, where a per-lane `all` was an out-of-line closure in scalar code (18 % of
    // the Taylor K = 3 step's time in the core).
    let mut probe = [0.0; L];
    for r in rows {
        for l in 0..L {
            probe[l] += r[l] * 0.0;
        }
    }
    let mut ok = [false; L];
    for l in 0..L {
        ok[l] = probe[l] == 0.0;
    }
    ok
}

impl<const N: usize, const M: usize> LaneStepper<N> for PolynomialLanes<'_, N, M> {
    const REPORTS: bool = true;

    /// Measured on the Nambu bracket (N = 3): paired blocks 0.66–0.68× the time of AVX2 blocks.
    #[inline(always)]
    fn avx512_paired(&self) -> bool {
        true
    }

    // Loops fill the arrays here rather than `std::array::from_fn`: a closure that evaluates
    // polynomials is compiled out of line, for the baseline CPU (SSE2), not inside the AVX-512
    // or AVX2 kernel that calls it (0.68–0.79× the step's time, the same bits).
    #[inline(always)]
    fn step_lanes_reporting<const L: usize>(
        &self,
        h: f64,
        mu: &mut [[f64; L]; N],
        live: &[bool; L],
        result: &mut [StepResult; L],
    ) {
        let (sou, tar_maps) = self.stepper.realization.maps();
        let newton = FullNewton {
            tol: self.stepper.newton.tol,
            max_iter: self.stepper.newton.max_iter,
            floor: self.stepper.scale_floor,
        };
        let target = *mu;
        let mut x = target;
        let mut active = *live;
        let mut converged = [false; L];
        let mut iterations = [0u32; L];
        let (mut s_scratch, mut a_scratch) = (Scratch::<N, L>::new(), Scratch::<M, L>::new());
        let mut s_jet = JetLanes::<N, L> {
            v: [0.0; L],
            g: [[0.0; L]; N],
            h: [[[0.0; L]; N]; N],
        };
        let mut a_jet = JetLanes::<M, L> {
            v: [0.0; L],
            g: [[0.0; L]; M],
            h: [[[0.0; L]; M]; M],
        };
        while active.contains(&true) {
            // p = ∇S(h, x) and ∇²S (the jet's upper triangle, mirrored).
            jet_lanes_into::<N, L, true, 0>(&self.s, h, &x, &mut s_scratch, &mut s_jet);
            let p = s_jet.g;
            let mut hs = [[[0.0; L]; N]; N];
            for a in 0..N {
                for b in a..N {
                    hs[a][b] = s_jet.h[a][b];
                    hs[b][a] = hs[a][b];
                }
            }
            let mut jet_ok = finite(&p);
            for row in &hs {
                let ok = finite(row);
                for l in 0..L {
                    jet_ok[l] &= ok[l];
                }
            }
            let mut v = [[0.0; L]; M];
            v[..N].copy_from_slice(&p);
            v[N..2 * N].copy_from_slice(&x);
            // α_i with its gradient in (p, x) (the tables of v's powers built once for all i); J = ∂α/∂x + ∂α/∂p · ∇²S (x moves p = ∇S(x));
            // f = x_k − α.
            let mut tar = [[0.0; L]; N];
            let mut j = [[[0.0; L]; N]; N];
            let mut f = [[0.0; L]; N];
            a_scratch.fill_powers(&self.tar_max, &v);
            for i in 0..N {
                jet_lanes_after_powers::<M, L, false>(
                    &self.tar[i],
                    0.0,
                    &v,
                    &mut a_scratch,
                    &mut a_jet,
                );
                tar[i] = a_jet.v;
                for c in 0..N {
                    let mut acc = a_jet.g[N + c];
                    for m in 0..N {
                        for l in 0..L {
                            acc[l] += a_jet.g[m][l] * hs[m][c][l];
                        }
                    }
                    j[i][c] = acc;
                }
                for l in 0..L {
                    f[i][l] = target[i][l] - tar[i][l];
                }
            }
            let tar_ok = finite(&tar);
            let mut delta = [[0.0; L]; N];
            let mut solvable = [true; L];
            solve_small_lanes(&j, &f, &mut delta, &mut solvable);
            for l in 0..L {
                // The dual-number step's order: S's jet and α, the cap, the solve.
                if active[l] {
                    converged[l] = newton.settle(
                        l,
                        jet_ok[l] && tar_ok[l],
                        solvable[l],
                        &delta,
                        &mut x,
                        &mut iterations,
                        &mut active,
                        result,
                    );
                }
            }
        }
        if !converged.contains(&true) {
            return;
        }
        // β(∇S(x), x) at the converged x, and α's residual there.
        jet_lanes_into::<N, L, false, 0>(&self.s, h, &x, &mut s_scratch, &mut s_jet);
        let p = s_jet.g;
        let tar = Self::apply(tar_maps, &p, &x);
        let out = Self::apply(sou, &p, &x);
        let (p_ok, tar_ok, out_ok) = (finite(&p), finite(&tar), finite(&out));
        for l in (0..L).filter(|&l| converged[l]) {
            if !(p_ok[l] && tar_ok[l] && out_ok[l]) {
                result[l] = Err(StepFailure::NonFinite);
                continue;
            }
            let mut residual = 0.0f64;
            for i in 0..N {
                residual = residual.max((tar[i][l] - target[i][l]).abs());
                mu[i][l] = out[i][l];
            }
            result[l] = Ok(StepStats {
                iterations: iterations[l],
                residual,
            });
        }
    }
}

impl<const N: usize, const M: usize> StepMap<N> for PolynomialLanes<'_, N, M> {
    type Workspace = ();
    fn workspace(&self) {}
    fn step(&self, h: f64, mu: &mut [f64; N], _: &mut ()) -> StepResult {
        let mut lane: [[f64; 1]; N] = mu.map(|v| [v]);
        let mut result = [Ok(StepStats::default())];
        self.step_lanes_reporting(h, &mut lane, &[true], &mut result);
        *mu = lane.map(|v| v[0]);
        result[0]
    }
}

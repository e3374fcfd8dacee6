//! Taylor-HJ on an approximate realization of a polynomial bivector in SIMD lanes: the step of
//! [`PolynomialBisection`] (full Newton on α(∇S(h, x), x) = x_k, then β) for a block of
//! trajectories in lockstep, one trajectory a lane.
//!
//! Every derivative the solve needs is a polynomial of its own, differentiated once when the
//! stepper is built ([`SparsePolynomial::derivative`], exact coefficients): ∇S and the upper
//! Hessian of S in (t, x), and ∂α/∂(p, x). A Newton update evaluates them lane by lane in f64
//! (powers by repeated multiplication, as the scalar polynomials), forms
//! J = ∂α/∂x + ∂α/∂p · ∇²S and solves J δ = x_k − α by cofactors (N ≤ 3) or pivoted
//! elimination. The rules are the dual-number step's (start at x_k, |δ|∞ ≤ tol · max(|x|∞, 1),
//! the same failures in the same order, β at ∇S of the converged x), so the two agree to
//! round-off (tested); the scalar step is this one with one lane, so every lane has its bits.

// Index loops over lanes, coordinates and matrix entries read as the formulas they evaluate.
#![allow(clippy::needless_range_loop)]

use super::polynomial::{PolynomialBisection, SparsePolynomial};
use crate::error::{CoreError, StepFailure};
use crate::lanes::{solve_small_lanes, FullNewton, LaneStepper};
use crate::step::{StepMap, StepResult, StepStats};

/// [`PolynomialBisection`] with its derivative polynomials, stepped in lanes.
pub struct PolynomialLanes<'a, const N: usize> {
    stepper: &'a PolynomialBisection<N>,
    /// ∂S/∂x_a, polynomials in (t, x).
    grad: Vec<SparsePolynomial>,
    /// ∂²S/∂x_a∂x_b for a ≤ b, row by row (N(N+1)/2 of them).
    hess: Vec<SparsePolynomial>,
    /// ∂α_i/∂v_k at i · 2N + k, v = (p, x).
    tar_d: Vec<SparsePolynomial>,
}

/// A fallibly allocated vector of `n` polynomials.
fn polynomials(
    n: usize,
    f: impl Fn(usize) -> Result<SparsePolynomial, CoreError>,
) -> Result<Vec<SparsePolynomial>, CoreError> {
    let mut out = Vec::new();
    out.try_reserve_exact(n)
        .map_err(|_| CoreError::Invalid("too many polynomials".into()))?;
    for k in 0..n {
        out.push(f(k)?);
    }
    Ok(out)
}

/// (a, b) with a ≤ b of the k-th upper-triangle entry of an N × N matrix, row by row.
fn upper_entry<const N: usize>(mut k: usize) -> (usize, usize) {
    let mut a = 0;
    while k >= N - a {
        k -= N - a;
        a += 1;
    }
    (a, a + k)
}

impl<'a, const N: usize> PolynomialLanes<'a, N> {
    /// The lane form of `stepper`: its derivative polynomials.
    pub fn new(stepper: &'a PolynomialBisection<N>) -> Result<Self, CoreError> {
        let s = stepper.generating.as_polynomial();
        let (_, tar) = stepper.realization.maps();
        // S's variables are (t, x): x_a is variable 1 + a.
        let grad = polynomials(N, |a| s.derivative(1 + a))?;
        let hess = polynomials(N * (N + 1) / 2, |k| {
            let (a, b) = upper_entry::<N>(k);
            grad[a].derivative(1 + b)
        })?;
        let tar_d = polynomials(2 * N * N, |k| tar[k / (2 * N)].derivative(k % (2 * N)))?;
        Ok(PolynomialLanes {
            stepper,
            grad,
            hess,
            tar_d,
        })
    }

    /// ∇S at L points x (t = h).
    ///
    /// Here and in the step, loops fill the arrays rather than `std::array::from_fn`: a closure
    /// that evaluates polynomials is compiled out of line, for the baseline CPU (SSE2), not inside
    /// the AVX-512 or AVX2 kernel that calls it (0.68–0.79× the step's time, the same bits).
    #[inline(always)]
    fn gradient<const L: usize>(&self, h: f64, x: &[[f64; L]; N]) -> [[f64; L]; N] {
        let mut out = [[0.0; L]; N];
        for a in 0..N {
            out[a] = self.grad[a].eval_lanes_after_t(h, x);
        }
        out
    }

    /// `maps` at (p, x) for L points.
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

impl<const N: usize> LaneStepper<N> for PolynomialLanes<'_, N> {
    const REPORTS: bool = true;

    /// Measured on the Nambu bracket (N = 3): paired blocks 0.66–0.68× the time of AVX2 blocks.
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
        while active.contains(&true) {
            let p = self.gradient(h, &x);
            let mut hs = [[[0.0; L]; N]; N];
            let mut k = 0;
            for a in 0..N {
                for b in a..N {
                    hs[a][b] = self.hess[k].eval_lanes_after_t(h, &x);
                    hs[b][a] = hs[a][b];
                    k += 1;
                }
            }
            let mut jet_ok = finite(&p);
            for row in &hs {
                let ok = finite(row);
                for l in 0..L {
                    jet_ok[l] &= ok[l];
                }
            }
            let tar = Self::apply(tar_maps, &p, &x);
            let tar_ok = finite(&tar);
            // J = ∂α/∂x + ∂α/∂p · ∇²S (x moves p = ∇S(x)); f = x_k − α.
            let v = [p, x];
            let v = v.as_flattened();
            let mut j = [[[0.0; L]; N]; N];
            let mut f = [[0.0; L]; N];
            for i in 0..N {
                // ∂α_i/∂p first, then each column's ∂α_i/∂x_c with ∂α_i/∂p · ∇²S added in
                // order (the sum as before, without a buffer of the largest size).
                let mut dp = [[0.0; L]; N];
                for m in 0..N {
                    dp[m] = self.tar_d[i * 2 * N + m].eval_lanes(v);
                }
                for c in 0..N {
                    let mut acc = self.tar_d[i * 2 * N + N + c].eval_lanes(v);
                    for m in 0..N {
                        for l in 0..L {
                            acc[l] += dp[m][l] * hs[m][c][l];
                        }
                    }
                    j[i][c] = acc;
                }
                for l in 0..L {
                    f[i][l] = target[i][l] - tar[i][l];
                }
            }
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
        let p = self.gradient(h, &x);
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

impl<const N: usize> StepMap<N> for PolynomialLanes<'_, N> {
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

//! The rigid body's splittings, discrete Moser–Veselov and the heavy top's splitting in SIMD
//! lanes: [`LaneStepper`] implementations that the [`crate::lanes::Lanes`] rollout kernel runs
//! (runtime AVX2 dispatch, masking, diagnostics, Ctrl-C and failures as for RK4 and midpoint).
//!
//! Every axis flow is an exact rotation whose sin and cos come from [`trig::sin_cos_lanes`]:
//! branch-free, so the loop over lanes vectorises, and the same function as the scalar
//! [`crate::classical`] steppers call, so each lane equals the scalar step bit for bit (the
//! same operations in the same order, plain multiplies and adds). DMV's Newton solve is masked
//! like [`ImplicitMidpoint`]'s: the residual for the whole block, each unconverged lane's 3×3
//! Jacobian and LU solve by the scalar functions.
//!
//! [`ImplicitMidpoint`]: crate::classical::ImplicitMidpoint

// Index loops over lanes and coordinates read as the formulas they evaluate.
#![allow(clippy::needless_range_loop)]

use crate::classical::{
    max_abs, CasimirSplitting, HeavyTop, HeavyTopSplitting, MoserVeselov, SplittingComposition,
};
use crate::error::StepFailure;
use crate::lanes::LaneStepper;
use crate::step::{StepResult, StepStats};
use crate::trig;

/// Turns rows `v[o + a]`, `v[o + b]` ((i, a, b) cyclic) of every lane by the angle −angle[l],
/// given its sine and cosine: the scalar `rotate_about`, lane by lane.
#[inline(always)]
fn rotate_lanes<const L: usize, const N: usize>(
    i: usize,
    o: usize,
    s: &[f64; L],
    c: &[f64; L],
    v: &mut [[f64; L]; N],
) {
    let (a, b) = (o + (i + 1) % 3, o + (i + 2) % 3);
    for l in 0..L {
        let (x, y) = (v[a][l], v[b][l]);
        v[a][l] = c[l] * x + s[l] * y;
        v[b][l] = c[l] * y - s[l] * x;
    }
}

/// sin and cos of `scale · mu[i]` in every lane (the angle as the scalar flows form it:
/// `t * mu[i] * inv[i]` is `(t * mu[i]) * inv[i]`, passed as `pre` = t, `post` = inv[i]).
#[inline(always)]
fn angle_sin_cos<const L: usize, const N: usize>(
    i: usize,
    pre: f64,
    post: f64,
    mu: &[[f64; L]; N],
) -> ([f64; L], [f64; L]) {
    let mut angle = [0.0; L];
    for l in 0..L {
        angle[l] = pre * mu[i][l] * post;
    }
    let (mut s, mut c) = ([0.0; L], [0.0; L]);
    trig::sin_cos_lanes(&angle, &mut s, &mut c);
    (s, c)
}

/// The rigid body's axis flow [`crate::classical::RigidBody::axis_flow`] in every lane.
#[inline(always)]
fn axis_flow_lanes<const L: usize>(inv: &[f64; 3], i: usize, t: f64, mu: &mut [[f64; L]; 3]) {
    let (s, c) = angle_sin_cos(i, t, inv[i], mu);
    rotate_lanes(i, 0, &s, &c, mu);
}

impl<const M: usize> LaneStepper<3> for SplittingComposition<M> {
    /// Measured: in blocks of 8 the order-4 composition took 1.11× its AVX2 time; Strang's
    /// splitting 0.94× in one build and 1.10× in two runs of another (code layout, not the
    /// instructions), so both stay on AVX2 there.
    const AVX512: bool = false;

    /// Measured with it (the paired gains below).
    const PROBE_BY_LANE: bool = true;

    /// Measured: paired blocks 0.43× (Strang) and 0.50× (order 4) the time of AVX2 blocks.
    #[inline(always)]
    fn avx512_paired(&self) -> bool {
        true
    }
    /// The scalar step's rotations in the same order, the merged H₁ half-flows included.
    #[inline(always)]
    fn step_lanes<const L: usize>(&self, h: f64, mu: &mut [[f64; L]; 3]) {
        let inv = self.body.inverse_inertia();
        let mut pending = 0.5 * self.weights[0] * h;
        for (j, &g) in self.weights.iter().enumerate() {
            let tau = g * h;
            axis_flow_lanes(&inv, 0, pending, mu);
            axis_flow_lanes(&inv, 1, 0.5 * tau, mu);
            axis_flow_lanes(&inv, 2, tau, mu);
            axis_flow_lanes(&inv, 1, 0.5 * tau, mu);
            pending = 0.5 * tau + self.weights.get(j + 1).map_or(0.0, |&n| 0.5 * n * h);
        }
        axis_flow_lanes(&inv, 0, pending, mu);
    }
}

impl LaneStepper<3> for CasimirSplitting {
    /// Measured: 0.59× the time of blocks of 8.
    #[inline(always)]
    fn avx512_paired(&self) -> bool {
        true
    }

    #[inline(always)]
    fn step_lanes<const L: usize>(&self, h: f64, mu: &mut [[f64; L]; 3]) {
        let ([j, k], [aj, ak]) = self.axes_and_coefficients();
        // The scalar angle is t * a * mu[i] = (t * a) * mu[i].
        let flow = |i: usize, ta: f64, mu: &mut [[f64; L]; 3]| {
            let (s, c) = angle_sin_cos(i, ta, 1.0, mu);
            rotate_lanes(i, 0, &s, &c, mu);
        };
        flow(j, 0.5 * h * aj, mu);
        flow(k, h * ak, mu);
        flow(j, 0.5 * h * aj, mu);
    }
}

/// The heavy top's axis flow: M (rows 0..3) and Γ (rows 3..6) turned by one angle.
#[inline(always)]
fn top_axis_flow_lanes<const L: usize>(inv: &[f64; 3], i: usize, t: f64, mu: &mut [[f64; L]; 6]) {
    let (s, c) = angle_sin_cos(i, t, inv[i], mu);
    rotate_lanes(i, 0, &s, &c, mu);
    rotate_lanes(i, 3, &s, &c, mu);
}

/// The potential flow: Γ fixed, M += t · Γ × (mgl χ), as [`HeavyTop`]'s scalar one.
#[inline(always)]
fn potential_flow_lanes<const L: usize>(top: &HeavyTop, t: f64, mu: &mut [[f64; L]; 6]) {
    let arm = &top.torque_arm;
    for l in 0..L {
        let g = [mu[3][l], mu[4][l], mu[5][l]];
        let d = [
            g[1] * arm[2] - g[2] * arm[1],
            g[2] * arm[0] - g[0] * arm[2],
            g[0] * arm[1] - g[1] * arm[0],
        ];
        for i in 0..3 {
            mu[i][l] += t * d[i];
        }
    }
}

impl HeavyTopSplitting {
    /// [`HeavyTopSplitting`]'s step on a block of heavy-top states.
    #[inline(always)]
    fn step_top_lanes<const L: usize>(&self, h: f64, mu: &mut [[f64; L]; 6]) {
        let top = &self.top;
        let inv = top.body.inverse_inertia();
        potential_flow_lanes(top, 0.5 * h, mu);
        top_axis_flow_lanes(&inv, 0, 0.5 * h, mu);
        top_axis_flow_lanes(&inv, 1, 0.5 * h, mu);
        top_axis_flow_lanes(&inv, 2, h, mu);
        top_axis_flow_lanes(&inv, 1, 0.5 * h, mu);
        top_axis_flow_lanes(&inv, 0, 0.5 * h, mu);
        potential_flow_lanes(top, 0.5 * h, mu);
    }
}

/// For every dimension N, so that the bindings' dimension-generic code can name it; only N = 6
/// (se(3)*) is ever built ([`crate::classical::LieStepper::new`] refuses the rest). Any other N
/// turns the lanes to NaN, which the block loop reports as a non-finite step, as the scalar
/// [`crate::classical::LieStepper`] does.
impl<const N: usize> LaneStepper<N> for HeavyTopSplitting {
    /// Measured with it (the paired gain below).
    const PROBE_BY_LANE: bool = true;

    /// Measured: paired blocks 0.41× the time of AVX2 blocks.
    #[inline(always)]
    fn avx512_paired(&self) -> bool {
        true
    }

    #[inline(always)]
    fn step_lanes<const L: usize>(&self, h: f64, mu: &mut [[f64; L]; N]) {
        match <&mut [[f64; L]; 6]>::try_from(&mut mu[..]) {
            Ok(m) => self.step_top_lanes(h, m),
            Err(_) => *mu = [[f64::NAN; L]; N],
        }
    }
}

impl MoserVeselov {
    /// G(y) in every lane, as the scalar [`MoserVeselov::residual`].
    #[inline(always)]
    fn residual_lanes<const L: usize>(
        &self,
        h: f64,
        m: &[[f64; L]; 3],
        y: &[[f64; L]; 3],
        g: &mut [[f64; L]; 3],
    ) {
        for l in 0..L {
            let r = self.residual(
                h,
                &[m[0][l], m[1][l], m[2][l]],
                &[y[0][l], y[1][l], y[2][l]],
            );
            for i in 0..3 {
                g[i][l] = r[i];
            }
        }
    }

    /// The Newton update [`MoserVeselov::newton_delta`] in every lane (straight-line code: the
    /// loop vectorises).
    #[inline(always)]
    fn newton_delta_lanes<const L: usize>(
        &self,
        h: f64,
        m: &[[f64; L]; 3],
        y: &[[f64; L]; 3],
        delta: &mut [[f64; L]; 3],
    ) {
        for l in 0..L {
            let d = self.newton_delta(
                h,
                &[m[0][l], m[1][l], m[2][l]],
                &[y[0][l], y[1][l], y[2][l]],
            );
            for i in 0..3 {
                delta[i][l] = d[i];
            }
        }
    }
}

impl LaneStepper<3> for MoserVeselov {
    /// Measured: blocks of 8 took 1.08–1.09× their AVX2 time.
    const AVX512: bool = false;
    const REPORTS: bool = true;

    /// Measured: paired blocks 0.87× the time of AVX2 blocks.
    #[inline(always)]
    fn avx512_paired(&self) -> bool {
        true
    }

    /// The scalar [`MoserVeselov`] step lane by lane: each Newton update for the whole block,
    /// then each live lane's bookkeeping. A converged lane is frozen while the others iterate
    /// (its update computed and dropped); a failing one stops alone with the scalar path's
    /// failure, its state untouched.
    #[inline(always)]
    fn step_lanes_reporting<const L: usize>(
        &self,
        h: f64,
        mu: &mut [[f64; L]; 3],
        live: &[bool; L],
        result: &mut [StepResult; L],
    ) {
        let m = *mu;
        let inv = self.body.inverse_inertia();
        let mut y = [[0.0; L]; 3];
        for i in 0..3 {
            for l in 0..L {
                // The scalar start: (0.5 * h) * (μᵢ / Iᵢ), μᵢ / Iᵢ as μᵢ * (1/Iᵢ).
                y[i][l] = 0.5 * h * (m[i][l] * inv[i]);
            }
        }
        let (mut g, mut delta) = ([[0.0; L]; 3], [[0.0; L]; 3]);
        let mut active = *live;
        let mut done = [false; L];
        let mut iterations = [0u32; L];
        let mut count = 0u32;
        while active.contains(&true) {
            if count >= self.newton.max_iter {
                for l in 0..L {
                    if active[l] {
                        result[l] = Err(StepFailure::NotConverged);
                        active[l] = false;
                    }
                }
                break;
            }
            self.newton_delta_lanes(h, &m, &y, &mut delta);
            count += 1;
            for l in 0..L {
                if !active[l] {
                    continue;
                }
                let d = [delta[0][l], delta[1][l], delta[2][l]];
                if !d.iter().all(|v| v.is_finite()) {
                    result[l] = Err(StepFailure::SingularJacobian);
                    active[l] = false;
                    continue;
                }
                for i in 0..3 {
                    y[i][l] += d[i];
                }
                let yl = [y[0][l], y[1][l], y[2][l]];
                if max_abs(&d) <= self.newton.tol * max_abs(&yl).max(1e-300) {
                    active[l] = false;
                    done[l] = true;
                    iterations[l] = count;
                }
            }
        }
        if !done.contains(&true) {
            return;
        }
        self.residual_lanes(h, &m, &y, &mut g);
        for l in 0..L {
            if !done[l] {
                continue;
            }
            let ml = [m[0][l], m[1][l], m[2][l]];
            let yl = [y[0][l], y[1][l], y[2][l]];
            let gl = [g[0][l], g[1][l], g[2][l]];
            let (next, residual) = MoserVeselov::finish(&ml, &yl, &gl);
            for i in 0..3 {
                mu[i][l] = next[i];
            }
            result[l] = if next.iter().all(|v| v.is_finite()) {
                Ok(StepStats {
                    iterations: iterations[l],
                    residual,
                })
            } else {
                Err(StepFailure::NonFinite)
            };
        }
    }
}

//! The se(3) lane solver (`lanes_bisection_se3`): its chart against the groupoid's scalar chart
//! (values bit for bit, Jacobian against dual numbers), its 6×6 inverse, and the shared lane
//! solver's checks (`exp_chart_lanes`) on the heavy top: against the generic dual-number step,
//! and lane bits that depend on neither the block nor the dispatch.

#![allow(clippy::needless_range_loop)]

use super::exp_chart_lanes::{
    newton_against_the_generic_step, same_for_every_dispatch_and_block, start_is_second_order,
};
use super::lie_poisson::{heavy_top, minus_t_h_terms};
use super::*;
use crate::dual::Dual1;
use crate::lanes_bisection::{inverse_lanes, V};
use crate::lanes_bisection_se3::{se3_tar_lanes, Se3Chart, Se3Newton};
use crate::structures::lie_groupoid::LieAlgebra;

const L: usize = 8;

/// −tH of the heavy top plus `extra` random terms t^k p^a (k = 2, 3; exponents ≤ 2 each, total
/// ≤ 4; coefficients in ±0.01): a polynomial S a step of h = 0.1 solves for |M| ≤ 2.
fn top_polynomial(rng: &mut Rng, extra: usize) -> Polynomial<6> {
    let mut terms = minus_t_h_terms(&heavy_top());
    while terms.len() < 4 + extra {
        let p_powers = [0u32; 6].map(|_| rng.below(3) as u32);
        if p_powers.iter().sum::<u32>() <= 4 {
            terms.push(Monomial {
                t_power: 2 + rng.below(2) as u32,
                p_powers,
                coeff: rng.range(-0.01, 0.01),
            });
        }
    }
    Polynomial::new(terms).unwrap()
}

fn top_state(rng: &mut Rng) -> [f64; 6] {
    let m = rng.vec3(-2.0, 2.0);
    let g = rng.sphere(1.0);
    [m[0], m[1], m[2], g[0], g[1], g[2]]
}

fn top_stepper(poly: Polynomial<6>) -> BisectionStepper<6> {
    BisectionStepper::new(
        GeneratingFunction::new(poly, None, 0, MlpInputs::Plain).unwrap(),
        Groupoid::new(LieAlgebra::se3(), Chart::Exp).unwrap(),
        NewtonOptions::default(),
    )
}

/// tar in lanes equals the groupoid's scalar chart bit for bit, and its Jacobian equals the
/// derivative of the scalar chart in dual numbers (x carrying a random symmetric Hessian) to
/// 1e-13 relative, for |ω| from 1e-4 to 3.5 (both sides of the series/closed-form switch at 1).
#[test]
fn lane_chart_equals_the_scalar_chart_and_its_dual_jacobian() {
    let mut rng = Rng::new(0x5E3_0001);
    let groupoid = Groupoid::new(LieAlgebra::se3(), Chart::Exp).unwrap();
    let mut worst = 0.0f64;
    for round in 0..40 {
        let mut xs = [[0.0; 6]; L];
        let mut ps = [[0.0; 6]; L];
        let mut hs = [[[0.0; 6]; 6]; L];
        for l in 0..L {
            let theta = [1e-4, 0.3, 0.99, 1.01, 2.0, 3.5][(round + l) % 6];
            let w = rng.sphere(theta);
            let v = rng.vec3(-1.0, 1.0);
            xs[l] = [w[0], w[1], w[2], v[0], v[1], v[2]];
            ps[l] = [0.0; 6].map(|_| rng.range(-2.0, 2.0));
            for a in 0..6 {
                for b in a..6 {
                    hs[l][a][b] = rng.range(-0.3, 0.3);
                    hs[l][b][a] = hs[l][a][b];
                }
            }
        }
        let x: [V<L>; 6] = std::array::from_fn(|i| V(std::array::from_fn(|l| xs[l][i])));
        let p: [V<L>; 6] = std::array::from_fn(|i| V(std::array::from_fn(|l| ps[l][i])));
        let h: [[V<L>; 6]; 6] = std::array::from_fn(|a| {
            std::array::from_fn(|b| V(std::array::from_fn(|l| hs[l][a][b])))
        });
        let mut jac = [[V([f64::NAN; L]); 6]; 6];
        let (t_plain, s) = se3_tar_lanes(&x, &p, None, &mut jac);
        assert!(jac.iter().flatten().all(|v| v.0.iter().all(|x| x.is_nan())));
        let (t, _) = se3_tar_lanes(&x, &p, Some(&h), &mut jac);
        for l in 0..L {
            let want = groupoid.tar(&xs[l], &ps[l]).unwrap();
            let got: [f64; 6] = std::array::from_fn(|i| t[i].0[l]);
            let plain: [f64; 6] = std::array::from_fn(|i| t_plain[i].0[l]);
            assert!(
                same_bits(&got, &want) && same_bits(&plain, &want),
                "lane {l}"
            );
            let w2 = xs[l][0] * xs[l][0] + xs[l][1] * xs[l][1] + xs[l][2] * xs[l][2];
            assert_eq!(s.0[l].to_bits(), w2.to_bits());
            let xd: [Dual1<6>; 6] = std::array::from_fn(|i| Dual1 {
                v: xs[l][i],
                g: hs[l][i],
            });
            let pd: [Dual1<6>; 6] = std::array::from_fn(|i| Dual1::var(ps[l][i], i));
            let td = groupoid.tar(&xd, &pd).unwrap();
            let scale = 1.0
                + td.iter()
                    .flat_map(|d| d.g)
                    .fold(0.0f64, |m, v| m.max(v.abs()));
            for r in 0..6 {
                for k in 0..6 {
                    worst = worst.max((jac[r][k].0[l] - td[r].g[k]).abs() / scale);
                }
            }
        }
    }
    assert!(worst <= 1e-13, "Jacobian off by {worst:e}");
}

/// Gauss–Jordan with partial pivoting: M M⁻¹ = I to 1e-12 on random and on permuted matrices
/// (a zero leading pivot that pivoting must step over), per lane; a singular lane (two equal
/// rows) and a NaN lane are flagged without touching the other lanes' inverses.
#[test]
fn lane_inverse_pivots_and_flags_singular_lanes() {
    let mut rng = Rng::new(0x5E3_0002);
    let mut ms = [[[0.0; 6]; 6]; L];
    for l in 0..L {
        for r in 0..6 {
            for c in 0..6 {
                ms[l][r][c] = rng.range(-1.0, 1.0) + if r == c { 0.5 } else { 0.0 };
            }
        }
    }
    // Lane 1: a permutation of the identity plus small entries (M[0][0] = 0).
    ms[1] = [[0.0; 6]; 6];
    for r in 0..6 {
        ms[1][r][(r + 1) % 6] = 1.0;
        ms[1][r][(r + 3) % 6] = 0.1;
    }
    // Lane 5: rows 2 and 4 equal; lane 6: a NaN.
    ms[5][4] = ms[5][2];
    ms[6][3][3] = f64::NAN;
    let m: [[V<L>; 6]; 6] =
        std::array::from_fn(|r| std::array::from_fn(|c| V(std::array::from_fn(|l| ms[l][r][c]))));
    let mut inv = [[V([0.0; L]); 6]; 6];
    let ok = inverse_lanes(&m, &mut inv);
    assert!(!ok[6], "NaN lane accepted");
    for l in (0..L).filter(|&l| l != 5 && l != 6) {
        assert!(ok[l], "lane {l} refused");
        for r in 0..6 {
            for c in 0..6 {
                let e: f64 = (0..6).map(|k| ms[l][r][k] * inv[k][c].0[l]).sum();
                let want = if r == c { 1.0 } else { 0.0 };
                assert!((e - want).abs() <= 1e-12, "lane {l}: ({r}, {c}) = {e}");
            }
        }
    }
    // Exactly singular in exact arithmetic; rounding may leave a tiny pivot, whose inverse is
    // then huge: either way the lane is not a usable inverse of a well-conditioned matrix.
    let big = inv
        .iter()
        .flatten()
        .fold(0.0f64, |a, v| a.max(v.0[5].abs()));
    assert!(
        !ok[5] || big > 1e12,
        "singular lane: ok with max |inverse| {big:e}"
    );
}

/// The lane inverse picks each lane's pivot as textbook partial pivoting does (the first row of
/// the largest |entry|; ties and NaN entries leave the earlier row): bit for bit against a
/// one-matrix Gauss–Jordan with the same operations, on small-integer matrices whose columns tie
/// often, lanes pivoting differently in one block, a NaN lane among them.
#[test]
fn lane_inverse_pivots_as_one_matrix_gauss_jordan() {
    fn one_matrix(m: &[[f64; 6]; 6]) -> [[f64; 6]; 6] {
        let mut a = *m;
        let mut inv = [[0.0; 6]; 6];
        for r in 0..6 {
            inv[r][r] = 1.0;
        }
        for col in 0..6 {
            let mut best = col;
            for r in col + 1..6 {
                if a[r][col].abs() > a[best][col].abs() {
                    best = r;
                }
            }
            a.swap(best, col);
            inv.swap(best, col);
            let r = 1.0 / a[col][col];
            for j in col + 1..6 {
                a[col][j] *= r;
            }
            for j in 0..6 {
                inv[col][j] *= r;
            }
            for row in (0..6).filter(|&row| row != col) {
                let f = a[row][col];
                for j in col + 1..6 {
                    a[row][j] -= f * a[col][j];
                }
                for j in 0..6 {
                    inv[row][j] -= f * inv[col][j];
                }
            }
        }
        inv
    }
    let mut rng = Rng::new(0x5E3_0007);
    let mut swapped = 0;
    for round in 0..30 {
        let mut ms = [[[0.0; 6]; 6]; L];
        for l in 0..L {
            for r in 0..6 {
                for c in 0..6 {
                    ms[l][r][c] = rng.below(5) as f64 - 2.0 + if r == c { 0.25 } else { 0.0 };
                }
            }
        }
        if round % 3 == 0 {
            ms[round % L][1][1] = f64::NAN;
        }
        swapped += (0..L)
            .filter(|&l| (1..6).any(|r| ms[l][r][0].abs() > ms[l][0][0].abs()))
            .count();
        let m: [[V<L>; 6]; 6] = std::array::from_fn(|r| {
            std::array::from_fn(|c| V(std::array::from_fn(|l| ms[l][r][c])))
        });
        let mut inv = [[V([0.0; L]); 6]; 6];
        inverse_lanes(&m, &mut inv);
        for l in 0..L {
            let want = one_matrix(&ms[l]);
            for r in 0..6 {
                let got: Vec<f64> = (0..6).map(|c| inv[r][c].0[l]).collect();
                assert!(same_bits(&got, &want[r]), "round {round} lane {l} row {r}");
            }
        }
    }
    // Lanes whose first pivot moves, and lanes whose does not, in the same blocks.
    assert!(swapped > 30 && swapped < 30 * L, "{swapped} lanes swapped");
}

/// The shared solver's checks (`exp_chart_lanes`) on the heavy top's −tH plus random terms:
/// against the generic dual-number step from 25 states, Casimirs |Γ|² and M·Γ kept.
#[test]
fn lane_newton_equals_the_generic_step() {
    let mut rng = Rng::new(0x5E3_0003);
    for extra in [0, 8] {
        let st = top_stepper(top_polynomial(&mut rng, extra));
        let states: Vec<[f64; 6]> = (0..25).map(|_| top_state(&mut rng)).collect();
        let label = format!("se(3), {extra} extra terms");
        newton_against_the_generic_step(&st, Se3Chart, &states, casimirs, &label);
    }
}

/// The shared solver's start is second order (`exp_chart_lanes`) on the heavy top's −tH, and
/// with 8 random t², t³ terms added.
#[test]
fn start_is_second_order_on_se3() {
    let mut rng = Rng::new(0x5E3_0005);
    for extra in [0, 8] {
        let st = top_stepper(top_polynomial(&mut rng, extra));
        let states: Vec<[f64; 6]> = (0..8).map(|_| top_state(&mut rng)).collect();
        let label = format!("se(3), {extra} extra terms");
        start_is_second_order(&st, Se3Chart, &states, &label);
    }
}

/// The shared solver's bits for every dispatch and block (`exp_chart_lanes`) on se(3): the
/// singular lane has |ω| beyond the exp chart.
#[test]
fn lane_newton_is_the_same_for_every_dispatch_and_block() {
    let mut rng = Rng::new(0x5E3_0004);
    let st = top_stepper(top_polynomial(&mut rng, 6));
    let sys = Se3Newton {
        poly: &st.generating.polynomial,
        network: None,
        chart: Se3Chart,
        tol: 1e-12,
        max_iter: 50,
        predict: true,
    };
    let mut mu0: Vec<[f64; 6]> = (0..29).map(|_| top_state(&mut rng)).collect();
    mu0[5] = [f64::NAN, 1.0, 0.0, 0.0, 0.0, 1.0];
    mu0[17] = [400.0, -300.0, 250.0, 0.0, 0.6, 0.8];
    same_for_every_dispatch_and_block(&st, sys, &mu0);
}

/// |Γ|² and M·Γ.
fn casimirs(mu: &[f64; 6]) -> Vec<f64> {
    vec![
        mu[3] * mu[3] + mu[4] * mu[4] + mu[5] * mu[5],
        mu[0] * mu[3] + mu[1] * mu[4] + mu[2] * mu[5],
    ]
}

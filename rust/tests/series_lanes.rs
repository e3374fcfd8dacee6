//! The series lane solver (`lanes_bisection_series`) on algebras without a closed-form chart:
//! sl(2) (3-D, not so(3)) and the 4-D oscillator algebra (the central extension that carries an
//! affine bracket). Its chart against the groupoid's scalar series (values, failures, and the
//! Jacobian against dual numbers), its Newton solve against the generic dual-number step, the
//! Casimirs, and lane bits that depend on neither the block nor the dispatch.

#![allow(clippy::needless_range_loop)]

use super::exp_chart_lanes::{
    newton_against_the_generic_step, same_for_every_dispatch_and_block, start_is_second_order,
};
use super::*;
use crate::dual::Dual1;
use crate::lanes_bisection::V;
use crate::lanes_bisection_series::{coadjoint_lanes, series_tar_lanes, SeriesChart, SeriesNewton};
use crate::structures::lie_groupoid::LieAlgebra;

const L: usize = 8;

/// The algebra with [e_i, e_j] = v e_k for each (i, j, k, v) (and the antisymmetric entry).
fn algebra<const N: usize>(brackets: &[(usize, usize, usize, f64)]) -> LieAlgebra<N> {
    let mut c = [[[0.0; N]; N]; N];
    for &(i, j, k, v) in brackets {
        c[i][j][k] = v;
        c[j][i][k] = -v;
    }
    LieAlgebra::new(c).unwrap()
}

/// sl(2) in the basis (h, e, f): [h, e] = 2e, [h, f] = −2f, [e, f] = h. Casimir x_h²/4 + x_e x_f.
fn sl2() -> LieAlgebra<3> {
    algebra(&[(0, 1, 1, 2.0), (0, 2, 2, -2.0), (1, 2, 0, 1.0)])
}

fn sl2_casimirs(x: &[f64; 3]) -> Vec<f64> {
    vec![0.25 * x[0] * x[0] + x[1] * x[2]]
}

/// The oscillator algebra: [e₃, e₁] = e₂, [e₃, e₂] = −e₁, [e₁, e₂] = e₄ (e₄ central): the
/// central extension of se(2) by a 2-cocycle. Casimirs x₄ and x₁² + x₂² + 2 x₃x₄.
fn oscillator() -> LieAlgebra<4> {
    algebra(&[(2, 0, 1, 1.0), (2, 1, 0, -1.0), (0, 1, 3, 1.0)])
}

fn oscillator_casimirs(x: &[f64; 4]) -> Vec<f64> {
    vec![x[3], x[0] * x[0] + x[1] * x[1] + 2.0 * x[2] * x[3]]
}

/// −t H for H = ½ Σ wᵢ xᵢ² (weights 1, 1.5, 2, …) plus `extra` random terms t^k x^a (k = 2, 3;
/// exponents ≤ 2, total ≤ 4; coefficients in ±0.01).
fn polynomial<const N: usize>(rng: &mut Rng, extra: usize) -> Polynomial<N> {
    let mut terms: Vec<Monomial<N>> = (0..N)
        .map(|i| {
            let mut p_powers = [0; N];
            p_powers[i] = 2;
            Monomial {
                t_power: 1,
                p_powers,
                coeff: -0.5 * (1.0 + 0.5 * i as f64),
            }
        })
        .collect();
    while terms.len() < N + extra {
        let p_powers = [0u32; N].map(|_| rng.below(3) as u32);
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

fn stepper<const N: usize>(algebra: LieAlgebra<N>, poly: Polynomial<N>) -> BisectionStepper<N> {
    BisectionStepper::new(
        GeneratingFunction::new(poly, None, 0, MlpInputs::Plain).unwrap(),
        Groupoid::new(algebra, Chart::Exp).unwrap(),
        NewtonOptions::default(),
    )
}

fn state<const N: usize>(rng: &mut Rng) -> [f64; N] {
    [0.0; N].map(|_| rng.range(-1.0, 1.0))
}

fn lanes<const N: usize>(rows: &[[f64; N]; L]) -> [V<L>; N] {
    std::array::from_fn(|i| V(std::array::from_fn(|l| rows[l][i])))
}

/// The chart in lanes against the groupoid's scalar series on one algebra: values to 1e-14 of
/// their size (the lanes multiply and add where the scalar series fuses), the Jacobian against
/// the dual-number derivative of the scalar chart (x carrying a random symmetric Hessian) to
/// 1e-12, and the same verdicts: a lane far past the singular angle refused, a NaN in x
/// NonFinite, neither touching the others.
fn chart_against_the_scalar_series<const N: usize>(algebra: LieAlgebra<N>, seed: u64) {
    let mut rng = Rng::new(seed);
    let groupoid = Groupoid::new(algebra.clone(), Chart::Exp).unwrap();
    let (mut worst, mut worst_jac, mut edge) = (0.0f64, 0.0f64, 0);
    for round in 0..30 {
        let mut xs = [[0.0; N]; L];
        let mut ps = [[0.0; N]; L];
        let mut hs = [[[0.0; N]; N]; L];
        for l in 0..L {
            let r = [1e-3, 0.1, 0.5, 1.0, 2.0][(round + l) % 5];
            xs[l] = [0.0; N].map(|_| rng.range(-r, r));
            ps[l] = [0.0; N].map(|_| rng.range(-2.0, 2.0));
            for a in 0..N {
                for b in a..N {
                    hs[l][a][b] = rng.range(-0.3, 0.3);
                    hs[l][b][a] = hs[l][a][b];
                }
            }
        }
        xs[3][1] = f64::NAN;
        // ad_x has eigenvalues of modulus above 2π on both algebras (sl(2): ±2√(x_h²/4 + x_e x_f);
        // the oscillator: ±i x₃): the series diverges (its terms Aⁿp overflow before 240 of
        // them are summed: NonFinite, as the scalar series says).
        xs[6] = [7.0; N];
        let h: [[V<L>; N]; N] = std::array::from_fn(|a| {
            std::array::from_fn(|b| V(std::array::from_fn(|l| hs[l][a][b])))
        });
        let mut live = [true; L];
        live[7] = false;
        let mut jac = [[V([f64::NAN; L]); N]; N];
        let (plain, fail_plain) =
            series_tar_lanes(&algebra, &lanes(&xs), &lanes(&ps), None, &mut jac, &live);
        assert!(jac.iter().flatten().all(|v| v.0.iter().all(|x| x.is_nan())));
        let (t, fail) = series_tar_lanes(
            &algebra,
            &lanes(&xs),
            &lanes(&ps),
            Some(&h),
            &mut jac,
            &live,
        );
        assert_eq!(fail, fail_plain, "failures depend on the Jacobian");
        assert_eq!(fail[7], None, "a lane that is not live");
        for l in 0..7 {
            let want = groupoid.tar(&xs[l], &ps[l]);
            let got: [f64; N] = std::array::from_fn(|i| t[i].0[l]);
            let got_plain: [f64; N] = std::array::from_fn(|i| plain[i].0[l]);
            match want {
                // Refused both ways (where the terms overflow, the two may name it apart:
                // NonFinite or ChartSingular).
                Err(_) => assert!(fail[l].is_some(), "lane {l}"),
                Ok(_) if l == 3 => {}
                Ok(want) => {
                    assert_eq!(fail[l], None, "lane {l}");
                    assert!(
                        same_bits(&got, &got_plain),
                        "lane {l}: values with the Jacobian"
                    );
                    let scale = want.iter().fold(1.0f64, |m, v| m.max(v.abs()));
                    for i in 0..N {
                        worst = worst.max((got[i] - want[i]).abs() / scale);
                    }
                    let xd: [Dual1<N>; N] = std::array::from_fn(|i| Dual1 {
                        v: xs[l][i],
                        g: hs[l][i],
                    });
                    let pd: [Dual1<N>; N] = std::array::from_fn(|i| Dual1::var(ps[l][i], i));
                    // The dual-number series also waits for the derivatives' terms (n times
                    // the values' at the n-th term), so near the singular angle it may refuse
                    // where the values (and the lanes) have converged: no oracle there.
                    let Ok(td) = groupoid.tar(&xd, &pd) else {
                        edge += 1;
                        continue;
                    };
                    let scale = td
                        .iter()
                        .flat_map(|d| d.g)
                        .fold(1.0f64, |m, v| m.max(v.abs()));
                    for r in 0..N {
                        for k in 0..N {
                            worst_jac = worst_jac.max((jac[r][k].0[l] - td[r].g[k]).abs() / scale);
                        }
                    }
                }
            }
        }
        // A NaN in x: NonFinite in lanes, where the scalar series (whose sizes skip NaN, as
        // f64::max does) returns NaN values.
        assert_eq!(fail[3], Some(StepFailure::NonFinite));
        assert!(fail[6].is_some(), "a diverging series accepted");
    }
    assert!(worst <= 1e-14, "values off by {worst:e}");
    assert!(worst_jac <= 1e-12, "Jacobian off by {worst_jac:e}");
    assert!(
        edge <= 6,
        "{edge} of 180 lanes without a dual-number Jacobian"
    );
}

#[test]
fn lane_series_equals_the_scalar_series_and_its_dual_jacobian() {
    chart_against_the_scalar_series(sl2(), 0x5E1_0001);
    chart_against_the_scalar_series(oscillator(), 0x5E1_0002);
}

/// The shared solver's checks (`exp_chart_lanes`) against the generic dual-number step on one
/// algebra: 20 states, with and without 8 extra random terms in S.
fn newton_on<const N: usize>(algebra: LieAlgebra<N>, casimirs: fn(&[f64; N]) -> Vec<f64>, seed: u64)
where
    nalgebra::Const<N>: nalgebra::DimMin<nalgebra::Const<N>, Output = nalgebra::Const<N>>,
{
    let mut rng = Rng::new(seed);
    for extra in [0, 8] {
        let st = stepper(algebra.clone(), polynomial::<N>(&mut rng, extra));
        let states: Vec<[f64; N]> = (0..20).map(|_| state::<N>(&mut rng)).collect();
        let chart = SeriesChart { algebra: &algebra };
        let label = format!("dim {N}, {extra} extra terms");
        newton_against_the_generic_step(&st, chart, &states, casimirs, &label);
    }
}

/// The shared solver's start is second order (`exp_chart_lanes`) on sl(2) and the oscillator
/// algebra, with and without 8 random t², t³ terms in S.
#[test]
fn start_is_second_order_on_any_algebra() {
    fn on<const N: usize>(algebra: LieAlgebra<N>, seed: u64) {
        let mut rng = Rng::new(seed);
        for extra in [0, 8] {
            let st = stepper(algebra.clone(), polynomial::<N>(&mut rng, extra));
            let states: Vec<[f64; N]> = (0..8).map(|_| state::<N>(&mut rng)).collect();
            let chart = SeriesChart { algebra: &algebra };
            start_is_second_order(
                &st,
                chart,
                &states,
                &format!("dim {N}, {extra} extra terms"),
            );
        }
    }
    on(sl2(), 0x5E1_0006);
    on(oscillator(), 0x5E1_0007);
}

#[test]
fn lane_newton_equals_the_generic_step() {
    newton_on(sl2(), sl2_casimirs, 0x5E1_0003);
    newton_on(oscillator(), oscillator_casimirs, 0x5E1_0004);
}

/// The shared solver's bits for every dispatch and block (`exp_chart_lanes`) on the oscillator
/// algebra: the singular lane's x is far past the singular angle.
#[test]
fn lane_newton_is_the_same_for_every_dispatch_and_block() {
    let mut rng = Rng::new(0x5E1_0005);
    let algebra = oscillator();
    let st = stepper(algebra.clone(), polynomial::<4>(&mut rng, 6));
    let sys = SeriesNewton {
        poly: &st.generating.polynomial,
        network: None,
        chart: SeriesChart { algebra: &algebra },
        tol: 1e-12,
        max_iter: 50,
        predict: true,
    };
    let mut mu0: Vec<[f64; 4]> = (0..29).map(|_| state::<4>(&mut rng)).collect();
    mu0[5] = [f64::NAN, 1.0, 0.0, 0.5];
    mu0[17] = [400.0, -300.0, 250.0, 200.0];
    same_for_every_dispatch_and_block(&st, sys, &mu0);
}

/// A learned S (−tH plus a network term) on the oscillator algebra takes the series lanes
/// through the stepper: 8 states × 15 steps, `step` (predicted start, lanes) within 1e-12 of the
/// generic dual-number step, both Casimirs kept to 1e-14 a step, and `step_batch` on the eight
/// at once gives `step`'s bits.
#[test]
fn learned_steps_take_the_series_lanes() {
    let mut rng = Rng::new(0x5E1_0006);
    let mut gf = super::network_lanes::network::<4>(&mut rng, 16, MlpInputs::Plain);
    gf.polynomial = polynomial::<4>(&mut rng, 0);
    gf.mlp_power = 3;
    assert!(gf.network_lanes().is_some(), "the network fits the lanes");
    let st = BisectionStepper::new(
        gf,
        Groupoid::new(oscillator(), Chart::Exp).unwrap(),
        NewtonOptions::default(),
    );
    let mut ws = st.workspace();
    let states: Vec<[f64; 4]> = (0..8).map(|_| state::<4>(&mut rng)).collect();
    let mut worst = 0.0f64;
    let mut batch = states.clone();
    for _ in 0..15 {
        let before = batch.clone();
        let mut res = vec![Err(StepFailure::OutOfDomain); 8];
        st.step_batch(0.1, &mut batch, &[true; 8], &mut res, &mut ws);
        for j in 0..8 {
            res[j].unwrap();
            let (mut one, mut generic) = (before[j], before[j]);
            st.step(0.1, &mut one, &mut ws).unwrap();
            st.step_generic(0.1, &mut generic, &mut ws).unwrap();
            assert!(
                same_bits(&one, &batch[j]),
                "state {j}: batch and step apart"
            );
            let scale = generic.iter().fold(1.0f64, |m, v| m.max(v.abs()));
            for i in 0..4 {
                worst = worst.max((one[i] - generic[i]).abs() / scale);
            }
            for (c0, c1) in oscillator_casimirs(&before[j])
                .iter()
                .zip(oscillator_casimirs(&one))
            {
                assert!((c1 - c0).abs() <= 1e-14 * scale * scale, "Casimir moved");
            }
        }
    }
    assert!(worst <= 1e-12, "lanes vs generic: {worst:e}");
}

/// The coadjoint action in lanes against the algebra's scalar `exp_coadjoint` on both algebras:
/// within 2e-16 of |μ|∞ for |x| from 1e-3 to 3, every Casimir of μ kept to 1e-15 of |μ|²; the
/// same failures (ρ beyond the series' reach: ChartSingular; a NaN: NonFinite) without touching
/// the other lanes; a lane that is not live has none.
fn coadjoint_against_the_scalar<const N: usize>(
    algebra: LieAlgebra<N>,
    casimirs: fn(&[f64; N]) -> Vec<f64>,
    seed: u64,
) {
    let mut rng = Rng::new(seed);
    let (mut worst, mut worst_casimir) = (0.0f64, 0.0f64);
    for round in 0..30 {
        let mut xs = [[0.0; N]; L];
        let mut ms = [[0.0; N]; L];
        for l in 0..L {
            let r = [1e-3, 0.1, 0.5, 1.0, 3.0][(round + l) % 5];
            xs[l] = [0.0; N].map(|_| rng.range(-r, r));
            ms[l] = state::<N>(&mut rng);
        }
        xs[2][0] = f64::NAN;
        xs[5] = [200.0; N];
        let mut live = [true; L];
        live[7] = false;
        let c = algebra.structure_constants();
        let (out, failed) = coadjoint_lanes(c, &lanes(&xs), &lanes(&ms), &live);
        assert_eq!(failed[7], None);
        for l in 0..7 {
            match algebra.exp_coadjoint(&xs[l], &ms[l]) {
                Err(e) => assert_eq!(failed[l], Some(e), "lane {l}"),
                Ok(want) => {
                    assert_eq!(failed[l], None, "lane {l}");
                    let got: [f64; N] = std::array::from_fn(|i| out[i].0[l]);
                    let scale = ms[l].iter().fold(0.0f64, |m, v| m.max(v.abs()));
                    for i in 0..N {
                        worst = worst.max((got[i] - want[i]).abs() / scale);
                    }
                    // Relative to the larger state (sl(2)'s action stretches).
                    let big = got.iter().fold(scale, |m, v| m.max(v.abs()));
                    for (c0, c1) in casimirs(&ms[l]).iter().zip(casimirs(&got)) {
                        worst_casimir = worst_casimir.max((c1 - c0).abs() / (big * big));
                    }
                }
            }
        }
        assert_eq!(failed[2], Some(StepFailure::NonFinite));
        assert_eq!(failed[5], Some(StepFailure::ChartSingular));
    }
    assert!(worst <= 2e-16 * 8.0, "off the scalar action by {worst:e}");
    assert!(worst_casimir <= 1e-15, "Casimirs moved {worst_casimir:e}");
}

#[test]
fn lane_coadjoint_equals_the_scalar_action() {
    coadjoint_against_the_scalar(sl2(), sl2_casimirs, 0x5E1_0007);
    coadjoint_against_the_scalar(oscillator(), oscillator_casimirs, 0x5E1_0008);
}

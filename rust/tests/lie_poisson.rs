//! Lie–Poisson systems beyond so(3): the exponential chart's series, Casimirs and fitted orders
//! of bisection and classical steps on the heavy top (se(3)*, N = 6) and on sl(2, R).

#![allow(clippy::needless_range_loop)]

use super::*;
use crate::classical::{HeavyTop, HeavyTopSplitting, LieMethod, LieStepper, Rk4};
use crate::dual::Dual1;
use crate::structures::lie_groupoid::LieAlgebra;
use crate::structures::lie_poisson::{Hamiltonian, LiePoisson};

/// se(3), basis R1..R3, T1..T3: [R_i,R_j] = ε_ijk R_k, [R_i,T_j] = ε_ijk T_k, [T_i,T_j] = 0.
fn se3() -> LieAlgebra<6> {
    LieAlgebra::se3()
}

/// sl(2, R), basis (h, e, f): [h,e] = 2e, [h,f] = −2f, [e,f] = h.
fn sl2() -> LieAlgebra<3> {
    let mut c = [[[0.0; 3]; 3]; 3];
    c[0][1][1] = 2.0;
    c[1][0][1] = -2.0;
    c[0][2][2] = -2.0;
    c[2][0][2] = 2.0;
    c[1][2][0] = 1.0;
    c[2][1][0] = -1.0;
    LieAlgebra::new(c).unwrap()
}

const TOP_INERTIA: [f64; 3] = [1.0, 1.5, 2.0];
const MGL: f64 = 0.981;
const COM: [f64; 3] = [0.0, 0.0, 1.0];

pub(super) fn heavy_top() -> LiePoisson<6> {
    LiePoisson::heavy_top(TOP_INERTIA, COM.map(|c| MGL * c)).unwrap()
}

/// H = ½ (h² + e² + f²)/… on sl(2): a quadratic form with distinct weights.
fn sl2_system() -> LiePoisson<3> {
    LiePoisson {
        algebra: sl2(),
        hamiltonian: Hamiltonian::new(vec![
            ([2, 0, 0], 0.5),
            ([0, 2, 0], 0.4),
            ([0, 0, 2], 0.3),
            ([0, 1, 1], 0.1),
        ])
        .unwrap(),
    }
}

/// |Γ|² and M·Γ.
fn top_casimirs(mu: &[f64; 6]) -> [f64; 2] {
    [
        mu[3] * mu[3] + mu[4] * mu[4] + mu[5] * mu[5],
        mu[0] * mu[3] + mu[1] * mu[4] + mu[2] * mu[5],
    ]
}

/// μ_h² + 4 μ_e μ_f.
fn sl2_casimir(mu: &[f64; 3]) -> f64 {
    mu[0] * mu[0] + 4.0 * mu[1] * mu[2]
}

/// The bisection stepper of S = −t H (a polynomial generating function) in the exp chart.
/// −tH as monomials of S (its first Taylor term).
pub(super) fn minus_t_h_terms<const N: usize>(system: &LiePoisson<N>) -> Vec<Monomial<N>> {
    system
        .hamiltonian
        .terms()
        .iter()
        .map(|(e, c)| Monomial {
            t_power: 1,
            p_powers: *e,
            coeff: -c,
        })
        .collect()
}

fn minus_t_h_stepper<const N: usize>(system: &LiePoisson<N>) -> BisectionStepper<N> {
    let terms = minus_t_h_terms(system);
    BisectionStepper::new(
        GeneratingFunction::new(Polynomial::new(terms).unwrap(), None, 0, MlpInputs::Plain)
            .unwrap(),
        Groupoid::new(system.algebra.clone(), Chart::Exp).unwrap(),
        NewtonOptions::default(),
    )
}

fn run<const N: usize, S: StepMap<N>>(s: &S, mu0: [f64; N], h: f64, n: usize) -> [f64; N] {
    let mut out = vec![0.0; N * n_records(n, n)];
    let info = rollout(s, &[mu0], h, n, n, &mut out).unwrap();
    assert!(info[0].converged, "{:?}", info[0]);
    std::array::from_fn(|i| out[N + i])
}

fn dist<const N: usize>(a: &[f64; N], b: &[f64; N]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// Fitted order of `s` at time T from steps h and h/2 against a fine RK4 reference.
fn fitted_order<const N: usize, S: StepMap<N>>(
    s: &S,
    system: &LiePoisson<N>,
    mu0: [f64; N],
    t: f64,
    h: f64,
) -> f64 {
    let fine = Rk4 {
        system: system.clone(),
    };
    let exact = run(&fine, mu0, t / 20000.0, 20000);
    let n = (t / h).round() as usize;
    let e1 = dist(&run(s, mu0, h, n), &exact);
    let e2 = dist(&run(s, mu0, h / 2.0, 2 * n), &exact);
    (e1 / e2).log2()
}

#[test]
fn exp_series_on_so3_matches_the_closed_form() {
    let g = Groupoid::so3(Chart::Exp).unwrap();
    let mut rng = Rng::new(7);
    for _ in 0..50 {
        let x = rng.vec3(-1.5, 1.5);
        let p = rng.vec3(-3.0, 3.0);
        let xd: [Dual1<3>; 3] = std::array::from_fn(|i| Dual1::var(x[i], i));
        let pd = p.map(Dual1::cst);
        for sign in [1.0, -1.0] {
            let closed = if sign > 0.0 {
                g.sou(&xd, &pd).unwrap()
            } else {
                g.tar(&xd, &pd).unwrap()
            };
            let series = g.exp_series(&xd, &pd, sign).unwrap();
            for i in 0..3 {
                assert!((closed[i].v - series[i].v).abs() < 1e-13, "{x:?} {p:?}");
                for j in 0..3 {
                    assert!((closed[i].g[j] - series[i].g[j]).abs() < 1e-12);
                }
            }
        }
    }
}

/// sou(x, p) = g(x) · tar(x, p): the coadjoint action (the so(3) rotations in closed form, the
/// exponential series on sl(2) and se(3)) against the two Bernoulli series or chart maps, to
/// round-off, for random x (|x| up to 3) and p; and g(x) keeps every Casimir.
#[test]
fn coadjoint_action_maps_target_to_source_and_keeps_casimirs() {
    fn check<const N: usize>(
        g: &Groupoid<N>,
        rng: &mut Rng,
        casimirs: &dyn Fn(&[f64; N]) -> Vec<f64>,
    ) {
        for _ in 0..300 {
            let r = rng.range(1e-3, 3.0);
            let x0: [f64; N] = std::array::from_fn(|_| rng.range(-1.0, 1.0));
            let scale = r / x0.iter().map(|v| v * v).sum::<f64>().sqrt();
            let x = x0.map(|v| v * scale);
            let p: [f64; N] = std::array::from_fn(|_| rng.range(-2.0, 2.0));
            let (Ok(t), Ok(s)) = (g.tar(&x, &p), g.sou(&x, &p)) else {
                continue; // beyond the series' radius for this algebra
            };
            let moved = g.coadjoint(&x, &t).unwrap();
            let size = s.iter().chain(&t).fold(1.0f64, |m, v| m.max(v.abs()));
            for i in 0..N {
                assert!(
                    (moved[i] - s[i]).abs() <= 1e-13 * size,
                    "{:?} |x| = {r}: component {i}, {} against {}",
                    g.chart,
                    moved[i],
                    s[i]
                );
            }
            for (a, b) in casimirs(&moved).iter().zip(casimirs(&t)) {
                assert!((a - b).abs() <= 1e-13 * size * size, "{a} against {b}");
            }
        }
    }
    let mut rng = Rng::new(0xC0AD_0001);
    let sphere = |m: &[f64; 3]| vec![m[0] * m[0] + m[1] * m[1] + m[2] * m[2]];
    for chart in [Chart::Cayley, Chart::Exp] {
        check(&Groupoid::so3(chart).unwrap(), &mut rng, &sphere);
    }
    check(
        &Groupoid::new(sl2(), Chart::Exp).unwrap(),
        &mut rng,
        &|m: &[f64; 3]| vec![sl2_casimir(m)],
    );
    check(
        &Groupoid::new(se3(), Chart::Exp).unwrap(),
        &mut rng,
        &|m: &[f64; 6]| top_casimirs(m).to_vec(),
    );
}

/// The new state is g(x) · μ, not sou at Newton's last iterate: a Newton tolerance of 0.5 stops
/// after one update and leaves a residual far above round-off in tar(x, p) = μ, yet every
/// Casimir is kept to round-off (sou(x, p) carried C(μ + residual)). so(3) in both charts (the lane
/// solver, at h = 0.5: its second-order start leaves one update from S = −tH at round-off at
/// h = 0.1), sl(2) and se(3) (the generic solve, one at a time and in lockstep).
#[test]
fn casimirs_do_not_depend_on_the_newton_residual() {
    fn check<const N: usize>(
        system: &LiePoisson<N>,
        chart: Chart,
        h: f64,
        mu0: &[[f64; N]],
        casimirs: &dyn Fn(&[f64; N]) -> Vec<f64>,
    ) where
        nalgebra::Const<N>: nalgebra::DimMin<nalgebra::Const<N>, Output = nalgebra::Const<N>>,
    {
        let mut st = minus_t_h_stepper(system);
        st.realization = Groupoid::new(system.algebra.clone(), chart).unwrap();
        st.newton.tol = 0.5;
        let n = 200;
        let mut out = vec![0.0; mu0.len() * N * n_records(n, n)];
        let info = rollout(&st, mu0, h, n, n, &mut out).unwrap();
        let mut residual = 0.0f64;
        for (j, m0) in mu0.iter().enumerate() {
            assert!(info[j].converged, "{:?}", info[j]);
            let end: [f64; N] = std::array::from_fn(|i| out[(2 * j + 1) * N + i]);
            for (a, b) in casimirs(&end).iter().zip(casimirs(m0)) {
                assert!((a - b).abs() <= 1e-13, "{chart:?}: {a} against {b}");
            }
            residual = residual.max(info[j].max_residual);
        }
        // The residual is there: the Casimirs are kept despite it, not for want of it.
        assert!(residual > 1e-12, "{chart:?}: residual {residual:e}");
    }
    let sphere = |m: &[f64; 3]| vec![m[0] * m[0] + m[1] * m[1] + m[2] * m[2]];
    let body = LiePoisson {
        algebra: LieAlgebra::so3().unwrap(),
        hamiltonian: Hamiltonian::new(vec![
            ([2, 0, 0], 1.0 / 3.0),
            ([0, 2, 0], 0.25),
            ([0, 0, 2], 0.2),
        ])
        .unwrap(),
    };
    let mut rng = Rng::new(0xC0AD_0002);
    let states: Vec<[f64; 3]> = (0..11).map(|_| rng.sphere(0.9)).collect();
    for chart in [Chart::Cayley, Chart::Exp] {
        check(&body, chart, 0.5, &states, &sphere);
    }
    check(&sl2_system(), Chart::Exp, 0.1, &states, &|m: &[f64; 3]| {
        vec![sl2_casimir(m)]
    });
    check(
        &sl2_system(),
        Chart::Exp,
        0.1,
        &states[..1],
        &|m: &[f64; 3]| vec![sl2_casimir(m)],
    );
    let tops: Vec<[f64; 6]> = (0..11)
        .map(|_| std::array::from_fn(|_| rng.range(-0.6, 0.6)))
        .collect();
    check(&heavy_top(), Chart::Exp, 0.1, &tops, &|m: &[f64; 6]| {
        top_casimirs(m).to_vec()
    });
}

#[test]
fn exp_series_refuses_beyond_its_radius() {
    let g = Groupoid::so3(Chart::Exp).unwrap();
    let x = [0.0, 0.0, 6.0];
    assert_eq!(
        g.exp_series(&x, &[1.0, 0.0, 0.0], 1.0),
        Err(StepFailure::ChartSingular)
    );
}

#[test]
fn cayley_is_refused_off_so3() {
    let e = Groupoid::new(se3(), Chart::Cayley).unwrap_err();
    assert!(e.to_string().contains("so(3) only"), "{e}");
}

#[test]
fn bad_structure_constants_are_refused() {
    let mut c = [[[0.0; 3]; 3]; 3];
    c[0][1][2] = 1.0; // not antisymmetric
    assert!(LieAlgebra::new(c)
        .unwrap_err()
        .to_string()
        .contains("antisymmetric"));
    // Antisymmetric but not a Lie algebra: [e0,e1] = e0, [e1,e2] = e1, [e2,e0] = e1.
    let mut c = [[[0.0; 3]; 3]; 3];
    for (i, j, k) in [(0, 1, 0), (1, 2, 1), (2, 0, 1)] {
        c[i][j][k] = 1.0;
        c[j][i][k] = -1.0;
    }
    assert!(LieAlgebra::new(c)
        .unwrap_err()
        .to_string()
        .contains("Jacobi"));
}

#[test]
fn heavy_top_bisection_keeps_both_casimirs() {
    let sys = heavy_top();
    let st = minus_t_h_stepper(&sys);
    let mu0 = [0.3, -0.8, 1.2, 0.6, 0.0, 0.8];
    let c0 = top_casimirs(&mu0);
    let n = 2000;
    let mut out = vec![0.0; 6 * n_records(n, 1)];
    let info = rollout(&st, &[mu0], 0.1, n, 1, &mut out).unwrap();
    assert!(info[0].converged);
    let mut drift = [0.0f64; 2];
    for rec in out.chunks_exact(6) {
        let c = top_casimirs(&std::array::from_fn(|i| rec[i]));
        for k in 0..2 {
            drift[k] = drift[k].max((c[k] - c0[k]).abs());
        }
    }
    assert!(drift[0] < 1e-12 && drift[1] < 1e-12, "{drift:?}");
}

#[test]
fn heavy_top_methods_have_their_orders() {
    let sys = heavy_top();
    let mu0 = [0.3, -0.8, 1.2, 0.6, 0.0, 0.8];
    let newton = NewtonOptions::default();
    let cases: [(&str, f64, LieStepper<6>); 3] = [
        (
            "rk4",
            4.0,
            LieStepper::new(LieMethod::Rk4, sys.clone(), None, newton).unwrap(),
        ),
        (
            "midpoint",
            2.0,
            LieStepper::new(LieMethod::Midpoint, sys.clone(), None, newton).unwrap(),
        ),
        (
            "splitting",
            2.0,
            LieStepper::new(
                LieMethod::Splitting,
                sys.clone(),
                Some(HeavyTop::new(TOP_INERTIA, MGL, COM).unwrap()),
                newton,
            )
            .unwrap(),
        ),
    ];
    for (name, order, st) in &cases {
        let p = fitted_order(st, &sys, mu0, 2.0, 0.05);
        assert!((p - order).abs() < 0.2, "{name}: fitted order {p}");
    }
    let p = fitted_order(&minus_t_h_stepper(&sys), &sys, mu0, 2.0, 0.05);
    assert!((p - 2.0).abs() < 0.2, "-tH bisection: fitted order {p}");
}

#[test]
fn heavy_top_splitting_keeps_casimirs_to_round_off() {
    let top = HeavyTopSplitting {
        top: HeavyTop::new(TOP_INERTIA, MGL, COM).unwrap(),
    };
    let mu0 = [0.3, -0.8, 1.2, 0.6, 0.0, 0.8];
    let c0 = top_casimirs(&mu0);
    let c = top_casimirs(&run(&top, mu0, 0.1, 10_000));
    assert!((c[0] - c0[0]).abs() < 1e-12 && (c[1] - c0[1]).abs() < 1e-12);
}

#[test]
fn splitting_needs_the_heavy_top() {
    let e = LieStepper::new(
        LieMethod::Splitting,
        sl2_system(),
        None,
        NewtonOptions::default(),
    )
    .unwrap_err();
    assert!(e.to_string().contains("heavy top"), "{e}");
}

#[test]
fn sl2_bisection_keeps_its_casimir_and_is_second_order() {
    let sys = sl2_system();
    let st = minus_t_h_stepper(&sys);
    let mu0 = [0.4, 0.7, -0.2];
    let c0 = sl2_casimir(&mu0);
    let end = run(&st, mu0, 0.05, 4000);
    assert!((sl2_casimir(&end) - c0).abs() < 1e-12);
    let p = fitted_order(&st, &sys, mu0, 1.0, 0.05);
    assert!((p - 2.0).abs() < 0.2, "fitted order {p}");
    let rk = Rk4 {
        system: sys.clone(),
    };
    let p = fitted_order(&rk, &sys, mu0, 1.0, 0.05);
    assert!((p - 4.0).abs() < 0.3, "rk4 fitted order {p}");
}

/// The predicted start (p₀ = μ − ½ ad_{x₀}ᵀ μ, what `step` and `step_batch` run) against the
/// generic step from μ (`step_generic`): the same solution to Newton's tolerance, in fewer
/// updates; and a batch in lockstep gives each trajectory the bits of its one-trajectory step.
#[test]
fn the_predicted_start_solves_the_same_step_in_fewer_updates() {
    fn check<const N: usize>(sys: &LiePoisson<N>, states: &[[f64; N]], h: f64) -> (u32, u32)
    where
        nalgebra::Const<N>: nalgebra::DimMin<nalgebra::Const<N>, Output = nalgebra::Const<N>>,
    {
        let st = minus_t_h_stepper(sys);
        let mut ws = st.workspace();
        let (mut predicted, mut plain) = (0, 0);
        for mu0 in states {
            let (mut a, mut b) = (*mu0, *mu0);
            for _ in 0..50 {
                let sa = st.step(h, &mut a, &mut ws).unwrap();
                let sb = st.step_generic(h, &mut b, &mut ws).unwrap();
                predicted += sa.iterations;
                plain += sb.iterations;
                let scale = a.iter().fold(1.0f64, |m, v| m.max(v.abs()));
                assert!(dist(&a, &b) <= 1e-11 * scale, "{a:?} {b:?}");
                b = a;
            }
        }
        // Lockstep (a batch, polynomial S: batched jets and gradients) against one at a time.
        let mut batch: Vec<[f64; N]> = states.to_vec();
        let mut results = vec![Err(StepFailure::OutOfDomain); batch.len()];
        st.step_batch(
            h,
            &mut batch,
            &vec![true; states.len()],
            &mut results,
            &mut ws,
        );
        for (mu0, got) in states.iter().zip(&batch) {
            let mut one = *mu0;
            st.step(h, &mut one, &mut ws).unwrap();
            assert_eq!(&one, got, "lockstep and one-at-a-time steps differ");
        }
        (predicted, plain)
    }
    let tops = [
        [0.3, -0.8, 1.2, 0.6, 0.0, 0.8],
        [2.0, 0.5, -1.0, 0.0, 0.6, 0.8],
        [-1.1, 0.4, 0.9, 0.36, 0.48, -0.8],
        [0.5, 1.5, -0.2, -0.6, 0.8, 0.0],
        [1.4, -1.2, 0.3, 0.0, 0.0, 1.0],
    ];
    let (predicted, plain) = check(&heavy_top(), &tops, 0.1);
    assert!(
        predicted < plain,
        "heavy top: {predicted} updates against {plain}"
    );
    let sl2_states = [
        [0.5, 0.3, -0.2],
        [1.0, -0.4, 0.7],
        [-0.3, 0.8, 0.1],
        [0.2, 0.2, 0.9],
    ];
    let (predicted, plain) = check(&sl2_system(), &sl2_states, 0.1);
    assert!(
        predicted < plain,
        "sl(2): {predicted} updates against {plain}"
    );
}

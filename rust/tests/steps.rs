//! Single bisection steps: Newton Jacobians, Casimirs, fitted orders and reported failures.

// Index loops over 3-vectors and 3×3 matrices read more clearly as the formulas they test.
#![allow(clippy::needless_range_loop)]

use super::*;

/// For the Cayley chart the Newton Jacobian has the closed form of DESIGN.md §1; the dual-number
/// chart (how the stepper builds it) must agree.
#[test]
fn cayley_newton_jacobian_matches_closed_form() {
    use crate::dual::Dual1;
    let mut rng = Rng::new(0x5EED_0004);
    for k in 0..20 {
        let gf = random_generating(&mut rng, ALL_INPUTS[k % 2]);
        let mut ws = gf.workspace();
        let h = rng.range(0.05, 0.5);
        let r = rng.range(1.0, 4.0);
        let p = rng.sphere(r);
        let jet = gf.jet(h, &p, &mut ws);
        let (x, hs) = (jet.grad(), jet.hess());
        let xd: [Dual1<3>; 3] = std::array::from_fn(|i| Dual1 { v: x[i], g: hs[i] });
        let pd: [Dual1<3>; 3] = std::array::from_fn(|i| Dual1::var(p[i], i));
        let t = Chart::Cayley.tar(&xd, &pd).unwrap();
        // J = (I − ½ x̂ + ¼ x xᵀ) + (½ p̂ + ¼ (x pᵀ + (x·p) I)) · Hs
        let hat = |v: &[f64; 3]| [[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]];
        let (xh, ph) = (hat(&x), hat(&p));
        let xp = dot(&x, &p);
        for r in 0..3 {
            for c in 0..3 {
                let id = if r == c { 1.0 } else { 0.0 };
                let a = id - 0.5 * xh[r][c] + 0.25 * x[r] * x[c];
                let b: f64 = (0..3)
                    .map(|k| {
                        let idk = if r == k { 1.0 } else { 0.0 };
                        (0.5 * ph[r][k] + 0.25 * (x[r] * p[k] + xp * idk)) * hs[k][c]
                    })
                    .sum();
                let j = a + b;
                assert!(
                    (t[r].g[c] - j).abs() < 1e-13 * (1.0 + j.abs()),
                    "J[{r}][{c}] = {} vs closed form {j}",
                    t[r].g[c]
                );
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// 2. The stepper: Casimir, order, residual, failures
// ---------------------------------------------------------------------------------------------

fn casimir_is_kept(chart: Chart, seed: u64) {
    let mut rng = Rng::new(seed);
    let mut worst_step = 0.0f64;
    let mut worst_total = 0.0f64;
    for case in 0..4 {
        let inputs = ALL_INPUTS[case % 2];
        let st = stepper(random_generating(&mut rng, inputs), chart);
        let mut ws = st.workspace();
        for _ in 0..3 {
            let r = rng.range(1.0, 4.0);
            let mu0 = rng.sphere(r);
            let c0 = dot(&mu0, &mu0);
            let mut mu = mu0;
            for k in 0..1000 {
                let before = dot(&mu, &mu);
                st.step(0.1, &mut mu, &mut ws).unwrap_or_else(|e| {
                    panic!("{chart:?} {inputs:?} case {case} mu0 {mu0:?}: step {k} failed: {e:?}")
                });
                let rel = (dot(&mu, &mu) - before).abs() / before;
                worst_step = worst_step.max(rel);
                assert!(
                    rel <= 1e-13,
                    "{chart:?} {inputs:?} case {case} mu0 {mu0:?}: step {k} changed |mu|^2 by {rel:e}"
                );
            }
            let rel = (dot(&mu, &mu) - c0).abs() / c0;
            worst_total = worst_total.max(rel);
            assert!(
                rel <= 1e-12,
                "{chart:?} {inputs:?} case {case} mu0 {mu0:?}: 1000 steps changed |mu|^2 by {rel:e}"
            );
            // The state moved: a map that does nothing would keep the Casimir trivially.
            assert!(norm(&sub(&mu, &mu0)) > 1e-3 * norm(&mu0));
        }
    }
    eprintln!("{chart:?}: worst relative Casimir change per step {worst_step:e}, over 1000 steps {worst_total:e}");
}

#[test]
fn casimir_kept_to_round_off_cayley() {
    casimir_is_kept(Chart::Cayley, 0x5EED_0010);
}

#[test]
fn casimir_kept_to_round_off_exp() {
    casimir_is_kept(Chart::Exp, 0x5EED_0011);
}

/// μ̇ = μ × ∇H(μ) with ∇H = μ / I.
fn rigid_body_rhs(mu: &[f64; 3]) -> [f64; 3] {
    let grad = [mu[0] / INERTIA[0], mu[1] / INERTIA[1], mu[2] / INERTIA[2]];
    cross(mu, &grad)
}

/// Classical RK4 with `n` steps over time `t`.
fn rk4(mu0: [f64; 3], t: f64, n: usize) -> [f64; 3] {
    let dt = t / n as f64;
    let mut y = mu0;
    let axpy =
        |y: &[f64; 3], a: f64, k: &[f64; 3]| [y[0] + a * k[0], y[1] + a * k[1], y[2] + a * k[2]];
    for _ in 0..n {
        let k1 = rigid_body_rhs(&y);
        let k2 = rigid_body_rhs(&axpy(&y, 0.5 * dt, &k1));
        let k3 = rigid_body_rhs(&axpy(&y, 0.5 * dt, &k2));
        let k4 = rigid_body_rhs(&axpy(&y, dt, &k3));
        for i in 0..3 {
            y[i] += dt / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
        }
    }
    y
}

/// S = −tH is a second-order integrator (S₂ = 0 in both charts): the local error is O(h³), so
/// halving h divides it by about 8. The Newton residual it reports is at round-off.
#[test]
fn minus_t_h_step_is_second_order_with_tight_residual() {
    let mut rng = Rng::new(0x5EED_0020);
    let mut states = vec![[1.0, 1.0, 2.0], [3.0, 2.0, 0.0]];
    for _ in 0..3 {
        let r = rng.range(1.0, 4.0);
        states.push(rng.sphere(r));
    }
    for chart in [Chart::Cayley, Chart::Exp] {
        let st = hamiltonian_stepper(chart);
        let mut ws = st.workspace();
        for mu0 in &states {
            let errs: Vec<f64> = [0.1, 0.05, 0.025]
                .iter()
                .map(|&h| {
                    let mut mu = *mu0;
                    let stats = st.step(h, &mut mu, &mut ws).unwrap();
                    assert!(
                        stats.residual <= 1e-13 * norm(mu0),
                        "{chart:?} {mu0:?} h={h}: residual {}",
                        stats.residual
                    );
                    assert!(stats.iterations >= 1);
                    let exact = rk4(*mu0, h, 2000);
                    norm(&sub(&mu, &exact))
                })
                .collect();
            eprintln!("{chart:?} {mu0:?}: local errors at h = 0.1, 0.05, 0.025: {errs:?}");
            for w in errs.windows(2) {
                let ratio = w[0] / w[1];
                assert!(
                    (7.0..=9.0).contains(&ratio),
                    "{chart:?} {mu0:?}: err(h)/err(h/2) = {ratio} (errors {errs:?}), expected about 8"
                );
            }
        }
    }
}

/// The Taylor K=3 function of DESIGN.md (Cayley chart) is a 4th-order integrator: its local error
/// is O(h⁵), a ratio of about 32 — the test vectors for S₃ are right.
#[test]
fn taylor3_step_is_fourth_order() {
    let gf = GeneratingFunction::new(
        Polynomial::new(taylor3()).unwrap(),
        None,
        0,
        MlpInputs::Plain,
    )
    .unwrap();
    let st = stepper(gf, Chart::Cayley);
    let mut ws = st.workspace();
    for mu0 in [[1.0, 1.0, 2.0], [3.0, 2.0, 0.0], [-0.5, 1.5, 1.0]] {
        let errs: Vec<f64> = [0.1, 0.05]
            .iter()
            .map(|&h| {
                let mut mu = mu0;
                st.step(h, &mut mu, &mut ws).unwrap();
                norm(&sub(&mu, &rk4(mu0, h, 4000)))
            })
            .collect();
        let ratio = errs[0] / errs[1];
        eprintln!("Taylor K=3 {mu0:?}: local errors at h = 0.1, 0.05: {errs:?}, ratio {ratio}");
        assert!(
            (28.0..=36.0).contains(&ratio),
            "{mu0:?}: ratio {ratio} (errors {errs:?}), expected about 32"
        );
    }
}

/// Newton failure is an Err from `step`, and the state is left untouched.
#[test]
fn newton_failure_is_reported_by_step() {
    let mu0 = [1.0, 1.0, 2.0];
    // A huge step of −tH. (In the Cayley chart tar is cubic in p and Newton from μ still finds
    // the small root up to h ≈ 1e8; beyond, it runs out of iterations or overflows. The
    // exponential chart leaves its domain |x| < 2π − 0.1 already at h = 10.)
    let cases = [
        (Chart::Cayley, vec![1e30, 1e100, 1e200, 1e300, f64::MAX]),
        (Chart::Exp, vec![10.0, 1e8, 1e300, f64::MAX]),
    ];
    for (chart, hs) in cases {
        let st = hamiltonian_stepper(chart);
        let mut ws = st.workspace();
        for h in hs {
            let mut mu = mu0;
            let r = st.step(h, &mut mu, &mut ws);
            assert!(
                r.is_err(),
                "{chart:?} h = {h}: expected a failure, got {r:?}"
            );
            if chart == Chart::Exp && h < 1e300 {
                assert_eq!(r, Err(StepFailure::ChartSingular));
            }
            assert_eq!(mu, mu0, "a failed step must not move the state");
        }
        // The same stepper still works at a sane step afterwards (no state carried over).
        let mut mu = mu0;
        assert!(st.step(0.1, &mut mu, &mut ws).is_ok());
    }
    // A huge MLP output: S = −tH + t · 1e12 · tanh(p₁ + p₂ + p₃ − 1).
    let mlp = Mlp::new(vec![
        Layer::new(4, 1, vec![0.0, 1.0, 1.0, 1.0], vec![-1.0]).unwrap(),
        Layer::new(1, 1, vec![1e12], vec![0.0]).unwrap(),
    ])
    .unwrap();
    for chart in [Chart::Cayley, Chart::Exp] {
        let gf = GeneratingFunction::new(
            Polynomial::new(minus_t_h()).unwrap(),
            Some(mlp.clone()),
            1,
            MlpInputs::Plain,
        )
        .unwrap();
        let st = stepper(gf, chart);
        let mut ws = st.workspace();
        let mut mu = mu0;
        let r = st.step(0.1, &mut mu, &mut ws);
        assert!(
            r.is_err(),
            "{chart:?} huge MLP: expected a failure, got {r:?}"
        );
        assert_eq!(mu, mu0);
    }
    // An iteration cap of 1 cannot be met by a nonlinear S.
    let mut st = hamiltonian_stepper(Chart::Cayley);
    st.newton = NewtonOptions::validated(1e-12, 1).unwrap();
    let mut ws = st.workspace();
    let mut mu = mu0;
    assert_eq!(
        st.step(0.1, &mut mu, &mut ws),
        Err(StepFailure::NotConverged)
    );
}

/// The Newton update's explicit inverse against nalgebra's LU solve, on seeded random matrices:
/// near the identity (as a step's Jacobian is), merely well conditioned, and ill conditioned
/// (condition numbers up to ~1e10, built as U diag(σ) Vᵀ from rotations). The solution error is
/// bounded by the conditioning, as an LU solve's is. N = 3 takes the cofactor formula, N = 4
/// and 6 the LU-based inverse.
#[test]
fn explicit_inverse_solves_like_lu() {
    use crate::stepper::{inverse3, Inverse};
    use nalgebra::{Matrix3, SMatrix, SVector};
    let mut rng = Rng::new(0x5EED_0017);
    let rotation = |rng: &mut Rng| {
        let a = rng.vec3(-1.0, 1.0);
        let th = rng.range(0.0, std::f64::consts::PI);
        nalgebra::Rotation3::new(nalgebra::Vector3::new(a[0], a[1], a[2]).normalize() * th)
            .into_inner()
    };
    for k in 0..3000 {
        let m: Matrix3<f64> = match k % 3 {
            0 => Matrix3::identity() + Matrix3::from_fn(|_, _| rng.range(-0.3, 0.3)),
            1 => Matrix3::from_fn(|_, _| rng.range(-2.0, 2.0)),
            _ => {
                let s = 10f64.powf(-rng.range(0.0, 10.0));
                let d = Matrix3::from_diagonal(&nalgebra::Vector3::new(1.0, rng.range(s, 1.0), s));
                rotation(&mut rng) * d * rotation(&mut rng).transpose() * rng.range(0.1, 10.0)
            }
        };
        let f = SVector::<f64, 3>::from_fn(|_, _| rng.range(-1.0, 1.0));
        let Some(reference) = m.lu().solve(&f) else {
            continue;
        };
        let rows: [[f64; 3]; 3] = std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]));
        let inv = Inverse::<3>::new(&rows).unwrap();
        let delta = inv.apply(&[f[0], f[1], f[2]]);
        let cond = m.norm() * m.try_inverse().unwrap().norm();
        let err = (0..3).fold(0.0f64, |e, i| e.max((delta[i] - reference[i]).abs()));
        let bound = 20.0 * f64::EPSILON * cond * reference.amax().max(f.amax() / m.norm());
        assert!(err <= bound, "k = {k}: error {err:e}, bound {bound:e}");
        assert_eq!(inverse3(&rows), Some(inv.0));
    }
    // Other N: nalgebra's LU inverse.
    for _ in 0..200 {
        let m = SMatrix::<f64, 6, 6>::identity()
            + SMatrix::<f64, 6, 6>::from_fn(|_, _| rng.range(-0.2, 0.2));
        let f = SVector::<f64, 6>::from_fn(|_, _| rng.range(-1.0, 1.0));
        let rows: [[f64; 6]; 6] = std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]));
        let delta = Inverse::<6>::new(&rows)
            .unwrap()
            .apply(&std::array::from_fn(|i| f[i]));
        let reference = m.lu().solve(&f).unwrap();
        for i in 0..6 {
            assert!((delta[i] - reference[i]).abs() < 1e-14, "N = 6");
        }
    }
}

/// Singular, NaN and infinite Jacobians fail cleanly with SingularJacobian, never a panic.
#[test]
fn explicit_inverse_refuses_singular_and_non_finite_matrices() {
    use crate::stepper::Inverse;
    let singular = [[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.5, -1.0, 2.0]];
    let zero = [[0.0; 3]; 3];
    let mut nan = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    nan[1][2] = f64::NAN;
    let mut inf = nan;
    inf[1][2] = f64::INFINITY;
    // Finite entries whose determinant underflows to 0.
    let tiny = [[1e-120, 0.0, 0.0], [0.0, 1e-120, 0.0], [0.0, 0.0, 1e-120]];
    for m in [singular, zero, nan, inf, tiny] {
        assert_eq!(
            Inverse::<3>::new(&m),
            Err(StepFailure::SingularJacobian),
            "{m:?}"
        );
    }
    let singular4 = [
        [1.0, 2.0, 0.0, 0.0],
        [2.0, 4.0, 0.0, 0.0],
        [0.0; 4],
        [0.0, 0.0, 0.0, 1.0],
    ];
    assert_eq!(
        Inverse::<4>::new(&singular4),
        Err(StepFailure::SingularJacobian)
    );
    let mut nan4 = [[0.0; 4]; 4];
    for i in 0..4 {
        nan4[i][i] = 1.0;
    }
    nan4[0][3] = f64::NAN;
    assert_eq!(Inverse::<4>::new(&nan4), Err(StepFailure::SingularJacobian));
}

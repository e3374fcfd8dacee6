//! The one bisection stepper: batched steps against the generic step on the Lie-algebra
//! groupoid (bit-identical), and the log-canonical structure of Lotka–Volterra
//! (units, fitted orders of Taylor-HJ and the log splittings, Casimirs, the positive orthant).

#![allow(clippy::needless_range_loop)]

use super::splitting_lanes::{check_lanes_equal_scalar, ulps};
use super::*;
use crate::exp::{exp, exp_lanes, EXP_MAX, EXP_MIN};
use crate::lanes::{Isa, LANES};
use crate::realization::Realization;
use crate::structures::log_canonical::PREDICT_MAX_SHIFT;
use crate::structures::{
    ExpMonomial, ExpPolynomial, LogBisection, LogCanonical, LogClassical, LogMethod, LogSystem,
    OrthantChecked,
};

/// The batched step (lockstep Newton over a chunk of trajectories, or SIMD lanes) is the
/// one-trajectory step, bit for bit, on the Lie-algebra groupoid with full Newton.
#[test]
fn batched_steps_are_the_one_trajectory_step_bit_for_bit() {
    let mut rng = Rng::new(20);
    for chart in [Chart::Cayley, Chart::Exp] {
        for gf in [
            GeneratingFunction::new(
                Polynomial::new(taylor3()).unwrap(),
                None,
                0,
                MlpInputs::Plain,
            )
            .unwrap(),
            random_generating(&mut rng, MlpInputs::Plain),
        ] {
            let newton = NewtonOptions {
                simplified: false,
                ..NewtonOptions::default()
            };
            let stepper = BisectionStepper::new(gf.clone(), Groupoid::so3(chart).unwrap(), newton);
            // A polynomial S steps in lockstep SIMD lanes (batch > 1), an MLP this small one
            // trajectory at a time: both must give the one-trajectory step's bits (the generic
            // path from the predicted start).
            assert_eq!(stepper.batch() > 1, gf.mlp.is_none());
            let mu0: Vec<[f64; 3]> = (0..5).map(|_| rng.sphere(2.0)).collect();
            let steps = 50;
            let mut a = vec![0.0; mu0.len() * n_records(steps, 1) * 3];
            rollout(&stepper, &mu0, 0.1, steps, 1, &mut a).unwrap();
            let mut ws = stepper.workspace();
            for (k, m0) in mu0.iter().enumerate() {
                let mut mu = *m0;
                for s in 1..=steps {
                    stepper.step(0.1, &mut mu, &mut ws).unwrap();
                    let at = (k * n_records(steps, 1) + s) * 3;
                    assert!((0..3).all(|i| a[at + i].to_bits() == mu[i].to_bits()));
                }
            }
        }
    }
}

/// PNN's Lotka–Volterra: c = [[0, 1], [−1, 0]], H = u − ln u + v − 2 ln v.
fn pnn() -> LogSystem<2> {
    let c = LogCanonical::new([[0.0, 1.0], [-1.0, 0.0]]).unwrap();
    LogSystem::new(c, vec![([1, 0], 1.0), ([0, 1], 1.0)], [1.0, 2.0]).unwrap()
}

/// S = t S₁ (+ t³ S₃) for PNN's system: S₁ = −(u + v) + (ln u + 2 ln v), and S₃ as derived
/// by the Python HJ series (checked there against the flow).
pub(super) fn pnn_taylor(order: u32) -> LogBisection<2> {
    let mut terms = vec![
        ExpMonomial {
            t_power: 1,
            exponents: [1, 0],
            coeff: -1.0,
        },
        ExpMonomial {
            t_power: 1,
            exponents: [0, 1],
            coeff: -1.0,
        },
    ];
    if order >= 3 {
        for (e, c) in [
            ([2, 1], -1.0 / 24.0),
            ([1, 1], 0.25),
            ([0, 1], -1.0 / 24.0),
            ([1, 2], -1.0 / 24.0),
            ([1, 0], -1.0 / 6.0),
        ] {
            terms.push(ExpMonomial {
                t_power: 3,
                exponents: e,
                coeff: c,
            });
        }
    }
    LogBisection::unit_scale(
        ExpPolynomial::new(terms, [1.0, 2.0]).unwrap(),
        LogCanonical::new([[0.0, 1.0], [-1.0, 0.0]]).unwrap(),
        NewtonOptions::default(),
    )
}

/// Final states in q of `n_steps` steps of size T/n_steps from `q0`.
fn final_state<S: StepMap<2>>(stepper: &S, q0: [f64; 2], t: f64, n_steps: usize) -> [f64; 2] {
    let mut out = vec![0.0; n_records(n_steps, n_steps) * 2];
    let info = rollout(
        stepper,
        &[q0],
        t / n_steps as f64,
        n_steps,
        n_steps,
        &mut out,
    )
    .unwrap();
    assert!(info[0].converged);
    [out[2], out[3]]
}

fn fitted_order<S: StepMap<2>>(stepper: &S, q0: [f64; 2], reference: [f64; 2]) -> f64 {
    let e = |n: usize| {
        let q = final_state(stepper, q0, 1.0, n);
        (q[0] - reference[0]).abs().max((q[1] - reference[1]).abs())
    };
    (e(10) / e(20)).log2()
}

#[test]
fn log_canonical_units_and_linearity() {
    let g = LogCanonical::new([[0.0, 1.5, -2.0], [-1.5, 0.0, 0.5], [2.0, -0.5, 0.0]]).unwrap();
    let q = [0.3, -0.2, 1.1];
    assert_eq!(g.sou(&[0.0; 3], &q).unwrap(), q);
    assert_eq!(g.tar(&[0.0; 3], &q).unwrap(), q);
    // sou − tar = −c P: the step q_{k+1} − q_k = −c ∇S.
    let p = [0.7, -0.4, 0.2];
    let (s, t) = (g.sou(&p, &q).unwrap(), g.tar(&p, &q).unwrap());
    for i in 0..3 {
        let cp: f64 = (0..3).map(|j| g.c()[i][j] * p[j]).sum();
        assert!((s[i] - t[i] + cp).abs() < 1e-15);
    }
    assert!(LogCanonical::new([[0.0, 1.0], [1.0, 0.0]]).is_err());
    assert!(LogCanonical::new([[0.0, f64::NAN], [f64::NAN, 0.0]]).is_err());
}

/// Taylor-HJ of order 1 and 3 has order 2 and 4; Strang and Suzuki splittings 2 and 4; RK4 4
/// and midpoint 2: against a Taylor-5 run of 2000 steps.
#[test]
fn log_canonical_fitted_orders() {
    let q0 = [0.0, (0.8f64).ln()];
    let reference = final_state(&pnn_taylor(3), q0, 1.0, 4000);
    for (order, expected) in [(1, 2.0), (3, 4.0)] {
        let p = fitted_order(&pnn_taylor(order), q0, reference);
        assert!((p - expected).abs() < 0.15, "Taylor {order}: order {p}");
    }
    let newton = NewtonOptions::default();
    for (method, expected) in [(LogMethod::Splitting, 2.0), (LogMethod::Splitting4, 4.0)] {
        let s = LogClassical::new(method, pnn(), newton).unwrap();
        let p = fitted_order(&s, q0, reference);
        assert!((p - expected).abs() < 0.15, "{method:?}: order {p}");
    }
    // RK4 and the midpoint rule step x.
    let x0 = q0.map(f64::exp);
    let xref = reference.map(f64::exp);
    for (method, expected) in [(LogMethod::Rk4, 4.0), (LogMethod::Midpoint, 2.0)] {
        let s = LogClassical::new(method, pnn(), newton).unwrap();
        let p = fitted_order(&s, x0, xref);
        assert!((p - expected).abs() < 0.15, "{method:?}: order {p}");
    }
}

/// A 3D Lotka–Volterra with the Casimir x₁x₃/x₂ (c k = 0 for k = (1, −1, 1)): kept to
/// round-off over 10⁴ steps by the Taylor-HJ step and the log splitting.
#[test]
fn log_canonical_casimir_is_kept() {
    let c = [[0.0, 1.0, 1.0], [-1.0, 0.0, 1.0], [-1.0, -1.0, 0.0]];
    let b = [1.0, 2.0, 1.0];
    let terms: Vec<ExpMonomial<3>> = (0..3)
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
    let taylor = OrthantChecked(LogBisection::unit_scale(
        ExpPolynomial::new(terms, b).unwrap(),
        LogCanonical::new(c).unwrap(),
        NewtonOptions::default(),
    ));
    let system = LogSystem::new(
        LogCanonical::new(c).unwrap(),
        vec![([1, 0, 0], 1.0), ([0, 1, 0], 1.0), ([0, 0, 1], 1.0)],
        b,
    )
    .unwrap();
    let split = LogClassical::new(LogMethod::Splitting, system, NewtonOptions::default()).unwrap();
    let q0 = [0.2, -0.3, 0.5];
    let casimir = |q: &[f64]| q[0] - q[1] + q[2];
    let steps = 10_000;
    let c0 = casimir(&q0);
    let mut out = vec![0.0; n_records(steps, 100) * 3];
    let check = |info: Vec<TrajectoryInfo>, out: &[f64]| {
        assert!(info[0].converged);
        let drift = out
            .chunks(3)
            .map(|q| (casimir(q) - c0).abs())
            .fold(0.0, f64::max);
        assert!(drift < 1e-12 * c0.abs(), "Casimir drift {drift}");
    };
    check(
        rollout(&split, &[q0], 0.1, steps, 100, &mut out).unwrap(),
        &out,
    );
    check(
        rollout(&taylor, &[q0], 0.1, steps, 100, &mut out).unwrap(),
        &out,
    );
    // The state moved: the test is not vacuous.
    assert!((out[out.len() - 3] - q0[0]).abs() > 1e-3);
}

/// A step that leaves the positive orthant is a failure, never a silent NaN: RK4 in x with a
/// step far too large, and a Taylor step whose e^q overflows.
#[test]
fn log_canonical_leaving_the_orthant_fails() {
    let rk4 = LogClassical::new(LogMethod::Rk4, pnn(), NewtonOptions::default()).unwrap();
    let mut out = vec![0.0; n_records(5, 1) * 2];
    let info = rollout(&rk4, &[[1.0, 3.0]], 2.0, 5, 1, &mut out).unwrap();
    assert!(!info[0].converged);
    assert_eq!(info[0].failure, Some(StepFailure::OutOfDomain));
    assert!(out[2 * (info[0].failed_step as usize + 1)..]
        .iter()
        .all(|v| v.is_nan()));
    let taylor = OrthantChecked(pnn_taylor(1));
    let info = rollout(&taylor, &[[700.0, 0.0]], 0.1, 5, 1, &mut out).unwrap();
    assert!(!info[0].converged);
    assert!(info[0].failure.is_some());
    // The splittings need a separable Hamiltonian.
    let mixed = LogSystem::new(
        LogCanonical::new([[0.0, 1.0], [-1.0, 0.0]]).unwrap(),
        vec![([1, 1], 1.0)],
        [1.0, 1.0],
    )
    .unwrap();
    assert!(LogClassical::new(LogMethod::Splitting, mixed, NewtonOptions::default()).is_err());
}

/// The project's bisection stepper runs on the log-canonical realization too: with any S
/// (here −tH of the rigid body, random polynomial terms and a random MLP, read as a function
/// of q), one at a time and batched with simplified Newton, the step is a Poisson map of the
/// constant bracket c, so the Casimir k·q (c k = 0) is kept to round-off.
#[test]
fn bisection_stepper_on_the_log_canonical_realization_keeps_the_casimir() {
    let mut rng = Rng::new(21);
    let c = [[0.0, 1.0, 1.0], [-1.0, 0.0, 1.0], [-1.0, -1.0, 0.0]];
    for generating in [
        random_generating(&mut rng, MlpInputs::Plain),
        wide_generating(&mut rng, MlpInputs::Plain),
    ] {
        let stepper = BisectionStepper::new(
            generating,
            LogCanonical::new(c).unwrap(),
            NewtonOptions::default(),
        );
        let q0: Vec<[f64; 3]> = (0..20).map(|_| rng.vec3(-0.5, 0.5)).collect();
        let steps = 500;
        let mut out = vec![0.0; q0.len() * n_records(steps, 50) * 3];
        let info = rollout(&stepper, &q0, 0.05, steps, 50, &mut out).unwrap();
        assert!(info.iter().all(|i| i.converged));
        let casimir = |q: &[f64]| q[0] - q[1] + q[2];
        for (traj, q) in out.chunks(n_records(steps, 50) * 3).zip(&q0) {
            let c0 = casimir(q);
            let drift = traj
                .chunks(3)
                .map(|s| (casimir(s) - c0).abs())
                .fold(0.0, f64::max);
            assert!(drift < 1e-13, "Casimir drift {drift}");
            // The state moved: the test is not vacuous.
            assert!((traj[traj.len() - 3] - q[0]).abs() > 1e-4);
        }
    }
}

// ---------------------------------------------------------------------------------------------
// exp in lanes, and the explicit methods in lanes
// ---------------------------------------------------------------------------------------------

#[test]
fn exp_is_within_one_ulp_of_libm() {
    let mut rng = Rng::new(71);
    let worst = |xs: &mut dyn Iterator<Item = f64>| {
        xs.map(|x| (ulps(exp(x), x.exp()), x))
            .fold((0, 0.0), |a, b| if b.0 > a.0 { b } else { a })
    };
    let uniform = worst(&mut (0..1_000_000).map(|_| rng.range(EXP_MIN, EXP_MAX)));
    let unit = worst(&mut (0..200_000).map(|_| rng.range(-2.0, 2.0)));
    let small =
        worst(&mut (0..200_000).map(|_| rng.range(-1.0, 1.0) * 10f64.powf(rng.range(-300.0, 0.0))));
    // Near the reduction's boundaries, (k + ½) ln 2, where k flips.
    let mut near = Vec::new();
    for k in -1000..1000 {
        let x0 = (f64::from(k) + 0.5) * std::f64::consts::LN_2;
        for d in -32i64..=32 {
            near.push(f64::from_bits((x0.to_bits() as i64 + d) as u64));
        }
    }
    let near = worst(&mut near.into_iter());
    for (what, (u, x)) in [
        ("uniform", uniform),
        ("[-2, 2]", unit),
        ("small", small),
        ("near (k + 1/2) ln 2", near),
    ] {
        println!("exp {what}: worst {u} ulp at x = {x:e}");
        assert!(u <= 1, "exp {what}: {u} ulp at {x:e}");
    }
    assert_eq!(exp(0.0), 1.0);
    assert_eq!(exp(-0.0), 1.0);
    // Outside the vectorised range (and for ±∞, NaN): libm's bits.
    for x in [
        EXP_MAX + 0.5,
        709.78,
        710.0,
        -708.5,
        -745.0,
        -746.0,
        f64::INFINITY,
        f64::NEG_INFINITY,
    ] {
        assert_eq!(exp(x).to_bits(), x.exp().to_bits(), "{x:e}");
    }
    assert!(exp(f64::NAN).is_nan());
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn exp_lanes_avx2(x: &[f64; LANES], out: &mut [f64; LANES]) {
    exp_lanes(x, out);
}

#[test]
fn exp_lanes_equal_the_scalar_call_bit_for_bit() {
    let mut rng = Rng::new(72);
    for round in 0..5000 {
        let mut x: [f64; LANES] = std::array::from_fn(|_| rng.range(-50.0, 50.0));
        // Every tenth block has a lane outside the vectorised range (or NaN): libm for it.
        if round % 10 == 0 {
            x[round % LANES] = [800.0, -800.0, f64::NAN, 709.5][round % 4];
        }
        let want = x.map(exp);
        let mut got = [0.0; LANES];
        exp_lanes(&x, &mut got);
        let same = |g: &[f64; LANES]| {
            g.iter()
                .zip(&want)
                .all(|(a, b)| a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()))
        };
        assert!(same(&got), "portable: {x:?}");
        #[cfg(target_arch = "x86_64")]
        if Isa::detect().is_avx2() {
            // SAFETY: the CPU runs AVX2 and FMA (checked just above).
            unsafe { exp_lanes_avx2(&x, &mut got) };
            assert!(same(&got), "avx2: {x:?}");
        }
    }
}

/// The 3D system with the Casimir x₁x₃/x₂ (c k = 0 for k = (1, −1, 1)).
fn lv3() -> LogSystem<3> {
    let c = LogCanonical::new([[0.0, 1.0, 1.0], [-1.0, 0.0, 1.0], [-1.0, -1.0, 0.0]]).unwrap();
    let h = vec![
        ([1, 0, 0], 1.0),
        ([0, 1, 0], 1.0),
        ([0, 0, 1], 1.0),
        ([0, 2, 0], 0.1),
    ];
    LogSystem::new(c, h, [1.0, 2.0, 1.0]).unwrap()
}

/// RK4 (in x) and both log splittings (in q) in SIMD lanes equal their scalar steps bit for
/// bit, on every dispatch path and batch size, with one state that leaves the orthant (RK4:
/// code 5) or whose e^q overflows (the splittings).
#[test]
fn explicit_log_canonical_methods_in_lanes_equal_the_scalar_path() {
    for method in [LogMethod::Rk4, LogMethod::Splitting, LogMethod::Splitting4] {
        let in_log = method.in_log();
        let pnn = LogClassical::new(method, pnn(), NewtonOptions::default()).unwrap();
        let explicit = pnn.explicit().unwrap();
        let state2 = |rng: &mut Rng| -> [f64; 2] {
            let q = [rng.range(-0.6, 0.6), 2f64.ln() + rng.range(-0.6, 0.6)];
            if in_log {
                q
            } else {
                q.map(f64::exp)
            }
        };
        let bad2 = if in_log { [705.0, 0.0] } else { [6.0, 0.05] };
        let what = format!("PNN {method:?}");
        let info = check_lanes_equal_scalar(&explicit, &what, state2, Some(bad2), (0.3, 40, 3));
        let code = if in_log {
            None
        } else {
            Some(StepFailure::OutOfDomain)
        };
        if let Some(code) = code {
            assert!(info.iter().any(|i| i.failure == Some(code)), "{what}");
        }
        let lv = LogClassical::new(method, lv3(), NewtonOptions::default()).unwrap();
        let state3 = |rng: &mut Rng| -> [f64; 3] {
            let q = [
                rng.range(-0.5, 0.5),
                2f64.ln() + rng.range(-0.5, 0.5),
                rng.range(-0.5, 0.5),
            ];
            if in_log {
                q
            } else {
                q.map(f64::exp)
            }
        };
        check_lanes_equal_scalar(
            &lv.explicit().unwrap(),
            &format!("3D {method:?}"),
            state3,
            None,
            (0.1, 30, 1),
        );
    }
    let midpoint = LogClassical::new(LogMethod::Midpoint, pnn(), NewtonOptions::default()).unwrap();
    assert!(midpoint.explicit().is_none());
}

/// A linear H (Lotka–Volterra's form: one a_i x_i a variable, in any order) takes RK4's
/// straight-line field, which it steps by lane in AVX-512 blocks; any other H keeps the loop
/// over its terms. The straight-line field's numbers are the term loop's: one RK4 step written
/// here on the generic field (`vector_field`, zero entries of c skipped, not multiplied) agrees
/// bit for bit at random states, with a zero entry of c and at N = 2, 3, 5; and RK4 in lanes,
/// on every dispatch path (paired AVX-512 blocks by lane where the CPU has them), equals its
/// scalar step.
#[test]
fn a_linear_hamiltonian_takes_the_straight_line_field() {
    use crate::stepper::StepMap;
    fn check<const N: usize>(system: &LogSystem<N>, rng: &mut Rng)
    where
        nalgebra::Const<N>: nalgebra::DimMin<nalgebra::Const<N>, Output = nalgebra::Const<N>>,
    {
        assert!(system.linear().is_some());
        let rk4 =
            LogClassical::new(LogMethod::Rk4, system.clone(), NewtonOptions::default()).unwrap();
        let h = 0.05;
        for _ in 0..200 {
            let x: [f64; N] = std::array::from_fn(|_| rng.range(0.2, 3.0));
            let f = |y: &[f64; N]| system.vector_field::<f64>(y);
            let at =
                |k: &[f64; N], w: f64| -> [f64; N] { std::array::from_fn(|i| x[i] + w * k[i]) };
            let k1 = f(&x);
            let k2 = f(&at(&k1, 0.5 * h));
            let k3 = f(&at(&k2, 0.5 * h));
            let k4 = f(&at(&k3, h));
            let expect: [f64; N] = std::array::from_fn(|i| {
                x[i] + h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
            });
            let mut got = x;
            rk4.step(h, &mut got, &mut ()).unwrap();
            assert_eq!(got.map(f64::to_bits), expect.map(f64::to_bits), "{x:?}");
        }
    }
    let mut rng = Rng::new(0x11_4EA2);
    check(&pnn(), &mut rng);
    // Terms out of order, a zero entry of c.
    let c3 = LogCanonical::new([[0.0, 0.0, 1.5], [0.0, 0.0, -0.5], [-1.5, 0.5, 0.0]]).unwrap();
    let lv3_linear = LogSystem::new(
        c3.clone(),
        vec![([0, 0, 1], 0.3), ([1, 0, 0], 1.7), ([0, 1, 0], -0.9)],
        [1.0, -2.0, 0.5],
    )
    .unwrap();
    assert_eq!(lv3_linear.linear(), Some(&[1.7, -0.9, 0.3]));
    check(&lv3_linear, &mut rng);
    let c5: [[f64; 5]; 5] = std::array::from_fn(|i| {
        std::array::from_fn(|j| match i.cmp(&j) {
            std::cmp::Ordering::Less => (i + 2 * j) as f64 * 0.25 - 1.0,
            std::cmp::Ordering::Greater => 1.0 - (j + 2 * i) as f64 * 0.25,
            std::cmp::Ordering::Equal => 0.0,
        })
    });
    let lv5 = LogSystem::new(
        LogCanonical::new(c5).unwrap(),
        (0..5)
            .map(|i| (std::array::from_fn(|j| u32::from(i == j)), 0.5 + i as f64))
            .collect(),
        [1.0, 2.0, 0.5, 1.5, 1.0],
    )
    .unwrap();
    check(&lv5, &mut rng);
    // Not linear: a square, a variable twice, a variable missing, a product.
    for terms in [
        vec![([1, 0, 0], 1.0), ([0, 1, 0], 1.0), ([0, 0, 2], 1.0)],
        vec![
            ([1, 0, 0], 1.0),
            ([1, 0, 0], 2.0),
            ([0, 1, 0], 1.0),
            ([0, 0, 1], 1.0),
        ],
        vec![([1, 0, 0], 1.0), ([0, 1, 0], 1.0)],
        vec![([1, 0, 0], 1.0), ([0, 1, 0], 1.0), ([0, 1, 1], 1.0)],
    ] {
        let s = LogSystem::new(c3.clone(), terms.clone(), [1.0; 3]).unwrap();
        assert!(s.linear().is_none(), "{terms:?}");
    }
    // RK4 in lanes on the 3-D and 5-D linear systems (PNN's 2-D one is in the test above).
    let rk4 = LogClassical::new(LogMethod::Rk4, lv3_linear, NewtonOptions::default()).unwrap();
    let state3 = |rng: &mut Rng| -> [f64; 3] { std::array::from_fn(|_| rng.range(0.5, 2.0)) };
    check_lanes_equal_scalar(
        &rk4.explicit().unwrap(),
        "3D linear RK4",
        state3,
        None,
        (0.1, 30, 1),
    );
    let rk4 = LogClassical::new(LogMethod::Rk4, lv5, NewtonOptions::default()).unwrap();
    let state5 = |rng: &mut Rng| -> [f64; 5] { std::array::from_fn(|_| rng.range(0.5, 2.0)) };
    let bad5 = Some([1e300, 1.0, 1.0, 1.0, 1.0]);
    check_lanes_equal_scalar(
        &rk4.explicit().unwrap(),
        "5D linear RK4",
        state5,
        bad5,
        (0.05, 30, 3),
    );
}

/// The implicit midpoint rule in x in SIMD lanes: its closed-form lane Jacobian equals dual
/// numbers through the scalar field to 1e-13 (a system whose monomials mix the coordinates,
/// a coordinate at 0 included); its steps equal the scalar step bit for bit on every dispatch
/// path and batch size, with one state that leaves the orthant; and each step solves
/// z = x + h f((x + z)/2) to Newton's tolerance (the residual, recomputed here in dual-free
/// scalar code).
#[test]
fn midpoint_in_lanes_equals_the_scalar_path_and_solves_its_equation() {
    use crate::lane_field::LaneField;
    use crate::structures::lie_poisson::VectorField;
    use crate::structures::log_canonical::FieldInX;
    let c = LogCanonical::new([[0.0, 1.0, -0.5], [-1.0, 0.0, 2.0], [0.5, -2.0, 0.0]]).unwrap();
    let mixed = LogSystem::new(
        c,
        vec![
            ([1, 0, 0], 1.0),
            ([2, 1, 0], -0.3),
            ([0, 3, 2], 0.2),
            ([1, 1, 1], 0.7),
        ],
        [1.0, 0.5, 2.0],
    )
    .unwrap();
    let field = FieldInX(&mixed);
    let mut rng = Rng::new(0x3D_317);
    let mut worst = 0.0f64;
    for k in 0..50 {
        let mut x: [f64; 3] = std::array::from_fn(|_| rng.range(0.2, 2.5));
        if k == 0 {
            x[1] = 0.0;
        }
        let mut lanes = [[[0.0; 1]; 3]; 3];
        assert!(field.jacobian_lanes(&x.map(|v| [v]), &mut lanes));
        let exact = field.jacobian(&x);
        for r in 0..3 {
            for col in 0..3 {
                let scale = 1.0 + exact[(r, col)].abs();
                worst = worst.max((lanes[r][col][0] - exact[(r, col)]).abs() / scale);
            }
        }
    }
    assert!(
        worst <= 1e-13,
        "lane Jacobian against dual numbers: {worst:e}"
    );

    for (system, what) in [(pnn(), "PNN"), (mixed_2d(), "mixed 2D")] {
        let midpoint =
            LogClassical::new(LogMethod::Midpoint, system, NewtonOptions::default()).unwrap();
        let lanes = midpoint.midpoint_in_lanes().unwrap();
        let state2 = |rng: &mut Rng| [rng.range(0.5, 1.8), 2.0 * rng.range(0.5, 1.5)];
        let info = check_lanes_equal_scalar(&lanes, what, state2, Some([6.0, 0.05]), (0.3, 40, 3));
        assert!(
            info.iter()
                .any(|i| i.failure == Some(StepFailure::OutOfDomain)),
            "{what}: the state thrown out of the orthant fails"
        );
        let f = FieldInX(&midpoint.system);
        for _ in 0..100 {
            let x0 = state2(&mut rng);
            let mut z = x0;
            let stats = midpoint.step(0.1, &mut z, &mut ()).unwrap();
            let fm = f.field(&[0.5 * (x0[0] + z[0]), 0.5 * (x0[1] + z[1])]);
            let residual = (0..2).fold(0.0f64, |m, i| m.max((x0[i] + 0.1 * fm[i] - z[i]).abs()));
            assert!(residual <= 1e-13, "{what}: residual {residual:e}");
            assert!(stats.iterations >= 1);
        }
    }
    let lv = LogClassical::new(LogMethod::Midpoint, lv3(), NewtonOptions::default()).unwrap();
    let state3 = |rng: &mut Rng| -> [f64; 3] {
        [
            rng.range(0.6, 1.6),
            2.0 * rng.range(0.6, 1.6),
            rng.range(0.6, 1.6),
        ]
    };
    check_lanes_equal_scalar(
        &lv.midpoint_in_lanes().unwrap(),
        "3D midpoint",
        state3,
        None,
        (0.1, 30, 1),
    );
}

/// A 2-D system whose monomials mix the coordinates (a dense Jacobian of the field).
fn mixed_2d() -> LogSystem<2> {
    let c = LogCanonical::new([[0.0, 1.0], [-1.0, 0.0]]).unwrap();
    LogSystem::new(
        c,
        vec![([1, 0], 1.0), ([0, 1], 1.0), ([1, 1], 0.2), ([2, 0], -0.05)],
        [1.0, 2.0],
    )
    .unwrap()
}

/// Taylor-HJ in SIMD lanes equals its scalar step bit for bit (every dispatch path, batch
/// size and segmentation, with one state whose e^q overflows), and the old one-trajectory
/// Newton stepper to round-off: the same map, by other arithmetic.
#[test]
fn taylor_in_lanes_equals_the_scalar_path_and_the_generic_stepper() {
    let pnn = pnn_taylor(3);
    let lanes = pnn.lanes();
    let state2 = |rng: &mut Rng| [rng.range(-0.6, 0.6), 2f64.ln() + rng.range(-0.6, 0.6)];
    let info = check_lanes_equal_scalar(
        &lanes,
        "PNN Taylor-3",
        state2,
        Some([705.0, 0.0]),
        (0.2, 30, 3),
    );
    assert!(info
        .iter()
        .filter(|i| i.converged)
        .all(|i| i.max_newton_iterations >= 2));
    // The overflowing state (e^705 in S's terms: ∇S overflows) fails as the generic stepper
    // fails it, for the reason the lanes' finiteness probe gives.
    let (mut a, mut b) = ([705.0, 0.0], [705.0, 0.0]);
    let generic = OrthantChecked(pnn_taylor(3)).step(0.2, &mut a, &mut ());
    let mine = lanes.step(0.2, &mut b, &mut ());
    assert_eq!(mine.err(), Some(StepFailure::NonFinite));
    assert_eq!(generic.err(), mine.err());
    // S = t S₁ of the 3D system (N = 3 takes the 3×3 cofactor inverse).
    let c = [[0.0, 1.0, 1.0], [-1.0, 0.0, 1.0], [-1.0, -1.0, 0.0]];
    let terms = (0..3)
        .map(|i| ExpMonomial {
            t_power: 1,
            exponents: std::array::from_fn(|k| i32::from(k == i)),
            coeff: -1.0,
        })
        .collect();
    let lv3 = LogBisection::unit_scale(
        ExpPolynomial::new(terms, [1.0, 2.0, 1.0]).unwrap(),
        LogCanonical::new(c).unwrap(),
        NewtonOptions::default(),
    );
    let state3 = |rng: &mut Rng| {
        [
            rng.range(-0.5, 0.5),
            2f64.ln() + rng.range(-0.5, 0.5),
            rng.range(-0.5, 0.5),
        ]
    };
    check_lanes_equal_scalar(&lv3.lanes(), "3D Taylor-1", state3, None, (0.1, 20, 1));
    // Against the generic Newton stepper: agreement to a few ulps of |q| per step.
    let mut rng = Rng::new(73);
    for _ in 0..200 {
        let q0 = state2(&mut rng);
        let (mut a, mut b) = (q0, q0);
        for _ in 0..20 {
            OrthantChecked(pnn_taylor(3))
                .step(0.2, &mut a, &mut ())
                .unwrap();
            lanes.step(0.2, &mut b, &mut ()).unwrap();
        }
        assert!(
            (0..2).all(|i| (a[i] - b[i]).abs() < 1e-13),
            "{a:?} vs {b:?}"
        );
    }
}

/// Above N = 3 the lanes solve J δ = f by pivoted elimination: on a 5-D system (−tH plus two
/// t² terms that couple the coordinates, so J is dense) the lanes equal the scalar path bit for
/// bit (every dispatch, batch and segmentation, one overflowing state), and the generic
/// one-trajectory stepper (dual numbers, nalgebra's LU) to 1e-13 over 20 steps of 100 states;
/// the Casimir k·q of c's null vector k stays to 1e-13.
#[test]
fn taylor_in_lanes_solves_any_dimension() {
    let c = [
        [0.0, 1.0, -0.5, 0.3, 0.2],
        [-1.0, 0.0, 0.7, -0.4, 0.1],
        [0.5, -0.7, 0.0, 0.6, -0.3],
        [-0.3, 0.4, -0.6, 0.0, 0.9],
        [-0.2, -0.1, 0.3, -0.9, 0.0],
    ];
    let b = [1.0, 2.0, 1.5, 0.5, 1.0];
    let make = || {
        let mut terms: Vec<ExpMonomial<5>> = (0..5)
            .map(|i| ExpMonomial {
                t_power: 1,
                exponents: std::array::from_fn(|k| i32::from(k == i)),
                coeff: -1.0,
            })
            .collect();
        for (exponents, coeff) in [([1, 1, 0, 0, 0], 0.05), ([0, 1, 0, 1, 1], -0.03)] {
            terms.push(ExpMonomial {
                t_power: 2,
                exponents,
                coeff,
            });
        }
        LogBisection::unit_scale(
            ExpPolynomial::new(terms, b).unwrap(),
            LogCanonical::new(c).unwrap(),
            NewtonOptions::default(),
        )
    };
    let lv5 = make();
    let lanes = lv5.lanes();
    let state =
        |rng: &mut Rng| -> [f64; 5] { std::array::from_fn(|i| b[i].ln() + rng.range(-0.4, 0.4)) };
    check_lanes_equal_scalar(
        &lanes,
        "5D Taylor",
        state,
        Some([705.0, 0.0, 0.0, 0.0, 0.0]),
        (0.1, 20, 2),
    );
    // c is 5×5 antisymmetric, so singular: its null vector k gives the Casimir k·q.
    let k = null_vector(&c);
    let generic = OrthantChecked(make());
    let mut rng = Rng::new(5);
    let (mut worst, mut casimir) = (0.0f64, 0.0f64);
    for _ in 0..100 {
        let q0 = state(&mut rng);
        let (mut a, mut q) = (q0, q0);
        let c0: f64 = (0..5).map(|i| k[i] * q0[i]).sum();
        for _ in 0..20 {
            generic.step(0.1, &mut a, &mut ()).unwrap();
            lanes.step(0.1, &mut q, &mut ()).unwrap();
            worst = worst.max((0..5).fold(0.0f64, |m, i| m.max((a[i] - q[i]).abs())));
            let c1: f64 = (0..5).map(|i| k[i] * q[i]).sum();
            casimir = casimir.max((c1 - c0).abs());
        }
    }
    assert!(
        worst <= 1e-13,
        "lanes against the generic stepper: {worst:e}"
    );
    assert!(casimir <= 1e-13, "Casimir moved {casimir:e}");
}

/// A unit null vector of an antisymmetric 5×5 matrix of rank 4: k₄ = 1 and the first four rows
/// of c k = 0 solved by nalgebra's LU, then normalised (checked against all five rows).
fn null_vector(c: &[[f64; 5]; 5]) -> [f64; 5] {
    let m = nalgebra::Matrix4::from_fn(|r, col| c[r][col]);
    let rhs = nalgebra::Vector4::from_fn(|r, _| -c[r][4]);
    let x = m
        .lu()
        .solve(&rhs)
        .expect("the leading 4×4 block is regular");
    let k = [x[0], x[1], x[2], x[3], 1.0];
    let n = k.iter().map(|v| v * v).sum::<f64>().sqrt();
    let k = k.map(|v| v / n);
    for row in c {
        assert!(row.iter().zip(&k).map(|(a, b)| a * b).sum::<f64>().abs() < 1e-14);
    }
    k
}

/// The predicted start q_k − ½c∇S(q_k) of the log-canonical Newton solve: started there, the
/// lanes reach the same states as the generic step started from q_k (to 1e-13 over 20 steps of
/// 200 states of PNN's Taylor-3 at h = 0.1 and 0.2) in fewer updates; the prediction is left out
/// where its shift exceeds [`PREDICT_MAX_SHIFT`] or is not finite.
#[test]
fn predicted_start_saves_newton_updates() {
    let pnn = pnn_taylor(3);
    let lanes = pnn.lanes();
    let mut rng = Rng::new(0x9_2ED1C7);
    for h in [0.1, 0.2] {
        let (mut predicted, mut unpredicted, mut worst) = (0u32, 0u32, 0.0f64);
        for _ in 0..200 {
            let q0 = [rng.range(-0.6, 0.6), 2f64.ln() + rng.range(-0.6, 0.6)];
            let (mut a, mut b) = (q0, q0);
            for _ in 0..20 {
                predicted += lanes.step(h, &mut a, &mut ()).unwrap().iterations;
                unpredicted += pnn.step_generic(h, &mut b, &mut ()).unwrap().iterations;
                worst = worst.max((a[0] - b[0]).abs().max((a[1] - b[1]).abs()));
            }
        }
        assert!(worst <= 1e-13, "h = {h}: predicted vs not {worst:e}");
        // benches/step_costs.py, this system at h = 0.1: 3.79 → 3.00 updates a step.
        assert!(
            f64::from(predicted) <= 0.85 * f64::from(unpredicted),
            "h = {h}: {predicted} updates predicted against {unpredicted}"
        );
    }
    let c = pnn.realization;
    let q = [0.1, 0.2];
    // x₀ = (0, 1): a shift of ½ in q₁ is taken, (0, 3) is refused, and so is a NaN.
    assert_eq!(c.predict(&[0.0, 1.0], &q), Some([0.1 - 0.5, 0.2]));
    assert_eq!(c.predict(&[0.0, 2.0 * PREDICT_MAX_SHIFT + 1.0], &q), None);
    assert_eq!(c.predict(&[f64::NAN, 0.0], &q), None);
}

/// `count` random terms c t^k y^e: k in 1 ..= `t_powers`, about half the exponents 0 and the
/// rest in −11 ..= 11, c in [−1, 1).
fn random_exp_terms<const N: usize>(
    rng: &mut Rng,
    count: usize,
    t_powers: usize,
) -> Vec<ExpMonomial<N>> {
    (0..count)
        .map(|_| ExpMonomial {
            t_power: 1 + rng.below(t_powers) as u32,
            exponents: [0; N].map(|_: i32| {
                if rng.below(2) == 0 {
                    0
                } else {
                    rng.below(23) as i32 - 11
                }
            }),
            coeff: rng.range(-1.0, 1.0),
        })
        .collect()
}

/// The accumulation in registers (every term into every entry, zeros included) and the one by
/// each term's own variables give the same bits, for N = 2 and 3 with and without the Hessian,
/// at random terms with many zero exponents, a constant term among them, and lanes whose y^e
/// overflows (non-finite sums must stay non-finite where they were).
#[test]
fn dense_and_sparse_lane_jets_agree_bit_for_bit() {
    fn check<const N: usize>(rng: &mut Rng) {
        const L: usize = 8;
        for case in 0..30 {
            let mut terms = random_exp_terms::<N>(rng, 14, 6);
            terms.push(ExpMonomial {
                t_power: 2,
                exponents: [0; N],
                coeff: 0.5,
            });
            let mut high = [0; N];
            high[0] = 11;
            terms.push(ExpMonomial {
                t_power: 1,
                exponents: high,
                coeff: 0.25,
            });
            let s = ExpPolynomial::new(terms, [0; N].map(|_: i32| rng.range(-1.0, 1.0))).unwrap();
            let t = rng.range(0.05, 1.2);
            let mut q = [[0.0; L]; N];
            for i in 0..N {
                for l in 0..L {
                    // Lane 7 far out: y^11 overflows there.
                    q[i][l] = if l == 7 { 80.0 } else { rng.range(-0.4, 0.4) };
                }
            }
            let table = crate::structures::log_canonical::t_power_table(t);
            for hess in [false, true] {
                let mut out = [([[0.0; L]; N], [[[0.0; L]; N]; N]); 2];
                for (k, dense) in [true, false].into_iter().enumerate() {
                    let (g, hs) = &mut out[k];
                    if hess {
                        s.taylor_lanes_by::<L, true>(dense, t, &table, &q, g, hs);
                    } else {
                        s.taylor_lanes_by::<L, false>(dense, t, &table, &q, g, hs);
                    }
                }
                for l in 0..L {
                    let entries = |k: usize| {
                        let (g, hs) = &out[k];
                        let mut v: Vec<f64> = (0..N).map(|a| g[a][l]).collect();
                        v.extend((0..N * N).map(|ab| hs[ab / N][ab % N][l]));
                        v
                    };
                    let (d, p) = (entries(0), entries(1));
                    let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
                    // A lane is judged whole: where a sum is not finite the solve fails there,
                    // and the dense sums may carry NaN (w·0 at w = ∞) into more entries.
                    assert_eq!(finite(&d), finite(&p), "N {N} case {case} lane {l}");
                    if finite(&p) {
                        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                        assert_eq!(bits(&d), bits(&p), "N {N} case {case} lane {l} hess {hess}");
                    }
                }
                // The far lane's y^11 overflows: not finite in both, so the solve fails there
                // either way.
                assert!(!out[1].0[0][7].is_finite());
            }
        }
    }
    let mut rng = Rng::new(0x5eed_d3a5e);
    check::<2>(&mut rng);
    check::<3>(&mut rng);
}

/// L random points q in [−0.4, 0.4]^N, lane by lane.
fn random_lanes<const N: usize, const L: usize>(rng: &mut Rng) -> [[f64; L]; N] {
    let mut q = [[0.0; L]; N];
    for i in 0..N {
        for l in 0..L {
            q[i][l] = rng.range(-0.4, 0.4);
        }
    }
    q
}

/// The lane gradient `g` and Hessian `hs` of S at the points `q` against its closed form
/// (`jet_at`), to 1e-12 of the gradient's size.
fn assert_closed_form<const N: usize, const L: usize>(
    s: &ExpPolynomial<N>,
    t: f64,
    q: &[[f64; L]; N],
    g: &[[f64; L]; N],
    hs: &[[[f64; L]; N]; N],
    what: &str,
) {
    for l in 0..L {
        let ql: [f64; N] = std::array::from_fn(|i| q[i][l]);
        let jet = s.jet_at(t, &ql);
        let hess = jet.hess();
        let scale = 1.0 + jet.g.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for a in 0..N {
            assert!(
                (g[a][l] - jet.g[a]).abs() <= 1e-12 * scale,
                "{what} lane {l}: ∂S/∂q{a} {} against {}",
                g[a][l],
                jet.g[a]
            );
            for b in 0..N {
                let want = hess[a][b];
                assert!(
                    (hs[a][b][l] - want).abs() <= 1e-12 * (1.0 + want.abs()) * scale,
                    "{what} lane {l}: ∂²S/∂q{a}∂q{b} {} against {want}",
                    hs[a][b][l]
                );
            }
        }
    }
}

/// The lane jet of an exp-polynomial S against its scalar closed form (`jet_at`, y^e by `powi`),
/// lane by lane: exponents of both signs, zero, past the table of powers (8) and t-powers past
/// the table of t's (16), so every branch of the compiled terms runs; the gradient pass alone
/// gives the jet pass's gradient bits.
#[test]
fn lane_jets_of_an_exp_polynomial_match_its_closed_form() {
    const N: usize = 4;
    const L: usize = 8;
    let mut rng = Rng::new(0x5EED_0E27);
    for case in 0..20 {
        let terms = random_exp_terms::<N>(&mut rng, 12, 20);
        let linear = [0; N].map(|_: i32| rng.range(-1.0, 1.0));
        let s = ExpPolynomial::new(terms, linear).unwrap();
        let t = rng.range(0.5, 1.2);
        let q = random_lanes::<N, L>(&mut rng);
        let table = crate::structures::log_canonical::t_power_table(t);
        let (mut g, mut hs) = ([[0.0; L]; N], [[[0.0; L]; N]; N]);
        s.taylor_lanes::<L, true>(t, &table, &q, &mut g, &mut hs);
        let (mut g1, mut unused) = ([[0.0; L]; N], [[[0.0; L]; N]; N]);
        s.taylor_lanes::<L, false>(t, &table, &q, &mut g1, &mut unused);
        assert_closed_form(&s, t, &q, &g, &hs, &format!("case {case}"));
        for l in 0..L {
            for a in 0..N {
                assert_eq!(
                    g[a][l].to_bits(),
                    g1[a][l].to_bits(),
                    "case {case} lane {l}"
                );
                for b in 0..N {
                    assert_eq!(hs[a][b][l].to_bits(), hs[b][a][l].to_bits());
                }
            }
        }
    }
}

/// S's t^k parts share most of their y^e: at terms drawn from four exponent vectors (each with
/// several t-powers, some repeated and some past the table of t's), both accumulations match the
/// closed form, for N = 2 and 3 (where the sums are kept in registers) and 4. The test above
/// draws distinct vectors at N = 4 only.
#[test]
fn terms_sharing_an_exponent_vector_match_the_closed_form() {
    fn check<const N: usize>(rng: &mut Rng) {
        const L: usize = 8;
        for case in 0..20 {
            let pool = random_exp_terms::<N>(rng, 4, 1);
            let terms: Vec<ExpMonomial<N>> = (0..24)
                .map(|_| ExpMonomial {
                    t_power: 1 + rng.below(20) as u32,
                    exponents: pool[rng.below(pool.len())].exponents,
                    coeff: rng.range(-1.0, 1.0),
                })
                .collect();
            let linear = [0; N].map(|_: i32| rng.range(-1.0, 1.0));
            let s = ExpPolynomial::new(terms, linear).unwrap();
            let t = rng.range(0.5, 1.2);
            let q = random_lanes::<N, L>(rng);
            let table = crate::structures::log_canonical::t_power_table(t);
            for dense in [true, false] {
                let (mut g, mut hs) = ([[0.0; L]; N], [[[0.0; L]; N]; N]);
                s.taylor_lanes_by::<L, true>(dense, t, &table, &q, &mut g, &mut hs);
                let what = format!("N {N} case {case} dense {dense}");
                assert_closed_form(&s, t, &q, &g, &hs, &what);
            }
        }
    }
    let mut rng = Rng::new(0x5eed_9a0b);
    check::<2>(&mut rng);
    check::<3>(&mut rng);
    check::<4>(&mut rng);
}

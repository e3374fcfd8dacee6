use super::rigid_body::cross;
use super::*;
use crate::step::{NewtonOptions, StepMap};

const PAPER: [f64; 3] = [1.5, 2.0, 2.5];
const STATES: [[f64; 3]; 4] = [
    [1.0, 1.0, 2.0],
    [3.0, 2.0, 0.0],
    [-0.7, 1.3, 0.4],
    [0.2, -2.1, 1.1],
];

fn body(inertia: [f64; 3]) -> RigidBody {
    RigidBody::new(inertia).unwrap()
}

/// One step of size h, in place; panics on a failed step.
type Step = Box<dyn Fn(f64, &mut [f64; 3])>;

fn stepper(method: ClassicalMethod, body: RigidBody) -> Step {
    let newton = NewtonOptions::default();
    fn boxed<S: StepMap<3, Workspace = ()> + 'static>(s: S) -> Step {
        Box::new(move |h, mu| {
            s.step(h, mu, &mut ()).unwrap();
        })
    }
    match method {
        ClassicalMethod::Rk4 => boxed(Rk4 { system: body }),
        ClassicalMethod::Midpoint => boxed(ImplicitMidpoint {
            system: body,
            newton,
        }),
        ClassicalMethod::Splitting => boxed(Splitting::strang(body)),
        ClassicalMethod::Splitting4 => boxed(Splitting4::suzuki(body)),
        ClassicalMethod::Dmv => boxed(MoserVeselov::new(body, newton)),
        ClassicalMethod::CasimirSplitting => boxed(CasimirSplitting::new(body)),
    }
}

/// The flow over time t by `n` RK4 steps: the reference for local errors.
fn fine(body: RigidBody, mu: [f64; 3], t: f64, n: usize) -> [f64; 3] {
    let rk = Rk4 { system: body };
    let mut m = mu;
    for _ in 0..n {
        rk.step(t / n as f64, &mut m, &mut ()).unwrap();
    }
    m
}

fn dist(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    (0..3).map(|i| (a[i] - b[i]).powi(2)).sum::<f64>().sqrt()
}

fn casimir(mu: &[f64; 3]) -> f64 {
    mu.iter().map(|v| v * v).sum()
}

#[test]
fn rejects_bad_inertia_and_names() {
    for bad in [
        [0.0, 1.0, 1.0],
        [1.0, -2.0, 1.0],
        [1.0, f64::NAN, 1.0],
        [f64::INFINITY; 3],
    ] {
        assert!(matches!(RigidBody::new(bad), Err(CoreError::Invalid(_))));
    }
    for m in ClassicalMethod::ALL {
        assert_eq!(ClassicalMethod::from_name(m.name()), Ok(m));
    }
    let err = ClassicalMethod::from_name("rk5").unwrap_err().to_string();
    assert!(err.contains("rk5") && err.contains("splitting4") && err.contains("dmv"));
}

#[test]
fn axis_flow_signs_follow_mu_cross_grad_h() {
    // (φ_t(μ) − φ_{−t}(μ))/2t → μ × ∇Hᵢ = (μᵢ/Iᵢ) μ × eᵢ; a flipped sign would give its negative.
    let b = body([1.3, 0.7, 2.9]);
    let t = 1e-5;
    for mu in STATES {
        for i in 0..3 {
            let (mut fwd, mut bwd) = (mu, mu);
            b.axis_flow(i, t, &mut fwd);
            b.axis_flow(i, -t, &mut bwd);
            let mut e = [0.0; 3];
            e[i] = mu[i] / b.inertia[i];
            let want = cross(&mu, &e);
            for k in 0..3 {
                let got = (fwd[k] - bwd[k]) / (2.0 * t);
                assert!(
                    (got - want[k]).abs() <= 1e-7,
                    "axis {i}: {got} vs {}",
                    want[k]
                );
            }
            // Hᵢ's flow keeps μᵢ and |μ|.
            assert_eq!(fwd[i], mu[i]);
            assert!((casimir(&fwd) / casimir(&mu) - 1.0).abs() <= 1e-15);
        }
    }
    // The three flows add up to the full vector field.
    for mu in STATES {
        let mut sum = [0.0; 3];
        for i in 0..3 {
            let (mut fwd, mut bwd) = (mu, mu);
            b.axis_flow(i, t, &mut fwd);
            b.axis_flow(i, -t, &mut bwd);
            for k in 0..3 {
                sum[k] += (fwd[k] - bwd[k]) / (2.0 * t);
            }
        }
        assert!(dist(&sum, &b.vector_field(&mu)) <= 1e-7);
    }
}

#[test]
fn rk4_matches_a_fine_rk4_reference() {
    let b = body(PAPER);
    for mu0 in STATES {
        // 50 steps of 0.1 against 5000 of 0.001: RK4's global error is ~h⁴.
        let coarse = fine(b, mu0, 5.0, 50);
        let reference = fine(b, mu0, 5.0, 5000);
        let err = dist(&coarse, &reference);
        assert!(err > 1e-9 && err < 1e-3, "err {err}");
    }
}

#[test]
fn every_method_matches_the_exact_symmetric_top() {
    // I₁ = I₂: μ₃ is constant and (μ₁, μ₂) turns at Ω = μ₃(1/I₃ − 1/I₁), an oracle
    // independent of RK4.
    let inertia = [2.0, 2.0, 0.8];
    let b = body(inertia);
    let (h, n) = (0.01, 300);
    for method in ClassicalMethod::ALL {
        let step = stepper(method, b);
        for mu0 in STATES {
            let mut mu = mu0;
            for _ in 0..n {
                step(h, &mut mu);
            }
            let angle = mu0[2] * (1.0 / inertia[2] - 1.0 / inertia[0]) * (h * n as f64);
            let (s, c) = angle.sin_cos();
            let exact = [mu0[0] * c + mu0[1] * s, mu0[1] * c - mu0[0] * s, mu0[2]];
            let err = dist(&mu, &exact);
            let bound = if method.order() == 4 { 1e-8 } else { 1e-3 };
            assert!(err <= bound, "{}: err {err}", method.name());
        }
    }
}

#[test]
fn local_error_ratio_matches_the_order() {
    // A one-step error ~ C h^(p+1), so err(h)/err(h/2) ≈ 2^(p+1).
    for inertia in [PAPER, [0.9, 3.1, 1.7]] {
        let b = body(inertia);
        for method in ClassicalMethod::ALL {
            let step = stepper(method, b);
            for mu0 in STATES {
                let err = |h: f64| {
                    let mut mu = mu0;
                    step(h, &mut mu);
                    dist(&mu, &fine(b, mu0, h, 200))
                };
                let h = match method {
                    ClassicalMethod::Rk4 => 0.08,
                    ClassicalMethod::Splitting4 => 0.03,
                    _ => 0.02,
                };
                let (e1, e2) = (err(h), err(0.5 * h));
                let slope = (e1 / e2).log2();
                let want = f64::from(method.order() + 1);
                assert!(
                    (slope - want).abs() <= 0.3,
                    "{} {inertia:?} {mu0:?}: log2 ratio {slope:.2} (errors {e1:.2e}, {e2:.2e})",
                    method.name()
                );
            }
        }
    }
}

#[test]
fn poisson_methods_keep_the_casimir_and_rk4_does_not() {
    for inertia in [PAPER, [0.9, 3.1, 1.7]] {
        let b = body(inertia);
        for method in ClassicalMethod::ALL {
            let step = stepper(method, b);
            for mu0 in STATES {
                let (mut mu, c0, h0) = (mu0, casimir(&mu0), b.hamiltonian(&mu0));
                let (mut dc, mut dh) = (0.0f64, 0.0f64);
                for _ in 0..10_000 {
                    step(0.1, &mut mu);
                    dc = dc.max((casimir(&mu) / c0 - 1.0).abs());
                    dh = dh.max((b.hamiltonian(&mu) / h0 - 1.0).abs());
                }
                let name = method.name();
                if method.is_poisson() {
                    assert!(dc <= 1e-12, "{name}: Casimir drift {dc:e}");
                } else {
                    assert!(dc > 1e-10, "{name}: Casimir drift {dc:e}");
                }
                // Midpoint and DMV keep H as well (up to Newton tolerance and round-off).
                if matches!(method, ClassicalMethod::Midpoint | ClassicalMethod::Dmv) {
                    assert!(dh <= 1e-12, "{name}: energy drift {dh:e}");
                }
            }
        }
    }
}

#[test]
fn newton_reports_failures_and_zero_state_is_a_fixed_point() {
    let b = body(PAPER);
    let tight = NewtonOptions::validated(1e-12, 1).unwrap();
    let mut mu = [1.0, 1.0, 2.0];
    let r = ImplicitMidpoint {
        system: b,
        newton: tight,
    }
    .step(0.1, &mut mu, &mut ());
    assert_eq!(r, Err(StepFailure::NotConverged));
    let r = MoserVeselov::new(b, tight).step(0.1, &mut mu, &mut ());
    assert_eq!(r, Err(StepFailure::NotConverged));
    for method in ClassicalMethod::ALL {
        let mut zero = [0.0; 3];
        stepper(method, b)(0.1, &mut zero);
        assert_eq!(zero, [0.0; 3], "{}", method.name());
    }
    // A converged implicit step reports its iterations and a round-off residual.
    let mut mu = [1.0, 1.0, 2.0];
    let s = MoserVeselov::new(b, NewtonOptions::default())
        .step(0.1, &mut mu, &mut ())
        .unwrap();
    assert!(s.iterations >= 2 && s.residual <= 1e-14, "{s:?}");
}

#[test]
fn rollout_by_name_matches_stepping() {
    let b = body(PAPER);
    let (h, n, every) = (0.1, 7, 3);
    for method in ClassicalMethod::ALL {
        let mut out = vec![0.0; STATES.len() * 3 * 3];
        let info = rollout_classical(
            method,
            b,
            NewtonOptions::default(),
            &STATES,
            h,
            n,
            every,
            &mut out,
        )
        .unwrap();
        assert!(info.iter().all(|i| i.converged));
        let step = stepper(method, b);
        for (k, mu0) in STATES.iter().enumerate() {
            let mut mu = *mu0;
            for _ in 0..6 {
                step(h, &mut mu);
            }
            assert_eq!(&out[9 * k + 6..9 * k + 9], &mu[..], "{}", method.name());
        }
    }
}

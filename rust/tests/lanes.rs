//! Systems compiled to their sparsity against the dense oracle, SIMD-lane rollouts against the
//! scalar steppers (bit for bit, on every dispatch path, any batch size and chunking), and the
//! local rate behind the step-size check.

#![allow(clippy::needless_range_loop)]

use super::*;
use crate::classical::{ImplicitMidpoint, RigidBody, Rk4};
use crate::lanes::{LaneStepper, Lanes, LANES};
use crate::rollout::{ChunkKernel, PerStep, Rollout};
use crate::stepper::NewtonOptions;
use crate::straight_line::{LieField, Se3QuadraticLinear, So3Quadratic, Torque};
use crate::structures::lie_groupoid::LieAlgebra;
use crate::structures::lie_poisson::{spectral_norm, Hamiltonian, LiePoisson, VectorField};

/// se(3): [R_i,R_j] = ε_ijk R_k, [R_i,T_j] = ε_ijk T_k, [T_i,T_j] = 0.
fn se3() -> [[[f64; 6]; 6]; 6] {
    *LieAlgebra::se3().structure_constants()
}

fn so3() -> [[[f64; 3]; 3]; 3] {
    *LieAlgebra::<3>::so3().unwrap().structure_constants()
}

/// The structure constants of the same algebra in the basis e'_a = Σ_b B[a][b] e_b, B random
/// and well conditioned (identity plus a small perturbation): every entry becomes nonzero.
fn random_basis<const N: usize>(rng: &mut Rng, c: &[[[f64; N]; N]; N]) -> [[[f64; N]; N]; N] {
    let b = nalgebra::SMatrix::<f64, N, N>::from_fn(|i, j| {
        f64::from(u8::from(i == j)) + rng.range(-0.3, 0.3)
    });
    let binv = b.try_inverse().unwrap();
    let mut out = [[[0.0; N]; N]; N];
    for i in 0..N {
        for j in 0..N {
            for k in 0..N {
                let mut s = 0.0;
                for a in 0..N {
                    for bb in 0..N {
                        for d in 0..N {
                            s += b[(i, a)] * b[(j, bb)] * c[a][bb][d] * binv[(d, k)];
                        }
                    }
                }
                out[i][j][k] = s;
            }
        }
    }
    // Exact antisymmetry (the Jacobi identity holds to round-off).
    for i in 0..N {
        for j in 0..i {
            for k in 0..N {
                out[j][i][k] = -out[i][j][k];
            }
        }
        out[i][i] = [0.0; N];
    }
    out
}

/// A random polynomial H: `n` monomials of total degree ≤ `max_deg`, one of them quadratic.
fn random_hamiltonian<const N: usize>(rng: &mut Rng, n: usize, max_deg: u32) -> Hamiltonian<N> {
    let mut terms = Vec::new();
    for _ in 0..n {
        let mut e = [0u32; N];
        let deg = 1 + rng.below(max_deg as usize) as u32;
        for _ in 0..deg {
            e[rng.below(N)] += 1;
        }
        terms.push((e, rng.range(-1.0, 1.0)));
    }
    Hamiltonian::new(terms).unwrap()
}

/// Σ |c| |∂ᵢH| |μ_k| with every coefficient and coordinate made positive: the size of the terms
/// summed in a field component, the scale of its rounding error.
fn field_scale<const N: usize>(sys: &LiePoisson<N>, mu: &[f64; N]) -> f64 {
    let abs_h = Hamiltonian::new(
        sys.hamiltonian
            .terms()
            .iter()
            .map(|(e, c)| (*e, c.abs()))
            .collect(),
    )
    .unwrap();
    let g = abs_h.gradient(&mu.map(f64::abs));
    let c = sys.algebra.structure_constants();
    let mut s = 0.0;
    for i in 0..N {
        for j in 0..N {
            for k in 0..N {
                s += c[i][j][k].abs() * g[i] * mu[k].abs();
            }
        }
    }
    s
}

fn check_sparse_equals_dense<const N: usize>(sys: &LiePoisson<N>, rng: &mut Rng, states: usize) {
    let compiled = sys.compile();
    for _ in 0..states {
        let mu: [f64; N] = std::array::from_fn(|_| rng.range(-2.0, 2.0));
        // Rounding of sums of up to N² products of up to 18 factors each, reordered.
        let tol = 64.0 * f64::EPSILON * (field_scale(sys, &mu) + f64::MIN_POSITIVE);
        let (fs, fd) = (compiled.field(&mu), sys.field(&mu));
        let (gs, gd) = (compiled.gradient(&mu), sys.hamiltonian.gradient(&mu));
        let (js, jd) = (compiled.jacobian(&mu), sys.jacobian(&mu));
        for j in 0..N {
            assert!(
                (fs[j] - fd[j]).abs() <= tol,
                "field {j}: {} vs {}",
                fs[j],
                fd[j]
            );
            let gtol = 64.0 * f64::EPSILON * (1.0 + gd[j].abs());
            assert!((gs[j] - gd[j]).abs() <= gtol * 8.0, "grad {j}");
            for m in 0..N {
                // The Jacobian's terms are up to max_deg × the field's per unit of μ.
                let jtol = 8.0 * tol / mu.iter().fold(1e-3f64, |a, v| a.max(v.abs()));
                assert!(
                    (js[(j, m)] - jd[(j, m)]).abs() <= jtol,
                    "J[{j},{m}]: {} vs {}",
                    js[(j, m)],
                    jd[(j, m)]
                );
            }
        }
        // The compiled rate is the dense one, to rounding.
        let (rs, rd) = (compiled.step_rate(&mu), sys.step_rate(&mu));
        assert!((rs - rd).abs() <= 1e-10 * (1.0 + rd), "rate {rs} vs {rd}");
    }
}

#[test]
fn sparse_field_equals_dense_on_random_algebras() {
    let mut rng = Rng::new(17);
    for _ in 0..6 {
        let c = random_basis(&mut rng, &so3());
        let sys = LiePoisson {
            algebra: LieAlgebra::new(c).unwrap(),
            hamiltonian: random_hamiltonian::<3>(&mut rng, 6, 4),
        };
        check_sparse_equals_dense(&sys, &mut rng, 20);
        let c = random_basis(&mut rng, &se3());
        let sys = LiePoisson {
            algebra: LieAlgebra::new(c).unwrap(),
            hamiltonian: random_hamiltonian::<6>(&mut rng, 10, 3),
        };
        check_sparse_equals_dense(&sys, &mut rng, 20);
    }
    // The sparse algebras themselves, with high powers (the power tables).
    let sys = LiePoisson {
        algebra: LieAlgebra::new(se3()).unwrap(),
        hamiltonian: random_hamiltonian::<6>(&mut rng, 12, 7),
    };
    assert_eq!(sys.compile().bracket().len(), 18);
    check_sparse_equals_dense(&sys, &mut rng, 50);
    // The heavy top's ∇H has two zero components and a constant one (dropped and folded terms).
    check_sparse_equals_dense(&heavy_top(), &mut rng, 50);
}

/// The heavy top with DPNN's parameters.
fn heavy_top() -> LiePoisson<6> {
    LiePoisson::heavy_top([1.0, 1.5, 2.0], [0.0, 0.0, 0.981]).unwrap()
}

/// A rollout of `mu0` with `kernel`, in segments of `segment` steps, serial or on the pool.
fn run<const N: usize, K: ChunkKernel<N>>(
    kernel: &K,
    mu0: &[[f64; N]],
    (h, n_steps, every): (f64, usize, usize),
    segment: usize,
    parallel: bool,
) -> (Vec<f64>, Vec<TrajectoryInfo>) {
    let mut out = vec![0.0; mu0.len() * n_records(n_steps, every) * N];
    let mut r = Rollout::start(mu0, h, n_steps, every, &mut out).unwrap();
    while !r.is_finished() {
        r.advance_kernel(kernel, segment, &mut out, parallel)
            .unwrap();
    }
    (out, r.into_info())
}

fn assert_same_bits(
    a: &(Vec<f64>, Vec<TrajectoryInfo>),
    b: &(Vec<f64>, Vec<TrajectoryInfo>),
    what: &str,
) {
    assert_eq!(a.0.len(), b.0.len());
    for (i, (x, y)) in a.0.iter().zip(&b.0).enumerate() {
        assert!(
            x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan()),
            "{what}: number {i}: {x:e} vs {y:e}"
        );
    }
    assert_eq!(a.1, b.1, "{what}: info");
}

fn check_lanes_equal_scalar<const N: usize, F>(field: F, rng: &mut Rng, scale: f64, h: f64)
where
    F: VectorField<N> + Clone,
    Rk4<F>: LaneStepper<N>,
{
    let rk4 = Rk4 { system: field };
    for n in [1, 3, LANES + 1, 2 * LANES - 1, 67, 133] {
        let mut mu0: Vec<[f64; N]> = (0..n)
            .map(|_| std::array::from_fn(|_| rng.range(-scale, scale)))
            .collect();
        // One state that overflows within a few steps, in the middle of a block: it fails
        // alone, at the same step as on the scalar path, and leaves its neighbours alone.
        if n > 2 {
            mu0[n / 2] = [1e80; N];
        }
        let args = (h, 23, 3);
        let scalar = run(&PerStep(&rk4), &mu0, args, 23, false);
        if n > 2 {
            assert!(!scalar.1[n / 2].converged, "the huge state should overflow");
            assert!(scalar.1.iter().filter(|i| i.converged).count() == n - 1);
        }
        for isa in isas() {
            let lanes = Lanes { stepper: &rk4, isa };
            let what = format!("N = {N}, n = {n}, {}", isa.name());
            assert_same_bits(&run(&lanes, &mu0, args, 23, false), &scalar, &what);
            // Any segmentation, serial or parallel.
            assert_same_bits(&run(&lanes, &mu0, args, 5, true), &scalar, &what);
            assert_same_bits(&run(&lanes, &mu0, args, 1, true), &scalar, &what);
        }
    }
}

#[test]
fn simd_rk4_equals_the_scalar_path_bit_for_bit() {
    let mut rng = Rng::new(23);
    check_lanes_equal_scalar(RigidBody::new(INERTIA).unwrap(), &mut rng, 3.0, 0.1);
    check_lanes_equal_scalar(heavy_top().compile(), &mut rng, 2.0, 0.05);
    // The straight-line kernels, alone and behind the stepper's dispatch, every pattern of b.
    for b in [
        [0.0; 3],
        [0.7, 0.0, 0.0],
        [0.0, -0.4, 0.0],
        [0.0, 0.0, 0.981],
        [0.3, -0.5, 0.8],
    ] {
        let top = random_top(&mut rng, b);
        check_lanes_equal_scalar(LieField::new(&top), &mut rng, 2.0, 0.05);
    }
    let se3 = Se3QuadraticLinear {
        a: [1.0, 1.0 / 1.5, 0.5],
        torque: Torque::Z(0.981),
    };
    check_lanes_equal_scalar(se3, &mut rng, 2.0, 0.05);
    check_lanes_equal_scalar(
        So3Quadratic {
            a: [0.7, -0.2, 1.3],
        },
        &mut rng,
        3.0,
        0.1,
    );
    let so3_sys = diagonal_so3(&mut rng);
    check_lanes_equal_scalar(LieField::new(&so3_sys), &mut rng, 3.0, 0.1);
    // A random dense algebra with a quartic H exercises the power tables.
    let sys = LiePoisson {
        algebra: LieAlgebra::new(random_basis(&mut rng, &so3())).unwrap(),
        hamiltonian: random_hamiltonian::<3>(&mut rng, 6, 4),
    };
    check_lanes_equal_scalar(sys.compile(), &mut rng, 1.0, 0.01);
}

/// Masked Newton lanes: the implicit midpoint in lanes against the scalar step, bit for bit
/// (states, records, Newton counts, residuals, failure codes and steps), on batches that are
/// not multiples of the lane count, with one overflowing state in the middle of a block and,
/// with `max_iter` tight, lanes that stop at the cap while their neighbours converge.
fn check_midpoint_lanes_equal_scalar<const N: usize, F>(
    field: F,
    rng: &mut Rng,
    scale: f64,
    h: f64,
    newton: NewtonOptions,
) -> Vec<TrajectoryInfo>
where
    F: VectorField<N> + crate::lanes::MidpointSolve<N> + Clone,
    ImplicitMidpoint<F>: LaneStepper<N>,
    nalgebra::Const<N>: nalgebra::DimMin<nalgebra::Const<N>, Output = nalgebra::Const<N>>,
{
    let mid = ImplicitMidpoint {
        system: field,
        newton,
    };
    let mut all = Vec::new();
    for n in [1, 3, LANES + 1, 2 * LANES - 1, 67] {
        // Scales spread over two decades: lanes converge after different numbers of updates.
        let mut mu0: Vec<[f64; N]> = (0..n)
            .map(|_| {
                let s = scale * 10f64.powf(rng.range(-1.0, 1.0));
                std::array::from_fn(|_| rng.range(-s, s))
            })
            .collect();
        if n > 2 {
            mu0[n / 2] = [1e80; N];
        }
        let args = (h, 13, 2);
        let scalar = run(&PerStep(&mid), &mu0, args, 13, false);
        if n > 2 {
            assert!(!scalar.1[n / 2].converged, "the huge state should fail");
        }
        for isa in isas() {
            let lanes = Lanes { stepper: &mid, isa };
            let what = format!("midpoint N = {N}, n = {n}, {}", isa.name());
            assert_same_bits(&run(&lanes, &mu0, args, 13, false), &scalar, &what);
            assert_same_bits(&run(&lanes, &mu0, args, 4, true), &scalar, &what);
            assert_same_bits(&run(&lanes, &mu0, args, 1, true), &scalar, &what);
        }
        // Every lane that succeeds equals its own scalar run, alone in its batch.
        for (i, m) in mu0.iter().enumerate().take(9) {
            let alone = run(&PerStep(&mid), std::slice::from_ref(m), args, 13, false);
            let row = alone.0.len();
            let lanes = Lanes::new(&mid);
            let batch = run(&lanes, &mu0, args, 13, false);
            let mine = (batch.0[i * row..(i + 1) * row].to_vec(), vec![batch.1[i]]);
            assert_same_bits(&mine, &alone, &format!("midpoint N = {N}, lane {i} alone"));
        }
        all.extend(scalar.1);
    }
    all
}

#[test]
fn simd_midpoint_equals_the_scalar_path_bit_for_bit() {
    let mut rng = Rng::new(29);
    let newton = NewtonOptions::default();
    let body = RigidBody::new(INERTIA).unwrap();
    let info = check_midpoint_lanes_equal_scalar(body, &mut rng, 3.0, 0.1, newton);
    assert!(info
        .iter()
        .any(|i| i.converged && i.max_newton_iterations > 0));
    check_midpoint_lanes_equal_scalar(heavy_top().compile(), &mut rng, 2.0, 0.05, newton);
    // The straight-line kernels solve lane-wide where a lane's matrix is diagonally dominant and
    // fall back to the pivoted LU per lane elsewhere: at h = 0.4 the large states do.
    for (b, h) in [
        ([0.0, 0.0, 0.981], 0.05),
        ([0.0; 3], 0.1),
        ([0.7, 0.0, 0.0], 0.1),
        ([0.0, -0.4, 0.0], 0.1),
        ([0.3, -0.5, 0.8], 0.05),
        ([0.3, -0.5, 0.8], 0.4),
    ] {
        let top = LieField::new(&random_top(&mut rng, b));
        check_midpoint_lanes_equal_scalar(top, &mut rng, 2.0, h, newton);
    }
    let so3_sys = LieField::new(&diagonal_so3(&mut rng));
    check_midpoint_lanes_equal_scalar(so3_sys, &mut rng, 3.0, 0.1, newton);
    // A tight iteration cap: some lanes stop at it (NotConverged) while others converge.
    let tight = NewtonOptions::validated(1e-15, 3).unwrap();
    let info = check_midpoint_lanes_equal_scalar(body, &mut rng, 3.0, 0.1, tight);
    assert_some_capped_some_converged(&info);
}

#[test]
fn compiled_rk4_matches_the_dense_rk4() {
    // The compiled field differs from the dense one by rounding only, so a short rollout does.
    let sys = heavy_top();
    let mut rng = Rng::new(5);
    let mu0: Vec<[f64; 6]> = (0..9)
        .map(|_| std::array::from_fn(|_| rng.range(-2.0, 2.0)))
        .collect();
    let args = (0.1, 50, 50);
    let dense = run(
        &PerStep(&Rk4 {
            system: sys.clone(),
        }),
        &mu0,
        args,
        50,
        false,
    );
    let sparse = run(
        &PerStep(&Rk4 {
            system: sys.compile(),
        }),
        &mu0,
        args,
        50,
        false,
    );
    for (a, b) in dense.0.iter().zip(&sparse.0) {
        assert!((a - b).abs() <= 1e-12 * (1.0 + a.abs()), "{a} vs {b}");
    }
}

#[test]
fn spectral_norm_matches_the_svd() {
    let mut rng = Rng::new(3);
    for _ in 0..50 {
        let a: [[f64; 6]; 6] =
            std::array::from_fn(|_| std::array::from_fn(|_| rng.range(-3.0, 3.0)));
        let m = nalgebra::SMatrix::<f64, 6, 6>::from_fn(|i, j| a[i][j]);
        let want = m.singular_values().max();
        let got = spectral_norm(&a);
        assert!((got - want).abs() <= 1e-12 * want, "{got} vs {want}");
    }
    // ‖ad_ω‖₂ = |ω| on so(3), where AᵀA has a double eigenvalue; the cheap rotation rate
    // ‖A‖_F/√2 is exact there.
    let w = [0.3, -1.2, 2.0];
    let a = [[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]];
    assert!((spectral_norm(&a) - norm(&w)).abs() <= 1e-14);
    assert!((crate::structures::lie_poisson::lie_poisson_rate(&a, 0.0) - norm(&w)).abs() <= 1e-14);
    // On any skew A it bounds ‖A‖₂ from above, and on any A it is within √(N/2) of it.
    for _ in 0..50 {
        let m: [[f64; 6]; 6] =
            std::array::from_fn(|_| std::array::from_fn(|_| rng.range(-3.0, 3.0)));
        let skew: [[f64; 6]; 6] =
            std::array::from_fn(|i| std::array::from_fn(|j| m[i][j] - m[j][i]));
        let cheap = crate::structures::lie_poisson::lie_poisson_rate(&skew, 0.0);
        assert!(cheap >= spectral_norm(&skew) * (1.0 - 1e-12));
        let (cheap, exact) = (
            crate::structures::lie_poisson::lie_poisson_rate(&m, 0.0),
            spectral_norm(&m),
        );
        assert!(
            cheap <= exact * 3f64.sqrt() * (1.0 + 1e-12)
                && cheap >= exact / 2f64.sqrt() * (1.0 - 1e-12)
        );
    }
}

#[test]
fn the_local_rate_sees_the_hessian() {
    // Rigid body: the rate is |ω| (the Jacobian's norm is smaller there).
    let body = RigidBody::new(INERTIA).unwrap();
    let mu = [60.0, 50.0, 60.0];
    let w = [40.0, 25.0, 24.0];
    assert!((body.step_rate(&mu) - norm(&w)).abs() <= 1e-12 * norm(&w));
    // The same body as a Lie–Poisson system gives the same rate.
    let rigid = LiePoisson {
        algebra: LieAlgebra::so3().unwrap(),
        hamiltonian: Hamiltonian::new(
            (0..3)
                .map(|i| {
                    let mut e = [0; 3];
                    e[i] = 2;
                    (e, 0.5 / INERTIA[i])
                })
                .collect(),
        )
        .unwrap(),
    };
    assert!((rigid.compile().step_rate(&mu) - norm(&w)).abs() <= 1e-12 * norm(&w));
    // A quartic H = Σ μᵢ⁴/(4Iᵢ): ∇H = μ³/I, and the Hessian 3μ²/I makes the local rate several
    // times the rotation rate |∇H| (1.7× here), which alone would pass steps the flow does not.
    let quartic = LiePoisson {
        algebra: LieAlgebra::so3().unwrap(),
        hamiltonian: Hamiltonian::new(
            (0..3)
                .map(|i| {
                    let mut e = [0; 3];
                    e[i] = 4;
                    (e, 0.25 / INERTIA[i])
                })
                .collect(),
        )
        .unwrap(),
    };
    let mu = [1.0, 2.0, 0.5];
    let g = quartic.hamiltonian.gradient(&mu);
    let rate = quartic.compile().step_rate(&mu);
    assert!(rate > 1.5 * norm(&g), "rate {rate} vs |∇H| {}", norm(&g));
    // It is the Jacobian's Frobenius norm, an upper bound of its spectral norm.
    let j = quartic.jacobian(&mu);
    assert!((rate - j.norm()).abs() <= 1e-12 * rate);
    assert!(rate >= j.singular_values().max());
}

/// A heavy top H = ½ Σ Mᵢ²/Iᵢ + b·Γ with random seeded inertia (the squares split over two
/// monomials on one axis, as a user might write them) and the given b (mgl χ, any direction).
fn random_top(rng: &mut Rng, b: [f64; 3]) -> LiePoisson<6> {
    let mut terms: Vec<([u32; 6], f64)> = Vec::new();
    for i in 0..3 {
        let mut e = [0; 6];
        e[i] = 2;
        let a = 1.0 / rng.range(0.5, 3.0);
        if i == 1 {
            terms.push((e, 0.25 * a));
            terms.push((e, 0.25 * a));
        } else {
            terms.push((e, 0.5 * a));
        }
        let mut e = [0; 6];
        e[3 + i] = 1;
        terms.push((e, b[i]));
    }
    // A constant shifts H only.
    terms.push(([0; 6], 4.2));
    LiePoisson {
        algebra: LieAlgebra::se3(),
        hamiltonian: Hamiltonian::new(terms).unwrap(),
    }
}

/// so(3) with H = ½ Σ aᵢ μᵢ², random seeded aᵢ of either sign.
fn diagonal_so3(rng: &mut Rng) -> LiePoisson<3> {
    let terms = (0..3)
        .map(|i| {
            let mut e = [0; 3];
            e[i] = 2;
            (e, rng.range(-1.0, 1.0))
        })
        .collect();
    LiePoisson {
        algebra: LieAlgebra::new(so3()).unwrap(),
        hamiltonian: Hamiltonian::new(terms).unwrap(),
    }
}

/// The straight-line field of `sys` against its compiled field and the dense oracle: field to
/// 4 ulps of the sum of the absolute terms, Jacobian to 4 ulps of that sum per unit of μ,
/// local rate to 1e-12.
fn check_straight_line<const N: usize>(sys: &LiePoisson<N>, kernel: &str, rng: &mut Rng) {
    let fast = LieField::new(sys);
    assert_eq!(fast.kernel_name(), kernel);
    let compiled = sys.compile();
    for _ in 0..200 {
        let s = 10f64.powf(rng.range(-2.0, 1.0));
        let mu: [f64; N] = std::array::from_fn(|_| rng.range(-s, s));
        let scale = field_scale(sys, &mu) + f64::MIN_POSITIVE;
        let tol = 4.0 * f64::EPSILON * scale;
        let jtol = tol / mu.iter().fold(0.0f64, |a, v| a.max(v.abs())) + 4.0 * f64::EPSILON;
        let f = fast.field(&mu);
        let j = fast.jacobian(&mu);
        for (name, other, oj) in [
            ("compiled", compiled.field(&mu), compiled.jacobian(&mu)),
            ("dense", sys.field(&mu), sys.jacobian(&mu)),
        ] {
            for r in 0..N {
                assert!(
                    (f[r] - other[r]).abs() <= tol,
                    "{kernel} vs {name}, field {r}: {} vs {} (tol {tol:e})",
                    f[r],
                    other[r]
                );
                for c in 0..N {
                    assert!(
                        (j[(r, c)] - oj[(r, c)]).abs() <= jtol,
                        "{kernel} vs {name}, J[{r},{c}]: {} vs {}",
                        j[(r, c)],
                        oj[(r, c)]
                    );
                }
            }
        }
        let (rf, rd) = (fast.step_rate(&mu), sys.step_rate(&mu));
        assert!((rf - rd).abs() <= 1e-12 * rd, "rate {rf} vs {rd}");
    }
}

#[test]
fn straight_line_fields_match_the_compiled_and_dense_ones() {
    let mut rng = Rng::new(31);
    for _ in 0..8 {
        // χ along each axis, along none (every b nonzero), in a coordinate plane, and b = 0.
        let dir = rng.vec3(-1.0, 1.0);
        let m = rng.range(0.1, 2.0);
        for b in [
            [m, 0.0, 0.0],
            [0.0, m, 0.0],
            [0.0, 0.0, m],
            dir.map(|v| m * v),
            [dir[0], 0.0, dir[2]],
            [0.0; 3],
        ] {
            check_straight_line(&random_top(&mut rng, b), "se3-quadratic-linear", &mut rng);
        }
        check_straight_line(&diagonal_so3(&mut rng), "so3-quadratic", &mut rng);
    }
    check_straight_line(&heavy_top(), "se3-quadratic-linear", &mut rng);
    // How b is stored: its zero components are not multiplied.
    let kinds = [
        [0.0; 3],
        [1.0, 0.0, 0.0],
        [0.0, 2.0, 0.0],
        [0.0, 0.0, 3.0],
        [1.0, 0.0, 3.0],
    ]
    .map(Torque::new);
    assert_eq!(
        kinds,
        [
            Torque::Zero,
            Torque::X(1.0),
            Torque::Y(2.0),
            Torque::Z(3.0),
            Torque::General([1.0, 0.0, 3.0])
        ]
    );
}

/// A system the pattern does not cover keeps the compiled field, and its rollouts are what the
/// compiled field gives, bit for bit (scalar and lanes, RK4 and midpoint).
fn check_falls_back<const N: usize>(sys: LiePoisson<N>, what: &str, rng: &mut Rng)
where
    nalgebra::Const<N>: nalgebra::DimMin<nalgebra::Const<N>, Output = nalgebra::Const<N>>,
{
    let field = LieField::new(&sys);
    assert_eq!(field.kernel_name(), "compiled", "{what}");
    assert_eq!(field, LieField::Compiled(sys.compile()), "{what}");
    let mu0: Vec<[f64; N]> = (0..LANES + 3)
        .map(|_| std::array::from_fn(|_| rng.range(-1.0, 1.0)))
        .collect();
    let args = (0.05, 11, 2);
    let newton = NewtonOptions::default();
    let before = Rk4 {
        system: sys.compile(),
    };
    let now = Rk4 {
        system: field.clone(),
    };
    let want = run(&PerStep(&before), &mu0, args, 11, false);
    assert_same_bits(&run(&PerStep(&now), &mu0, args, 11, false), &want, what);
    assert_same_bits(&run(&Lanes::new(&now), &mu0, args, 11, false), &want, what);
    let before = ImplicitMidpoint {
        system: sys.compile(),
        newton,
    };
    let now = ImplicitMidpoint {
        system: field,
        newton,
    };
    let want = run(&PerStep(&before), &mu0, args, 11, false);
    assert_same_bits(&run(&PerStep(&now), &mu0, args, 11, false), &want, what);
    assert_same_bits(&run(&Lanes::new(&now), &mu0, args, 11, false), &want, what);
}

#[test]
fn systems_off_the_pattern_keep_the_compiled_field() {
    let mut rng = Rng::new(37);
    let top = heavy_top();
    assert_eq!(LieField::new(&top).kernel_name(), "se3-quadratic-linear");
    let with = |extra: ([u32; 6], f64)| {
        let mut terms = top.hamiltonian.terms().to_vec();
        terms.push(extra);
        LiePoisson {
            algebra: top.algebra.clone(),
            hamiltonian: Hamiltonian::new(terms).unwrap(),
        }
    };
    check_falls_back(with(([3, 0, 0, 0, 0, 0], 0.1)), "a cubic term", &mut rng);
    check_falls_back(
        with(([1, 0, 0, 1, 0, 0], 0.2)),
        "an M·Γ cross term",
        &mut rng,
    );
    check_falls_back(with(([0, 1, 1, 0, 0, 0], 0.2)), "an M₁M₂ term", &mut rng);
    check_falls_back(with(([0, 0, 0, 0, 2, 0], 0.3)), "a Γ² term", &mut rng);
    check_falls_back(
        with(([1, 0, 0, 0, 0, 0], 0.3)),
        "a term linear in M",
        &mut rng,
    );
    // A zero coefficient is no term: still the pattern.
    let zero = with(([3, 0, 0, 0, 0, 0], 0.0));
    assert_eq!(LieField::new(&zero).kernel_name(), "se3-quadratic-linear");
    // One structure constant pair perturbed (a valid algebra, not exactly se(3)), and se(3) in
    // another basis.
    let mut c = se3();
    c[0][1][2] += 1e-13;
    c[1][0][2] -= 1e-13;
    let perturbed = LiePoisson {
        algebra: LieAlgebra::new(c).expect("within the Jacobi tolerance"),
        hamiltonian: top.hamiltonian.clone(),
    };
    check_falls_back(perturbed, "a perturbed structure constant", &mut rng);
    let rotated = LiePoisson {
        algebra: LieAlgebra::new(random_basis(&mut rng, &se3())).unwrap(),
        hamiltonian: top.hamiltonian.clone(),
    };
    check_falls_back(rotated, "se(3) in another basis", &mut rng);
    // so(3): a quartic or a linear term, or another algebra of dimension 3.
    let so3_sys = diagonal_so3(&mut rng);
    let so3_with = |extra: ([u32; 3], f64)| {
        let mut terms = so3_sys.hamiltonian.terms().to_vec();
        terms.push(extra);
        LiePoisson {
            algebra: so3_sys.algebra.clone(),
            hamiltonian: Hamiltonian::new(terms).unwrap(),
        }
    };
    check_falls_back(so3_with(([4, 0, 0], 0.1)), "a quartic so(3) term", &mut rng);
    check_falls_back(so3_with(([0, 1, 0], 0.5)), "a linear so(3) term", &mut rng);
    let sl2 = LiePoisson {
        algebra: LieAlgebra::new(random_basis(&mut rng, &so3())).unwrap(),
        hamiltonian: so3_sys.hamiltonian.clone(),
    };
    check_falls_back(sl2, "so(3) in another basis", &mut rng);
}

/// The generic lane-wide Newton solve of the midpoint (dense elimination, here on the compiled
/// heavy top) against the LU with pivoting: the same δ to rounding where a lane's matrix is
/// diagonally dominant, and the pivoted LU itself, bit for bit, in the lanes that are not (large
/// states at a large step); a lane's choice and bits do not depend on its neighbours (the scalar
/// update is the solve with one lane). The se(3) kernel's lane-wide Jacobian is its scalar one.
/// One lane of a lane-wide midpoint solve against the pivoted LU of the full matrix: a lane
/// kept (`solved`) has δ = `got`, the scalar update's bits and the LU's to `tol` relative; a lane
/// left over has the LU's update (or its failure) on the scalar path. Returns `solved`.
fn check_lane_against_lu(
    solved: bool,
    got: [f64; 6],
    scalar: Result<[f64; 6], StepFailure>,
    lu: Result<[f64; 6], StepFailure>,
    tol: f64,
    what: &str,
) -> bool {
    if !solved {
        assert_eq!(scalar, lu, "{what}: falls back to the pivoted LU");
        return false;
    }
    assert_eq!(
        scalar,
        Ok(got),
        "{what}: the scalar update is the one-lane solve"
    );
    let want = lu.unwrap();
    let size = max_abs(&want);
    for i in 0..6 {
        assert!(
            (got[i] - want[i]).abs() <= tol * size,
            "{what}: {got:?} vs {want:?}"
        );
    }
    true
}

#[test]
fn lane_wide_midpoint_solve_matches_the_pivoted_lu() {
    use crate::lane_field::newton_update;
    use crate::lanes::{midpoint_update_lanes, MidpointSolve};
    let mut rng = Rng::new(41);
    let (mut wide, mut pivoted) = (0, 0);
    for _ in 0..40 {
        let b = rng.vec3(-1.0, 1.0);
        let top = random_top(&mut rng, b);
        let LieField::Se3(se3) = LieField::new(&top) else {
            panic!("a heavy top is the se(3) pattern")
        };
        let f = top.compile();
        let half = 0.5 * rng.range(0.01, 0.5);
        let mut m = [[0.0; LANES]; 6];
        let mut r = [[0.0; LANES]; 6];
        for l in 0..LANES {
            let s = 10f64.powf(rng.range(-1.0, 1.5));
            for i in 0..6 {
                m[i][l] = rng.range(-s, s);
                r[i][l] = rng.range(-1e-3, 1e-3);
            }
        }
        let (mut delta, mut solved) = ([[0.0; LANES]; 6], [false; LANES]);
        assert!(midpoint_update_lanes(
            &f,
            half,
            &m,
            &r,
            &mut delta,
            &mut solved
        ));
        // The se(3) kernel's lane-wide Jacobian is its scalar one, entry by entry.
        let mut jl = [[[0.0; LANES]; 6]; 6];
        assert!(crate::lanes::LaneField::jacobian_lanes(&se3, &m, &mut jl));
        for l in 0..LANES {
            let ml: [f64; 6] = std::array::from_fn(|i| m[i][l]);
            let rl: [f64; 6] = std::array::from_fn(|i| r[i][l]);
            let lu = newton_update(nalgebra::SMatrix::identity() - half * f.jacobian(&ml), &rl);
            let scalar = f.midpoint_update(half, &ml, &rl);
            let j = se3.jacobian(&ml);
            for a in 0..6 {
                for c in 0..6 {
                    assert_eq!(jl[a][c][l], j[(a, c)], "J[{a},{c}]");
                }
            }
            let got: [f64; 6] = std::array::from_fn(|i| delta[i][l]);
            if check_lane_against_lu(solved[l], got, scalar, lu, 1e-13, &format!("lane {l}")) {
                wide += 1;
            } else {
                pivoted += 1;
            }
        }
    }
    assert!(
        wide > 50 && pivoted > 10,
        "lane-wide {wide}, pivoted {pivoted}"
    );
}

/// The se(3) kernel's Newton update by blocks (the closed-form inverse of I + s[Ω]× and a 3 × 3
/// Schur complement) against an independent oracle, nalgebra's pivoted LU of the full 6 × 6
/// I − s J, on seeded random states, for every pattern of b: δ agrees to 1e-12 relative where a
/// lane is kept, the lane is kept exactly where the Schur complement (formed here from the
/// blocks by nalgebra's inverse) is clearly diagonally dominant, the scalar update is the
/// one-lane solve bit for bit, and the lanes left over (a large state at a large step, built to
/// be one; a NaN state) take the pivoted LU or fail cleanly.
#[test]
fn se3_block_midpoint_solve_matches_the_full_lu() {
    use crate::lane_field::newton_update;
    use crate::lanes::{LaneField, MidpointSolve};
    use nalgebra::{Matrix3, SMatrix};
    let mut rng = Rng::new(43);
    let (mut wide, mut pivoted) = (0, 0);
    let patterns = |rng: &mut Rng| {
        let v = rng.range(-1.0, 1.0);
        [
            [0.0; 3],
            [v, 0.0, 0.0],
            [0.0, v, 0.0],
            [0.0, 0.0, v],
            rng.vec3(-1.0, 1.0),
        ]
    };
    for round in 0..60 {
        let b = patterns(&mut rng)[round % 5];
        let LieField::Se3(f) = LieField::new(&random_top(&mut rng, b)) else {
            panic!("a heavy top is the se(3) pattern")
        };
        let half = 0.5 * rng.range(0.01, 0.5);
        let mut m = [[0.0; LANES]; 6];
        let mut r = [[0.0; LANES]; 6];
        for l in 0..LANES {
            let s = 10f64.powf(rng.range(-1.0, 1.5));
            for i in 0..6 {
                m[i][l] = rng.range(-s, s);
                r[i][l] = rng.range(-1e-3, 1e-3);
            }
        }
        if round == 0 {
            // Built to need the fallback: |s J₁₁| ≫ 1 makes the Schur complement's
            // off-diagonal dominate.
            for (i, v) in [30.0, -20.0, 10.0, 1.0, 2.0, 3.0].into_iter().enumerate() {
                m[i][1] = v;
            }
        }
        if round == 1 {
            m[2][3] = f64::NAN;
        }
        let (mut delta, mut solved) = ([[0.0; LANES]; 6], [false; LANES]);
        assert!(f.solve_midpoint_lanes(half, &m, &r, &mut delta, &mut solved));
        for l in 0..LANES {
            let ml: [f64; 6] = std::array::from_fn(|i| m[i][l]);
            let rl: [f64; 6] = std::array::from_fn(|i| r[i][l]);
            let a: SMatrix<f64, 6, 6> = SMatrix::identity() - half * f.jacobian(&ml);
            let lu = newton_update(a, &rl);
            let scalar = f.midpoint_update(half, &ml, &rl);
            if round == 1 && l == 3 {
                assert!(!solved[l], "a NaN state is left to the fallback");
                assert!(scalar.is_err(), "and fails there: {scalar:?}");
                continue;
            }
            // The Schur complement from the blocks, by nalgebra.
            let blk = |r0: usize, c0: usize| Matrix3::from_fn(|i, j| a[(r0 + i, c0 + j)]);
            let s = blk(0, 0) - blk(0, 3) * blk(3, 3).try_inverse().unwrap() * blk(3, 0);
            let margin = (0..3)
                .map(|i| {
                    let off: f64 = (0..3).filter(|&j| j != i).map(|j| s[(i, j)].abs()).sum();
                    (s[(i, i)].abs() - off) / s.row(i).abs().sum()
                })
                .fold(f64::INFINITY, f64::min);
            if margin > 1e-9 {
                assert!(
                    solved[l],
                    "round {round} lane {l}: dominant, margin {margin:e}"
                );
            } else if margin < -1e-9 {
                assert!(!solved[l], "round {round} lane {l}: not dominant");
            }
            if round == 0 && l == 1 {
                assert!(!solved[l], "the state built for the fallback takes it");
            }
            let got: [f64; 6] = std::array::from_fn(|i| delta[i][l]);
            if check_lane_against_lu(
                solved[l],
                got,
                scalar,
                lu,
                1e-12,
                &format!("round {round} lane {l}"),
            ) {
                wide += 1;
            } else {
                pivoted += 1;
            }
        }
    }
    assert!(
        wide > 200 && pivoted > 10,
        "block {wide}, pivoted {pivoted}"
    );
}

/// The midpoint step of the heavy top (block solve, fixed-point predictor) fails cleanly, with
/// the same failure in lanes and on the scalar path, on non-finite states and where Newton
/// cannot converge within its cap; where it converges the midpoint equation holds.
#[test]
fn se3_midpoint_fails_cleanly_and_solves_the_midpoint_equation() {
    use crate::error::StepFailure;
    use crate::step::StepMap;
    let mut rng = Rng::new(47);
    let field = LieField::new(&random_top(&mut rng, [0.0, 0.0, 0.981]));
    let mid = ImplicitMidpoint {
        system: field.clone(),
        newton: NewtonOptions::default(),
    };
    let h = 0.1;
    for mu in [
        [0.3, -1.2, 0.8, 0.1, 0.5, 0.86],
        [1.5, 1.0, -1.4, 0.6, -0.6, 0.5],
    ] {
        let mut next = mu;
        let stats = mid.step(h, &mut next, &mut ()).unwrap();
        assert!(stats.iterations >= 1 && stats.residual <= 1e-13);
        // μ' = μ + h f((μ + μ')/2), to the Newton tolerance.
        let m: [f64; 6] = std::array::from_fn(|i| 0.5 * (mu[i] + next[i]));
        let fm = field.field(&m);
        for i in 0..6 {
            assert!((next[i] - mu[i] - h * fm[i]).abs() <= 1e-12);
        }
    }
    for bad in [f64::NAN, f64::INFINITY] {
        let mut mu = [0.3, -1.2, bad, 0.1, 0.5, 0.86];
        assert!(mid.step(h, &mut mu, &mut ()).is_err());
    }
    let capped = ImplicitMidpoint {
        system: field,
        newton: NewtonOptions::validated(1e-15, 1).unwrap(),
    };
    let mut mu = [1.5, 1.0, -1.4, 0.6, -0.6, 0.5];
    assert_eq!(
        capped.step(0.3, &mut mu, &mut ()),
        Err(StepFailure::NotConverged)
    );
}

fn max_abs(v: &[f64; 6]) -> f64 {
    v.iter().fold(0.0, |a: f64, x| a.max(x.abs()))
}

/// An `Isa` claiming AVX2 or AVX-512 comes from run-time detection only: `Isa::avx2()` is Some
/// exactly where the CPU reports AVX2 and FMA, `Isa::avx512()` where it also reports AVX-512 F
/// and VL, `Isa::detect()` is the widest of them or the portable baseline, and the baseline
/// claims nothing. (Writing a proof by hand, `Isa { avx2: true, avx512: false }`, does not
/// compile outside `isa`: the doctest of `Isa` checks that.)
#[test]
fn the_isa_proofs_come_from_detection_only() {
    use crate::lanes::Isa;
    #[cfg(target_arch = "x86_64")]
    let has = std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma");
    #[cfg(not(target_arch = "x86_64"))]
    let has = false;
    assert_eq!(Isa::avx2().is_some(), has);
    assert!(Isa::avx2().is_none_or(|isa| isa.is_avx2() && !isa.is_avx512()));
    #[cfg(target_arch = "x86_64")]
    let wide = has
        && std::is_x86_feature_detected!("avx512f")
        && std::is_x86_feature_detected!("avx512vl");
    #[cfg(not(target_arch = "x86_64"))]
    let wide = false;
    assert_eq!(Isa::avx512().is_some(), wide);
    assert!(Isa::avx512().is_none_or(|isa| isa.is_avx2() && isa.is_avx512()));
    let widest = Isa::avx512().or(Isa::avx2()).unwrap_or(Isa::PORTABLE);
    assert_eq!(Isa::detect(), widest);
    assert_eq!(Isa::detect().is_avx2(), has);
    assert!(!Isa::PORTABLE.is_avx2() && !Isa::PORTABLE.is_avx512());
    assert_eq!(Isa::PORTABLE.name(), "portable");
}

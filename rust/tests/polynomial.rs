//! Polynomial realizations: the sparse polynomial's exact derivatives on jets (against the hand
//! derivatives) and its construction checks. Steps against the NumPy oracle are tested in
//! `tests/test_polynomial_bivector.py`.

use super::*;
use crate::realization::Generating;
use crate::structures::{PolynomialGenerating, SparsePolynomial};

/// S(t, x, y) = 2 + t·(3x²y − y³): value, gradient and Hessian in (x, y) at fixed t.
#[test]
fn sparse_polynomial_jets_are_exact() {
    let s = SparsePolynomial::new(3, &[2.0, 3.0, -1.0], &[0, 0, 0, 1, 2, 1, 1, 0, 3]).unwrap();
    let g = PolynomialGenerating::<2>::new(s).unwrap();
    let mut rng = Rng::new(7);
    for _ in 0..20 {
        let (t, x, y) = (
            rng.range(-1.0, 1.0),
            rng.range(-2.0, 2.0),
            rng.range(-2.0, 2.0),
        );
        let jet = g.jet(t, &[x, y], &mut ());
        let value = 2.0 + t * (3.0 * x * x * y - y * y * y);
        let grad = [t * 6.0 * x * y, t * (3.0 * x * x - 3.0 * y * y)];
        let hess = [[t * 6.0 * y, t * 6.0 * x], [t * 6.0 * x, -t * 6.0 * y]];
        let tol = 1e-13 * (1.0 + value.abs());
        assert!((jet.v - value).abs() <= tol, "{} vs {value}", jet.v);
        let (jg, jh) = (jet.grad(), jet.hess());
        for i in 0..2 {
            assert!((jg[i] - grad[i]).abs() <= 1e-12, "grad {i}");
            for j in 0..2 {
                assert!((jh[i][j] - hess[i][j]).abs() <= 1e-12, "hess {i} {j}");
            }
        }
        let d = g.gradient(t, &[x, y], &mut ());
        assert_eq!(d.g, jg);
    }
}

#[test]
fn sparse_polynomial_refuses_bad_tables() {
    let msg = |r: Result<SparsePolynomial, CoreError>| r.unwrap_err().to_string();
    assert!(msg(SparsePolynomial::new(2, &[1.0], &[1])).contains("exponents"));
    assert!(msg(SparsePolynomial::new(2, &[f64::NAN], &[1, 0])).contains("not finite"));
    assert!(msg(SparsePolynomial::new(2, &[1.0], &[65, 0])).contains("over 64"));
    assert!(msg(SparsePolynomial::new(0, &[], &[])).contains("variables"));
    let two = SparsePolynomial::new(2, &[1.0], &[1, 1]).unwrap();
    assert!(PolynomialGenerating::<2>::new(two).is_err()); // S needs t and 2 coordinates
}

/// S's jets with t multiplied in f64 first are `eval`'s jets with t a constant jet, bit for bit:
/// at t = +0, −0, t > 0 and t < 0 (the fallback), and where c·tᵉ overflows (the fallback per
/// term, whose jet products turn the derivatives into NaN as `eval`'s do).
#[test]
fn jets_after_the_constant_t_are_evals_bits() {
    use crate::dual::{Dual1, Jet2, Scalar};
    let mut rng = Rng::new(0x5EED_0007);
    for round in 0..40 {
        let n_terms = 1 + rng.below(12);
        let coeffs: Vec<f64> = (0..n_terms).map(|_| rng.range(-2.0, 2.0)).collect();
        let exps: Vec<u32> = (0..n_terms * 4).map(|_| rng.below(5) as u32).collect();
        let s = SparsePolynomial::new(4, &coeffs, &exps).unwrap();
        let t = match round % 5 {
            0 => 0.0,
            1 => -0.0,
            2 => rng.range(0.0, 0.5),
            3 => rng.range(-0.5, 0.0),
            _ => 1e200,
        };
        let p = [
            rng.range(-2.0, 2.0),
            rng.range(-2.0, 2.0),
            rng.range(-2.0, 2.0),
        ];
        let jets: [Jet2<3>; 3] = std::array::from_fn(|i| Jet2::var(p[i], i));
        let duals: [Dual1<3>; 3] = std::array::from_fn(|i| Dual1::var(p[i], i));
        let mut v = [Jet2::<3>::cst(t); 4];
        v[1..].copy_from_slice(&jets);
        let mut d = [Dual1::<3>::cst(t); 4];
        d[1..].copy_from_slice(&duals);
        let (a, b) = (s.eval(&v), s.eval_after_constant(t, &jets));
        assert!(
            same_bits(&a.flat(), &b.flat()),
            "round {round}, t = {t}: jets"
        );
        let (a, b) = (s.eval(&d), s.eval_after_constant(t, &duals));
        assert_eq!(a.v.to_bits(), b.v.to_bits(), "round {round}: dual value");
        assert!(
            same_bits(&a.g, &b.g),
            "round {round}, t = {t}: dual gradient"
        );
    }
}

/// `derivative` against the jets' exact gradient and Hessian (the dual numbers' product rule),
/// on random sparse polynomials in (t, x, y, z); `eval_lanes_after_t` of a block against
/// `eval_after_constant` on f64, and `eval_lanes` (the polynomial field's lanes) against `eval`,
/// lane by lane, bit for bit.
#[test]
fn derivative_polynomials_are_the_jets_derivatives() {
    use crate::dual::Scalar;
    let mut rng = Rng::new(0x5EED_0008);
    for _ in 0..30 {
        let n_terms = 1 + rng.below(10);
        let coeffs: Vec<f64> = (0..n_terms).map(|_| rng.range(-2.0, 2.0)).collect();
        let exps: Vec<u32> = (0..n_terms * 4).map(|_| rng.below(5) as u32).collect();
        let s = SparsePolynomial::new(4, &coeffs, &exps).unwrap();
        let g = PolynomialGenerating::<3>::new(s.clone()).unwrap();
        let t = rng.range(0.0, 0.5);
        let pts: Vec<[f64; 3]> = (0..8).map(|_| rng.vec3(-1.5, 1.5)).collect();
        let lanes: [[f64; 8]; 3] = std::array::from_fn(|i| std::array::from_fn(|l| pts[l][i]));
        let value = s.eval_lanes_after_t(t, &lanes);
        let with_t: [[f64; 8]; 4] = std::array::from_fn(|i| {
            std::array::from_fn(|l| if i == 0 { t } else { lanes[i - 1][l] })
        });
        let plain = s.eval_lanes(&with_t);
        for (l, q) in pts.iter().enumerate() {
            assert_eq!(
                value[l].to_bits(),
                s.eval_after_constant(t, q).value().to_bits()
            );
            assert_eq!(plain[l].to_bits(), s.eval(&[t, q[0], q[1], q[2]]).to_bits());
            let jet = g.jet(t, q, &mut ());
            let scale = 1.0 + jet.flat().iter().fold(0.0f64, |m, v| m.max(v.abs()));
            for a in 0..3 {
                let da = s.derivative(1 + a).unwrap();
                let close = |u: f64, v: f64| (u - v).abs() <= 1e-13 * scale;
                assert!(close(da.eval_after_constant(t, q), jet.grad()[a]), "∂{a}");
                for b in 0..3 {
                    let dab = da.derivative(1 + b).unwrap();
                    assert!(
                        close(dab.eval_after_constant(t, q), jet.hess()[a][b]),
                        "∂{a}∂{b}"
                    );
                }
            }
        }
    }
    // A variable that no term holds differentiates to the zero polynomial.
    let s = SparsePolynomial::new(2, &[3.0], &[2, 0]).unwrap();
    assert_eq!(s.derivative(1).unwrap().eval(&[1.5, 2.0]), 0.0);
}

/// A realization of the cubic Nambu bracket to first order (α, β = x ± ½π(x)p, π_ij = ε_ijk
/// ∂_k C, C = x₁² + x₂² + x₃³/3) and S = −t H + t³ · (a cubic), enough to make Newton work: the
/// lane step against the dual-number step of the same [`PolynomialBisection`] on 24 states,
/// 20 steps each, the same Newton counts and states to 1e-12; a block of 8 gives the one-lane
/// bits; the same failures (NaN state, a one-update cap) in both.
#[test]
fn polynomial_lanes_equal_the_dual_number_step() {
    use crate::lanes::{LaneStepper, LANES};
    use crate::structures::{PolynomialBisection, PolynomialLanes, PolynomialRealization};
    // ∂C as (coefficient, exponents of x) per component.
    let dc: [(f64, [u32; 3]); 3] = [(2.0, [1, 0, 0]), (2.0, [0, 1, 0]), (1.0, [0, 0, 2])];
    let eps = |i: usize, j: usize, k: usize| -> f64 {
        match (i, j, k) {
            (0, 1, 2) | (1, 2, 0) | (2, 0, 1) => 1.0,
            (0, 2, 1) | (2, 1, 0) | (1, 0, 2) => -1.0,
            _ => 0.0,
        }
    };
    let map = |sign: f64| -> Vec<SparsePolynomial> {
        (0..3)
            .map(|i| {
                // Variables (p₁, p₂, p₃, x₁, x₂, x₃).
                let (mut co, mut ex) = (vec![1.0], vec![0, 0, 0, 0, 0, 0]);
                ex[3 + i] = 1;
                for j in 0..3 {
                    for (k, &(c, e)) in dc.iter().enumerate() {
                        let s = eps(i, j, k);
                        if s != 0.0 {
                            co.push(sign * 0.5 * s * c);
                            let mut row = vec![0; 6];
                            row[j] = 1;
                            row[3..].copy_from_slice(&e);
                            ex.extend(row);
                        }
                    }
                }
                SparsePolynomial::new(6, &co, &ex).unwrap()
            })
            .collect()
    };
    // S in (t, x): −t (x₁²/2 + x₂² + x₃²/3) + t³ (0.1 x₁x₂x₃ − 0.05 x₃³).
    let s = SparsePolynomial::new(
        4,
        &[-0.5, -1.0, -1.0 / 3.0, 0.1, -0.05],
        &[1, 2, 0, 0, 1, 0, 2, 0, 1, 0, 0, 2, 3, 1, 1, 1, 3, 0, 0, 3],
    )
    .unwrap();
    let newton = NewtonOptions::default();
    let generic = PolynomialBisection::<3>::unit_scale(
        PolynomialGenerating::new(s.clone()).unwrap(),
        PolynomialRealization::new(map(-1.0), map(1.0)).unwrap(),
        newton,
    );
    let lanes = PolynomialLanes::new(&generic).unwrap();
    let mut rng = Rng::new(0x5EED_0009);
    let states: Vec<[f64; 3]> = (0..24).map(|_| rng.vec3(-0.8, 0.8)).collect();
    let mut worst = 0.0f64;
    for &x0 in &states {
        let (mut a, mut b) = (x0, x0);
        for _ in 0..20 {
            let ra = lanes.step(0.1, &mut a, &mut ()).unwrap();
            let rb = generic.step(0.1, &mut b, &mut ()).unwrap();
            assert_eq!(ra.iterations, rb.iterations, "Newton counts");
            worst = worst.max((0..3).fold(0.0f64, |m, i| m.max((a[i] - b[i]).abs())));
        }
    }
    assert!(worst <= 1e-12, "lanes vs dual numbers {worst:e}");
    // A block of LANES against one lane at a time.
    let block: Vec<[f64; 3]> = states[..LANES].to_vec();
    let mut mu: [[f64; LANES]; 3] = std::array::from_fn(|i| std::array::from_fn(|l| block[l][i]));
    let mut results = [Ok(StepStats::default()); LANES];
    lanes.step_lanes_reporting(0.1, &mut mu, &[true; LANES], &mut results);
    for (l, x0) in block.iter().enumerate() {
        let mut one = *x0;
        let r = lanes.step(0.1, &mut one, &mut ()).unwrap();
        assert_eq!(results[l].unwrap().iterations, r.iterations);
        assert!(same_bits(&one, &[mu[0][l], mu[1][l], mu[2][l]]), "lane {l}");
    }
    // Through the rollout kernel on every dispatch path (paired AVX-512 blocks where the CPU
    // has them) at batches 1–67, one state failing mid-block: the scalar step's bits.
    super::splitting_lanes::check_lanes_equal_scalar(
        &lanes,
        "polynomial lanes",
        |rng| rng.vec3(-0.8, 0.8),
        Some([1e200, 0.1, 0.2]),
        (0.1, 12, 3),
    );
    // The same failures, the state left alone.
    let mut bad = [f64::NAN, 0.1, 0.2];
    let mut bad2 = bad;
    assert_eq!(
        lanes.step(0.1, &mut bad, &mut ()),
        generic.step(0.1, &mut bad2, &mut ())
    );
    assert!(bad[0].is_nan() && bad[1] == 0.1);
    let capped = PolynomialBisection::<3>::unit_scale(
        PolynomialGenerating::new(s).unwrap(),
        PolynomialRealization::new(map(-1.0), map(1.0)).unwrap(),
        NewtonOptions {
            max_iter: 1,
            ..newton
        },
    );
    let capped_lanes = PolynomialLanes::new(&capped).unwrap();
    let (mut a, mut b) = (states[0], states[0]);
    let (ra, rb) = (
        capped_lanes.step(0.1, &mut a, &mut ()),
        capped.step(0.1, &mut b, &mut ()),
    );
    assert_eq!(ra, Err(StepFailure::NotConverged));
    assert_eq!(ra, rb);
    assert_eq!(a, states[0]);
}

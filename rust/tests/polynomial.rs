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

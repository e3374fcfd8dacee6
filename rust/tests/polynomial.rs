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

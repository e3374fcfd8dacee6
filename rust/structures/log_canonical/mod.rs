//! Log-canonical structures π_ij(x) = c_ij x_i x_j on the positive orthant.
//!
//! In q = ln x the bracket is the constant antisymmetric matrix c and the exact symplectic
//! groupoid is linear: with P_j = x_j p_j, sou = β(q, P) = q − ½ c P and tar = α(q, P) = q + ½ c P.
//! Hamiltonians are log-polynomials H = Σ_m a_m e^{e_m·q} − b·q, so every Hamilton–Jacobi Taylor
//! term S_k (k ≥ 2) is a polynomial in y = e^q ([`ExpPolynomial`]).
//!
//! Coordinates: the bisection stepper and the splittings work in q (a step never leaves the
//! orthant, only overflows); RK4 and the implicit midpoint rule work in x, where a step can leave
//! the orthant, which is a [`StepFailure::OutOfDomain`].

// Index loops over small fixed-size vectors and matrices read as the formulas they implement.
#![allow(clippy::needless_range_loop)]

mod classical;
mod learned;
mod structure;
mod taylor;

pub use classical::{FieldInX, LogClassical, LogExplicit, LogMethod, LogMidpoint, OrthantChecked};
pub use learned::{LearnedExp, LearnedLogBisection, LearnedLogStepper};
pub use structure::{LogCanonical, LogSystem, MAX_HAMILTONIAN_EXPONENT, PREDICT_MAX_SHIFT};
#[cfg(test)]
pub(crate) use taylor::t_power_table;
pub use taylor::{ExpMonomial, ExpPolynomial, LogBisection, LogTaylorLanes, MAX_EXPONENT};

use crate::error::StepFailure;
use crate::exp::{EXP_MAX, EXP_MIN};

/// x^e at L lanes by binary powering: the same multiplications for every lane (e is the
/// term's, not the lane's), the loop over e's bits outside the lanes so that they vectorise.
#[inline(always)]
pub(super) fn pow_lanes<const L: usize>(x: &[f64; L], mut e: u32) -> [f64; L] {
    let (mut base, mut acc) = (*x, [1.0; L]);
    loop {
        if e & 1 == 1 {
            for l in 0..L {
                acc[l] *= base[l];
            }
        }
        e >>= 1;
        if e == 0 {
            return acc;
        }
        for l in 0..L {
            base[l] *= base[l];
        }
    }
}

pub(super) fn in_orthant<const N: usize>(x: &[f64; N]) -> Result<(), StepFailure> {
    if x.iter().any(|v| !v.is_finite()) {
        Err(StepFailure::NonFinite)
    } else if x.iter().any(|&v| v <= 0.0) {
        Err(StepFailure::OutOfDomain)
    } else {
        Ok(())
    }
}

/// q must stay finite and x = e^q representable (neither 0 nor ∞). On [[`EXP_MIN`],
/// [`EXP_MAX`]] e^q is a normal number, so libm is asked only outside it: the same answer, without
/// two calls to libm's exp a trajectory and step (7.6 % of a profile's samples of PNN's
/// Taylor K = 5 rollout).
#[inline]
pub(super) fn log_state_in_orthant<const N: usize>(q: &[f64; N]) -> Result<(), StepFailure> {
    if q.iter().any(|v| !v.is_finite()) {
        return Err(StepFailure::NonFinite);
    }
    if q.iter().all(|v| (EXP_MIN..=EXP_MAX).contains(v)) {
        return Ok(());
    }
    in_orthant(&q.map(f64::exp))
}

#[cfg(test)]
mod tests {
    //! The orthant check without libm: the same answer as asking libm's e^q, on both sides of
    //! the range it skips libm on and at the edges where e^q underflows to 0 or overflows.

    use super::*;

    /// The check as it was written before: e^q by libm, then the orthant.
    fn by_libm(q: &[f64; 2]) -> Result<(), StepFailure> {
        if q.iter().any(|v| !v.is_finite()) {
            return Err(StepFailure::NonFinite);
        }
        in_orthant(&q.map(f64::exp))
    }

    #[test]
    fn orthant_check_agrees_with_libm_across_the_range() {
        let mut edges = vec![
            0.0,
            -0.0,
            EXP_MIN,
            EXP_MAX,
            -745.0,
            -745.2,
            -800.0,
            709.78,
            709.79,
            710.0,
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ];
        edges.extend([EXP_MIN, EXP_MAX].iter().flat_map(|&e| {
            [
                f64::from_bits(e.to_bits() - 1),
                f64::from_bits(e.to_bits() + 1),
            ]
        }));
        // A grid across the whole range and past both ends.
        edges.extend((0..=400).map(|k| -800.0 + 4.0 * f64::from(k)));
        let mut outcomes = [0usize; 3];
        for &a in &edges {
            for &b in &[0.5, -746.0, 709.9, f64::NAN] {
                let q = [a, b];
                let mine = log_state_in_orthant(&q);
                assert_eq!(mine, by_libm(&q), "q = {q:?}");
                outcomes[match mine {
                    Ok(()) => 0,
                    Err(StepFailure::OutOfDomain) => 1,
                    Err(_) => 2,
                }] += 1;
            }
        }
        // Every answer occurs: inside, underflow to 0, and overflow or NaN.
        assert!(outcomes.iter().all(|&c| c > 0), "{outcomes:?}");
    }
}

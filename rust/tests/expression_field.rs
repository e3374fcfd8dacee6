//! RK4 on an expression field whose π∇H is an interpreted program ([`HamiltonianField`], its
//! wide blocks: AVX2 blocks of 32 lanes, AVX-512 blocks of 64 where the CPU has it): every lane
//! its scalar step, bit for bit, on every dispatch path and any chunking.

use super::splitting_lanes::check_lanes_equal_scalar;
use super::*;
use crate::classical::Rk4;
use crate::expression::Expression;
use crate::structures::bivector::HamiltonianField;
use crate::structures::SparsePolynomial;

/// The extended pendulum's field as `benches/peers.py`'s peers write it, as a program in
/// (u, v, r): u̇ = −sin v, v̇ = u + r − u² − v², ṙ = 2(u u̇ + v v̇).
fn pendulum_program() -> Expression {
    let [var, constant, add, sub, mul, neg, sin] =
        ["var", "const", "add", "sub", "mul", "neg", "sin"].map(opcode);
    #[rustfmt::skip]
    let rows: [TapeRow; 15] = [
        (var, 0, 0, 0.0), (var, 1, 0, 0.0), (var, 2, 0, 0.0),   // 0 u, 1 v, 2 r
        (sin, 1, 0, 0.0), (neg, 3, 0, 0.0),                     // 4 u̇
        (mul, 0, 0, 0.0), (mul, 1, 1, 0.0), (add, 0, 2, 0.0),   // 5 u², 6 v², 7 u + r
        (sub, 7, 5, 0.0), (sub, 8, 6, 0.0),                     // 9 v̇
        (mul, 0, 4, 0.0), (mul, 1, 9, 0.0), (add, 10, 11, 0.0), // 12 u u̇ + v v̇
        (constant, 0, 0, 2.0), (mul, 13, 12, 0.0),              // 14 ṙ
    ];
    tape(3, &rows, Some(&[4, 9, 14]))
}

#[test]
fn rk4_on_an_interpreted_field_takes_each_lanes_scalar_step() {
    let zero = || SparsePolynomial::new(3, &[], &[]).unwrap();
    // H (read only by the Jacobian, which RK4 does not use): u.
    let h = tape(3, &[(opcode("var"), 0, 0, 0.0)], None);
    let field = HamiltonianField::<3>::new(
        vec![zero(), zero(), zero()],
        h,
        Some(pendulum_program()),
        None,
    )
    .unwrap();
    let rk4 = Rk4 { system: field };
    let state = |rng: &mut Rng| {
        [
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
            rng.range(0.0, 2.0),
        ]
    };
    // Batches 1 to 67: blocks of 1, 8, 32 and 64 lanes, a huge state failing alone.
    check_lanes_equal_scalar(
        &rk4,
        "the pendulum's program",
        state,
        Some([1e80; 3]),
        (0.1, 17, 4),
    );
}

//! Point vortices in the plane as straight-line code ([`PointVortices`]): the pattern read off
//! an expression system, its field against the generic distance path (bit for bit) and against
//! π∇H with ∇H by forward mode (an independent oracle), RK4 in lanes against the scalar step and
//! against the generic path's RK4 on every dispatch path, and the systems it must leave alone.

use super::splitting_lanes::{assert_same_bits, check_lanes_equal_scalar, run};
use super::*;
use crate::classical::Rk4;
use crate::distance_sum::DistanceSum;
use crate::expression::Expression;
use crate::lanes::Lanes;
use crate::rollout::PerStep;
use crate::structures::bivector::{DistanceField, HamiltonianField};
use crate::structures::lie_poisson::VectorField;
use crate::structures::point_vortices::PointVortices;
use crate::structures::SparsePolynomial;

/// One distance term as [`DistanceSum::new`] reads it: (radial, weight, power, dims, first,
/// second).
type Term = (i64, f64, f64, i64, [i64; 3], [i64; 3]);

/// The ln r² term of the points i and j in the plane, weight w.
fn pair(i: i64, j: i64, w: f64) -> Term {
    (0, w, 0.0, 2, [2 * i, 2 * i + 1, 0], [2 * j, 2 * j + 1, 0])
}

/// H = Σ_k w_k φ_k(r_k²) as an expression tape (code, a, b, c), for the jets' ∇H: φ = ln or a
/// power, a second point of −1s the origin.
fn distances_expression(vars: usize, terms: &[Term]) -> Expression {
    let [var, constant, add, sub, mul, powf, log] =
        ["var", "const", "add", "sub", "mul", "powf", "log"].map(opcode);
    let mut rows: Vec<TapeRow> = Vec::new();
    let mut push = |row: TapeRow| {
        rows.push(row);
        rows.len() as i64 - 1
    };
    let mut total = None;
    for &(radial, w, power, dims, a, b) in terms {
        let mut q = None;
        for d in 0..dims as usize {
            let xa = push((var, a[d], 0, 0.0));
            let diff = match b[d] {
                -1 => xa,
                bd => {
                    let xb = push((var, bd, 0, 0.0));
                    push((sub, xa, xb, 0.0))
                }
            };
            let square = push((mul, diff, diff, 0.0));
            q = Some(match q {
                None => square,
                Some(q) => push((add, q, square, 0.0)),
            });
        }
        let q = q.unwrap();
        let phi = match radial {
            0 => push((log, q, 0, 0.0)),
            _ => push((powf, q, 0, power)),
        };
        let weight = push((constant, 0, 0, w));
        let term = push((mul, weight, phi, 0.0));
        total = Some(match total {
            None => term,
            Some(t) => push((add, t, term, 0.0)),
        });
    }
    tape(vars, &rows, None)
}

/// The expression system of H = Σ terms on the bracket whose upper triangle has the constant
/// `entries` (i, j, value) and zeros elsewhere, H's gradient by the distance terms.
fn system<const N: usize>(terms: &[Term], entries: &[(usize, usize, f64)]) -> HamiltonianField<N> {
    let mut upper = Vec::new();
    for i in 0..N {
        for j in i + 1..N {
            let value = entries.iter().find(|e| (e.0, e.1) == (i, j)).map(|e| e.2);
            upper.push(match value {
                Some(v) => SparsePolynomial::new(N, &[v], &[0; N]).unwrap(),
                None => SparsePolynomial::new(N, &[], &[]).unwrap(),
            });
        }
    }
    let column = |f: fn(&Term) -> f64| terms.iter().map(f).collect::<Vec<_>>();
    let radial: Vec<i64> = terms.iter().map(|t| t.0).collect();
    let dims: Vec<i64> = terms.iter().map(|t| t.3).collect();
    let first: Vec<[i64; 3]> = terms.iter().map(|t| t.4).collect();
    let second: Vec<[i64; 3]> = terms.iter().map(|t| t.5).collect();
    let distances = DistanceSum::new(
        N,
        &radial,
        &column(|t| t.1),
        &column(|t| t.2),
        &dims,
        &first,
        &second,
        None,
    )
    .unwrap();
    let h = distances_expression(N, terms);
    HamiltonianField::new(upper, h, None, Some(distances)).unwrap()
}

/// P vortices with circulations Γ_i: {x_{2i}, x_{2i+1}} = 1/Γ_i, H = −(1/4π) Σ_{i<j} Γ_iΓ_j
/// ln r_ij², the pairs in order.
fn vortices<const N: usize>(gamma: &[f64]) -> HamiltonianField<N> {
    let p = gamma.len();
    assert_eq!(2 * p, N);
    let mut terms = Vec::new();
    for i in 0..p {
        for j in i + 1..p {
            let w = -gamma[i] * gamma[j] / (4.0 * std::f64::consts::PI);
            terms.push(pair(i as i64, j as i64, w));
        }
    }
    let blocks: Vec<(usize, usize, f64)> =
        (0..p).map(|i| (2 * i, 2 * i + 1, 1.0 / gamma[i])).collect();
    system::<N>(&terms, &blocks)
}

/// Points spread over the unit disc's neighbourhood (no two closer than the draws allow).
fn state<const N: usize>(rng: &mut Rng) -> [f64; N] {
    std::array::from_fn(|_| rng.range(-1.5, 1.5))
}

fn check_vortices<const N: usize>(gamma: &[f64], rng: &mut Rng) {
    let generic = vortices::<N>(gamma);
    let fast = PointVortices::new(generic.clone()).expect("the vortices' pattern");
    // The field: the generic distance path's bits, and π∇H with ∇H by forward mode.
    for _ in 0..200 {
        let x = state::<N>(rng);
        let (f, g) = (fast.field(&x), generic.field(&x));
        assert_eq!(f.map(f64::to_bits), g.map(f64::to_bits), "N = {N}, {x:?}");
        let jet = generic.jet(&x);
        let grad = jet.grad();
        for i in 0..N / 2 {
            let c = 1.0 / gamma[i];
            let expect = [c * grad[2 * i + 1], -c * grad[2 * i]];
            for (got, want) in [f[2 * i], f[2 * i + 1]].iter().zip(expect) {
                assert!(
                    (got - want).abs() <= 1e-13 * (1.0 + want.abs()),
                    "N = {N}: {got:e} vs {want:e}"
                );
            }
        }
    }
    // RK4 in lanes: every lane its scalar step on every dispatch path, a collision (r² = 0)
    // failing alone.
    let rk4 = Rk4 {
        system: fast.clone(),
    };
    let mut collide = state::<N>(rng);
    collide[2] = collide[0];
    collide[3] = collide[1];
    let args = (0.05, 29, 4);
    check_lanes_equal_scalar(
        &rk4,
        &format!("vortices N = {N}"),
        state::<N>,
        Some(collide),
        args,
    );
    // … and the generic distance path's RK4, bit for bit.
    let slow = Rk4 {
        system: DistanceField::new(generic).unwrap(),
    };
    let mu0: Vec<[f64; N]> = (0..67).map(|_| state::<N>(rng)).collect();
    let reference = run(&PerStep(&slow), &mu0, args, args.1, false);
    for isa in isas() {
        let lanes = Lanes { stepper: &rk4, isa };
        let what = format!("vortices N = {N} against the distance path, {}", isa.name());
        assert_same_bits(&run(&lanes, &mu0, args, args.1, true), &reference, &what);
    }
}

#[test]
fn vortices_take_the_straight_line_field_with_the_distance_paths_bits() {
    let mut rng = Rng::new(0x70_127E);
    check_vortices::<4>(&[1.0, -0.7], &mut rng);
    // The scene's circulations.
    check_vortices::<6>(&[1.0, 1.0, 0.5], &mut rng);
    check_vortices::<8>(&[1.3, -0.4, 0.9, 2.0], &mut rng);
    check_vortices::<10>(&[0.6, 1.1, -1.4, 0.8, 1.7], &mut rng);
}

/// Any other H or bracket keeps the generic path, and gets its field back intact.
#[test]
fn other_systems_keep_the_distance_path() {
    let w = 0.3;
    let in_order = [pair(0, 1, w), pair(0, 2, -w), pair(1, 2, 2.0 * w)];
    let blocks = [(0, 1, 1.0), (2, 3, 2.0), (4, 5, -0.5)];
    assert!(PointVortices::new(system::<6>(&in_order, &blocks)).is_ok());
    let mut power = in_order;
    power[1] = (1, w, -0.5, 2, [0, 1, 0], [4, 5, 0]);
    let mut from_origin = in_order;
    from_origin[2] = (0, w, 0.0, 2, [2, 3, 0], [-1, -1, 0]);
    let mut crossed = in_order;
    crossed[0] = (0, w, 0.0, 2, [0, 3, 0], [2, 1, 0]);
    type Case<'a> = (&'a str, &'a [Term], &'a [(usize, usize, f64)]);
    let cases: [Case; 6] = [
        (
            "pairs out of order",
            &[in_order[1], in_order[0], in_order[2]],
            &blocks,
        ),
        ("a pair missing", &in_order[..2], &blocks),
        ("a power of r²", &power, &blocks),
        ("a distance from the origin", &from_origin, &blocks),
        ("coordinates of two points crossed", &crossed, &blocks),
        (
            "a bracket entry between two points",
            &in_order,
            &[(0, 1, 1.0), (1, 2, 1.0), (2, 3, 2.0), (4, 5, -0.5)],
        ),
    ];
    for (what, terms, entries) in cases {
        let field = system::<6>(terms, entries);
        let x = state::<6>(&mut Rng::new(3));
        let before = field.field(&x);
        match PointVortices::new(field) {
            Ok(_) => panic!("{what}: taken as vortices"),
            Err(back) => assert_eq!(back.field(&x).map(f64::to_bits), before.map(f64::to_bits)),
        }
    }
    // A bracket block not constant: {x0, x1} = x2.
    let mut upper: Vec<SparsePolynomial> = (0..15)
        .map(|_| SparsePolynomial::new(6, &[], &[]).unwrap())
        .collect();
    upper[0] = SparsePolynomial::new(6, &[1.0], &[0, 0, 1, 0, 0, 0]).unwrap();
    upper[9] = SparsePolynomial::new(6, &[2.0], &[0; 6]).unwrap();
    upper[14] = SparsePolynomial::new(6, &[-0.5], &[0; 6]).unwrap();
    let reference = system::<6>(&in_order, &blocks);
    let distances = reference.distances().unwrap().clone();
    let h = distances_expression(6, &in_order);
    let varying = HamiltonianField::<6>::new(upper, h, None, Some(distances)).unwrap();
    assert!(varying.constant_pair_blocks().is_none());
    assert!(PointVortices::new(varying).is_err());
    // Points in space (three coordinates a point): N = 6 is two points, not three.
    let space = [(0, w, 0.0, 3, [0, 1, 2], [3, 4, 5])];
    assert!(PointVortices::new(system::<6>(&space, &blocks)).is_err());
}

/// By lane, one or two lanes an iteration ([`rk4_by_lane`]), is RK4 lane by lane, bit for bit,
/// on even blocks and on odd ones (the last lane run as a pair with itself).
#[test]
fn by_lane_takes_each_lanes_own_step() {
    use crate::lane_field::{rk4_by_lane, rk4_with, AtStates, LaneField};
    fn check<const L: usize>(v: &PointVortices<6>, rng: &mut Rng) {
        let mu: [[f64; L]; 6] =
            std::array::from_fn(|_| std::array::from_fn(|_| rng.range(-1.5, 1.5)));
        let (mut lanes, mut pairs) = (mu, mu);
        rk4_with(v, 0.05, &mut lanes);
        let bits = |m: &[[f64; L]; 6]| m.map(|r| r.map(f64::to_bits));
        let f = AtStates::<2, _>(|y: &[[f64; 2]; 6], o: &mut [[f64; 2]; 6]| v.field_lanes(y, o));
        rk4_by_lane(&f, 0.05, &mut pairs);
        assert_eq!(bits(&lanes), bits(&pairs), "pairs, L = {L}");
        let mut ones = mu;
        let f = AtStates::<1, _>(|y: &[[f64; 1]; 6], o: &mut [[f64; 1]; 6]| v.field_lanes(y, o));
        rk4_by_lane(&f, 0.05, &mut ones);
        assert_eq!(bits(&lanes), bits(&ones), "one lane, L = {L}");
    }
    let v = PointVortices::new(vortices::<6>(&[1.0, 1.0, 0.5])).unwrap();
    let mut rng = Rng::new(0x9A125);
    check::<1>(&v, &mut rng);
    check::<5>(&v, &mut rng);
    check::<16>(&v, &mut rng);
}

//! The branch-free sin/cos against libm (ulp by ulp), and the splittings, DMV and the heavy
//! top's splitting in SIMD lanes against their scalar steps, bit for bit: on every dispatch
//! path, for batch sizes around the lane count, any segmentation, serial or on the pool.

#![allow(clippy::needless_range_loop)]

use super::*;
use crate::classical::{
    CasimirSplitting, HeavyTop, HeavyTopSplitting, MoserVeselov, RigidBody, Splitting, Splitting4,
};
use crate::lanes::{Isa, LaneStepper, Lanes, LANES};
use crate::rollout::{ChunkKernel, PerStep, Rollout};
use crate::trig::{sin_cos, sin_cos_lanes, REDUCED_RANGE};

// ---------------------------------------------------------------------------------------------
// sin_cos
// ---------------------------------------------------------------------------------------------

/// The distance in units in the last place between two finite doubles (0 between ±0).
pub(super) fn ulps(a: f64, b: f64) -> u64 {
    let ordered = |x: f64| {
        let bits = x.to_bits() as i64;
        if bits < 0 {
            i64::MIN - bits
        } else {
            bits
        }
    };
    ordered(a).abs_diff(ordered(b))
}

/// The worst ulp distance of sin and cos from libm's over `xs`.
fn worst_ulps(xs: impl Iterator<Item = f64>) -> (u64, u64, f64, f64) {
    let (mut ws, mut wc, mut xs_worst, mut xc_worst) = (0, 0, 0.0, 0.0);
    for x in xs {
        let (s, c) = sin_cos(x);
        let (es, ec) = (ulps(s, x.sin()), ulps(c, x.cos()));
        if es > ws {
            (ws, xs_worst) = (es, x);
        }
        if ec > wc {
            (wc, xc_worst) = (ec, x);
        }
    }
    (ws, wc, xs_worst, xc_worst)
}

#[test]
fn sin_cos_is_within_one_ulp_of_libm() {
    let mut rng = Rng::new(41);
    // 10⁶ uniform arguments in [−100, 100].
    let uniform = worst_ulps((0..1_000_000).map(|_| rng.range(-100.0, 100.0)));
    // Near every multiple k π/2, |k| ≤ 64, and near a spread of larger ones up to the end of
    // the reduced range: the double nearest k π/2 and its 64 neighbours each side, where the
    // reduction cancels the most.
    let mut near = Vec::new();
    let mut ks: Vec<f64> = (-64..=64).map(f64::from).collect();
    ks.extend(
        (0..2000)
            .map(|_| (rng.range(-1.0, 1.0) * REDUCED_RANGE / std::f64::consts::FRAC_PI_2).floor()),
    );
    for k in ks {
        let x0 = k * std::f64::consts::FRAC_PI_2;
        for d in -64i64..=64 {
            let x = f64::from_bits((x0.to_bits() as i64 + d) as u64);
            if x.abs() <= REDUCED_RANGE {
                near.push(x);
            }
        }
    }
    let near = worst_ulps(near.into_iter());
    // Uniform over the whole reduced range, and small arguments (no reduction at all).
    let wide = worst_ulps((0..200_000).map(|_| rng.range(-REDUCED_RANGE, REDUCED_RANGE)));
    let small =
        worst_ulps((0..200_000).map(|_| rng.range(-1.0, 1.0) * 10f64.powf(rng.range(-300.0, 0.0))));
    for (what, (s, c, xs, xc)) in [
        ("[-100, 100]", uniform),
        ("near k pi/2", near),
        ("wide", wide),
        ("small", small),
    ] {
        println!("sin_cos {what}: worst sin {s} ulp (x = {xs:e}), worst cos {c} ulp (x = {xc:e})");
        assert!(
            s <= 1 && c <= 1,
            "{what}: sin {s} ulp at {xs:e}, cos {c} ulp at {xc:e}"
        );
    }
}

#[test]
fn sin_cos_special_values_and_libm_beyond_the_range() {
    // Signed zeros, and every argument out of range (or not finite) is libm's, bit for bit.
    assert_eq!(sin_cos(0.0).0.to_bits(), 0.0f64.to_bits());
    assert_eq!(sin_cos(-0.0).0.to_bits(), (-0.0f64).to_bits());
    assert_eq!(sin_cos(0.0).1, 1.0);
    for x in [REDUCED_RANGE * 1.0000001, -1e6, 1e300, f64::MAX] {
        let (s, c) = sin_cos(x);
        assert_eq!(
            (s.to_bits(), c.to_bits()),
            (x.sin().to_bits(), x.cos().to_bits()),
            "{x:e}"
        );
    }
    for x in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        let (s, c) = sin_cos(x);
        assert!(s.is_nan() && c.is_nan(), "{x}");
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn sin_cos_lanes_avx2(x: &[f64; LANES], s: &mut [f64; LANES], c: &mut [f64; LANES]) {
    sin_cos_lanes(x, s, c);
}

#[test]
fn sin_cos_lanes_equal_the_scalar_call_bit_for_bit() {
    let mut rng = Rng::new(43);
    for round in 0..2000 {
        // Every fourth block has all its angles below the no-reduction cut (the block-wide
        // shortcut); the others mix in every kind of argument.
        let small = round % 4 == 1;
        let x: [f64; LANES] = std::array::from_fn(|l| match (round + l) % 11 {
            _ if small => rng.range(-0.7775, 0.7775),
            // Now and then a lane out of range or not finite, among in-range ones.
            0 if round % 3 == 0 => [f64::NAN, 1e7, -f64::INFINITY][round % 3],
            // Around the scalar path's no-reduction cut (0.99 π/4) and signed zeros.
            1 if round % 2 == 0 => rng.range(0.77, 0.79) * [1.0, -1.0][(round / 2) % 2],
            2 if round % 5 == 0 => [0.0, -0.0][round % 2],
            3 => rng.range(-1.0, 1.0) * 10f64.powf(rng.range(-20.0, 0.0)),
            _ => rng.range(-50.0, 50.0),
        });
        let want: [(u64, u64); LANES] = std::array::from_fn(|l| {
            let (s, c) = sin_cos(x[l]);
            (s.to_bits(), c.to_bits())
        });
        let (mut s, mut c) = ([0.0; LANES], [0.0; LANES]);
        sin_cos_lanes(&x, &mut s, &mut c);
        let got: [(u64, u64); LANES] = std::array::from_fn(|l| (s[l].to_bits(), c[l].to_bits()));
        assert_eq!(got, want, "portable, {x:?}");
        #[cfg(target_arch = "x86_64")]
        if Isa::detect().is_avx2() {
            // SAFETY: the CPU runs AVX2 and FMA (just detected).
            unsafe { sin_cos_lanes_avx2(&x, &mut s, &mut c) };
            let got: [(u64, u64); LANES] =
                std::array::from_fn(|l| (s[l].to_bits(), c[l].to_bits()));
            assert_eq!(got, want, "avx2, {x:?}");
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Lane steppers against the scalar steps
// ---------------------------------------------------------------------------------------------

pub(super) type Run = (Vec<f64>, Vec<TrajectoryInfo>);

/// A rollout of `mu0` with `kernel`, in segments of `segment` steps, serial or on the pool.
pub(super) fn run<const N: usize, K: ChunkKernel<N>>(
    kernel: &K,
    mu0: &[[f64; N]],
    (h, n_steps, every): (f64, usize, usize),
    segment: usize,
    parallel: bool,
) -> Run {
    let mut out = vec![0.0; mu0.len() * n_records(n_steps, every) * N];
    let mut r = Rollout::start(mu0, h, n_steps, every, &mut out).unwrap();
    while !r.is_finished() {
        r.advance_kernel(kernel, segment, &mut out, parallel)
            .unwrap();
    }
    (out, r.into_info())
}

pub(super) fn assert_same_bits(a: &Run, b: &Run, what: &str) {
    assert_eq!(a.0.len(), b.0.len());
    for (i, (x, y)) in a.0.iter().zip(&b.0).enumerate() {
        assert!(
            x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan()),
            "{what}: number {i}: {x:e} vs {y:e}"
        );
    }
    assert_eq!(a.1, b.1, "{what}: info");
}

/// `stepper` in lanes equals its scalar step bit for bit (states, records, diagnostics,
/// failures): batch sizes 1, 7, 8, 9, 64 and 67 (a padded last block), one state that fails in
/// the middle of a block, on every dispatch path, segmented and serial or on the pool; and each
/// of the first lanes equals its own scalar run alone. Returns the scalar runs' diagnostics.
pub(super) fn check_lanes_equal_scalar<const N: usize, S>(
    stepper: &S,
    what: &str,
    state: impl Fn(&mut Rng) -> [f64; N],
    bad: Option<[f64; N]>,
    args: (f64, usize, usize),
) -> Vec<TrajectoryInfo>
where
    S: LaneStepper<N> + StepMap<N, Workspace = ()>,
{
    let mut rng = Rng::new(47);
    let mut all = Vec::new();
    for n in [1, 7, 8, 9, 64, 67] {
        let mut mu0: Vec<[f64; N]> = (0..n).map(|_| state(&mut rng)).collect();
        let bad = bad.filter(|_| n > 2);
        if let Some(b) = bad {
            mu0[n / 2] = b;
        }
        let scalar = run(&PerStep(stepper), &mu0, args, args.1, false);
        if bad.is_some() {
            assert!(
                !scalar.1[n / 2].converged,
                "{what}: the bad state should fail"
            );
            assert_eq!(
                scalar.1.iter().filter(|i| i.converged).count(),
                n - 1,
                "{what}: one failure only"
            );
        }
        for isa in isas() {
            let lanes = Lanes { stepper, isa };
            let w = format!("{what}, n = {n}, {}", isa.name());
            assert_same_bits(&run(&lanes, &mu0, args, args.1, false), &scalar, &w);
            assert_same_bits(&run(&lanes, &mu0, args, 4, true), &scalar, &w);
            assert_same_bits(&run(&lanes, &mu0, args, 1, true), &scalar, &w);
        }
        let lanes = Lanes::new(stepper);
        let batch = run(&lanes, &mu0, args, args.1, true);
        for (i, m) in mu0.iter().enumerate().take(9) {
            let alone = run(
                &PerStep(stepper),
                std::slice::from_ref(m),
                args,
                args.1,
                false,
            );
            let row = alone.0.len();
            let mine = (batch.0[i * row..(i + 1) * row].to_vec(), vec![batch.1[i]]);
            assert_same_bits(&mine, &alone, &format!("{what}, lane {i} alone"));
        }
        all.extend(scalar.1);
    }
    all
}

fn rigid_state(rng: &mut Rng) -> [f64; 3] {
    // Scales over two decades, so the angles (and DMV's Newton counts) differ between lanes.
    let s = 3.0 * 10f64.powf(rng.range(-1.0, 1.0));
    rng.vec3(-s, s)
}

#[test]
fn simd_splittings_equal_the_scalar_path_bit_for_bit() {
    for inertia in [INERTIA, [0.9, 3.1, 1.7]] {
        let body = RigidBody::new(inertia).unwrap();
        // A state at the edge of the doubles overflows in a rotation: NonFinite in its lane
        // alone.
        let bad = Some([1.7e308; 3]);
        let args = (0.1, 17, 3);
        check_lanes_equal_scalar(&Splitting::strang(body), "strang", rigid_state, bad, args);
        check_lanes_equal_scalar(&Splitting4::suzuki(body), "suzuki", rigid_state, bad, args);
        check_lanes_equal_scalar(
            &CasimirSplitting::new(body),
            "casimir",
            rigid_state,
            bad,
            args,
        );
    }
    // Angles far beyond the reduced range go to libm in their lanes, the same as scalar.
    let body = RigidBody::new(INERTIA).unwrap();
    let huge = |rng: &mut Rng| rng.vec3(-1e6, 1e6);
    check_lanes_equal_scalar(
        &Splitting::strang(body),
        "strang huge",
        huge,
        Some([f64::MAX; 3]),
        (1.0, 5, 1),
    );
}

#[test]
fn simd_heavy_top_splitting_equals_the_scalar_path_bit_for_bit() {
    let top = HeavyTopSplitting {
        top: HeavyTop::new([1.0, 1.5, 2.0], 0.981, [0.1, -0.2, 1.0]).unwrap(),
    };
    let state = |rng: &mut Rng| {
        let s = 2.0 * 10f64.powf(rng.range(-1.0, 1.0));
        std::array::from_fn(|_| rng.range(-s, s))
    };
    // Γ × χ overflows in the potential flow.
    let bad = Some([0.5, 0.5, 0.5, 1.7e308, 1.7e308, 0.5]);
    check_lanes_equal_scalar::<6, _>(&top, "heavy top", state, bad, (0.05, 19, 4));
}

/// States whose steps h|ω| ≤ 0.4 all converge, over a decade of scales.
fn dmv_state(rng: &mut Rng) -> [f64; 3] {
    let s = 3.0 * 10f64.powf(rng.range(-1.0, 0.0));
    rng.vec3(-s, s)
}

#[test]
fn simd_dmv_equals_the_scalar_path_and_fails_lane_by_lane() {
    let body = RigidBody::new(INERTIA).unwrap();
    let dmv = MoserVeselov::new(body, NewtonOptions::default());
    // A state whose |y|² overflows: its Newton solve fails in its lane alone.
    let info = check_lanes_equal_scalar(
        &dmv,
        "dmv",
        dmv_state,
        Some([1e300, -1e300, 1e300]),
        (0.1, 13, 2),
    );
    let failures: Vec<_> = info.iter().filter_map(|i| i.failure).collect();
    assert!(!failures.is_empty() && failures.iter().all(|&f| f == StepFailure::SingularJacobian));
    assert!(info
        .iter()
        .any(|i| i.converged && i.max_newton_iterations > 0));
    // A state so large that the step h|ω| is huge: Newton does not converge there, while the
    // lanes beside it do.
    let info = check_lanes_equal_scalar(
        &dmv,
        "dmv huge",
        dmv_state,
        Some([3e4, -2e4, 1e4]),
        (0.1, 13, 2),
    );
    assert!(info.iter().any(|i| !i.converged));
    // A tight iteration cap: some lanes stop at it (NotConverged) while others converge.
    let tight = MoserVeselov::new(body, NewtonOptions::validated(1e-15, 3).unwrap());
    let info = check_lanes_equal_scalar(&tight, "dmv capped", dmv_state, None, (0.1, 13, 2));
    assert_some_capped_some_converged(&info);
}

#[test]
fn simd_poisson_steppers_keep_the_casimirs_over_many_steps() {
    // 20 000 steps of h = 0.1 in lanes: |μ|² (and for the heavy top |Γ|², M·Γ) to round-off.
    let body = RigidBody::new(INERTIA).unwrap();
    let mut rng = Rng::new(53);
    let mu0: Vec<[f64; 3]> = (0..11).map(|_| rng.vec3(-3.0, 3.0)).collect();
    let casimir = |m: &[f64]| m[0] * m[0] + m[1] * m[1] + m[2] * m[2];
    let n = 20_000;
    fn last<const N: usize, S: LaneStepper<N>>(s: &S, mu0: &[[f64; N]], n: usize) -> Run {
        run(&Lanes::new(s), mu0, (0.1, n, n), n, true)
    }
    let finals = [
        ("strang", last(&Splitting::strang(body), &mu0, n)),
        ("suzuki", last(&Splitting4::suzuki(body), &mu0, n)),
        ("casimir", last(&CasimirSplitting::new(body), &mu0, n)),
        (
            "dmv",
            last(&MoserVeselov::new(body, NewtonOptions::default()), &mu0, n),
        ),
    ];
    for (what, (out, info)) in finals {
        assert!(info.iter().all(|i| i.converged), "{what}");
        for (k, m) in mu0.iter().enumerate() {
            let end = &out[6 * k + 3..6 * k + 6];
            let drift = (casimir(end) / casimir(m) - 1.0).abs();
            assert!(drift <= 1e-12, "{what}: Casimir drift {drift:e}");
        }
    }
    let top = HeavyTopSplitting {
        top: HeavyTop::new([1.0, 1.5, 2.0], 0.981, [0.0, 0.0, 1.0]).unwrap(),
    };
    let mu0: Vec<[f64; 6]> = (0..11)
        .map(|_| std::array::from_fn(|_| rng.range(-1.0, 1.0)))
        .collect();
    let (out, info) = last(&top, &mu0, n);
    assert!(info.iter().all(|i| i.converged));
    let invariants = |m: &[f64]| {
        (
            m[3] * m[3] + m[4] * m[4] + m[5] * m[5],
            m[0] * m[3] + m[1] * m[4] + m[2] * m[5],
        )
    };
    for (k, m) in mu0.iter().enumerate() {
        let (g0, mg0) = invariants(m);
        let (g1, mg1) = invariants(&out[12 * k + 6..12 * k + 12]);
        assert!((g1 / g0 - 1.0).abs() <= 1e-12, "|Γ|² {g0} → {g1}");
        assert!(
            (mg1 - mg0).abs() <= 1e-12 * (1.0 + mg0.abs()),
            "M·Γ {mg0} → {mg1}"
        );
    }
}

#[test]
fn dmv_newton_update_solves_with_the_finite_difference_jacobian() {
    // δ from the closed-form Jacobian and the cofactor solve against −(∂G/∂y)⁻¹ G with ∂G/∂y
    // by central differences of G itself and nalgebra's LU.
    let mut rng = Rng::new(59);
    for inertia in [INERTIA, [0.9, 3.1, 1.7], [1.0, 1.0, 1.9]] {
        let dmv = MoserVeselov::new(RigidBody::new(inertia).unwrap(), NewtonOptions::default());
        for _ in 0..50 {
            let (m, y, h) = (
                rng.vec3(-3.0, 3.0),
                rng.vec3(-0.5, 0.5),
                rng.range(0.01, 0.5),
            );
            let eps = 1e-6;
            let jac = nalgebra::Matrix3::from_fn(|r, k| {
                let (mut yp, mut ym) = (y, y);
                yp[k] += eps;
                ym[k] -= eps;
                (dmv.residual(h, &m, &yp)[r] - dmv.residual(h, &m, &ym)[r]) / (2.0 * eps)
            });
            let g = nalgebra::Vector3::from(dmv.residual(h, &m, &y));
            let want = -jac.lu().solve(&g).unwrap();
            let got = dmv.newton_delta(h, &m, &y);
            for i in 0..3 {
                assert!(
                    (got[i] - want[i]).abs() <= 1e-7 * (1.0 + want.amax()),
                    "{inertia:?}: δ {got:?} vs {want:?}"
                );
            }
        }
    }
}

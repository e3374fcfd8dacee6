//! The network term in SIMD lanes ([`crate::generating::NetworkLanes`]) and the lane Newton
//! solves of a learned S (polynomial plus network) on so(3) and se(3):
//! - the lane jets (tangents forward, one adjoint back) and gradients (reverse mode) against the
//!   scalar forward mode ([`GeneratingFunction::jet`], libm's tanh) to round-off, for both input
//!   maps, in 2, 3 and 6 dimensions, the origin of the homogeneous map included; one lane and a
//!   block give the same bits;
//! - a learned step in lanes against the generic dual-number step of the same stepper, on so(3)
//!   through the stepper and on se(3) through the lane solver itself;
//! - `step` and `step_batch` give the same bits in every block.

#![allow(clippy::needless_range_loop)]

use super::*;
use crate::generating::polynomial_lanes::JetLanes;
use crate::generating::{scratch_len, NetworkLanes, NETWORK_LANES_MAX_WIDTH};
use crate::lanes::{Isa, LANES};
use crate::structures::lie_groupoid::LieAlgebra;
use crate::structures::{ExpMonomial, ExpPolynomial, LogCanonical};
use nalgebra::{Const, DimMin};

/// The lane form of `gf`'s network whatever N (the steppers take it for N ≤ 3 only).
fn lanes_of<const N: usize>(gf: &GeneratingFunction<N>) -> NetworkLanes<'_> {
    NetworkLanes::new(gf.mlp.as_ref().unwrap(), gf.mlp_power, gf.inputs).expect("narrow")
}

/// A random network term with 1 + N inputs: one or two hidden layers of at most `width`.
pub(super) fn network<const N: usize>(
    rng: &mut Rng,
    width: usize,
    inputs: MlpInputs,
) -> GeneratingFunction<N> {
    let mut widths = vec![N + 1];
    for _ in 0..1 + rng.below(2) {
        widths.push(1 + rng.below(width));
    }
    widths.push(1);
    let layers = widths
        .windows(2)
        .map(|w| {
            let a = (6.0 / (w[0] + w[1]) as f64).sqrt();
            let weight = (0..w[0] * w[1]).map(|_| rng.range(-a, a)).collect();
            let bias = (0..w[1]).map(|_| rng.range(-0.5, 0.5)).collect();
            Layer::new(w[0], w[1], weight, bias).unwrap()
        })
        .collect();
    let m = 1 + rng.below(4) as u32;
    GeneratingFunction::new(
        Polynomial::default(),
        Some(Mlp::new(layers).unwrap()),
        m,
        inputs,
    )
    .unwrap()
}

/// The lane jets of `net` at L momenta (the Hessian when `HESS`), from zero.
fn lane_jets<const N: usize, const L: usize, const HESS: bool>(
    gf: &GeneratingFunction<N>,
    t: f64,
    p: &[[f64; N]],
) -> JetLanes<N, L> {
    let net = lanes_of(gf);
    let mut pl = [[0.0; L]; N];
    for (l, q) in p.iter().enumerate() {
        for i in 0..N {
            pl[i][l] = q[i];
        }
    }
    let mut jet = JetLanes {
        v: [0.0; L],
        g: [[0.0; L]; N],
        h: [[[0.0; L]; N]; N],
    };
    let mut buf = vec![[0.0; LANES]; scratch_len(gf.mlp.as_ref().unwrap(), N)];
    net.add_jet_lanes::<N, L, HESS>(t, &pl, &mut buf, &mut jet);
    jet
}

fn check_jets<const N: usize>(rng: &mut Rng) {
    for inputs in ALL_INPUTS {
        for _ in 0..6 {
            let gf = network::<N>(rng, 12, inputs);
            let t = rng.range(0.01, 0.3);
            let mut p: Vec<[f64; N]> = (0..LANES)
                .map(|_| [0.0; N].map(|_: f64| rng.range(-2.0, 2.0)))
                .collect();
            // The origin: the homogeneous term and its derivatives vanish there.
            p[3] = [0.0; N];
            let block = lane_jets::<N, LANES, true>(&gf, t, &p);
            let grads = lane_jets::<N, LANES, false>(&gf, t, &p);
            let mut ws = gf.workspace();
            for (l, q) in p.iter().enumerate() {
                let one = lane_jets::<N, 1, true>(&gf, t, std::slice::from_ref(q));
                let one_g = lane_jets::<N, 1, false>(&gf, t, std::slice::from_ref(q));
                let exact = gf.jet(t, q, &mut ws);
                let scale = 1.0 + exact.flat().iter().fold(0.0f64, |m, v| m.max(v.abs()));
                let close = |a: f64, b: f64| (a - b).abs() <= 1e-13 * scale;
                assert_eq!(
                    one.v[0].to_bits(),
                    block.v[l].to_bits(),
                    "{inputs:?} lane {l}"
                );
                assert!(close(block.v[l], exact.v), "{inputs:?} value {l}");
                assert_eq!(one_g.v[0].to_bits(), grads.v[l].to_bits());
                assert!(close(grads.v[l], exact.v), "{inputs:?} reverse value {l}");
                for a in 0..N {
                    assert_eq!(one.g[a][0].to_bits(), block.g[a][l].to_bits());
                    assert_eq!(one_g.g[a][0].to_bits(), grads.g[a][l].to_bits());
                    assert!(
                        close(grads.g[a][l], exact.g[a]),
                        "{inputs:?} N={N} reverse ∂{a}"
                    );
                    assert!(
                        close(block.g[a][l], exact.g[a]),
                        "{inputs:?} N={N} ∂{a} {l}"
                    );
                    for b in a..N {
                        assert_eq!(one.h[a][b][0].to_bits(), block.h[a][b][l].to_bits());
                        let h = exact.hess()[a][b];
                        assert!(
                            close(block.h[a][b][l], h),
                            "{inputs:?} N={N} ∂{a}∂{b} lane {l}: {} vs {h}",
                            block.h[a][b][l]
                        );
                    }
                }
            }
            if inputs == MlpInputs::Homogeneous {
                assert!(block.v[3] == 0.0 && block.g.iter().all(|g| g[3] == 0.0));
            }
        }
    }
}

#[test]
fn network_lanes_equal_the_scalar_forward_mode() {
    let mut rng = Rng::new(0x4E7_1A4E);
    check_jets::<2>(&mut rng);
    check_jets::<3>(&mut rng);
    check_jets::<6>(&mut rng);
}

/// Networks wider than [`NETWORK_LANES_MAX_WIDTH`] keep the batched kernel.
#[test]
fn wide_networks_keep_the_batched_path() {
    let mut rng = Rng::new(0x4E7_1A4F);
    let wide = mlp_with_widths(&mut rng, &[4, NETWORK_LANES_MAX_WIDTH + 1, 1], 1.0);
    let gf = GeneratingFunction::<3>::new(Polynomial::default(), Some(wide), 3, MlpInputs::Plain)
        .unwrap();
    assert!(gf.network_lanes().is_none());
    assert!(gf.workspace().lanes.is_empty());
    let narrow = mlp_with_widths(&mut rng, &[4, NETWORK_LANES_MAX_WIDTH, 1], 1.0);
    let gf = GeneratingFunction::<3>::new(Polynomial::default(), Some(narrow), 3, MlpInputs::Plain)
        .unwrap();
    assert!(gf.network_lanes().is_some());
}

/// A learned S on so(3), both charts and both input maps: `step` (the lane solver with one lane)
/// against `step_generic` (dual numbers through the scalar MLP, started from μ) over 20 steps of
/// 25 states: the same states to 1e-12 relative and the Casimir |μ|² kept to 1e-13 a step; and
/// `step_batch` in blocks of 1, 3, 8 and 29 gives `step`'s bits.
#[test]
fn learned_so3_step_in_lanes_equals_the_generic_step() {
    let mut rng = Rng::new(0x4E7_1A50);
    for chart in [Chart::Cayley, Chart::Exp] {
        for inputs in ALL_INPUTS {
            let st = stepper(random_generating(&mut rng, inputs), chart);
            let states: Vec<[f64; 3]> = (0..29)
                .map(|_| {
                    let r = rng.range(0.5, 3.0);
                    rng.sphere(r)
                })
                .collect();
            let mut ws = st.workspace();
            let mut worst = 0.0f64;
            for &mu in &states[..25] {
                let (mut a, mut b) = (mu, mu);
                for _ in 0..20 {
                    let c0 = dot(&a, &a);
                    st.step(0.1, &mut a, &mut ws).unwrap();
                    st.step_generic(0.1, &mut b, &mut ws).unwrap();
                    assert!((dot(&a, &a) - c0).abs() <= 1e-13 * c0, "{chart:?} Casimir");
                    let r = norm(&b);
                    worst = worst.max(norm(&sub(&a, &b)) / r);
                }
            }
            assert!(
                worst <= 1e-12,
                "{chart:?} {inputs:?}: lanes vs generic {worst:e}"
            );
            let mut one = states.clone();
            for m in &mut one {
                st.step(0.1, m, &mut ws).unwrap();
            }
            for block in [1, 3, 8, 29] {
                let mut mu = states.clone();
                for (m, r) in mu
                    .chunks_mut(block)
                    .zip(vec![Ok(StepStats::default()); 29].chunks_mut(block))
                {
                    st.step_batch(0.1, m, &vec![true; m.len()], r, &mut ws);
                    assert!(r.iter().all(|r| r.is_ok()));
                }
                assert!(
                    same_bits(&mu.concat(), &one.concat()),
                    "{chart:?} {inputs:?}: blocks of {block}"
                );
            }
        }
    }
}

/// The premise of the lane networks' bit identity across instruction sets: the FMA instruction
/// and `f64::mul_add` in portable code (the C library's `fma`) round alike, on random operands
/// of every magnitude, on cancelling ones (a·b ≈ −c, where the fused and the plain forms differ
/// most), subnormal results and the special values.
#[test]
fn fused_multiply_add_has_the_same_bits_in_hardware_and_software() {
    #[cfg(target_arch = "x86_64")]
    {
        // The instruction itself (`f64::mul_add` is a call to the C library in a debug build).
        #[target_feature(enable = "fma")]
        fn hardware(a: f64, b: f64, c: f64) -> f64 {
            use std::arch::x86_64::{_mm_cvtsd_f64, _mm_fmadd_sd, _mm_set_sd};
            _mm_cvtsd_f64(_mm_fmadd_sd(_mm_set_sd(a), _mm_set_sd(b), _mm_set_sd(c)))
        }
        #[inline(never)]
        fn software(a: f64, b: f64, c: f64) -> f64 {
            a.mul_add(b, c)
        }
        if !std::is_x86_feature_detected!("fma") {
            return;
        }
        let mut rng = Rng::new(0x4E7_1A53);
        let specials = [
            0.0,
            -0.0,
            1.0,
            f64::MIN_POSITIVE,
            5e-324,
            f64::MAX,
            f64::INFINITY,
        ];
        let mut cases: Vec<[f64; 3]> = (0..200_000)
            .map(|_| {
                let mut x = || rng.range(-1.0, 1.0) * 10f64.powf(rng.range(-300.0, 300.0));
                [x(), x(), x()]
            })
            .collect();
        for _ in 0..200_000 {
            let (a, b) = (rng.range(-2.0, 2.0), rng.range(-2.0, 2.0));
            let c = -(a * b) * (1.0 + rng.range(-1e-15, 1e-15));
            cases.push([a, b, c]);
            cases.push([a * 1e-300, b * 1e-10, c * 1e-310]);
        }
        for &a in &specials {
            for &b in &specials {
                for c in [0.0, -1.0, f64::NEG_INFINITY, f64::NAN] {
                    cases.push([a, -b, c]);
                }
            }
        }
        let mut differ = 0;
        for [a, b, c] in cases {
            // SAFETY: this CPU runs FMA (detected above).
            let h = unsafe { hardware(a, b, c) };
            let s = software(a, b, c);
            assert!(
                h.to_bits() == s.to_bits() || (h.is_nan() && s.is_nan()),
                "fma({a:e}, {b:e}, {c:e}): {h:e} against {s:e}"
            );
            differ += usize::from(h.to_bits() != (a * b + c).to_bits());
        }
        eprintln!("fused and plain differ in {differ} cases");
        // The cases reach where fusing matters (so the comparison is not of plain products).
        assert!(
            differ > 10_000,
            "{differ} cases where fused and plain differ"
        );
    }
}

/// A learned so(3) step's bits depend on neither the dispatch nor the block: the portable path
/// (the C library's `fma` for every fused multiply-add), the widest one (FMA instructions),
/// whole chunks and one state at a time agree bit for bit, in both charts and for both input
/// maps, with a NaN state failing alone.
#[test]
fn learned_lane_bits_are_the_same_for_every_dispatch_and_block() {
    use crate::lanes_bisection::{so3_newton_steps, ChartNewton};
    use crate::realization::Generating;
    let mut rng = Rng::new(0x4E7_1A52);
    for chart in [Chart::Cayley, Chart::Exp] {
        for inputs in ALL_INPUTS {
            // t · N (m = 1): the network's last bits reach the states at h = 0.1 (t^m N with a
            // larger m rounds away against the polynomial's terms).
            let mut terms = minus_t_h();
            terms.extend(random_terms(&mut rng, 4, (2, 4), 3, 0.02));
            let poly = Polynomial::new(terms).unwrap();
            let mlp = random_mlp(&mut rng, 12, 1.0);
            let gf = GeneratingFunction::new(poly, Some(mlp), 1, inputs).unwrap();
            let (poly, network) = gf.lane_parts().expect("a narrow network");
            let sys = ChartNewton {
                poly,
                network,
                chart,
                tol: 1e-12,
                max_iter: 50,
                predict: true,
            };
            let mut mu0: Vec<[f64; 3]> = (0..29)
                .map(|_| {
                    let r = rng.range(0.5, 3.0);
                    rng.sphere(r)
                })
                .collect();
            mu0[5] = [f64::NAN, 1.0, 0.0];
            let mut buf = vec![[0.0; LANES]; scratch_len(gf.mlp.as_ref().unwrap(), 3)];
            let mut run = |isa: Isa, block: usize| {
                let mut mu = mu0.clone();
                let mut res = vec![Ok(StepStats::default()); mu.len()];
                for (m, r) in mu.chunks_mut(block).zip(res.chunks_mut(block)) {
                    let live = vec![true; m.len()];
                    so3_newton_steps(&sys, isa, &mut buf, 0.1, m, &live, r);
                }
                (mu, res)
            };
            let (reference, ref_results) = run(Isa::PORTABLE, 29);
            assert_eq!(ref_results[5], Err(StepFailure::NonFinite));
            assert!(ref_results.iter().filter(|r| r.is_ok()).count() == 28);
            for isa in isas() {
                for block in [1, 3, 8, 13, 29] {
                    let (mu, res) = run(isa, block);
                    assert_eq!(res, ref_results, "{chart:?} {inputs:?} {isa:?} {block}");
                    assert!(
                        same_bits(&mu.concat(), &reference.concat()),
                        "{chart:?} {inputs:?} {isa:?} blocks of {block}"
                    );
                }
            }
        }
    }
}

/// A learned S on se(3) (−tH of a heavy top plus a random network, plain inputs), in the lane
/// solver itself from μ: the generic step's Newton counts and states to 1e-12 over 15 steps,
/// both Casimirs kept to 1e-13 a step, and a block of 8 gives the one-lane bits; through the
/// stepper (which takes the lanes for N = 6 too, from the predicted start): the generic step's
/// states to 1e-12 and `step_batch` gives `step`'s bits.
#[test]
fn learned_se3_lane_solve_equals_the_generic_step() {
    use crate::lanes_bisection_exp::chart_newton_steps;
    use crate::lanes_bisection_se3::{Se3Chart, Se3Newton};
    let mut rng = Rng::new(0x4E7_1A51);
    // −tH for H = ½ Σ M_i²/I_i + Γ₃ (mgl = 1, χ = e₃).
    let inertia = [1.0, 1.5, 2.0];
    let mut terms: Vec<Monomial<6>> = (0..3)
        .map(|i| {
            let mut p_powers = [0; 6];
            p_powers[i] = 2;
            Monomial {
                t_power: 1,
                p_powers,
                coeff: -0.5 / inertia[i],
            }
        })
        .collect();
    terms.push(Monomial {
        t_power: 1,
        p_powers: [0, 0, 0, 0, 0, 1],
        coeff: -1.0,
    });
    let mut gf = network::<6>(&mut rng, 16, MlpInputs::Plain);
    gf.polynomial = Polynomial::new(terms).unwrap();
    gf.mlp_power = 3;
    assert!(gf.network_lanes().is_some());
    let st = BisectionStepper::new(
        gf,
        Groupoid::new(LieAlgebra::se3(), Chart::Exp).unwrap(),
        NewtonOptions::default(),
    );
    let sys = Se3Newton {
        poly: &st.generating.polynomial,
        network: Some(lanes_of(&st.generating)),
        chart: Se3Chart,
        tol: st.newton.tol,
        max_iter: st.newton.max_iter,
        predict: false,
    };
    let mut buf = vec![[0.0; LANES]; scratch_len(st.generating.mlp.as_ref().unwrap(), 6)];
    let mut ws = st.workspace();
    let casimirs = |m: &[f64; 6]| {
        let (mm, g) = ([m[0], m[1], m[2]], [m[3], m[4], m[5]]);
        (dot(&g, &g), dot(&mm, &g))
    };
    let mut states = Vec::new();
    for _ in 0..8 {
        let g = rng.sphere(1.0);
        let m = rng.vec3(-1.0, 1.0);
        states.push([m[0], m[1], m[2], g[0], g[1], g[2]]);
    }
    let mut worst = 0.0f64;
    for &mu in &states {
        let (mut a, mut b) = (mu, mu);
        for _ in 0..15 {
            let (c1, c2) = casimirs(&a);
            let mut ra = [Err(StepFailure::OutOfDomain)];
            let mut one = [a];
            chart_newton_steps(
                &sys,
                Isa::detect(),
                &mut buf,
                0.1,
                &mut one,
                &[true],
                &mut ra,
            );
            a = one[0];
            let rb = st.step_generic(0.1, &mut b, &mut ws).unwrap();
            assert_eq!(ra[0].unwrap().iterations, rb.iterations, "Newton counts");
            let (d1, d2) = casimirs(&a);
            assert!(
                (d1 - c1).abs() <= 1e-13 && (d2 - c2).abs() <= 1e-13,
                "Casimirs"
            );
            let diff = (0..6).fold(0.0f64, |m, i| m.max((a[i] - b[i]).abs()));
            worst = worst.max(diff);
        }
    }
    assert!(worst <= 1e-12, "se(3) lanes vs generic {worst:e}");
    let mut one = states.clone();
    for m in &mut one {
        let mut r = [Err(StepFailure::OutOfDomain)];
        chart_newton_steps(
            &sys,
            Isa::detect(),
            &mut buf,
            0.1,
            std::slice::from_mut(m),
            &[true],
            &mut r,
        );
    }
    let mut block = states.clone();
    let mut results = vec![Ok(StepStats::default()); 8];
    chart_newton_steps(
        &sys,
        Isa::detect(),
        &mut buf,
        0.1,
        &mut block,
        &[true; 8],
        &mut results,
    );
    assert!(same_bits(&block.concat(), &one.concat()));
    // The stepper's own step: the lanes with the predicted start.
    let mut worst = 0.0f64;
    for &mu in &states {
        let (mut a, mut b) = (mu, mu);
        for _ in 0..15 {
            st.step(0.1, &mut a, &mut ws).unwrap();
            st.step_generic(0.1, &mut b, &mut ws).unwrap();
            worst = worst.max((0..6).fold(0.0f64, |m, i| m.max((a[i] - b[i]).abs())));
        }
    }
    assert!(worst <= 1e-12, "stepper lanes vs generic {worst:e}");
    let mut one = states.clone();
    for m in &mut one {
        st.step(0.1, m, &mut ws).unwrap();
    }
    let mut block = states.clone();
    st.step_batch(0.1, &mut block, &[true; 8], &mut results, &mut ws);
    assert!(results.iter().all(|r| r.is_ok()));
    assert!(same_bits(&block.concat(), &one.concat()));
}

/// A learned log-canonical S (the exact t-linear terms of a Lotka–Volterra H plus a random
/// network, plain inputs) stepped by [`LearnedLogStepper`] in lanes against the generic
/// dual-number step of the same integrator (full Newton from the whole S's start), on PNN's 2-D
/// system and a 5-D one (one Casimir): the same states to 1e-12 over 20 steps of 13 states; the
/// same Newton counts for a t⁵ network term (the shipped models' power), at most one update more
/// for a t³ one (the lanes keep the network's Hessian from their first update); `step` and
/// `step_batch` in blocks of 1, 5, 8 and 13 give the same bits; a network too wide for the lanes
/// takes the generic step itself, with its counts.
#[test]
fn learned_log_canonical_steps_in_lanes_equal_the_generic_step() {
    let mut rng = Rng::new(0x4E7_1A52);
    // PNN's H = x₁ + x₂ − ln x₁ − 2 ln x₂: S = −t(x₁ + x₂) + t(1, 2)·q plus the network.
    let base = super::log_canonical::pnn_taylor(1);
    check_learned_log(
        &mut rng,
        base.generating,
        base.realization,
        [0.0, 2f64.ln()],
    );
    // H = Σ x_i − b_i ln x_i on a rank-4 c: S = −t Σ x_i + t b·q, states about x = b.
    let b = [1.0, 2.0, 1.5, 0.5, 1.0];
    let c = [
        [0.0, 1.0, -1.0, 1.0, 0.0],
        [-1.0, 0.0, 1.0, 0.0, 1.0],
        [1.0, -1.0, 0.0, 1.0, -1.0],
        [-1.0, 0.0, -1.0, 0.0, 1.0],
        [0.0, -1.0, 1.0, -1.0, 0.0],
    ];
    let terms = (0..5)
        .map(|i| {
            let mut exponents = [0; 5];
            exponents[i] = 1;
            ExpMonomial {
                t_power: 1,
                exponents,
                coeff: -1.0,
            }
        })
        .collect();
    let taylor = ExpPolynomial::new(terms, b).unwrap();
    check_learned_log(
        &mut rng,
        taylor,
        LogCanonical::new(c).unwrap(),
        b.map(f64::ln),
    );
}

fn check_learned_log<const N: usize>(
    rng: &mut Rng,
    taylor: ExpPolynomial<N>,
    c: LogCanonical<N>,
    centre: [f64; N],
) where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    use crate::structures::log_canonical::{LearnedExp, LearnedLogBisection, LearnedLogStepper};
    // (width, m): the lanes (narrow) and the batched kernel (wide); m = 5 is the shipped
    // models' power, m = 3 a network term 100× larger at h = 0.1.
    for (width, power) in [(6, 5), (6, 3), (NETWORK_LANES_MAX_WIDTH + 1, 3)] {
        let mut network = network::<N>(rng, width.min(6), MlpInputs::Plain);
        if width > NETWORK_LANES_MAX_WIDTH {
            network.mlp = Some(super::mlp_with_widths(rng, &[N + 1, width, 1], 1.0));
        }
        network.mlp_power = power;
        let wide = network.network_lanes().is_none();
        let s = LearnedExp::new(taylor.clone(), network).unwrap();
        let stepper = LearnedLogStepper(LearnedLogBisection::unit_scale(
            s,
            c.clone(),
            NewtonOptions::default(),
        ));
        assert_eq!(stepper.batch() == 1, wide);
        let mut ws = stepper.workspace();
        let states: Vec<[f64; N]> = (0..13)
            .map(|_| centre.map(|q| q + rng.range(-0.4, 0.4)))
            .collect();
        let mut worst = 0.0f64;
        for &q0 in &states {
            let (mut a, mut b) = (q0, q0);
            for _ in 0..20 {
                let ra = stepper.step(0.1, &mut a, &mut ws).unwrap();
                let rb = stepper.0.step(0.1, &mut b, &mut ws).unwrap();
                // The lanes start from the Taylor terms alone and keep the network's Hessian
                // from their first update (full Newton refreshes all of it): the same updates
                // where the term is t⁵-small, at most one more where it is t³.
                if wide || power == 5 {
                    assert_eq!(ra.iterations, rb.iterations, "Newton counts, m = {power}");
                } else {
                    assert!(
                        ra.iterations <= rb.iterations + 1,
                        "Newton counts, m = {power}"
                    );
                }
                worst = worst.max((0..N).fold(0.0f64, |m, i| m.max((a[i] - b[i]).abs())));
            }
        }
        assert!(
            worst <= 1e-12,
            "N = {N}, width {width}, m = {power}: lanes vs generic {worst:e}"
        );
        let mut one = states.clone();
        for q in &mut one {
            stepper.step(0.1, q, &mut ws).unwrap();
        }
        for block in [1, 5, 8, 13] {
            let mut q = states.clone();
            let mut results = vec![Ok(StepStats::default()); 13];
            for (m, r) in q.chunks_mut(block).zip(results.chunks_mut(block)) {
                stepper.step_batch(0.1, m, &vec![true; m.len()], r, &mut ws);
            }
            assert!(results.iter().all(|r| r.is_ok()));
            assert!(same_bits(&q.concat(), &one.concat()), "blocks of {block}");
        }
    }
}

//! Bisection steps of a polynomial S in SIMD lanes against the scalar path: the polynomial jets
//! lane by lane (bit for bit, every dispatch path, batches that are not multiples of the lane
//! count, exponents beyond the table of powers), the lockstep Newton solve of a block against
//! one trajectory at a time, and masked lanes (a failing lane leaves the others' bits alone).

#![allow(clippy::needless_range_loop)]

use super::*;
use crate::dual::Dual1;
use crate::lanes::{Isa, LANES};
use crate::lanes_bisection::{polynomial_gradients, polynomial_jets};

/// Random polynomials in N variables with exponents up to 11 (the table of powers stops at 8:
/// the `powi` fallback runs too).
fn random_polynomial<const N: usize>(rng: &mut Rng, n_terms: usize) -> Polynomial<N> {
    Polynomial::new(
        (0..n_terms)
            .map(|_| Monomial {
                t_power: 1 + rng.below(10) as u32,
                p_powers: [0; N].map(|_: u32| rng.below(12) as u32),
                coeff: rng.range(-1.0, 1.0),
            })
            .collect(),
    )
    .unwrap()
}

/// Random polynomials whose terms lack variables: each exponent 0 half the time, so a term has
/// any number of variables from 0 to N (the lanes take terms in one, two or three variables by
/// code of their own and the others by the general loop). Every count appears at least once.
fn sparse_polynomial<const N: usize>(rng: &mut Rng, n_terms: usize) -> Polynomial<N> {
    let mut terms: Vec<Monomial<N>> = (0..=N)
        .map(|count| {
            let mut p_powers = [0; N];
            for i in 0..count {
                p_powers[(i + count) % N] = 1 + rng.below(11) as u32;
            }
            Monomial {
                t_power: 1 + rng.below(10) as u32,
                p_powers,
                coeff: rng.range(-1.0, 1.0),
            }
        })
        .collect();
    terms.extend((0..n_terms).map(|_| Monomial {
        t_power: 1 + rng.below(10) as u32,
        p_powers: [0; N].map(|_: u32| {
            if rng.below(2) == 0 {
                0
            } else {
                1 + rng.below(11) as u32
            }
        }),
        coeff: rng.range(-1.0, 1.0),
    }));
    Polynomial::new(terms).unwrap()
}

fn check_jets<const N: usize>(rng: &mut Rng) {
    for (n, sparse) in [1, 7, 8, 13, 37]
        .into_iter()
        .flat_map(|n| [(n, false), (n, true)])
    {
        let poly = if sparse {
            sparse_polynomial::<N>(rng, 9)
        } else {
            random_polynomial::<N>(rng, 9)
        };
        let t = rng.range(0.0, 0.5);
        let p: Vec<[f64; N]> = (0..n)
            .map(|_| [0.0; N].map(|_: f64| rng.range(-2.0, 2.0)))
            .collect();
        for isa in isas() {
            let mut jets = vec![Jet2::<N>::default(); n];
            let mut grads = vec![Dual1::<N>::default(); n];
            polynomial_jets(&poly, isa, t, &p, &mut jets);
            polynomial_gradients(&poly, isa, t, &p, &mut grads);
            for (j, q) in p.iter().enumerate() {
                let (a, b) = (poly.jet(t, q), poly.gradient(t, q));
                assert!(
                    same_bits(&a.flat(), &jets[j].flat()),
                    "{isa:?} N={N} jet {j}"
                );
                assert_eq!(a.v.to_bits(), b.v.to_bits());
                assert!(same_bits(&a.g, &b.g), "scalar gradient = jet's gradient");
                assert_eq!(b.v.to_bits(), grads[j].v.to_bits(), "{isa:?} gradient {j}");
                assert!(same_bits(&b.g, &grads[j].g), "{isa:?} N={N} gradient {j}");
            }
        }
    }
}

/// Lane l of the lane evaluation is the scalar jet at p_l, bit for bit.
#[test]
fn polynomial_lanes_equal_the_scalar_jets() {
    let mut rng = Rng::new(0x1A2E_5001);
    check_jets::<1>(&mut rng);
    check_jets::<2>(&mut rng);
    check_jets::<3>(&mut rng);
    check_jets::<4>(&mut rng);
    check_jets::<6>(&mut rng);
}

/// A Taylor-HJ stepper (polynomial S) in both charts, simplified and full Newton.
fn taylor_steppers() -> Vec<BisectionStepper<3>> {
    let mut v = Vec::new();
    for chart in [Chart::Cayley, Chart::Exp] {
        for simplified in [true, false] {
            let mut st = stepper(
                GeneratingFunction::new(
                    Polynomial::new(taylor3()).unwrap(),
                    None,
                    0,
                    MlpInputs::Plain,
                )
                .unwrap(),
                chart,
            );
            st.newton.simplified = simplified;
            v.push(st);
        }
    }
    v
}

/// Every trajectory of a lockstep block ends where the scalar step takes it, bit for bit, in
/// rollouts of 37 states (chunks of 32: blocks of 8 lanes and a ragged tail).
#[test]
fn lockstep_block_equals_the_scalar_step() {
    let mut rng = Rng::new(0x1A2E_5002);
    for st in taylor_steppers() {
        assert!(st.batch() > 1 && st.batch() % LANES == 0);
        let mu0: Vec<[f64; 3]> = (0..37)
            .map(|_| {
                let r = rng.range(0.5, 4.0);
                rng.sphere(r)
            })
            .collect();
        let (h, n_steps) = (0.1, 25);
        let mut out = vec![0.0; mu0.len() * n_records(n_steps, 1) * 3];
        let info = rollout(&st, &mu0, h, n_steps, 1, &mut out).unwrap();
        let mut ws = st.workspace();
        for (j, m0) in mu0.iter().enumerate() {
            let mut mu = *m0;
            let (mut iterations, mut residual) = (0u64, 0.0f64);
            for k in 0..n_steps {
                let stats = st.step(h, &mut mu, &mut ws).unwrap();
                iterations += u64::from(stats.iterations);
                residual = residual.max(stats.residual);
                let r = (j * n_records(n_steps, 1) + k + 1) * 3;
                assert!(same_bits(&mu, &out[r..r + 3]), "trajectory {j} step {k}");
            }
            assert!(info[j].converged);
            assert_eq!(info[j].newton_iterations, iterations);
            assert_eq!(info[j].max_residual.to_bits(), residual.to_bits());
        }
    }
}

/// One lane whose Newton solve fails (the exp chart's singular angle) stops with the scalar
/// path's failure; the other lanes of its block keep the bits they have without it.
#[test]
fn a_failing_lane_leaves_the_others_unchanged() {
    let mut rng = Rng::new(0x1A2E_5003);
    let st = taylor_steppers().swap_remove(2); // exp chart, simplified Newton
    let mut mu: Vec<[f64; 3]> = (0..11).map(|_| rng.sphere(2.0)).collect();
    let mut ws = st.workspace();
    let bad = [400.0, -300.0, 250.0];
    assert!(st.step(0.1, &mut bad.clone(), &mut ws).is_err());
    let live = vec![true; mu.len()];
    let mut clean = mu.clone();
    let mut clean_results = vec![Ok(StepStats::default()); mu.len()];
    st.step_batch(0.1, &mut clean, &live, &mut clean_results, &mut ws);
    mu[3] = bad;
    let before = mu.clone();
    let mut results = vec![Ok(StepStats::default()); mu.len()];
    st.step_batch(0.1, &mut mu, &live, &mut results, &mut ws);
    let mut scalar = bad;
    let failure = st.step(0.1, &mut scalar, &mut ws);
    assert_eq!(results[3], failure);
    assert!(
        same_bits(&mu[3], &before[3]),
        "a failed lane keeps its state"
    );
    for j in (0..mu.len()).filter(|&j| j != 3) {
        assert_eq!(results[j], clean_results[j], "lane {j}");
        assert!(same_bits(&mu[j], &clean[j]), "lane {j}");
    }
}

/// The branch-free tanh of the batched MLP passes against libm's, in units of the last place
/// of the result, in both forms (plain multiply-adds, and fused as the AVX2 passes run it): at
/// most 4 over a dense grid, at tiny and huge arguments; NaN stays NaN.
#[test]
fn fast_tanh_is_within_four_ulp_of_libm() {
    use crate::generating::{tanh_fast, tanh_fast_fma};
    for (name, tanh) in [
        ("plain", tanh_fast as fn(f64) -> f64),
        ("fused", tanh_fast_fma as fn(f64) -> f64),
    ] {
        let ulp = |x: f64| {
            let (a, b) = (tanh(x), x.tanh());
            ((a - b) / (b.abs().max(f64::MIN_POSITIVE) * f64::EPSILON)).abs()
        };
        let mut worst = (0.0f64, 0.0f64);
        let mut rng = Rng::new(0x1A2E_5004);
        let grid = (-400_000..=400_000).map(|i| f64::from(i) * 6.25e-5);
        let random =
            (0..200_000).map(|_| rng.range(-1.0, 1.0) * 10f64.powf(rng.range(-300.0, 3.0)));
        for x in grid.chain(random) {
            let u = ulp(x);
            if u > worst.0 {
                worst = (u, x);
            }
        }
        assert!(
            worst.0 <= 4.0,
            "{name}: {} ulp at x = {:e}",
            worst.0,
            worst.1
        );
        for x in [f64::INFINITY, 1e300, 40.0, 19.5] {
            assert_eq!(tanh(x), 1.0, "{name}");
            assert_eq!(tanh(-x), -1.0, "{name}");
        }
        assert!(tanh(f64::NAN).is_nan(), "{name}");
        eprintln!("fast tanh ({name}): worst {} ulp at {:e}", worst.0, worst.1);
    }
}

/// The lockstep tanh of the lane networks (4 rows of 8 lanes, each stage over every element)
/// against the one-at-a-time [`tanh_fast`] and [`tanh_fast_fma`], bit for bit in both forms: the
/// same operations per element, in every slot of the block, over a dense grid, random
/// magnitudes and the edge values (±0, clamped arguments, infinities, NaN).
#[test]
fn lockstep_tanh_has_the_bits_of_tanh_fast() {
    use crate::generating::{tanh_fast, tanh_fast_fma, tanh_fast_rows};
    let mut rng = Rng::new(0x1A2E_5006);
    let mut xs: Vec<f64> = (-20_000..=20_000).map(|i| f64::from(i) * 1.3e-3).collect();
    xs.extend((0..20_000).map(|_| rng.range(-1.0, 1.0) * 10f64.powf(rng.range(-300.0, 3.0))));
    xs.extend([
        0.0,
        -0.0,
        19.5,
        -19.5,
        40.0,
        1e300,
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::NAN,
    ]);
    for chunk in xs.chunks(32) {
        let mut block = [[0.0f64; 8]; 4];
        for (i, &x) in chunk.iter().enumerate() {
            block[i / 8][i % 8] = x;
        }
        let (mut plain, mut fused) = (block, block);
        tanh_fast_rows::<false, 4, 8>(&mut plain);
        tanh_fast_rows::<true, 4, 8>(&mut fused);
        let pairs = [(plain, tanh_fast as fn(f64) -> f64), (fused, tanh_fast_fma)];
        for (got, tanh) in pairs {
            let want = block.map(|row| row.map(tanh));
            for (got, want) in got.iter().flatten().zip(want.iter().flatten()) {
                assert_eq!(got.to_bits(), want.to_bits(), "tanh of a block slot");
            }
        }
    }
}

/// The narrow-layer kernel of the MLP passes against the panel kernel: the same chain of
/// multiply-adds per element, so the same bits, for every shape up to its limits and column
/// counts that are not multiples of its 8-column blocks (which kernel a layer takes never
/// changes a trajectory).
#[test]
fn narrow_layer_kernel_equals_the_panel_kernel() {
    use crate::generating::narrow_gemm;
    use crate::kernel;
    let mut rng = Rng::new(0x1A2E_5005);
    for n_out in 1..=10 {
        for n_in in [1, 2, 3, 4, 7, 8, 9, 16] {
            for cols in [1, 3, 8, 10, 13, 40, 97] {
                let w: Vec<f64> = (0..n_out * n_in).map(|_| rng.range(-2.0, 2.0)).collect();
                // Some exact zeros and negative products: the sums start from +0 in both.
                let x: Vec<f64> = (0..n_in * cols)
                    .map(|i| {
                        if i % 11 == 0 {
                            0.0
                        } else {
                            rng.range(-3.0, 3.0)
                        }
                    })
                    .collect();
                let mut a = vec![f64::NAN; n_out * cols];
                let mut b = vec![f64::NAN; n_out * cols];
                kernel::gemm(
                    &kernel::pack(&w, n_in, n_out),
                    n_in,
                    n_out,
                    &x,
                    cols,
                    &mut a,
                );
                narrow_gemm(&w, n_in, n_out, &x, cols, &mut b);
                assert!(same_bits(&a, &b), "{n_out}x{n_in}, {cols} columns");
            }
        }
    }
}

/// The so(3) chart in lanes: its values are the chart's own (`Chart::tar` / `Chart::sou` /
/// `Chart::rotate` in f64) bit for bit, and its hand-written Newton Jacobian J = ∂T/∂p + ∂T/∂x · Hess S equals the
/// dual-number one (x seeded with the Hessian as its derivative, p with the identity) to
/// 1e-13 relative. Angles |x| up to 5 run both the series (|x|² < 1) and the closed form of
/// the exponential chart's coefficient.
#[test]
fn lane_chart_jacobian_matches_dual_numbers() {
    use crate::lanes_bisection::{so3_chart_lanes, so3_rotate_lanes, V};
    let mut rng = Rng::new(0x1A2E_5017);
    for k in 0..2000 {
        let chart = [Chart::Cayley, Chart::Exp][k % 2];
        let (rx, rp) = (rng.range(1e-3, 5.0), rng.range(0.1, 4.0));
        let (x, p) = (rng.sphere(rx), rng.sphere(rp));
        let mut hs = [[0.0; 3]; 3];
        for a in 0..3 {
            for b in a..3 {
                hs[a][b] = rng.range(-1.0, 1.0);
                hs[b][a] = hs[a][b];
            }
        }
        let xl = x.map(|v| V([v]));
        let pl = p.map(|v| V([v]));
        let hl = hs.map(|r| r.map(|v| V([v])));
        let (t, s, jac) = so3_chart_lanes::<1>(chart, -1.0, &xl, &pl, Some(&hl));
        let (sou, _, _) = so3_chart_lanes::<1>(chart, 1.0, &xl, &pl, None);
        assert_eq!(s.0[0].to_bits(), dot(&x, &x).to_bits());
        let (t_ref, s_ref) = (chart.tar(&x, &p).unwrap(), chart.sou(&x, &p).unwrap());
        let turned = so3_rotate_lanes::<1>(chart, &xl, &pl, s);
        let turned_ref = chart.rotate(&x, &p).unwrap();
        for i in 0..3 {
            assert_eq!(t[i].0[0].to_bits(), t_ref[i].to_bits(), "{chart:?} tar");
            assert_eq!(sou[i].0[0].to_bits(), s_ref[i].to_bits(), "{chart:?} sou");
            assert_eq!(
                turned[i].0[0].to_bits(),
                turned_ref[i].to_bits(),
                "{chart:?} rotation"
            );
        }
        let xd: [Dual1<3>; 3] = std::array::from_fn(|i| Dual1 { v: x[i], g: hs[i] });
        let pd: [Dual1<3>; 3] = std::array::from_fn(|i| Dual1::var(p[i], i));
        let td = chart.tar(&xd, &pd).unwrap();
        let jac = jac.unwrap();
        let scale = td
            .iter()
            .flat_map(|d| d.g)
            .fold(1.0f64, |m, v| m.max(v.abs()));
        for r in 0..3 {
            for c in 0..3 {
                let (a, b) = (jac[r][c].0[0], td[r].g[c]);
                assert!(
                    (a - b).abs() <= 1e-13 * scale,
                    "{chart:?} J[{r}][{c}] = {a} against {b} at |x|² = {}",
                    dot(&x, &x)
                );
            }
        }
    }
}

/// A polynomial S with simplified Newton on so(3) (the lane solver) against the generic
/// dual-number step of the same stepper (`step_generic`), over 20 steps of 37 states, in both
/// charts, for Taylor K = 3 and for Taylor K = 3 plus random terms (exponents up to 3):
/// - started from μ as the generic step is, the same Newton counts and states within 1e-13
///   relative;
/// - with the predictor (what `step` runs), states within 1e-13 relative and fewer updates in
///   all.
#[test]
fn lane_newton_equals_the_generic_step() {
    use crate::lanes_bisection::{so3_newton_steps, So3Newton};
    let mut rng = Rng::new(0x1A2E_5018);
    for chart in [Chart::Cayley, Chart::Exp] {
        for extra in [0, 6] {
            let mut terms = taylor3();
            terms.extend(random_terms(&mut rng, extra, (2, 5), 3, 0.01));
            let gf =
                GeneratingFunction::new(Polynomial::new(terms).unwrap(), None, 0, MlpInputs::Plain)
                    .unwrap();
            let st = stepper(gf, chart);
            assert!(st.newton.simplified);
            let plain = So3Newton {
                poly: &st.generating.polynomial,
                network: None,
                chart,
                tol: st.newton.tol,
                max_iter: st.newton.max_iter,
                predict: false,
            };
            let mut ws = st.workspace();
            let mut worst = 0.0f64;
            let (mut n_lane, mut n_predicted, mut n_generic) = (0, 0, 0);
            for _ in 0..37 {
                let r = rng.range(0.5, 4.0);
                let mu = rng.sphere(r);
                let (mut a, mut b, mut c) = (mu, mu, mu);
                for _ in 0..20 {
                    let mut sa = [Err(StepFailure::OutOfDomain)];
                    let mut one = [a];
                    so3_newton_steps(
                        &plain,
                        Isa::detect(),
                        &mut [],
                        0.1,
                        &mut one,
                        &[true],
                        &mut sa,
                    );
                    a = one[0];
                    let sa = sa[0].unwrap();
                    let sb = st.step_generic(0.1, &mut b, &mut ws).unwrap();
                    let sc = st.step(0.1, &mut c, &mut ws).unwrap();
                    assert_eq!(
                        sa.iterations, sb.iterations,
                        "{chart:?}: Newton counts differ"
                    );
                    (n_lane, n_predicted, n_generic) = (
                        n_lane + sa.iterations,
                        n_predicted + sc.iterations,
                        n_generic + sb.iterations,
                    );
                    for s in [sa, sb, sc] {
                        assert!(s.residual <= 1e-13 * r);
                    }
                    worst = worst
                        .max(norm(&sub(&a, &b)) / r)
                        .max(norm(&sub(&c, &b)) / r);
                }
            }
            assert!(worst <= 1e-13, "{chart:?}: relative distance {worst:e}");
            assert_eq!(n_lane, n_generic);
            assert!(
                n_predicted < n_generic,
                "{chart:?}: {n_predicted} updates with the predictor, {n_generic} without"
            );
            eprintln!("{chart:?}, {extra} extra terms: {n_predicted} / {n_generic} updates");
        }
    }
}

/// so(3)'s Newton start is second order in both charts: its distance to the solved bisection
/// momentum p* falls at least as h³ (the slope fitted from h = 0.2 to 0.025: 3.0 in the
/// exponential chart, 3.0–4.0 in the Cayley one), where the first-order start
/// p₁ = μ + ½ x₀ × μ falls as h². The oracle p* is the fixed-point iteration
/// p ← p + μ − tar(∇S(p), p) of the scalar chart (a contraction by O(h)), run 200 times. From
/// that start the lane solve of the rigid body's Taylor K = 3 at h = 0.1 takes 2 updates a step
/// (3 from the first-order one, `benches/newton_predictors.py`).
#[test]
fn so3_start_is_second_order() {
    use crate::generating::polynomial_lanes::{JetLanes, Scratch};
    use crate::lanes_bisection::{so3_newton_steps, so3_start, V};
    let mut rng = Rng::new(0x1A2E_5020);
    for (chart, terms) in [(Chart::Exp, taylor3_exp()), (Chart::Cayley, taylor3())] {
        let poly = Polynomial::new(terms).unwrap();
        let groupoid = Groupoid::so3(chart).unwrap();
        let start = |h: f64, mu: &[f64; 3]| {
            let mut scratch = Scratch::<3, 1>::new();
            let mut jet = JetLanes {
                v: [0.0],
                g: [[0.0]; 3],
                h: [[[0.0]; 3]; 3],
            };
            let (pl, target) = (mu.map(|m| [m]), mu.map(|m| V([m])));
            let (p0, _) = match chart {
                Chart::Exp => {
                    so3_start::<3, 1, true>(&poly, h, &pl, &target, &mut scratch, &mut jet)
                }
                Chart::Cayley => {
                    so3_start::<3, 1, false>(&poly, h, &pl, &target, &mut scratch, &mut jet)
                }
            };
            p0.map(|v| v.0[0])
        };
        let hs = [0.2, 0.025];
        for _ in 0..8 {
            let r = rng.range(1.0, 3.0);
            let mu = rng.sphere(r);
            let (mut second, mut first) = ([0.0; 2], [0.0; 2]);
            for (k, &h) in hs.iter().enumerate() {
                let mut solved = mu;
                for _ in 0..200 {
                    let x = poly.gradient(h, &solved).g;
                    let t = groupoid.tar(&x, &solved).unwrap();
                    solved = std::array::from_fn(|i| solved[i] + (mu[i] - t[i]));
                }
                second[k] = norm(&sub(&start(h, &mu), &solved));
                // x₀ = ∇ of S's t-linear terms, −t H: −h μᵢ / Iᵢ.
                let x0: [f64; 3] = std::array::from_fn(|i| -h * mu[i] / INERTIA[i]);
                let turn = cross(&x0, &mu);
                let p1: [f64; 3] = std::array::from_fn(|i| mu[i] + 0.5 * turn[i]);
                first[k] = norm(&sub(&p1, &solved));
            }
            assert_start_orders(hs, second, first, &format!("{chart:?}"));
        }
        let sys = predicted(&poly, chart);
        let mut mu: Vec<[f64; 3]> = (0..64)
            .map(|_| {
                let r = rng.range(1.0, 3.0);
                rng.sphere(r)
            })
            .collect();
        let mut results = vec![Err(StepFailure::OutOfDomain); mu.len()];
        let live = vec![true; mu.len()];
        so3_newton_steps(
            &sys,
            Isa::detect(),
            &mut [],
            0.1,
            &mut mu,
            &live,
            &mut results,
        );
        let updates: u32 = results.iter().map(|r| r.unwrap().iterations).sum();
        eprintln!("{chart:?}: {updates} updates over {} steps", mu.len());
        assert!(
            updates as f64 <= 2.1 * mu.len() as f64,
            "{chart:?}: {updates} updates over {} steps",
            mu.len()
        );
    }
}

/// Lane bits depend on neither the dispatch path nor the block: the portable and the widest
/// dispatch, whole chunks, and one state at a time agree bit for bit, failures included (a NaN
/// state fails with NonFinite, a state beyond the exp chart with ChartSingular, and the other
/// lanes of their blocks keep their bits).
#[test]
fn lane_newton_is_the_same_for_every_dispatch_and_block() {
    use crate::lanes_bisection::so3_newton_steps;
    let mut rng = Rng::new(0x1A2E_5019);
    for chart in [Chart::Cayley, Chart::Exp] {
        let poly = Polynomial::new(taylor3()).unwrap();
        let sys = predicted(&poly, chart);
        let mut mu0: Vec<[f64; 3]> = (0..29)
            .map(|_| {
                let r = rng.range(0.5, 4.0);
                rng.sphere(r)
            })
            .collect();
        mu0[5] = [f64::NAN, 1.0, 0.0];
        mu0[17] = [400.0, -300.0, 250.0];
        let mut live = vec![true; mu0.len()];
        live[9] = false;
        let run = |isa: Isa, block: usize| {
            let mut mu = mu0.clone();
            let mut res = vec![Err(StepFailure::OutOfDomain); mu.len()];
            for ((m, l), r) in mu
                .chunks_mut(block)
                .zip(live.chunks(block))
                .zip(res.chunks_mut(block))
            {
                so3_newton_steps(&sys, isa, &mut [], 0.1, m, l, r);
            }
            (mu, res)
        };
        let (reference, ref_results) = run(Isa::PORTABLE, 29);
        assert_eq!(ref_results[5], Err(StepFailure::NonFinite));
        if chart == Chart::Exp {
            assert_eq!(ref_results[17], Err(StepFailure::ChartSingular));
        }
        assert_eq!(
            ref_results[9],
            Err(StepFailure::OutOfDomain),
            "not live: untouched"
        );
        assert!(same_bits(&reference[9], &mu0[9]) && same_bits(&reference[5][1..], &mu0[5][1..]));
        for isa in isas() {
            for block in [1, 3, 8, 13, 29] {
                let (mu, res) = run(isa, block);
                assert_eq!(res, ref_results, "{chart:?} {isa:?} block {block}");
                for j in 0..mu.len() {
                    assert!(
                        same_bits(&mu[j], &reference[j]),
                        "{chart:?} {isa:?} {block} {j}"
                    );
                }
            }
        }
    }
}

/// The vector finiteness check the lane rounds use: a lane's sum of a − a probes is 0 exactly
/// where every number summed is finite (±∞ and NaN anywhere make it non-zero, the largest and
/// the subnormal finite numbers do not), whatever else the other lanes hold.
#[test]
fn finite_probes_agree_with_is_finite_lane_by_lane() {
    use crate::lanes_bisection::{finite_probe, round_probes, V};
    let specials = [
        0.0,
        -0.0,
        f64::MAX,
        -f64::MAX,
        f64::MIN_POSITIVE / 4.0,
        1.5,
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::NAN,
    ];
    let mut rng = Rng::new(0x1A2E_5020);
    for _ in 0..500 {
        // Three vectors of 8 lanes, each number a special value or a random one.
        let pick = |rng: &mut Rng| -> f64 {
            if rng.below(3) == 0 {
                specials[rng.below(specials.len())]
            } else {
                rng.range(-1e300, 1e300)
            }
        };
        let vs: [V<8>; 3] = [0; 3].map(|_| V([0; 8].map(|_| pick(&mut rng))));
        let probe = finite_probe(vs);
        for l in 0..8 {
            let finite = vs.iter().all(|v| v.0[l].is_finite());
            assert_eq!(
                probe.0[l] == 0.0,
                finite,
                "lane {l}: {:?}",
                vs.map(|v| v.0[l])
            );
        }
        let value = [0; 8].map(|_| pick(&mut rng));
        let h = [
            [vs[0], vs[1], vs[2]],
            [vs[2], vs[0], vs[1]],
            [vs[1], vs[2], vs[0]],
        ];
        let x = [V(value), vs[1], vs[0]];
        for hess in [false, true] {
            let (p, hp) = round_probes(&value, &x, &h, hess);
            for l in 0..8 {
                let finite = value[l].is_finite() && x.iter().all(|v| v.0[l].is_finite());
                assert_eq!(p.0[l] == 0.0, finite);
                let h_finite = !hess || h.iter().flatten().all(|v| v.0[l].is_finite());
                assert_eq!(hp.0[l] == 0.0, h_finite);
            }
        }
    }
}

/// The lane solver a stepper takes is the realization's own answer: so(3) in either chart,
/// se(3) in its exponential chart, the series chart for another algebra of the same dimension
/// (sl(2)), nothing for another realization (log-canonical).
#[test]
fn the_lane_chart_is_the_realizations_answer() {
    use crate::realization::{LaneChart, Realization};
    use crate::structures::lie_groupoid::LieAlgebra;
    use crate::structures::LogCanonical;

    for chart in [Chart::Exp, Chart::Cayley] {
        let so3 = Groupoid::<3>::so3(chart).unwrap();
        assert_eq!(so3.lane_chart(), Some(LaneChart::So3(chart)));
    }
    let se3 = Groupoid::new(LieAlgebra::<6>::se3(), Chart::Exp).unwrap();
    assert_eq!(se3.lane_chart(), Some(LaneChart::Se3Exp));
    // sl(2) in the basis (h, e, f): [h, e] = 2e, [h, f] = −2f, [e, f] = h.
    let mut c = [[[0.0; 3]; 3]; 3];
    for (i, j, k, v) in [(0, 1, 1, 2.0), (0, 2, 2, -2.0), (1, 2, 0, 1.0)] {
        c[i][j][k] = v;
        c[j][i][k] = -v;
    }
    let sl2 = Groupoid::new(LieAlgebra::<3>::new(c).unwrap(), Chart::Exp).unwrap();
    assert_eq!(sl2.lane_chart(), Some(LaneChart::ExpSeries));
    let log = LogCanonical::<2>::new([[0.0, 1.0], [-1.0, 0.0]]).unwrap();
    assert_eq!(log.lane_chart(), None);
    assert!(sl2.lie_algebra().is_some() && log.lie_algebra().is_none());
}

/// The lane solve of `poly` in `chart` from the predicted start, at tol 1e-12 and at most 50
/// updates (the steppers' settings).
fn predicted(poly: &Polynomial<3>, chart: Chart) -> crate::lanes_bisection::So3Newton<'_, 3> {
    crate::lanes_bisection::So3Newton {
        poly,
        network: None,
        chart,
        tol: 1e-12,
        max_iter: 50,
        predict: true,
    }
}

/// so(3)'s first two rounds taken straight through (`so3_two_rounds`) end every kind of block
/// as the round-by-round loop does: each lane of a block of 8 has the bits, update count and
/// residual of its one-trajectory step (which never takes them), whether the block finishes
/// there (every lane 2 updates), hands lanes on to the loop (one lane needing more), or is
/// declined (one lane converged after one update: μ = 0), and where the loop runs alone (one
/// lane too far out for the prediction, beyond the exponential chart). The tally of how blocks
/// ran shows that each of the four did.
#[test]
fn two_rounds_straight_through_end_as_the_loop_does() {
    use crate::lanes_bisection::two_rounds_tally;
    let mut rng = Rng::new(0x1A2E_5010);
    let h = 0.1;
    let steppers = taylor_steppers()
        .into_iter()
        .filter(|s| s.newton.simplified);
    for (st, chart) in steppers.zip(["Cayley", "exp"]) {
        let mut ws = st.workspace();
        let scalar = |mu: [f64; 3], ws: &mut _| {
            let mut m = mu;
            let r = st.step(h, &mut m, ws);
            (m, r)
        };
        // Eight states the scalar step takes two updates for.
        let base: Vec<[f64; 3]> = (0..400)
            .map(|_| {
                let r = rng.range(0.5, 2.0);
                rng.sphere(r)
            })
            .filter(|&m| matches!(scalar(m, &mut ws).1, Ok(s) if s.iterations == 2))
            .take(LANES)
            .collect();
        assert_eq!(base.len(), LANES);
        // A state the scalar step takes more than two updates for, from larger momenta.
        let slow = (0..400)
            .map(|_| {
                let r = rng.range(4.0, 9.0);
                rng.sphere(r)
            })
            .find(|&m| matches!(scalar(m, &mut ws).1, Ok(s) if s.iterations > 2))
            .expect("a state with more than two updates");
        let mut cases = vec![(base.clone(), 3usize)];
        for (lane, state, outcome) in [
            (5, slow, 2),
            (2, [0.0; 3], 1),
            (6, [400.0, -300.0, 250.0], 0),
        ] {
            let mut mu = base.clone();
            mu[lane] = state;
            cases.push((mu, outcome));
        }
        for (mu0, outcome) in cases {
            let mut mu = mu0.clone();
            let mut results = vec![Ok(StepStats::default()); LANES];
            two_rounds_tally::take();
            st.step_batch(h, &mut mu, &[true; LANES], &mut results, &mut ws);
            let mut expected = [0; 4];
            expected[outcome] = 1;
            assert_eq!(two_rounds_tally::take(), expected, "{chart}, {:?}", mu0);
            for l in 0..LANES {
                let (m, r) = scalar(mu0[l], &mut ws);
                assert_eq!(results[l], r, "lane {l}, {chart}");
                let want = if r.is_ok() { m } else { mu0[l] };
                assert!(same_bits(&mu[l], &want), "lane {l}");
                if outcome == 3 {
                    assert_eq!(r.unwrap().iterations, 2);
                }
            }
        }
    }
}

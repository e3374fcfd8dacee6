//! The batched kernel and batched steps against the one-trajectory path.

// Index loops over 3-vectors and 3×3 matrices read more clearly as the formulas they test.
#![allow(clippy::needless_range_loop)]

use super::*;

// The batched kernel
// ---------------------------------------------------------------------------------------------

/// The packed register-blocked product equals the textbook one exactly: every element is the
/// same chain of multiply-adds over k, whatever its block, column position or k-block.
#[test]
fn kernel_gemm_is_the_sequential_product_exactly() {
    use crate::kernel::{gemm, pack, uses_fma};
    let mut rng = Rng::new(71);
    // Shapes around the block sizes: MR = 6 rows, NR = 8 columns, KC = 128 k-block.
    for &(n_in, n_out, cols) in &[
        (1, 1, 1),
        (4, 5, 7),
        (4, 6, 8),
        (7, 13, 17),
        (130, 11, 40),
        (300, 250, 10),
        (257, 7, 9),
    ] {
        let w: Vec<f64> = (0..n_in * n_out).map(|_| rng.range(-1.0, 1.0)).collect();
        let x: Vec<f64> = (0..n_in * cols).map(|_| rng.range(-2.0, 2.0)).collect();
        let mut z = vec![f64::NAN; n_out * cols];
        gemm(&pack(&w, n_in, n_out), n_in, n_out, &x, cols, &mut z);
        for o in 0..n_out {
            for c in 0..cols {
                let mut acc = 0.0;
                for k in 0..n_in {
                    let (a, b) = (w[o * n_in + k], x[k * cols + c]);
                    acc = if uses_fma() {
                        a.mul_add(b, acc)
                    } else {
                        a * b + acc
                    };
                }
                assert_eq!(
                    z[o * cols + c].to_bits(),
                    acc.to_bits(),
                    "({n_in}, {n_out}, {cols}) at ({o}, {c})"
                );
            }
        }
    }
}

/// Batched jets and gradients (forward and reverse mode) agree with the one-at-a-time path (a different summation
/// order, so to round-off) for every input kind, batch size and p = 0.
#[test]
fn batched_derivatives_match_single_ones() {
    use crate::dual::Dual1;
    use crate::generating::MAX_BATCH;
    let mut rng = Rng::new(72);
    for inputs in ALL_INPUTS {
        for _ in 0..6 {
            let gf = random_generating(&mut rng, inputs);
            let mut ws = gf.workspace();
            for n in [1, 3, 8, 13, MAX_BATCH] {
                let mut p: Vec<[f64; 3]> = (0..n).map(|_| rng.vec3(-3.0, 3.0)).collect();
                p[n / 2] = [0.0; 3];
                let mut jets = vec![Jet2::default(); n];
                let mut grads = vec![Dual1::default(); n];
                gf.jets(0.1, &p, &mut jets, &mut ws);
                gf.gradients(0.1, &p, &mut grads, &mut ws);
                let mut reverse = vec![Dual1::default(); n];
                gf.gradients_reverse(0.1, &p, &mut reverse, &mut ws);
                for j in 0..n {
                    let single = gf.jet(0.1, &p[j], &mut ws);
                    let g = gf.gradient(0.1, &p[j], &mut ws);
                    let scale = single.flat().iter().fold(1.0_f64, |m, v| m.max(v.abs()));
                    for c in 0..10 {
                        assert!(
                            (jets[j].flat()[c] - single.flat()[c]).abs() <= 1e-13 * scale,
                            "{inputs:?} n={n} j={j} c={c}: {} vs {}",
                            jets[j].flat()[c],
                            single.flat()[c]
                        );
                    }
                    assert!((reverse[j].v - single.flat()[0]).abs() <= 1e-13 * scale);
                    for c in 0..3 {
                        assert!(
                            (reverse[j].g[c] - g.g[c]).abs() <= 1e-13 * scale,
                            "{inputs:?} n={n} j={j}: reverse {:?} vs {:?}",
                            reverse[j],
                            g
                        );
                        assert!((grads[j].g[c] - g.g[c]).abs() <= 1e-13 * scale);
                        assert!((grads[j].g[c] - jets[j].g[c]).abs() <= 1e-13 * scale);
                    }
                }
            }
        }
    }
}

/// A batched Newton step gives each trajectory what its own step gives, to round-off, with the
/// dead ones left untouched.
#[test]
fn batched_step_matches_single_steps() {
    use crate::stepper::StepResult;
    let mut rng = Rng::new(73);
    for chart in [Chart::Cayley, Chart::Exp] {
        for inputs in ALL_INPUTS {
            for simplified in [false, true] {
                let mut st = stepper(wide_generating(&mut rng, inputs), chart);
                st.newton.simplified = simplified;
                let mut ws = st.workspace();
                let n = st.batch();
                assert!(n > 1);
                let mu0: Vec<[f64; 3]> = (0..n)
                    .map(|_| {
                        let r = rng.range(0.5, 4.0);
                        rng.sphere(r)
                    })
                    .collect();
                let live: Vec<bool> = (0..n).map(|i| i % 5 != 2).collect();
                let mut mu = mu0.clone();
                let mut results: Vec<StepResult> = vec![Err(StepFailure::NonFinite); n];
                st.step_batch(0.1, &mut mu, &live, &mut results, &mut ws);
                for i in 0..n {
                    if !live[i] {
                        assert_eq!(mu[i], mu0[i]);
                        assert_eq!(results[i], Err(StepFailure::NonFinite));
                        continue;
                    }
                    let mut single = mu0[i];
                    let stats = st.step(0.1, &mut single, &mut ws).unwrap();
                    let batched = results[i].unwrap();
                    // Simplified Newton converges linearly: more, cheaper updates.
                    if simplified {
                        assert!(batched.iterations >= stats.iterations);
                    } else {
                        assert!(
                            batched.iterations.abs_diff(stats.iterations) <= 1,
                            "{chart:?} {inputs:?} {i}: {batched:?} vs {stats:?}"
                        );
                    }
                    assert!(batched.residual <= 1e-11 * norm(&single));
                    for c in 0..3 {
                        assert!(
                            (mu[i][c] - single[c]).abs() <= 1e-12 * norm(&single),
                            "{chart:?} {inputs:?} {simplified} {i}: {:?} vs {single:?}",
                            mu[i]
                        );
                    }
                }
            }
        }
    }
}

/// A batch in which every trajectory fails: no panic, each failure reported, NaN after it.
#[test]
fn batched_rollout_where_every_trajectory_fails() {
    let mut rng = Rng::new(74);
    let widths = [4, 40, 40, 1];
    let layers = widths
        .windows(2)
        .map(|w| {
            let (n_in, n_out) = (w[0], w[1]);
            // A last layer of 1e12 makes ∂S/∂p astronomically large: Newton cannot converge.
            let a = if n_out == 1 { 1e12 } else { 1.0 };
            let weight = (0..n_in * n_out).map(|_| rng.range(-a, a)).collect();
            Layer::new(n_in, n_out, weight, vec![0.0; n_out]).unwrap()
        })
        .collect();
    let gf = GeneratingFunction::new(
        Polynomial::new(minus_t_h()).unwrap(),
        Some(Mlp::new(layers).unwrap()),
        1,
        MlpInputs::Plain,
    )
    .unwrap();
    let st = stepper(gf, Chart::Cayley);
    assert!(st.batch() > 1);
    let mu0: Vec<[f64; 3]> = (0..20).map(|_| rng.sphere(2.0)).collect();
    let (n_steps, every) = (5, 1);
    let nr = n_records(n_steps, every);
    let mut out = vec![0.0; mu0.len() * nr * 3];
    let infos = rollout(&st, &mu0, 0.1, n_steps, every, &mut out).unwrap();
    for (i, info) in infos.iter().enumerate() {
        assert!(!info.converged && info.failure.is_some(), "{i}: {info:?}");
        let k = info.failed_step as usize;
        assert!(k < n_steps);
        let rec = &out[i * nr * 3..(i + 1) * nr * 3];
        assert_eq!(rec[..3], mu0[i]);
        assert!(rec[3..3 * (k + 1)].iter().all(|v| v.is_finite()));
        assert!(rec[3 * (k + 1)..].iter().all(|v| v.is_nan()));
    }
}

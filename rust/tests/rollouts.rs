//! Rollouts: failure bookkeeping, thread-count and segmentation independence, argument checks.

// Index loops over 3-vectors and 3×3 matrices read more clearly as the formulas they test.
#![allow(clippy::needless_range_loop)]

use super::*;

/// A generating function that fails only in a region of phase space: with a sharp tanh bump of
/// huge amplitude around p₁ = 5, trajectories starting there fail, the others are unaffected.
#[test]
fn rollout_reports_newton_failure_per_trajectory() {
    // N(p) = 1e8 · tanh(10 (p₁ − 5)): its gradient is ~1e9 near p₁ = 5, ~1e-25 near |p| ≤ 2.
    let mlp = Mlp::new(vec![
        Layer::new(4, 1, vec![0.0, 10.0, 0.0, 0.0], vec![-50.0]).unwrap(),
        Layer::new(1, 1, vec![1e8], vec![0.0]).unwrap(),
    ])
    .unwrap();
    let gf = GeneratingFunction::new(
        Polynomial::new(minus_t_h()).unwrap(),
        Some(mlp),
        1,
        MlpInputs::Plain,
    )
    .unwrap();
    let st = stepper(gf, Chart::Cayley);
    let mu0 = vec![
        [1.0, 1.0, 2.0],
        [5.0, 0.1, 0.1],
        [-0.5, 1.0, 0.3],
        [5.0, -0.2, 0.05],
        [0.2, -1.5, 1.0],
    ];
    let failing = [false, true, false, true, false];
    let (h, n_steps, every) = (0.1, 20, 3);
    let nr = n_records(n_steps, every);
    let mut out = vec![0.0; mu0.len() * nr * 3];
    let infos = rollout(&st, &mu0, h, n_steps, every, &mut out).unwrap();
    for (i, info) in infos.iter().enumerate() {
        let rec = &out[i * nr * 3..(i + 1) * nr * 3];
        if failing[i] {
            assert!(
                !info.converged,
                "trajectory {i} should have failed: {info:?}"
            );
            assert!(info.failure.is_some());
            let k = info.failed_step;
            assert!((0..n_steps as i64).contains(&k), "failed_step {k}");
            // Records of states ≤ k are finite, later ones NaN.
            for r in 0..nr {
                let state = r * every;
                let finite = rec[3 * r..3 * r + 3].iter().all(|v| v.is_finite());
                let nan = rec[3 * r..3 * r + 3].iter().all(|v| v.is_nan());
                if state as i64 <= k {
                    assert!(
                        finite,
                        "trajectory {i}: record {r} (state {state}) should be kept"
                    );
                } else {
                    assert!(
                        nan,
                        "trajectory {i}: record {r} (state {state}) should be NaN"
                    );
                }
            }
        } else {
            assert!(info.converged, "trajectory {i} should not fail: {info:?}");
            assert_eq!(info.failed_step, -1);
            assert_eq!(info.failure, None);
            assert!(rec.iter().all(|v| v.is_finite()));
            // Bit-identical to the same trajectory run alone.
            let mut alone = vec![0.0; nr * 3];
            let info_alone = rollout(&st, &mu0[i..i + 1], h, n_steps, every, &mut alone).unwrap();
            assert_eq!(info_alone[0], *info);
            assert!(alone
                .iter()
                .zip(rec)
                .all(|(a, b)| a.to_bits() == b.to_bits()));
        }
    }
}

/// A scripted stepper: adds 1 to μ₁ each step and fails once μ₁ ≥ 5. Checks the bookkeeping of
/// `failed_step`, the NaN fill and the statistics exactly.
struct FailAtFive;

impl StepMap<3> for FailAtFive {
    type Workspace = ();
    fn workspace(&self) {}
    fn step(&self, _h: f64, mu: &mut [f64; 3], _ws: &mut ()) -> Result<StepStats, StepFailure> {
        if mu[0] >= 5.0 {
            return Err(StepFailure::SingularJacobian);
        }
        mu[0] += 1.0;
        Ok(StepStats {
            iterations: mu[0] as u32,
            residual: mu[0] * 1e-16,
        })
    }
}

#[test]
fn rollout_failure_bookkeeping_is_exact() {
    let mu0 = [
        [0.0, 1.0, 2.0],
        [3.0, 0.0, 0.0],
        [-100.0, 0.0, 0.0],
        [5.0, 0.0, 0.0],
    ];
    for every in [1, 2, 3, 4, 11, 20] {
        let n_steps = 10;
        let nr = n_records(n_steps, every);
        assert_eq!(nr, n_steps / every + 1);
        let mut out = vec![0.0; 4 * nr * 3];
        let infos = rollout(&FailAtFive, &mu0, 0.1, n_steps, every, &mut out).unwrap();
        let expect_fail = [Some(5), Some(2), None, Some(0)];
        for (i, info) in infos.iter().enumerate() {
            match expect_fail[i] {
                Some(k) => {
                    assert!(!info.converged);
                    assert_eq!(info.failed_step, k as i64, "every {every} trajectory {i}");
                    assert_eq!(info.failure, Some(StepFailure::SingularJacobian));
                }
                None => {
                    assert_eq!(info.failed_step, -1);
                    assert!(info.converged);
                    // 10 steps from −100: iterations (μ₁ as u32) saturate at 0 for negatives.
                    assert_eq!(info.newton_iterations, 0);
                }
            }
            let steps_done = expect_fail[i].unwrap_or(n_steps);
            for r in 0..nr {
                let state = r * every;
                let rec = &out[(i * nr + r) * 3..(i * nr + r) * 3 + 3];
                if state <= steps_done {
                    let want = [mu0[i][0] + state as f64, mu0[i][1], mu0[i][2]];
                    assert_eq!(rec, &want, "every {every} trajectory {i} record {r}");
                } else {
                    assert!(
                        rec.iter().all(|v| v.is_nan()),
                        "every {every} trajectory {i} record {r}: {rec:?}"
                    );
                }
            }
        }
        // Trajectory 0: 5 successful steps with iterations 1..=5.
        assert_eq!(infos[0].newton_iterations, 15);
        assert_eq!(infos[0].max_newton_iterations, 5);
        assert_eq!(infos[0].max_residual, 5e-16);
    }
}

// ---------------------------------------------------------------------------------------------
// 3. Rollouts: thread independence and argument checks
// ---------------------------------------------------------------------------------------------

fn rollout_in_pool(
    threads: usize,
    st: &BisectionStepper<3>,
    mu0: &[[f64; 3]],
    h: f64,
    n_steps: usize,
    every: usize,
) -> (Vec<f64>, Vec<TrajectoryInfo>) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| {
        let mut out = vec![0.0; mu0.len() * n_records(n_steps, every) * 3];
        let infos = rollout(st, mu0, h, n_steps, every, &mut out).unwrap();
        (out, infos)
    })
}

#[test]
fn rollout_is_bit_identical_across_thread_counts() {
    let mut rng = Rng::new(0x5EED_0030);
    for (chart, inputs, wide) in [
        (Chart::Cayley, MlpInputs::Plain, false),
        (Chart::Exp, MlpInputs::Homogeneous, false),
        (Chart::Cayley, MlpInputs::Homogeneous, true),
        (Chart::Exp, MlpInputs::Plain, true),
    ] {
        let gf = if wide {
            wide_generating(&mut rng, inputs)
        } else {
            random_generating(&mut rng, inputs)
        };
        let st = stepper(gf, chart);
        // The wide models take the batched path, in chunks that straddle the thread split.
        assert_eq!(st.batch() > 1, wide);
        let mut mu0: Vec<[f64; 3]> = (0..37)
            .map(|_| {
                let r = rng.range(1.0, 4.0);
                rng.sphere(r)
            })
            .collect();
        mu0.push([0.0, 0.0, 0.0]);
        let (h, n_steps, every) = (0.1, 60, 7);
        let (out1, info1) = rollout_in_pool(1, &st, &mu0, h, n_steps, every);
        for threads in [2, 3] {
            let (out2, info2) = rollout_in_pool(threads, &st, &mu0, h, n_steps, every);
            assert_eq!(out1.len(), out2.len());
            for (k, (a, b)) in out1.iter().zip(&out2).enumerate() {
                assert_eq!(
                    a.to_bits(),
                    b.to_bits(),
                    "{chart:?} {threads} threads: value {k}"
                );
            }
            for (a, b) in info1.iter().zip(&info2) {
                assert_eq!(a.max_residual.to_bits(), b.max_residual.to_bits());
                assert_eq!(a, b);
            }
        }
        // And the rollout did something: the last record differs from the first.
        let nr = n_records(n_steps, every);
        assert_ne!(out1[0..3], out1[(nr - 1) * 3..nr * 3]);
        assert!(info1.iter().all(|i| i.converged));
    }
}

#[test]
fn rollout_rejects_bad_arguments() {
    let st = hamiltonian_stepper(Chart::Cayley);
    let mu0 = [[1.0, 1.0, 2.0], [3.0, 2.0, 0.0]];
    let good = |n_steps: usize, every: usize| vec![0.0; 2 * n_records(n_steps, every) * 3];
    let is_invalid = |r: Result<Vec<TrajectoryInfo>, CoreError>, what: &str| match r {
        Err(CoreError::Invalid(m)) => assert!(!m.is_empty()),
        other => panic!("{what}: expected CoreError::Invalid, got {other:?}"),
    };
    // Sanity: the good call works.
    assert!(rollout(&st, &mu0, 0.1, 10, 1, &mut good(10, 1)).is_ok());
    for h in [0.0, -0.1, -0.0, f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        is_invalid(
            rollout(&st, &mu0, h, 10, 1, &mut good(10, 1)),
            &format!("h = {h}"),
        );
    }
    // every = 0 (n_records would divide by zero: the check must come first).
    is_invalid(rollout(&st, &mu0, 0.1, 10, 0, &mut [0.0; 6]), "every = 0");
    for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        for slot in 0..3 {
            let mut m = mu0;
            m[1][slot] = bad;
            is_invalid(
                rollout(&st, &m, 0.1, 10, 1, &mut good(10, 1)),
                &format!("mu0 with {bad}"),
            );
        }
    }
    let n = good(10, 3).len();
    for len in [0, n - 1, n + 1, n - 3, 2 * n] {
        is_invalid(
            rollout(&st, &mu0, 0.1, 10, 3, &mut vec![0.0; len]),
            &format!("buffer of {len}"),
        );
    }
    // An empty batch with an empty buffer is fine.
    assert_eq!(rollout(&st, &[], 0.1, 10, 1, &mut []).unwrap(), vec![]);
}

// ---------------------------------------------------------------------------------------------
// 4. Model files
// ---------------------------------------------------------------------------------------------

/// Runs `rollout` as a [`crate::rollout::Rollout`] advanced in segments of the given sizes
/// (cycled), checking the step bookkeeping on the way.
fn rollout_in_segments<S: StepMap<3>>(
    st: &S,
    mu0: &[[f64; 3]],
    h: f64,
    n_steps: usize,
    every: usize,
    segments: &[usize],
) -> (Vec<f64>, Vec<TrajectoryInfo>) {
    let mut out = vec![0.0; mu0.len() * n_records(n_steps, every) * 3];
    let mut r = crate::rollout::Rollout::start(mu0, h, n_steps, every, &mut out).unwrap();
    let mut sizes = segments.iter().cycle();
    while !r.is_finished() {
        let want = *sizes.next().unwrap();
        let before = r.steps_done();
        let took = r.advance(st, want, &mut out).unwrap();
        assert_eq!(took, want.min(n_steps - before));
        assert_eq!(r.steps_done(), before + took);
    }
    // A finished rollout takes no more steps and leaves the output alone.
    let snapshot = out.clone();
    assert_eq!(r.advance(st, 5, &mut out).unwrap(), 0);
    assert!(out
        .iter()
        .zip(&snapshot)
        .all(|(a, b)| a.to_bits() == b.to_bits()));
    (out, r.into_info())
}

#[track_caller]
fn assert_bit_identical(
    a: &(Vec<f64>, Vec<TrajectoryInfo>),
    b: &(Vec<f64>, Vec<TrajectoryInfo>),
    what: &str,
) {
    assert_eq!(a.0.len(), b.0.len(), "{what}: lengths");
    for (k, (x, y)) in a.0.iter().zip(&b.0).enumerate() {
        assert_eq!(x.to_bits(), y.to_bits(), "{what}: value {k}: {x} vs {y}");
    }
    for (x, y) in a.1.iter().zip(&b.1) {
        assert_eq!(x.max_residual.to_bits(), y.max_residual.to_bits(), "{what}");
        assert_eq!(x, y, "{what}");
    }
}

/// Any split of a rollout into segments gives the one-shot result bit for bit, including
/// trajectories that fail mid-way (records, failed step and statistics).
#[test]
fn segmented_rollout_is_bit_identical_to_one_shot() {
    let segmentations: [&[usize]; 5] = [&[1], &[3, 1, 4], &[7], &[13], &[1000]];
    let mut rng = Rng::new(0x5EED_0070);
    // A learned-like S in both charts, plus the tanh bump of huge amplitude around p₁ = 5 that
    // makes the trajectories starting near there fail after a few steps.
    let bump = Mlp::new(vec![
        Layer::new(4, 1, vec![0.0, 10.0, 0.0, 0.0], vec![-50.0]).unwrap(),
        Layer::new(1, 1, vec![1e8], vec![0.0]).unwrap(),
    ])
    .unwrap();
    let failing = GeneratingFunction::new(
        Polynomial::new(minus_t_h()).unwrap(),
        Some(bump),
        1,
        MlpInputs::Plain,
    )
    .unwrap();
    let steppers = [
        stepper(random_generating(&mut rng, MlpInputs::Plain), Chart::Cayley),
        stepper(
            random_generating(&mut rng, MlpInputs::Homogeneous),
            Chart::Exp,
        ),
        stepper(failing, Chart::Cayley),
    ];
    let mut mu0: Vec<[f64; 3]> = (0..5)
        .map(|_| {
            let r = rng.range(1.0, 4.0);
            rng.sphere(r)
        })
        .collect();
    // One state on the bump (fails at once), two large ones whose μ₁ grows towards it (the
    // bump or, in the exponential chart, the chart's singularity stops them later), and 0.
    mu0.extend([
        [5.0, 0.1, 0.1],
        [3.9, 5.2, -0.4],
        [3.9, -5.2, -0.6],
        [0.0, 0.0, 0.0],
    ]);
    let n_steps = 60;
    let mut saw_mid_failure = false;
    for (s, st) in steppers.iter().enumerate() {
        for every in [1, 3, 7, 61] {
            let mut out = vec![0.0; mu0.len() * n_records(n_steps, every) * 3];
            let infos = rollout(st, &mu0, 0.1, n_steps, every, &mut out).unwrap();
            saw_mid_failure |= infos.iter().any(|i| i.failed_step >= 10);
            let one_shot = (out, infos);
            for seg in segmentations {
                let got = rollout_in_segments(st, &mu0, 0.1, n_steps, every, seg);
                assert_bit_identical(
                    &got,
                    &one_shot,
                    &format!("stepper {s}, every {every}, segments {seg:?}"),
                );
            }
        }
    }
    assert!(saw_mid_failure, "no trajectory failed mid-way");
    // The scripted stepper fails at exactly known steps; segment boundaries on either side of a
    // failure or a record must not matter.
    let scripted = [
        [0.0, 1.0, 2.0],
        [3.0, 0.0, 0.0],
        [-100.0, 0.0, 0.0],
        [5.0, 0.0, 0.0],
    ];
    for every in [1, 2, 3, 4, 11] {
        let mut out = vec![0.0; 4 * n_records(10, every) * 3];
        let infos = rollout(&FailAtFive, &scripted, 0.1, 10, every, &mut out).unwrap();
        assert_eq!(infos[0].failed_step, 5);
        let one_shot = (out, infos);
        for seg in [&[1usize][..], &[2], &[4, 1], &[5], &[6], &[3, 3, 4]] {
            let got = rollout_in_segments(&FailAtFive, &scripted, 0.1, 10, every, seg);
            assert_bit_identical(
                &got,
                &one_shot,
                &format!("scripted, every {every}, {seg:?}"),
            );
        }
    }
}

#[test]
fn segmented_rollout_checks_its_arguments() {
    use crate::rollout::Rollout;
    let st = hamiltonian_stepper(Chart::Cayley);
    let mu0 = [[1.0, 1.0, 2.0], [3.0, 2.0, 0.0]];
    let mut out = vec![0.0; 2 * n_records(10, 3) * 3];
    for (h, every) in [(0.0, 1), (f64::NAN, 1), (0.1, 0)] {
        assert!(matches!(
            Rollout::start(&mu0, h, 10, every, &mut out),
            Err(CoreError::Invalid(_))
        ));
    }
    assert!(matches!(
        Rollout::start(&[[f64::NAN, 0.0, 0.0]], 0.1, 10, 3, &mut out[..12]),
        Err(CoreError::Invalid(_))
    ));
    let mut r = Rollout::start(&mu0, 0.1, 10, 3, &mut out).unwrap();
    assert_eq!(&out[..3], &mu0[0]);
    // A buffer of another size is refused, not indexed out of bounds.
    let mut wrong = vec![0.0; out.len() - 3];
    assert!(matches!(
        r.advance(&st, 4, &mut wrong),
        Err(CoreError::Invalid(_))
    ));
    assert_eq!(r.steps_done(), 0);
    assert_eq!(r.advance(&st, 4, &mut out).unwrap(), 4);
    assert_eq!(r.advance(&st, 0, &mut out).unwrap(), 0);
    assert_eq!(r.advance(&st, 100, &mut out).unwrap(), 6);
    assert!(r.is_finished() && r.info().iter().all(|i| i.converged));
    // An empty batch advances (its step count) without touching anything.
    let mut empty = Rollout::start(&[], 0.1, 10, 1, &mut []).unwrap();
    assert_eq!(empty.advance(&st, 7, &mut []).unwrap(), 7);
}

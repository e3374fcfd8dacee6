//! The lane Newton solve on an exponential chart (`lanes_bisection_exp`), whatever the chart:
//! its start's order, against the generic dual-number step, and lane bits that depend on neither
//! the block nor the dispatch. Each chart's test module (`se3_lanes`, `series_lanes`) runs these on its own
//! systems and states.

use super::*;
use crate::generating::polynomial_lanes::{jet_lanes_into, JetLanes, Scratch};
use crate::isa::Isa;
use crate::lanes_bisection::{ChartNewton, V};
use crate::lanes_bisection_exp::{chart_newton_steps, second_order_start, ExpChartLanes};

/// The lane solver on `chart` against the generic dual-number step (`step_generic`, nalgebra's
/// LU) of `st`, 20 steps of h = 0.1 from each of `states`: started from μ, the same Newton counts
/// and states within 1e-13 relative; with the predictor (what `step` runs), within 1e-12 and
/// fewer updates in all; every Casimir kept to 1e-14 a step. Distances are Euclidean, relative
/// to max(|μ|∞, 1).
pub(super) fn newton_against_the_generic_step<const N: usize, C: ExpChartLanes<N>>(
    st: &BisectionStepper<N>,
    chart: C,
    states: &[[f64; N]],
    casimirs: fn(&[f64; N]) -> Vec<f64>,
    label: &str,
) where
    nalgebra::Const<N>: nalgebra::DimMin<nalgebra::Const<N>, Output = nalgebra::Const<N>>,
{
    let plain = ChartNewton {
        poly: &st.generating.polynomial,
        network: None,
        chart,
        tol: st.newton.tol,
        max_iter: st.newton.max_iter,
        predict: false,
    };
    let mut ws = st.workspace();
    let (mut worst, mut worst_predicted, mut worst_casimir) = (0.0f64, 0.0f64, 0.0f64);
    let (mut n_lane, mut n_predicted, mut n_generic) = (0, 0, 0);
    let dist =
        |u: &[f64; N], v: &[f64; N]| (0..N).map(|i| (u[i] - v[i]).powi(2)).sum::<f64>().sqrt();
    for &mu in states {
        let (mut a, mut b, mut c) = (mu, mu, mu);
        for _ in 0..20 {
            let mut sa = [Err(StepFailure::OutOfDomain)];
            let mut one = [a];
            chart_newton_steps(
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
            let before = c;
            let sc = st.step(0.1, &mut c, &mut ws).unwrap();
            assert_eq!(
                sa.iterations, sb.iterations,
                "{label}: Newton counts differ"
            );
            n_lane += sa.iterations;
            n_generic += sb.iterations;
            n_predicted += sc.iterations;
            let scale = b.iter().fold(1.0f64, |m, v| m.max(v.abs()));
            worst = worst.max(dist(&a, &b) / scale);
            worst_predicted = worst_predicted.max(dist(&c, &b) / scale);
            for (c0, c1) in casimirs(&before).iter().zip(casimirs(&c)) {
                worst_casimir = worst_casimir.max((c1 - c0).abs());
            }
            (a, b) = (c, c);
        }
    }
    assert!(worst <= 1e-13, "{label}: {worst:e}");
    assert!(
        worst_predicted <= 1e-12,
        "{label}: predicted {worst_predicted:e}"
    );
    assert!(
        worst_casimir <= 1e-14,
        "{label}: Casimirs moved {worst_casimir:e}"
    );
    assert_eq!(n_lane, n_generic);
    assert!(
        n_predicted < n_generic,
        "{label}: {n_predicted} vs {n_generic} updates"
    );
    eprintln!("{label}: {n_predicted} / {n_generic} updates");
}

/// Lane bits depend on neither the dispatch nor the block: the portable and the detected
/// dispatch, blocks of 1, 3, 8, 13 and 29 states and the stepper's `step` / `step_batch` agree
/// bit for bit, failures included: `mu0` has 29 states, [5] a NaN (NonFinite), [17] one whose x
/// is far past the chart's singular angle (ChartSingular), [9] not live (left alone); with one
/// Newton update allowed every other lane stops NotConverged. `st` must take the lane solver
/// `sys` (the predicted start, tol 1e-12, at most 50 updates).
pub(super) fn same_for_every_dispatch_and_block<const N: usize, C: ExpChartLanes<N>>(
    st: &BisectionStepper<N>,
    sys: ChartNewton<'_, N, C>,
    mu0: &[[f64; N]],
) where
    nalgebra::Const<N>: nalgebra::DimMin<nalgebra::Const<N>, Output = nalgebra::Const<N>>,
{
    assert_eq!(mu0.len(), 29);
    let mut live = vec![true; mu0.len()];
    live[9] = false;
    let run = |sys: &ChartNewton<'_, N, C>, isa: Isa, block: usize| {
        let mut mu = mu0.to_vec();
        let mut res = vec![Err(StepFailure::OutOfDomain); mu.len()];
        for ((m, l), r) in mu
            .chunks_mut(block)
            .zip(live.chunks(block))
            .zip(res.chunks_mut(block))
        {
            chart_newton_steps(sys, isa, &mut [], 0.1, m, l, r);
        }
        (mu, res)
    };
    let (reference, ref_results) = run(&sys, Isa::PORTABLE, 29);
    assert_eq!(ref_results[5], Err(StepFailure::NonFinite));
    assert_eq!(ref_results[17], Err(StepFailure::ChartSingular));
    assert_eq!(ref_results[9], Err(StepFailure::OutOfDomain), "not live");
    assert!(same_bits(&reference[9], &mu0[9]) && same_bits(&reference[17], &mu0[17]));
    assert!(ref_results
        .iter()
        .enumerate()
        .all(|(j, r)| [5, 9, 17].contains(&j) || r.is_ok()));
    for isa in isas() {
        for block in [1, 3, 8, 13, 29] {
            let (mu, res) = run(&sys, isa, block);
            assert_eq!(res, ref_results, "{isa:?} block {block}");
            for j in 0..mu.len() {
                assert!(same_bits(&mu[j], &reference[j]), "{isa:?} {block} {j}");
            }
        }
    }
    // The stepper takes the lane solver one at a time and in batches.
    let mut ws = st.workspace();
    let mut batch = mu0.to_vec();
    let mut res = vec![Err(StepFailure::OutOfDomain); batch.len()];
    st.step_batch(0.1, &mut batch, &live, &mut res, &mut ws);
    assert_eq!(res, ref_results);
    for j in (0..mu0.len()).filter(|&j| ref_results[j].is_ok()) {
        let mut one = mu0[j];
        st.step(0.1, &mut one, &mut ws).unwrap();
        assert!(same_bits(&one, &reference[j]) && same_bits(&batch[j], &reference[j]));
    }
    // One update allowed: every finite lane stops NotConverged.
    let capped = ChartNewton { max_iter: 1, ..sys };
    let (_, res) = run(&capped, Isa::detect(), 8);
    for j in (0..mu0.len()).filter(|&j| ![5, 9, 17].contains(&j)) {
        assert_eq!(res[j], Err(StepFailure::NotConverged), "state {j}");
    }
}

/// Newton's start on `chart` is second order: its distance to the solved bisection momentum p*
/// falls at least as h³ from h = 0.2 to 0.025 (the fitted slope), where the first-order
/// p₁ = μ − ½ A(x₁) μ (x₁: the gradient of S's t-linear terms at μ) falls as h². The oracle p* is
/// the fixed-point iteration p ← p + μ − tar(∇S(p), p) of the groupoid's scalar chart (a
/// contraction by O(h)), run 200 times. Every state of `states` must take the start (|x₀|² ≤ 1).
pub(super) fn start_is_second_order<const N: usize, C: ExpChartLanes<N>>(
    st: &BisectionStepper<N>,
    chart: C,
    states: &[[f64; N]],
    label: &str,
) {
    let poly = &st.generating.polynomial;
    let sys = ChartNewton {
        poly,
        network: None,
        chart,
        tol: st.newton.tol,
        max_iter: st.newton.max_iter,
        predict: true,
    };
    let dist =
        |u: &[f64; N], v: &[f64; N]| (0..N).map(|i| (u[i] - v[i]).powi(2)).sum::<f64>().sqrt();
    let hs = [0.2, 0.025];
    for mu in states {
        let (mut second, mut first) = ([0.0; 2], [0.0; 2]);
        for (k, &h) in hs.iter().enumerate() {
            let mut solved = *mu;
            for _ in 0..200 {
                let x = poly.gradient(h, &solved).g;
                let t = st.realization.tar(&x, &solved).unwrap();
                solved = std::array::from_fn(|i| solved[i] + (mu[i] - t[i]));
            }
            let mut scratch = Scratch::<N, 1>::new();
            let mut jet = JetLanes {
                v: [0.0],
                g: [[0.0]; N],
                h: [[[0.0]; N]; N],
            };
            let (pl, target) = (mu.map(|m| [m]), mu.map(|m| V([m])));
            let (p0, keep) = second_order_start(&sys, h, &pl, &target, &mut scratch, &mut jet);
            assert!(keep[0], "{label}: the start was not taken at h = {h}");
            second[k] = dist(&p0.map(|v| v.0[0]), &solved);
            jet_lanes_into::<N, 1, false, 1>(poly, h, &pl, &mut scratch, &mut jet);
            let x1: [V<1>; N] = std::array::from_fn(|i| V(jet.g[i]));
            let turn = sys.chart.turn(&x1, &target);
            let p1: [f64; N] = std::array::from_fn(|i| mu[i] - 0.5 * turn[i].0[0]);
            first[k] = dist(&p1, &solved);
        }
        assert_start_orders(hs, second, first, label);
    }
}

//! Exact derivatives (jets, polynomials, homogeneous inputs, charts) against independent differences.

// Index loops over 3-vectors and 3×3 matrices read more clearly as the formulas they test.
#![allow(clippy::needless_range_loop)]

use super::*;

/// only.)
/// ∂S/∂p and ∂²S/∂p² from the Jet2 pass agree with central differences of the plain f64 value
/// path, and ∂S/∂t agrees with central differences in t. (Finite differences are a test oracle
#[test]
fn jet2_gradient_and_hessian_match_central_differences() {
    let mut rng = Rng::new(0x5EED_0001);
    let mut worst = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    for case in 0..60 {
        let inputs = if case % 2 == 0 {
            MlpInputs::Plain
        } else {
            MlpInputs::Homogeneous
        };
        let mlp = random_mlp(&mut rng, 12, 1.0);
        let terms = random_terms(&mut rng, 5, (1, 4), 3, 0.5);
        let m = 1 + rng.below(4) as u32;
        let gf =
            GeneratingFunction::new(Polynomial::new(terms).unwrap(), Some(mlp), m, inputs).unwrap();
        let mut ws_jet = gf.workspace();
        let ws = std::cell::RefCell::new(gf.workspace());
        let value =
            |t: f64, q: [f64; 3]| gf.value_and_time_derivative(t, &q, &mut ws.borrow_mut()).0;
        for _ in 0..5 {
            let t = rng.range(0.05, 1.0);
            // Away from p = 0, where the homogeneous ansatz is only C^m.
            let r = rng.range(0.3, 2.0);
            let p = rng.sphere(r);
            let jet = gf.jet(t, &p, &mut ws_jet);
            let (v, dt) = gf.value_and_time_derivative(t, &p, &mut ws.borrow_mut());
            let (g, h) = (jet.grad(), jet.hess());
            let scale = 1.0
                + v.abs()
                + g.iter().map(|x| x.abs()).fold(0.0, f64::max)
                + h.iter().flatten().map(|x| x.abs()).fold(0.0, f64::max);

            // The value itself.
            let e = (jet.value() - v).abs() / scale;
            worst.0 = worst.0.max(e);
            assert!(
                e < 1e-14,
                "case {case} {inputs:?}: jet value {} vs {v}",
                jet.value()
            );

            let delta = 2e-3;
            let shift = |i: usize, a: f64, j: usize, b: f64| {
                let mut q = p;
                q[i] += a;
                q[j] += b;
                value(t, q)
            };
            for i in 0..3 {
                let fd = richardson(
                    |d| (shift(i, d, i, 0.0) - shift(i, -d, i, 0.0)) / (2.0 * d),
                    delta,
                );
                let e = (g[i] - fd).abs() / scale;
                worst.1 = worst.1.max(e);
                assert!(
                    e < 1e-9,
                    "case {case} {inputs:?}: dS/dp{i} = {} but FD gives {fd}",
                    g[i]
                );
                for j in i..3 {
                    let fd = if i == j {
                        richardson(
                            |d| (shift(i, d, i, 0.0) - 2.0 * v + shift(i, -d, i, 0.0)) / (d * d),
                            delta,
                        )
                    } else {
                        richardson(
                            |d| {
                                (shift(i, d, j, d) - shift(i, d, j, -d) - shift(i, -d, j, d)
                                    + shift(i, -d, j, -d))
                                    / (4.0 * d * d)
                            },
                            delta,
                        )
                    };
                    let e = (h[i][j] - fd).abs() / scale;
                    worst.2 = worst.2.max(e);
                    assert!(
                        e < 1e-7,
                        "case {case} {inputs:?}: d2S/dp{i}dp{j} = {} but FD gives {fd}",
                        h[i][j]
                    );
                    assert_eq!(h[i][j], h[j][i]);
                }
            }
            let fd = richardson(|d| (value(t + d, p) - value(t - d, p)) / (2.0 * d), delta);
            let e = (dt - fd).abs() / (1.0 + v.abs() + dt.abs());
            worst.3 = worst.3.max(e);
            assert!(
                e < 1e-8,
                "case {case} {inputs:?}: dS/dt = {dt} but FD gives {fd}"
            );
        }
    }
    eprintln!("worst scaled errors (value, grad, hess, dt): {worst:?}");
}

/// The homogeneous ansatz builds in S(t, λp) = λ S(λt, p) for λ > 0 (as do −tH and the Taylor
/// terms of a quadratic H): so ∇S(t, λp) = ∇S(λt, p), ∇²S(t, λp) = ∇²S(λt, p)/λ and a step of
/// size h from λμ is λ times a step of size λh from μ.
#[test]
fn homogeneous_inputs_scale_correctly() {
    let mut rng = Rng::new(0x5EED_0005);
    for case in 0..10 {
        let mlp = random_mlp(&mut rng, 10, 1.0);
        let m = 1 + rng.below(4) as u32;
        let gf = GeneratingFunction::new(
            Polynomial::new(taylor3()).unwrap(),
            Some(mlp),
            m,
            MlpInputs::Homogeneous,
        )
        .unwrap();
        let mut ws = gf.workspace();
        let t = rng.range(0.05, 0.3);
        let r = rng.range(0.5, 2.0);
        let p = rng.sphere(r);
        let lambda = rng.range(0.3, 3.0);
        let lp = p.map(|v| lambda * v);
        let a = gf.jet(t, &lp, &mut ws);
        let b = gf.jet(lambda * t, &p, &mut ws);
        let tol = 1e-13 * (1.0 + b.max_abs());
        assert!(
            (a.value() - lambda * b.value()).abs() < tol * lambda,
            "case {case}: value"
        );
        let (ha, hb) = (a.hess(), b.hess());
        for i in 0..3 {
            assert!(
                (a.grad()[i] - b.grad()[i]).abs() < tol,
                "case {case}: grad {i}"
            );
            for j in 0..3 {
                assert!(
                    (ha[i][j] - hb[i][j] / lambda).abs() < tol / lambda,
                    "case {case}: hess {i}{j}"
                );
            }
        }
        let (va, _) = gf.value_and_time_derivative(t, &lp, &mut ws);
        let (vb, _) = gf.value_and_time_derivative(lambda * t, &p, &mut ws);
        assert!(
            (va - lambda * vb).abs() < tol * lambda,
            "case {case}: value path"
        );

        let st = stepper(gf, Chart::Cayley);
        let mu = rng.sphere(r);
        let (mut x, mut y) = (mu.map(|v| lambda * v), mu);
        st.step(t, &mut x, &mut ws).unwrap();
        st.step(lambda * t, &mut y, &mut ws).unwrap();
        let y = y.map(|v| lambda * v);
        assert!(
            norm(&sub(&x, &y)) < 1e-13 * norm(&x),
            "case {case}: step {x:?} vs {y:?}"
        );
    }
}

/// The polynomial part alone (no MLP): closed-form jets against the value path, including
/// p-powers 0, 1 and 2 where the power rule has special cases.
#[test]
fn polynomial_jet_matches_central_differences() {
    let mut rng = Rng::new(0x5EED_0002);
    for case in 0..50 {
        let terms = random_terms(&mut rng, 6, (1, 5), 4, 1.0);
        let gf =
            GeneratingFunction::new(Polynomial::new(terms).unwrap(), None, 0, MlpInputs::Plain)
                .unwrap();
        let mut ws = gf.workspace();
        let t = rng.range(0.1, 1.2);
        let p = rng.vec3(-1.5, 1.5);
        let jet = gf.jet(t, &p, &mut ws);
        let scale = 1.0 + jet.max_abs();
        let value = |q: [f64; 3]| gf.polynomial.value_and_time_derivative(t, &q).0;
        for i in 0..3 {
            let fd = richardson(
                |d| {
                    let (mut a, mut b) = (p, p);
                    a[i] += d;
                    b[i] -= d;
                    (value(a) - value(b)) / (2.0 * d)
                },
                2e-3,
            );
            assert!(
                (jet.grad()[i] - fd).abs() < 1e-9 * scale,
                "case {case}: grad {i}"
            );
        }
        // Spot-check one Hessian entry per case.
        let (i, j) = (rng.below(3), rng.below(3));
        let fd = richardson(
            |d| {
                let f = |a: f64, b: f64| {
                    let mut q = p;
                    q[i] += a;
                    q[j] += b;
                    value(q)
                };
                (f(d, d) - f(d, -d) - f(-d, d) + f(-d, -d)) / (4.0 * d * d)
            },
            2e-3,
        );
        assert!(
            (jet.hess()[i][j] - fd).abs() < 1e-7 * scale,
            "case {case}: hess {i}{j}: {} vs {fd}",
            jet.hess()[i][j]
        );
    }
}

/// The charts evaluated on Jet2 inputs (x depending on three variables) give the derivatives of
/// the f64 charts; this exercises c, c' and c'' of the exponential chart on both sides of the
/// series/closed-form switch at |x| = 1.
#[test]
fn charts_on_jets_match_central_differences() {
    let mut rng = Rng::new(0x5EED_0003);
    for chart in [Chart::Cayley, Chart::Exp] {
        for r in [0.05, 0.5, 0.99, 1.01, 2.0, 4.5] {
            let x0 = rng.sphere(r);
            let p = rng.vec3(-2.0, 2.0);
            let xj: [Jet2<3>; 3] = std::array::from_fn(|i| Jet2::var(x0[i], i));
            let pj = p.map(Jet2::cst);
            for (which, sign) in [("sou", 1.0), ("tar", -1.0)] {
                let eval = |x: [f64; 3]| {
                    if sign > 0.0 {
                        chart.sou(&x, &p).unwrap()
                    } else {
                        chart.tar(&x, &p).unwrap()
                    }
                };
                let out = if sign > 0.0 {
                    chart.sou(&xj, &pj).unwrap()
                } else {
                    chart.tar(&xj, &pj).unwrap()
                };
                let f0 = eval(x0);
                for k in 0..3 {
                    assert!((out[k].value() - f0[k]).abs() < 1e-14 * (1.0 + f0[k].abs()));
                    let scale = 1.0 + out[k].max_abs();
                    for i in 0..3 {
                        for j in i..3 {
                            let fd = richardson(
                                |d| {
                                    let f = |a: f64, b: f64| {
                                        let mut x = x0;
                                        x[i] += a;
                                        x[j] += b;
                                        eval(x)[k]
                                    };
                                    (f(d, d) - f(d, -d) - f(-d, d) + f(-d, -d)) / (4.0 * d * d)
                                },
                                2e-3,
                            );
                            let h = out[k].hess()[i][j];
                            assert!(
                                (h - fd).abs() < 1e-7 * scale,
                                "{chart:?} {which} |x| = {r}: d2/dx{i}dx{j} of component {k}: {h} vs {fd}"
                            );
                        }
                    }
                }
            }
        }
    }
}

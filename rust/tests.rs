//! Crate-level tests of the core: exact derivatives against finite differences of the value path,
//! Casimir conservation, the order of the −tH integrator against a fine RK4 reference, failure
//! reporting, thread-count independence of rollouts, argument checks, model files (valid and
//! corrupt) and the exponential chart against an independent matrix implementation.
//!
//! Every random test draws from a fixed-seed splitmix64 generator, so a failure reproduces.

// Index loops over 3-vectors and 3×3 matrices read more clearly as the formulas they test.
#![allow(clippy::needless_range_loop)]

use std::collections::HashMap;
use std::panic::{catch_unwind, AssertUnwindSafe};

use safetensors::tensor::TensorView;
use safetensors::{serialize, Dtype};

use crate::dual::{Jet2, Scalar};
use crate::error::{CoreError, StepFailure};
use crate::generating::{GeneratingFunction, Layer, Mlp, MlpInputs, Monomial, Polynomial};
use crate::groupoid::{Chart, Groupoid};
use crate::model::{Model, FORMAT};
use crate::rollout::{n_records, rollout, TrajectoryInfo};
use crate::stepper::{BisectionStepper, NewtonOptions, StepMap, StepStats};

// ---------------------------------------------------------------------------------------------
// Helpers
// ---------------------------------------------------------------------------------------------

/// splitmix64: a tiny deterministic generator, enough for test inputs.
struct Rng(u64);

impl Rng {
    fn new(seed: u64) -> Self {
        Rng(seed)
    }

    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    fn range(&mut self, a: f64, b: f64) -> f64 {
        a + (b - a) * self.uniform()
    }

    /// Uniform integer in [0, n).
    fn below(&mut self, n: usize) -> usize {
        (self.next_u64() % n as u64) as usize
    }

    fn vec3(&mut self, a: f64, b: f64) -> [f64; 3] {
        [self.range(a, b), self.range(a, b), self.range(a, b)]
    }

    /// A uniformly random point on the sphere of radius `r`.
    fn sphere(&mut self, r: f64) -> [f64; 3] {
        loop {
            let v = self.vec3(-1.0, 1.0);
            let n = norm(&v);
            if n > 0.1 && n <= 1.0 {
                return v.map(|c| r * c / n);
            }
        }
    }
}

const INERTIA: [f64; 3] = [1.5, 2.0, 2.5];

const ALL_INPUTS: [MlpInputs; 2] = [MlpInputs::Plain, MlpInputs::Homogeneous];

fn dot(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn norm(a: &[f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

fn cross(a: &[f64; 3], b: &[f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn sub(a: &[f64; 3], b: &[f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// −t H(p) = −t Σ pᵢ²/(2 Iᵢ) as monomials.
fn minus_t_h() -> Vec<Monomial<3>> {
    (0..3)
        .map(|i| {
            let mut p_powers = [0; 3];
            p_powers[i] = 2;
            Monomial {
                t_power: 1,
                p_powers,
                coeff: -1.0 / (2.0 * INERTIA[i]),
            }
        })
        .collect()
}

/// The Taylor K = 3 generating function t S₁ + t³ S₃ for I = (1.5, 2, 2.5), Cayley chart.
fn taylor3() -> Vec<Monomial<3>> {
    let mut terms = minus_t_h();
    let s3: [([u32; 3], f64); 6] = [
        ([4, 0, 0], -2.0 / 81.0),
        ([2, 2, 0], -71.0 / 2160.0),
        ([2, 0, 2], -17.0 / 675.0),
        ([0, 4, 0], -1.0 / 96.0),
        ([0, 2, 2], -11.0 / 720.0),
        ([0, 0, 4], -2.0 / 375.0),
    ];
    terms.extend(s3.iter().map(|&(p_powers, coeff)| Monomial {
        t_power: 3,
        p_powers,
        coeff,
    }));
    terms
}

/// A tanh MLP R⁴ → R with 1–3 hidden layers of random widths in 1..=max_width and Xavier-uniform
/// weights times `gain`.
fn random_mlp(rng: &mut Rng, max_width: usize, gain: f64) -> Mlp {
    let n_hidden = 1 + rng.below(3);
    let mut widths = vec![4];
    for _ in 0..n_hidden {
        widths.push(1 + rng.below(max_width));
    }
    widths.push(1);
    mlp_with_widths(rng, &widths, gain)
}

/// A tanh MLP with the given layer sizes (4 first, 1 last), Xavier-uniform weights times `gain`
/// and biases in (−0.5, 0.5).
fn mlp_with_widths(rng: &mut Rng, widths: &[usize], gain: f64) -> Mlp {
    let layers = widths
        .windows(2)
        .map(|w| {
            let (n_in, n_out) = (w[0], w[1]);
            let a = gain * (6.0 / (n_in + n_out) as f64).sqrt();
            let weight = (0..n_in * n_out).map(|_| rng.range(-a, a)).collect();
            let bias = (0..n_out).map(|_| rng.range(-0.5, 0.5)).collect();
            Layer::new(n_in, n_out, weight, bias).unwrap()
        })
        .collect();
    Mlp::new(layers).unwrap()
}

/// `n` random monomials with t-power in `t_powers`, p-powers in 0..=max_p and coefficients in
/// (−scale, scale).
fn random_terms(
    rng: &mut Rng,
    n: usize,
    t_powers: (u32, u32),
    max_p: u32,
    scale: f64,
) -> Vec<Monomial<3>> {
    (0..n)
        .map(|_| Monomial {
            t_power: t_powers.0 + rng.below((t_powers.1 - t_powers.0 + 1) as usize) as u32,
            p_powers: [0; 3].map(|_: u32| rng.below(max_p as usize + 1) as u32),
            coeff: rng.range(-scale, scale),
        })
        .collect()
}

/// −tH plus small random polynomial terms plus t^m · (random MLP): a "random S" that a step of
/// h ≈ 0.1 can still solve for states of radius ≤ 4.
fn random_generating(rng: &mut Rng, inputs: MlpInputs) -> GeneratingFunction<3> {
    let mut terms = minus_t_h();
    terms.extend(random_terms(rng, 4, (2, 4), 3, 0.02));
    let mlp = random_mlp(rng, 12, 1.0);
    let m = 2 + rng.below(3) as u32;
    GeneratingFunction::new(Polynomial { terms }, Some(mlp), m, inputs).unwrap()
}

/// Like [`random_generating`] with two hidden layers of 40: wide enough for the batched path.
fn wide_generating(rng: &mut Rng, inputs: MlpInputs) -> GeneratingFunction<3> {
    let mlp = mlp_with_widths(rng, &[4, 40, 40, 1], 1.0);
    let mut terms = minus_t_h();
    terms.extend(random_terms(rng, 4, (2, 4), 3, 0.02));
    GeneratingFunction::new(Polynomial { terms }, Some(mlp), 3, inputs).unwrap()
}

fn stepper(generating: GeneratingFunction<3>, chart: Chart) -> BisectionStepper<3> {
    BisectionStepper {
        generating,
        groupoid: Groupoid::so3(chart).unwrap(),
        newton: NewtonOptions::default(),
    }
}

fn hamiltonian_stepper(chart: Chart) -> BisectionStepper<3> {
    let gf = GeneratingFunction::new(Polynomial { terms: minus_t_h() }, None, 0, MlpInputs::Plain)
        .unwrap();
    stepper(gf, chart)
}

/// Richardson-extrapolated central difference: (4 D(δ/2) − D(δ)) / 3, error O(δ⁴).
fn richardson(d: impl Fn(f64) -> f64, delta: f64) -> f64 {
    (4.0 * d(0.5 * delta) - d(delta)) / 3.0
}

// ---------------------------------------------------------------------------------------------
// 1. Exact derivatives of the generating function
// ---------------------------------------------------------------------------------------------

/// ∂S/∂p and ∂²S/∂p² from the Jet2 pass agree with central differences of the plain f64 value
/// path, and ∂S/∂t agrees with central differences in t. (Finite differences are a test oracle
/// only.)
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
        let gf = GeneratingFunction::new(Polynomial { terms }, Some(mlp), m, inputs).unwrap();
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
            Polynomial { terms: taylor3() },
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
        let gf = GeneratingFunction::new(Polynomial { terms }, None, 0, MlpInputs::Plain).unwrap();
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

/// For the Cayley chart the Newton Jacobian has the closed form of DESIGN.md §1; the dual-number
/// chart (how the stepper builds it) must agree.
#[test]
fn cayley_newton_jacobian_matches_closed_form() {
    use crate::dual::Dual1;
    let mut rng = Rng::new(0x5EED_0004);
    for k in 0..20 {
        let gf = random_generating(&mut rng, ALL_INPUTS[k % 2]);
        let mut ws = gf.workspace();
        let h = rng.range(0.05, 0.5);
        let r = rng.range(1.0, 4.0);
        let p = rng.sphere(r);
        let jet = gf.jet(h, &p, &mut ws);
        let (x, hs) = (jet.grad(), jet.hess());
        let xd: [Dual1<3>; 3] = std::array::from_fn(|i| Dual1 { v: x[i], g: hs[i] });
        let pd: [Dual1<3>; 3] = std::array::from_fn(|i| Dual1::var(p[i], i));
        let t = Chart::Cayley.tar(&xd, &pd).unwrap();
        // J = (I − ½ x̂ + ¼ x xᵀ) + (½ p̂ + ¼ (x pᵀ + (x·p) I)) · Hs
        let hat = |v: &[f64; 3]| [[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]];
        let (xh, ph) = (hat(&x), hat(&p));
        let xp = dot(&x, &p);
        for r in 0..3 {
            for c in 0..3 {
                let id = if r == c { 1.0 } else { 0.0 };
                let a = id - 0.5 * xh[r][c] + 0.25 * x[r] * x[c];
                let b: f64 = (0..3)
                    .map(|k| {
                        let idk = if r == k { 1.0 } else { 0.0 };
                        (0.5 * ph[r][k] + 0.25 * (x[r] * p[k] + xp * idk)) * hs[k][c]
                    })
                    .sum();
                let j = a + b;
                assert!(
                    (t[r].g[c] - j).abs() < 1e-13 * (1.0 + j.abs()),
                    "J[{r}][{c}] = {} vs closed form {j}",
                    t[r].g[c]
                );
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// 2. The stepper: Casimir, order, residual, failures
// ---------------------------------------------------------------------------------------------

fn casimir_is_kept(chart: Chart, seed: u64) {
    let mut rng = Rng::new(seed);
    let mut worst_step = 0.0f64;
    let mut worst_total = 0.0f64;
    for case in 0..4 {
        let inputs = ALL_INPUTS[case % 2];
        let st = stepper(random_generating(&mut rng, inputs), chart);
        let mut ws = st.workspace();
        for _ in 0..3 {
            let r = rng.range(1.0, 4.0);
            let mu0 = rng.sphere(r);
            let c0 = dot(&mu0, &mu0);
            let mut mu = mu0;
            for k in 0..1000 {
                let before = dot(&mu, &mu);
                st.step(0.1, &mut mu, &mut ws).unwrap_or_else(|e| {
                    panic!("{chart:?} {inputs:?} case {case} mu0 {mu0:?}: step {k} failed: {e:?}")
                });
                let rel = (dot(&mu, &mu) - before).abs() / before;
                worst_step = worst_step.max(rel);
                assert!(
                    rel <= 1e-13,
                    "{chart:?} {inputs:?} case {case} mu0 {mu0:?}: step {k} changed |mu|^2 by {rel:e}"
                );
            }
            let rel = (dot(&mu, &mu) - c0).abs() / c0;
            worst_total = worst_total.max(rel);
            assert!(
                rel <= 1e-12,
                "{chart:?} {inputs:?} case {case} mu0 {mu0:?}: 1000 steps changed |mu|^2 by {rel:e}"
            );
            // The state moved: a map that does nothing would keep the Casimir trivially.
            assert!(norm(&sub(&mu, &mu0)) > 1e-3 * norm(&mu0));
        }
    }
    eprintln!("{chart:?}: worst relative Casimir change per step {worst_step:e}, over 1000 steps {worst_total:e}");
}

#[test]
fn casimir_kept_to_round_off_cayley() {
    casimir_is_kept(Chart::Cayley, 0x5EED_0010);
}

#[test]
fn casimir_kept_to_round_off_exp() {
    casimir_is_kept(Chart::Exp, 0x5EED_0011);
}

/// μ̇ = μ × ∇H(μ) with ∇H = μ / I.
fn rigid_body_rhs(mu: &[f64; 3]) -> [f64; 3] {
    let grad = [mu[0] / INERTIA[0], mu[1] / INERTIA[1], mu[2] / INERTIA[2]];
    cross(mu, &grad)
}

/// Classical RK4 with `n` steps over time `t`.
fn rk4(mu0: [f64; 3], t: f64, n: usize) -> [f64; 3] {
    let dt = t / n as f64;
    let mut y = mu0;
    let axpy =
        |y: &[f64; 3], a: f64, k: &[f64; 3]| [y[0] + a * k[0], y[1] + a * k[1], y[2] + a * k[2]];
    for _ in 0..n {
        let k1 = rigid_body_rhs(&y);
        let k2 = rigid_body_rhs(&axpy(&y, 0.5 * dt, &k1));
        let k3 = rigid_body_rhs(&axpy(&y, 0.5 * dt, &k2));
        let k4 = rigid_body_rhs(&axpy(&y, dt, &k3));
        for i in 0..3 {
            y[i] += dt / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
        }
    }
    y
}

/// S = −tH is a second-order integrator (S₂ = 0 in both charts): the local error is O(h³), so
/// halving h divides it by about 8. The Newton residual it reports is at round-off.
#[test]
fn minus_t_h_step_is_second_order_with_tight_residual() {
    let mut rng = Rng::new(0x5EED_0020);
    let mut states = vec![[1.0, 1.0, 2.0], [3.0, 2.0, 0.0]];
    for _ in 0..3 {
        let r = rng.range(1.0, 4.0);
        states.push(rng.sphere(r));
    }
    for chart in [Chart::Cayley, Chart::Exp] {
        let st = hamiltonian_stepper(chart);
        let mut ws = st.workspace();
        for mu0 in &states {
            let errs: Vec<f64> = [0.1, 0.05, 0.025]
                .iter()
                .map(|&h| {
                    let mut mu = *mu0;
                    let stats = st.step(h, &mut mu, &mut ws).unwrap();
                    assert!(
                        stats.residual <= 1e-13 * norm(mu0),
                        "{chart:?} {mu0:?} h={h}: residual {}",
                        stats.residual
                    );
                    assert!(stats.iterations >= 1);
                    let exact = rk4(*mu0, h, 2000);
                    norm(&sub(&mu, &exact))
                })
                .collect();
            eprintln!("{chart:?} {mu0:?}: local errors at h = 0.1, 0.05, 0.025: {errs:?}");
            for w in errs.windows(2) {
                let ratio = w[0] / w[1];
                assert!(
                    (7.0..=9.0).contains(&ratio),
                    "{chart:?} {mu0:?}: err(h)/err(h/2) = {ratio} (errors {errs:?}), expected about 8"
                );
            }
        }
    }
}

/// The Taylor K=3 function of DESIGN.md (Cayley chart) is a 4th-order integrator: its local error
/// is O(h⁵), a ratio of about 32 — the test vectors for S₃ are right.
#[test]
fn taylor3_step_is_fourth_order() {
    let gf = GeneratingFunction::new(Polynomial { terms: taylor3() }, None, 0, MlpInputs::Plain)
        .unwrap();
    let st = stepper(gf, Chart::Cayley);
    let mut ws = st.workspace();
    for mu0 in [[1.0, 1.0, 2.0], [3.0, 2.0, 0.0], [-0.5, 1.5, 1.0]] {
        let errs: Vec<f64> = [0.1, 0.05]
            .iter()
            .map(|&h| {
                let mut mu = mu0;
                st.step(h, &mut mu, &mut ws).unwrap();
                norm(&sub(&mu, &rk4(mu0, h, 4000)))
            })
            .collect();
        let ratio = errs[0] / errs[1];
        eprintln!("Taylor K=3 {mu0:?}: local errors at h = 0.1, 0.05: {errs:?}, ratio {ratio}");
        assert!(
            (28.0..=36.0).contains(&ratio),
            "{mu0:?}: ratio {ratio} (errors {errs:?}), expected about 32"
        );
    }
}

/// Newton failure is an Err from `step`, and the state is left untouched.
#[test]
fn newton_failure_is_reported_by_step() {
    let mu0 = [1.0, 1.0, 2.0];
    // A huge step of −tH. (In the Cayley chart tar is cubic in p and Newton from μ still finds
    // the small root up to h ≈ 1e8; beyond, it runs out of iterations or overflows. The
    // exponential chart leaves its domain |x| < 2π − 0.1 already at h = 10.)
    let cases = [
        (Chart::Cayley, vec![1e30, 1e100, 1e200, 1e300, f64::MAX]),
        (Chart::Exp, vec![10.0, 1e8, 1e300, f64::MAX]),
    ];
    for (chart, hs) in cases {
        let st = hamiltonian_stepper(chart);
        let mut ws = st.workspace();
        for h in hs {
            let mut mu = mu0;
            let r = st.step(h, &mut mu, &mut ws);
            assert!(
                r.is_err(),
                "{chart:?} h = {h}: expected a failure, got {r:?}"
            );
            if chart == Chart::Exp && h < 1e300 {
                assert_eq!(r, Err(StepFailure::ChartSingular));
            }
            assert_eq!(mu, mu0, "a failed step must not move the state");
        }
        // The same stepper still works at a sane step afterwards (no state carried over).
        let mut mu = mu0;
        assert!(st.step(0.1, &mut mu, &mut ws).is_ok());
    }
    // A huge MLP output: S = −tH + t · 1e12 · tanh(p₁ + p₂ + p₃ − 1).
    let mlp = Mlp::new(vec![
        Layer::new(4, 1, vec![0.0, 1.0, 1.0, 1.0], vec![-1.0]).unwrap(),
        Layer::new(1, 1, vec![1e12], vec![0.0]).unwrap(),
    ])
    .unwrap();
    for chart in [Chart::Cayley, Chart::Exp] {
        let gf = GeneratingFunction::new(
            Polynomial { terms: minus_t_h() },
            Some(mlp.clone()),
            1,
            MlpInputs::Plain,
        )
        .unwrap();
        let st = stepper(gf, chart);
        let mut ws = st.workspace();
        let mut mu = mu0;
        let r = st.step(0.1, &mut mu, &mut ws);
        assert!(
            r.is_err(),
            "{chart:?} huge MLP: expected a failure, got {r:?}"
        );
        assert_eq!(mu, mu0);
    }
    // An iteration cap of 1 cannot be met by a nonlinear S.
    let mut st = hamiltonian_stepper(Chart::Cayley);
    st.newton = NewtonOptions::validated(1e-12, 1).unwrap();
    let mut ws = st.workspace();
    let mut mu = mu0;
    assert_eq!(
        st.step(0.1, &mut mu, &mut ws),
        Err(StepFailure::NotConverged)
    );
}

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
        Polynomial { terms: minus_t_h() },
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

/// An owned tensor to serialise.
#[derive(Clone)]
struct Tensor {
    name: String,
    dtype: Dtype,
    shape: Vec<usize>,
    data: Vec<u8>,
}

fn f64_tensor(name: &str, shape: &[usize], values: &[f64]) -> Tensor {
    Tensor {
        name: name.into(),
        dtype: Dtype::F64,
        shape: shape.to_vec(),
        data: values.iter().flat_map(|v| v.to_le_bytes()).collect(),
    }
}

fn i64_tensor(name: &str, shape: &[usize], values: &[i64]) -> Tensor {
    Tensor {
        name: name.into(),
        dtype: Dtype::I64,
        shape: shape.to_vec(),
        data: values.iter().flat_map(|v| v.to_le_bytes()).collect(),
    }
}

fn f32_tensor(name: &str, shape: &[usize], values: &[f32]) -> Tensor {
    Tensor {
        name: name.into(),
        dtype: Dtype::F32,
        shape: shape.to_vec(),
        data: values.iter().flat_map(|v| v.to_le_bytes()).collect(),
    }
}

fn serialize_tensors(tensors: &[Tensor], metadata: Option<HashMap<String, String>>) -> Vec<u8> {
    let views: Vec<(String, TensorView<'_>)> = tensors
        .iter()
        .map(|t| {
            (
                t.name.clone(),
                TensorView::new(t.dtype, t.shape.clone(), &t.data).unwrap(),
            )
        })
        .collect();
    serialize(views, metadata).unwrap()
}

/// Metadata of a model file; `mlp` = (mlp_power, inputs) when the file holds an MLP.
fn metadata(chart: &str, mlp: Option<(u32, MlpInputs)>) -> HashMap<String, String> {
    let mut m = HashMap::new();
    m.insert("format".to_string(), FORMAT.to_string());
    m.insert("chart".to_string(), chart.to_string());
    if let Some((k, inputs)) = mlp {
        m.insert("mlp_power".to_string(), k.to_string());
        m.insert("mlp_inputs".to_string(), inputs.name().to_string());
    }
    m.insert("system".to_string(), "rigid_body".to_string());
    m.insert("inertia".to_string(), "[1.5, 2.0, 2.5]".to_string());
    m
}

fn polynomial_tensors(poly: &Polynomial<3>) -> Vec<Tensor> {
    let n = poly.terms.len();
    let powers: Vec<i64> = poly
        .terms
        .iter()
        .flat_map(|m| {
            [
                m.t_power as i64,
                m.p_powers[0] as i64,
                m.p_powers[1] as i64,
                m.p_powers[2] as i64,
            ]
        })
        .collect();
    let coeffs: Vec<f64> = poly.terms.iter().map(|m| m.coeff).collect();
    vec![
        i64_tensor("poly.powers", &[n, 4], &powers),
        f64_tensor("poly.coeffs", &[n], &coeffs),
    ]
}

fn mlp_tensors(mlp: &Mlp) -> Vec<Tensor> {
    mlp.layers
        .iter()
        .enumerate()
        .flat_map(|(i, l)| {
            [
                f64_tensor(&format!("mlp.{i}.weight"), &[l.n_out, l.n_in], &l.weight),
                f64_tensor(&format!("mlp.{i}.bias"), &[l.n_out], &l.bias),
            ]
        })
        .collect()
}

fn generating_tensors(gf: &GeneratingFunction<3>) -> Vec<Tensor> {
    let mut t = polynomial_tensors(&gf.polynomial);
    if let Some(mlp) = &gf.mlp {
        t.extend(mlp_tensors(mlp));
    }
    t
}

/// A valid model: −tH + small terms + t^m MLP.
fn valid_model(seed: u64) -> (GeneratingFunction<3>, Vec<Tensor>, HashMap<String, String>) {
    let mut rng = Rng::new(seed);
    let gf = random_generating(&mut rng, MlpInputs::Plain);
    let tensors = generating_tensors(&gf);
    let meta = metadata("cayley", Some((gf.mlp_power, gf.inputs)));
    (gf, tensors, meta)
}

fn valid_bytes() -> Vec<u8> {
    let (_, tensors, meta) = valid_model(0x5EED_0040);
    serialize_tensors(&tensors, Some(meta))
}

/// `Model::from_bytes` must give `CoreError::Format` with a message containing `needle`, and must
/// not panic.
#[track_caller]
fn expect_format_error(bytes: &[u8], needle: &str, what: &str) {
    match catch_unwind(AssertUnwindSafe(|| Model::from_bytes(bytes))) {
        Ok(Err(CoreError::Format(m))) => assert!(
            m.contains(needle),
            "{what}: message {m:?} does not mention {needle:?}"
        ),
        Ok(other) => panic!("{what}: expected CoreError::Format, got {other:?}"),
        Err(_) => panic!("{what}: Model::from_bytes panicked"),
    }
}

#[test]
fn model_round_trips_through_safetensors() {
    for (seed, chart_name, chart, inputs) in [
        (0x5EED_0041, "cayley", Chart::Cayley, MlpInputs::Plain),
        (0x5EED_0042, "exp", Chart::Exp, MlpInputs::Homogeneous),
        (0x5EED_0043, "cayley", Chart::Cayley, MlpInputs::Homogeneous),
    ] {
        let mut rng = Rng::new(seed);
        let gf = random_generating(&mut rng, inputs);
        let bytes = serialize_tensors(
            &generating_tensors(&gf),
            Some(metadata(chart_name, Some((gf.mlp_power, inputs)))),
        );
        let model = Model::from_bytes(&bytes).unwrap();
        assert_eq!(model.chart, chart);
        assert_eq!(model.generating::<3>().unwrap().inputs, inputs);
        assert_eq!(model.generating::<3>().unwrap(), gf);
        assert_eq!(model.metadata["system"], "rigid_body");
        assert_eq!(model.metadata["inertia"], "[1.5, 2.0, 2.5]");
        // It evaluates bit-for-bit like the directly built one.
        let (mut w1, mut w2) = (gf.workspace(), model.generating::<3>().unwrap().workspace());
        for _ in 0..20 {
            let t = rng.range(0.0, 1.0);
            let p = rng.vec3(-3.0, 3.0);
            let (a, b) = (
                gf.jet(t, &p, &mut w1),
                model.generating::<3>().unwrap().jet(t, &p, &mut w2),
            );
            assert!(a
                .flat()
                .iter()
                .zip(&b.flat())
                .all(|(x, y)| x.to_bits() == y.to_bits()));
            let (a, b) = (
                gf.value_and_time_derivative(t, &p, &mut w1),
                model
                    .generating::<3>()
                    .unwrap()
                    .value_and_time_derivative(t, &p, &mut w2),
            );
            assert_eq!(a.0.to_bits(), b.0.to_bits());
            assert_eq!(a.1.to_bits(), b.1.to_bits());
        }
        // Its stepper steps like the directly built one.
        let st = model.stepper::<3>(NewtonOptions::default()).unwrap();
        let direct = stepper(gf, chart);
        let mu0 = [1.0, 1.0, 2.0];
        let (mut a, mut b) = (mu0, mu0);
        st.step(0.1, &mut a, &mut w1).unwrap();
        direct.step(0.1, &mut b, &mut w2).unwrap();
        assert_eq!(a, b);
        assert_ne!(a, mu0);
    }
    // Polynomial only (no MLP, no mlp_power needed) and MLP only (no polynomial tensors).
    let poly = Polynomial { terms: taylor3() };
    let bytes = serialize_tensors(&polynomial_tensors(&poly), Some(metadata("cayley", None)));
    let model = Model::from_bytes(&bytes).unwrap();
    assert_eq!(model.generating::<3>().unwrap().polynomial, poly);
    assert!(model.generating::<3>().unwrap().mlp.is_none());
    let mut rng = Rng::new(0x5EED_0044);
    let mlp = random_mlp(&mut rng, 8, 1.0);
    let bytes = serialize_tensors(
        &mlp_tensors(&mlp),
        Some(metadata("exp", Some((3, MlpInputs::Plain)))),
    );
    let model = Model::from_bytes(&bytes).unwrap();
    assert_eq!(model.generating::<3>().unwrap().mlp.as_ref(), Some(&mlp));
    assert_eq!(model.generating::<3>().unwrap().mlp_power, 3);
    assert!(model.generating::<3>().unwrap().polynomial.terms.is_empty());
}

#[test]
fn model_from_file_round_trip_and_missing_path() {
    let bytes = valid_bytes();
    let dir = std::env::temp_dir();
    let path = dir.join(format!(
        "poisson_rs_test_{}.safetensors",
        std::process::id()
    ));
    std::fs::write(&path, &bytes).unwrap();
    let loaded = Model::from_file(&path);
    std::fs::remove_file(&path).unwrap();
    let from_bytes = Model::from_bytes(&bytes).unwrap();
    assert_eq!(
        loaded.unwrap().generating::<3>().unwrap(),
        from_bytes.generating::<3>().unwrap()
    );

    let missing = dir.join("poisson_rs_test_this_file_does_not_exist.safetensors");
    match Model::from_file(&missing) {
        Err(CoreError::NotFound(m)) => assert!(m.contains("does_not_exist"), "{m}"),
        other => panic!("expected NotFound, got {other:?}"),
    }
    // A directory is an I/O error, not a format error and not a panic.
    match Model::from_file(&dir) {
        Err(CoreError::Io(_)) => {}
        other => panic!("expected Io for a directory, got {other:?}"),
    }
}

#[test]
fn model_rejects_empty_and_truncated_bytes() {
    expect_format_error(&[], "not a readable safetensors file", "empty bytes");
    let bytes = valid_bytes();
    assert!(Model::from_bytes(&bytes).is_ok());
    for len in 0..bytes.len() {
        expect_format_error(
            &bytes[..len],
            "not a readable safetensors file",
            &format!("prefix of {len} of {} bytes", bytes.len()),
        );
    }
    // Trailing garbage is refused too.
    let mut longer = bytes.clone();
    longer.extend_from_slice(&[0; 8]);
    expect_format_error(
        &longer,
        "not a readable safetensors file",
        "8 trailing bytes",
    );
}

/// Random byte changes in the header (and its length prefix) never panic: the result is either a
/// model or a format error.
#[test]
fn model_survives_random_header_corruption() {
    let bytes = valid_bytes();
    let header_len = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let mut rng = Rng::new(0x5EED_0050);
    let (mut n_ok, mut n_err) = (0, 0);
    for trial in 0..3000 {
        let mut b = bytes.clone();
        let n_flips = 1 + rng.below(3);
        for _ in 0..n_flips {
            let at = rng.below(8 + header_len);
            if rng.below(2) == 0 {
                b[at] ^= 1 << rng.below(8);
            } else {
                b[at] = rng.below(256) as u8;
            }
        }
        match catch_unwind(AssertUnwindSafe(|| Model::from_bytes(&b))) {
            Ok(Ok(_)) => n_ok += 1,
            Ok(Err(CoreError::Format(m))) => {
                assert!(!m.is_empty());
                n_err += 1
            }
            Ok(Err(e)) => panic!("trial {trial}: expected Format, got {e:?}"),
            Err(_) => panic!("trial {trial}: Model::from_bytes panicked"),
        }
    }
    // Most corruptions are caught; a few (a digit of a metadata value) still load.
    eprintln!("header corruption: {n_ok} loaded, {n_err} refused");
    assert!(n_err > 2000, "{n_ok} loaded, {n_err} refused");
}

#[test]
fn model_rejects_bad_metadata() {
    let (gf, tensors, meta) = valid_model(0x5EED_0060);
    let with = |edit: &dyn Fn(&mut HashMap<String, String>)| {
        let mut m = meta.clone();
        edit(&mut m);
        serialize_tensors(&tensors, Some(m))
    };
    expect_format_error(
        &serialize_tensors(&tensors, None),
        "no metadata",
        "no metadata",
    );
    expect_format_error(
        &with(&|m| {
            m.remove("format");
        }),
        "'format' is missing",
        "missing format",
    );
    expect_format_error(
        &with(&|m| {
            m.insert("format".into(), "poisson_rs.generating/2".into());
        }),
        "poisson_rs.generating/2",
        "wrong format",
    );
    expect_format_error(
        &with(&|m| {
            m.insert("format".into(), "".into());
        }),
        "format",
        "empty format",
    );
    expect_format_error(
        &with(&|m| {
            m.remove("chart");
        }),
        "'chart' is missing",
        "missing chart",
    );
    expect_format_error(
        &with(&|m| {
            m.insert("chart".into(), "quaternion".into());
        }),
        "unknown chart 'quaternion'",
        "unknown chart",
    );
    expect_format_error(
        &with(&|m| {
            m.insert("chart".into(), "Cayley".into());
        }),
        "unknown chart",
        "chart names are case-sensitive",
    );
    expect_format_error(
        &with(&|m| {
            m.remove("mlp_power");
        }),
        "'mlp_power' is missing",
        "missing mlp_power",
    );
    expect_format_error(
        &with(&|m| {
            m.remove("mlp_inputs");
        }),
        "'mlp_inputs' is missing",
        "missing mlp_inputs",
    );
    expect_format_error(
        &with(&|m| {
            m.insert("mlp_inputs".into(), "polar".into());
        }),
        "unknown mlp_inputs 'polar'",
        "unknown mlp_inputs",
    );
    expect_format_error(
        &with(&|m| {
            m.insert("mlp_power".into(), "0".into());
        }),
        "mlp_power must be at least 1",
        "mlp_power 0",
    );
    for bad in ["-1", "three", "2.5", ""] {
        expect_format_error(
            &with(&|m| {
                m.insert("mlp_power".into(), bad.into());
            }),
            "mlp_power",
            &format!("mlp_power {bad:?}"),
        );
    }
    assert!(
        Model::from_bytes(&with(&|_| {}))
            .unwrap()
            .generating::<3>()
            .unwrap()
            == gf
    );
}

#[test]
fn model_rejects_bad_polynomials() {
    let meta = metadata("cayley", None);
    let poly = |powers: &[i64], coeffs: &[f64]| {
        serialize_tensors(
            &[
                i64_tensor("poly.powers", &[coeffs.len(), 4], powers),
                f64_tensor("poly.coeffs", &[coeffs.len()], coeffs),
            ],
            Some(meta.clone()),
        )
    };
    // Valid to start with.
    assert!(Model::from_bytes(&poly(&[1, 2, 0, 0, 3, 0, 2, 2], &[-0.5, 0.1])).is_ok());
    expect_format_error(
        &poly(&[1, 2, 0, 0, 0, 0, 2, 2], &[-0.5, 0.1]),
        "t-power 0",
        "a t-power-0 term",
    );
    expect_format_error(
        &poly(&[1, 2, 0, 0, 3, 0, 2, 2], &[-0.5, f64::NAN]),
        "not finite",
        "a NaN coefficient",
    );
    expect_format_error(
        &poly(&[1, -2, 0, 0], &[1.0]),
        "exponent -2",
        "a negative exponent",
    );
    expect_format_error(
        &poly(&[1, 2, 0, 1000], &[1.0]),
        "exponent 1000",
        "a huge exponent",
    );
    // Shapes and dtypes.
    expect_format_error(
        &serialize_tensors(
            &[
                i64_tensor("poly.powers", &[2, 3], &[1, 2, 0, 1, 0, 2]),
                f64_tensor("poly.coeffs", &[2], &[1.0, 1.0]),
            ],
            Some(meta.clone()),
        ),
        "needs the tensor algebra.structure_constants",
        "powers of shape (2, 3)",
    );
    expect_format_error(
        &serialize_tensors(
            &[
                i64_tensor("poly.powers", &[1, 4], &[1, 2, 0, 0]),
                f64_tensor("poly.coeffs", &[2], &[1.0, 1.0]),
            ],
            Some(meta.clone()),
        ),
        "poly.coeffs has shape",
        "coeffs longer than powers",
    );
    expect_format_error(
        &serialize_tensors(
            &[
                f64_tensor("poly.powers", &[1, 4], &[1.0, 2.0, 0.0, 0.0]),
                f64_tensor("poly.coeffs", &[1], &[1.0]),
            ],
            Some(meta.clone()),
        ),
        "must be int64",
        "float powers",
    );
    expect_format_error(
        &serialize_tensors(
            &[i64_tensor("poly.powers", &[1, 4], &[1, 2, 0, 0])],
            Some(meta.clone()),
        ),
        "poly.coeffs",
        "coeffs missing",
    );
    expect_format_error(
        &serialize_tensors(
            &[f64_tensor("poly.coeffs", &[1], &[1.0])],
            Some(meta.clone()),
        ),
        "poly.powers",
        "powers missing",
    );
}

#[test]
fn model_rejects_bad_mlps() {
    let meta = metadata("cayley", Some((3, MlpInputs::Plain)));
    let layer = |i: usize, n_out: usize, n_in: usize, v: f64| {
        [
            f64_tensor(
                &format!("mlp.{i}.weight"),
                &[n_out, n_in],
                &vec![v; n_out * n_in],
            ),
            f64_tensor(&format!("mlp.{i}.bias"), &[n_out], &vec![0.1; n_out]),
        ]
    };
    let file = |layers: Vec<[Tensor; 2]>| {
        let t: Vec<Tensor> = layers.into_iter().flatten().collect();
        serialize_tensors(&t, Some(meta.clone()))
    };
    // Valid to start with.
    assert!(Model::from_bytes(&file(vec![layer(0, 8, 4, 0.1), layer(1, 1, 8, 0.1)])).is_ok());

    // A NaN (or infinite) weight.
    let mut l0 = layer(0, 8, 4, 0.1);
    let mut w = vec![0.1; 32];
    w[17] = f64::NAN;
    l0[0] = f64_tensor("mlp.0.weight", &[8, 4], &w);
    expect_format_error(
        &file(vec![l0.clone(), layer(1, 1, 8, 0.1)]),
        "NaN",
        "a NaN weight",
    );
    w[17] = f64::NEG_INFINITY;
    l0[0] = f64_tensor("mlp.0.weight", &[8, 4], &w);
    expect_format_error(
        &file(vec![l0, layer(1, 1, 8, 0.1)]),
        "infinite",
        "an infinite weight",
    );
    let mut l1 = layer(1, 1, 8, 0.1);
    l1[1] = f64_tensor("mlp.1.bias", &[1], &[f64::NAN]);
    expect_format_error(&file(vec![layer(0, 8, 4, 0.1), l1]), "NaN", "a NaN bias");

    // An F32 weight tensor.
    let mut l0 = layer(0, 8, 4, 0.1);
    l0[0] = f32_tensor("mlp.0.weight", &[8, 4], &[0.1; 32]);
    expect_format_error(
        &file(vec![l0, layer(1, 1, 8, 0.1)]),
        "must be float64",
        "an F32 weight",
    );

    // Mismatched layer shapes.
    expect_format_error(
        &file(vec![layer(0, 8, 4, 0.1), layer(1, 1, 5, 0.1)]),
        "layer 0 has 8 outputs but layer 1 takes 5 inputs",
        "mismatched layers",
    );
    let mut l0 = layer(0, 8, 4, 0.1);
    l0[1] = f64_tensor("mlp.0.bias", &[7], &[0.0; 7]);
    expect_format_error(
        &file(vec![l0, layer(1, 1, 8, 0.1)]),
        "do not match",
        "bias of the wrong length",
    );
    let mut l0 = layer(0, 8, 4, 0.1);
    l0[0] = f64_tensor("mlp.0.weight", &[32], &[0.1; 32]);
    expect_format_error(
        &file(vec![l0, layer(1, 1, 8, 0.1)]),
        "do not match",
        "a 1-d weight",
    );

    // First layer not taking 4 inputs; last layer not 1 output.
    expect_format_error(
        &file(vec![layer(0, 8, 3, 0.1), layer(1, 1, 8, 0.1)]),
        "needs the tensor algebra.structure_constants",
        "first layer with 3 inputs",
    );
    expect_format_error(
        &file(vec![layer(0, 8, 4, 0.1), layer(1, 2, 8, 0.1)]),
        "must have 1 output",
        "last layer with 2 outputs",
    );
    // A missing layer in the middle, a missing bias.
    expect_format_error(
        &file(vec![layer(0, 8, 4, 0.1), layer(2, 1, 8, 0.1)]),
        "mlp.1.weight",
        "layer 1 missing",
    );
    let l0 = layer(0, 1, 4, 0.1);
    expect_format_error(
        &serialize_tensors(&[l0[0].clone()], Some(meta.clone())),
        "mlp.0.bias",
        "bias missing",
    );

    // An unexpected tensor, and no tensors at all.
    let mut t: Vec<Tensor> = [layer(0, 8, 4, 0.1), layer(1, 1, 8, 0.1)]
        .into_iter()
        .flatten()
        .collect();
    t.push(f64_tensor("optimizer.state", &[2], &[0.0, 1.0]));
    expect_format_error(
        &serialize_tensors(&t, Some(meta.clone())),
        "unexpected tensor 'optimizer.state'",
        "an unexpected tensor",
    );
    let mut t: Vec<Tensor> = layer(0, 1, 4, 0.1).to_vec();
    t.push(f64_tensor("mlp.0.scale", &[1], &[1.0]));
    expect_format_error(
        &serialize_tensors(&t, Some(meta.clone())),
        "unexpected tensor 'mlp.0.scale'",
        "mlp.0.scale",
    );
    expect_format_error(
        &serialize_tensors(&[], Some(meta.clone())),
        "neither polynomial terms nor an MLP",
        "no tensors",
    );
}

/// A tensor whose layer index is usize::MAX must be a format error, not an arithmetic overflow
/// (`n_layers.max(i + 1)` in model.rs panics in debug builds and wraps to 0 in release builds,
/// where the tensor is then silently ignored).
#[test]
fn model_rejects_absurd_layer_index() {
    let meta = metadata("cayley", Some((3, MlpInputs::Plain)));
    let mut t = polynomial_tensors(&Polynomial { terms: minus_t_h() });
    t.push(f64_tensor(
        &format!("mlp.{}.weight", usize::MAX),
        &[1],
        &[1.0],
    ));
    expect_format_error(
        &serialize_tensors(&t, Some(meta.clone())),
        "mlp",
        "layer index usize::MAX",
    );
}

/// Layer names must be spelled canonically: `mlp.+0.weight` or `mlp.00.bias` beside a valid
/// `mlp.0.weight` are extra tensors the loader would otherwise ignore (`usize::from_str` accepts
/// a leading `+` and leading zeros).
#[test]
fn model_rejects_non_canonical_layer_names() {
    let meta = metadata("cayley", Some((3, MlpInputs::Plain)));
    for alias in ["mlp.+0.weight", "mlp.00.bias"] {
        let mut rng = Rng::new(0x5EED_0070);
        let mlp = random_mlp(&mut rng, 4, 1.0);
        let mut t = mlp_tensors(&mlp);
        t.push(f64_tensor(alias, &[1], &[1.0]));
        expect_format_error(&serialize_tensors(&t, Some(meta.clone())), alias, alias);
    }
}

/// mlp_power above i32::MAX is cast to a negative exponent in `t.powi(m as i32)`: it must be
/// refused or evaluate correctly (t^m → 0 for t < 1), never silently produce inf.
#[test]
fn model_huge_mlp_power_is_refused_or_correct() {
    let mut rng = Rng::new(0x5EED_0071);
    let mlp = random_mlp(&mut rng, 4, 1.0);
    let mut t = polynomial_tensors(&Polynomial { terms: minus_t_h() });
    t.extend(mlp_tensors(&mlp));
    let bytes = serialize_tensors(
        &t,
        Some(metadata("cayley", Some((3_000_000_000, MlpInputs::Plain)))),
    );
    match Model::from_bytes(&bytes) {
        Err(CoreError::Format(m)) => assert!(m.contains("mlp_power"), "{m}"),
        Ok(model) => {
            let mut ws = model.generating::<3>().unwrap().workspace();
            let p = [1.0, 1.0, 2.0];
            let jet = model.generating::<3>().unwrap().jet(0.5, &p, &mut ws);
            let (v, dt) = model
                .generating::<3>()
                .unwrap()
                .value_and_time_derivative(0.5, &p, &mut ws);
            assert!(
                jet.is_finite() && v.is_finite() && dt.is_finite(),
                "jet {jet:?} v {v} dt {dt}"
            );
        }
        Err(e) => panic!("expected Format, got {e:?}"),
    }
}

// ---------------------------------------------------------------------------------------------
// 5. The exponential chart against an independent implementation
// ---------------------------------------------------------------------------------------------

type M3 = [[f64; 3]; 3];

fn hat(v: &[f64; 3]) -> M3 {
    [[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]]
}

fn matmul(a: &M3, b: &M3) -> M3 {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
}

/// dexpinv(x) = I − ½ x̂ + c(θ) x̂², c = (1 − (θ/2) cot(θ/2)) / θ², closed form only.
fn dexpinv(x: &[f64; 3]) -> M3 {
    let th = norm(x);
    let c = (1.0 - 0.5 * th / (0.5 * th).tan()) / (th * th);
    let xh = hat(x);
    let xh2 = matmul(&xh, &xh);
    std::array::from_fn(|i| {
        std::array::from_fn(|j| (if i == j { 1.0 } else { 0.0 }) - 0.5 * xh[i][j] + c * xh2[i][j])
    })
}

/// Mᵀ p.
fn transpose_apply(m: &M3, p: &[f64; 3]) -> [f64; 3] {
    std::array::from_fn(|j| (0..3).map(|i| m[i][j] * p[i]).sum())
}

#[test]
fn exp_chart_matches_dexpinv_matrix_form() {
    let mut rng = Rng::new(0x5EED_0080);
    let mut radii: Vec<f64> = vec![
        0.05,
        0.1001,
        0.5,
        0.999,
        1.0,
        1.001,
        std::f64::consts::PI,
        6.0,
    ];
    for _ in 0..10 {
        radii.push(rng.range(0.1, 1.0));
        radii.push(rng.range(1.0, 6.0));
    }
    for &r in &radii {
        let x = rng.sphere(r);
        let p = rng.vec3(-3.0, 3.0);
        let sou_ref = transpose_apply(&dexpinv(&x), &p);
        let tar_ref = transpose_apply(&dexpinv(&x.map(|v| -v)), &p);
        let sou = Chart::Exp.sou(&x, &p).unwrap();
        let tar = Chart::Exp.tar(&x, &p).unwrap();
        // The closed form for c loses ~eps/θ² relative near 0, but its term is θ² small, so the
        // sizes of the terms set the scale.
        let scale = norm(&p) * (1.0 + r * r * (1.0 + 1.0 / (2.0 * std::f64::consts::PI - r)));
        let tol = 1e-14 * scale;
        let (es, et) = (norm(&sub(&sou, &sou_ref)), norm(&sub(&tar, &tar_ref)));
        assert!(
            es <= tol,
            "|x| = {r}: sou {sou:?} vs {sou_ref:?} (error {es:e}, tol {tol:e})"
        );
        assert!(
            et <= tol,
            "|x| = {r}: tar {tar:?} vs {tar_ref:?} (error {et:e}, tol {tol:e})"
        );
        // |sou| = |tar| (both are rotations of one another).
        assert!((norm(&sou) - norm(&tar)).abs() <= 1e-14 * scale);
    }
    // Near the identity the chart is p ± ½ x×p + x×(x×p)/12 to third order.
    let x = [1e-5, -2e-5, 3e-5];
    let p = [1.0, 2.0, 3.0];
    let xp = cross(&x, &p);
    let xxp = cross(&x, &xp);
    let approx: [f64; 3] = std::array::from_fn(|i| p[i] + 0.5 * xp[i] + xxp[i] / 12.0);
    let sou = Chart::Exp.sou(&x, &p).unwrap();
    assert!(norm(&sub(&sou, &approx)) < 1e-15 * norm(&p));
    // Beyond the guard the chart reports itself singular.
    let x = [0.0, 6.25, 0.0];
    assert_eq!(Chart::Exp.sou(&x, &p), Err(StepFailure::ChartSingular));
    assert_eq!(Chart::Exp.tar(&x, &p), Err(StepFailure::ChartSingular));
}

/// The Cayley chart against its formula written as a matrix: sou = (I + ½ x̂ + ¼ x xᵀ) p.
#[test]
fn cayley_chart_matches_matrix_form() {
    let mut rng = Rng::new(0x5EED_0081);
    for _ in 0..50 {
        let x = rng.vec3(-3.0, 3.0);
        let p = rng.vec3(-3.0, 3.0);
        let xh = hat(&x);
        for sign in [1.0, -1.0] {
            let m: M3 = std::array::from_fn(|i| {
                std::array::from_fn(|j| {
                    (if i == j { 1.0 } else { 0.0 }) + 0.5 * sign * xh[i][j] + 0.25 * x[i] * x[j]
                })
            });
            let want: [f64; 3] = std::array::from_fn(|i| (0..3).map(|j| m[i][j] * p[j]).sum());
            let got = if sign > 0.0 {
                Chart::Cayley.sou(&x, &p).unwrap()
            } else {
                Chart::Cayley.tar(&x, &p).unwrap()
            };
            assert!(norm(&sub(&got, &want)) < 1e-13 * (1.0 + norm(&x)).powi(2) * norm(&p));
        }
    }
}

/// A layer index of 4e9 would make the loader reserve ~256 GB before reading any layer, and the
/// allocation failure would abort the whole process: the index must be refused first.
#[test]
fn model_rejects_huge_layer_index() {
    let meta = metadata("cayley", Some((3, MlpInputs::Plain)));
    let mut t = polynomial_tensors(&Polynomial { terms: minus_t_h() });
    t.push(f64_tensor("mlp.4000000000.weight", &[1], &[1.0]));
    expect_format_error(&serialize_tensors(&t, Some(meta)), "mlp", "layer index 4e9");
}

// ---------------------------------------------------------------------------------------------
// 6. Segmented rollouts and a property-based fuzz of the model loader
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
        Polynomial { terms: minus_t_h() },
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

/// `Model::from_bytes` on arbitrary input either loads or returns `CoreError::Format`; it never
/// panics (proptest turns a panic into a failing, shrunk case). Seeded, so it reproduces.
mod loader_fuzz {
    use proptest::prelude::*;
    use proptest::sample::Index;
    use proptest::test_runner::{Config, RngSeed};

    use super::valid_bytes;
    use crate::error::CoreError;
    use crate::model::Model;

    fn config() -> Config {
        Config {
            cases: 2000,
            failure_persistence: None,
            rng_seed: RngSeed::Fixed(0x5EED_0080),
            ..Config::default()
        }
    }

    /// Ok or a non-empty Format error; anything else (another variant, a panic) fails the case.
    fn check(bytes: &[u8]) -> Result<(), TestCaseError> {
        match Model::from_bytes(bytes) {
            Ok(_) => Ok(()),
            Err(CoreError::Format(m)) if !m.is_empty() => Ok(()),
            Err(e) => Err(TestCaseError::fail(format!("unexpected error {e:?}"))),
        }
    }

    /// One edit of a byte string: overwrite, bit flip, insertion, deletion or truncation.
    #[derive(Clone, Debug)]
    enum Edit {
        Set(Index, u8),
        Flip(Index, u8),
        Insert(Index, Vec<u8>),
        Delete(Index, usize),
        Truncate(Index),
    }

    fn edit() -> impl Strategy<Value = Edit> {
        prop_oneof![
            (any::<Index>(), any::<u8>()).prop_map(|(i, b)| Edit::Set(i, b)),
            (any::<Index>(), 0u8..8).prop_map(|(i, b)| Edit::Flip(i, b)),
            (any::<Index>(), prop::collection::vec(any::<u8>(), 1..16))
                .prop_map(|(i, v)| Edit::Insert(i, v)),
            (any::<Index>(), 1usize..64).prop_map(|(i, n)| Edit::Delete(i, n)),
            any::<Index>().prop_map(Edit::Truncate),
        ]
    }

    fn apply(bytes: &mut Vec<u8>, e: &Edit) {
        if bytes.is_empty() {
            return;
        }
        match e {
            Edit::Set(i, b) => {
                let at = i.index(bytes.len());
                bytes[at] = *b;
            }
            Edit::Flip(i, bit) => {
                let at = i.index(bytes.len());
                bytes[at] ^= 1 << bit;
            }
            Edit::Insert(i, v) => {
                let at = i.index(bytes.len() + 1);
                bytes.splice(at..at, v.iter().copied());
            }
            Edit::Delete(i, n) => {
                let at = i.index(bytes.len());
                let end = (at + n).min(bytes.len());
                bytes.drain(at..end);
            }
            Edit::Truncate(i) => {
                let at = i.index(bytes.len());
                bytes.truncate(at);
            }
        }
    }

    proptest! {
        #![proptest_config(config())]

        #[test]
        fn random_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..600)) {
            check(&bytes)?;
        }

        /// Random bytes behind a plausible header length, so the parser gets past the prefix.
        #[test]
        fn random_headers_never_panic(body in prop::collection::vec(any::<u8>(), 0..600),
                                      len in 0u64..700) {
            let mut bytes = len.to_le_bytes().to_vec();
            bytes.extend(body);
            check(&bytes)?;
        }

        /// 1–8 random edits anywhere in a valid file (header, metadata, tensor data).
        #[test]
        fn mutated_valid_files_never_panic(edits in prop::collection::vec(edit(), 1..8)) {
            let mut bytes = valid_bytes();
            for e in &edits {
                apply(&mut bytes, e);
            }
            check(&bytes)?;
        }
    }
}

// ---------------------------------------------------------------------------------------------
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
        Polynomial { terms: minus_t_h() },
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

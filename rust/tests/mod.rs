//! Crate-level tests of the core, by subject: exact derivatives ([`derivatives`]), single steps
//! ([`steps`]), rollouts ([`rollouts`]), model files ([`model_files`]), the so(3) charts against
//! their matrix forms ([`charts`]), the batched kernel ([`batched`]) and Lie–Poisson systems of
//! other dimensions ([`lie_poisson`]). This module holds the shared helpers.
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
use crate::model::{Model, FORMAT};
use crate::rollout::{n_records, rollout, TrajectoryInfo};
use crate::stepper::{BisectionStepper, NewtonOptions, StepMap, StepStats};
use crate::structures::lie_groupoid::{Chart, Groupoid};

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

/// Equal bit for bit (any NaN equals any NaN).
fn same_bits(a: &[f64], b: &[f64]) -> bool {
    a.len() == b.len()
        && a.iter()
            .zip(b)
            .all(|(x, y)| x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan()))
}

/// Every instruction set this CPU runs: the portable path, and the detected one if wider.
/// One row (opcode, a, b, c) of an expression's table, as the bindings receive it.
type TapeRow = (i64, i64, i64, f64);

/// The opcode of `name` in an expression's table ([`crate::expression::OPCODES`]).
fn opcode(name: &str) -> i64 {
    crate::expression::OPCODES
        .iter()
        .position(|&n| n == name)
        .expect("an opcode") as i64
}

/// The program of `rows` in `vars` variables with these outputs (None: one output, the last
/// row, as a Hamiltonian).
fn tape(vars: usize, rows: &[TapeRow], outputs: Option<&[i64]>) -> crate::expression::Expression {
    let column = |f: fn(&TapeRow) -> i64| rows.iter().map(f).collect::<Vec<_>>();
    let (code, a, b) = (column(|t| t.0), column(|t| t.1), column(|t| t.2));
    let c: Vec<f64> = rows.iter().map(|t| t.3).collect();
    match outputs {
        None => crate::expression::Expression::from_table(vars, &code, &a, &b, &c),
        Some(o) => crate::expression::Expression::program(vars, &code, &a, &b, &c, o),
    }
    .unwrap()
}

fn isas() -> Vec<crate::lanes::Isa> {
    use crate::lanes::Isa;
    // Every path this CPU runs: the baseline, AVX2 and AVX-512 where detected.
    let mut v = vec![Isa::PORTABLE];
    v.extend(Isa::avx2());
    v.extend(Isa::avx512());
    v
}

/// A tight Newton cap must split a batch: some trajectories stop at it (NotConverged) while
/// others converge, so the lane-wide solve is checked on both outcomes at once.
fn assert_some_capped_some_converged(info: &[TrajectoryInfo]) {
    let capped = info
        .iter()
        .filter(|i| i.failure == Some(StepFailure::NotConverged))
        .count();
    let fine = info.iter().filter(|i| i.converged).count();
    assert!(capped > 0 && fine > 0, "capped {capped}, converged {fine}");
}

fn dot(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// A Newton start's distances to the solved p at the steps hs[0] > hs[1] (`second`) fall at
/// least as h³ (the slope fitted between them ≥ 2.8), the first-order start's (`first`) as h²
/// (1.7–2.6).
fn assert_start_orders(hs: [f64; 2], second: [f64; 2], first: [f64; 2], label: &str) {
    let slope = |e: [f64; 2]| (e[0] / e[1]).ln() / (hs[0] / hs[1]).ln();
    let (a, b) = (slope(second), slope(first));
    assert!(a >= 2.8, "{label}: second-order start: slope {a}");
    assert!(
        (1.7..=2.6).contains(&b),
        "{label}: first-order start: slope {b}"
    );
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
    let s3: [([u32; 3], f64); 6] = [
        ([4, 0, 0], -2.0 / 81.0),
        ([2, 2, 0], -71.0 / 2160.0),
        ([2, 0, 2], -17.0 / 675.0),
        ([0, 4, 0], -1.0 / 96.0),
        ([0, 2, 2], -11.0 / 720.0),
        ([0, 0, 4], -2.0 / 375.0),
    ];
    with_t3(minus_t_h(), &s3)
}

/// The exponential chart's Taylor K = 3 for I = (1.5, 2, 2.5): −t H and t³ S₃ (S₃ as Python's
/// `system_taylor_terms` gives it).
fn taylor3_exp() -> Vec<Monomial<3>> {
    let s3: [([u32; 3], f64); 3] = [
        ([0, 2, 2], -1.0 / 3600.0),
        ([2, 0, 2], -1.0 / 675.0),
        ([2, 2, 0], -1.0 / 2160.0),
    ];
    with_t3(minus_t_h(), &s3)
}

/// `terms` and a t³ term c·pᵉ for each (e, c) of `s3`.
fn with_t3(mut terms: Vec<Monomial<3>>, s3: &[([u32; 3], f64)]) -> Vec<Monomial<3>> {
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
    GeneratingFunction::new(Polynomial::new(terms).unwrap(), Some(mlp), m, inputs).unwrap()
}

/// Like [`random_generating`] with two hidden layers of 40: wide enough for the batched path.
fn wide_generating(rng: &mut Rng, inputs: MlpInputs) -> GeneratingFunction<3> {
    let mlp = mlp_with_widths(rng, &[4, 40, 40, 1], 1.0);
    let mut terms = minus_t_h();
    terms.extend(random_terms(rng, 4, (2, 4), 3, 0.02));
    GeneratingFunction::new(Polynomial::new(terms).unwrap(), Some(mlp), 3, inputs).unwrap()
}

fn stepper(generating: GeneratingFunction<3>, chart: Chart) -> BisectionStepper<3> {
    BisectionStepper::new(
        generating,
        Groupoid::so3(chart).unwrap(),
        NewtonOptions::default(),
    )
}

fn hamiltonian_stepper(chart: Chart) -> BisectionStepper<3> {
    let gf = GeneratingFunction::new(
        Polynomial::new(minus_t_h()).unwrap(),
        None,
        0,
        MlpInputs::Plain,
    )
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

mod batched;
mod bisection_lanes;
mod charts;
mod derivatives;
mod exp_chart_lanes;
mod expression_field;
mod lanes;
mod layout;
mod lie_poisson;
mod log_canonical;
mod model_files;
mod network_lanes;
mod point_vortices;
mod polynomial;
mod rollouts;
mod se3_lanes;
mod series_lanes;
mod splitting_lanes;
mod steps;

//! Generating functions S(t, p) = P(t, p) + t^m · N(t, p).
//!
//! P is a sparse polynomial (exact Taylor terms, or −tH) and N a tanh MLP with inputs (t, p),
//! p ∈ R^N for a Lie algebra of dimension N (a const generic: N = 3 for the rigid body, 6 for the
//! heavy top). A step only needs ∂S/∂p and ∂²S/∂p² at fixed t = h; both come out of one
//! forward-mode pass.

// Index loops over small fixed-size vectors and matrices read as the formulas they implement.
#![allow(clippy::needless_range_loop)]

use crate::dual::{Dual1, Jet2, Scalar, Variable};
use crate::error::CoreError;
use crate::kernel::{self, madd};
use crate::lanes::Isa;
use crate::lanes_bisection;
use crate::memory::{try_collect, try_filled};
use std::sync::Arc;

/// Most trajectories one batched evaluation takes.
pub const MAX_BATCH: usize = 32;

/// Batches of at most this many momenta take per-call scratch arrays sized for it rather than
/// for [`MAX_BATCH`] (a rollout of one state steps through the batched path too).
const FEW: usize = 4;

/// One monomial c · t^k p₁^e₁ ⋯ p_N^e_N.
#[derive(Clone, Debug, PartialEq)]
pub struct Monomial<const N: usize> {
    pub t_power: u32,
    pub p_powers: [u32; N],
    pub coeff: f64,
}

/// A sparse polynomial in (t, p).
#[derive(Clone, Debug, PartialEq)]
pub struct Polynomial<const N: usize> {
    pub terms: Vec<Monomial<N>>,
}

impl<const N: usize> Default for Polynomial<N> {
    fn default() -> Self {
        Polynomial { terms: Vec::new() }
    }
}

/// Exponents up to this are read from a table of powers built by repeated multiplication (one
/// multiply per entry, shared by every term); higher ones (a model file allows 64) use `powi`.
pub(crate) const TABLE_POWER: usize = 8;

/// A table of x⁰ … x^[`TABLE_POWER`].
type PowerTable = [f64; TABLE_POWER + 1];

/// Fills `pw` with x⁰ … x^max by repeated multiplication (max capped at [`TABLE_POWER`]).
#[inline(always)]
fn power_table(x: f64, max: u32, pw: &mut PowerTable) {
    pw[0] = 1.0;
    for k in 1..=(max as usize).min(TABLE_POWER) {
        pw[k] = pw[k - 1] * x;
    }
}

/// (xⁿ, n xⁿ⁻¹, n(n−1) xⁿ⁻²) without negative powers, from the table `pw` of x's powers.
#[inline(always)]
fn power_jet(x: f64, pw: &PowerTable, n: u32) -> [f64; 3] {
    match n {
        0 => [1.0, 0.0, 0.0],
        1 => [x, 1.0, 0.0],
        _ if n as usize <= TABLE_POWER => {
            let (k, nf) = (n as usize, n as f64);
            [pw[k], nf * pw[k - 1], nf * (nf - 1.0) * pw[k - 2]]
        }
        _ => {
            let xn2 = x.powi(n as i32 - 2);
            let nf = n as f64;
            [xn2 * x * x, nf * xn2 * x, nf * (nf - 1.0) * xn2]
        }
    }
}

impl<const N: usize> Polynomial<N> {
    /// Fills the tables of powers of t and of each p_i, up to the largest exponent of any term.
    #[inline(always)]
    fn powers(&self, t: f64, p: &[f64; N], tp: &mut PowerTable, pp: &mut [PowerTable; N]) {
        let (mut tmax, mut pmax) = (0u32, [0u32; N]);
        for m in &self.terms {
            tmax = tmax.max(m.t_power);
            for i in 0..N {
                pmax[i] = pmax[i].max(m.p_powers[i]);
            }
        }
        power_table(t, tmax, tp);
        for i in 0..N {
            power_table(p[i], pmax[i], &mut pp[i]);
        }
    }

    /// The coefficient times t^k of one term, and the jets (xⁿ, n xⁿ⁻¹, n(n−1) xⁿ⁻²) of its
    /// factors.
    #[inline(always)]
    fn term_factors(
        m: &Monomial<N>,
        t: f64,
        p: &[f64; N],
        tp: &PowerTable,
        pp: &[PowerTable; N],
    ) -> (f64, [[f64; 3]; N]) {
        let tk = if m.t_power as usize <= TABLE_POWER {
            tp[m.t_power as usize]
        } else {
            t.powi(m.t_power as i32)
        };
        let mut j = [[0.0; 3]; N];
        for i in 0..N {
            j[i] = power_jet(p[i], &pp[i], m.p_powers[i]);
        }
        (m.coeff * tk, j)
    }

    /// P(t, ·) with its p-gradient and p-Hessian, in closed form.
    pub fn jet(&self, t: f64, p: &[f64; N]) -> Jet2<N> {
        let mut out = Jet2::<N>::default();
        let (mut tp, mut pp) = ([0.0; TABLE_POWER + 1], [[0.0; TABLE_POWER + 1]; N]);
        self.powers(t, p, &mut tp, &mut pp);
        for m in &self.terms {
            let (c, j) = Self::term_factors(m, t, p, &tp, &pp);
            // ∂/∂p_i picks the derivative factor of variable i, the value of the others.
            let factor = |d: [usize; N]| {
                let mut f = c;
                for i in 0..N {
                    f *= j[i][d[i]];
                }
                f
            };
            out.v += factor([0; N]);
            for i in 0..N {
                let mut d = [0; N];
                d[i] = 1;
                out.g[i] += factor(d);
            }
            let packed = out.packed_mut();
            let mut k = 0;
            for a in 0..N {
                for b in a..N {
                    let mut d = [0; N];
                    d[a] += 1;
                    d[b] += 1;
                    packed[k] += factor(d);
                    k += 1;
                }
            }
        }
        out
    }

    /// P(t, ·) and its p-gradient only: the value and gradient of [`Polynomial::jet`] bit for
    /// bit (the same products summed in the same order), without the Hessian's sums.
    pub fn gradient(&self, t: f64, p: &[f64; N]) -> Dual1<N> {
        let mut out = Dual1::<N>::default();
        let (mut tp, mut pp) = ([0.0; TABLE_POWER + 1], [[0.0; TABLE_POWER + 1]; N]);
        self.powers(t, p, &mut tp, &mut pp);
        for m in &self.terms {
            let (c, j) = Self::term_factors(m, t, p, &tp, &pp);
            let factor = |d: [usize; N]| {
                let mut f = c;
                for i in 0..N {
                    f *= j[i][d[i]];
                }
                f
            };
            out.v += factor([0; N]);
            for i in 0..N {
                let mut d = [0; N];
                d[i] = 1;
                out.g[i] += factor(d);
            }
        }
        out
    }

    /// P(t, p) and ∂P/∂t.
    pub fn value_and_time_derivative(&self, t: f64, p: &[f64; N]) -> (f64, f64) {
        let (mut v, mut dt) = (0.0, 0.0);
        for m in &self.terms {
            let mut pp = 1.0;
            for i in 0..N {
                pp *= p[i].powi(m.p_powers[i] as i32);
            }
            v += m.coeff * t.powi(m.t_power as i32) * pp;
            if m.t_power > 0 {
                dt += m.coeff * m.t_power as f64 * t.powi(m.t_power as i32 - 1) * pp;
            }
        }
        (v, dt)
    }
}

/// A dense layer y = W x + b, W row-major of shape (out, in).
#[derive(Clone, Debug, PartialEq)]
pub struct Layer {
    pub n_in: usize,
    pub n_out: usize,
    pub weight: Vec<f64>,
    pub bias: Vec<f64>,
    /// W and Wᵀ in the batched kernel's panel layout ([`kernel::pack`]).
    packed: Vec<f64>,
    packed_t: Vec<f64>,
    /// Wᵀ row-major (`n_in × n_out`), for [`narrow_gemm`] in the reverse pass.
    weight_t: Vec<f64>,
}

impl Layer {
    pub fn new(
        n_in: usize,
        n_out: usize,
        weight: Vec<f64>,
        bias: Vec<f64>,
    ) -> Result<Self, CoreError> {
        if n_in == 0 || n_out == 0 {
            return Err(CoreError::Format(format!(
                "a layer of shape ({n_out}, {n_in}) has zero width"
            )));
        }
        if weight.len() != n_in * n_out || bias.len() != n_out {
            return Err(CoreError::Format(format!(
                "layer of shape ({n_out}, {n_in}) needs {} weights and {n_out} biases, got {} and {}",
                n_in * n_out,
                weight.len(),
                bias.len()
            )));
        }
        if weight.iter().chain(&bias).any(|w| !w.is_finite()) {
            return Err(CoreError::Format(
                "a layer holds a NaN or infinite weight".into(),
            ));
        }
        // Two packed copies of W: allocated fallibly, since the width comes from a file.
        let packed = kernel::try_pack(&weight, n_in, n_out)?;
        let transposed = try_collect(
            n_in * n_out,
            (0..n_in * n_out).map(|i| weight[(i % n_out) * n_in + i / n_out]),
            "a transposed layer",
        )?;
        let packed_t = kernel::try_pack(&transposed, n_out, n_in)?;
        Ok(Layer {
            n_in,
            n_out,
            weight,
            bias,
            packed,
            packed_t,
            weight_t: transposed,
        })
    }

    /// z = W x + b for a batch: `x` holds `n_in` rows and `z` `n_out` rows of `K·n` columns
    /// (component-major); the bias enters the value columns `0..n` only.
    fn forward_batch(&self, x: &[f64], n: usize, k: usize, z: &mut [f64]) {
        let cols = k * n;
        self.product(x, cols, z);
        for (row, &b) in z.chunks_exact_mut(cols).zip(&self.bias) {
            for v in &mut row[..n] {
                *v += b;
            }
        }
    }

    /// z = W x for `cols` columns: [`narrow_gemm`] for a narrow layer, else [`kernel::gemm`]
    /// (the same bits either way).
    #[inline]
    fn product(&self, x: &[f64], cols: usize, z: &mut [f64]) {
        if self.n_out <= NARROW_ROWS && self.n_in <= NARROW_INPUTS {
            narrow_gemm(&self.weight, self.n_in, self.n_out, x, cols, z);
        } else {
            kernel::gemm(&self.packed, self.n_in, self.n_out, x, cols, z);
        }
    }

    /// g = Wᵀ δ for `cols` columns, as [`Self::product`] chooses.
    #[inline]
    fn product_t(&self, delta: &[f64], cols: usize, g: &mut [f64]) {
        if self.n_in <= NARROW_ROWS && self.n_out <= NARROW_INPUTS {
            narrow_gemm(&self.weight_t, self.n_out, self.n_in, delta, cols, g);
        } else {
            kernel::gemm(&self.packed_t, self.n_out, self.n_in, delta, cols, g);
        }
    }

    /// out = W x + b, with `x` and `out` of any [`Scalar`].
    #[inline]
    fn forward<T: Scalar>(&self, x: &[T], out: &mut [T]) {
        for (o, (row, &b)) in out
            .iter_mut()
            .zip(self.weight.chunks_exact(self.n_in).zip(&self.bias))
        {
            *o = T::cst(b);
            for (xi, &w) in x.iter().zip(row) {
                o.add_scaled(xi, w);
            }
        }
    }
}

/// Layers with at most this many outputs (and [`NARROW_INPUTS`] inputs) take [`narrow_gemm`]:
/// the panel kernel computes [`kernel::MR`] = 6 rows a block, so a layer of 8 outputs paid for
/// 12 and the output layer (1) for 6.
const NARROW_ROWS: usize = 16;
/// Inputs of a narrow layer: its block of accumulators stays in registers over the whole sum.
const NARROW_INPUTS: usize = 64;

/// z = W·x for a narrow layer, W row-major (`n_out × n_in`), `x` (`n_in × cols`) and `z`
/// (`n_out × cols`) row-major: blocks of up to 4 rows by 8 columns, and no padded rows.
///
/// Every element is the chain of multiply-adds of [`kernel::gemm`] (from 0, over k = 0, 1, …,
/// n_in − 1, fused where the CPU has FMA), so the two kernels give the same bits: the choice
/// between them never changes a trajectory (tested).
pub(crate) fn narrow_gemm(
    weight: &[f64],
    n_in: usize,
    n_out: usize,
    x: &[f64],
    cols: usize,
    z: &mut [f64],
) {
    #[cfg(target_arch = "x86_64")]
    if kernel::uses_fma() {
        // SAFETY: the CPU has the features `narrow_gemm_fma` is compiled for.
        unsafe { narrow_gemm_fma(weight, n_in, n_out, x, cols, z) };
        return;
    }
    narrow_gemm_body::<false>(weight, n_in, n_out, x, cols, z);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn narrow_gemm_fma(
    weight: &[f64],
    n_in: usize,
    n_out: usize,
    x: &[f64],
    cols: usize,
    z: &mut [f64],
) {
    narrow_gemm_body::<true>(weight, n_in, n_out, x, cols, z);
}

#[inline(always)]
fn narrow_gemm_body<const FMA: bool>(
    weight: &[f64],
    n_in: usize,
    n_out: usize,
    x: &[f64],
    cols: usize,
    z: &mut [f64],
) {
    let (weight, x) = (&weight[..n_out * n_in], &x[..n_in * cols]);
    let z = &mut z[..n_out * cols];
    let mut o = 0;
    while o < n_out {
        let rows = (n_out - o).min(4);
        let w = &weight[o * n_in..(o + rows) * n_in];
        let zo = &mut z[o * cols..(o + rows) * cols];
        match rows {
            4 => narrow_rows::<4, FMA>(w, n_in, x, cols, zo),
            3 => narrow_rows::<3, FMA>(w, n_in, x, cols, zo),
            2 => narrow_rows::<2, FMA>(w, n_in, x, cols, zo),
            _ => narrow_rows::<1, FMA>(w, n_in, x, cols, zo),
        }
        o += rows;
    }
}

/// R rows of [`narrow_gemm_body`]: `w` holds them (`R × n_in`), `z` receives them.
#[inline(always)]
fn narrow_rows<const R: usize, const FMA: bool>(
    w: &[f64],
    n_in: usize,
    x: &[f64],
    cols: usize,
    z: &mut [f64],
) {
    const C: usize = 8;
    let mut c = 0;
    while c + C <= cols {
        let mut acc = [[0.0; C]; R];
        for k in 0..n_in {
            let xk: &[f64; C] = x[k * cols + c..k * cols + c + C].try_into().unwrap();
            for r in 0..R {
                let wr = w[r * n_in + k];
                for j in 0..C {
                    acc[r][j] = madd::<FMA>(wr, xk[j], acc[r][j]);
                }
            }
        }
        for (r, a) in acc.iter().enumerate() {
            z[r * cols + c..r * cols + c + C].copy_from_slice(a);
        }
        c += C;
    }
    // The last columns one at a time: the same chain per element.
    while c < cols {
        let mut acc = [0.0; R];
        for k in 0..n_in {
            let xv = x[k * cols + c];
            for r in 0..R {
                acc[r] = madd::<FMA>(w[r * n_in + k], xv, acc[r]);
            }
        }
        for (r, &a) in acc.iter().enumerate() {
            z[r * cols + c] = a;
        }
        c += 1;
    }
}

/// tanh for the batched passes, without a library call: tanh(x) = e/(e + 2) with
/// e = expm1(2x), and expm1 by Cody–Waite reduction 2x = k ln 2 + r, |r| ≤ ln 2 / 2, a degree-13
/// Taylor polynomial for expm1(r) and 2^k from the exponent bits. Branch-free, so a row of
/// trajectories runs in SIMD lanes; libm's tanh, a call per neuron, took 40 % of a step of the
/// default model. Within 4 ulp of libm's tanh (tested); ±1 for |x| ≥ 20, NaN for NaN.
///
/// This is the portable form (plain multiplies and adds); the AVX2 passes run
/// [`tanh_fast_fma`], the same formula with its multiply-adds fused.
#[inline(always)]
pub fn tanh_fast(x: f64) -> f64 {
    tanh_with::<false>(x)
}

/// [`tanh_fast`] with every multiply-add fused (the form the AVX2+FMA passes run: half the
/// instructions of the degree-13 Horner chain). Within 4 ulp of libm's tanh (tested). Like the
/// layer kernel ([`kernel::gemm`]), the form is chosen once per CPU, so a trajectory's bits
/// never depend on its chunk or thread.
#[inline(always)]
pub fn tanh_fast_fma(x: f64) -> f64 {
    tanh_with::<true>(x)
}

#[inline(always)]
fn tanh_with<const FMA: bool>(x: f64) -> f64 {
    // 1.5 · 2^52: adding it rounds to an integer, whose bits land in the mantissa's low bits.
    const SHIFT: f64 = 6755399441055744.0;
    const LOG2E: f64 = std::f64::consts::LOG2_E;
    // ln 2 split so that k · LN2_HI is exact for |k| < 2^11 (fdlibm's constants).
    const LN2_HI: f64 = f64::from_bits(0x3FE6_2E42_FEE0_0000);
    const LN2_LO: f64 = f64::from_bits(0x3DEA_39EF_3579_3C76);
    // 1/n! for n = 13 down to 2.
    const C: [f64; 12] = [
        1.0 / 6227020800.0,
        1.0 / 479001600.0,
        1.0 / 39916800.0,
        1.0 / 3628800.0,
        1.0 / 362880.0,
        1.0 / 40320.0,
        1.0 / 5040.0,
        1.0 / 720.0,
        1.0 / 120.0,
        1.0 / 24.0,
        1.0 / 6.0,
        0.5,
    ];
    // |tanh(x)| rounds to 1 beyond |x| ≈ 19.1; clamping keeps 2^k finite (NaN passes through).
    let y = (2.0 * x).clamp(-40.0, 40.0);
    let shifted = madd::<FMA>(y, LOG2E, SHIFT);
    let k = shifted - SHIFT;
    // k · LN2_HI is exact, so the fused and the plain form agree on the first subtraction.
    let r = madd::<FMA>(-k, LN2_LO, madd::<FMA>(-k, LN2_HI, y));
    let mut q = C[0];
    for c in &C[1..] {
        q = madd::<FMA>(q, r, *c);
    }
    // expm1(r) = r + r² (1/2 + r/6 + …)
    let em = madd::<FMA>(r * r, q, r);
    // 2^k: k + 1023 into the exponent field (the shift drops SHIFT's own exponent bits).
    let s = f64::from_bits(shifted.to_bits().wrapping_add(1023) << 52);
    let e = madd::<FMA>(s, em, s - 1.0);
    e / (e + 2.0)
}

/// [`tanh_fast`] on every element.
#[inline(always)]
fn tanh_slice_body<const FMA: bool>(z: &mut [f64]) {
    for v in z {
        *v = tanh_with::<FMA>(*v);
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn tanh_slice_avx2(z: &mut [f64]) {
    tanh_slice_body::<true>(z);
}

/// [`tanh_fast`] on every element, compiled for `isa` ([`tanh_fast_fma`] on the AVX2+FMA
/// path).
fn tanh_slice(isa: Isa, z: &mut [f64]) {
    #[cfg(target_arch = "x86_64")]
    if isa.is_avx2() {
        // SAFETY: an `Isa` claims AVX2 only where run-time detection found AVX2 and FMA.
        unsafe { tanh_slice_avx2(z) };
        return;
    }
    tanh_slice_body::<false>(z);
}

/// tanh with its chain rule, in place, on `rows` of a batched layer of `comps` components
/// (1 + N: value and gradient; more: value, gradient and packed Hessian), each row holding the
/// components of `n` trajectories component-major (`row[c·n + j]`): the formulas of
/// `Variable::tanh_rows`, with [`tanh_fast`] in place of libm's tanh.
#[inline(always)]
fn tanh_rows_body<const N: usize, const FMA: bool>(
    comps: usize,
    z: &mut [f64],
    rows: usize,
    n: usize,
) {
    let hess = comps > 1 + N;
    // tanh' and tanh'' of the row, reused by every row (each row writes its n first).
    let (mut d1, mut d2) = ([0.0; MAX_BATCH], [0.0; MAX_BATCH]);
    let (d1, d2) = (&mut d1[..n], &mut d2[..n]);
    // Loops over zipped slices, not indices: without bounds checks the row loops run in
    // SIMD lanes (indexed, the Hessian update ran one element at a time). Same formulas, same
    // order, so the same bits.
    for row in z.chunks_exact_mut(comps * n).take(rows) {
        let (v, rest) = row.split_at_mut(n);
        let (g, h) = rest.split_at_mut(N * n);
        for ((vj, d1j), d2j) in v.iter_mut().zip(d1.iter_mut()).zip(d2.iter_mut()) {
            let y = tanh_with::<FMA>(*vj);
            *vj = y;
            *d1j = 1.0 - y * y;
            *d2j = -2.0 * y * *d1j;
        }
        if hess {
            // The Hessian first: it needs the incoming gradient (Jet2::chain's formula).
            let mut hk = h.chunks_exact_mut(n);
            for a in 0..N {
                let ga = &g[a * n..(a + 1) * n];
                for b in a..N {
                    let gb = &g[b * n..(b + 1) * n];
                    let Some(hk) = hk.next() else { return };
                    for ((hj, (&x1, &x2)), (&ua, &ub)) in hk
                        .iter_mut()
                        .zip(d1.iter().zip(d2.iter()))
                        .zip(ga.iter().zip(gb))
                    {
                        *hj = x1 * *hj + x2 * ua * ub;
                    }
                }
            }
        }
        for gi in g.chunks_exact_mut(n) {
            for (gj, &x1) in gi.iter_mut().zip(d1.iter()) {
                *gj *= x1;
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn tanh_rows_avx2<const N: usize>(comps: usize, z: &mut [f64], rows: usize, n: usize) {
    tanh_rows_body::<N, true>(comps, z, rows, n);
}

/// [`tanh_rows_body`] compiled for `isa`.
fn tanh_rows<const N: usize>(isa: Isa, comps: usize, z: &mut [f64], rows: usize, n: usize) {
    assert!(n <= MAX_BATCH, "batch of {n} trajectories");
    #[cfg(target_arch = "x86_64")]
    if isa.is_avx2() {
        // SAFETY: an `Isa` claims AVX2 only where run-time detection found AVX2 and FMA.
        unsafe { tanh_rows_avx2::<N>(comps, z, rows, n) };
        return;
    }
    tanh_rows_body::<N, false>(comps, z, rows, n);
}

/// A tanh MLP R^{1+N} → R with inputs (t, p₁, …, p_N); tanh after every layer but the last.
///
/// The layers are shared: cloning an MLP (a stepper per call, per dimension) copies a pointer,
/// never the weights, so it cannot run out of memory.
#[derive(Clone, Debug, PartialEq)]
pub struct Mlp {
    pub layers: Arc<[Layer]>,
}

impl Mlp {
    /// Checks that consecutive layers fit and that the network has one output; the number of
    /// inputs is checked against the system by [`GeneratingFunction::new`].
    pub fn new(layers: Vec<Layer>) -> Result<Self, CoreError> {
        if layers.is_empty() {
            return Err(CoreError::Format("an MLP needs at least one layer".into()));
        }
        if let Some((i, _)) = layers
            .iter()
            .enumerate()
            .find(|(_, l)| l.n_in == 0 || l.n_out == 0)
        {
            return Err(CoreError::Format(format!("layer {i} has zero width")));
        }
        for (i, w) in layers.windows(2).enumerate() {
            if w[0].n_out != w[1].n_in {
                return Err(CoreError::Format(format!(
                    "layer {i} has {} outputs but layer {} takes {} inputs",
                    w[0].n_out,
                    i + 1,
                    w[1].n_in
                )));
            }
        }
        let last = &layers[layers.len() - 1];
        if last.n_out != 1 {
            return Err(CoreError::Format(format!(
                "the last layer must have 1 output, it has {}",
                last.n_out
            )));
        }
        Ok(Mlp {
            layers: layers.into(),
        })
    }

    /// Inputs of the first layer (1 + N: time and momentum).
    pub fn n_inputs(&self) -> usize {
        self.layers[0].n_in
    }

    /// Widest layer: the size of each workspace buffer.
    pub fn max_width(&self) -> usize {
        self.layers
            .iter()
            .map(|l| l.n_out.max(l.n_in))
            .max()
            .unwrap_or(0)
    }

    pub fn n_parameters(&self) -> usize {
        self.layers
            .iter()
            .map(|l| l.weight.len() + l.bias.len())
            .sum()
    }

    /// N(inputs) for any scalar type; the inputs are `a[..n_inputs]`, and `a` and `b` (each ≥
    /// `max_width`) are scratch.
    fn eval<T: Scalar>(&self, a: &mut [T], b: &mut [T]) -> T {
        let mut width = self.n_inputs();
        let n = self.layers.len();
        let (mut src, mut dst) = (a, b);
        for (i, layer) in self.layers.iter().enumerate() {
            layer.forward(&src[..width], &mut dst[..layer.n_out]);
            width = layer.n_out;
            if i + 1 < n {
                for z in dst[..width].iter_mut() {
                    *z = z.tanh();
                }
            }
            std::mem::swap(&mut src, &mut dst);
        }
        src[0]
    }

    /// N and its gradient with respect to its inputs for `n` trajectories: one pass of values
    /// forward (keeping every layer's activations in `acts`) and one of adjoints back, 4 flops
    /// per weight against forward mode's 2(1+N). Inputs are rows 0..n_inputs of `acts` (`n`
    /// columns); returns the output row, and the input adjoints in rows 0..n_inputs of `a` or `b`.
    fn value_and_input_gradient<'a>(
        &self,
        n: usize,
        acts: &'a mut [f64],
        a: &'a mut [f64],
        b: &'a mut [f64],
    ) -> (&'a [f64], &'a [f64]) {
        let last = self.layers.len() - 1;
        let mut off = 0;
        for (i, layer) in self.layers.iter().enumerate() {
            let (x, z) = acts[off..].split_at_mut(layer.n_in * n);
            layer.forward_batch(x, n, 1, z);
            if i < last {
                tanh_slice(Isa::detect(), &mut z[..layer.n_out * n]);
            }
            off += layer.n_in * n;
        }
        // `off` is now the output row. Adjoints: δ = 1 at the output, g = Wᵀ δ per layer, and
        // δ = g ⊙ tanh' through each hidden activation y (tanh' = 1 − y²).
        let (acts, out) = acts.split_at(off);
        let (mut delta, mut g) = (a, b);
        delta[..n].fill(1.0);
        for (i, layer) in self.layers.iter().enumerate().rev() {
            layer.product_t(delta, n, g);
            off -= layer.n_in * n;
            if i > 0 {
                let y = &acts[off..off + layer.n_in * n];
                for (gv, &yv) in g[..layer.n_in * n].iter_mut().zip(y) {
                    *gv *= 1.0 - yv * yv;
                }
            }
            std::mem::swap(&mut delta, &mut g);
        }
        (&out[..n], &delta[..self.n_inputs() * n])
    }

    /// Rows of activations `value_and_input_gradient` keeps per trajectory: the inputs and
    /// every layer's output.
    fn activation_rows(&self) -> usize {
        self.n_inputs() + self.layers.iter().map(|l| l.n_out).sum::<usize>()
    }

    /// N for `n` trajectories at once. The inputs are rows 0..n_inputs of `a` (`K · n` columns
    /// each, K = `T::COMPONENTS`, component-major); returns the output row, in `a` or `b`.
    fn eval_batch<'a, const N: usize, T: Variable<N>>(
        &self,
        n: usize,
        a: &'a mut [f64],
        b: &'a mut [f64],
    ) -> &'a [f64] {
        let k = T::COMPONENTS;
        let last = self.layers.len() - 1;
        let (mut src, mut dst) = (a, b);
        for (i, layer) in self.layers.iter().enumerate() {
            layer.forward_batch(src, n, k, dst);
            if i < last {
                tanh_rows::<N>(Isa::detect(), T::COMPONENTS, dst, layer.n_out, n);
            }
            std::mem::swap(&mut src, &mut dst);
        }
        &src[..k * n]
    }
}

/// Scratch memory for one evaluation at a time; allocated once per worker, never per step.
#[derive(Clone, Debug)]
pub struct Workspace<const N: usize> {
    jet_a: Vec<Jet2<N>>,
    jet_b: Vec<Jet2<N>>,
    d1_a: Vec<Dual1<N>>,
    d1_b: Vec<Dual1<N>>,
    /// Two (widest layer × COMPONENTS·MAX_BATCH) activation buffers for batched passes.
    batch_a: Vec<f64>,
    batch_b: Vec<f64>,
    /// Every layer's activations for MAX_BATCH trajectories, kept for the reverse pass.
    acts: Vec<f64>,
}

impl<const N: usize> Workspace<N> {
    /// Bytes a workspace for `generating` takes, computed without allocating it (the bindings
    /// check it against the memory available before a rollout creates one per thread).
    pub fn bytes(generating: &GeneratingFunction<N>) -> usize {
        let (singles, batch, acts) = Self::sizes(generating);
        singles
            .saturating_mul(
                2 * std::mem::size_of::<Jet2<N>>() + 2 * std::mem::size_of::<Dual1<N>>(),
            )
            .saturating_add(batch.saturating_mul(16))
            .saturating_add(acts.saturating_mul(8))
    }

    /// Elements of the single-trajectory buffers, of each batch buffer, and of `acts`.
    fn sizes(generating: &GeneratingFunction<N>) -> (usize, usize, usize) {
        let mlp = generating.mlp.as_ref();
        let w = mlp.map_or(0, Mlp::max_width).max(N + 1);
        let batch = if mlp.is_some() {
            w.saturating_mul(<Jet2<N> as Variable<N>>::COMPONENTS)
                .saturating_mul(MAX_BATCH)
        } else {
            0
        };
        let acts = mlp
            .map_or(0, Mlp::activation_rows)
            .saturating_mul(MAX_BATCH);
        (w, batch, acts)
    }
}

/// |p|² below which the homogeneous MLP term is taken as zero: its size is |p|^(m+1) ≤ 1e-100
/// there, while the derivatives of p/|p| (up to |p|⁻³ in the Hessian) would overflow.
pub const HOMOGENEOUS_MIN_R2: f64 = 1e-100;

/// What the MLP sees.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MlpInputs {
    /// N(t, p): the MLP takes (t, p₁, …, p_N) as they are (the paper's ansatz).
    Plain,
    /// |p|^(m+1) · N(|p| t, p/|p|): the scaling S(t, λp) = λ S(λt, p) of every quadratic
    /// Hamiltonian on a Lie–Poisson space is built in, so the MLP only learns a function on
    /// [0, τ_max] × S^{N−1}.
    Homogeneous,
}

impl MlpInputs {
    pub fn name(self) -> &'static str {
        match self {
            MlpInputs::Plain => "t,p",
            MlpInputs::Homogeneous => "homogeneous",
        }
    }

    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            "t,p" => Some(MlpInputs::Plain),
            "homogeneous" => Some(MlpInputs::Homogeneous),
            _ => None,
        }
    }
}

/// The MLP's inputs at one (t, p): the time input, the N momentum inputs and the factor that
/// multiplies the MLP's output.
type Inputs<T, const N: usize> = (T, [T; N], T);

/// S(t, p) = P(t, p) + t^m N(t, p). S(0, ·) = 0 holds by construction (k ≥ 1, m ≥ 1).
#[derive(Clone, Debug, PartialEq)]
pub struct GeneratingFunction<const N: usize> {
    pub polynomial: Polynomial<N>,
    pub mlp: Option<Mlp>,
    pub mlp_power: u32,
    pub inputs: MlpInputs,
}

impl<const N: usize> GeneratingFunction<N> {
    pub fn new(
        polynomial: Polynomial<N>,
        mlp: Option<Mlp>,
        mlp_power: u32,
        inputs: MlpInputs,
    ) -> Result<Self, CoreError> {
        if let Some(m) = polynomial.terms.iter().find(|m| m.t_power == 0) {
            return Err(CoreError::Format(format!(
                "polynomial term with t-power 0 (p-powers {:?}) would break S(0, p) = 0",
                m.p_powers
            )));
        }
        if let Some(m) = polynomial.terms.iter().find(|m| !m.coeff.is_finite()) {
            return Err(CoreError::Format(format!(
                "polynomial coefficient {} is not finite",
                m.coeff
            )));
        }
        if let Some(mlp) = &mlp {
            if mlp.n_inputs() != N + 1 {
                return Err(CoreError::Format(format!(
                    "the first layer must take {} inputs (t and p in R^{N}), it takes {}",
                    N + 1,
                    mlp.n_inputs()
                )));
            }
            if mlp_power == 0 {
                return Err(CoreError::Format(
                    "mlp_power must be at least 1 so that S(0, p) = 0".into(),
                ));
            }
        }
        Ok(GeneratingFunction {
            polynomial,
            mlp,
            mlp_power,
            inputs,
        })
    }

    /// A workspace for this function. Where the memory is refused it unwinds with a
    /// [`crate::memory::OutOfMemory`] payload (which the bindings turn into MemoryError), never
    /// aborts; callers check [`Workspace::bytes`] first or use [`Self::try_workspace`].
    pub fn workspace(&self) -> Workspace<N> {
        self.try_workspace()
            .unwrap_or_else(|e| crate::memory::panic_out_of_memory(&e))
    }

    /// A workspace, or [`CoreError::Memory`] where the memory is refused.
    pub fn try_workspace(&self) -> Result<Workspace<N>, CoreError> {
        let (w, batch, acts) = Workspace::sizes(self);
        let what = "the evaluation workspace (a very wide layer?)";
        Ok(Workspace {
            jet_a: try_filled(w, Jet2::default(), what)?,
            jet_b: try_filled(w, Jet2::default(), what)?,
            d1_a: try_filled(w, Dual1::default(), what)?,
            d1_b: try_filled(w, Dual1::default(), what)?,
            batch_a: try_filled(batch, 0.0, what)?,
            batch_b: try_filled(batch, 0.0, what)?,
            acts: try_filled(acts, 0.0, what)?,
        })
    }

    /// S(t, p), ∂S/∂p and ∂²S/∂p² at fixed t, exactly (forward mode).
    pub fn jet(&self, t: f64, p: &[f64; N], ws: &mut Workspace<N>) -> Jet2<N> {
        self.derivatives(t, p, &mut ws.jet_a, &mut ws.jet_b)
    }

    /// S(t, p) and ∂S/∂p only: the cheaper pass (1 + N components instead of
    /// 1 + N + N(N+1)/2) for when the Hessian is not needed, such as the final evaluation of a
    /// Newton solve.
    pub fn gradient(&self, t: f64, p: &[f64; N], ws: &mut Workspace<N>) -> Dual1<N> {
        self.derivatives(t, p, &mut ws.d1_a, &mut ws.d1_b)
    }

    /// `jet` for up to [`MAX_BATCH`] momenta at once: `out[j]` is the jet at `p[j]`. Each layer
    /// of the MLP is one matrix–matrix product over the batch.
    pub fn jets(&self, t: f64, p: &[[f64; N]], out: &mut [Jet2<N>], ws: &mut Workspace<N>) {
        self.derivatives_batch(t, p, out, ws);
    }

    /// `gradient` for up to [`MAX_BATCH`] momenta at once.
    pub fn gradients(&self, t: f64, p: &[[f64; N]], out: &mut [Dual1<N>], ws: &mut Workspace<N>) {
        self.derivatives_batch(t, p, out, ws);
    }

    /// S and ∂S/∂p for up to [`MAX_BATCH`] momenta, with the MLP differentiated in reverse
    /// mode: fewer flops than [`GeneratingFunction::gradients`], the same numbers to round-off.
    pub fn gradients_reverse(
        &self,
        t: f64,
        p: &[[f64; N]],
        out: &mut [Dual1<N>],
        ws: &mut Workspace<N>,
    ) {
        let n = p.len();
        assert!(n <= MAX_BATCH && out.len() == n, "batch of {n} momenta");
        lanes_bisection::polynomial_gradients(&self.polynomial, Isa::detect(), t, p, out);
        let Some(mlp) = self.mlp.as_ref().filter(|_| n > 0) else {
            return;
        };
        if n <= FEW {
            self.reverse_mlp::<FEW>(mlp, t, p, out, ws);
        } else {
            self.reverse_mlp::<MAX_BATCH>(mlp, t, p, out, ws);
        }
    }

    /// The MLP term of [`Self::gradients_reverse`], added into `out`, with scratch for
    /// `CAP` ≥ `p.len()` momenta (a few momenta do not zero 32 momenta's worth).
    fn reverse_mlp<const CAP: usize>(
        &self,
        mlp: &Mlp,
        t: f64,
        p: &[[f64; N]],
        out: &mut [Dual1<N>],
        ws: &mut Workspace<N>,
    ) {
        let n = p.len();
        let mut inputs: [Option<Inputs<Dual1<N>, N>>; CAP] = [None; CAP];
        for (j, pj) in p.iter().enumerate() {
            inputs[j] = self.mlp_inputs::<Dual1<N>>(t, pj);
            let (t_in, p_in) = inputs[j].map_or((0.0, [0.0; N]), |(a, b, _)| (a.v, b.map(|x| x.v)));
            ws.acts[j] = t_in;
            for i in 0..N {
                ws.acts[(1 + i) * n + j] = p_in[i];
            }
        }
        let (value, adjoint) =
            mlp.value_and_input_gradient(n, &mut ws.acts, &mut ws.batch_a, &mut ws.batch_b);
        for (j, (o, inp)) in out.iter_mut().zip(&inputs[..n]).enumerate() {
            if let Some((t_in, p_in, f)) = inp {
                // Chain rule through the input map: ∂N/∂p = Σᵢ ∂N/∂inᵢ · ∂inᵢ/∂p.
                let mut nd = Dual1::cst(value[j]);
                for (i, xi) in std::iter::once(t_in).chain(p_in).enumerate() {
                    for c in 0..N {
                        nd.g[c] += adjoint[i * n + j] * xi.g[c];
                    }
                }
                *o = *o + nd * *f;
            }
        }
    }

    /// The MLP's inputs at (t, p) with p seeded as the dual variables of `T`, and the factor
    /// that multiplies its output; None where the MLP term vanishes identically.
    #[inline]
    fn mlp_inputs<T: Variable<N>>(&self, t: f64, p: &[f64; N]) -> Option<Inputs<T, N>> {
        let tm = t.powi(self.mlp_power as i32);
        let pj: [T; N] = std::array::from_fn(|i| T::variable(p[i], i));
        match self.inputs {
            MlpInputs::Plain => Some((T::cst(t), pj, T::cst(tm))),
            MlpInputs::Homogeneous => {
                let mut r2 = pj[0] * pj[0];
                for q in &pj[1..] {
                    r2 = r2 + *q * *q;
                }
                // At p = 0 the term and its derivatives up to order m ≥ 1 vanish; below
                // |p|² = HOMOGENEOUS_MIN_R2 the term (O(|p|^(m+1))) is far below round-off of S
                // while 1/|p| and its derivatives overflow, so it is dropped there too.
                if r2.value() <= HOMOGENEOUS_MIN_R2 {
                    return None;
                }
                let r = r2.sqrt();
                let inv = r.recip();
                Some((
                    r.scale(t),
                    pj.map(|q| q * inv),
                    r.powi(self.mlp_power as i32 + 1).scale(tm),
                ))
            }
        }
    }

    /// The polynomial part P(t, ·) as a `T`: its gradient alone where `T` carries no Hessian.
    #[inline(always)]
    fn polynomial_part<T: Variable<N>>(&self, t: f64, p: &[f64; N]) -> T {
        if T::COMPONENTS == 1 + N {
            let d = self.polynomial.gradient(t, p);
            T::from_components(|c| if c == 0 { d.v } else { d.g[c - 1] })
        } else {
            T::from_jet(&self.polynomial.jet(t, p))
        }
    }

    /// [`Self::polynomial_part`] at every momentum of a batch, in SIMD lanes (the same bits).
    #[inline]
    fn polynomial_parts<T: Variable<N>>(&self, t: f64, p: &[[f64; N]], out: &mut [T]) {
        let isa = Isa::detect();
        for (pb, ob) in p.chunks(MAX_BATCH).zip(out.chunks_mut(MAX_BATCH)) {
            if pb.len() <= FEW {
                self.polynomial_chunk::<T, FEW>(isa, t, pb, ob);
            } else {
                self.polynomial_chunk::<T, MAX_BATCH>(isa, t, pb, ob);
            }
        }
    }

    /// [`Self::polynomial_parts`] on `CAP` ≥ `p.len()` momenta.
    #[inline(always)]
    fn polynomial_chunk<T: Variable<N>, const CAP: usize>(
        &self,
        isa: Isa,
        t: f64,
        pb: &[[f64; N]],
        ob: &mut [T],
    ) {
        {
            let n = pb.len();
            if T::COMPONENTS == 1 + N {
                let mut d = [Dual1::<N>::default(); CAP];
                lanes_bisection::polynomial_gradients(&self.polynomial, isa, t, pb, &mut d[..n]);
                for (o, d) in ob.iter_mut().zip(&d) {
                    *o = T::from_components(|c| if c == 0 { d.v } else { d.g[c - 1] });
                }
            } else {
                let mut j = [Jet2::<N>::default(); CAP];
                lanes_bisection::polynomial_jets(&self.polynomial, isa, t, pb, &mut j[..n]);
                for (o, j) in ob.iter_mut().zip(&j) {
                    *o = T::from_jet(j);
                }
            }
        }
    }

    /// S at fixed t with p seeded as the dual variables of `T`.
    fn derivatives<T: Variable<N>>(&self, t: f64, p: &[f64; N], a: &mut [T], b: &mut [T]) -> T {
        let s = self.polynomial_part::<T>(t, p);
        match (&self.mlp, self.mlp_inputs::<T>(t, p)) {
            (Some(mlp), Some((t_in, p_in, factor))) => {
                a[0] = t_in;
                a[1..=N].copy_from_slice(&p_in);
                s + mlp.eval(a, b) * factor
            }
            _ => s,
        }
    }

    /// `derivatives` for a batch: the per-trajectory inputs and outputs of the MLP are mapped
    /// one at a time, the MLP itself runs on all of them together.
    fn derivatives_batch<T: Variable<N>>(
        &self,
        t: f64,
        p: &[[f64; N]],
        out: &mut [T],
        ws: &mut Workspace<N>,
    ) {
        let n = p.len();
        assert!(n <= MAX_BATCH && out.len() == n, "batch of {n} momenta");
        self.polynomial_parts::<T>(t, p, out);
        let Some(mlp) = self.mlp.as_ref().filter(|_| n > 0) else {
            return;
        };
        if n <= FEW {
            self.forward_mlp::<T, FEW>(mlp, t, p, out, ws);
        } else {
            self.forward_mlp::<T, MAX_BATCH>(mlp, t, p, out, ws);
        }
    }

    /// The MLP term of [`Self::derivatives_batch`], added into `out`, with scratch for
    /// `CAP` ≥ `p.len()` momenta.
    fn forward_mlp<T: Variable<N>, const CAP: usize>(
        &self,
        mlp: &Mlp,
        t: f64,
        p: &[[f64; N]],
        out: &mut [T],
        ws: &mut Workspace<N>,
    ) {
        let n = p.len();
        let cols = T::COMPONENTS * n;
        let mut factors = [None; CAP];
        for (j, pj) in p.iter().enumerate() {
            let inputs = self.mlp_inputs::<T>(t, pj);
            // A vanishing term still gets finite (zero) inputs; its output is not used.
            let zero = T::cst(0.0);
            let (t_in, p_in) = inputs.map_or((zero, [zero; N]), |(a, b, _)| (a, b));
            for (i, x) in std::iter::once(&t_in).chain(&p_in).enumerate() {
                x.components(|c, v| ws.batch_a[i * cols + c * n + j] = v);
            }
            factors[j] = inputs.map(|(_, _, f)| f);
        }
        let row = mlp.eval_batch::<N, T>(n, &mut ws.batch_a, &mut ws.batch_b);
        for (j, (o, f)) in out.iter_mut().zip(&factors).enumerate() {
            if let Some(f) = f {
                *o = *o + T::from_components(|c| row[c * n + j]) * *f;
            }
        }
    }

    /// S(t, p) and ∂S/∂t, for the Hamilton–Jacobi residual.
    pub fn value_and_time_derivative(
        &self,
        t: f64,
        p: &[f64; N],
        ws: &mut Workspace<N>,
    ) -> (f64, f64) {
        let (mut v, mut dt) = self.polynomial.value_and_time_derivative(t, p);
        let Some(mlp) = &self.mlp else { return (v, dt) };
        // Seed the time input as dual variable 0; p enters as constants.
        let (t_in, p_in, factor) = match self.inputs {
            MlpInputs::Plain => (Dual1::<N>::var(t, 0), p.map(Dual1::cst), 1.0),
            MlpInputs::Homogeneous => {
                let r2 = p.iter().map(|x| x * x).sum::<f64>();
                if r2 <= HOMOGENEOUS_MIN_R2 {
                    return (v, dt);
                }
                let r = r2.sqrt();
                let mut tau = Dual1::<N>::var(r * t, 0);
                tau.g[0] = r;
                (
                    tau,
                    p.map(|x| Dual1::cst(x / r)),
                    r.powi(self.mlp_power as i32 + 1),
                )
            }
        };
        ws.d1_a[0] = t_in;
        ws.d1_a[1..=N].copy_from_slice(&p_in);
        let n = mlp.eval(&mut ws.d1_a, &mut ws.d1_b);
        let m = self.mlp_power as i32;
        v += factor * t.powi(m) * n.v;
        dt += factor * (t.powi(m) * n.g[0] + f64::from(m) * t.powi(m - 1) * n.v);
        (v, dt)
    }
}

//! The MLP part N(t, p) of a generating function: dense tanh layers, evaluated for one input
//! on any [`Variable`] (forward mode) or for a batch of inputs by the packed [`crate::kernel`],
//! with its input gradient by a reverse pass.

// Index loops over small fixed-size vectors and matrices read as the formulas they implement.
#![allow(clippy::needless_range_loop)]

use super::MAX_BATCH;
use crate::dual::{Scalar, Variable};
use crate::error::CoreError;
use crate::isa::Isa;
use crate::kernel::{self, madd};
use crate::memory::try_collect;
use std::sync::Arc;

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

/// [`tanh_fast`] (`FMA` false) or [`tanh_fast_fma`] (true) on R rows of L lanes at once, bit for
/// bit: each stage of [`tanh_with`]
/// (`tanh_reduce`, the Horner steps, `tanh_finish`) over every element before the next. One
/// tanh is a chain of ~20 dependent operations; run unit by unit, the out-of-order window holds
/// about two of those chains and the core waits on their latency. In lockstep 4 rows of 8 lanes
/// (8 AVX2 registers) advance together (1.2× the single-unit loop's throughput in isolation).
#[inline(always)]
pub(crate) fn tanh_fast_rows<const FMA: bool, const R: usize, const L: usize>(
    x: &mut [[f64; L]; R],
) {
    let mut shifted = [[0.0; L]; R];
    let mut r = [[0.0; L]; R];
    for i in 0..R {
        for l in 0..L {
            (shifted[i][l], r[i][l]) = tanh_reduce::<FMA>(x[i][l]);
        }
    }
    let mut q = [[TANH_C[0]; L]; R];
    for c in &TANH_C[1..] {
        for i in 0..R {
            for l in 0..L {
                q[i][l] = madd::<FMA>(q[i][l], r[i][l], *c);
            }
        }
    }
    for i in 0..R {
        for l in 0..L {
            x[i][l] = tanh_finish::<FMA>(shifted[i][l], r[i][l], q[i][l]);
        }
    }
}

// 1/n! for n = 13 down to 2: expm1(r) = r + r² (1/2 + r/6 + …).
const TANH_C: [f64; 12] = [
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

#[inline(always)]
fn tanh_with<const FMA: bool>(x: f64) -> f64 {
    let (shifted, r) = tanh_reduce::<FMA>(x);
    let mut q = TANH_C[0];
    for c in &TANH_C[1..] {
        q = madd::<FMA>(q, r, *c);
    }
    tanh_finish::<FMA>(shifted, r, q)
}

/// tanh's first stage: 2x = k ln 2 + r, |r| ≤ ln 2 / 2, as (k + 1.5 · 2^52, r).
#[inline(always)]
fn tanh_reduce<const FMA: bool>(x: f64) -> (f64, f64) {
    // 1.5 · 2^52: adding it rounds to an integer, whose bits land in the mantissa's low bits.
    const SHIFT: f64 = 6755399441055744.0;
    const LOG2E: f64 = std::f64::consts::LOG2_E;
    // ln 2 split so that k · LN2_HI is exact for |k| < 2^11 (fdlibm's constants).
    const LN2_HI: f64 = f64::from_bits(0x3FE6_2E42_FEE0_0000);
    const LN2_LO: f64 = f64::from_bits(0x3DEA_39EF_3579_3C76);
    // |tanh(x)| rounds to 1 beyond |x| ≈ 19.1; clamping keeps 2^k finite (NaN passes through).
    let y = (2.0 * x).clamp(-40.0, 40.0);
    let shifted = madd::<FMA>(y, LOG2E, SHIFT);
    let k = shifted - SHIFT;
    // k · LN2_HI is exact, so the fused and the plain form agree on the first subtraction.
    (shifted, madd::<FMA>(-k, LN2_LO, madd::<FMA>(-k, LN2_HI, y)))
}

/// tanh's last stage from the first's (shifted k, r) and the Horner sum q: e = expm1(2x) =
/// 2^k (expm1(r) + 1) − 1, and tanh = e / (e + 2).
#[inline(always)]
fn tanh_finish<const FMA: bool>(shifted: f64, r: f64, q: f64) -> f64 {
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
    /// inputs is checked against the system by
    /// [`GeneratingFunction::new`](super::GeneratingFunction::new).
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
    pub(super) fn eval<T: Scalar>(&self, a: &mut [T], b: &mut [T]) -> T {
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
    pub(super) fn value_and_input_gradient<'a>(
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
    pub(super) fn activation_rows(&self) -> usize {
        self.n_inputs() + self.layers.iter().map(|l| l.n_out).sum::<usize>()
    }

    /// N for `n` trajectories at once. The inputs are rows 0..n_inputs of `a` (`K · n` columns
    /// each, K = `T::COMPONENTS`, component-major); returns the output row, in `a` or `b`.
    pub(super) fn eval_batch<'a, const N: usize, T: Variable<N>>(
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

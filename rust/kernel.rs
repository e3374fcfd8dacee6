//! The batched dense-layer kernel: Z = W·X for a chunk of trajectories at once.
//!
//! A forward-mode pass carries K numbers per neuron and trajectory (K = 10 for value, gradient
//! and packed Hessian; K = 4 for value and gradient). Stacking the K components of n
//! trajectories as columns turns every layer into one (n_out × n_in)·(n_in × K·n) matrix
//! product, which a register-blocked kernel runs near the FMA units' rate; one trajectory alone
//! is a matrix–vector product per component, bound by loading the weights.
//!
//! Layout: activations are row-major (neuron, column) with column = component · n + trajectory,
//! so the row stride is K·n and the chain rule of tanh runs over contiguous trajectories.
//!
//! Every output element is one chain of multiply-adds over k = 0, 1, …, n_in − 1 starting from 0,
//! whichever block, remainder loop or column position computes it. A trajectory's numbers
//! therefore never depend on which other trajectories share its chunk.

use crate::error::CoreError;

/// Weight rows per register block.
pub const MR: usize = 6;
/// Columns per register block: two 4-wide vectors.
pub const NR: usize = 8;
/// k-block: a (KC × K·n) block of X stays in L2 while every weight panel passes over it.
const KC: usize = 128;

/// W (row-major, `n_out × n_in`) repacked for [`gemm`]: panels of MR rows, each k-major
/// (`panel[k·MR + r] = W[q·MR + r, k]`), with zero rows past `n_out`.
pub fn pack(weight: &[f64], n_in: usize, n_out: usize) -> Vec<f64> {
    try_pack(weight, n_in, n_out).unwrap_or_else(|e| crate::memory::panic_out_of_memory(&e))
}

/// [`pack`], with the packed copy allocated fallibly ([`CoreError::Memory`] where refused):
/// the width of a layer comes from a model file.
pub fn try_pack(weight: &[f64], n_in: usize, n_out: usize) -> Result<Vec<f64>, CoreError> {
    let panels = n_out.div_ceil(MR);
    let len = panels.checked_mul(MR * n_in).ok_or_else(|| {
        CoreError::Memory(format!("a packed layer of {n_out} x {n_in} is too large"))
    })?;
    let mut packed = crate::memory::try_filled(len, 0.0, "a packed layer")?;
    for (o, row) in weight.chunks_exact(n_in).enumerate() {
        let (q, r) = (o / MR, o % MR);
        for (k, &w) in row.iter().enumerate() {
            packed[q * MR * n_in + k * MR + r] = w;
        }
    }
    Ok(packed)
}

/// a·b + c: one fused multiply-add (a single rounding) when `FMA`, else a multiply and an add.
#[inline(always)]
pub(crate) fn madd<const FMA: bool>(a: f64, b: f64, c: f64) -> f64 {
    if FMA {
        // A single instruction where the caller enables the `fma` target feature.
        a.mul_add(b, c)
    } else {
        a * b + c
    }
}

/// z[o, c] = Σ_k W[o, k] x[k, c] for o < n_out, c < cols; `x` has `n_in` rows and `z` `n_out`
/// rows, both of stride `cols`.
#[inline(always)]
fn gemm_body<const FMA: bool>(
    packed: &[f64],
    n_in: usize,
    n_out: usize,
    x: &[f64],
    cols: usize,
    z: &mut [f64],
) {
    let x = &x[..n_in * cols];
    let z = &mut z[..n_out * cols];
    for k0 in (0..n_in).step_by(KC) {
        let k1 = (k0 + KC).min(n_in);
        let first = k0 == 0;
        let xb = &x[k0 * cols..k1 * cols];
        for (q, panel) in packed.chunks_exact(MR * n_in).enumerate() {
            let rows = (n_out - q * MR).min(MR);
            let panel = &panel[k0 * MR..k1 * MR];
            let zq = &mut z[q * MR * cols..(q * MR + rows) * cols];
            let mut c = 0;
            while c + NR <= cols {
                let mut acc = [[0.0; NR]; MR];
                if !first {
                    for (r, a) in acc.iter_mut().enumerate().take(rows) {
                        a.copy_from_slice(&zq[r * cols + c..r * cols + c + NR]);
                    }
                }
                for (w, xrow) in panel.chunks_exact(MR).zip(xb.chunks_exact(cols)) {
                    let w: &[f64; MR] = w.try_into().unwrap();
                    let xk: &[f64; NR] = xrow[c..c + NR].try_into().unwrap();
                    for r in 0..MR {
                        for j in 0..NR {
                            acc[r][j] = madd::<FMA>(w[r], xk[j], acc[r][j]);
                        }
                    }
                }
                for (r, a) in acc.iter().enumerate().take(rows) {
                    zq[r * cols + c..r * cols + c + NR].copy_from_slice(a);
                }
                c += NR;
            }
            // The last columns one at a time: the same chain of multiply-adds per element.
            while c < cols {
                let mut acc = [0.0; MR];
                if !first {
                    for (r, a) in acc.iter_mut().enumerate().take(rows) {
                        *a = zq[r * cols + c];
                    }
                }
                for (w, xrow) in panel.chunks_exact(MR).zip(xb.chunks_exact(cols)) {
                    let xv = xrow[c];
                    for r in 0..MR {
                        acc[r] = madd::<FMA>(w[r], xv, acc[r]);
                    }
                }
                for (r, &a) in acc.iter().enumerate().take(rows) {
                    zq[r * cols + c] = a;
                }
                c += 1;
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn gemm_fma(packed: &[f64], n_in: usize, n_out: usize, x: &[f64], cols: usize, z: &mut [f64]) {
    gemm_body::<true>(packed, n_in, n_out, x, cols, z);
}

/// Whether [`gemm`] runs the fused multiply-add kernel on this CPU.
pub fn uses_fma() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// z = W·x with W packed by [`pack`]: `x` is (n_in × cols) and `z` (n_out × cols), row-major.
///
/// The fused kernel is chosen at run time, once per CPU, so a result is the same for every
/// thread and chunk on one machine.
pub fn gemm(packed: &[f64], n_in: usize, n_out: usize, x: &[f64], cols: usize, z: &mut [f64]) {
    debug_assert_eq!(packed.len(), n_out.div_ceil(MR) * MR * n_in);
    #[cfg(target_arch = "x86_64")]
    if uses_fma() {
        // SAFETY: the CPU has the features `gemm_fma` is compiled for.
        unsafe { gemm_fma(packed, n_in, n_out, x, cols, z) };
        return;
    }
    gemm_body::<false>(packed, n_in, n_out, x, cols, z);
}

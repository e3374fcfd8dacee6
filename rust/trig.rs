//! A branch-free sin/cos for f64 that vectorises across SIMD lanes.
//!
//! The splittings' exact axis rotations spend most of their time in sin and cos. libm's are
//! scalar calls with data-dependent branches, so a loop over lanes cannot vectorise through
//! them. [`sin_cos`] reduces by π/2 (Cody–Waite, π/2 split in four parts, the reduced argument
//! kept as a double-double), evaluates fdlibm's minimax polynomials on [−π/4, π/4] (the kernels
//! that carry the reduced argument's tail), and picks the quadrant by integer masks: no calls and
//! no branches on a lane's data, only plain multiplies and adds (never contracted into FMAs), so
//! the same bits come out of the scalar call and out of every lane of [`sin_cos_lanes`] on every
//! dispatch path. Two tests per block, not per lane, take shortcuts that change no bit: a block
//! whose angles are all below 0.99 π/4 (every rotation of a resolved step) skips the reduction,
//! which would leave them unchanged, and a block with an angle out of range sends that lane to
//! libm after the vectorised pass.
//!
//! Accuracy: within 1 ulp of libm's sin and cos over a seeded sample of 10⁶ arguments in
//! [−100, 100], near multiples of π/2, and across the whole reduced range (tested in
//! rust/tests/splitting_lanes.rs). For |x| > [`REDUCED_RANGE`] (and for ±∞, NaN) the
//! reduction would lose bits, so those arguments go to libm: nothing is refused or degraded.

/// |x| up to which the Cody–Waite reduction is exact: k = round(2x/π) stays below 2^19, so
/// k times a 33-bit part of π/2 is exact. Angles of a rotation step are far smaller.
pub const REDUCED_RANGE: f64 = 524288.0;

// π/2 = P1 + P2 + P3 + P4, the first three with at most 33 significant bits (fdlibm's pio2_1,
// pio2_2, pio2_3, pio2_3t): k·P1, k·P2, k·P3 are exact for |k| < 2^20.
const P1: f64 = f64::from_bits(0x3FF9_21FB_5440_0000);
const P2: f64 = f64::from_bits(0x3DD0_B461_1A60_0000);
const P3: f64 = f64::from_bits(0x3BA3_198A_2E00_0000);
const P4: f64 = f64::from_bits(0x397B_839A_2520_49C1);
const TWO_OVER_PI: f64 = std::f64::consts::FRAC_2_PI;
/// 1.5 · 2^52: adding it rounds to an integer whose low bits land in the mantissa's low bits.
const SHIFT: f64 = 6755399441055744.0;

// fdlibm's minimax coefficients for sin and cos on [−π/4, π/4] (__kernel_sin, __kernel_cos).
const S1: f64 = f64::from_bits(0xBFC5_5555_5555_5549);
const S2: f64 = f64::from_bits(0x3F81_1111_1110_F8A6);
const S3: f64 = f64::from_bits(0xBF2A_01A0_19C1_61D5);
const S4: f64 = f64::from_bits(0x3EC7_1DE3_57B1_FE7D);
const S5: f64 = f64::from_bits(0xBE5A_E5E6_8A2B_9CEB);
const S6: f64 = f64::from_bits(0x3DE5_D93A_5ACF_D57C);
const C1: f64 = f64::from_bits(0x3FA5_5555_5555_554C);
const C2: f64 = f64::from_bits(0xBF56_C16C_16C1_5177);
const C3: f64 = f64::from_bits(0x3EFA_01A0_19CB_1590);
const C4: f64 = f64::from_bits(0xBE92_7E4F_809C_52AD);
const C5: f64 = f64::from_bits(0x3E21_EE9E_BDB4_B1C4);
const C6: f64 = f64::from_bits(0xBDA8_FAE9_BE88_38D4);

/// Below this |x|, k = round(2x/π) is 0 and the reduction leaves (x, 0) exactly.
const NO_REDUCTION: f64 = 0.99 * std::f64::consts::FRAC_PI_4;

/// (sin x, cos x) of one argument, the same bits as a lane of [`sin_cos_lanes`]. One at a time
/// a branch is cheap, so small angles (every rotation of a resolved step) skip the reduction,
/// which would leave them unchanged, and go straight to the kernels.
#[inline(always)]
pub fn sin_cos(x: f64) -> (f64, f64) {
    if x.abs() < NO_REDUCTION {
        // What sin_cos_reduced computes for k = 0: r = x, tail 0, quadrant 0 (and sin(±0) = ±0
        // comes out of the kernel itself).
        (kernel_sin(x, 0.0), kernel_cos(x, 0.0))
    } else if in_range(x) {
        sin_cos_reduced(x)
    } else {
        x.sin_cos()
    }
}

/// [`sin_cos`] of every lane: one branch-free pass over all lanes (it vectorises), then libm
/// for the lanes out of range, if any. Lane l equals `sin_cos(x[l])` bit for bit.
#[inline(always)]
pub fn sin_cos_lanes<const L: usize>(x: &[f64; L], s: &mut [f64; L], c: &mut [f64; L]) {
    if L == 1 {
        // A lone trajectory: the scalar form with its branches is faster than the lane form.
        (s[0], c[0]) = sin_cos(x[0]);
        return;
    }
    // One test for the whole block (not per lane): when every angle is below the cut, as in
    // every rotation of a resolved step, the reduction would leave each unchanged, so the
    // kernels alone give the same bits at half the work.
    let mut all_small = true;
    for v in x {
        all_small &= v.abs() < NO_REDUCTION;
    }
    if all_small {
        for l in 0..L {
            (s[l], c[l]) = (kernel_sin(x[l], 0.0), kernel_cos(x[l], 0.0));
        }
        return;
    }
    let mut all_in = true;
    for l in 0..L {
        (s[l], c[l]) = sin_cos_reduced(x[l]);
        all_in &= in_range(x[l]);
    }
    if !all_in {
        fix_out_of_range(x, s, c);
    }
}

#[cold]
#[inline(never)]
fn fix_out_of_range<const L: usize>(x: &[f64; L], s: &mut [f64; L], c: &mut [f64; L]) {
    for l in 0..L {
        if !in_range(x[l]) {
            (s[l], c[l]) = x[l].sin_cos();
        }
    }
}

/// False for NaN as well.
#[inline(always)]
fn in_range(x: f64) -> bool {
    x.abs() <= REDUCED_RANGE
}

/// a + b = s + e exactly (Knuth's TwoSum: no ordering of |a|, |b| needed).
#[inline(always)]
fn two_sum(a: f64, b: f64) -> (f64, f64) {
    let s = a + b;
    let bb = s - a;
    let e = (a - (s - bb)) + (b - bb);
    (s, e)
}

/// The branch-free body of [`sin_cos`]; its value is meaningless (but harmless) out of range.
#[inline(always)]
pub fn sin_cos_reduced(x: f64) -> (f64, f64) {
    // k = round(2x/π); its two low bits are the quadrant (two's complement, so also for k < 0).
    let shifted = x * TWO_OVER_PI + SHIFT;
    let k = shifted - SHIFT;
    let quadrant = shifted.to_bits() & 3;
    // r = x − k π/2 as a double-double (hi, lo). x − k·P1 is exact (k·P1 is, and the two are
    // within a factor 2 of each other); the next parts go in by TwoSum, so a cancellation near a
    // multiple of π/2 leaves the bits that P2, P3 carry.
    let t = x - k * P1;
    let (hi, e1) = two_sum(t, -(k * P2));
    let (hi, e2) = two_sum(hi, -(k * P3));
    let lo = (e1 + e2) - k * P4;
    let r = hi + lo;
    let r_lo = lo - (r - hi);
    let (s, c) = (kernel_sin(r, r_lo), kernel_cos(r, r_lo));
    // Quadrant q: (sin, cos) = (s, c), (c, −s), (−s, −c), (−c, s). Swap on odd q by masks;
    // flip sin's sign for q ∈ {2, 3} and cos's for q ∈ {1, 2}.
    let swap = 0u64.wrapping_sub(quadrant & 1);
    let (sb, cb) = (s.to_bits(), c.to_bits());
    let sin_bits = (cb & swap) | (sb & !swap);
    let cos_bits = (sb & swap) | (cb & !swap);
    let sin_sign = (quadrant & 2) << 62;
    let cos_sign = ((quadrant + 1) & 2) << 62;
    let sin = f64::from_bits(sin_bits ^ sin_sign);
    // sin(±0) = ±0: the reduction loses the sign of a zero (a select, not a branch).
    let sin = if x == 0.0 { x } else { sin };
    (sin, f64::from_bits(cos_bits ^ cos_sign))
}

/// sin(x + y) on |x| ≤ π/4 with y a tail below ulp(x)/2 (fdlibm's __kernel_sin, tail form).
#[inline(always)]
fn kernel_sin(x: f64, y: f64) -> f64 {
    let z = x * x;
    let w = z * z;
    let r = S2 + z * (S3 + z * S4) + z * w * (S5 + z * S6);
    let v = z * x;
    x - ((z * (0.5 * y - v * r) - y) - v * S1)
}

/// cos(x + y) on |x| ≤ π/4 (fdlibm's __kernel_cos in its branch-free form).
#[inline(always)]
fn kernel_cos(x: f64, y: f64) -> f64 {
    let z = x * x;
    let w = z * z;
    let r = z * (C1 + z * (C2 + z * C3)) + w * w * (C4 + z * (C5 + z * C6));
    let hz = 0.5 * z;
    let w = 1.0 - hz;
    w + (((1.0 - w) - hz) + (z * r - x * y))
}

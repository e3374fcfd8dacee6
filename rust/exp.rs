//! A branch-free exp for f64 that vectorises across SIMD lanes.
//!
//! Log-canonical steps live in q = ln x and spend their time in e^q: the log splittings' exact
//! one-variable flows and the Taylor-HJ generating function's monomials y^e with y = e^q. libm's
//! exp is a scalar call, so a loop over lanes cannot vectorise through it. [`exp`] is fdlibm's
//! algorithm written without branches on a lane's data:
//!
//! - k = round(x / ln 2) by the 1.5 · 2^52 shift (its low mantissa bits are k in two's
//!   complement, so no float-to-int conversion is needed);
//! - r = (x − k·ln2_hi) − k·ln2_lo, with ln2_hi's 32 significant bits making k·ln2_hi exact;
//! - fdlibm's minimax rational form e^r = 1 − ((lo − r·c/(2 − c)) − hi) on |r| ≤ ln 2 / 2;
//! - scaling by 2^k built from its exponent bits.
//!
//! Only plain multiplies, adds and one divide, never contracted into FMAs, so the scalar call and
//! every lane of [`exp_lanes`] give the same bits on every dispatch path. Arguments outside
//! [[`EXP_MIN`], [`EXP_MAX`]] (where 2^k would leave the normal range), and NaN, go to libm: a
//! block with one such lane takes libm for that lane after the vectorised pass. Accuracy: within
//! 1 ulp of libm over a seeded sample of 10⁶ arguments across the range (tested in
//! rust/tests/log_canonical.rs).

/// Smallest argument of the vectorised path: e^x is a normal number down to here.
pub const EXP_MIN: f64 = -708.0;
/// Largest argument of the vectorised path: 2^k stays below 2^1023.
pub const EXP_MAX: f64 = 709.0;

const LN2_HI: f64 = f64::from_bits(0x3FE6_2E42_FEE0_0000);
const LN2_LO: f64 = f64::from_bits(0x3DEA_39EF_3579_3C76);
const INV_LN2: f64 = f64::from_bits(0x3FF7_1547_652B_82FE);
/// 1.5 · 2^52: adding it rounds to an integer whose low bits land in the mantissa's low bits.
const SHIFT: f64 = 6755399441055744.0;

// fdlibm's e_exp.c minimax coefficients (P1 … P5) on [−ln 2 / 2, ln 2 / 2].
const P1: f64 = f64::from_bits(0x3FC5_5555_5555_553E);
const P2: f64 = f64::from_bits(0xBF66_C16C_16BE_BD93);
const P3: f64 = f64::from_bits(0x3F11_566A_AF25_DE2C);
const P4: f64 = f64::from_bits(0xBEBB_BD41_C5D2_6BF1);
const P5: f64 = f64::from_bits(0x3E66_3769_72BE_A4D0);

/// e^x for x in [[`EXP_MIN`], [`EXP_MAX`]]: the branch-free body shared by the scalar call and
/// the lanes.
#[inline(always)]
fn exp_reduced(x: f64) -> f64 {
    let shifted = x * INV_LN2 + SHIFT;
    let k = shifted - SHIFT;
    // The low 32 bits of the shifted value's mantissa hold k (|k| < 2^11) in two's complement.
    let ki = (shifted.to_bits() as i64).wrapping_sub(SHIFT.to_bits() as i64);
    let hi = x - k * LN2_HI;
    let lo = k * LN2_LO;
    let r = hi - lo;
    let t = r * r;
    let c = r - t * (P1 + t * (P2 + t * (P3 + t * (P4 + t * P5))));
    let y = 1.0 - ((lo - (r * c) / (2.0 - c)) - hi);
    // 2^k for k in [−1021, 1023]: its biased exponent in the top bits.
    let scale = f64::from_bits(((ki + 1023) as u64) << 52);
    y * scale
}

/// e^x, the same bits as a lane of [`exp_lanes`]; libm outside [[`EXP_MIN`], [`EXP_MAX`]].
#[inline(always)]
pub fn exp(x: f64) -> f64 {
    if (EXP_MIN..=EXP_MAX).contains(&x) {
        exp_reduced(x)
    } else {
        x.exp()
    }
}

/// [`exp`] of every lane: one branch-free pass (it vectorises), then libm for the lanes out of
/// range, if any. Lane l equals `exp(x[l])` bit for bit.
#[inline(always)]
pub fn exp_lanes<const L: usize>(x: &[f64; L], out: &mut [f64; L]) {
    if L == 1 {
        out[0] = exp(x[0]);
        return;
    }
    let mut outside = false;
    for l in 0..L {
        let v = x[l];
        let inside = (EXP_MIN..=EXP_MAX).contains(&v);
        outside |= !inside;
        // Out-of-range lanes (NaN included) compute on 0 and are redone below.
        out[l] = exp_reduced(if inside { v } else { 0.0 });
    }
    if outside {
        for l in 0..L {
            if !(EXP_MIN..=EXP_MAX).contains(&x[l]) {
                out[l] = x[l].exp();
            }
        }
    }
}

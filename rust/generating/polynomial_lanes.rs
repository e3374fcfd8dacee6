//! The polynomial part of a generating function in SIMD lanes: the jets (value, p-gradient,
//! p-Hessian) of P(t, ·) at a batch of momenta, in structure-of-arrays blocks of [`LANES`].
//!
//! A bisection step of a Taylor-HJ integrator spends most of its time evaluating the jet of
//! S = Σ t^k S_k at each Newton iterate: a dozen monomials, each a chain of multiplies and
//! adds whose latency bounds one trajectory. Across trajectories the same chain runs in every
//! lane: the exponents, coefficients and t-powers are shared, only p differs.
//!
//! **Bit identity.** Every lane performs exactly the operations of the scalar
//! [`Polynomial::jet`] / [`Polynomial::gradient`] in the same order (plain multiplies and adds,
//! never contracted into FMAs; the same tables of powers; the same `powi` fallback above the
//! table), so a lane equals the scalar evaluation bit for bit whatever the batch, the padding
//! and the instruction set; the tests check it. This is what lets
//! [`crate::stepper::BisectionStepper`]'s `step_batch` solve a block of Newton systems in lockstep
//! and still give every trajectory the scalar step's bits.
//!
//! **Dispatch** as in [`crate::lanes`]: the block loop compiled for the baseline and, behind
//! `#[target_feature(enable = "avx2,fma")]`, for AVX2, chosen once per call by [`Isa::detect`]. An
//! [`Isa`] claims AVX2 only where detection found it, so the safe functions here cannot run AVX2
//! code on a CPU without it.

// Index loops over lanes, coordinates and monomials read as the formulas they evaluate.
#![allow(clippy::needless_range_loop)]

use super::polynomial::{Factor, PlannedTerm};
use super::{Polynomial, TABLE_POWER};
use crate::dual::{Dual1, Jet2};
use crate::isa::{Isa, LANES};

/// Blocks with at most this many momenta take the scalar path: a block of 8 lanes costs about
/// five scalar evaluations.
pub(crate) const SCALAR_AT_MOST: usize = LANES / 2;

/// The jet of P at L momenta, structure of arrays: `h[a][b]` for a ≤ b holds ∂²P/∂p_a∂p_b.
#[derive(Clone, Copy)]
pub(crate) struct JetLanes<const N: usize, const L: usize> {
    pub(crate) v: [f64; L],
    pub(crate) g: [[f64; L]; N],
    pub(crate) h: [[[f64; L]; N]; N],
}

/// The powers x⁰ … x^[`TABLE_POWER`] of each coordinate, lane by lane: `pw[i][k][l]`.
type PowerLanes<const N: usize, const L: usize> = [[[f64; L]; TABLE_POWER + 1]; N];

/// Scratch of [`jet_lanes_into`] kept across the evaluations of a block: the tables of powers
/// (only the rows up to each coordinate's largest exponent are written and read) and the factor
/// jets of one term by position in the term (only its variables' positions are written and
/// read). Nothing in it needs clearing between evaluations.
pub(crate) struct Scratch<const N: usize, const L: usize> {
    pw: PowerLanes<N, L>,
    j: [[[f64; L]; 3]; N],
}

impl<const N: usize, const L: usize> Scratch<N, L> {
    #[inline(always)]
    pub(crate) fn new() -> Self {
        Scratch {
            pw: [[[0.0; L]; TABLE_POWER + 1]; N],
            j: [[[0.0; L]; 3]; N],
        }
    }
}

/// `acc[l] += x[l]` lane by lane.
#[inline(always)]
fn add_into<const L: usize>(acc: &mut [f64; L], x: &[f64; L]) {
    for l in 0..L {
        acc[l] += x[l];
    }
}

/// `x[l] *= y[l]` lane by lane.
#[inline(always)]
fn mul_into<const L: usize>(x: &mut [f64; L], y: &[f64; L]) {
    for l in 0..L {
        x[l] *= y[l];
    }
}

/// `x · Π_{r ≥ from} f[r][0]` lane by lane, multiplied left to right.
#[inline(always)]
fn times_values<const N: usize, const L: usize>(
    mut x: [f64; L],
    f: &[[[f64; L]; 3]; N],
    from: usize,
    m: usize,
) -> [f64; L] {
    for r in from..m {
        mul_into(&mut x, &f[r][0]);
    }
    x
}

/// The jets of P(t, ·) at the L momenta `p[i][l]` (the Hessian only when `HESS`) into `out`:
/// lane l gets the numbers of the scalar [`Polynomial::jet`] at p[·][l], bit for bit.
///
/// The scalar evaluation multiplies every term by all N factor jets; a variable absent from a
/// term contributes the factor 1 to the value and 0 to its derivatives. Here such factors are
/// skipped: a product by 1 is exact, and a zero product added to a non-zero sum (or to +0)
/// leaves it unchanged, so for finite inputs the sums are the same bits (the tests check it).
/// The products of one term are formed left to right in the scalar order too, but those that
/// begin with the same factors share them: a term in m variables takes m + m(m−1)/2 multiplies
/// for its value and gradient where m + m² were spent before, and with its Hessian about half.
/// (A table of every power's factor jets, built once an evaluation instead of once a term, was
/// tried: 1–4 % slower on the heavy top.)
#[inline(always)]
pub(crate) fn jet_lanes_into<const N: usize, const L: usize, const HESS: bool, const T_MAX: u32>(
    poly: &Polynomial<N>,
    t: f64,
    p: &[[f64; L]; N],
    scratch: &mut Scratch<N, L>,
    out: &mut JetLanes<N, L>,
) {
    out.v = [0.0; L];
    for i in 0..N {
        out.g[i] = [0.0; L];
        if HESS {
            for b in i..N {
                out.h[i][b] = [0.0; L];
            }
        }
    }
    // The tables of powers, as Polynomial::powers builds them. The t table has every row,
    // whatever the plan's largest t-power: a loop of fixed length unrolls into registers, where
    // one bounded by the plan ran through memory, each power waiting on the store of the one
    // before (4.5 % of the lane solver's samples in the rigid body's Taylor step). The rows the
    // plan reads are the same products. The p tables stop at the plan's largest exponents.
    let plan = poly.plan();
    let mut tp = [0.0; TABLE_POWER + 1];
    tp[0] = 1.0;
    for k in 1..=TABLE_POWER {
        tp[k] = tp[k - 1] * t;
    }
    let pw = &mut scratch.pw;
    for i in 0..N {
        pw[i][0] = [1.0; L];
        for k in 1..=(plan.p_max[i] as usize).min(TABLE_POWER) {
            for l in 0..L {
                pw[i][k][l] = pw[i][k - 1][l] * p[i][l];
            }
        }
    }
    for m in &plan.terms {
        // With T_MAX > 0, only the terms in t¹ … t^T_MAX (the cheap part of S that the Newton
        // predictors take: T_MAX = 1 is t ∂S/∂t(0, p)).
        if T_MAX > 0 && (m.t_power == 0 || m.t_power > T_MAX) {
            continue;
        }
        let tk = if m.t_power as usize <= TABLE_POWER {
            tp[m.t_power as usize]
        } else {
            t.powi(m.t_power as i32)
        };
        let c = m.coeff * tk;
        // Terms in one, two or three variables (every term of the rigid body's Taylor S, 35 of
        // the heavy top's 40 at K = 5) take code with their count fixed at compile time: the
        // loops over their factors unroll and the factor jets stay in registers, where a count
        // read at run time kept every loop and every factor in memory. The same operations in
        // the same order: the same bits.
        match m.count {
            1 => term_into::<N, L, HESS, 1>(m, 1, c, p, &scratch.pw, &mut [[[0.0; L]; 3]; 1], out),
            2 if N >= 2 => {
                let f = &mut [[[0.0; L]; 3]; 2];
                term_into::<N, L, HESS, 2>(m, 2, c, p, &scratch.pw, f, out)
            }
            3 if N >= 3 => {
                let f = &mut [[[0.0; L]; 3]; 3];
                term_into::<N, L, HESS, 3>(m, 3, c, p, &scratch.pw, f, out)
            }
            count => term_into::<N, L, HESS, N>(m, count, c, p, &scratch.pw, &mut scratch.j, out),
        }
    }
}

/// One term c · Π xⁿ of [`jet_lanes_into`] added into `out`: its `count` (≤ C) factors, `f` the
/// scratch of their jets (C = the count where the caller fixed it, else N).
#[inline(always)]
fn term_into<const N: usize, const L: usize, const HESS: bool, const C: usize>(
    m: &PlannedTerm<N>,
    count: usize,
    c: f64,
    p: &[[f64; L]; N],
    pw: &PowerLanes<N, L>,
    f: &mut [[[f64; L]; 3]; C],
    out: &mut JetLanes<N, L>,
) {
    // The (xⁿ, n xⁿ⁻¹, n(n−1) xⁿ⁻²) of this term's variables lane by lane
    // (generating::power_jet), by position in the term (the plan lists its variables in
    // increasing order); the second derivative only where n ≥ 2.
    for k in 0..count {
        let Factor { var: i, n, nf, nn } = m.factors[k];
        let fk = &mut f[k];
        if n == 1 {
            for l in 0..L {
                fk[0][l] = p[i][l];
                fk[1][l] = 1.0;
            }
        } else if n as usize <= TABLE_POWER {
            let k = n as usize;
            for l in 0..L {
                fk[0][l] = pw[i][k][l];
                fk[1][l] = nf * pw[i][k - 1][l];
                fk[2][l] = nn * pw[i][k - 2][l];
            }
        } else {
            for l in 0..L {
                let x = p[i][l];
                let xn2 = x.powi(n as i32 - 2);
                fk[0][l] = xn2 * x * x;
                fk[1][l] = nf * xn2 * x;
                fk[2][l] = nn * xn2;
            }
        }
    }
    // Every product is c times the factors in increasing variable order, left to right,
    // as the scalar jet forms it; products that start alike share their common prefix.
    // `prefix` = c · Π_{r<k} xⁿ of position r.
    let mut prefix = [c; L];
    for k in 0..count {
        let a = m.factors[k].var;
        // ∂/∂p_a = prefix · n xⁿ⁻¹ · Π_{r>k} xⁿ; the off-diagonal ∂²/∂p_a∂p_b (b at a
        // position l > k) branch off this chain at l.
        let mut chain = prefix;
        mul_into(&mut chain, &f[k][1]);
        if HESS {
            if m.factors[k].n >= 2 {
                let mut aa = prefix;
                mul_into(&mut aa, &f[k][2]);
                add_into(&mut out.h[a][a], &times_values(aa, f, k + 1, count));
            }
            for l in k + 1..count {
                let mut ab = chain;
                mul_into(&mut ab, &f[l][1]);
                add_into(
                    &mut out.h[a][m.factors[l].var],
                    &times_values(ab, f, l + 1, count),
                );
                mul_into(&mut chain, &f[l][0]);
            }
        } else {
            chain = times_values(chain, f, k + 1, count);
        }
        add_into(&mut out.g[a], &chain);
        mul_into(&mut prefix, &f[k][0]);
    }
    add_into(&mut out.v, &prefix);
}

/// [`jet_lanes_into`] with fresh scratch.
#[inline(always)]
fn jet_lanes<const N: usize, const L: usize, const HESS: bool>(
    poly: &Polynomial<N>,
    t: f64,
    p: &[[f64; L]; N],
) -> JetLanes<N, L> {
    let mut out = JetLanes {
        v: [0.0; L],
        g: [[0.0; L]; N],
        h: [[[0.0; L]; N]; N],
    };
    jet_lanes_into::<N, L, HESS, 0>(poly, t, p, &mut Scratch::new(), &mut out);
    out
}

/// What a block writes back: a [`Jet2`] or a [`Dual1`] per momentum.
trait FromLanes<const N: usize>: Copy {
    const HESS: bool;
    fn from_lanes<const L: usize>(jet: &JetLanes<N, L>, l: usize) -> Self;
    /// The scalar evaluation the lanes reproduce.
    fn scalar(poly: &Polynomial<N>, t: f64, p: &[f64; N]) -> Self;
}

impl<const N: usize> FromLanes<N> for Jet2<N> {
    const HESS: bool = true;
    #[inline(always)]
    fn scalar(poly: &Polynomial<N>, t: f64, p: &[f64; N]) -> Self {
        poly.jet(t, p)
    }
    #[inline(always)]
    fn from_lanes<const L: usize>(jet: &JetLanes<N, L>, l: usize) -> Self {
        let mut out = Jet2::<N>::default();
        out.v = jet.v[l];
        for i in 0..N {
            out.g[i] = jet.g[i][l];
        }
        let packed = out.packed_mut();
        let mut k = 0;
        for a in 0..N {
            for b in a..N {
                packed[k] = jet.h[a][b][l];
                k += 1;
            }
        }
        out
    }
}

impl<const N: usize> FromLanes<N> for Dual1<N> {
    const HESS: bool = false;
    #[inline(always)]
    fn scalar(poly: &Polynomial<N>, t: f64, p: &[f64; N]) -> Self {
        poly.gradient(t, p)
    }
    #[inline(always)]
    fn from_lanes<const L: usize>(jet: &JetLanes<N, L>, l: usize) -> Self {
        Dual1 {
            v: jet.v[l],
            g: std::array::from_fn(|i| jet.g[i][l]),
        }
    }
}

/// Blocks of [`LANES`] momenta (the last one padded with zeros, whose lanes are dropped). A
/// block of at most [`SCALAR_AT_MOST`] momenta is evaluated one momentum at a time by the scalar
/// functions instead: the same bits, without paying for eight lanes (a rollout of one state
/// would otherwise be 3× slower than before the lanes).
#[inline(always)]
fn blocks<const N: usize, T: FromLanes<N>>(
    poly: &Polynomial<N>,
    t: f64,
    p: &[[f64; N]],
    out: &mut [T],
) {
    for (pb, ob) in p.chunks(LANES).zip(out.chunks_mut(LANES)) {
        if pb.len() <= SCALAR_AT_MOST {
            for (o, q) in ob.iter_mut().zip(pb) {
                *o = T::scalar(poly, t, q);
            }
            continue;
        }
        let mut lanes = [[0.0; LANES]; N];
        for (l, q) in pb.iter().enumerate() {
            for i in 0..N {
                lanes[i][l] = q[i];
            }
        }
        let jet = if T::HESS {
            jet_lanes::<N, LANES, true>(poly, t, &lanes)
        } else {
            jet_lanes::<N, LANES, false>(poly, t, &lanes)
        };
        for (l, o) in ob.iter_mut().enumerate() {
            *o = T::from_lanes(&jet, l);
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn blocks_avx2<const N: usize, T: FromLanes<N>>(
    poly: &Polynomial<N>,
    t: f64,
    p: &[[f64; N]],
    out: &mut [T],
) {
    blocks(poly, t, p, out);
}

#[inline]
fn dispatch<const N: usize, T: FromLanes<N>>(
    poly: &Polynomial<N>,
    isa: Isa,
    t: f64,
    p: &[[f64; N]],
    out: &mut [T],
) {
    assert_eq!(p.len(), out.len(), "one output per momentum");
    #[cfg(target_arch = "x86_64")]
    if isa.is_avx2() {
        // SAFETY: an `Isa` claims AVX2 only where run-time detection found AVX2 and FMA (its
        // field is private: safe code cannot forge it).
        unsafe { blocks_avx2(poly, t, p, out) };
        return;
    }
    blocks(poly, t, p, out);
}

/// `out[j]` = [`Polynomial::jet`] at `p[j]`, bit for bit, evaluated in lanes compiled for `isa`.
pub fn polynomial_jets<const N: usize>(
    poly: &Polynomial<N>,
    isa: Isa,
    t: f64,
    p: &[[f64; N]],
    out: &mut [Jet2<N>],
) {
    dispatch(poly, isa, t, p, out);
}

/// `out[j]` = [`Polynomial::gradient`] at `p[j]`, bit for bit, evaluated in lanes compiled for
/// `isa`.
pub fn polynomial_gradients<const N: usize>(
    poly: &Polynomial<N>,
    isa: Isa,
    t: f64,
    p: &[[f64; N]],
    out: &mut [Dual1<N>],
) {
    dispatch(poly, isa, t, p, out);
}

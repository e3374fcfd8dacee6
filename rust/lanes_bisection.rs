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
//! [`crate::stepper::BisectionStepper::step_batch`] solve a block of Newton systems in lockstep
//! and still give every trajectory the scalar step's bits.
//!
//! **Dispatch** as in [`crate::lanes`]: the block loop compiled for the baseline and, behind
//! `#[target_feature(enable = "avx2,fma")]`, for AVX2, chosen once per call by [`Isa::detect`].

// Index loops over lanes, coordinates and monomials read as the formulas they evaluate.
#![allow(clippy::needless_range_loop)]

use crate::dual::{Dual1, Jet2};
use crate::generating::{Polynomial, TABLE_POWER};
use crate::lanes::{Isa, LANES};

/// Blocks with at most this many momenta take the scalar path: a block of 8 lanes costs about
/// five scalar evaluations.
const SCALAR_AT_MOST: usize = LANES / 2;

/// The jet of P at L momenta, structure of arrays: `h[a][b]` for a ≤ b holds ∂²P/∂p_a∂p_b.
#[derive(Clone, Copy)]
struct JetLanes<const N: usize, const L: usize> {
    v: [f64; L],
    g: [[f64; L]; N],
    h: [[[f64; L]; N]; N],
}

/// The powers x⁰ … x^[`TABLE_POWER`] of each coordinate, lane by lane: `pw[i][k][l]`.
type PowerLanes<const N: usize, const L: usize> = [[[f64; L]; TABLE_POWER + 1]; N];

/// The jets of P(t, ·) at the L momenta `p[i][l]` (the Hessian only when `HESS`): lane l gets
/// the numbers of the scalar [`Polynomial::jet`] at p[·][l], bit for bit.
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
    // The tables of powers, as Polynomial::powers builds them.
    let (mut tmax, mut pmax) = (0u32, [0u32; N]);
    for m in &poly.terms {
        tmax = tmax.max(m.t_power);
        for i in 0..N {
            pmax[i] = pmax[i].max(m.p_powers[i]);
        }
    }
    let mut tp = [0.0; TABLE_POWER + 1];
    tp[0] = 1.0;
    for k in 1..=(tmax as usize).min(TABLE_POWER) {
        tp[k] = tp[k - 1] * t;
    }
    let mut pw: PowerLanes<N, L> = [[[0.0; L]; TABLE_POWER + 1]; N];
    for i in 0..N {
        pw[i][0] = [1.0; L];
        for k in 1..=(pmax[i] as usize).min(TABLE_POWER) {
            for l in 0..L {
                pw[i][k][l] = pw[i][k - 1][l] * p[i][l];
            }
        }
    }
    for m in &poly.terms {
        let tk = if m.t_power as usize <= TABLE_POWER {
            tp[m.t_power as usize]
        } else {
            t.powi(m.t_power as i32)
        };
        let c = m.coeff * tk;
        // (xⁿ, n xⁿ⁻¹, n(n−1) xⁿ⁻²) of each factor, lane by lane (generating::power_jet),
        // written element by element: whole-array moves of lane rows stall on store forwarding.
        let mut j = [[[0.0; L]; 3]; N];
        for i in 0..N {
            let n = m.p_powers[i];
            let ji = &mut j[i];
            if n == 0 {
                for l in 0..L {
                    ji[0][l] = 1.0;
                }
            } else if n == 1 {
                for l in 0..L {
                    ji[0][l] = p[i][l];
                    ji[1][l] = 1.0;
                }
            } else if n as usize <= TABLE_POWER {
                let (k, nf) = (n as usize, n as f64);
                let nn = nf * (nf - 1.0);
                for l in 0..L {
                    ji[0][l] = pw[i][k][l];
                    ji[1][l] = nf * pw[i][k - 1][l];
                    ji[2][l] = nn * pw[i][k - 2][l];
                }
            } else {
                let nf = n as f64;
                let nn = nf * (nf - 1.0);
                for l in 0..L {
                    let x = p[i][l];
                    let xn2 = x.powi(n as i32 - 2);
                    ji[0][l] = xn2 * x * x;
                    ji[1][l] = nf * xn2 * x;
                    ji[2][l] = nn * xn2;
                }
            }
        }
        // c · Π_i j[i][d_i], multiplied in the order i = 0, 1, …, N − 1, added into `acc`.
        let add_factor = |d: [usize; N], acc: &mut [f64; L]| {
            for l in 0..L {
                let mut f = c;
                for i in 0..N {
                    f *= j[i][d[i]][l];
                }
                acc[l] += f;
            }
        };
        add_factor([0; N], &mut out.v);
        for i in 0..N {
            let mut d = [0; N];
            d[i] = 1;
            add_factor(d, &mut out.g[i]);
        }
        if HESS {
            for a in 0..N {
                for b in a..N {
                    let mut d = [0; N];
                    d[a] += 1;
                    d[b] += 1;
                    add_factor(d, &mut out.h[a][b]);
                }
            }
        }
    }
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
    match isa {
        #[cfg(target_arch = "x86_64")]
        Isa::Avx2 => {
            // SAFETY: `Isa::Avx2` is only chosen (by `Isa::detect` or a caller that checked)
            // where the CPU runs AVX2 and FMA.
            unsafe { blocks_avx2(poly, t, p, out) }
        }
        _ => blocks(poly, t, p, out),
    }
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

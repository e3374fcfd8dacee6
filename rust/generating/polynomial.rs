//! The polynomial part P(t, p) of a generating function: a sparse polynomial, evaluated with
//! its p-jet by tables of powers shared by every term.

// Index loops over small fixed-size vectors and matrices read as the formulas they implement.
#![allow(clippy::needless_range_loop)]

use crate::dual::{Dual1, Jet2};
use crate::error::CoreError;
use crate::memory::try_collect;

/// One monomial c · t^k p₁^e₁ ⋯ p_N^e_N.
#[derive(Clone, Debug, PartialEq)]
pub struct Monomial<const N: usize> {
    pub t_power: u32,
    pub p_powers: [u32; N],
    pub coeff: f64,
}

/// A sparse polynomial in (t, p), with its terms compiled for evaluation once, when it is made:
/// the largest exponents (the size of the tables of powers) and each term's variables and
/// factor constants, which every evaluation read from the terms before (a scan of all terms and
/// N branches a term, at every Newton update).
#[derive(Clone, Debug, PartialEq)]
pub struct Polynomial<const N: usize> {
    terms: Vec<Monomial<N>>,
    plan: Plan<N>,
}

/// One factor xⁿ (n ≥ 1) of a [`PlannedTerm`]: its variable and the constants of its jet
/// (xⁿ, n xⁿ⁻¹, n(n−1) xⁿ⁻²), formed as [`power_jet`] forms them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Factor {
    pub(crate) var: usize,
    pub(crate) n: u32,
    pub(crate) nf: f64,
    pub(crate) nn: f64,
}

/// A term as the lanes evaluate it: c · t^k times its `count` factors in increasing variable
/// order (`factors[..count]`); variables absent from it are not listed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct PlannedTerm<const N: usize> {
    pub(crate) t_power: u32,
    pub(crate) coeff: f64,
    pub(crate) count: usize,
    pub(crate) factors: [Factor; N],
}

/// What the evaluations of a [`Polynomial`] read instead of its terms.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Plan<const N: usize> {
    /// The largest t-power and p_i-powers of any term: the rows of the tables of powers.
    pub(crate) t_max: u32,
    pub(crate) p_max: [u32; N],
    pub(crate) terms: Vec<PlannedTerm<N>>,
}

impl<const N: usize> Default for Polynomial<N> {
    fn default() -> Self {
        Polynomial {
            terms: Vec::new(),
            plan: Plan {
                t_max: 0,
                p_max: [0; N],
                terms: Vec::new(),
            },
        }
    }
}

impl<const N: usize> Polynomial<N> {
    /// The polynomial Σ `terms`, compiled (the plan's memory is taken fallibly: a model file sets
    /// the number of terms).
    pub fn new(terms: Vec<Monomial<N>>) -> Result<Self, CoreError> {
        let (mut t_max, mut p_max) = (0u32, [0u32; N]);
        for m in &terms {
            t_max = t_max.max(m.t_power);
            for i in 0..N {
                p_max[i] = p_max[i].max(m.p_powers[i]);
            }
        }
        let planned = try_collect(
            terms.len(),
            terms.iter().map(|m| {
                let none = Factor {
                    var: 0,
                    n: 0,
                    nf: 0.0,
                    nn: 0.0,
                };
                let mut factors = [none; N];
                let mut count = 0;
                for (i, &n) in m.p_powers.iter().enumerate() {
                    if n > 0 {
                        let nf = n as f64;
                        factors[count] = Factor {
                            var: i,
                            n,
                            nf,
                            nn: nf * (nf - 1.0),
                        };
                        count += 1;
                    }
                }
                PlannedTerm {
                    t_power: m.t_power,
                    coeff: m.coeff,
                    count,
                    factors,
                }
            }),
            "the polynomial's terms",
        )?;
        Ok(Polynomial {
            terms,
            plan: Plan {
                t_max,
                p_max,
                terms: planned,
            },
        })
    }

    /// The terms, in the order they are summed.
    pub fn terms(&self) -> &[Monomial<N>] {
        &self.terms
    }

    /// The compiled terms the lanes evaluate.
    #[inline(always)]
    pub(crate) fn plan(&self) -> &Plan<N> {
        &self.plan
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
        power_table(t, self.plan.t_max, tp);
        for i in 0..N {
            power_table(p[i], self.plan.p_max[i], &mut pp[i]);
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

//! Taylor-HJ for any smooth Hamiltonian, by jets: the generating function
//! S(t, p) = Σ_{k=1..K} t^k S_k(p) of the HJ equation ∂S/∂t + H(sou(∂S/∂p, p)) = 0 is computed
//! at the point where Newton needs it, as a truncated power series in (t, δ) around p
//! ([`crate::series`]), by K Picard sweeps S ← −∫₀ᵗ H(sou(∂S/∂δ, p + δ)) dt. No symbolic
//! polynomial is formed, so H may be any [`Expression`]; on a polynomial H the coefficients are
//! those of the symbolic series (tested from Python to 1e-14).
//!
//! The realization's source map acts on series through [`SeriesSource`]: a polynomial map
//! (the order-n realization of a polynomial bivector, exact for a constant one) or the
//! exponential chart of a Lie algebra (the Bernoulli series, which the truncation makes finite).

use crate::dual::{Dual1, Jet2, Scalar};
use crate::error::CoreError;
use crate::expression::Expression;
use crate::realization::Generating;
use crate::series::{eval_expression, SeriesRegisters, SeriesSpace};
use crate::structures::lie_groupoid::bernoulli_over_factorial;
use crate::structures::polynomial::SparsePolynomial;

/// The source map sou(x, p) of a realization on series (x fibre, p base; N series each, laid
/// out one after another).
pub trait SeriesSource<const N: usize>: Sync {
    /// Scratch series the evaluation needs.
    fn scratch_series(&self) -> usize;
    fn sou_series(
        &self,
        space: &SeriesSpace,
        fibre: &[f64],
        base: &[f64],
        out: &mut [f64],
        scratch: &mut [f64],
    );
}

/// sou as N polynomials in (fibre, base), 2N variables.
#[derive(Clone, Debug)]
pub struct PolynomialSource<const N: usize> {
    maps: Vec<SparsePolynomial>,
}

impl<const N: usize> PolynomialSource<N> {
    pub fn new(maps: Vec<SparsePolynomial>) -> Result<Self, CoreError> {
        if maps.len() != N || maps.iter().any(|m| m.vars() != 2 * N) {
            return Err(CoreError::Invalid(format!(
                "sou must be {N} polynomials in {} variables (fibre, base)",
                2 * N
            )));
        }
        Ok(PolynomialSource { maps })
    }
}

impl<const N: usize> SeriesSource<N> for PolynomialSource<N> {
    fn scratch_series(&self) -> usize {
        2
    }

    fn sou_series(
        &self,
        space: &SeriesSpace,
        fibre: &[f64],
        base: &[f64],
        out: &mut [f64],
        scratch: &mut [f64],
    ) {
        let m = space.len();
        let (term, tmp) = scratch.split_at_mut(m);
        let tmp = &mut tmp[..m];
        let var = |v: usize| -> &[f64] {
            if v < N {
                &fibre[v * m..(v + 1) * m]
            } else {
                &base[(v - N) * m..(v - N + 1) * m]
            }
        };
        for (i, map) in self.maps.iter().enumerate() {
            let o = &mut out[i * m..(i + 1) * m];
            o.fill(0.0);
            for (c, e) in map.terms() {
                let degree: u32 = e.iter().map(|&v| u32::from(v)).sum();
                if degree == 0 {
                    o[0] += c;
                    continue;
                }
                if degree == 1 {
                    // A linear term needs no product (all of a constant bracket's).
                    let v = e.iter().position(|&x| x == 1).unwrap_or(0);
                    for (a, b) in o.iter_mut().zip(var(v)) {
                        *a += c * b;
                    }
                    continue;
                }
                term.fill(0.0);
                term[0] = c;
                for (v, &ev) in e.iter().enumerate() {
                    for _ in 0..ev {
                        space.mul(term, var(v), tmp);
                        term.copy_from_slice(tmp);
                    }
                }
                for (a, b) in o.iter_mut().zip(term.iter()) {
                    *a += b;
                }
            }
        }
    }
}

/// The exponential chart of a Lie algebra: sou(x, p) = Σ_n (Bₙ/n!) Aⁿ p with A = ad_xᵀ,
/// (ad_xᵀ)_{jk} = Σ_i c[i][j][k] x_i — the same series as
/// [`crate::structures::lie_groupoid::Groupoid`]'s, cut where the truncation makes its terms
/// vanish (x = ∂S/∂p is O(t)).
#[derive(Clone, Debug)]
pub struct LieSource<const N: usize> {
    /// The non-zero structure constants (i, j, k, c[i][j][k]).
    constants: Vec<(usize, usize, usize, f64)>,
}

impl<const N: usize> LieSource<N> {
    pub fn new(c: &[[[f64; N]; N]; N]) -> Self {
        let mut constants = Vec::new();
        for (i, ci) in c.iter().enumerate() {
            for (j, cij) in ci.iter().enumerate() {
                for (k, &v) in cij.iter().enumerate() {
                    if v != 0.0 {
                        constants.push((i, j, k, v));
                    }
                }
            }
        }
        LieSource { constants }
    }
}

impl<const N: usize> SeriesSource<N> for LieSource<N> {
    fn scratch_series(&self) -> usize {
        2 * N + 1
    }

    fn sou_series(
        &self,
        space: &SeriesSpace,
        fibre: &[f64],
        base: &[f64],
        out: &mut [f64],
        scratch: &mut [f64],
    ) {
        let m = space.len();
        let b = bernoulli_over_factorial();
        let (term, rest) = scratch.split_at_mut(N * m);
        let (next, rest) = rest.split_at_mut(N * m);
        let tmp = &mut rest[..m];
        term.copy_from_slice(&base[..N * m]);
        out[..N * m].copy_from_slice(&base[..N * m]);
        // x = ∂S/∂p carries a factor t, so Aⁿ p is past the t-degree for n > K.
        for &bn in &b[1..=usize::from(space.t_degree())] {
            next.fill(0.0);
            for &(i, j, k, c) in &self.constants {
                space.mul(&fibre[i * m..(i + 1) * m], &term[k * m..(k + 1) * m], tmp);
                for (a, v) in next[j * m..(j + 1) * m].iter_mut().zip(tmp.iter()) {
                    *a += c * v;
                }
            }
            term.copy_from_slice(next);
            if bn != 0.0 {
                for (o, v) in out[..N * m].iter_mut().zip(term.iter()) {
                    *o += bn * v;
                }
            }
        }
    }
}

/// Where the jet of S(h, ·) sits in a series: per t-power a, the coefficient of t^a, t^a δ_i and
/// t^a δ_i δ_j (i ≤ j, packed as [`Jet2`]).
#[derive(Clone, Debug)]
struct JetIndex {
    value: Vec<usize>,
    grad: Vec<[usize; 32]>,
    hess: Vec<Vec<usize>>,
}

/// S(t, p) by the HJ recursion on series, for an [`Expression`] H of the first
/// `hamiltonian.vars()` coordinates (an affine system's H does not see the central one).
#[derive(Clone, Debug)]
pub struct JetGenerating<const N: usize, R> {
    hamiltonian: Expression,
    source: R,
    space: SeriesSpace,
    order: usize,
    index: JetIndex,
}

/// The series buffers of one [`JetGenerating`] evaluation.
#[derive(Clone, Debug)]
pub struct JetWorkspace {
    s: Vec<f64>,
    fibre: Vec<f64>,
    base: Vec<f64>,
    sou: Vec<f64>,
    h: Vec<f64>,
    scratch: Vec<f64>,
    regs: SeriesRegisters,
}

fn try_zeros(n: usize) -> Result<Vec<f64>, CoreError> {
    let mut v = Vec::new();
    v.try_reserve_exact(n)
        .map_err(|_| CoreError::Memory("the series workspace".into()))?;
    v.resize(n, 0.0);
    Ok(v)
}

/// Largest Taylor order by jets.
pub const MAX_JET_ORDER: usize = 8;

impl<const N: usize, R: SeriesSource<N>> JetGenerating<N, R> {
    /// Taylor-HJ of order `order` (S truncated after t^order).
    pub fn new(hamiltonian: Expression, source: R, order: usize) -> Result<Self, CoreError> {
        if !(1..=MAX_JET_ORDER).contains(&order) {
            return Err(CoreError::Invalid(format!(
                "the Taylor order by jets must be in 1..={MAX_JET_ORDER}, got {order}"
            )));
        }
        if hamiltonian.vars() > N || N >= 32 {
            return Err(CoreError::Invalid(format!(
                "H has {} variables; the realization has {N}",
                hamiltonian.vars()
            )));
        }
        let space = SeriesSpace::new(N + 1, order as u8, order as u8 + 2)?;
        let mut e = [0u8; 33];
        // Every t^a δ^α with a ≤ order and |α| ≤ 2 is in the truncation (total ≤ order + 2).
        let find = |e: &[u8]| {
            space
                .index_of(e)
                .ok_or_else(|| CoreError::Invalid("a jet coefficient outside the series".into()))
        };
        let mut value = Vec::new();
        let mut grad = Vec::new();
        let mut hess = Vec::new();
        for a in 1..=order {
            e.fill(0);
            e[0] = a as u8;
            value.push(find(&e[..=N])?);
            let mut g = [0usize; 32];
            for (i, gi) in g.iter_mut().enumerate().take(N) {
                e[i + 1] += 1;
                *gi = find(&e[..=N])?;
                e[i + 1] -= 1;
            }
            grad.push(g);
            let mut hs = Vec::new();
            for i in 0..N {
                for j in i..N {
                    e[i + 1] += 1;
                    e[j + 1] += 1;
                    hs.push(find(&e[..=N])?);
                    e[i + 1] -= 1;
                    e[j + 1] -= 1;
                }
            }
            hess.push(hs);
        }
        Ok(JetGenerating {
            hamiltonian,
            source,
            space,
            order,
            index: JetIndex { value, grad, hess },
        })
    }

    pub fn order(&self) -> usize {
        self.order
    }

    /// Coefficients of one series (the cost grows with it and with the product table).
    pub fn series_len(&self) -> usize {
        self.space.len()
    }

    pub fn try_workspace(&self) -> Result<JetWorkspace, CoreError> {
        let m = self.space.len();
        Ok(JetWorkspace {
            s: try_zeros(m)?,
            fibre: try_zeros(N * m)?,
            base: try_zeros(N * m)?,
            sou: try_zeros(N * m)?,
            h: try_zeros(m)?,
            scratch: try_zeros(self.source.scratch_series() * m)?,
            regs: SeriesRegisters::new(&self.space, &self.hamiltonian)?,
        })
    }

    /// Bytes of one workspace.
    pub fn workspace_bytes(&self) -> usize {
        let m = self.space.len();
        (1 + 3 * N + 1 + self.source.scratch_series()) * m * 8
            + SeriesRegisters::bytes(&self.space, &self.hamiltonian)
    }

    /// The series of S(t, p + δ) into `ws.s`.
    fn solve(&self, p: &[f64; N], ws: &mut JetWorkspace) {
        let space = &self.space;
        let m = space.len();
        ws.base.fill(0.0);
        for (i, pi) in p.iter().enumerate() {
            ws.base[i * m] = *pi;
            // δ_i is the monomial right after t in degree order (index 0 the constant, 1 t).
            let k = 2 + i;
            ws.base[i * m + k] = 1.0;
        }
        ws.s.fill(0.0);
        for sweep in 0..self.order {
            for i in 0..N {
                if sweep == 0 {
                    ws.fibre[i * m..(i + 1) * m].fill(0.0);
                } else {
                    space.derivative(&ws.s, i + 1, &mut ws.fibre[i * m..(i + 1) * m]);
                }
            }
            self.source
                .sou_series(space, &ws.fibre, &ws.base, &mut ws.sou, &mut ws.scratch);
            let inputs: [&[f64]; N] = std::array::from_fn(|i| &ws.sou[i * m..(i + 1) * m]);
            eval_expression(
                space,
                &self.hamiltonian,
                &inputs[..self.hamiltonian.vars()],
                &mut ws.h,
                &mut ws.regs,
            );
            space.integral(&ws.h, &mut ws.s);
            for v in ws.s.iter_mut() {
                *v = -*v;
            }
        }
    }
}

impl<const N: usize, R: SeriesSource<N>> Generating<N> for JetGenerating<N, R> {
    type Workspace = JetWorkspace;

    fn workspace(&self) -> JetWorkspace {
        self.try_workspace()
            .unwrap_or_else(|e| crate::memory::panic_out_of_memory(&e))
    }

    fn jet(&self, t: f64, p: &[f64; N], ws: &mut JetWorkspace) -> Jet2<N> {
        self.solve(p, ws);
        let mut jet = Jet2::<N>::cst(0.0);
        let mut tk = 1.0;
        for a in 0..self.order {
            tk *= t;
            jet.v += tk * ws.s[self.index.value[a]];
            for i in 0..N {
                jet.g[i] += tk * ws.s[self.index.grad[a][i]];
            }
            let mut k = 0;
            let packed = jet.packed_mut();
            for i in 0..N {
                for j in i..N {
                    // The coefficient of δ_i² is half the second derivative.
                    let f = if i == j { 2.0 } else { 1.0 };
                    packed[k] += f * tk * ws.s[self.index.hess[a][k]];
                    k += 1;
                }
            }
        }
        jet
    }

    fn gradient(&self, t: f64, p: &[f64; N], ws: &mut JetWorkspace) -> Dual1<N> {
        self.solve(p, ws);
        let mut d = Dual1::<N>::default();
        let mut tk = 1.0;
        for a in 0..self.order {
            tk *= t;
            d.v += tk * ws.s[self.index.value[a]];
            for i in 0..N {
                d.g[i] += tk * ws.s[self.index.grad[a][i]];
            }
        }
        d
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// so(3) with H = ½|μ|²/I: S₁ = −H exactly, and S₂ = 0 (DESIGN: S₂ vanishes in both charts).
    #[test]
    fn first_terms_on_so3_match_the_design_anchors() {
        let mut c = [[[0.0; 3]; 3]; 3];
        for (i, j, k) in [(0, 1, 2), (1, 2, 0), (2, 0, 1)] {
            c[i][j][k] = 1.0;
            c[j][i][k] = -1.0;
        }
        // H = x0²/3 + x1²/4 + x2²/5: code var, var, var, powi, ... built by hand.
        let code = [0, 0, 0, 7, 7, 7, 1, 1, 1, 4, 4, 4, 2, 2];
        let a = [0, 1, 2, 0, 1, 2, 0, 0, 0, 3, 4, 5, 9, 12];
        let b = [0, 0, 0, 2, 2, 2, 0, 0, 0, 6, 7, 8, 10, 11];
        let cc = [
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            1.0 / 3.0,
            0.25,
            0.2,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
        ];
        let h = Expression::from_table(3, &code, &a, &b, &cc).unwrap();
        let g = JetGenerating::<3, _>::new(h, LieSource::new(&c), 3).unwrap();
        let mut ws = g.try_workspace().unwrap();
        let p = [0.3, -0.2, 0.5];
        g.solve(&p, &mut ws);
        let s1 = ws.s[g.index.value[0]];
        let h0 = p[0] * p[0] / 3.0 + p[1] * p[1] / 4.0 + p[2] * p[2] / 5.0;
        assert!((s1 + h0).abs() < 1e-15);
        assert!(ws.s[g.index.value[1]].abs() < 1e-15);
        // S₃ from DESIGN's Cayley test vector differs in the exp chart; its p₁⁴ coefficient
        // in S₃ is checked from Python against the symbolic series.
        assert!(ws.s[g.index.value[2]].is_finite());
    }
}

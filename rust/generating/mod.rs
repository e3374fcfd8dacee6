//! Generating functions S(t, p) = P(t, p) + t^m · N(t, p).
//!
//! P is a sparse polynomial (exact Taylor terms, or −tH) and N a tanh MLP with inputs (t, p),
//! p ∈ R^N for a Lie algebra of dimension N (a const generic: N = 3 for the rigid body, 6 for the
//! heavy top). A step only needs ∂S/∂p and ∂²S/∂p² at fixed t = h; both come out of one
//! forward-mode pass.

// Index loops over small fixed-size vectors and matrices read as the formulas they implement.
#![allow(clippy::needless_range_loop)]

mod mlp;
mod network_lanes;
mod polynomial;
pub mod polynomial_lanes;
mod workspace;

#[cfg(test)]
pub(crate) use mlp::narrow_gemm;
pub(crate) use mlp::tanh_fast_rows;
pub use mlp::{tanh_fast, tanh_fast_fma, Layer, Mlp};
pub use network_lanes::{
    scratch_len, LaneRow, NetworkLanes, NETWORK_LANES_MAX_DIM, NETWORK_LANES_MAX_WIDTH,
};
pub(crate) use polynomial::TABLE_POWER;
pub use polynomial::{Monomial, Polynomial};
pub use workspace::Workspace;

use crate::dual::{Dual1, Jet2, Scalar, Variable};
use crate::error::CoreError;
use crate::isa::{Isa, LANES};
use crate::memory::try_filled;

/// Most trajectories one batched evaluation takes.
pub const MAX_BATCH: usize = 32;

/// Batches of at most this many momenta take per-call scratch arrays sized for it rather than
/// for [`MAX_BATCH`] (a rollout of one state steps through the batched path too).
const FEW: usize = 4;

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
        if let Some(m) = polynomial.terms().iter().find(|m| m.t_power == 0) {
            return Err(CoreError::Format(format!(
                "polynomial term with t-power 0 (p-powers {:?}) would break S(0, p) = 0",
                m.p_powers
            )));
        }
        if let Some(m) = polynomial.terms().iter().find(|m| !m.coeff.is_finite()) {
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
        let lanes = Workspace::lane_len(self);
        let what = "the evaluation workspace (a very wide layer?)";
        Ok(Workspace {
            lanes: try_filled(lanes, [0.0; LANES], what)?,
            jet_a: try_filled(w, Jet2::default(), what)?,
            jet_b: try_filled(w, Jet2::default(), what)?,
            d1_a: try_filled(w, Dual1::default(), what)?,
            d1_b: try_filled(w, Dual1::default(), what)?,
            batch_a: try_filled(batch, 0.0, what)?,
            batch_b: try_filled(batch, 0.0, what)?,
            acts: try_filled(acts, 0.0, what)?,
        })
    }

    /// The network term in the form the lane Newton solvers take, where there is one, N is at
    /// most [`NETWORK_LANES_MAX_DIM`] and its layers fit the lanes
    /// ([`NETWORK_LANES_MAX_WIDTH`]).
    pub fn network_lanes(&self) -> Option<NetworkLanes<'_>> {
        if N > NETWORK_LANES_MAX_DIM {
            return None;
        }
        NetworkLanes::new(self.mlp.as_ref()?, self.mlp_power, self.inputs)
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
        polynomial_lanes::polynomial_gradients(&self.polynomial, Isa::detect(), t, p, out);
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
                polynomial_lanes::polynomial_gradients(&self.polynomial, isa, t, pb, &mut d[..n]);
                for (o, d) in ob.iter_mut().zip(&d) {
                    *o = T::from_components(|c| if c == 0 { d.v } else { d.g[c - 1] });
                }
            } else {
                let mut j = [Jet2::<N>::default(); CAP];
                polynomial_lanes::polynomial_jets(&self.polynomial, isa, t, pb, &mut j[..n]);
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

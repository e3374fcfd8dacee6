//! The network term t^m · f · N(inputs) of a generating function in SIMD lanes: its value,
//! exact p-gradient and (when asked) p-Hessian at L momenta, one lane per trajectory.
//!
//! The batched kernel ([`super::GeneratingFunction::jets`]) runs a layer as a matrix product over
//! a batch and pays off for wide layers; the shipped models have hidden layers of 4 to 32 units,
//! where the per-trajectory chart and Newton solve around it cost more than the layers. Here the
//! network runs inside the lane Newton solvers ([`crate::lanes_bisection`]) instead: every unit
//! holds its value and N tangents (first derivatives) as lane vectors, a layer is a sum of
//! weighted tangents, one adjoint comes back, and the Hessian is a sum of outer products of the
//! units' tangents (tanh is the only nonlinearity).
//!
//! **Bit identity.** Every lane performs the same operations in the same order (multiplies,
//! adds, fused multiply-adds, IEEE square root and division, [`tanh_fast_fma`]), so one
//! trajectory (L = 1) and a block (L = [`crate::isa::LANES`]) give the same bits whatever the
//! instruction set: IEEE 754 rounds a fused multiply-add once, in an FMA instruction and in
//! the C library's software `fma` alike. The AVX2+FMA solvers (every block and every lone
//! trajectory on such a CPU) run it as one instruction; the portable build calls the library
//! per operation, slower, with the same bits. The numbers agree with the scalar forward mode
//! to round-off (tested), not bit for bit: the scalar path's tanh is libm's.
//!
//! Fused, a weight's multiply-add is one instruction where it was two: with the Hessian's sums
//! in registers as well (`add_outer_products`), the learned heavy top's step (layers of 32)
//! took 0.80–0.86× the plain form's time (docs/performance.md).

// Index loops over lanes, units and components read as the formulas they evaluate.
#![allow(clippy::needless_range_loop)]

use super::polynomial_lanes::JetLanes;
use super::{tanh_fast_fma, tanh_fast_rows, Layer, Mlp, MlpInputs, HOMOGENEOUS_MIN_R2};
use crate::isa::LANES;

/// Widest layer the lane path takes: wider networks keep the batched kernel, whose matrix
/// products beat forward mode per trajectory.
pub const NETWORK_LANES_MAX_WIDTH: usize = 32;

/// Largest N whose steps take the network in lanes (every structure the lane solvers cover).
/// With the Hessian from tangents and one adjoint, the heavy top's model (N = 6, hidden layers
/// of 32) steps in 0.60× the batched kernel's time; with whole jets (1 + N + N(N+1)/2 rows a
/// unit) it took 1.25×.
pub const NETWORK_LANES_MAX_DIM: usize = 6;

/// The network term of a generating function, as the lane solvers evaluate it.
#[derive(Clone, Copy, Debug)]
pub struct NetworkLanes<'a> {
    pub mlp: &'a Mlp,
    /// m in t^m · N.
    pub power: u32,
    pub inputs: MlpInputs,
}

/// Lane rows one unit takes in the Hessian pass (`NetworkLanes::tangent_jet`): its value, N
/// tangents of y and N of z.
pub const fn unit_rows(n: usize) -> usize {
    1 + 2 * n
}

/// One row of the scratch: a number per lane of a block (a one-lane solve uses lane 0).
pub type LaneRow = [f64; LANES];

/// Rows of scratch [`NetworkLanes::add_jet_lanes`] needs: every unit's value and tangents plus
/// two adjoint rows a unit of the widest layer for the Hessian, or every unit's value and the
/// same adjoint rows for the gradient alone.
pub fn scratch_len(mlp: &Mlp, n: usize) -> usize {
    let width = mlp.max_width().max(n + 1);
    let units = n + 1 + mlp.layers.iter().map(|l| l.n_out).sum::<usize>();
    units * unit_rows(n) + 2 * width
}

/// Lanes 0..L of a row.
#[inline(always)]
fn get<const L: usize>(row: &LaneRow) -> [f64; L] {
    std::array::from_fn(|l| row[l])
}

/// Writes lanes 0..L of a row.
#[inline(always)]
fn put<const L: usize>(row: &mut LaneRow, v: &[f64; L]) {
    row[..L].copy_from_slice(v);
}

impl<'a> NetworkLanes<'a> {
    /// The lane form of a network term, where its layers fit [`NETWORK_LANES_MAX_WIDTH`].
    pub fn new(mlp: &'a Mlp, power: u32, inputs: MlpInputs) -> Option<Self> {
        let fits = mlp.max_width() <= NETWORK_LANES_MAX_WIDTH && mlp.n_inputs() <= MAX_INPUTS;
        fits.then_some(NetworkLanes { mlp, power, inputs })
    }

    /// `jet` += t^m · f · N at the L momenta `p[i][l]` (the Hessian only when `HESS`), where f
    /// and the inputs are those of [`MlpInputs`]. `buf` holds at least
    /// [`scratch_len`]`(mlp, N)` rows; nothing in it needs clearing. Lanes whose homogeneous
    /// term vanishes (|p|² ≤ [`HOMOGENEOUS_MIN_R2`]) get nothing added, as in the scalar path.
    ///
    /// With the Hessian every unit carries its value and N tangents forward and one adjoint
    /// comes back ([`Self::tangent_jet`]); without it (most simplified-Newton updates) only the
    /// values go forward, 2 lane operations a weight instead of 2 + N.
    // Inlined into the lane solvers in optimised builds (so that it runs with their AVX2
    // features); a call of its own in debug builds, where every inlined local keeps its own
    // stack slot and the so(3) and se(3) blocks overflowed a test thread's stack.
    #[cfg_attr(not(debug_assertions), inline(always))]
    #[cfg_attr(debug_assertions, inline(never))]
    pub(crate) fn add_jet_lanes<const N: usize, const L: usize, const HESS: bool>(
        &self,
        t: f64,
        p: &[[f64; L]; N],
        buf: &mut [LaneRow],
        jet: &mut JetLanes<N, L>,
    ) {
        let (inputs, factor, vanish) = self.inputs_lanes::<N, L, HESS>(t, p);
        let net = if HESS {
            self.tangent_jet::<N, L>(&inputs, buf)
        } else {
            self.reverse_gradient::<N, L>(&inputs, buf)
        };
        let term = product::<N, L, HESS>(&factor, &net);
        for l in (0..L).filter(|&l| !vanish[l]) {
            jet.v[l] += term.v[l];
            for a in 0..N {
                jet.g[a][l] += term.g[a][l];
                if HESS {
                    for b in a..N {
                        jet.h[a][b][l] += term.h[a][b][l];
                    }
                }
            }
        }
    }

    /// The network's 1 + N input jets, the factor that multiplies its output (t^m, or
    /// t^m |p|^(m+1) for the homogeneous map) and the lanes where the term vanishes.
    #[inline(always)]
    fn inputs_lanes<const N: usize, const L: usize, const HESS: bool>(
        &self,
        t: f64,
        p: &[[f64; L]; N],
    ) -> (InputJets<N, L>, JetLanes<N, L>, [bool; L]) {
        let tm = t.powi(self.power as i32);
        let mut vanish = [false; L];
        match self.inputs {
            MlpInputs::Plain => (InputJets::Plain { t, p: *p }, constant([tm; L]), vanish),
            MlpInputs::Homogeneous => {
                // r = |p| and u = p / r; lanes at the origin take r² = 1 (finite numbers, then
                // dropped). The inputs' derivatives are closed forms in u and 1/r
                // (`InputJets::Homogeneous`); jets of |p|², r, 1/r and p_i/r by the chain rule
                // cost the learned rigid body 11 % of its step.
                let mut r2 = [0.0; L];
                for i in 0..N {
                    for l in 0..L {
                        r2[l] += p[i][l] * p[i][l];
                    }
                }
                for l in 0..L {
                    if r2[l] <= HOMOGENEOUS_MIN_R2 {
                        vanish[l] = true;
                        r2[l] = 1.0;
                    }
                }
                let r: [f64; L] = std::array::from_fn(|l| r2[l].sqrt());
                let ir: [f64; L] = std::array::from_fn(|l| 1.0 / r[l]);
                let u: [[f64; L]; N] =
                    std::array::from_fn(|i| std::array::from_fn(|l| p[i][l] * ir[l]));
                // F = t^m r^k (k = m + 1): ∇F = t^m k r^(k−1) u and
                // ∇²F = t^m k r^(k−2) (I + (k − 2) u uᵀ); r's powers by repeated products.
                let k = self.power + 1;
                let mut factor = constant::<N, L>([0.0; L]);
                for l in 0..L {
                    let x = r[l];
                    let (mut acc, mut below, mut two_below) = (1.0, 1.0, 1.0);
                    for e in 0..k {
                        if e + 2 == k {
                            two_below = acc;
                        }
                        if e + 1 == k {
                            below = acc;
                        }
                        acc *= x;
                    }
                    factor.v[l] = tm * acc;
                    let d1 = tm * f64::from(k) * below;
                    for a in 0..N {
                        factor.g[a][l] = d1 * u[a][l];
                    }
                    if HESS {
                        let d2 = tm * f64::from(k) * two_below;
                        let bend = f64::from(k) - 2.0;
                        for a in 0..N {
                            for b in a..N {
                                let delta = if a == b { 1.0 } else { 0.0 };
                                factor.h[a][b][l] = d2 * (delta + bend * u[a][l] * u[b][l]);
                            }
                        }
                    }
                }
                (InputJets::Homogeneous { t, r, ir, u }, factor, vanish)
            }
        }
    }

    /// N's jet with its Hessian by tangents forward and one adjoint back. Every unit carries its
    /// value and N tangents (1 + N lane rows a weight, where a jet would take 1 + N + N(N+1)/2);
    /// tanh is the network's only nonlinearity, so the Hessian is
    /// ∇²N = Σ_hidden units ȳ · tanh″(z) · ∇z ∇zᵀ + Σ_inputs x̄_i ∇²x_i,
    /// with ȳ and x̄ the adjoints of the reverse pass (∂N/∂y, ∂N/∂x) and ∇z the unit's tangents.
    /// A unit holds 1 + 2N rows in `buf`: y, ∇y (what the next layer sums) and ∇z (what the
    /// outer product takes); the inputs use the first 1 + N.
    #[inline(always)]
    fn tangent_jet<const N: usize, const L: usize>(
        &self,
        inputs: &InputJets<N, L>,
        buf: &mut [LaneRow],
    ) -> JetLanes<N, L> {
        let layers = &self.mlp.layers;
        let c = unit_rows(N);
        let units = N + 1 + layers.iter().map(|l| l.n_out).sum::<usize>();
        let width = self.mlp.max_width().max(N + 1);
        let (rows, rest) = buf[..units * c + 2 * width].split_at_mut(units * c);
        let (mut delta, mut grad) = rest.split_at_mut(width);
        // Plain inputs' tangents are 0 and the unit vectors, so the first layer's tangents are
        // its weight columns (below) and the input rows hold the values alone.
        let plain = matches!(inputs, InputJets::Plain { .. });
        for i in 0..=N {
            put(&mut rows[i * c], &inputs.value(i));
            if !plain {
                for a in 0..N {
                    put(&mut rows[i * c + 1 + a], &inputs.tangent(i, a));
                }
            }
        }
        let last = layers.len() - 1;
        let mut base = 0;
        for (depth, layer) in layers.iter().enumerate() {
            let (src, dst) = rows[base * c..].split_at_mut(layer.n_in * c);
            for k in 0..layer.n_out {
                let row = &layer.weight[k * layer.n_in..(k + 1) * layer.n_in];
                let mut v = [layer.bias[k]; L];
                let mut d = [[0.0; L]; N];
                if depth == 0 && plain {
                    for (j, &w) in row.iter().enumerate() {
                        for l in 0..L {
                            v[l] = w.mul_add(src[j * c][l], v[l]);
                        }
                    }
                    // Σ_j w_j ∂x_j/∂p_a from 0 adds the ±0 products and w_(1+a)·1: exactly
                    // 0 + w_(1+a) (the weights are finite), the bits of the full sum, fused or
                    // not.
                    for a in 0..N {
                        d[a] = [0.0 + row[1 + a]; L];
                    }
                } else {
                    for (j, &w) in row.iter().enumerate() {
                        let x = &src[j * c..j * c + 1 + N];
                        for l in 0..L {
                            v[l] = w.mul_add(x[0][l], v[l]);
                        }
                        for a in 0..N {
                            for l in 0..L {
                                d[a][l] = w.mul_add(x[1 + a][l], d[a][l]);
                            }
                        }
                    }
                }
                let out = &mut dst[k * c..(k + 1) * c];
                put(&mut out[0], &v);
                // The output's tangents are the gradient; a hidden unit's are ∇z, kept for the
                // outer product, with ∇y = tanh′(z) ∇z written once y is known.
                let at = if depth < last { 1 + N } else { 1 };
                for a in 0..N {
                    put(&mut out[at + a], &d[a]);
                }
            }
            if depth < last {
                // Every unit's tanh first (independent chains, in lockstep), then ∇y.
                tanh_units::<L>(dst, c, layer.n_out);
                for k in 0..layer.n_out {
                    let u = &mut dst[k * c..(k + 1) * c];
                    let s: [f64; L] = std::array::from_fn(|l| (-u[0][l]).mul_add(u[0][l], 1.0));
                    for a in 0..N {
                        for l in 0..L {
                            u[1 + a][l] = s[l] * u[1 + N + a][l];
                        }
                    }
                }
            }
            base += layer.n_in;
        }
        // `base` is the output unit.
        let mut out = constant::<N, L>(get(&rows[base * c]));
        for a in 0..N {
            out.g[a] = get(&rows[base * c + 1 + a]);
        }
        put(&mut delta[0], &[1.0; L]);
        for (depth, layer) in layers.iter().enumerate().rev() {
            adjoint_through::<L>(layer, delta, grad);
            base -= layer.n_in;
            if depth > 0 {
                // grad holds ȳ of the layer below: its Hessian term, then z̄ = ȳ tanh′(z). A
                // unit's y is not read again, so its row takes the curvature ȳ · tanh″(z).
                let below = &mut rows[base * c..(base + layer.n_in) * c];
                for (j, u) in below.chunks_exact_mut(c).enumerate() {
                    for l in 0..L {
                        let y = u[0][l];
                        let s = (-y).mul_add(y, 1.0);
                        u[0][l] = grad[j][l] * (-2.0 * y * s);
                        grad[j][l] *= s;
                    }
                }
                add_outer_products::<N, L>(below, &mut out.h);
            }
            std::mem::swap(&mut delta, &mut grad);
        }
        // delta holds x̄; the plain inputs (t and p) are linear in p and add nothing.
        inputs.add_curvature(delta, &mut out.h);
        out
    }

    /// N and its gradient (no Hessian) by reverse mode: the values forward, keeping every
    /// layer's activations in `buf`, then one adjoint back to the inputs, whose gradients carry
    /// it to p.
    #[inline(always)]
    fn reverse_gradient<const N: usize, const L: usize>(
        &self,
        inputs: &InputJets<N, L>,
        buf: &mut [LaneRow],
    ) -> JetLanes<N, L> {
        let layers = &self.mlp.layers;
        let width = self.mlp.max_width().max(N + 1);
        let rows = N + 1 + layers.iter().map(|l| l.n_out).sum::<usize>();
        let (acts, rest) = buf.split_at_mut(rows);
        let (mut delta, rest) = rest.split_at_mut(width);
        let mut grad = &mut rest[..width];
        for i in 0..=N {
            put(&mut acts[i], &inputs.value(i));
        }
        let last = layers.len() - 1;
        let mut off = 0;
        for (depth, layer) in layers.iter().enumerate() {
            let (x, z) = acts[off..].split_at_mut(layer.n_in);
            for k in 0..layer.n_out {
                let row = &layer.weight[k * layer.n_in..(k + 1) * layer.n_in];
                let mut acc = [layer.bias[k]; L];
                for (j, &w) in row.iter().enumerate() {
                    for l in 0..L {
                        acc[l] = w.mul_add(x[j][l], acc[l]);
                    }
                }
                put(&mut z[k], &acc);
            }
            if depth < last {
                tanh_units::<L>(z, 1, layer.n_out);
            }
            off += layer.n_in;
        }
        // `off` is the output row. Adjoints: δ = 1 at the output, g = Wᵀ δ through a layer,
        // δ = g ⊙ (1 − y²) through a hidden activation y.
        let value: [f64; L] = get(&acts[off]);
        put(&mut delta[0], &[1.0; L]);
        for (depth, layer) in layers.iter().enumerate().rev() {
            adjoint_through::<L>(layer, delta, grad);
            off -= layer.n_in;
            if depth > 0 {
                for j in 0..layer.n_in {
                    let y = acts[off + j];
                    for l in 0..L {
                        grad[j][l] *= (-y[l]).mul_add(y[l], 1.0);
                    }
                }
            }
            std::mem::swap(&mut delta, &mut grad);
        }
        // ∂N/∂p_a = Σ_i adj_i ∂in_i/∂p_a.
        let mut out = constant::<N, L>(value);
        for i in 0..=N {
            for a in 0..N {
                let g = inputs.tangent(i, a);
                for l in 0..L {
                    out.g[a][l] = delta[i][l].mul_add(g[l], out.g[a][l]);
                }
            }
        }
        out
    }
}

/// `h` += Σ_units curv · ∇z ∇zᵀ (upper triangle) over a layer's unit rows (curvature in row 0,
/// ∇z in rows 1 + N …), each entry summed over the units in order, in registers: three entries
/// of a row of `h` a sweep over the units, (curv ∂_a z) · ∂_b z fused into each (an entry
/// stored and reloaded every unit made the learned heavy top's step depend on where the
/// compiler placed `h`: 1.9× with the same operations).
#[inline(always)]
fn add_outer_products<const N: usize, const L: usize>(
    units: &[LaneRow],
    h: &mut [[[f64; L]; N]; N],
) {
    const B: usize = 3;
    let c = unit_rows(N);
    for a in 0..N {
        let mut b0 = a;
        while b0 < N {
            let nb = (N - b0).min(B);
            let mut acc = [[0.0; L]; B];
            acc[..nb].copy_from_slice(&h[a][b0..b0 + nb]);
            for u in units.chunks_exact(c) {
                let cza: [f64; L] = std::array::from_fn(|l| u[0][l] * u[1 + N + a][l]);
                for i in 0..nb {
                    let zb: [f64; L] = get(&u[1 + N + b0 + i]);
                    for l in 0..L {
                        acc[i][l] = cza[l].mul_add(zb[l], acc[i][l]);
                    }
                }
            }
            h[a][b0..b0 + nb].copy_from_slice(&acc[..nb]);
            b0 += B;
        }
    }
}

/// g = Wᵀ δ through one layer: the input adjoints (`grad`, n_in rows) from the output ones
/// (`delta`, n_out rows). Each g_j is summed over k in order, as a register accumulator, four
/// inputs at a time so that each δ_k is loaded once for them (summing into `grad` row by row
/// stored and reloaded every row n_out times: 11 % of a learned rigid-body step).
#[inline(always)]
fn adjoint_through<const L: usize>(layer: &Layer, delta: &[LaneRow], grad: &mut [LaneRow]) {
    const J: usize = 4;
    let (n_in, n_out) = (layer.n_in, layer.n_out);
    let mut j = 0;
    while j + J <= n_in {
        let mut acc = [[0.0; L]; J];
        for k in 0..n_out {
            let d: [f64; L] = get(&delta[k]);
            let w = &layer.weight[k * n_in + j..k * n_in + j + J];
            for b in 0..J {
                for l in 0..L {
                    acc[b][l] = w[b].mul_add(d[l], acc[b][l]);
                }
            }
        }
        for b in 0..J {
            put(&mut grad[j + b], &acc[b]);
        }
        j += J;
    }
    for j in j..n_in {
        let mut acc = [0.0; L];
        for k in 0..n_out {
            let d: [f64; L] = get(&delta[k]);
            let w = layer.weight[k * n_in + j];
            for l in 0..L {
                acc[l] = w.mul_add(d[l], acc[l]);
            }
        }
        put(&mut grad[j], &acc);
    }
}

/// tanh (lanes 0..L) of the rows `rows[k · stride]`, k < n (one layer's units), four units in
/// lockstep ([`tanh_fast_rows`], the bits of [`tanh_fast_fma`]) and the rest one at a time.
#[inline(always)]
fn tanh_units<const L: usize>(rows: &mut [LaneRow], stride: usize, n: usize) {
    const R: usize = 4;
    let mut k = 0;
    while k + R <= n {
        let mut block: [[f64; L]; R] = std::array::from_fn(|i| get(&rows[(k + i) * stride]));
        tanh_fast_rows::<true, R, L>(&mut block);
        for (i, v) in block.iter().enumerate() {
            put(&mut rows[(k + i) * stride], v);
        }
        k += R;
    }
    for k in k..n {
        let u = &mut rows[k * stride];
        for l in 0..L {
            u[l] = tanh_fast_fma(u[l]);
        }
    }
}

/// The network's 1 + N inputs (time first) at a block's momenta: what the passes read of them,
/// their values, p-tangents and, for the homogeneous map, p-Hessians.
enum InputJets<const N: usize, const L: usize> {
    /// (t, p) themselves: tangents 0 and the unit vectors, no curvature. Nothing is stored past
    /// (t, p): whole jets of the heavy top's 7 inputs (2.7 KB each, Hessians of zeros) cost a
    /// block 11 % of its step in memset and memcpy.
    Plain { t: f64, p: [[f64; L]; N] },
    /// (t r, u = p / r) with r = |p|, kept as r, 1/r and u: ∇(t r) = t u,
    /// ∂u_i/∂p_a = (δ_ia − u_i u_a)/r, and the curvature in closed form
    /// ([`InputJets::add_curvature`]).
    Homogeneous {
        t: f64,
        r: [f64; L],
        ir: [f64; L],
        u: [[f64; L]; N],
    },
}

impl<const N: usize, const L: usize> InputJets<N, L> {
    /// Input i's value in each lane.
    #[inline(always)]
    fn value(&self, i: usize) -> [f64; L] {
        match self {
            InputJets::Plain { t, p } => {
                if i == 0 {
                    [*t; L]
                } else {
                    p[i - 1]
                }
            }
            InputJets::Homogeneous { t, r, u, .. } => {
                if i == 0 {
                    std::array::from_fn(|l| t * r[l])
                } else {
                    u[i - 1]
                }
            }
        }
    }

    /// ∂(input i)/∂p_a in each lane: for plain inputs the 0 and 1 a whole jet would hold (the
    /// passes multiply by them as before, so the bits are those of the jets).
    #[inline(always)]
    fn tangent(&self, i: usize, a: usize) -> [f64; L] {
        match self {
            InputJets::Plain { .. } => [if i == 1 + a { 1.0 } else { 0.0 }; L],
            InputJets::Homogeneous { t, ir, u, .. } => {
                if i == 0 {
                    std::array::from_fn(|l| t * u[a][l])
                } else {
                    let d = if i - 1 == a { 1.0 } else { 0.0 };
                    std::array::from_fn(|l| (d - u[i - 1][l] * u[a][l]) * ir[l])
                }
            }
        }
    }

    /// `h` += Σ_i x̄_i ∇²(input i) (upper triangle) with x̄ = `adj` (1 + N rows, time first):
    /// nothing for plain inputs; for the homogeneous map, with w = Σ_i x̄_(1+i) u_i,
    /// x̄_0 t (δ_ab − u_a u_b)/r − (x̄_(1+a) u_b + x̄_(1+b) u_a + δ_ab w − 3 w u_a u_b)/r².
    #[inline(always)]
    fn add_curvature(&self, adj: &[LaneRow], h: &mut [[[f64; L]; N]; N]) {
        let InputJets::Homogeneous { t, ir, u, .. } = self else {
            return;
        };
        for l in 0..L {
            let mut w = 0.0;
            for i in 0..N {
                w += adj[1 + i][l] * u[i][l];
            }
            let (ir, tr) = (ir[l], adj[0][l] * t);
            for a in 0..N {
                for b in a..N {
                    let delta = if a == b { 1.0 } else { 0.0 };
                    let uu = u[a][l] * u[b][l];
                    let bend = adj[1 + a][l] * u[b][l] + adj[1 + b][l] * u[a][l] + delta * w
                        - 3.0 * w * uu;
                    h[a][b][l] += ir * (tr * (delta - uu) - ir * bend);
                }
            }
        }
    }
}

/// Inputs of a network the lanes take: time and a momentum of at most 7 components (covers the
/// heavy top's 6).
const MAX_INPUTS: usize = 8;

/// A constant's jet.
#[inline(always)]
fn constant<const N: usize, const L: usize>(v: [f64; L]) -> JetLanes<N, L> {
    JetLanes {
        v,
        g: [[0.0; L]; N],
        h: [[[0.0; L]; N]; N],
    }
}

/// The jet of a·b (the Hessian's upper triangle when `HESS`).
#[inline(always)]
fn product<const N: usize, const L: usize, const HESS: bool>(
    a: &JetLanes<N, L>,
    b: &JetLanes<N, L>,
) -> JetLanes<N, L> {
    let mut r = constant::<N, L>([0.0; L]);
    for l in 0..L {
        r.v[l] = a.v[l] * b.v[l];
    }
    for i in 0..N {
        for l in 0..L {
            r.g[i][l] = a.v[l] * b.g[i][l] + b.v[l] * a.g[i][l];
        }
        if HESS {
            for k in i..N {
                for l in 0..L {
                    r.h[i][k][l] = a.v[l] * b.h[i][k][l]
                        + b.v[l] * a.h[i][k][l]
                        + (a.g[i][l] * b.g[k][l] + a.g[k][l] * b.g[i][l]);
                }
            }
        }
    }
    r
}

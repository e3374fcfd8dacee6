//! Any polynomial bivector with any smooth Hamiltonian: the vector field ẋ = π(x) ∇H(x) of an
//! [`Expression`] H, with π given entry by entry as polynomials (linear for Lie–Poisson, affine
//! with a cocycle, quadratic for log-canonical, constant for point vortices). ∇H and ∇²H come
//! from forward-mode jets of H, ∂π from dual numbers: the classical baselines (RK4, the implicit
//! midpoint rule) run on it in SIMD lanes with an exact Jacobian.

use nalgebra::SMatrix;

use crate::distance_sum::DistanceSum;
use crate::dual::{Dual1, Jet2};
use crate::error::CoreError;
use crate::expression::Expression;
use crate::lanes::LaneField;
use crate::structures::lie_poisson::VectorField;
use crate::structures::polynomial::SparsePolynomial;

/// π's upper triangle, row by row (π_ij for i < j, N(N − 1)/2 polynomials in N variables), and
/// H.
#[derive(Clone, Debug)]
pub struct HamiltonianField<const N: usize> {
    upper: Vec<SparsePolynomial>,
    hamiltonian: Expression,
    /// π∇H written out as one program with N outputs (H's gradient differentiated symbolically,
    /// π's entries multiplied in): values only, the fast path of the field. None: H's gradient
    /// by forward mode, then π.
    program: Option<Expression>,
    /// H as a sum over distances (the same H as `hamiltonian`): its gradient compiled, then π.
    /// Takes precedence over `program`.
    distances: Option<DistanceSum>,
    /// π's entries that are not zero: (i, j, the entry's index in `upper`, its value where it
    /// is a constant).
    entries: Vec<(usize, usize, usize, Option<f64>)>,
}

impl<const N: usize> HamiltonianField<N> {
    pub fn new(
        upper: Vec<SparsePolynomial>,
        hamiltonian: Expression,
        program: Option<Expression>,
        distances: Option<DistanceSum>,
    ) -> Result<Self, CoreError> {
        use crate::expression::{MAX_LIVE, MAX_TAPE};
        if hamiltonian.ops().len() > MAX_TAPE || hamiltonian.live() > MAX_LIVE {
            return Err(CoreError::Invalid(format!(
                "H has {} instructions and keeps {} values live; the core takes up to \
                 {MAX_TAPE} and {MAX_LIVE}",
                hamiltonian.ops().len(),
                hamiltonian.live()
            )));
        }
        if let Some(p) = &program {
            if p.n_outputs() != N || p.vars() != N {
                return Err(CoreError::Invalid(format!(
                    "the field program must have {N} outputs in {N} variables, got {} in {}",
                    p.n_outputs(),
                    p.vars()
                )));
            }
        }
        if upper.len() != N * (N - 1) / 2 || upper.iter().any(|p| p.vars() != N) {
            return Err(CoreError::Invalid(format!(
                "a bivector in dimension {N} needs {} polynomials in {N} variables (its upper \
                 triangle)",
                N * (N - 1) / 2
            )));
        }
        if hamiltonian.vars() != N {
            return Err(CoreError::Invalid(format!(
                "H has {} variables; the bivector {N}",
                hamiltonian.vars()
            )));
        }
        if let Some(d) = &distances {
            if d.vars() != N {
                return Err(CoreError::Invalid(format!(
                    "the distance terms have {} variables; the bivector {N}",
                    d.vars()
                )));
            }
        }
        let mut entries = Vec::new();
        entries
            .try_reserve_exact(upper.len())
            .map_err(|_| CoreError::Memory("the bivector's entries".into()))?;
        let mut k = 0;
        for i in 0..N {
            for j in i + 1..N {
                let terms: Vec<(f64, &[u8])> = upper[k].terms().filter(|t| t.0 != 0.0).collect();
                if !terms.is_empty() {
                    let constant = match terms.as_slice() {
                        [(c, e)] if e.iter().all(|&p| p == 0) => Some(*c),
                        _ => None,
                    };
                    entries.push((i, j, k, constant));
                }
                k += 1;
            }
        }
        Ok(HamiltonianField {
            upper,
            hamiltonian,
            program,
            distances,
            entries,
        })
    }

    /// H at x.
    pub fn hamiltonian(&self, x: &[f64; N]) -> f64 {
        self.hamiltonian.eval(x)
    }

    /// ∇H at x (the one-lane case of [`Expression::gradient_lanes`]).
    pub fn gradient(&self, x: &[f64; N]) -> [f64; N] {
        let xl: [[f64; 1]; N] = std::array::from_fn(|i| [x[i]]);
        let (mut v, mut g) = ([0.0; 1], [[0.0; 1]; N]);
        self.hamiltonian.gradient_lanes(&xl, &mut v, &mut g);
        std::array::from_fn(|i| g[i][0])
    }

    /// π(x)∇H(x) at L states: H's gradient in lanes, then π's entries.
    #[inline(always)]
    fn field_in_lanes<const L: usize>(&self, x: &[[f64; L]; N], out: &mut [[f64; L]; N]) {
        if let Some(d) = &self.distances {
            self.distance_field(d, x, out);
            return;
        }
        if let Some(p) = &self.program {
            p.values_lanes(x, out);
            return;
        }
        if L > crate::isa::LANES {
            // A wide block on the tape path, in narrow pieces: the tape's registers live on
            // the stack, sized by the lanes.
            const W: usize = crate::isa::LANES;
            for start in (0..L).step_by(W) {
                let width = W.min(L - start);
                let mut xb = [[0.0; W]; N];
                let mut ob = [[0.0; W]; N];
                for i in 0..N {
                    xb[i][..width].copy_from_slice(&x[i][start..start + width]);
                }
                self.field_in_lanes(&xb, &mut ob);
                for i in 0..N {
                    out[i][start..start + width].copy_from_slice(&ob[i][..width]);
                }
            }
            return;
        }
        let (mut v, mut g) = ([0.0; L], [[0.0; L]; N]);
        self.hamiltonian.gradient_lanes(x, &mut v, &mut g);
        self.bivector_times(x, &g, out);
    }

    /// Whether H's gradient is the compiled one of a sum over distances.
    pub fn has_distances(&self) -> bool {
        self.distances.is_some()
    }

    /// H as a sum over distances, where it is one.
    pub fn distances(&self) -> Option<&DistanceSum> {
        self.distances.as_ref()
    }

    /// c_i where π's entries that are not zero are exactly the constants {x_{2i}, x_{2i+1}} =
    /// c_i, one for each i < N/2 (the point vortices' bracket, c_i = 1/Γ_i); None otherwise.
    pub fn constant_pair_blocks(&self) -> Option<[f64; N]> {
        if !N.is_multiple_of(2) || self.entries.len() != N / 2 {
            return None;
        }
        let mut c = [0.0; N];
        for (p, &(i, j, _, constant)) in self.entries.iter().enumerate() {
            if (i, j) != (2 * p, 2 * p + 1) {
                return None;
            }
            c[p] = constant?;
        }
        Some(c)
    }

    /// π∇H at W states, ∇H from the distance terms.
    #[inline(always)]
    fn distance_field<const W: usize>(
        &self,
        d: &DistanceSum,
        x: &[[f64; W]; N],
        out: &mut [[f64; W]; N],
    ) {
        let mut g = [[0.0; W]; N];
        d.gradient_lanes(x, &mut g);
        self.bivector_times(x, &g, out);
    }

    /// out = π(x) g at L states, over π's entries that are not zero (a constant one without
    /// evaluating its polynomial).
    #[inline(always)]
    fn bivector_times<const L: usize>(
        &self,
        x: &[[f64; L]; N],
        g: &[[f64; L]; N],
        out: &mut [[f64; L]; N],
    ) {
        *out = [[0.0; L]; N];
        for &(i, j, k, constant) in &self.entries {
            let p = match constant {
                Some(c) => [c; L],
                None => self.upper[k].eval_lanes(x),
            };
            for l in 0..L {
                out[i][l] += p[l] * g[j][l];
                out[j][l] -= p[l] * g[i][l];
            }
        }
    }

    /// H, ∇H and ∇²H at x.
    pub fn jet(&self, x: &[f64; N]) -> Jet2<N> {
        let d: [Jet2<N>; N] = std::array::from_fn(|i| Jet2::var(x[i], i));
        self.hamiltonian.eval(&d)
    }
}

impl<const N: usize> VectorField<N> for HamiltonianField<N> {
    fn field(&self, x: &[f64; N]) -> [f64; N] {
        let xl: [[f64; 1]; N] = std::array::from_fn(|i| [x[i]]);
        let mut out = [[0.0; 1]; N];
        self.field_in_lanes(&xl, &mut out);
        std::array::from_fn(|i| out[i][0])
    }

    fn jacobian(&self, x: &[f64; N]) -> SMatrix<f64, N, N> {
        let jet = self.jet(x);
        let (g, hs) = (jet.grad(), jet.hess());
        let d: [Dual1<N>; N] = std::array::from_fn(|i| Dual1::var(x[i], i));
        let mut out = SMatrix::<f64, N, N>::zeros();
        let mut k = 0;
        for i in 0..N {
            for j in i + 1..N {
                let p = self.upper[k].eval(&d);
                k += 1;
                // ∂_c (π_ij g_j) = ∂_c π_ij g_j + π_ij H_jc, and π_ji = −π_ij.
                for c in 0..N {
                    out[(i, c)] += p.g[c] * g[j] + p.v * hs[j][c];
                    out[(j, c)] -= p.g[c] * g[i] + p.v * hs[i][c];
                }
            }
        }
        out
    }
}

/// The field in lanes (the scalar field is its one-lane case, so both give the same bits); the
/// Jacobian lane by lane from the scalar jets.
impl<const N: usize> LaneField<N> for HamiltonianField<N> {
    // An interpreted program: wide blocks spread each instruction's dispatch over more lanes.
    const WIDE: bool = true;

    #[inline(always)]
    fn field_lanes<const L: usize>(&self, x: &[[f64; L]; N], out: &mut [[f64; L]; N]) {
        self.field_in_lanes(x, out);
    }

    #[inline(always)]
    fn jacobian_lanes<const L: usize>(
        &self,
        x: &[[f64; L]; N],
        out: &mut [[[f64; L]; N]; N],
    ) -> bool {
        crate::straight_line::jacobian_lanes_by(x, out, |m| {
            let j = VectorField::jacobian(self, m);
            std::array::from_fn(|r| std::array::from_fn(|c| j[(r, c)]))
        })
    }
}

/// A [`HamiltonianField`] whose H is a sum over distances: its field in lanes is compiled code
/// ([`DistanceSum`]), so RK4 steps it in blocks of one lane group, where the wide blocks pay
/// only for an interpreter's dispatch (a term's differences and factors would go through
/// memory there). The same bits as the field itself: each lane is computed alone.
#[derive(Clone, Debug)]
pub struct DistanceField<const N: usize>(HamiltonianField<N>);

impl<const N: usize> DistanceField<N> {
    /// The field, which must carry distance terms.
    pub fn new(field: HamiltonianField<N>) -> Result<Self, CoreError> {
        if !field.has_distances() {
            return Err(CoreError::Invalid(
                "a distance field needs H's distance terms".into(),
            ));
        }
        Ok(DistanceField(field))
    }
}

impl<const N: usize> VectorField<N> for DistanceField<N> {
    fn field(&self, x: &[f64; N]) -> [f64; N] {
        self.0.field(x)
    }

    fn jacobian(&self, x: &[f64; N]) -> SMatrix<f64, N, N> {
        self.0.jacobian(x)
    }
}

impl<const N: usize> LaneField<N> for DistanceField<N> {
    #[inline(always)]
    fn field_lanes<const L: usize>(&self, x: &[[f64; L]; N], out: &mut [[f64; L]; N]) {
        self.0.field_in_lanes(x, out);
    }

    #[inline(always)]
    fn jacobian_lanes<const L: usize>(
        &self,
        x: &[[f64; L]; N],
        out: &mut [[[f64; L]; N]; N],
    ) -> bool {
        self.0.jacobian_lanes(x, out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// so(3)* (π_ij = −ε_ijk x_k) with H = cos x₃ + x₁²/2: the field μ × ∇H, and its Jacobian
    /// against central differences.
    #[test]
    fn field_and_jacobian_on_so3_with_a_cosine() {
        // π_01 = −x2, π_02 = x1, π_12 = −x0.
        let upper = vec![
            SparsePolynomial::new(3, &[-1.0], &[0, 0, 1]).unwrap(),
            SparsePolynomial::new(3, &[1.0], &[0, 1, 0]).unwrap(),
            SparsePolynomial::new(3, &[-1.0], &[1, 0, 0]).unwrap(),
        ];
        // cos(x2) + 0.5 * x0^2
        let h = Expression::from_table(
            3,
            &[0, 12, 0, 7, 1, 4, 2],
            &[2, 0, 0, 2, 0, 3, 1],
            &[0, 0, 0, 2, 0, 4, 5],
            &[0.0, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0],
        )
        .unwrap();
        let f = HamiltonianField::<3>::new(upper, h, None, None).unwrap();
        let x: [f64; 3] = [0.4, -0.7, 1.1];
        let g = [x[0], 0.0, -x[2].sin()];
        let cross = [
            x[1] * g[2] - x[2] * g[1],
            x[2] * g[0] - x[0] * g[2],
            x[0] * g[1] - x[1] * g[0],
        ];
        let v = f.field(&x);
        for i in 0..3 {
            assert!((v[i] - cross[i]).abs() < 1e-15, "{v:?} vs {cross:?}");
        }
        let j = f.jacobian(&x);
        for c in 0..3 {
            let (mut a, mut b) = (x, x);
            a[c] += 1e-6;
            b[c] -= 1e-6;
            let (fa, fb) = (f.field(&a), f.field(&b));
            for r in 0..3 {
                assert!((j[(r, c)] - (fa[r] - fb[r]) / 2e-6).abs() < 1e-8);
            }
        }
    }
}

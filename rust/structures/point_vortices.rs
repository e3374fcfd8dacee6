//! Point vortices in the plane as straight-line code: the field of an expression system whose
//! bracket is {x_{2i}, x_{2i+1}} = c_i and whose H is Σ_{i<j} w_ij ln r_ij² over every pair of
//! its N/2 points (the pattern read off the system by [`PointVortices::new`]).
//!
//! The generic distance path ([`crate::distance_sum::DistanceSum`], then π's entries) reads
//! each term's coordinates at run-time indices, so its gradient and field go through memory and
//! have no by-lane form. Here the pairs are loops over constants the compiler unrolls: the
//! field stays in registers, and RK4 runs by lane in AVX-512 blocks, two lanes an iteration
//! ([`crate::lane_field::rk4_by_lane`] with K = 2). The same operations in the same order as the generic
//! path, so the same bits (`rust/tests/point_vortices.rs`).

// Index loops over points and lanes read as the formulas they evaluate.
#![allow(clippy::needless_range_loop)]

use nalgebra::SMatrix;

use crate::lane_field::{rk4_by_lane, AtStates, LaneField};
use crate::structures::bivector::HamiltonianField;
use crate::structures::lie_poisson::VectorField;

/// The vortices' field π∇H: `scale[i][j]` = 2w_ij for the points i < j, `bracket[i]` = c_i
/// (only the first N/2 entries of each are read), and the expression system it was read off
/// (its Jacobian, for the implicit steps).
#[derive(Clone, Debug)]
pub struct PointVortices<const N: usize> {
    scale: [[f64; N]; N],
    bracket: [f64; N],
    field: HamiltonianField<N>,
}

impl<const N: usize> PointVortices<N> {
    /// The field's straight-line form where it has the vortices' pattern (a bracket of
    /// constant 2×2 blocks and H a sum of ln r² over every pair of points, in order:
    /// [`HamiltonianField::constant_pair_blocks`],
    /// [`crate::distance_sum::DistanceSum::planar_log_pairs`]); the field itself back where it
    /// does not (whole, not a copy: hence the large error type).
    #[allow(clippy::result_large_err)]
    pub fn new(field: HamiltonianField<N>) -> Result<Self, HamiltonianField<N>> {
        let scale = field.distances().and_then(|d| d.planar_log_pairs::<N>());
        match (scale, field.constant_pair_blocks()) {
            (Some(scale), Some(bracket)) if N >= 4 => Ok(PointVortices {
                scale,
                bracket,
                field,
            }),
            _ => Err(field),
        }
    }
}

/// π∇H at L states, lane by lane: each pair's differences, r² and 2w/r² (the distance path's
/// [`crate::distance_sum::DistanceSum::gradient_lanes`] term by term), its gradient added in the
/// terms' order, then π's blocks (`bivector_times`): the generic path's operations, in
/// registers.
#[inline(always)]
fn vortices_lanes<const N: usize, const L: usize>(
    scale: &[[f64; N]; N],
    bracket: &[f64; N],
    x: &[[f64; L]; N],
    out: &mut [[f64; L]; N],
) {
    let points = N / 2;
    for l in 0..L {
        let mut g = [0.0; N];
        for i in 0..points {
            for j in i + 1..points {
                let dx = x[2 * i][l] - x[2 * j][l];
                let dy = x[2 * i + 1][l] - x[2 * j + 1][l];
                let s = scale[i][j] / (dx * dx + dy * dy);
                g[2 * i] += s * dx;
                g[2 * j] -= s * dx;
                g[2 * i + 1] += s * dy;
                g[2 * j + 1] -= s * dy;
            }
        }
        for i in 0..points {
            // From zero, as π's entries are added there (keeps the sign of a zero).
            out[2 * i][l] = 0.0 + bracket[i] * g[2 * i + 1];
            out[2 * i + 1][l] = 0.0 - bracket[i] * g[2 * i];
        }
    }
}

impl<const N: usize> VectorField<N> for PointVortices<N> {
    fn field(&self, x: &[f64; N]) -> [f64; N] {
        let mut out = [[0.0; 1]; N];
        vortices_lanes(&self.scale, &self.bracket, &x.map(|v| [v]), &mut out);
        out.map(|v| v[0])
    }

    fn jacobian(&self, x: &[f64; N]) -> SMatrix<f64, N, N> {
        self.field.jacobian(x)
    }
}

impl<const N: usize> LaneField<N> for PointVortices<N> {
    /// Straight-line code with no branch (measured in `benches/peers.py`: see
    /// docs/performance.md, "Point vortices by lane").
    const AVX512_BY_LANE: bool = true;

    #[inline(always)]
    fn field_lanes<const L: usize>(&self, x: &[[f64; L]; N], out: &mut [[f64; L]; N]) {
        vortices_lanes(&self.scale, &self.bracket, x, out);
    }

    /// On copies of the constants, which the loop over lanes then holds in registers; two
    /// lanes an iteration, since each lane's step is a chain of divisions (measured: 4.1 ns a
    /// step against 5.7 with one lane an iteration).
    #[inline(always)]
    fn rk4_step_by_lane<const L: usize>(&self, h: f64, mu: &mut [[f64; L]; N]) {
        let (scale, bracket) = (self.scale, self.bracket);
        let f = AtStates::<2, _>(|y: &[[f64; 2]; N], o: &mut [[f64; 2]; N]| {
            vortices_lanes(&scale, &bracket, y, o)
        });
        rk4_by_lane(&f, h, mu);
    }

    #[inline(always)]
    fn jacobian_lanes<const L: usize>(
        &self,
        x: &[[f64; L]; N],
        out: &mut [[[f64; L]; N]; N],
    ) -> bool {
        self.field.jacobian_lanes(x, out)
    }
}

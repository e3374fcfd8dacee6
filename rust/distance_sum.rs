//! Hamiltonians that are sums over distances between points,
//! H(x) = Σ_k w_k φ_k(r_k²) + P(x), r_k² = Σ_{d < D_k} (x_{a_kd} − x_{b_kd})² (or Σ x_{a_kd}²,
//! the distance from the origin), with φ = ln or a power (r⁻¹ = (r²)^{−1/2}) and D_k ≤ 3
//! coordinates a point, P a polynomial:
//! point vortices (w ln r²), Kepler, gravitating and charged bodies (w r⁻¹ beside |p|²/2).
//!
//! Their gradient in SIMD lanes is compiled code, term by term: the differences, r², the radial
//! factor 2w φ'(r²) and the scattered gradient stay in registers, where an interpreted field
//! program pays a load and a store per instruction and lane group (3× straight-line code on the
//! three vortices). The fast path of such an H's field
//! ([`crate::structures::bivector::HamiltonianField`]); which H qualifies is decided where the
//! expression is read (Python's `distance_sums`), and the interpreted program stays the path of
//! every other H.

use crate::error::CoreError;
use crate::structures::polynomial::SparsePolynomial;

/// The most coordinates of one point (D ≤ 3: the plane or space).
pub const MAX_POINT_DIM: usize = 3;
/// The most distance terms an H may have (a bound on untrusted input).
pub const MAX_DISTANCE_TERMS: usize = 4096;

/// φ of one term, as a function of r².
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Radial {
    /// ln r².
    Log,
    /// (r²)^p, p ≠ 0 finite.
    Power(f64),
}

/// One term w φ(r²) of a [`DistanceSum`], with the constant of its gradient folded at
/// construction: `scale` = 2w for ln (2w/r²), 2wp for a power (2wp (r²)^{p−1}).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Term {
    radial: Radial,
    scale: f64,
    dims: usize,
    a: [usize; MAX_POINT_DIM],
    /// None: the second point is the origin.
    b: Option<[usize; MAX_POINT_DIM]>,
}

/// H = Σ_k w_k φ_k(r_k²) + P(x) in `vars` coordinates.
#[derive(Clone, Debug)]
pub struct DistanceSum {
    vars: usize,
    terms: Vec<Term>,
    polynomial: Option<SparsePolynomial>,
}

impl DistanceSum {
    /// From one row per term: `radial` (0: ln, 1: a power), the weight w, the power p (read for a
    /// power only), the point's dimension D (1 ..= 3) and the coordinates a_d, b_d of its two
    /// points (`first`, `second`: at least D entries each; `second`'s all −1 for the origin);
    /// `polynomial` the rest P. Errors name the term and field that is out of range: the input
    /// is untrusted.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        vars: usize,
        radial: &[i64],
        weight: &[f64],
        power: &[f64],
        dims: &[i64],
        first: &[[i64; MAX_POINT_DIM]],
        second: &[[i64; MAX_POINT_DIM]],
        polynomial: Option<SparsePolynomial>,
    ) -> Result<Self, CoreError> {
        let k = radial.len();
        if [
            weight.len(),
            power.len(),
            dims.len(),
            first.len(),
            second.len(),
        ]
        .iter()
        .any(|&n| n != k)
        {
            return Err(CoreError::Invalid(
                "distance terms: radial, weight, power, dims, first and second must have one \
                 row per term"
                    .into(),
            ));
        }
        if k > MAX_DISTANCE_TERMS {
            return Err(CoreError::Invalid(format!(
                "distance terms: {k} terms, more than {MAX_DISTANCE_TERMS}"
            )));
        }
        if let Some(p) = &polynomial {
            if p.vars() != vars {
                return Err(CoreError::Invalid(format!(
                    "distance terms: the polynomial part has {} variables, H {vars}",
                    p.vars()
                )));
            }
        }
        let mut terms = Vec::new();
        terms
            .try_reserve_exact(k)
            .map_err(|_| CoreError::Memory("the distance terms".into()))?;
        for t in 0..k {
            let bad = |what: &str| CoreError::Invalid(format!("distance term {t}: {what}"));
            let d = usize::try_from(dims[t])
                .ok()
                .filter(|d| (1..=MAX_POINT_DIM).contains(d))
                .ok_or_else(|| bad("dims must be 1, 2 or 3"))?;
            let index = |v: i64| usize::try_from(v).ok().filter(|&i| i < vars);
            let mut a = [0; MAX_POINT_DIM];
            for j in 0..d {
                a[j] =
                    index(first[t][j]).ok_or_else(|| bad("a coordinate of first out of range"))?;
            }
            let b = if second[t][..d].iter().all(|&v| v == -1) {
                None
            } else {
                let mut b = [0; MAX_POINT_DIM];
                for j in 0..d {
                    b[j] = index(second[t][j]).ok_or_else(|| {
                        bad("a coordinate of second out of range (all −1: the origin)")
                    })?;
                }
                if (0..d).all(|j| a[j] == b[j]) {
                    return Err(bad("its two points are the same coordinates (r² ≡ 0)"));
                }
                Some(b)
            };
            let w = weight[t];
            if !w.is_finite() {
                return Err(bad("weight must be finite"));
            }
            let (radial, scale) = match radial[t] {
                0 => (Radial::Log, 2.0 * w),
                1 => {
                    let p = power[t];
                    if !p.is_finite() || p == 0.0 {
                        return Err(bad("power must be finite and nonzero"));
                    }
                    (Radial::Power(p), 2.0 * w * p)
                }
                _ => return Err(bad("radial must be 0 (ln) or 1 (a power)")),
            };
            if !scale.is_finite() {
                return Err(bad("2·weight·power overflows"));
            }
            terms.push(Term {
                radial,
                scale,
                dims: d,
                a,
                b,
            });
        }
        Ok(DistanceSum {
            vars,
            terms,
            polynomial,
        })
    }

    /// The coordinates of H.
    pub fn vars(&self) -> usize {
        self.vars
    }

    /// The scales 2w_ij (at `[i][j]`, i < j) where H = Σ_{i<j} w_ij ln r_ij² over every pair of
    /// the N/2 points of the plane, point i at (x_{2i}, x_{2i+1}), its terms in the order
    /// (0, 1), (0, 2), …, (1, 2), … and no polynomial: point vortices, whose gradient is then
    /// the straight-line loop of [`crate::structures::point_vortices`]. None for any other H.
    #[allow(clippy::needless_range_loop)] // (i, j) name the points, not just the entry.
    pub fn planar_log_pairs<const N: usize>(&self) -> Option<[[f64; N]; N]> {
        let points = N / 2;
        if self.vars != N || !N.is_multiple_of(2) || self.polynomial.is_some() {
            return None;
        }
        let mut scale = [[0.0; N]; N];
        let mut terms = self.terms.iter();
        for i in 0..points {
            for j in i + 1..points {
                let t = terms.next()?;
                let pair = t.radial == Radial::Log
                    && t.dims == 2
                    && t.a[..2] == [2 * i, 2 * i + 1]
                    && t.b.is_some_and(|b| b[..2] == [2 * j, 2 * j + 1]);
                if !pair {
                    return None;
                }
                scale[i][j] = t.scale;
            }
        }
        terms.next().is_none().then_some(scale)
    }

    /// ∇H at L states at once (`x[i][l]`: coordinate i of lane l; `grad` overwritten). Every
    /// lane is computed alone, so a lane's bits do not depend on its neighbours.
    #[inline(always)]
    pub fn gradient_lanes<const N: usize, const L: usize>(
        &self,
        x: &[[f64; L]; N],
        grad: &mut [[f64; L]; N],
    ) {
        *grad = [[0.0; L]; N];
        for t in &self.terms {
            let mut diff = [[0.0; L]; MAX_POINT_DIM];
            let mut q = [0.0; L];
            for d in 0..t.dims {
                let xa = &x[t.a[d]];
                match t.b {
                    Some(b) => {
                        let xb = &x[b[d]];
                        for l in 0..L {
                            diff[d][l] = xa[l] - xb[l];
                        }
                    }
                    None => diff[d] = *xa,
                }
                for l in 0..L {
                    q[l] += diff[d][l] * diff[d][l];
                }
            }
            // s = 2w φ'(r²): ∂H/∂x_a = s (x_a − x_b) = −∂H/∂x_b.
            let mut s = [0.0; L];
            match t.radial {
                Radial::Log => {
                    for l in 0..L {
                        s[l] = t.scale / q[l];
                    }
                }
                // r⁻¹, the gravitational and Coulomb potential: (r²)^{−3/2} = 1/(r² √r²).
                Radial::Power(-0.5) => {
                    for l in 0..L {
                        s[l] = t.scale / (q[l] * q[l].sqrt());
                    }
                }
                Radial::Power(-1.0) => {
                    for l in 0..L {
                        s[l] = t.scale / (q[l] * q[l]);
                    }
                }
                Radial::Power(p) => {
                    for l in 0..L {
                        s[l] = t.scale * q[l].powf(p - 1.0);
                    }
                }
            }
            for d in 0..t.dims {
                for l in 0..L {
                    grad[t.a[d]][l] += s[l] * diff[d][l];
                }
                if let Some(b) = t.b {
                    for l in 0..L {
                        grad[b[d]][l] -= s[l] * diff[d][l];
                    }
                }
            }
        }
        if let Some(p) = &self.polynomial {
            add_polynomial_gradient(p, x, grad);
        }
    }
}

/// grad += ∇P at L states: each monomial c Π x_j^{e_j} adds c e_i x_i^{e_i − 1} Π_{j≠i} x_j^{e_j}
/// to ∂_i, by repeated multiplication (exact at x_i = 0).
#[inline(always)]
fn add_polynomial_gradient<const N: usize, const L: usize>(
    p: &SparsePolynomial,
    x: &[[f64; L]; N],
    grad: &mut [[f64; L]; N],
) {
    for (c, row) in p.terms() {
        for (i, &ei) in row.iter().enumerate() {
            if ei == 0 {
                continue;
            }
            let mut term = [c * f64::from(ei); L];
            for (j, &ej) in row.iter().enumerate() {
                let e = if j == i { ej - 1 } else { ej };
                for _ in 0..e {
                    for l in 0..L {
                        term[l] *= x[j][l];
                    }
                }
            }
            for l in 0..L {
                grad[i][l] += term[l];
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// H = −ln((x0 − x2)² + (x1 − x3)²)/(4π) + 0.3 ((x0 − x4)² + (x1 − x5)²)^{−1/2}
    /// + 2 ((x2 − x4)²)^{0.7} − 1.5 (x3² + x5²)^{−1} + x0² x3 / 2, by hand.
    fn h(x: &[f64; 6]) -> f64 {
        let q1 = (x[0] - x[2]).powi(2) + (x[1] - x[3]).powi(2);
        let q2 = (x[0] - x[4]).powi(2) + (x[1] - x[5]).powi(2);
        let q3 = (x[2] - x[4]).powi(2);
        let q4 = x[3] * x[3] + x[5] * x[5];
        -q1.ln() / (4.0 * std::f64::consts::PI) + 0.3 / q2.sqrt() + 2.0 * q3.powf(0.7) - 1.5 / q4
            + 0.5 * x[0] * x[0] * x[3]
    }

    fn sum() -> DistanceSum {
        let poly = SparsePolynomial::new(6, &[0.5], &[2, 0, 0, 1, 0, 0]).unwrap();
        DistanceSum::new(
            6,
            &[0, 1, 1, 1],
            &[-1.0 / (4.0 * std::f64::consts::PI), 0.3, 2.0, -1.5],
            &[0.0, -0.5, 0.7, -1.0],
            &[2, 2, 1, 2],
            &[[0, 1, 0], [0, 1, 0], [2, 0, 0], [3, 5, 0]],
            &[[2, 3, 0], [4, 5, 0], [4, 0, 0], [-1, -1, 0]],
            Some(poly),
        )
        .unwrap()
    }

    #[test]
    fn gradient_matches_central_differences_in_every_lane() {
        let s = sum();
        let states = [
            [0.3, -0.2, 1.1, 0.4, -0.7, 0.9],
            [1.0, 0.0, -0.5, 0.6, -0.3, -0.8],
            [-0.4, 0.8, 0.2, -1.3, 0.9, 0.1],
        ];
        let x: [[f64; 3]; 6] = std::array::from_fn(|i| std::array::from_fn(|l| states[l][i]));
        let mut g = [[0.0; 3]; 6];
        s.gradient_lanes(&x, &mut g);
        for (l, state) in states.iter().enumerate() {
            for i in 0..6 {
                let e = 1e-6;
                let (mut up, mut down) = (*state, *state);
                up[i] += e;
                down[i] -= e;
                let fd = (h(&up) - h(&down)) / (2.0 * e);
                assert!((g[i][l] - fd).abs() < 1e-8 * (1.0 + fd.abs()), "{i} {l}");
            }
            // One lane alone gives the same bits.
            let one: [[f64; 1]; 6] = std::array::from_fn(|i| [state[i]]);
            let mut g1 = [[0.0; 1]; 6];
            s.gradient_lanes(&one, &mut g1);
            for i in 0..6 {
                assert_eq!(g1[i][0].to_bits(), g[i][l].to_bits());
            }
        }
    }

    #[test]
    fn bad_terms_are_refused_naming_the_term_and_field() {
        let ok = |radial: i64, w: f64, p: f64, d: i64, a: [i64; 3], b: [i64; 3]| {
            DistanceSum::new(4, &[radial], &[w], &[p], &[d], &[a], &[b], None)
        };
        assert!(ok(0, 1.0, 0.0, 2, [0, 1, 0], [2, 3, 0]).is_ok());
        assert!(ok(1, 1.0, -0.5, 2, [0, 1, 0], [-1, -1, 7]).is_ok());
        for (e, needle) in [
            (ok(2, 1.0, 0.0, 2, [0, 1, 0], [2, 3, 0]), "radial"),
            (ok(0, f64::NAN, 0.0, 2, [0, 1, 0], [2, 3, 0]), "weight"),
            (ok(1, 1.0, 0.0, 2, [0, 1, 0], [2, 3, 0]), "power"),
            (ok(1, 1.0, f64::INFINITY, 2, [0, 1, 0], [2, 3, 0]), "power"),
            (ok(0, 1.0, 0.0, 4, [0, 1, 0], [2, 3, 0]), "dims"),
            (ok(0, 1.0, 0.0, 0, [0, 1, 0], [2, 3, 0]), "dims"),
            (ok(0, 1.0, 0.0, 2, [0, 4, 0], [2, 3, 0]), "first"),
            (ok(0, 1.0, 0.0, 2, [0, 1, 0], [-1, 3, 0]), "second"),
            (ok(0, 1.0, 0.0, 2, [0, 1, 0], [-2, -2, 0]), "second"),
            (ok(0, 1.0, 0.0, 2, [0, 1, 0], [0, 1, 0]), "same coordinates"),
        ] {
            let msg = e.unwrap_err().to_string();
            assert!(
                msg.contains("distance term 0") && msg.contains(needle),
                "{msg}"
            );
        }
        let short = DistanceSum::new(
            4,
            &[0, 0],
            &[1.0],
            &[0.0],
            &[2],
            &[[0, 1, 0]],
            &[[2, 3, 0]],
            None,
        );
        assert!(short.unwrap_err().to_string().contains("one row per term"));
    }
}

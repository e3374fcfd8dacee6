//! Forward-mode dual numbers: one generic code path gives values, gradients and Hessians exactly.
//!
//! `Dual1<N>` carries a value and a gradient with respect to N seeds; `Jet2<N>` adds the symmetric
//! Hessian. Both, and plain `f64`, implement [`Scalar`], so the charts and the MLP are written
//! once and differentiated by evaluation. N is a const generic, so the rigid body's N = 3 is as
//! fast as hand-unrolled code.

// Index loops over small fixed-size vectors and matrices read as the formulas they implement.
#![allow(
    clippy::needless_range_loop,
    clippy::suspicious_arithmetic_impl,
    clippy::field_reassign_with_default
)]

use std::ops::{Add, Mul, Neg, Sub};

/// The arithmetic the generic code needs.
pub trait Scalar:
    Copy + Add<Output = Self> + Sub<Output = Self> + Mul<Output = Self> + Neg<Output = Self>
{
    /// The highest derivative order carried (0 for `f64`, 1 for [`Dual1`], 2 for [`Jet2`]):
    /// lets a smooth function skip the derivatives of its own that [`Scalar::chain`] would drop.
    const ORDER: u8;
    /// A constant (all derivatives zero).
    fn cst(v: f64) -> Self;
    /// The value part.
    fn value(&self) -> f64;
    /// `self * c` for a plain number.
    fn scale(self, c: f64) -> Self;
    /// `f(self)` for a smooth scalar `f` given `f, f', f''` at `self.value()`.
    fn chain(self, f: f64, df: f64, d2f: f64) -> Self;
    /// `acc + self * c`, the inner step of a matrix-vector product.
    #[inline(always)]
    fn mul_add(self, c: f64, acc: Self) -> Self {
        acc + self.scale(c)
    }
    /// `*self += x * c` in place: the same numbers as [`Scalar::mul_add`], without moving a
    /// whole jet through every multiply-add of a layer.
    #[inline(always)]
    fn add_scaled(&mut self, x: &Self, c: f64) {
        *self = x.mul_add(c, *self);
    }
    fn tanh(self) -> Self {
        let v = self.value().tanh();
        let d = 1.0 - v * v;
        self.chain(v, d, -2.0 * v * d)
    }
    fn sqrt(self) -> Self {
        let r = self.value().sqrt();
        self.chain(r, 0.5 / r, -0.25 / (r * r * r))
    }
    fn recip(self) -> Self {
        let v = self.value();
        self.chain(1.0 / v, -1.0 / (v * v), 2.0 / (v * v * v))
    }
    fn powi(self, n: i32) -> Self {
        let v = self.value();
        let nf = f64::from(n);
        self.chain(
            v.powi(n),
            nf * v.powi(n - 1),
            nf * (nf - 1.0) * v.powi(n - 2),
        )
    }
    /// True when every component is finite.
    fn is_finite(&self) -> bool;
    /// The largest absolute component (value and derivatives): a series has converged once its
    /// terms are negligible in every component.
    fn max_abs(&self) -> f64;
}

impl Scalar for f64 {
    const ORDER: u8 = 0;
    #[inline(always)]
    fn cst(v: f64) -> Self {
        v
    }
    #[inline(always)]
    fn value(&self) -> f64 {
        *self
    }
    #[inline(always)]
    fn scale(self, c: f64) -> Self {
        self * c
    }
    #[inline(always)]
    fn chain(self, f: f64, _df: f64, _d2f: f64) -> Self {
        f
    }
    #[inline(always)]
    fn mul_add(self, c: f64, acc: Self) -> Self {
        // Not f64::mul_add: without a target FMA feature that is a libm call per weight.
        acc + self * c
    }
    fn is_finite(&self) -> bool {
        f64::is_finite(*self)
    }
    fn max_abs(&self) -> f64 {
        self.abs()
    }
}

/// Value and gradient with respect to N variables.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Dual1<const N: usize> {
    pub v: f64,
    pub g: [f64; N],
}

impl<const N: usize> Default for Dual1<N> {
    fn default() -> Self {
        Dual1 {
            v: 0.0,
            g: [0.0; N],
        }
    }
}

impl<const N: usize> Dual1<N> {
    /// The `i`-th independent variable with value `v`.
    pub fn var(v: f64, i: usize) -> Self {
        let mut g = [0.0; N];
        g[i] = 1.0;
        Dual1 { v, g }
    }
}

impl<const N: usize> Add for Dual1<N> {
    type Output = Self;
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        Dual1 {
            v: self.v + o.v,
            g: std::array::from_fn(|i| self.g[i] + o.g[i]),
        }
    }
}

impl<const N: usize> Sub for Dual1<N> {
    type Output = Self;
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        Dual1 {
            v: self.v - o.v,
            g: std::array::from_fn(|i| self.g[i] - o.g[i]),
        }
    }
}

impl<const N: usize> Neg for Dual1<N> {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        Dual1 {
            v: -self.v,
            g: self.g.map(|x| -x),
        }
    }
}

impl<const N: usize> Mul for Dual1<N> {
    type Output = Self;
    #[inline(always)]
    fn mul(self, o: Self) -> Self {
        Dual1 {
            v: self.v * o.v,
            g: std::array::from_fn(|i| self.v * o.g[i] + o.v * self.g[i]),
        }
    }
}

impl<const N: usize> Scalar for Dual1<N> {
    const ORDER: u8 = 1;
    fn cst(v: f64) -> Self {
        Dual1 { v, g: [0.0; N] }
    }
    fn value(&self) -> f64 {
        self.v
    }
    #[inline(always)]
    fn scale(self, c: f64) -> Self {
        Dual1 {
            v: self.v * c,
            g: self.g.map(|x| x * c),
        }
    }
    fn chain(self, f: f64, df: f64, _d2f: f64) -> Self {
        Dual1 {
            v: f,
            g: self.g.map(|x| df * x),
        }
    }
    fn is_finite(&self) -> bool {
        self.v.is_finite() && self.g.iter().all(|x| x.is_finite())
    }
    fn max_abs(&self) -> f64 {
        self.g.iter().fold(self.v.abs(), |m, x| m.max(x.abs()))
    }
}

/// Entries of the packed upper triangle of an N×N symmetric matrix.
pub const fn n_pairs(n: usize) -> usize {
    n * (n + 1) / 2
}

/// Value, gradient and symmetric Hessian with respect to N variables.
///
/// The Hessian's upper triangle is stored packed, row by row, in the first N(N+1)/2 entries of
/// `h` read as a flat array (the rest stays zero): with `#[repr(C)]`, the numbers every operation
/// touches (value, gradient, packed Hessian) lie contiguous, in the order the batched kernel lays
/// them out (for N = 3: v, g0, g1, g2, h00, h01, h02, h11, h12, h22). [`Jet2::hess`] unpacks it.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C)]
pub struct Jet2<const N: usize> {
    pub v: f64,
    pub g: [f64; N],
    h: [[f64; N]; N],
}

impl<const N: usize> Default for Jet2<N> {
    fn default() -> Self {
        Jet2 {
            v: 0.0,
            g: [0.0; N],
            h: [[0.0; N]; N],
        }
    }
}

impl<const N: usize> Jet2<N> {
    /// Entries of the packed upper triangle.
    pub const PAIRS: usize = n_pairs(N);

    /// The `i`-th independent variable with value `v`.
    pub fn var(v: f64, i: usize) -> Self {
        let mut j = Self::cst(v);
        j.g[i] = 1.0;
        j
    }
    pub fn grad(&self) -> [f64; N] {
        self.g
    }
    /// The packed upper triangle of the Hessian, row by row.
    #[inline(always)]
    pub fn packed(&self) -> &[f64] {
        &self.h.as_flattened()[..Self::PAIRS]
    }
    #[inline(always)]
    pub fn packed_mut(&mut self) -> &mut [f64] {
        &mut self.h.as_flattened_mut()[..Self::PAIRS]
    }
    /// The full symmetric Hessian.
    pub fn hess(&self) -> [[f64; N]; N] {
        let mut h = [[0.0; N]; N];
        let mut k = 0;
        let packed = self.packed();
        for i in 0..N {
            for j in i..N {
                h[i][j] = packed[k];
                h[j][i] = packed[k];
                k += 1;
            }
        }
        h
    }
    /// Every component in order (value, gradient, upper triangle), for tests.
    #[cfg(test)]
    pub fn flat(&self) -> Vec<f64> {
        let mut v = Vec::new();
        Variable::<N>::components(self, |_, x| v.push(x));
        v
    }
    /// Applies `f` to every component pair of `self` and `o`.
    #[inline(always)]
    fn zip_with(self, o: Self, f: impl Fn(f64, f64) -> f64) -> Self {
        let mut r = self;
        r.v = f(self.v, o.v);
        for i in 0..N {
            r.g[i] = f(self.g[i], o.g[i]);
        }
        for (x, y) in r.packed_mut().iter_mut().zip(o.packed()) {
            *x = f(*x, *y);
        }
        r
    }
}

impl<const N: usize> Add for Jet2<N> {
    type Output = Self;
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        self.zip_with(o, |a, b| a + b)
    }
}

impl<const N: usize> Sub for Jet2<N> {
    type Output = Self;
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        self.zip_with(o, |a, b| a - b)
    }
}

impl<const N: usize> Neg for Jet2<N> {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        self.scale(-1.0)
    }
}

impl<const N: usize> Mul for Jet2<N> {
    type Output = Self;
    #[inline(always)]
    fn mul(self, o: Self) -> Self {
        let (a, b) = (&self, &o);
        let mut r = Jet2::default();
        r.v = a.v * b.v;
        for i in 0..N {
            r.g[i] = a.v * b.g[i] + b.v * a.g[i];
        }
        let (ap, bp) = (a.packed(), b.packed());
        let rp = r.packed_mut();
        let mut k = 0;
        for i in 0..N {
            for j in i..N {
                rp[k] = a.v * bp[k] + b.v * ap[k] + a.g[i] * b.g[j] + a.g[j] * b.g[i];
                k += 1;
            }
        }
        r
    }
}

impl<const N: usize> Scalar for Jet2<N> {
    const ORDER: u8 = 2;
    fn cst(v: f64) -> Self {
        Jet2 {
            v,
            ..Default::default()
        }
    }
    fn value(&self) -> f64 {
        self.v
    }
    #[inline(always)]
    fn scale(self, c: f64) -> Self {
        self.zip_with(self, |a, _| a * c)
    }
    #[inline(always)]
    fn mul_add(self, c: f64, acc: Self) -> Self {
        acc.zip_with(self, |a, x| a + x * c)
    }
    #[inline(always)]
    fn add_scaled(&mut self, x: &Self, c: f64) {
        self.v += x.v * c;
        for i in 0..N {
            self.g[i] += x.g[i] * c;
        }
        for (a, b) in self.packed_mut().iter_mut().zip(x.packed()) {
            *a += b * c;
        }
    }
    fn chain(self, f: f64, df: f64, d2f: f64) -> Self {
        let a = &self;
        let mut r = Jet2::default();
        r.v = f;
        for i in 0..N {
            r.g[i] = df * a.g[i];
        }
        let ap = a.packed();
        let rp = r.packed_mut();
        let mut k = 0;
        for i in 0..N {
            for j in i..N {
                rp[k] = df * ap[k] + d2f * a.g[i] * a.g[j];
                k += 1;
            }
        }
        r
    }
    fn is_finite(&self) -> bool {
        self.v.is_finite()
            && self.g.iter().all(|x| x.is_finite())
            && self.packed().iter().all(|x| x.is_finite())
    }
    fn max_abs(&self) -> f64 {
        let m = self.g.iter().fold(self.v.abs(), |m, x| m.max(x.abs()));
        self.packed().iter().fold(m, |m, x| m.max(x.abs()))
    }
}

/// A scalar that can seed one of the N independent variables p₁ … p_N: lets one generic
/// evaluation of S give either its gradient ([`Dual1`]) or its gradient and Hessian ([`Jet2`]).
pub trait Variable<const N: usize>: Scalar {
    /// Numbers carried per quantity: the rows of a batched layer hold this many per trajectory.
    const COMPONENTS: usize;
    /// The `i`-th independent variable with value `v`.
    fn variable(v: f64, i: usize) -> Self;
    /// The same quantity from a [`Jet2`] (dropping what this type does not carry).
    fn from_jet(j: &Jet2<N>) -> Self;
    /// Writes component `c` (0 is the value) through `f(c, value)`, in component order.
    fn components(&self, f: impl FnMut(usize, f64));
    /// The quantity whose component `c` is `f(c)`.
    fn from_components(f: impl Fn(usize) -> f64) -> Self;
    /// tanh with its chain rule, in place, on `rows` of a batched layer: each row holds the
    /// components of `n` trajectories, component-major (`row[c·n + j]`).
    fn tanh_rows(z: &mut [f64], rows: usize, n: usize);
}

impl<const N: usize> Variable<N> for Dual1<N> {
    const COMPONENTS: usize = 1 + N;
    fn variable(v: f64, i: usize) -> Self {
        Dual1::var(v, i)
    }
    fn from_jet(j: &Jet2<N>) -> Self {
        Dual1 { v: j.v, g: j.g }
    }
    #[inline(always)]
    fn components(&self, mut f: impl FnMut(usize, f64)) {
        f(0, self.v);
        for (i, &g) in self.g.iter().enumerate() {
            f(1 + i, g);
        }
    }
    #[inline(always)]
    fn from_components(f: impl Fn(usize) -> f64) -> Self {
        Dual1 {
            v: f(0),
            g: std::array::from_fn(|i| f(1 + i)),
        }
    }
    fn tanh_rows(z: &mut [f64], rows: usize, n: usize) {
        for row in z.chunks_exact_mut((1 + N) * n).take(rows) {
            let (v, g) = row.split_at_mut(n);
            for j in 0..n {
                let y = v[j].tanh();
                let d = 1.0 - y * y;
                v[j] = y;
                for gi in g.chunks_exact_mut(n) {
                    gi[j] *= d;
                }
            }
        }
    }
}

impl<const N: usize> Variable<N> for Jet2<N> {
    const COMPONENTS: usize = 1 + N + n_pairs(N);
    fn variable(v: f64, i: usize) -> Self {
        Jet2::var(v, i)
    }
    fn from_jet(j: &Jet2<N>) -> Self {
        *j
    }
    #[inline(always)]
    fn components(&self, mut f: impl FnMut(usize, f64)) {
        f(0, self.v);
        for (i, &g) in self.g.iter().enumerate() {
            f(1 + i, g);
        }
        for (k, &h) in self.packed().iter().enumerate() {
            f(1 + N + k, h);
        }
    }
    #[inline(always)]
    fn from_components(f: impl Fn(usize) -> f64) -> Self {
        let mut r = Jet2::cst(f(0));
        for i in 0..N {
            r.g[i] = f(1 + i);
        }
        for (k, h) in r.packed_mut().iter_mut().enumerate() {
            *h = f(1 + N + k);
        }
        r
    }
    fn tanh_rows(z: &mut [f64], rows: usize, n: usize) {
        for row in z.chunks_exact_mut(Self::COMPONENTS * n).take(rows) {
            let (v, rest) = row.split_at_mut(n);
            let (g, h) = rest.split_at_mut(N * n);
            for j in 0..n {
                let y = v[j].tanh();
                let d1 = 1.0 - y * y;
                let d2 = -2.0 * y * d1;
                v[j] = y;
                let gj: [f64; N] = std::array::from_fn(|i| g[i * n + j]);
                // The Hessian first: it needs the incoming gradient (Jet2::chain's formula).
                let mut k = 0;
                for a in 0..N {
                    for b in a..N {
                        h[k * n + j] = d1 * h[k * n + j] + d2 * gj[a] * gj[b];
                        k += 1;
                    }
                }
                for (i, &gi) in gj.iter().enumerate() {
                    g[i * n + j] = d1 * gi;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// f(p) = tanh(p0 * p1) + p2^3 p0, differentiated by hand.
    #[test]
    fn jet2_matches_hand_derivatives() {
        let p = [0.3, -0.7, 1.1];
        let x: [Jet2<3>; 3] = [Jet2::var(p[0], 0), Jet2::var(p[1], 1), Jet2::var(p[2], 2)];
        let f = (x[0] * x[1]).tanh() + x[2] * x[2] * x[2] * x[0];
        let u = p[0] * p[1];
        let th = u.tanh();
        let d1 = 1.0 - th * th;
        let d2 = -2.0 * th * d1;
        assert!((f.value() - (th + p[2].powi(3) * p[0])).abs() < 1e-15);
        let g = f.grad();
        let g_ref = [
            d1 * p[1] + p[2].powi(3),
            d1 * p[0],
            3.0 * p[2] * p[2] * p[0],
        ];
        for i in 0..3 {
            assert!((g[i] - g_ref[i]).abs() < 1e-14, "grad {i}");
        }
        let h = f.hess();
        let h_ref = [
            [d2 * p[1] * p[1], d2 * p[0] * p[1] + d1, 3.0 * p[2] * p[2]],
            [d2 * p[0] * p[1] + d1, d2 * p[0] * p[0], 0.0],
            [3.0 * p[2] * p[2], 0.0, 6.0 * p[2] * p[0]],
        ];
        for i in 0..3 {
            for j in 0..3 {
                assert!((h[i][j] - h_ref[i][j]).abs() < 1e-14, "hess {i}{j}");
            }
        }
    }

    #[test]
    fn dual1_product_rule() {
        let a = Dual1::<3>::var(2.0, 0);
        let b = Dual1::var(3.0, 1);
        let c = (a * b - a.scale(2.0)).tanh();
        let v = (6.0f64 - 4.0).tanh();
        let d = 1.0 - v * v;
        assert!((c.v - v).abs() < 1e-15);
        assert!((c.g[0] - d * (3.0 - 2.0)).abs() < 1e-15);
        assert!((c.g[1] - d * 2.0).abs() < 1e-15);
        assert_eq!(c.g[2], 0.0);
    }
}

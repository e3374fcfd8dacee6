//! Forward-mode dual numbers: one generic code path gives values, gradients and Hessians exactly.
//!
//! `Dual1` carries a value and a gradient with respect to three seeds; `Jet2` adds the symmetric
//! Hessian. Both, and plain `f64`, implement [`Scalar`], so the charts and the MLP are written
//! once and differentiated by evaluation.

use std::ops::{Add, Mul, Neg, Sub};

/// The arithmetic the generic code needs.
pub trait Scalar:
    Copy + Add<Output = Self> + Sub<Output = Self> + Mul<Output = Self> + Neg<Output = Self>
{
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
}

impl Scalar for f64 {
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
}

/// Value and gradient with respect to three variables.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Dual1 {
    pub v: f64,
    pub g: [f64; 3],
}

impl Dual1 {
    /// The `i`-th independent variable with value `v`.
    pub fn var(v: f64, i: usize) -> Self {
        let mut g = [0.0; 3];
        g[i] = 1.0;
        Dual1 { v, g }
    }
}

impl Add for Dual1 {
    type Output = Self;
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        Dual1 {
            v: self.v + o.v,
            g: [self.g[0] + o.g[0], self.g[1] + o.g[1], self.g[2] + o.g[2]],
        }
    }
}

impl Sub for Dual1 {
    type Output = Self;
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        Dual1 {
            v: self.v - o.v,
            g: [self.g[0] - o.g[0], self.g[1] - o.g[1], self.g[2] - o.g[2]],
        }
    }
}

impl Neg for Dual1 {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        Dual1 {
            v: -self.v,
            g: [-self.g[0], -self.g[1], -self.g[2]],
        }
    }
}

impl Mul for Dual1 {
    type Output = Self;
    #[inline(always)]
    fn mul(self, o: Self) -> Self {
        let mut g = [0.0; 3];
        for (i, gi) in g.iter_mut().enumerate() {
            *gi = self.v * o.g[i] + o.v * self.g[i];
        }
        Dual1 { v: self.v * o.v, g }
    }
}

impl Scalar for Dual1 {
    fn cst(v: f64) -> Self {
        Dual1 { v, g: [0.0; 3] }
    }
    fn value(&self) -> f64 {
        self.v
    }
    #[inline(always)]
    fn scale(self, c: f64) -> Self {
        Dual1 {
            v: self.v * c,
            g: [self.g[0] * c, self.g[1] * c, self.g[2] * c],
        }
    }
    fn chain(self, f: f64, df: f64, _d2f: f64) -> Self {
        Dual1 {
            v: f,
            g: [df * self.g[0], df * self.g[1], df * self.g[2]],
        }
    }
    fn is_finite(&self) -> bool {
        self.v.is_finite() && self.g.iter().all(|x| x.is_finite())
    }
}

/// Index of the Hessian entry (i, j) in the packed upper triangle `[00, 01, 02, 11, 12, 22]`.
pub const fn sym(i: usize, j: usize) -> usize {
    let (a, b) = if i <= j { (i, j) } else { (j, i) };
    match (a, b) {
        (0, 0) => 0,
        (0, 1) => 1,
        (0, 2) => 2,
        (1, 1) => 3,
        (1, 2) => 4,
        _ => 5,
    }
}

/// Pairs (i, j), i ≤ j, in packed order.
pub const PAIRS: [(usize, usize); 6] = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)];

/// Value, gradient and (packed, symmetric) Hessian with respect to three variables.
///
/// Stored as one array `[v, g0, g1, g2, h00, h01, h02, h11, h12, h22]` so that a linear layer is
/// ten multiply-adds over contiguous memory.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Jet2(pub [f64; 10]);

impl Jet2 {
    /// The `i`-th independent variable with value `v`.
    pub fn var(v: f64, i: usize) -> Self {
        let mut a = [0.0; 10];
        a[0] = v;
        a[1 + i] = 1.0;
        Jet2(a)
    }
    pub fn grad(&self) -> [f64; 3] {
        [self.0[1], self.0[2], self.0[3]]
    }
    pub fn hess(&self) -> [[f64; 3]; 3] {
        let mut h = [[0.0; 3]; 3];
        for (k, &(i, j)) in PAIRS.iter().enumerate() {
            h[i][j] = self.0[4 + k];
            h[j][i] = self.0[4 + k];
        }
        h
    }
}

impl Add for Jet2 {
    type Output = Self;
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        let mut a = self.0;
        for (x, y) in a.iter_mut().zip(o.0) {
            *x += y;
        }
        Jet2(a)
    }
}

impl Sub for Jet2 {
    type Output = Self;
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        let mut a = self.0;
        for (x, y) in a.iter_mut().zip(o.0) {
            *x -= y;
        }
        Jet2(a)
    }
}

impl Neg for Jet2 {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        self.scale(-1.0)
    }
}

impl Mul for Jet2 {
    type Output = Self;
    #[inline(always)]
    fn mul(self, o: Self) -> Self {
        let (a, b) = (&self.0, &o.0);
        let mut r = [0.0; 10];
        r[0] = a[0] * b[0];
        for i in 0..3 {
            r[1 + i] = a[0] * b[1 + i] + b[0] * a[1 + i];
        }
        for (k, &(i, j)) in PAIRS.iter().enumerate() {
            r[4 + k] =
                a[0] * b[4 + k] + b[0] * a[4 + k] + a[1 + i] * b[1 + j] + a[1 + j] * b[1 + i];
        }
        Jet2(r)
    }
}

impl Scalar for Jet2 {
    fn cst(v: f64) -> Self {
        let mut a = [0.0; 10];
        a[0] = v;
        Jet2(a)
    }
    fn value(&self) -> f64 {
        self.0[0]
    }
    #[inline(always)]
    fn scale(self, c: f64) -> Self {
        let mut a = self.0;
        for x in a.iter_mut() {
            *x *= c;
        }
        Jet2(a)
    }
    #[inline(always)]
    fn mul_add(self, c: f64, acc: Self) -> Self {
        let mut a = acc.0;
        for (x, y) in a.iter_mut().zip(self.0) {
            *x += y * c;
        }
        Jet2(a)
    }
    fn chain(self, f: f64, df: f64, d2f: f64) -> Self {
        let a = &self.0;
        let mut r = [0.0; 10];
        r[0] = f;
        for i in 0..3 {
            r[1 + i] = df * a[1 + i];
        }
        for (k, &(i, j)) in PAIRS.iter().enumerate() {
            r[4 + k] = df * a[4 + k] + d2f * a[1 + i] * a[1 + j];
        }
        Jet2(r)
    }
    fn is_finite(&self) -> bool {
        self.0.iter().all(|x| x.is_finite())
    }
}

/// A scalar that can seed one of the three independent variables p₁, p₂, p₃: lets one generic
/// evaluation of S give either its gradient ([`Dual1`]) or its gradient and Hessian ([`Jet2`]).
pub trait Variable: Scalar {
    /// Numbers carried per quantity: the rows of a batched layer hold this many per trajectory.
    const COMPONENTS: usize;
    /// The `i`-th independent variable with value `v`.
    fn variable(v: f64, i: usize) -> Self;
    /// The same quantity from a [`Jet2`] (dropping what this type does not carry).
    fn from_jet(j: &Jet2) -> Self;
    /// Component `c` (0 is the value).
    fn component(&self, c: usize) -> f64;
    /// The quantity whose component `c` is `f(c)`.
    fn from_components(f: impl Fn(usize) -> f64) -> Self;
    /// tanh with its chain rule, in place, on `rows` of a batched layer: each row holds the
    /// components of `n` trajectories, component-major (`row[c·n + j]`).
    fn tanh_rows(z: &mut [f64], rows: usize, n: usize);
}

impl Variable for Dual1 {
    const COMPONENTS: usize = 4;
    fn variable(v: f64, i: usize) -> Self {
        Dual1::var(v, i)
    }
    fn from_jet(j: &Jet2) -> Self {
        Dual1 {
            v: j.0[0],
            g: j.grad(),
        }
    }
    #[inline(always)]
    fn component(&self, c: usize) -> f64 {
        if c == 0 {
            self.v
        } else {
            self.g[c - 1]
        }
    }
    #[inline(always)]
    fn from_components(f: impl Fn(usize) -> f64) -> Self {
        Dual1 {
            v: f(0),
            g: [f(1), f(2), f(3)],
        }
    }
    fn tanh_rows(z: &mut [f64], rows: usize, n: usize) {
        for row in z.chunks_exact_mut(4 * n).take(rows) {
            let (v, g) = row.split_at_mut(n);
            let (g0, g12) = g.split_at_mut(n);
            let (g1, g2) = g12.split_at_mut(n);
            for j in 0..n {
                let y = v[j].tanh();
                let d = 1.0 - y * y;
                v[j] = y;
                g0[j] *= d;
                g1[j] *= d;
                g2[j] *= d;
            }
        }
    }
}

impl Variable for Jet2 {
    const COMPONENTS: usize = 10;
    fn variable(v: f64, i: usize) -> Self {
        Jet2::var(v, i)
    }
    fn from_jet(j: &Jet2) -> Self {
        *j
    }
    #[inline(always)]
    fn component(&self, c: usize) -> f64 {
        self.0[c]
    }
    #[inline(always)]
    fn from_components(f: impl Fn(usize) -> f64) -> Self {
        Jet2(std::array::from_fn(f))
    }
    fn tanh_rows(z: &mut [f64], rows: usize, n: usize) {
        for row in z.chunks_exact_mut(10 * n).take(rows) {
            let (v, rest) = row.split_at_mut(n);
            let (g, h) = rest.split_at_mut(3 * n);
            for j in 0..n {
                let y = v[j].tanh();
                let d1 = 1.0 - y * y;
                let d2 = -2.0 * y * d1;
                v[j] = y;
                let gj = [g[j], g[n + j], g[2 * n + j]];
                // The Hessian first: it needs the incoming gradient (Jet2::chain's formula).
                for (k, &(a, b)) in PAIRS.iter().enumerate() {
                    h[k * n + j] = d1 * h[k * n + j] + d2 * gj[a] * gj[b];
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
        let x: [Jet2; 3] = [Jet2::var(p[0], 0), Jet2::var(p[1], 1), Jet2::var(p[2], 2)];
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
        let a = Dual1::var(2.0, 0);
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

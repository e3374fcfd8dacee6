//! Truncated power series in (t, δ₁ … δ_N): the arithmetic of Taylor-HJ by jets.
//!
//! A series is a dense coefficient vector over the monomials t^a δ^α with a ≤ K and
//! a + |α| ≤ K + 2 ([`SeriesSpace`]). That set is closed under the operations the HJ recursion
//! needs: S(t, p + δ) = Σ_{k ≤ K} t^k S_k(p + δ), ∂S/∂δ lowers |α| by one and the t-integral of
//! H(sou(∂S/∂δ, p + δ)) raises a by one, so the coefficients of S_k up to |α| = K + 2 − k are
//! exact; the gradient and Hessian of S(h, ·) at p (|α| ≤ 2) are what the Newton step needs.
//! Smooth functions act by their Taylor coefficients at the constant term (Horner in the
//! non-constant part, which is nilpotent in the truncation).

use crate::error::CoreError;
use crate::expression::{Expression, Op};

/// Largest number of series variables (t and δ).
pub const MAX_VARS: usize = 12;
/// Largest number of coefficients of one series, and of entries of the product table: the
/// memory of a space stays below ~100 MB.
pub const MAX_COEFFS: usize = 200_000;
pub const MAX_PRODUCTS: usize = 8_000_000;

fn oom(what: &str) -> CoreError {
    CoreError::Memory(format!("cannot allocate {what}"))
}

fn try_vec<T: Clone>(n: usize, v: T, what: &str) -> Result<Vec<T>, CoreError> {
    let mut out = Vec::new();
    out.try_reserve_exact(n).map_err(|_| oom(what))?;
    out.resize(n, v);
    Ok(out)
}

/// The monomials and operation tables of the series in `vars` variables (variable 0 is t),
/// t-degree ≤ `t_degree`, total degree ≤ `degree`.
#[derive(Clone, Debug)]
pub struct SeriesSpace {
    vars: usize,
    t_degree: u8,
    degree: u8,
    exponents: Vec<u8>,
    /// (j, k) of row i at `rows[i]..rows[i + 1]`: coefficient i times coefficient j adds to k.
    products: Vec<(u32, u32)>,
    rows: Vec<u32>,
    /// Per δ variable (1..vars): (from, to, factor) of ∂/∂δ.
    derivatives: Vec<Vec<(u32, u32, f64)>>,
    /// (from, to, factor) of ∫₀ᵗ · dt.
    integral: Vec<(u32, u32, f64)>,
}

impl SeriesSpace {
    pub fn new(vars: usize, t_degree: u8, degree: u8) -> Result<Self, CoreError> {
        if vars == 0 || vars > MAX_VARS || degree > 15 || t_degree > degree {
            return Err(CoreError::Invalid(format!(
                "a series space needs 1..={MAX_VARS} variables and t-degree <= degree <= 15, \
                 got {vars}, {t_degree}, {degree}"
            )));
        }
        // Every exponent vector, by total degree then lexicographically.
        let mut exponents: Vec<u8> = Vec::new();
        let mut current = vec![0u8; vars];
        for total in 0..=degree {
            let start = exponents.len();
            Self::compositions(&mut current, 0, total, &mut |e: &[u8]| {
                if e[0] <= t_degree {
                    exponents.extend_from_slice(e);
                }
            });
            if exponents.len() / vars > MAX_COEFFS {
                let _ = start;
                return Err(CoreError::Invalid(format!(
                    "a series in {vars} variables to degree {degree} has over {MAX_COEFFS} \
                     coefficients: lower the order or the dimension"
                )));
            }
        }
        let m = exponents.len() / vars;
        let key = |e: &[u8]| e.iter().fold(0u64, |k, &v| (k << 4) | u64::from(v));
        let mut index = std::collections::HashMap::new();
        index.try_reserve(m).map_err(|_| oom("the series index"))?;
        for i in 0..m {
            index.insert(key(&exponents[i * vars..(i + 1) * vars]), i as u32);
        }
        let deg = |i: usize| -> u8 { exponents[i * vars..(i + 1) * vars].iter().sum() };
        let mut products = Vec::new();
        let mut rows = Vec::new();
        rows.try_reserve_exact(m + 1)
            .map_err(|_| oom("the product table"))?;
        let mut sum = vec![0u8; vars];
        for i in 0..m {
            rows.push(products.len() as u32);
            let di = deg(i);
            for j in 0..m {
                // Sorted by degree: the rest of the row is past the truncation.
                if di + deg(j) > degree {
                    break;
                }
                let (ei, ej) = (
                    &exponents[i * vars..][..vars],
                    &exponents[j * vars..][..vars],
                );
                if ei[0] + ej[0] > t_degree {
                    continue;
                }
                for v in 0..vars {
                    sum[v] = ei[v] + ej[v];
                }
                if let Some(&k) = index.get(&key(&sum)) {
                    if products.len() >= MAX_PRODUCTS {
                        return Err(CoreError::Invalid(format!(
                            "a series in {vars} variables to degree {degree} needs over \
                             {MAX_PRODUCTS} products: lower the order or the dimension"
                        )));
                    }
                    products
                        .try_reserve(1)
                        .map_err(|_| oom("the product table"))?;
                    products.push((j as u32, k));
                }
            }
        }
        rows.push(products.len() as u32);
        let mut derivatives = Vec::new();
        derivatives
            .try_reserve_exact(vars)
            .map_err(|_| oom("the derivative tables"))?;
        derivatives.push(Vec::new());
        for v in 1..vars {
            let mut table = Vec::new();
            for i in 0..m {
                let e = &exponents[i * vars..(i + 1) * vars];
                if e[v] > 0 {
                    sum.copy_from_slice(e);
                    sum[v] -= 1;
                    let k = index[&key(&sum)];
                    table
                        .try_reserve(1)
                        .map_err(|_| oom("the derivative tables"))?;
                    table.push((i as u32, k, f64::from(e[v])));
                }
            }
            derivatives.push(table);
        }
        let mut integral = Vec::new();
        for i in 0..m {
            let e = &exponents[i * vars..(i + 1) * vars];
            sum.copy_from_slice(e);
            sum[0] += 1;
            if let Some(&k) = index.get(&key(&sum)) {
                integral
                    .try_reserve(1)
                    .map_err(|_| oom("the integral table"))?;
                integral.push((i as u32, k, 1.0 / f64::from(sum[0])));
            }
        }
        Ok(SeriesSpace {
            vars,
            t_degree,
            degree,
            exponents,
            products,
            rows,
            derivatives,
            integral,
        })
    }

    fn compositions(current: &mut [u8], at: usize, left: u8, f: &mut impl FnMut(&[u8])) {
        if at == current.len() - 1 {
            current[at] = left;
            f(current);
            return;
        }
        for v in (0..=left).rev() {
            current[at] = v;
            Self::compositions(current, at + 1, left - v, f);
        }
    }

    /// Coefficients of one series.
    pub fn len(&self) -> usize {
        self.exponents.len() / self.vars
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn vars(&self) -> usize {
        self.vars
    }

    pub fn t_degree(&self) -> u8 {
        self.t_degree
    }

    pub fn degree(&self) -> u8 {
        self.degree
    }

    pub fn n_products(&self) -> usize {
        self.products.len()
    }

    pub fn exponent(&self, i: usize) -> &[u8] {
        &self.exponents[i * self.vars..(i + 1) * self.vars]
    }

    /// The index of the monomial with these exponents, if it is in the space.
    pub fn index_of(&self, e: &[u8]) -> Option<usize> {
        (0..self.len()).find(|&i| self.exponent(i) == e)
    }

    /// out = a · b.
    pub fn mul(&self, a: &[f64], b: &[f64], out: &mut [f64]) {
        out.fill(0.0);
        for (i, &ai) in a.iter().enumerate() {
            // Most series are sparse (∂S/∂δ has no t⁰ term, a constant has one coefficient).
            if ai == 0.0 {
                continue;
            }
            let row = &self.products[self.rows[i] as usize..self.rows[i + 1] as usize];
            for &(j, k) in row {
                out[k as usize] += ai * b[j as usize];
            }
        }
    }

    /// out = ∂a/∂δ_v (v in 1..vars).
    pub fn derivative(&self, a: &[f64], v: usize, out: &mut [f64]) {
        out.fill(0.0);
        for &(i, k, f) in &self.derivatives[v] {
            out[k as usize] += f * a[i as usize];
        }
    }

    /// out = ∫₀ᵗ a dt (terms past the truncation dropped).
    pub fn integral(&self, a: &[f64], out: &mut [f64]) {
        out.fill(0.0);
        for &(i, k, f) in &self.integral {
            out[k as usize] = f * a[i as usize];
        }
    }

    /// out = f(a) for f given by its Taylor coefficients `c[k] = f⁽ᵏ⁾(a₀)/k!` (k = 0 ..=
    /// degree) at the constant term a₀: Horner in a − a₀. `tmp` is scratch of the same length.
    pub fn compose(&self, c: &[f64], a: &[f64], out: &mut [f64], tmp: &mut [f64], hat: &mut [f64]) {
        hat.copy_from_slice(a);
        hat[0] = 0.0;
        let d = usize::from(self.degree);
        out.fill(0.0);
        out[0] = c[d];
        for k in (0..d).rev() {
            self.mul(out, hat, tmp);
            tmp[0] += c[k];
            out.copy_from_slice(tmp);
        }
    }
}

/// The Taylor coefficients f⁽ᵏ⁾(a)/k!, k = 0 ..= degree, of the smooth functions of the tape
/// (out of domain: NaN, which the step reports as non-finite).
pub fn taylor_coefficients(op: &Op, a: f64, degree: usize, c: &mut [f64]) {
    let mut factorial = 1.0;
    match *op {
        Op::Exp(_) => {
            let e = a.exp();
            for (k, ck) in c.iter_mut().enumerate().take(degree + 1) {
                if k > 0 {
                    factorial *= k as f64;
                }
                *ck = e / factorial;
            }
        }
        Op::Log(_) => {
            c[0] = a.ln();
            let mut pw = 1.0;
            for (k, ck) in c.iter_mut().enumerate().take(degree + 1).skip(1) {
                pw *= a;
                let sign = if k % 2 == 1 { 1.0 } else { -1.0 };
                *ck = if a > 0.0 {
                    sign / (k as f64 * pw)
                } else {
                    f64::NAN
                };
            }
        }
        Op::Sin(_) | Op::Cos(_) => {
            let (s, co) = a.sin_cos();
            let cycle = if matches!(op, Op::Sin(_)) {
                [s, co, -s, -co]
            } else {
                [co, -s, -co, s]
            };
            for (k, ck) in c.iter_mut().enumerate().take(degree + 1) {
                if k > 0 {
                    factorial *= k as f64;
                }
                *ck = cycle[k % 4] / factorial;
            }
        }
        Op::Powf(_, r) => power_coefficients(a, r, degree, c),
        Op::Sqrt(_) => power_coefficients(a, 0.5, degree, c),
        _ => {
            // 1/a: (−1)^k / a^{k+1}, for any a ≠ 0.
            let inv = 1.0 / a;
            let mut v = inv;
            for (k, ck) in c.iter_mut().enumerate().take(degree + 1) {
                *ck = if k % 2 == 0 { v } else { -v };
                v *= inv;
            }
        }
    }
}

/// (a + x)^r = Σ binom(r, k) a^{r−k} x^k; NaN for a ≤ 0 (not smooth there for a real r).
fn power_coefficients(a: f64, r: f64, degree: usize, c: &mut [f64]) {
    if a <= 0.0 || !a.is_finite() {
        c[..=degree].fill(f64::NAN);
        return;
    }
    c[0] = a.powf(r);
    for k in 1..=degree {
        c[k] = c[k - 1] * (r - (k as f64) + 1.0) / (k as f64 * a);
    }
}

/// Registers for evaluating an [`Expression`] on series: `ops` + 4 scratch series.
#[derive(Clone, Debug)]
pub struct SeriesRegisters {
    regs: Vec<f64>,
    coeffs: Vec<f64>,
}

impl SeriesRegisters {
    pub fn new(space: &SeriesSpace, expression: &Expression) -> Result<Self, CoreError> {
        let m = space.len();
        let n = (expression.ops().len() + 4)
            .checked_mul(m)
            .ok_or_else(|| oom("series registers"))?;
        Ok(SeriesRegisters {
            regs: try_vec(n, 0.0, "series registers")?,
            coeffs: try_vec(usize::from(space.degree()) + 1, 0.0, "series registers")?,
        })
    }

    pub fn bytes(space: &SeriesSpace, expression: &Expression) -> usize {
        (expression.ops().len() + 4) * space.len() * 8
    }
}

/// H(u) on series: `inputs[i]` is the series of variable i; the value goes to `out`.
pub fn eval_expression(
    space: &SeriesSpace,
    expression: &Expression,
    inputs: &[&[f64]],
    out: &mut [f64],
    ws: &mut SeriesRegisters,
) {
    let m = space.len();
    let n = expression.ops().len();
    let (regs, scratch) = ws.regs.split_at_mut(n * m);
    let (t1, rest) = scratch.split_at_mut(m);
    let (t2, rest) = rest.split_at_mut(m);
    let (t3, rest) = rest.split_at_mut(m);
    let t4 = &mut rest[..m];
    for (k, op) in expression.ops().iter().enumerate() {
        let (done, now) = regs.split_at_mut(k * m);
        let r = &mut now[..m];
        let get = |i: usize| &done[i * m..(i + 1) * m];
        match *op {
            Op::Var(i) => r.copy_from_slice(inputs[i]),
            Op::Const(c) => {
                r.fill(0.0);
                r[0] = c;
            }
            Op::Add(a, b) => {
                for ((o, x), y) in r.iter_mut().zip(get(a)).zip(get(b)) {
                    *o = x + y;
                }
            }
            Op::Sub(a, b) => {
                for ((o, x), y) in r.iter_mut().zip(get(a)).zip(get(b)) {
                    *o = x - y;
                }
            }
            Op::Neg(a) => {
                for (o, x) in r.iter_mut().zip(get(a)) {
                    *o = -x;
                }
            }
            Op::Mul(a, b) => space.mul(get(a), get(b), r),
            Op::Div(a, b) => {
                let bb = get(b);
                taylor_coefficients(
                    &Op::Div(0, 0),
                    bb[0],
                    usize::from(space.degree()),
                    &mut ws.coeffs,
                );
                space.compose(&ws.coeffs, bb, t1, t2, t3);
                space.mul(get(a), t1, r);
            }
            Op::Powi(a, e) => {
                // Repeated squaring of a (or of 1/a).
                let base = get(a);
                if e < 0 {
                    taylor_coefficients(
                        &Op::Div(0, 0),
                        base[0],
                        usize::from(space.degree()),
                        &mut ws.coeffs,
                    );
                    space.compose(&ws.coeffs, base, t4, t2, t3);
                } else {
                    t4.copy_from_slice(base);
                }
                r.fill(0.0);
                r[0] = 1.0;
                let mut left = e.unsigned_abs();
                while left > 0 {
                    if left & 1 == 1 {
                        space.mul(r, t4, t1);
                        r.copy_from_slice(t1);
                    }
                    left >>= 1;
                    if left > 0 {
                        space.mul(t4, t4, t1);
                        t4.copy_from_slice(t1);
                    }
                }
            }
            Op::Tan(a) => {
                let x = get(a);
                let d = usize::from(space.degree());
                taylor_coefficients(&Op::Cos(0), x[0], d, &mut ws.coeffs);
                space.compose(&ws.coeffs, x, t4, t2, t3);
                taylor_coefficients(&Op::Div(0, 0), t4[0], d, &mut ws.coeffs);
                space.compose(&ws.coeffs, t4, t1, t2, t3);
                taylor_coefficients(&Op::Sin(0), x[0], d, &mut ws.coeffs);
                space.compose(&ws.coeffs, x, t4, t2, t3);
                space.mul(t4, t1, r);
            }
            Op::Tanh(a) => {
                // tanh x = 1 − 2/(e^{2x} + 1).
                let x = get(a);
                let d = usize::from(space.degree());
                for (o, v) in t4.iter_mut().zip(x) {
                    *o = 2.0 * v;
                }
                taylor_coefficients(&Op::Exp(0), t4[0], d, &mut ws.coeffs);
                space.compose(&ws.coeffs, t4, t1, t2, t3);
                t1[0] += 1.0;
                taylor_coefficients(&Op::Div(0, 0), t1[0], d, &mut ws.coeffs);
                space.compose(&ws.coeffs, t1, t4, t2, t3);
                for (o, v) in r.iter_mut().zip(t4.iter()) {
                    *o = -2.0 * v;
                }
                r[0] += 1.0;
            }
            Op::Exp(a) | Op::Log(a) | Op::Sin(a) | Op::Cos(a) | Op::Powf(a, _) | Op::Sqrt(a) => {
                let x = get(a);
                taylor_coefficients(op, x[0], usize::from(space.degree()), &mut ws.coeffs);
                space.compose(&ws.coeffs, x, r, t2, t3);
            }
        }
    }
    out.copy_from_slice(&regs[(n - 1) * m..n * m]);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn coefficient(space: &SeriesSpace, s: &[f64], e: &[u8]) -> f64 {
        s[space.index_of(e).unwrap()]
    }

    /// exp, log, sin, tan and a division on a two-variable series against their known
    /// expansions.
    #[test]
    fn elementary_functions_match_their_expansions() {
        let space = SeriesSpace::new(2, 4, 6).unwrap();
        // u = 0.3 + t + δ.
        let mut u = vec![0.0; space.len()];
        u[0] = 0.3;
        u[space.index_of(&[1, 0]).unwrap()] = 1.0;
        u[space.index_of(&[0, 1]).unwrap()] = 1.0;
        // f(0.3 + t + δ): coefficient of t δ is f''(0.3)/1! · (2!/(1!1!))/2! = f''(0.3).
        let cases: [(i64, f64, f64); 4] = [
            (9, 0.3f64.exp(), 0.3f64.exp()),
            (10, 0.3f64.ln(), -1.0 / 0.09),
            (11, 0.3f64.sin(), -0.3f64.sin()),
            (13, 0.3f64.tan(), {
                let t = 0.3f64.tan();
                2.0 * t * (1.0 + t * t)
            }),
        ];
        for (code, v, d2) in cases {
            let e = Expression::from_table(1, &[0, code], &[0, 0], &[0, 0], &[0.0, 0.0]).unwrap();
            let mut ws = SeriesRegisters::new(&space, &e).unwrap();
            let mut out = vec![0.0; space.len()];
            eval_expression(&space, &e, &[&u], &mut out, &mut ws);
            assert!((out[0] - v).abs() < 1e-14, "opcode {code}");
            let td = coefficient(&space, &out, &[1, 1]);
            assert!((td - d2).abs() < 1e-12, "opcode {code}: {td} vs {d2}");
        }
    }

    #[test]
    fn products_respect_the_truncation() {
        let space = SeriesSpace::new(2, 1, 3).unwrap();
        let mut t = vec![0.0; space.len()];
        t[space.index_of(&[1, 0]).unwrap()] = 1.0;
        let mut out = vec![0.0; space.len()];
        space.mul(&t, &t, &mut out);
        assert!(out.iter().all(|&v| v == 0.0), "t² is past t-degree 1");
        assert!(SeriesSpace::new(13, 2, 4).is_err());
    }
}

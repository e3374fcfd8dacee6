//! A Hamiltonian given as an expression: a straight-line program ("tape") over + − × ÷, integer
//! and real powers, exp, log, sin, cos, tan, sqrt and tanh, compiled in Python from a bounded
//! grammar. The core evaluates it on any [`Scalar`] (f64, [`crate::dual::Dual1`] for ∇H,
//! [`crate::dual::Jet2`] for ∇²H, exactly, by forward mode) and on truncated power series
//! ([`crate::series`]) for Taylor-HJ by jets.

use crate::dual::Scalar;
use crate::error::CoreError;

/// Most instructions of a tape: the registers of one evaluation live on the stack.
pub const MAX_TAPE: usize = 256;
/// Largest |n| of an integer power.
pub const MAX_POWI: i64 = 64;

/// One instruction; operands name earlier instructions (registers).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Op {
    Var(usize),
    Const(f64),
    Add(usize, usize),
    Sub(usize, usize),
    Mul(usize, usize),
    Div(usize, usize),
    Neg(usize),
    Powi(usize, i32),
    Powf(usize, f64),
    Exp(usize),
    Log(usize),
    Sin(usize),
    Cos(usize),
    Tan(usize),
    Sqrt(usize),
    Tanh(usize),
}

/// The opcodes of the table the bindings receive, in order (`ops[k]` is the index of a name).
pub const OPCODES: [&str; 16] = [
    "var", "const", "add", "sub", "mul", "div", "neg", "powi", "powf", "exp", "log", "sin", "cos",
    "tan", "sqrt", "tanh",
];

/// A checked tape in `vars` variables; its value is the last instruction's.
#[derive(Clone, Debug, PartialEq)]
pub struct Expression {
    vars: usize,
    ops: Vec<Op>,
}

impl Expression {
    /// From the table form: `code[k]` indexes [`OPCODES`], `a[k]`/`b[k]` are operands (a
    /// variable's index for "var", an integer exponent in `b` for "powi"), `c[k]` a constant
    /// ("const", the exponent of "powf"). Every operand must name an earlier instruction.
    pub fn from_table(
        vars: usize,
        code: &[i64],
        a: &[i64],
        b: &[i64],
        c: &[f64],
    ) -> Result<Self, CoreError> {
        let n = code.len();
        if n == 0 || n > MAX_TAPE {
            return Err(CoreError::Invalid(format!(
                "an expression needs 1..={MAX_TAPE} instructions, got {n}"
            )));
        }
        if a.len() != n || b.len() != n || c.len() != n {
            return Err(CoreError::Invalid(format!(
                "an expression table needs {n} entries in each column, got {}, {}, {}",
                a.len(),
                b.len(),
                c.len()
            )));
        }
        let mut ops = Vec::new();
        ops.try_reserve_exact(n)
            .map_err(|_| CoreError::Invalid("expression too long".into()))?;
        for k in 0..n {
            let bad =
                |what: &str| CoreError::Invalid(format!("expression instruction {k}: {what}"));
            let reg = |r: i64| -> Result<usize, CoreError> {
                if r >= 0 && (r as usize) < k {
                    Ok(r as usize)
                } else {
                    Err(bad(&format!(
                        "operand {r} does not name an earlier instruction"
                    )))
                }
            };
            let op = match code[k] {
                0 => {
                    if a[k] < 0 || a[k] as usize >= vars {
                        return Err(bad(&format!("variable {} outside 0..{vars}", a[k])));
                    }
                    Op::Var(a[k] as usize)
                }
                1 => {
                    if !c[k].is_finite() {
                        return Err(bad("constant is not finite"));
                    }
                    Op::Const(c[k])
                }
                2 => Op::Add(reg(a[k])?, reg(b[k])?),
                3 => Op::Sub(reg(a[k])?, reg(b[k])?),
                4 => Op::Mul(reg(a[k])?, reg(b[k])?),
                5 => Op::Div(reg(a[k])?, reg(b[k])?),
                6 => Op::Neg(reg(a[k])?),
                7 => {
                    if b[k].abs() > MAX_POWI {
                        return Err(bad(&format!("integer exponent {} over {MAX_POWI}", b[k])));
                    }
                    Op::Powi(reg(a[k])?, b[k] as i32)
                }
                8 => {
                    if !c[k].is_finite() {
                        return Err(bad("exponent is not finite"));
                    }
                    Op::Powf(reg(a[k])?, c[k])
                }
                9 => Op::Exp(reg(a[k])?),
                10 => Op::Log(reg(a[k])?),
                11 => Op::Sin(reg(a[k])?),
                12 => Op::Cos(reg(a[k])?),
                13 => Op::Tan(reg(a[k])?),
                14 => Op::Sqrt(reg(a[k])?),
                15 => Op::Tanh(reg(a[k])?),
                other => return Err(bad(&format!("unknown opcode {other}"))),
            };
            ops.push(op);
        }
        Ok(Expression { vars, ops })
    }

    pub fn vars(&self) -> usize {
        self.vars
    }

    pub fn ops(&self) -> &[Op] {
        &self.ops
    }

    /// The value at `x` (at least `vars` entries), on any scalar. Outside the domain of a
    /// function (log of a negative number, a pole) the result is not finite, never a panic.
    pub fn eval<T: Scalar>(&self, x: &[T]) -> T {
        let mut r = [T::cst(0.0); MAX_TAPE];
        for (k, op) in self.ops.iter().enumerate() {
            r[k] = match *op {
                Op::Var(i) => x[i],
                Op::Const(c) => T::cst(c),
                Op::Add(a, b) => r[a] + r[b],
                Op::Sub(a, b) => r[a] - r[b],
                Op::Mul(a, b) => r[a] * r[b],
                Op::Div(a, b) => r[a] * r[b].recip(),
                Op::Neg(a) => -r[a],
                Op::Powi(a, n) => powi(r[a], n),
                Op::Powf(a, p) => {
                    let v = r[a].value();
                    let vp = v.powf(p);
                    r[a].chain(vp, p * vp / v, p * (p - 1.0) * vp / (v * v))
                }
                Op::Exp(a) => {
                    let e = r[a].value().exp();
                    r[a].chain(e, e, e)
                }
                Op::Log(a) => {
                    let v = r[a].value();
                    r[a].chain(v.ln(), 1.0 / v, -1.0 / (v * v))
                }
                Op::Sin(a) => {
                    let (s, c) = r[a].value().sin_cos();
                    r[a].chain(s, c, -s)
                }
                Op::Cos(a) => {
                    let (s, c) = r[a].value().sin_cos();
                    r[a].chain(c, -s, -c)
                }
                Op::Tan(a) => {
                    let t = r[a].value().tan();
                    let d = 1.0 + t * t;
                    r[a].chain(t, d, 2.0 * t * d)
                }
                Op::Sqrt(a) => r[a].sqrt(),
                Op::Tanh(a) => r[a].tanh(),
            };
        }
        r[self.ops.len() - 1]
    }
}

/// Value and gradient registers of [`Expression::gradient_lanes`] for tapes of up to `CAP`
/// instructions: sized by the tape, so a short H does not clear a long register file.
macro_rules! by_capacity {
    ($len:expr, $cap:ident => $body:expr) => {
        match $len {
            0..=16 => {
                const $cap: usize = 16;
                $body
            }
            17..=48 => {
                const $cap: usize = 48;
                $body
            }
            49..=128 => {
                const $cap: usize = 128;
                $body
            }
            _ => {
                const $cap: usize = MAX_TAPE;
                $body
            }
        }
    };
}

impl Expression {
    /// H and ∇H at L states at once (`x[i][l]`: coordinate i of lane l), forward mode in
    /// structure-of-arrays form: the arithmetic vectorises across lanes, sin/cos and exp go
    /// through the crate's branch-free lane kernels ([`crate::trig`], [`crate::exp`]), the
    /// rest lane by lane. Every lane gets the bits a one-lane call gives it.
    pub fn gradient_lanes<const N: usize, const L: usize>(
        &self,
        x: &[[f64; L]; N],
        value: &mut [f64; L],
        grad: &mut [[f64; L]; N],
    ) {
        by_capacity!(self.ops.len(), CAP => self.gradient_lanes_in::<N, L, CAP>(x, value, grad))
    }

    fn gradient_lanes_in<const N: usize, const L: usize, const CAP: usize>(
        &self,
        x: &[[f64; L]; N],
        value: &mut [f64; L],
        grad: &mut [[f64; L]; N],
    ) {
        let mut v = [[0.0f64; L]; CAP];
        let mut d = [[[0.0f64; L]; N]; CAP];
        for (k, op) in self.ops.iter().enumerate() {
            let (vd, vr) = v.split_at_mut(k);
            let (dd, dr) = d.split_at_mut(k);
            let (out, dout) = (&mut vr[0], &mut dr[0]);
            // out = f(a), dout = f'(a) · da for a smooth f given lane by lane as (f, f').
            let chain = |a: usize, fd: &[[f64; L]; 2], out: &mut [f64; L], dout: &mut [[f64; L]; N]| {
                *out = fd[0];
                for i in 0..N {
                    for l in 0..L {
                        dout[i][l] = fd[1][l] * dd[a][i][l];
                    }
                }
            };
            match *op {
                Op::Var(i) => {
                    *out = x[i];
                    dout[i] = [1.0; L];
                }
                Op::Const(c) => *out = [c; L],
                Op::Add(a, b) => {
                    for l in 0..L {
                        out[l] = vd[a][l] + vd[b][l];
                    }
                    for i in 0..N {
                        for l in 0..L {
                            dout[i][l] = dd[a][i][l] + dd[b][i][l];
                        }
                    }
                }
                Op::Sub(a, b) => {
                    for l in 0..L {
                        out[l] = vd[a][l] - vd[b][l];
                    }
                    for i in 0..N {
                        for l in 0..L {
                            dout[i][l] = dd[a][i][l] - dd[b][i][l];
                        }
                    }
                }
                Op::Neg(a) => {
                    for l in 0..L {
                        out[l] = -vd[a][l];
                    }
                    for i in 0..N {
                        for l in 0..L {
                            dout[i][l] = -dd[a][i][l];
                        }
                    }
                }
                Op::Mul(a, b) => {
                    for l in 0..L {
                        out[l] = vd[a][l] * vd[b][l];
                    }
                    for i in 0..N {
                        for l in 0..L {
                            dout[i][l] = dd[a][i][l] * vd[b][l] + vd[a][l] * dd[b][i][l];
                        }
                    }
                }
                Op::Div(a, b) => {
                    let mut r = [0.0; L];
                    for l in 0..L {
                        r[l] = 1.0 / vd[b][l];
                        out[l] = vd[a][l] * r[l];
                    }
                    for i in 0..N {
                        for l in 0..L {
                            dout[i][l] = (dd[a][i][l] - out[l] * dd[b][i][l]) * r[l];
                        }
                    }
                }
                Op::Powi(a, n) => {
                    // a^(m−1) by repeated multiplication, then a^m and m·a^(m−1); a negative
                    // power as the reciprocal of the positive one.
                    let m = n.unsigned_abs();
                    let mut below = [1.0; L];
                    for _ in 1..m {
                        for l in 0..L {
                            below[l] *= vd[a][l];
                        }
                    }
                    let mut fd = [[0.0; L]; 2];
                    for l in 0..L {
                        let (p, dp) = if m == 0 {
                            (1.0, 0.0)
                        } else {
                            (below[l] * vd[a][l], f64::from(m) * below[l])
                        };
                        fd[0][l] = if n < 0 { 1.0 / p } else { p };
                        fd[1][l] = if n < 0 { -dp / (p * p) } else { dp };
                    }
                    chain(a, &fd, out, dout);
                }
                Op::Exp(a) => {
                    let mut fd = [[0.0; L]; 2];
                    crate::exp::exp_lanes(&vd[a], &mut fd[0]);
                    fd[1] = fd[0];
                    chain(a, &fd, out, dout);
                }
                Op::Sin(a) | Op::Cos(a) | Op::Tan(a) => {
                    let (mut sn, mut cs) = ([0.0; L], [0.0; L]);
                    crate::trig::sin_cos_lanes(&vd[a], &mut sn, &mut cs);
                    let mut fd = [[0.0; L]; 2];
                    for l in 0..L {
                        (fd[0][l], fd[1][l]) = match op {
                            Op::Sin(_) => (sn[l], cs[l]),
                            Op::Cos(_) => (cs[l], -sn[l]),
                            _ => {
                                let t = sn[l] / cs[l];
                                (t, 1.0 + t * t)
                            }
                        };
                    }
                    chain(a, &fd, out, dout);
                }
                Op::Sqrt(a) => chain(a, &lanewise(&vd[a], |y| {
                    let r = y.sqrt();
                    (r, 0.5 / r)
                }), out, dout),
                Op::Log(a) => chain(a, &lanewise(&vd[a], |y| (y.ln(), 1.0 / y)), out, dout),
                Op::Tanh(a) => chain(a, &lanewise(&vd[a], |y| {
                    let t = y.tanh();
                    (t, 1.0 - t * t)
                }), out, dout),
                Op::Powf(a, p) => chain(a, &lanewise(&vd[a], |y| {
                    let yp = y.powf(p);
                    (yp, p * yp / y)
                }), out, dout),
            }
        }
        let last = self.ops.len() - 1;
        *value = v[last];
        *grad = d[last];
    }
}

/// (f(y), f'(y)) lane by lane.
#[inline(always)]
fn lanewise<const L: usize>(y: &[f64; L], f: impl Fn(f64) -> (f64, f64)) -> [[f64; L]; 2] {
    let mut fd = [[0.0; L]; 2];
    for l in 0..L {
        (fd[0][l], fd[1][l]) = f(y[l]);
    }
    fd
}

/// xⁿ by repeated squaring: exact derivatives at x = 0 for n ≥ 0 (the chain rule through
/// n·xⁿ⁻¹ would give 0 · ∞ there).
fn powi<T: Scalar>(x: T, n: i32) -> T {
    if n < 0 {
        return powi(x, -n).recip();
    }
    let mut result = T::cst(1.0);
    let mut base = x;
    let mut e = n as u32;
    let mut first = true;
    while e > 0 {
        if e & 1 == 1 {
            result = if first { base } else { result * base };
            first = false;
        }
        e >>= 1;
        if e > 0 {
            base = base * base;
        }
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dual::Jet2;

    /// H = x0² sin(x1) / (1 + x0) + exp(x1) log(2 + x0²), checked against its hand derivatives.
    #[test]
    fn derivatives_of_a_mixed_expression_match_the_hand_formulas() {
        // 0 x0, 1 x1, 2 x0^2, 3 sin x1, 4 (2)*(3), 5 1, 6 1+x0, 7 (4)/(6), 8 exp x1, 9 2,
        // 10 2+x0^2, 11 log, 12 (8)*(11), 13 (7)+(12)
        let code = [0, 0, 7, 11, 4, 1, 2, 5, 9, 1, 2, 10, 4, 2];
        let a = [0, 1, 0, 1, 2, 0, 5, 4, 1, 0, 9, 10, 8, 7];
        let b = [0, 0, 2, 0, 3, 0, 0, 6, 0, 0, 2, 0, 11, 12];
        let c = [
            0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 0.0,
        ];
        let e = Expression::from_table(2, &code, &a, &b, &c).unwrap();
        let (x, y) = (0.7_f64, -0.4_f64);
        let f = |x: f64, y: f64| x * x * y.sin() / (1.0 + x) + y.exp() * (2.0 + x * x).ln();
        let jet = e.eval(&[Jet2::<2>::var(x, 0), Jet2::<2>::var(y, 1)]);
        assert!((jet.v - f(x, y)).abs() < 1e-15);
        let gx = (2.0 * x * (1.0 + x) - x * x) / (1.0 + x).powi(2) * y.sin()
            + y.exp() * 2.0 * x / (2.0 + x * x);
        let gy = x * x * y.cos() / (1.0 + x) + y.exp() * (2.0 + x * x).ln();
        assert!((jet.g[0] - gx).abs() < 1e-14 && (jet.g[1] - gy).abs() < 1e-14);
        let hyy = -x * x * y.sin() / (1.0 + x) + y.exp() * (2.0 + x * x).ln();
        assert!((jet.hess()[1][1] - hyy).abs() < 1e-14);
    }

    #[test]
    fn bad_tables_are_refused() {
        assert!(Expression::from_table(1, &[2], &[0], &[0], &[0.0]).is_err());
        assert!(Expression::from_table(1, &[0], &[1], &[0], &[0.0]).is_err());
        assert!(Expression::from_table(1, &[1], &[0], &[0], &[f64::NAN]).is_err());
        assert!(Expression::from_table(1, &[0, 7], &[0, 0], &[0, 99], &[0.0, 0.0]).is_err());
        assert!(Expression::from_table(1, &[99], &[0], &[0], &[0.0]).is_err());
        assert!(Expression::from_table(1, &[], &[], &[], &[]).is_err());
    }
}

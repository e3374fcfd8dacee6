//! A Hamiltonian given as an expression: a straight-line program ("tape") over + − × ÷, integer
//! and real powers, exp, log, sin, cos, tan, sqrt and tanh, compiled in Python from a bounded
//! grammar. The core evaluates it on any [`Scalar`] (f64, [`crate::dual::Dual1`] for ∇H,
//! [`crate::dual::Jet2`] for ∇²H, exactly, by forward mode) and on truncated power series
//! ([`crate::series`]) for Taylor-HJ by jets.

use crate::dual::Scalar;
use crate::error::CoreError;

/// Most instructions of a tape evaluated with derivatives: the registers of one evaluation
/// live on the stack.
pub const MAX_TAPE: usize = 256;
/// Most instructions of a program evaluated for values only (a vector field: H's gradient
/// written out, and π).
pub const MAX_PROGRAM: usize = 1024;
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
    /// The registers whose values are the outputs (the last instruction for a Hamiltonian).
    outputs: Vec<usize>,
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
        if code.is_empty() || code.len() > MAX_TAPE {
            return Err(CoreError::Invalid(format!(
                "an expression needs 1..={MAX_TAPE} instructions, got {}",
                code.len()
            )));
        }
        Self::program(vars, code, a, b, c, &[code.len() as i64 - 1])
    }

    /// A program with several outputs (`outputs[m]`: the register of output m), evaluated for
    /// values only ([`Self::values_lanes`]); up to [`MAX_PROGRAM`] instructions.
    pub fn program(
        vars: usize,
        code: &[i64],
        a: &[i64],
        b: &[i64],
        c: &[f64],
        outputs: &[i64],
    ) -> Result<Self, CoreError> {
        let n = code.len();
        if n == 0 || n > MAX_PROGRAM {
            return Err(CoreError::Invalid(format!(
                "a program needs 1..={MAX_PROGRAM} instructions, got {n}"
            )));
        }
        if let Some(bad) = outputs.iter().find(|&&o| o < 0 || o as usize >= n) {
            return Err(CoreError::Invalid(format!(
                "program output {bad} does not name an instruction"
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
        let mut outs = Vec::new();
        outs.try_reserve_exact(outputs.len())
            .map_err(|_| CoreError::Invalid("too many outputs".into()))?;
        outs.extend(outputs.iter().map(|&o| o as usize));
        Ok(Expression {
            vars,
            ops,
            outputs: outs,
        })
    }

    /// The number of outputs.
    pub fn n_outputs(&self) -> usize {
        self.outputs.len()
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
        if self.ops.len() > MAX_TAPE {
            // Only a multi-output program is this long, and it is evaluated by values_lanes.
            return T::cst(f64::NAN);
        }
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

/// Lanes of one block of [`Expression::values_lanes`] (the rollouts' SIMD width).
pub const BLOCK: usize = crate::isa::LANES;
/// Lanes of a wide block, for calls of at least that many lanes: each instruction's dispatch
/// (the match, the operand lookups) is paid once for four times the arithmetic.
pub const WIDE_BLOCK: usize = 4 * BLOCK;

type Registers<const W: usize> = std::cell::RefCell<Vec<[f64; W]>>;

thread_local! {
    /// The value registers of [`Expression::values_lanes`] on this thread, per block width.
    static REGISTERS: Registers<BLOCK> = const { std::cell::RefCell::new(Vec::new()) };
    static WIDE_REGISTERS: Registers<WIDE_BLOCK> = const { std::cell::RefCell::new(Vec::new()) };
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
            129..=MAX_TAPE => {
                const $cap: usize = MAX_TAPE;
                $body
            }
            _ => {
                const $cap: usize = MAX_PROGRAM;
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

    /// The outputs at L states at once, values only (`out[m][l]`: output m of lane l): the
    /// same lane kernels as [`Self::gradient_lanes`]. Lanes run in blocks of [`BLOCK`], or
    /// [`WIDE_BLOCK`] for calls of that many lanes or more (the
    /// last one padded), each lane independent of the others, so every lane gets a one-lane
    /// call's bits. The registers live in a per-thread buffer that is grown once and never
    /// cleared (every register is written before it is read): clearing a register file per
    /// call cost more than the arithmetic.
    #[inline(always)]
    pub fn values_lanes<const L: usize>(&self, x: &[[f64; L]], out: &mut [[f64; L]]) {
        if L >= WIDE_BLOCK {
            WIDE_REGISTERS.with(|cell| self.values_in_blocks(cell, x, out));
        } else {
            REGISTERS.with(|cell| self.values_in_blocks(cell, x, out));
        }
    }

    /// [`Self::values_lanes`] in blocks of W lanes, the registers in `cell` (or, where this
    /// thread's are in use, a buffer of the call's own).
    #[inline(always)]
    fn values_in_blocks<const L: usize, const W: usize>(
        &self,
        cell: &Registers<W>,
        x: &[[f64; L]],
        out: &mut [[f64; L]],
    ) {
        let mut own = Vec::new();
        let mut borrowed = cell.try_borrow_mut();
        let buf: &mut Vec<[f64; W]> = match borrowed.as_mut() {
            Ok(b) => b,
            Err(_) => &mut own,
        };
        let need = self.ops.len();
        if buf.len() < need {
            if buf.try_reserve_exact(need - buf.len()).is_err() {
                crate::memory::panic_out_of_memory(&CoreError::Memory(
                    "the registers of an expression".into(),
                ));
            }
            buf.resize(need, [0.0; W]);
        }
        let mut xb = [[0.0; W]; crate::MAX_DIM];
        let mut ob = [[0.0; W]; crate::MAX_DIM];
        for start in (0..L).step_by(W) {
            let width = W.min(L - start);
            for (xi, row) in xb.iter_mut().zip(x) {
                xi[..width].copy_from_slice(&row[start..start + width]);
            }
            self.values_block(&xb, &mut ob, &mut buf[..need]);
            for (o, row) in out.iter_mut().zip(&ob) {
                o[start..start + width].copy_from_slice(&row[..width]);
            }
        }
    }

    // Inlined into the caller's SIMD kernel (compiled for AVX2 where the CPU has it): on its own
    // it would be compiled for the baseline's two-wide vectors.
    #[inline(always)]
    fn values_block<const W: usize>(
        &self,
        x: &[[f64; W]],
        out: &mut [[f64; W]],
        v: &mut [[f64; W]],
    ) {
        for (k, op) in self.ops.iter().enumerate() {
            let (vd, vr) = v.split_at_mut(k);
            let r = &mut vr[0];
            match *op {
                Op::Var(i) => *r = x[i],
                Op::Const(c) => *r = [c; W],
                Op::Add(a, b) => {
                    let (p, q) = (&vd[a], &vd[b]);
                    for l in 0..W {
                        r[l] = p[l] + q[l];
                    }
                }
                Op::Sub(a, b) => {
                    let (p, q) = (&vd[a], &vd[b]);
                    for l in 0..W {
                        r[l] = p[l] - q[l];
                    }
                }
                Op::Mul(a, b) => {
                    let (p, q) = (&vd[a], &vd[b]);
                    for l in 0..W {
                        r[l] = p[l] * q[l];
                    }
                }
                Op::Div(a, b) => {
                    let (p, q) = (&vd[a], &vd[b]);
                    for l in 0..W {
                        r[l] = p[l] / q[l];
                    }
                }
                Op::Neg(a) => {
                    let p = &vd[a];
                    for l in 0..W {
                        r[l] = -p[l];
                    }
                }
                Op::Powi(a, n) => {
                    let y = &vd[a];
                    let mut p = [1.0; W];
                    for _ in 0..n.unsigned_abs() {
                        for l in 0..W {
                            p[l] *= y[l];
                        }
                    }
                    for l in 0..W {
                        r[l] = if n < 0 { 1.0 / p[l] } else { p[l] };
                    }
                }
                Op::Exp(a) => crate::exp::exp_lanes(&vd[a], r),
                Op::Sin(a) | Op::Cos(a) | Op::Tan(a) => {
                    let (mut f, mut g) = ([0.0; W], [0.0; W]);
                    crate::trig::sin_cos_lanes(&vd[a], &mut f, &mut g);
                    match op {
                        Op::Sin(_) => *r = f,
                        Op::Cos(_) => *r = g,
                        _ => {
                            for l in 0..W {
                                r[l] = f[l] / g[l];
                            }
                        }
                    }
                }
                Op::Sqrt(a) => {
                    let p = &vd[a];
                    for l in 0..W {
                        r[l] = p[l].sqrt();
                    }
                }
                Op::Log(a) => {
                    let p = &vd[a];
                    for l in 0..W {
                        r[l] = p[l].ln();
                    }
                }
                Op::Tanh(a) => {
                    let p = &vd[a];
                    for l in 0..W {
                        r[l] = p[l].tanh();
                    }
                }
                Op::Powf(a, e) => {
                    let p = &vd[a];
                    for l in 0..W {
                        r[l] = p[l].powf(e);
                    }
                }
            }
        }
        for (o, &k) in out.iter_mut().zip(&self.outputs) {
            *o = v[k];
        }
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
            let chain =
                |a: usize, fd: &[[f64; L]; 2], out: &mut [f64; L], dout: &mut [[f64; L]; N]| {
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
                Op::Sqrt(a) => chain(
                    a,
                    &lanewise(&vd[a], |y| {
                        let r = y.sqrt();
                        (r, 0.5 / r)
                    }),
                    out,
                    dout,
                ),
                Op::Log(a) => chain(a, &lanewise(&vd[a], |y| (y.ln(), 1.0 / y)), out, dout),
                Op::Tanh(a) => chain(
                    a,
                    &lanewise(&vd[a], |y| {
                        let t = y.tanh();
                        (t, 1.0 - t * t)
                    }),
                    out,
                    dout,
                ),
                Op::Powf(a, p) => chain(
                    a,
                    &lanewise(&vd[a], |y| {
                        let yp = y.powf(p);
                        (yp, p * yp / y)
                    }),
                    out,
                    dout,
                ),
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

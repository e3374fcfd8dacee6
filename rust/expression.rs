//! A Hamiltonian given as an expression: a straight-line program ("tape") over + − × ÷, integer
//! and real powers, exp, log, sin, cos, tan, sqrt and tanh, compiled in Python from a bounded
//! grammar. The core evaluates it on any [`Scalar`] (f64, [`crate::dual::Dual1`] for ∇H,
//! [`crate::dual::Jet2`] for ∇²H, exactly, by forward mode) and on truncated power series
//! ([`crate::series`]) for Taylor-HJ by jets.

use crate::dual::Scalar;
use crate::error::CoreError;

/// Most instructions of a tape evaluated with derivatives (a Hamiltonian).
pub const MAX_TAPE: usize = 1024;
/// Most registers of a tape live at once. [`Expression::eval`]'s registers live on the stack, one
/// slot per live value (a slot is reused once its value's last reader has run), so a long sum of
/// short terms fits where a wide one would not.
pub const MAX_LIVE: usize = 256;
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
    /// The same program for [`Expression::values_lanes`]: constants carried in the
    /// instructions that use them, single-use products fused ([`Lowered`]).
    lowered: Lowered,
    /// [`Expression::eval`]'s register slot of each instruction ([`slots`]), and how many slots
    /// it needs (the most values live at once).
    slots: Vec<u16>,
    live: usize,
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
        let e = Self::program(vars, code, a, b, c, &[code.len() as i64 - 1])?;
        if e.live > MAX_LIVE {
            return Err(CoreError::Invalid(format!(
                "an expression may keep at most {MAX_LIVE} values live at once, this one keeps {}",
                e.live
            )));
        }
        Ok(e)
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
        let lowered = Lowered::new(vars, &ops, &outs)?;
        let (slots, live) = slots(&ops, &outs)?;
        Ok(Expression {
            vars,
            ops,
            outputs: outs,
            lowered,
            slots,
            live,
        })
    }

    /// The most values live at once in [`Self::eval`] (its register slots).
    pub fn live(&self) -> usize {
        self.live
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
        let mut r = [T::cst(0.0); MAX_LIVE];
        let n = self.ops.len();
        if self.live > MAX_LIVE {
            // Only a multi-output program is this wide, and it is evaluated by values_lanes.
            return T::cst(f64::NAN);
        }
        if n <= MAX_LIVE {
            // Every instruction its own register: no slot lookups on the common short tape.
            for (k, op) in self.ops.iter().enumerate() {
                r[k] = apply(op, x, &r, |j| j);
            }
            r[n - 1]
        } else {
            let slots = &self.slots;
            for (k, op) in self.ops.iter().enumerate() {
                // Computed before it is stored: the slot may be an operand's, freed here.
                let v = apply(op, x, &r, |j| usize::from(slots[j]));
                r[usize::from(slots[k])] = v;
            }
            r[usize::from(slots[n - 1])]
        }
    }
}

/// One instruction's value, its operands read from `r` at the slots `at` gives them.
#[inline(always)]
fn apply<T: Scalar>(op: &Op, x: &[T], r: &[T], at: impl Fn(usize) -> usize) -> T {
    let r = |j: usize| r[at(j)];
    match *op {
        Op::Var(i) => x[i],
        Op::Const(c) => T::cst(c),
        Op::Add(a, b) => r(a) + r(b),
        Op::Sub(a, b) => r(a) - r(b),
        Op::Mul(a, b) => r(a) * r(b),
        Op::Div(a, b) => r(a) * r(b).recip(),
        Op::Neg(a) => -r(a),
        Op::Powi(a, n) => powi(r(a), n),
        Op::Powf(a, p) => {
            let a = r(a);
            let v = a.value();
            let vp = v.powf(p);
            a.chain(vp, p * vp / v, p * (p - 1.0) * vp / (v * v))
        }
        Op::Exp(a) => {
            let a = r(a);
            let e = a.value().exp();
            a.chain(e, e, e)
        }
        Op::Log(a) => {
            let a = r(a);
            let v = a.value();
            a.chain(v.ln(), 1.0 / v, -1.0 / (v * v))
        }
        Op::Sin(a) => {
            let a = r(a);
            let (s, c) = a.value().sin_cos();
            a.chain(s, c, -s)
        }
        Op::Cos(a) => {
            let a = r(a);
            let (s, c) = a.value().sin_cos();
            a.chain(c, -s, -c)
        }
        Op::Tan(a) => {
            let a = r(a);
            let t = a.value().tan();
            let d = 1.0 + t * t;
            a.chain(t, d, 2.0 * t * d)
        }
        Op::Sqrt(a) => r(a).sqrt(),
        Op::Tanh(a) => r(a).tanh(),
    }
}

impl Op {
    /// The instructions this one reads.
    fn operands(&self) -> [Option<usize>; 2] {
        match *self {
            Op::Var(_) | Op::Const(_) => [None, None],
            Op::Add(a, b) | Op::Sub(a, b) | Op::Mul(a, b) | Op::Div(a, b) => [Some(a), Some(b)],
            Op::Neg(a)
            | Op::Powi(a, _)
            | Op::Powf(a, _)
            | Op::Exp(a)
            | Op::Log(a)
            | Op::Sin(a)
            | Op::Cos(a)
            | Op::Tan(a)
            | Op::Sqrt(a)
            | Op::Tanh(a) => [Some(a), None],
        }
    }
}

/// A register slot for each instruction of `ops` (the outputs kept to the end), by a linear scan:
/// a value's slot is freed once its last reader has run, and the next instruction takes the slot
/// freed last. Returns the slots and how many there are (the most values live at once).
fn slots(ops: &[Op], outputs: &[usize]) -> Result<(Vec<u16>, usize), CoreError> {
    let oom = || CoreError::Memory("the register slots of an expression".into());
    let n = ops.len();
    // The last instruction that reads each value (itself where none does; past the end for an
    // output).
    let mut last: Vec<usize> = Vec::new();
    last.try_reserve_exact(n).map_err(|_| oom())?;
    last.extend(0..n);
    for (k, op) in ops.iter().enumerate() {
        for a in op.operands().into_iter().flatten() {
            last[a] = k;
        }
    }
    for &o in outputs {
        last[o] = usize::MAX;
    }
    let mut slot: Vec<u16> = Vec::new();
    slot.try_reserve_exact(n).map_err(|_| oom())?;
    let mut free: Vec<u16> = Vec::new();
    free.try_reserve_exact(n).map_err(|_| oom())?;
    let mut count = 0usize;
    for (k, op) in ops.iter().enumerate() {
        let [a, b] = op.operands();
        for (i, o) in [a, b].into_iter().enumerate() {
            // x·x reads one value twice: its slot is freed once.
            if let Some(o) = o.filter(|&o| last[o] == k && (i == 0 || a != Some(o))) {
                free.push(slot[o]);
            }
        }
        let s = match free.pop() {
            Some(s) => s,
            None => {
                count += 1;
                u16::try_from(count - 1).map_err(|_| {
                    CoreError::Invalid(format!("an expression keeps over {} values live", u16::MAX))
                })?
            }
        };
        slot.push(s);
        if last[k] == k {
            free.push(s); // never read
        }
    }
    Ok((slot, count))
}

/// Lanes of one block of [`Expression::values_lanes`] (the rollouts' SIMD width).
pub const BLOCK: usize = crate::isa::LANES;
/// Lanes of a wide block, for calls of at least that many lanes: each instruction's dispatch
/// (the match, the operand lookups) is paid once for eight times the arithmetic (the rollouts'
/// AVX-512 wide blocks, [`crate::lanes::WIDE512_LANES`]; their AVX2 blocks of 32 run as one
/// block too).
pub const WIDE_BLOCK: usize = 8 * BLOCK;

thread_local! {
    /// The value registers of [`Expression::values_lanes`] on this thread, flat (register r of
    /// a call with L lanes at `[r·L, (r + 1)·L)`): grown once, never cleared.
    static REGISTERS: std::cell::Cell<Vec<f64>> = const { std::cell::Cell::new(Vec::new()) };
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
            129..=256 => {
                const $cap: usize = 256;
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

    /// The outputs at L states at once, values only (`out[m][l]`: output m of lane l), by the
    /// lowered program ([`Lowered`]): the same lane kernels as [`Self::gradient_lanes`]. Up to
    /// [`WIDE_BLOCK`] lanes run as one block of L lanes, straight from `x` into `out`; more run in
    /// blocks of [`WIDE_BLOCK`] (the last one padded). Each lane is independent of the others,
    /// so every lane gets a one-lane call's bits. The registers live in a per-thread buffer that
    /// is grown once and never cleared (every register is written before it is read): clearing
    /// a register file per call cost more than the arithmetic.
    #[inline(always)]
    pub fn values_lanes<const L: usize>(&self, x: &[[f64; L]], out: &mut [[f64; L]]) {
        // The buffer is taken out of the thread-local and put back, rather than used inside
        // `with`'s closure: code in a closure is compiled for the baseline's two-wide vectors
        // unless inlined into the caller's AVX2 kernel, which `with` does not promise (the
        // vortices' field ran 2× slower that way).
        let mut buf = REGISTERS.with(|cell| cell.take());
        let need = self.lowered.registers * L.min(WIDE_BLOCK);
        if buf.len() < need {
            if buf.try_reserve_exact(need - buf.len()).is_err() {
                crate::memory::panic_out_of_memory(&CoreError::Memory(
                    "the registers of an expression".into(),
                ));
            }
            buf.resize(need, 0.0);
        }
        let v = &mut buf[..need];
        if L <= WIDE_BLOCK {
            self.lowered.run(x, out, v);
        } else {
            let mut xb = [[0.0; WIDE_BLOCK]; crate::MAX_DIM];
            let mut ob = [[0.0; WIDE_BLOCK]; crate::MAX_DIM];
            let (xb, ob) = (&mut xb[..x.len()], &mut ob[..out.len()]);
            for start in (0..L).step_by(WIDE_BLOCK) {
                let width = WIDE_BLOCK.min(L - start);
                for (xi, row) in xb.iter_mut().zip(x) {
                    xi[..width].copy_from_slice(&row[start..start + width]);
                }
                self.lowered.run(xb, ob, v);
                for (o, row) in out.iter_mut().zip(ob.iter()) {
                    o[start..start + width].copy_from_slice(&row[..width]);
                }
            }
        }
        REGISTERS.with(|cell| cell.set(buf));
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

/// A value in the lowering: a register, or a constant known when the program is built.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Val {
    Reg(u32),
    Const(f64),
}

/// One instruction of a [`Lowered`] program: `d` the register written, `a`, `b` registers read,
/// `c` a constant carried in the instruction. Each computes what the [`Op`] it comes from
/// computes, with the same IEEE operations (x·c for c·x, c − x, c/x), so the bits are the same.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Instr {
    Splat(u32, f64),
    Add(u32, u32, u32),
    Sub(u32, u32, u32),
    Mul(u32, u32, u32),
    Div(u32, u32, u32),
    AddC(u32, u32, f64),
    SubC(u32, u32, f64),
    CSub(u32, f64, u32),
    MulC(u32, u32, f64),
    DivC(u32, u32, f64),
    CDiv(u32, f64, u32),
    Neg(u32, u32),
    Square(u32, u32),
    Powi(u32, u32, i32),
    Unary(u32, u32, Op),
    /// x + a·b, x − a·b, a·b − x, (a·b)·c and (a·c)·b: a product read once, by this
    /// instruction only, fused into it (the same two roundings, one store fewer).
    AddMul(u32, u32, u32, u32),
    AddMulC(u32, u32, u32, f64),
    SubMul(u32, u32, u32, u32),
    SubMulC(u32, u32, u32, f64),
    MulSub(u32, u32, u32, u32),
    MulMulC(u32, u32, u32, f64),
    MulCMul(u32, u32, f64, u32),
}

/// A product that [`fuse`] may fold into the one instruction that reads it: a·b (a square as
/// a·a, the same bits) or a·c.
#[derive(Clone, Copy)]
enum Product {
    Mul(u32, u32),
    MulC(u32, f64),
}

/// The instructions of `code` with each product (or square) that one addition, subtraction or
/// multiplication alone reads fused into it ([`Instr::AddMul`] …). Sums and products commute
/// exactly in IEEE arithmetic, so x + a·b is a·b + x to the bit; nothing is reassociated.
fn fuse(code: Vec<Instr>, outputs: &[Val], registers: usize) -> Result<Vec<Instr>, CoreError> {
    let oom = || CoreError::Memory("the lowered form of an expression".into());
    // How often each register is read, and the instruction that writes it.
    let mut reads = Vec::new();
    reads.try_reserve_exact(registers).map_err(|_| oom())?;
    reads.resize(registers, 0u32);
    let mut writer = Vec::new();
    writer.try_reserve_exact(registers).map_err(|_| oom())?;
    writer.resize(registers, usize::MAX);
    for (k, ins) in code.iter().enumerate() {
        let (d, operands) = ins.registers();
        writer[d as usize] = k;
        for r in operands.into_iter().flatten() {
            reads[r as usize] += 1;
        }
    }
    for o in outputs {
        if let Val::Reg(r) = *o {
            reads[r as usize] += 1;
        }
    }
    let mut gone = Vec::new();
    gone.try_reserve_exact(code.len()).map_err(|_| oom())?;
    gone.resize(code.len(), false);
    let mut fused = code.clone();
    // The product in register r, where only one instruction reads it and its own operands are
    // still there (a product that absorbed another is no longer a plain product).
    let product = |r: u32, fused: &[Instr]| -> Option<(usize, Product)> {
        let k = *writer.get(r as usize)?;
        if k == usize::MAX || reads[r as usize] != 1 {
            return None;
        }
        match fused[k] {
            Instr::Mul(_, a, b) => Some((k, Product::Mul(a, b))),
            Instr::Square(_, a) => Some((k, Product::Mul(a, a))),
            Instr::MulC(_, a, c) => Some((k, Product::MulC(a, c))),
            _ => None,
        }
    };
    for k in 0..code.len() {
        let f = &fused;
        let new = match code[k] {
            Instr::Add(d, x, y) => match (product(y, f), product(x, f)) {
                (Some((j, p)), _) => Some((j, add_mul(d, x, p, false))),
                (None, Some((j, p))) => Some((j, add_mul(d, y, p, false))),
                _ => None,
            },
            Instr::Sub(d, x, y) => match (product(y, f), product(x, f)) {
                (Some((j, p)), _) => Some((j, add_mul(d, x, p, true))),
                (None, Some((j, Product::Mul(a, b)))) => Some((j, Instr::MulSub(d, a, b, y))),
                _ => None,
            },
            Instr::MulC(d, x, c) => match product(x, f) {
                Some((j, Product::Mul(a, b))) => Some((j, Instr::MulMulC(d, a, b, c))),
                _ => None,
            },
            Instr::Mul(d, x, y) => match (product(x, f), product(y, f)) {
                (Some((j, Product::MulC(a, c))), _) => Some((j, Instr::MulCMul(d, a, c, y))),
                (_, Some((j, Product::MulC(a, c)))) => Some((j, Instr::MulCMul(d, a, c, x))),
                _ => None,
            },
            _ => None,
        };
        if let Some((j, ins)) = new {
            gone[j] = true;
            fused[k] = ins;
        }
    }
    let mut out = Vec::new();
    out.try_reserve_exact(code.len()).map_err(|_| oom())?;
    out.extend(
        fused
            .into_iter()
            .zip(&gone)
            .filter(|(_, g)| !**g)
            .map(|(i, _)| i),
    );
    Ok(out)
}

/// x ± (the product p), written to d.
fn add_mul(d: u32, x: u32, p: Product, minus: bool) -> Instr {
    match (p, minus) {
        (Product::Mul(a, b), false) => Instr::AddMul(d, x, a, b),
        (Product::Mul(a, b), true) => Instr::SubMul(d, x, a, b),
        (Product::MulC(a, c), false) => Instr::AddMulC(d, x, a, c),
        (Product::MulC(a, c), true) => Instr::SubMulC(d, x, a, c),
    }
}

impl Instr {
    /// The register written and those read.
    fn registers(&self) -> (u32, [Option<u32>; 3]) {
        use Instr::*;
        match *self {
            Splat(d, _) => (d, [None; 3]),
            Add(d, a, b) | Sub(d, a, b) | Mul(d, a, b) | Div(d, a, b) => {
                (d, [Some(a), Some(b), None])
            }
            AddC(d, a, _)
            | SubC(d, a, _)
            | CSub(d, _, a)
            | MulC(d, a, _)
            | DivC(d, a, _)
            | CDiv(d, _, a)
            | Neg(d, a)
            | Square(d, a)
            | Powi(d, a, _)
            | Unary(d, a, _) => (d, [Some(a), None, None]),
            AddMul(d, x, a, b) | SubMul(d, x, a, b) | MulSub(d, a, b, x) => {
                (d, [Some(x), Some(a), Some(b)])
            }
            AddMulC(d, x, a, _) | SubMulC(d, x, a, _) | MulCMul(d, a, _, x) => {
                (d, [Some(x), Some(a), None])
            }
            MulMulC(d, a, b, _) => (d, [Some(a), Some(b), None]),
        }
    }
}

/// The program as [`Expression::values_lanes`] runs it. The variables are registers
/// `0..vars`, the caller's lanes copied there once a call; a constant never occupies a
/// register unless an instruction with no constant form needs it (then one [`Instr::Splat`]
/// per constant); every other instruction writes a new register above its operands. On the
/// vortices' field (76 instructions, 8 of them constants and 6 variables) this leaves 62
/// instructions, 23 of them with their constant carried.
#[derive(Clone, Debug, PartialEq)]
struct Lowered {
    vars: usize,
    code: Vec<Instr>,
    outputs: Vec<Val>,
    /// Registers a call needs per lane.
    registers: usize,
}

impl Lowered {
    fn new(vars: usize, ops: &[Op], outputs: &[usize]) -> Result<Self, CoreError> {
        let oom = || CoreError::Memory("the lowered form of an expression".into());
        let mut code = Vec::new();
        code.try_reserve_exact(ops.len()).map_err(|_| oom())?;
        let mut val: Vec<Val> = Vec::new();
        val.try_reserve_exact(ops.len()).map_err(|_| oom())?;
        // The register a constant instruction was splat into, where one needed it.
        let mut splat: Vec<Option<u32>> = Vec::new();
        splat.try_reserve_exact(ops.len()).map_err(|_| oom())?;
        splat.resize(ops.len(), None);
        let mut next = vars as u32;
        let mut fresh = || {
            next += 1;
            next - 1
        };
        for op in ops {
            let mut reg =
                |k: usize, code: &mut Vec<Instr>, fresh: &mut dyn FnMut() -> u32| match val[k] {
                    Val::Reg(r) => r,
                    Val::Const(c) => *splat[k].get_or_insert_with(|| {
                        let d = fresh();
                        code.push(Instr::Splat(d, c));
                        d
                    }),
                };
            let v = match *op {
                Op::Var(i) => Val::Reg(i as u32),
                Op::Const(c) => Val::Const(c),
                Op::Add(a, b) | Op::Sub(a, b) | Op::Mul(a, b) | Op::Div(a, b) => {
                    match (val[a], val[b]) {
                        (Val::Const(p), Val::Const(q)) => Val::Const(match op {
                            Op::Add(..) => p + q,
                            Op::Sub(..) => p - q,
                            Op::Mul(..) => p * q,
                            _ => p / q,
                        }),
                        (Val::Reg(p), Val::Reg(q)) => {
                            let d = fresh();
                            code.push(match op {
                                Op::Add(..) => Instr::Add(d, p, q),
                                Op::Sub(..) => Instr::Sub(d, p, q),
                                Op::Mul(..) => Instr::Mul(d, p, q),
                                _ => Instr::Div(d, p, q),
                            });
                            Val::Reg(d)
                        }
                        (Val::Reg(p), Val::Const(c)) => {
                            let d = fresh();
                            code.push(match op {
                                Op::Add(..) => Instr::AddC(d, p, c),
                                Op::Sub(..) => Instr::SubC(d, p, c),
                                Op::Mul(..) => Instr::MulC(d, p, c),
                                _ => Instr::DivC(d, p, c),
                            });
                            Val::Reg(d)
                        }
                        (Val::Const(c), Val::Reg(q)) => {
                            let d = fresh();
                            // Addition and multiplication commute exactly in IEEE arithmetic.
                            code.push(match op {
                                Op::Add(..) => Instr::AddC(d, q, c),
                                Op::Sub(..) => Instr::CSub(d, c, q),
                                Op::Mul(..) => Instr::MulC(d, q, c),
                                _ => Instr::CDiv(d, c, q),
                            });
                            Val::Reg(d)
                        }
                    }
                }
                Op::Neg(a) => match val[a] {
                    Val::Const(c) => Val::Const(-c),
                    Val::Reg(p) => {
                        let d = fresh();
                        code.push(Instr::Neg(d, p));
                        Val::Reg(d)
                    }
                },
                Op::Powi(a, n) => {
                    let p = reg(a, &mut code, &mut fresh);
                    let d = fresh();
                    // 1·y·y is y·y to the bit.
                    code.push(if n == 2 {
                        Instr::Square(d, p)
                    } else {
                        Instr::Powi(d, p, n)
                    });
                    Val::Reg(d)
                }
                Op::Powf(a, _)
                | Op::Exp(a)
                | Op::Log(a)
                | Op::Sin(a)
                | Op::Cos(a)
                | Op::Tan(a)
                | Op::Sqrt(a)
                | Op::Tanh(a) => {
                    let p = reg(a, &mut code, &mut fresh);
                    let d = fresh();
                    code.push(Instr::Unary(d, p, *op));
                    Val::Reg(d)
                }
            };
            val.push(v);
        }
        let mut outs = Vec::new();
        outs.try_reserve_exact(outputs.len()).map_err(|_| oom())?;
        outs.extend(outputs.iter().map(|&k| val[k]));
        let registers = next as usize;
        let code = fuse(code, &outs, registers)?;
        Ok(Lowered {
            vars,
            code,
            outputs: outs,
            registers,
        })
    }

    /// The outputs at W lanes: `v` holds at least `registers · W` numbers.
    #[inline(always)]
    fn run<const W: usize>(&self, x: &[[f64; W]], out: &mut [[f64; W]], v: &mut [f64]) {
        for (i, row) in x.iter().take(self.vars).enumerate() {
            v[i * W..(i + 1) * W].copy_from_slice(row);
        }
        // The register written and those read: every operand sits below its destination.
        #[inline(always)]
        fn split<const W: usize>(v: &mut [f64], d: u32) -> (&[f64], &mut [f64; W]) {
            let (lo, hi) = v.split_at_mut(d as usize * W);
            let r = hi
                .first_chunk_mut::<W>()
                .expect("a register of the lowered program");
            (lo, r)
        }
        #[inline(always)]
        fn get<const W: usize>(lo: &[f64], a: u32) -> &[f64; W] {
            lo[a as usize * W..]
                .first_chunk::<W>()
                .expect("an operand of the lowered program")
        }
        macro_rules! binary {
            ($d:expr, $a:expr, $b:expr, |$p:ident, $q:ident| $e:expr) => {{
                let (lo, r) = split::<W>(v, $d);
                let (p, q) = (get::<W>(lo, $a), get::<W>(lo, $b));
                for l in 0..W {
                    let ($p, $q) = (p[l], q[l]);
                    r[l] = $e;
                }
            }};
        }
        macro_rules! ternary {
            ($d:expr, $x:expr, $a:expr, $b:expr, |$xv:ident, $p:ident, $q:ident| $e:expr) => {{
                let (lo, r) = split::<W>(v, $d);
                let (xs, p, q) = (get::<W>(lo, $x), get::<W>(lo, $a), get::<W>(lo, $b));
                for l in 0..W {
                    let ($xv, $p, $q) = (xs[l], p[l], q[l]);
                    r[l] = $e;
                }
            }};
        }
        macro_rules! unary {
            ($d:expr, $a:expr, |$p:ident| $e:expr) => {{
                let (lo, r) = split::<W>(v, $d);
                let p = get::<W>(lo, $a);
                for l in 0..W {
                    let $p = p[l];
                    r[l] = $e;
                }
            }};
        }
        for ins in &self.code {
            match *ins {
                Instr::Splat(d, c) => *split::<W>(v, d).1 = [c; W],
                Instr::Add(d, a, b) => binary!(d, a, b, |p, q| p + q),
                Instr::Sub(d, a, b) => binary!(d, a, b, |p, q| p - q),
                Instr::Mul(d, a, b) => binary!(d, a, b, |p, q| p * q),
                Instr::Div(d, a, b) => binary!(d, a, b, |p, q| p / q),
                Instr::AddC(d, a, c) => unary!(d, a, |p| p + c),
                Instr::SubC(d, a, c) => unary!(d, a, |p| p - c),
                Instr::CSub(d, c, a) => unary!(d, a, |p| c - p),
                Instr::MulC(d, a, c) => unary!(d, a, |p| p * c),
                Instr::DivC(d, a, c) => unary!(d, a, |p| p / c),
                Instr::CDiv(d, c, a) => unary!(d, a, |p| c / p),
                Instr::Neg(d, a) => unary!(d, a, |p| -p),
                Instr::Square(d, a) => unary!(d, a, |p| p * p),
                Instr::Powi(d, a, n) => {
                    let (lo, r) = split::<W>(v, d);
                    let y = get::<W>(lo, a);
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
                Instr::Unary(d, a, op) => {
                    let (lo, r) = split::<W>(v, d);
                    unary_lanes(op, get::<W>(lo, a), r);
                }
                Instr::AddMul(d, x, a, b) => ternary!(d, x, a, b, |x, p, q| x + p * q),
                Instr::SubMul(d, x, a, b) => ternary!(d, x, a, b, |x, p, q| x - p * q),
                Instr::MulSub(d, a, b, x) => ternary!(d, x, a, b, |x, p, q| p * q - x),
                Instr::AddMulC(d, x, a, c) => binary!(d, x, a, |x, p| x + p * c),
                Instr::SubMulC(d, x, a, c) => binary!(d, x, a, |x, p| x - p * c),
                Instr::MulCMul(d, a, c, x) => binary!(d, x, a, |x, p| (p * c) * x),
                Instr::MulMulC(d, a, b, c) => binary!(d, a, b, |p, q| (p * q) * c),
            }
        }
        for (o, val) in out.iter_mut().zip(&self.outputs) {
            *o = match *val {
                Val::Reg(k) => *get::<W>(v, k),
                Val::Const(c) => [c; W],
            };
        }
    }
}

/// The elementary functions of an [`Op`] at W lanes (sin, cos and exp through the crate's
/// lane kernels; the others lane by lane).
#[inline(always)]
fn unary_lanes<const W: usize>(op: Op, p: &[f64; W], r: &mut [f64; W]) {
    match op {
        Op::Exp(_) => crate::exp::exp_lanes(p, r),
        Op::Sin(_) | Op::Cos(_) | Op::Tan(_) => {
            let (mut f, mut g) = ([0.0; W], [0.0; W]);
            crate::trig::sin_cos_lanes(p, &mut f, &mut g);
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
        Op::Sqrt(_) => {
            for l in 0..W {
                r[l] = p[l].sqrt();
            }
        }
        Op::Log(_) => {
            for l in 0..W {
                r[l] = p[l].ln();
            }
        }
        Op::Tanh(_) => {
            for l in 0..W {
                r[l] = p[l].tanh();
            }
        }
        Op::Powf(_, e) => {
            for l in 0..W {
                r[l] = p[l].powf(e);
            }
        }
        // Lowered to instructions of their own.
        _ => {}
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

    /// A table of `ops` (the inverse of `from_table`'s decoding, for the ops used here).
    fn table(ops: &[Op]) -> (Vec<i64>, Vec<i64>, Vec<i64>, Vec<f64>) {
        let mut t = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for op in ops {
            let (k, a, b, c) = match *op {
                Op::Var(i) => (0, i as i64, 0, 0.0),
                Op::Const(v) => (1, 0, 0, v),
                Op::Add(p, q) => (2, p as i64, q as i64, 0.0),
                Op::Sub(p, q) => (3, p as i64, q as i64, 0.0),
                Op::Mul(p, q) => (4, p as i64, q as i64, 0.0),
                Op::Powi(p, n) => (7, p as i64, n as i64, 0.0),
                Op::Log(p) => (10, p as i64, 0, 0.0),
                Op::Sqrt(p) => (14, p as i64, 0, 0.0),
                other => unreachable!("{other:?}"),
            };
            t.0.push(k);
            t.1.push(a);
            t.2.push(b);
            t.3.push(c);
        }
        t
    }

    /// A long sum of short terms in 3 variables, more instructions than `MAX_LIVE` (so `eval`
    /// runs on reused slots): its value has the bits of the slot-free oracle, and its gradient
    /// and Hessian by `eval` on jets match the lane path's gradient (which keeps every value)
    /// and central differences of it.
    #[test]
    fn a_tape_longer_than_the_live_registers_evaluates_on_reused_slots() {
        let mut ops = vec![Op::Var(0), Op::Var(1), Op::Var(2)];
        let mut sum = None;
        for k in 0..120 {
            let n = ops.len();
            // (x_i + 1) · log(c_k + x_j²), some minus sqrt(c_k + x_j²), the variables read again.
            ops.push(Op::Const(0.25 + k as f64 / 97.0));
            ops.push(Op::Powi(k % 3, 2));
            ops.push(Op::Add(n, n + 1));
            ops.push(Op::Log(n + 2));
            ops.push(Op::Mul((k + 1) % 3, n + 3));
            // The log read by two instructions in a row, the sum inside it three apart.
            ops.push(Op::Add(n + 4, n + 3));
            let term = if k % 4 == 0 {
                ops.push(Op::Sqrt(n + 2));
                ops.push(Op::Sub(n + 5, n + 6));
                n + 7
            } else {
                n + 5
            };
            sum = Some(match sum {
                None => term,
                Some(s) => {
                    ops.push(Op::Add(s, term));
                    ops.len() - 1
                }
            });
        }
        assert!(ops.len() > MAX_LIVE, "{} instructions", ops.len());
        let (code, a, b, c) = table(&ops);
        let e = Expression::from_table(3, &code, &a, &b, &c).unwrap();
        assert!(e.live() < 12, "{} slots", e.live());
        let x = [0.3, -0.8, 1.4];
        let oracle = interpret(&e, &x)[0];
        assert_eq!(e.eval(&x).to_bits(), oracle.to_bits());
        let jet = e.eval(&[
            Jet2::<3>::var(x[0], 0),
            Jet2::<3>::var(x[1], 1),
            Jet2::<3>::var(x[2], 2),
        ]);
        assert_eq!(jet.v.to_bits(), oracle.to_bits());
        let grad_at = |x: [f64; 3]| {
            let xl: [[f64; 1]; 3] = std::array::from_fn(|i| [x[i]]);
            let (mut v, mut g) = ([0.0; 1], [[0.0; 1]; 3]);
            e.gradient_lanes(&xl, &mut v, &mut g);
            g.map(|r| r[0])
        };
        let g = grad_at(x);
        let hess = jet.hess();
        for i in 0..3 {
            assert!(
                (jet.g[i] - g[i]).abs() <= 1e-12 * g[i].abs().max(1.0),
                "{i}"
            );
            let (mut up, mut down) = (x, x);
            up[i] += 1e-5;
            down[i] -= 1e-5;
            let (gu, gd) = (grad_at(up), grad_at(down));
            for j in 0..3 {
                let fd = (gu[j] - gd[j]) / 2e-5;
                assert!(
                    (hess[j][i] - fd).abs() <= 1e-6 * fd.abs().max(1.0),
                    "{i} {j}"
                );
            }
        }
    }

    /// Values kept live past `MAX_LIVE` are refused with the count; the same values summed as
    /// they are made need two slots.
    #[test]
    fn live_values_are_bounded_not_instructions() {
        let n = MAX_LIVE + 10;
        let mut wide: Vec<Op> = (0..n).map(|k| Op::Const(k as f64)).collect();
        wide.push(Op::Add(0, 1));
        for k in 2..n {
            wide.push(Op::Add(wide.len() - 1, k));
        }
        let (code, a, b, c) = table(&wide);
        let err = Expression::from_table(1, &code, &a, &b, &c).unwrap_err();
        assert!(
            err.to_string().contains(&format!("this one keeps {n}")),
            "{err}"
        );
        let mut narrow = vec![Op::Const(0.0)];
        for k in 1..n {
            narrow.push(Op::Const(k as f64));
            narrow.push(Op::Add(narrow.len() - 2, narrow.len() - 1));
        }
        let (code, a, b, c) = table(&narrow);
        let e = Expression::from_table(1, &code, &a, &b, &c).unwrap();
        assert_eq!(e.live(), 2);
        let want = (n * (n - 1) / 2) as f64;
        assert_eq!(e.eval(&[0.0]), want);
        let long = vec![Op::Const(1.0); MAX_TAPE + 1];
        let (code, a, b, c) = table(&long);
        assert!(Expression::from_table(1, &code, &a, &b, &c).is_err());
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

    /// The unlowered program, one lane, one op after another (x / y as a division): the oracle
    /// for the lowered form.
    fn interpret(e: &Expression, x: &[f64]) -> Vec<f64> {
        let mut r: Vec<f64> = Vec::new();
        for op in e.ops() {
            let v = match *op {
                Op::Var(i) => x[i],
                Op::Const(c) => c,
                Op::Add(a, b) => r[a] + r[b],
                Op::Sub(a, b) => r[a] - r[b],
                Op::Mul(a, b) => r[a] * r[b],
                Op::Div(a, b) => r[a] / r[b],
                Op::Neg(a) => -r[a],
                Op::Powi(a, n) => {
                    let mut p = 1.0;
                    for _ in 0..n.unsigned_abs() {
                        p *= r[a];
                    }
                    if n < 0 {
                        1.0 / p
                    } else {
                        p
                    }
                }
                Op::Sin(a) => crate::trig::sin_cos(r[a]).0,
                Op::Cos(a) => crate::trig::sin_cos(r[a]).1,
                Op::Exp(a) => crate::exp::exp(r[a]),
                Op::Log(a) => r[a].ln(),
                Op::Sqrt(a) => r[a].sqrt(),
                Op::Tanh(a) => r[a].tanh(),
                Op::Powf(a, p) => r[a].powf(p),
                Op::Tan(a) => {
                    let (s, c) = crate::trig::sin_cos(r[a]);
                    s / c
                }
            };
            r.push(v);
        }
        e.outputs.iter().map(|&k| r[k]).collect()
    }

    /// Constants in every position (left and right of each binary operation, under a power,
    /// a sine and a negation, both operands constant, an output that is a constant and one that
    /// is a variable): the lowered program gives the unlowered one's bits in every lane, for
    /// blocks of 1, 8 and 32 lanes and for 40 (two padded blocks); constants take registers only
    /// where an instruction has no constant form.
    #[test]
    fn the_lowered_program_computes_the_program_bit_for_bit() {
        use Op::*;
        let ops = [
            Var(0),       // 0
            Var(1),       // 1
            Const(0.3),   // 2
            Const(-1.7),  // 3
            Add(2, 0),    // 4  c + x
            Sub(2, 1),    // 5  c − y
            Sub(0, 3),    // 6  x − c
            Mul(3, 4),    // 7  c · r
            Div(2, 6),    // 8  c / r
            Div(5, 3),    // 9  r / c
            Mul(2, 3),    // 10 c · c
            Powi(3, 3),   // 11 c³: a splat
            Sin(2),       // 12 sin c: the same splat register
            Neg(3),       // 13 −c
            Add(7, 8),    // 14
            Mul(9, 11),   // 15
            Powi(14, 2),  // 16 a square
            Powi(15, -3), // 17
            Cos(1),       // 18
            Add(16, 12),  // 19
            Sub(17, 18),  // 20
            Mul(19, 13),  // 21
            Add(20, 10),  // 22
            Div(21, 22),  // 23
            Exp(5),       // 24
            Sqrt(24),     // 25
            Mul(0, 1),    // 26
            Sub(26, 25),  // 27 x·y − r: MulSub
            Mul(0, 0),    // 28
            Sub(27, 28),  // 29 r − x·x: SubMul
            Mul(1, 1),    // 30
            Mul(30, 2),   // 31 (y·y)·c: MulMulC
            Mul(3, 0),    // 32 c·x
            Mul(32, 31),  // 33 (x·c)·r: MulCMul
            Mul(1, 0),    // 34 read twice: stays
            Add(34, 34),  // 35
            Add(29, 35),  // 36
            Add(33, 36),  // 37
            Add(7, 9),    // 38 7 read twice (14, 38): stays
            Powi(1, 2),   // 39 y²
            Add(38, 39),  // 40 r + y·y: AddMul
        ];
        let mut code = Vec::new();
        let (mut a, mut b, mut c) = (Vec::new(), Vec::new(), Vec::new());
        for op in ops {
            let (k, x, y, z) = match op {
                Var(i) => (0, i as i64, 0, 0.0),
                Const(v) => (1, 0, 0, v),
                Add(p, q) => (2, p as i64, q as i64, 0.0),
                Sub(p, q) => (3, p as i64, q as i64, 0.0),
                Mul(p, q) => (4, p as i64, q as i64, 0.0),
                Div(p, q) => (5, p as i64, q as i64, 0.0),
                Neg(p) => (6, p as i64, 0, 0.0),
                Powi(p, n) => (7, p as i64, n as i64, 0.0),
                Exp(p) => (9, p as i64, 0, 0.0),
                Sin(p) => (11, p as i64, 0, 0.0),
                Cos(p) => (12, p as i64, 0, 0.0),
                Sqrt(p) => (14, p as i64, 0, 0.0),
                _ => unreachable!(),
            };
            code.push(k);
            a.push(x);
            b.push(y);
            c.push(z);
        }
        let e = Expression::program(2, &code, &a, &b, &c, &[23, 10, 1, 37, 40]).unwrap();
        // Two splats (0.3 under sin, −1.7 under the cube), and no register for 2, 3, 10, 13.
        let splats = e
            .lowered
            .code
            .iter()
            .filter(|i| matches!(i, Instr::Splat(..)))
            .count();
        assert_eq!(splats, 2);
        // The inputs, the splats, and one register for each instruction but the two variables,
        // the two constants and the two folded ones.
        assert_eq!(e.lowered.registers, 2 + splats + ops.len() - 6);
        assert_eq!(e.lowered.outputs[1], Val::Const(0.3 * -1.7));
        // Fused: 19 (16, a square read only there, + sin c), 27, 29, 31, 33, 40 (a square):
        // six. Not: 14 (7 is read twice), 15 (r·r⁻³: a DivC is no product), 21 (an Add's
        // MulC), 36 (35 is an Add), 37 (33 absorbed a product already).
        let fused = e
            .lowered
            .code
            .iter()
            .filter(|i| {
                matches!(
                    i,
                    Instr::AddMul(..)
                        | Instr::AddMulC(..)
                        | Instr::SubMul(..)
                        | Instr::SubMulC(..)
                        | Instr::MulSub(..)
                        | Instr::MulMulC(..)
                        | Instr::MulCMul(..)
                )
            })
            .count();
        assert_eq!(fused, 6);
        fn check<const L: usize>(e: &Expression, seed: u64) {
            let mut s = seed;
            let mut rnd = || {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (s >> 11) as f64 / (1u64 << 53) as f64 * 4.0 - 2.0
            };
            let x: [[f64; L]; 2] = std::array::from_fn(|_| std::array::from_fn(|_| rnd()));
            let mut out = [[0.0; L]; 5];
            e.values_lanes(&x, &mut out);
            for l in 0..L {
                let want = interpret(e, &[x[0][l], x[1][l]]);
                for (m, w) in want.iter().enumerate() {
                    assert_eq!(
                        out[m][l].to_bits(),
                        w.to_bits(),
                        "lane {l} of {L}, output {m}"
                    );
                }
            }
        }
        check::<1>(&e, 1);
        check::<8>(&e, 2);
        check::<32>(&e, 3);
        check::<40>(&e, 4);
        check::<64>(&e, 5);
        // More than a wide block: in blocks of WIDE_BLOCK, the last one padded.
        check::<100>(&e, 6);
    }
}

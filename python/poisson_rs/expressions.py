"""Hamiltonians as expressions: a bounded grammar of its own, never ``eval``.

A string in the system's coordinates (its component names, or x1 … xn) over ``+ - * /``,
integer and real powers (``**`` or ``^``, a number as the exponent), ``exp log sin cos tan sqrt
tanh``, the constant ``pi`` and decimal numbers, e.g. ``"0.5*u**2 - cos(v) + u*(r - u^2 - v^2)"``.
It is parsed by recursive descent into a straight-line program (common subexpressions shared,
constants folded) that the Rust core evaluates exactly with its derivatives, and that NumPy and
torch evaluate here (the torch form gives autograd's ∇H, the core's oracle).

Bounds, each refused with one ValueError naming the field: the text (``MAX_CHARS``), its nesting
(``MAX_DEPTH``), the program (``MAX_INSTRUCTIONS``, the core's tape, of which at most
``MAX_LIVE`` values are live at once), integer exponents (``|n| <= MAX_POWER``) and real ones
(finite, ``|r| <= MAX_POWER``); numbers must be finite.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

#: Longest text.
MAX_CHARS = 16384
#: Deepest nesting of parentheses, functions and operators.
MAX_DEPTH = 64
#: Longest program (the core's ``MAX_TAPE``).
MAX_INSTRUCTIONS = 1024
#: Most values of a program live at once (the core's ``MAX_LIVE``: its registers with
#: derivatives live on the stack, a slot reused once its value's last reader has run). A long
#: sum of short terms keeps a few; see :func:`live_values`.
MAX_LIVE = 256
#: Longest program of a vector field (H's gradient and π; the core's ``MAX_PROGRAM``).
MAX_FIELD_INSTRUCTIONS = 1024
#: Largest |exponent|.
MAX_POWER = 64

#: Opcodes in the order the core numbers them.
OPCODES = (
    "var", "const", "add", "sub", "mul", "div", "neg", "powi", "powf",
    "exp", "log", "sin", "cos", "tan", "sqrt", "tanh",
)  # fmt: skip
FUNCTIONS = ("exp", "log", "sin", "cos", "tan", "sqrt", "tanh")
_TOKEN = re.compile(
    r"\s*(?:(?P<num>(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)|(?P<name>[^\W\d]\w*)"
    r"|(?P<op>\*\*|[-+*/^(),]))"
)

# A node: (opcode, operand registers..., constant) in the program; registers are indices.
Node = tuple[Any, ...]
#: A vector field's program as the core takes it: (code, a, b, c, output registers).
FieldProgram = tuple[
    NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], FloatArray, NDArray[np.int64]
]


class ExpressionError(ValueError):
    """A Hamiltonian text the grammar refuses."""


def _operands(node: Node) -> tuple[int, ...]:
    """The registers ``node`` reads."""
    op = node[0]
    if op in ("var", "const"):
        return ()
    if op in ("powi", "powf") or len(node) == 2:
        return (int(node[1]),)
    return (int(node[1]), int(node[2]))


def _tokens(text: str, field_name: str) -> list[tuple[str, str]]:
    out: list[tuple[str, str]] = []
    pos = 0
    text = text.rstrip()
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        if m is None or m.end() == pos:
            raise ExpressionError(
                f"{field_name}: unexpected character {text[pos:].lstrip()[:1]!r} at position "
                f"{pos} (allowed: numbers, names, + - * / ** ^ ( ) and the functions "
                f"{', '.join(FUNCTIONS)})"
            )
        kind = m.lastgroup or "op"
        out.append((kind, m.group(kind)))
        pos = m.end()
    return out


class _Builder:
    """Hash-consed program: equal subexpressions get one register; constants fold."""

    def __init__(
        self, field_name: str, limit: int = MAX_INSTRUCTIONS, *, reassociate: bool = False
    ) -> None:
        self.nodes: list[Node] = []
        self.index: dict[Node, int] = {}
        self.field = field_name
        self.limit = limit
        # Constant factors moved out of products and quotients and into sums (exact in real
        # arithmetic, not bit for bit): for a field program, where the chain rule scatters
        # constants (2·dx, −2·dx, ½·…, the bracket's entries) through otherwise equal products.
        self.reassociate = reassociate

    def add(self, node: Node) -> int:
        simpler = self._simplify(node)
        if simpler is not None:
            return simpler
        node = self._fold(node)
        if node in self.index:
            return self.index[node]
        if len(self.nodes) >= self.limit:
            raise ExpressionError(
                f"{self.field}: the expression needs more than {self.limit} instructions"
            )
        self.nodes.append(node)
        self.index[node] = len(self.nodes) - 1
        return len(self.nodes) - 1

    def _simplify(self, node: Node) -> int | None:
        """An equivalent register by a cheap rewrite, or None: the identities exact in floating
        point (x + 0, x · 1, x / 1, −(−x), x · 0 for finite x), and the rewrites that let a
        constant factor meet another (c · x with the constant first, c₁ · (c₂ · x), x / c by a
        power of two, −(c · x), x + (−y)), which the differentiated field is full of."""
        op = node[0]
        if op in ("add", "sub", "mul", "div"):
            a, b = node[1], node[2]
            ca, cb = self.const_value(a), self.const_value(b)
            if ca is not None and cb is not None:
                return None  # folded
            if op == "add" and ca == 0.0:
                return int(b)
            if op in ("add", "sub") and cb == 0.0:
                return int(a)
            if op == "sub" and ca == 0.0:
                return self.add(("neg", b))
            if op == "mul" and (ca == 0.0 or cb == 0.0):
                return self.add(("const", 0.0))
            if op == "mul" and cb is not None:
                return self.add(("mul", b, a))
            if op == "mul" and ca is not None:
                if ca == 1.0:
                    return int(b)
                if ca == -1.0:
                    return self.add(("neg", b))
                inner = self.nodes[b]
                if inner[0] == "mul" and self.const_value(inner[1]) is not None:
                    c = ca * float(self.nodes[inner[1]][1])
                    return self.add(("mul", self.add(("const", c)), inner[2]))
                if inner[0] == "neg":
                    return self.add(("mul", self.add(("const", -ca)), inner[1]))
            if op == "div" and cb == 1.0:
                return int(a)
            if op == "div" and cb is not None and cb != 0.0 and math.frexp(cb)[0] == 0.5:
                return self.add(("mul", self.add(("const", 1.0 / cb)), a))
            if self.reassociate and ca is None and cb is None:
                moved = self._move_constants(op, a, b)
                if moved is not None:
                    return moved
            if op in ("add", "sub") and self.nodes[b][0] == "neg":
                return self.add(("sub" if op == "add" else "add", a, self.nodes[b][1]))
            if op == "add" and self.nodes[a][0] == "neg":
                return self.add(("sub", b, self.nodes[a][1]))
        if op == "neg":
            inner = self.nodes[node[1]]
            if inner[0] == "neg":
                return int(inner[1])
            if inner[0] == "mul" and self.const_value(inner[1]) is not None:
                c = -float(self.nodes[inner[1]][1])
                return self.add(("mul", self.add(("const", c)), inner[2]))
        return None

    def _scaled(self, r: int) -> tuple[float, int] | None:
        """(c, y) where register r is c · y or −y (c = −1), else None."""
        node = self.nodes[r]
        if node[0] == "mul" and self.const_value(node[1]) is not None:
            return float(self.nodes[node[1]][1]), int(node[2])
        if node[0] == "neg":
            return -1.0, int(node[1])
        return None

    def _move_constants(self, op: str, a: int, b: int) -> int | None:
        """(c·x)·y → c·(x·y), x·(c·y) → c·(x·y), (c·x)/y → c·(x/y), and c·x ± d·y → c·(x ± y)
        where d = c (c·(x ∓ y) where d = −c): one constant factor per product, met by the
        others, so the products it scales are shared."""
        sa, sb = self._scaled(a), self._scaled(b)
        if op == "mul" and (sa is not None or sb is not None):
            ca, xa = sa if sa is not None else (1.0, a)
            cb, xb = sb if sb is not None else (1.0, b)
            return self.add(("mul", self.add(("const", ca * cb)), self.add(("mul", xa, xb))))
        if op == "div" and sa is not None:
            return self.add(("mul", self.add(("const", sa[0])), self.add(("div", sa[1], b))))
        if op in ("add", "sub") and sa is not None and sb is not None:
            if sa[0] == sb[0]:
                inner = self.add((op, sa[1], sb[1]))
            elif sa[0] == -sb[0]:
                inner = self.add(("sub" if op == "add" else "add", sa[1], sb[1]))
            else:
                return None
            return self.add(("mul", self.add(("const", sa[0])), inner))
        return None

    def const_value(self, r: int) -> float | None:
        node = self.nodes[r]
        return float(node[1]) if node[0] == "const" else None

    def _fold(self, node: Node) -> Node:
        op = node[0]
        if op in ("var", "const"):
            return node
        args = [self.const_value(r) for r in _operands(node)]
        if any(a is None for a in args):
            return node
        vals = [float(a) for a in args if a is not None]
        try:
            with np.errstate(all="raise"):
                value = _apply_float(node, vals)
        except (FloatingPointError, ValueError, ZeroDivisionError, OverflowError):
            raise ExpressionError(
                f"{self.field}: a constant part ({op}) is undefined or overflows"
            ) from None
        if not math.isfinite(value):
            raise ExpressionError(f"{self.field}: a constant part ({op}) is not finite")
        return ("const", value)


def _apply_float(node: Node, v: list[float]) -> float:
    op = node[0]
    if op == "add":
        return v[0] + v[1]
    if op == "sub":
        return v[0] - v[1]
    if op == "mul":
        return v[0] * v[1]
    if op == "div":
        return v[0] / v[1]
    if op == "neg":
        return -v[0]
    if op == "powi":
        return float(v[0] ** int(node[2]))
    if op == "powf":
        if v[0] < 0:
            raise ValueError("negative base")
        return float(v[0] ** float(node[2]))
    f = {"exp": math.exp, "log": math.log, "sin": math.sin, "cos": math.cos,
         "tan": math.tan, "sqrt": math.sqrt, "tanh": math.tanh}[op]  # fmt: skip
    return float(f(v[0]))


class _Parser:
    def __init__(self, tokens: list[tuple[str, str]], names: dict[str, int], field_name: str):
        self.tokens, self.pos, self.field = tokens, 0, field_name
        self.names = names
        self.b = _Builder(field_name)
        self.depth = 0

    def error(self, what: str) -> ExpressionError:
        return ExpressionError(f"{self.field}: {what}")

    def peek(self) -> tuple[str, str] | None:
        return self.tokens[self.pos] if self.pos < len(self.tokens) else None

    def take(self, value: str) -> bool:
        t = self.peek()
        if t is not None and t[0] == "op" and t[1] == value:
            self.pos += 1
            return True
        return False

    def enter(self) -> None:
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise self.error(f"the expression nests deeper than {MAX_DEPTH}")

    def parse(self) -> int:
        if not self.tokens:
            raise self.error("the expression is empty")
        r = self.expr()
        rest = self.peek()
        if rest is not None:
            raise self.error(f"unexpected {rest[1]!r} after a complete expression")
        return r

    def expr(self) -> int:
        self.enter()
        r = self.term()
        while True:
            if self.take("+"):
                r = self.b.add(("add", r, self.term()))
            elif self.take("-"):
                r = self.b.add(("sub", r, self.term()))
            else:
                break
        self.depth -= 1
        return r

    def term(self) -> int:
        self.enter()
        r = self.unary()
        while True:
            if self.take("*"):
                r = self.b.add(("mul", r, self.unary()))
            elif self.take("/"):
                r = self.b.add(("div", r, self.unary()))
            else:
                break
        self.depth -= 1
        return r

    def unary(self) -> int:
        self.enter()
        if self.take("-"):
            r = self.b.add(("neg", self.unary()))
        elif self.take("+"):
            r = self.unary()
        else:
            r = self.power()
        self.depth -= 1
        return r

    def exponent(self) -> float:
        """The exponent after ** or ^: a signed number (or a parenthesised one)."""
        sign = 1.0
        while True:
            if self.take("-"):
                sign = -sign
            elif not self.take("+"):
                break
        t = self.peek()
        if t is not None and t[0] == "num":
            self.pos += 1
            return sign * float(t[1])
        if self.take("("):
            v = self.exponent()
            if not self.take(")"):
                raise self.error("missing ')' in an exponent")
            return sign * v
        raise self.error("an exponent must be a number (write exp(y*log(x)) for x**y)")

    def power(self) -> int:
        self.enter()
        base = self.atom()
        if self.take("**") or self.take("^"):
            e = self.exponent()
            if not math.isfinite(e) or abs(e) > MAX_POWER:
                raise self.error(f"exponent {e} is outside [-{MAX_POWER}, {MAX_POWER}]")
            if e == int(e):
                n = int(e)
                if n == 1:
                    r = base
                elif n == 0:
                    r = self.b.add(("const", 1.0))
                else:
                    r = self.b.add(("powi", base, n))
            elif e == 0.5:
                r = self.b.add(("sqrt", base))
            else:
                r = self.b.add(("powf", base, e))
        else:
            r = base
        self.depth -= 1
        return r

    def atom(self) -> int:
        t = self.peek()
        if t is None:
            raise self.error("the expression ends too early")
        kind, value = t
        self.pos += 1
        if kind == "num":
            v = float(value)
            if not math.isfinite(v):
                raise self.error(f"number {value!r} is not finite")
            return self.b.add(("const", v))
        if kind == "name":
            if value in FUNCTIONS:
                if not self.take("("):
                    raise self.error(f"{value} needs an argument in parentheses")
                r = self.expr()
                if not self.take(")"):
                    raise self.error(f"missing ')' after the argument of {value}")
                return self.b.add((value, r))
            if value in self.names:
                return self.b.add(("var", self.names[value]))
            if value == "pi":
                return self.b.add(("const", math.pi))
            raise self.error(
                f"unknown name {value!r}; the coordinates are {', '.join(self.names)} and the "
                f"functions {', '.join(FUNCTIONS)}"
            )
        if value == "(":
            r = self.expr()
            if not self.take(")"):
                raise self.error("missing ')'")
            return r
        raise self.error(f"unexpected {value!r}")


@dataclass(frozen=True)
class Expression:
    """A Hamiltonian expression in the coordinates ``names`` (parsed at construction).

    ``program``: the straight-line program; its value is the last instruction's.
    """

    text: str
    names: tuple[str, ...]
    #: Other names of the same coordinates (x1 … xn), where they do not clash with ``names``.
    aliases: tuple[str, ...] = ()
    program: tuple[Node, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "names", tuple(self.names))
        object.__setattr__(self, "aliases", tuple(self.aliases))
        program = parse_program(self.text, self.names, aliases=self.aliases)
        object.__setattr__(self, "program", program)

    @property
    def dim(self) -> int:
        return len(self.names)

    def uses(self) -> tuple[int, ...]:
        """The coordinates H depends on (by the program's variables)."""
        return tuple(sorted({int(n[1]) for n in self.program if n[0] == "var"}))

    def tape(self) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], FloatArray]:
        """The core's table: opcode, first and second operand (a variable's index for "var", an
        integer exponent for "powi"), constant ("const", the exponent of "powf")."""
        return _table(self.program)

    def evaluate(self, x: Any, lib: Any = np) -> Any:
        """H at ``x`` (..., n) with ``lib`` NumPy or torch (differentiable with torch)."""
        regs: list[Any] = []
        for node in self.program:
            op = node[0]
            if op == "var":
                v = x[..., node[1]]
            elif op == "const":
                v = node[1]
            elif op == "add":
                v = regs[node[1]] + regs[node[2]]
            elif op == "sub":
                v = regs[node[1]] - regs[node[2]]
            elif op == "mul":
                v = regs[node[1]] * regs[node[2]]
            elif op == "div":
                v = regs[node[1]] / regs[node[2]]
            elif op == "neg":
                v = -regs[node[1]]
            elif op == "powi":
                v = regs[node[1]] ** int(node[2])
            elif op == "powf":
                v = regs[node[1]] ** float(node[2])
            else:
                v = getattr(lib, op)(regs[node[1]])
            regs.append(v)
        out = regs[-1]
        if not hasattr(out, "shape") or out.shape != x.shape[:-1]:
            out = out + 0.0 * x[..., 0]
        return out

    def __call__(self, x: ArrayLike) -> Any:
        return self.evaluate(np.asarray(x, dtype=np.float64))

    def __str__(self) -> str:
        return self.text

    def __reduce__(self) -> tuple[Any, ...]:
        return (Expression, (self.text, self.names, self.aliases))


def parse_program(
    text: Any,
    names: Sequence[str],
    field_name: str = "hamiltonian",
    aliases: Sequence[str] = (),
) -> tuple[Node, ...]:
    """The program of ``text`` in the coordinates ``names``; ExpressionError (a ValueError)
    naming ``field_name`` for anything outside the grammar or its bounds."""
    if not isinstance(text, str):
        raise ExpressionError(f"{field_name} must be a string, got {type(text).__name__}")
    if len(text) > MAX_CHARS:
        raise ExpressionError(f"{field_name} is longer than {MAX_CHARS} characters")
    table = {n: i for i, n in enumerate(names)}
    for i, n in enumerate(aliases):
        table.setdefault(n, i)
    # A component name the grammar cannot spell (or a function's) is left out: x1 … xn remain.
    table = {
        n: i
        for n, i in table.items()
        if n not in FUNCTIONS and n != "pi" and re.fullmatch(r"[^\W\d]\w*", n)
    }
    p = _Parser(_tokens(text, field_name), table, field_name)
    root = p.parse()
    program = _compact(p.b.nodes, root)
    live = live_values(program)
    if live > MAX_LIVE:
        raise ExpressionError(
            f"{field_name}: the expression keeps {live} values live at once, more than "
            f"{MAX_LIVE} (write repeated subexpressions once, or sum terms as they are made)"
        )
    return program


def live_values(program: Sequence[Node]) -> int:
    """The most values of ``program`` live at once as the core evaluates it with derivatives
    (its last instruction the output): a linear scan in which a value's slot is freed once its
    last reader has run and the next instruction takes the slot freed last (the core's slot
    assignment, counted the same way)."""
    n = len(program)
    last = list(range(n))
    for k, node in enumerate(program):
        for a in _operands(node):
            last[a] = k
    if n:
        last[n - 1] = n  # the output: kept to the end
    slot = [0] * n
    free: list[int] = []
    count = 0
    for k, node in enumerate(program):
        ops = _operands(node)
        for i, o in enumerate(ops):
            if last[o] == k and (i == 0 or o != ops[0]):
                free.append(slot[o])
        if free:
            slot[k] = free.pop()
        else:
            slot[k] = count
            count += 1
        if last[k] == k:
            free.append(slot[k])
    return count


def _compact(nodes: list[Node], root: int) -> tuple[Node, ...]:
    """The nodes ``root`` reaches, renumbered in order, ``root`` last (folding leaves dead
    constants behind)."""
    return _compact_roots(nodes, [root])[0]


def _compact_roots(nodes: list[Node], roots: Sequence[int]) -> tuple[tuple[Node, ...], list[int]]:
    """The nodes the ``roots`` reach, renumbered in order, and the roots' new registers."""
    top = max(roots)
    live = [False] * len(nodes)
    for r in roots:
        live[r] = True
    root = top
    for k in range(root, -1, -1):
        if live[k]:
            for r in _operands(nodes[k]):
                live[r] = True
    new: dict[int, int] = {}
    out: list[Node] = []
    for k in range(root + 1):
        if not live[k]:
            continue
        node = nodes[k]
        op = node[0]
        if op in ("var", "const"):
            renamed = node
        elif op in ("powi", "powf"):
            renamed = (op, new[node[1]], node[2])
        else:
            renamed = (op, *(new[r] for r in node[1:]))
        new[k] = len(out)
        out.append(renamed)
    return tuple(out), [new[r] for r in roots]


def substitute(
    text: str,
    names: Sequence[str],
    replacements: Sequence[str | None],
    *,
    aliases: Sequence[str] = (),
    field_name: str = "hamiltonian",
) -> str:
    """``text`` (an expression in ``names`` or ``aliases``) with coordinate k replaced by the
    expression ``replacements[k]``, parenthesised (None: by its own name ``names[k]``), e.g.
    H(x, v) ↦ H(x, p − A(x)). The text is parsed first: ExpressionError naming
    ``field_name`` for one outside the grammar."""
    parse_program(text, names, field_name, aliases=aliases)
    table = {n: i for i, n in enumerate(names)}
    for i, n in enumerate(aliases):
        table.setdefault(n, i)
    out = []
    for kind, value in _tokens(text, field_name):
        k = table.get(value) if kind == "name" and value not in FUNCTIONS else None
        if k is None:
            out.append(value)
        else:
            r = replacements[k]
            out.append(names[k] if r is None else f"({r})")
    return " ".join(out)


def default_names(dim: int) -> tuple[str, ...]:
    """x1 … xn."""
    return tuple(f"x{i + 1}" for i in range(dim))


def _derivatives(
    b: _Builder, program: Sequence[Node], dim: int
) -> tuple[list[int], list[list[int | None]]]:
    """``program`` copied into ``b`` and, per variable, the register of ∂H/∂x_i (None: zero),
    by forward differentiation node by node."""
    reg: list[int] = []
    der: list[list[int | None]] = []

    def mul(x: int | None, y: int | None) -> int | None:
        return None if x is None or y is None else b.add(("mul", x, y))

    def const(v: float) -> int:
        return b.add(("const", float(v)))

    for node in program:
        op = node[0]
        if op == "var":
            r = b.add(node)
            d: list[int | None] = [const(1.0) if i == node[1] else None for i in range(dim)]
        elif op == "const":
            r = b.add(node)
            d = [None] * dim
        elif op in ("add", "sub"):
            x, y = reg[node[1]], reg[node[2]]
            r = b.add((op, x, y))
            d = []
            for dx, dy in zip(der[node[1]], der[node[2]], strict=True):
                if dy is None:
                    d.append(dx)
                elif dx is None:
                    d.append(dy if op == "add" else b.add(("neg", dy)))
                else:
                    d.append(b.add((op, dx, dy)))
        elif op == "neg":
            r = b.add(("neg", reg[node[1]]))
            d = [None if v is None else b.add(("neg", v)) for v in der[node[1]]]
        elif op == "mul":
            x, y = reg[node[1]], reg[node[2]]
            r = b.add(("mul", x, y))
            d = []
            for dx, dy in zip(der[node[1]], der[node[2]], strict=True):
                terms = [t for t in (mul(dx, y), mul(x, dy)) if t is not None]
                d.append(
                    None if not terms else terms[0] if len(terms) == 1 else b.add(("add", *terms))
                )
        elif op == "div":
            x, y = reg[node[1]], reg[node[2]]
            r = b.add(("div", x, y))
            d = []
            for dx, dy in zip(der[node[1]], der[node[2]], strict=True):
                # (dx − (x/y) dy) / y
                if dx is None and dy is None:
                    d.append(None)
                    continue
                top = (
                    dx
                    if dy is None
                    else b.add(("sub", dx if dx is not None else const(0.0), b.add(("mul", r, dy))))
                )
                d.append(b.add(("div", top, y)))
        else:
            x = reg[node[1]]
            if op == "powi":
                n = int(node[2])
                r = b.add(("powi", x, n))
                lower = x if n - 1 == 1 else const(1.0) if n - 1 == 0 else b.add(("powi", x, n - 1))
                factor = b.add(("mul", const(n), lower))
            elif op == "powf":
                p = float(node[2])
                r = b.add(("powf", x, p))
                factor = b.add(("mul", const(p), b.add(("powf", x, p - 1.0))))
            elif op == "exp":
                r = b.add(("exp", x))
                factor = r
            elif op == "log":
                r = b.add(("log", x))
                factor = b.add(("div", const(1.0), x))
            elif op == "sin":
                r = b.add(("sin", x))
                factor = b.add(("cos", x))
            elif op == "cos":
                r = b.add(("cos", x))
                factor = b.add(("neg", b.add(("sin", x))))
            elif op == "tan":
                r = b.add(("tan", x))
                factor = b.add(("add", const(1.0), b.add(("mul", r, r))))
            elif op == "sqrt":
                r = b.add(("sqrt", x))
                factor = b.add(("div", const(0.5), r))
            else:  # tanh
                r = b.add(("tanh", x))
                factor = b.add(("sub", const(1.0), b.add(("mul", r, r))))
            d = [mul(factor, v) for v in der[node[1]]]
        reg.append(r)
        der.append(d)
    return reg, der


def field_program(
    expression: Expression,
    index: NDArray[np.int64],
    coeffs: FloatArray,
    exponents: NDArray[np.int64],
    entries: Mapping[tuple[int, int], Sequence[Node]] | None = None,
) -> FieldProgram:
    """The program of ẋ = π(x)∇H(x), one output per coordinate: ∇H by forward differentiation
    of H's program (shared subexpressions, exact identities folded), π from its upper-triangle
    term table (index, coeffs, exponents (M, n)) plus ``entries``, programs in the same
    coordinates added to π_ij (i < j) for a bracket that is not polynomial. Returns the core's
    table and the outputs' registers. ExpressionError when it exceeds the core's program
    size."""
    n = expression.dim
    # Dead intermediate nodes are dropped at the end: build with room for them.
    b = _Builder("hamiltonian", limit=4 * MAX_FIELD_INSTRUCTIONS, reassociate=True)
    _, der = _derivatives(b, expression.program, n)
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    entry: dict[tuple[int, int], int] = {}
    for (i, j), program in (entries or {}).items():
        reg: list[int] = []
        for node in program:
            op = node[0]
            if op in ("var", "const"):
                reg.append(b.add(node))
            elif op in ("powi", "powf"):
                reg.append(b.add((op, reg[node[1]], node[2])))
            else:
                reg.append(b.add((op, *(reg[k] for k in node[1:]))))
        entry[(i, j)] = reg[-1] if (i, j) not in entry else b.add(("add", entry[(i, j)], reg[-1]))
    for m, c, e in zip(index.tolist(), coeffs.tolist(), exponents.tolist(), strict=True):
        term = b.add(("const", float(c)))
        for v, ev in enumerate(e):
            if ev:
                x = b.add(("var", v))
                term = b.add(("mul", term, x if ev == 1 else b.add(("powi", x, int(ev)))))
        i, j = pairs[int(m)]
        entry[(i, j)] = term if (i, j) not in entry else b.add(("add", entry[(i, j)], term))
    out: list[int] = []
    for i in range(n):
        acc: int | None = None
        for j in range(n):
            if i == j or der[-1][j] is None:
                continue
            p = entry.get((min(i, j), max(i, j)))
            if p is None:
                continue
            t = b.add(("mul", p, der[-1][j]))
            if acc is None:
                acc = t if i < j else b.add(("neg", t))
            else:
                acc = b.add(("add" if i < j else "sub", acc, t))
        out.append(acc if acc is not None else b.add(("const", 0.0)))
    nodes, outputs = _compact_roots(b.nodes, out)
    if len(nodes) > MAX_FIELD_INSTRUCTIONS:
        raise ExpressionError(
            f"hamiltonian: its vector field needs {len(nodes)} instructions, more than "
            f"{MAX_FIELD_INSTRUCTIONS}"
        )
    code, a, bb, c = _table(nodes)
    return code, a, bb, c, np.array(outputs, dtype=np.int64)


def _table(
    program: Sequence[Node],
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], FloatArray]:
    n = len(program)
    code, a, b = (np.zeros(n, dtype=np.int64) for _ in range(3))
    c = np.zeros(n, dtype=np.float64)
    for k, node in enumerate(program):
        op = node[0]
        code[k] = OPCODES.index(op)
        if op == "var":
            a[k] = node[1]
        elif op == "const":
            c[k] = node[1]
        elif op == "powi":
            a[k], b[k] = node[1], node[2]
        elif op == "powf":
            a[k], c[k] = node[1], node[2]
        else:
            a[k] = node[1]
            if len(node) > 2:
                b[k] = node[2]
    return code, a, b, c


def evaluate_table(
    table: tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], FloatArray],
    outputs: Sequence[int] | NDArray[np.int64],
    x: Any,
    lib: Any = np,
) -> Any:
    """The core's program table (code, a, b, c; as :func:`field_program` returns it) evaluated
    at ``x`` (..., n) with ``lib`` NumPy or torch, registers ``outputs`` stacked last:
    (..., len(outputs)). Straight-line array code (no autograd), the torch form of the core's
    field for the device rollouts."""
    code, a, b, c = (np.asarray(v).tolist() for v in table)
    regs: list[Any] = []
    for op, ra, rb, rc in zip(code, a, b, c, strict=True):
        name = OPCODES[op]
        if name == "var":
            v = x[..., ra]
        elif name == "const":
            v = float(rc)
        elif name == "add":
            v = regs[ra] + regs[rb]
        elif name == "sub":
            v = regs[ra] - regs[rb]
        elif name == "mul":
            v = regs[ra] * regs[rb]
        elif name == "div":
            v = regs[ra] / regs[rb]
        elif name == "neg":
            v = -regs[ra]
        elif name == "powi":
            v = regs[ra] ** int(rb)
        elif name == "powf":
            v = regs[ra] ** float(rc)
        else:
            v = getattr(lib, name)(regs[ra])
        regs.append(v)
    zero = 0.0 * x[..., 0]
    # A constant output (a coordinate the field leaves fixed) is broadcast to the batch.
    return lib.stack([regs[k] + zero for k in np.asarray(outputs).tolist()], -1)

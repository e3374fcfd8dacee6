"""Any polynomial Poisson bivector π(x) on R^n, checked on construction, with approximate
symplectic realizations of any order up to :data:`MAX_REALIZATION_ORDER` and a Taylor-HJ
integrator on them (stepped by the Rust core; NumPy Newton as its oracle).

- Antisymmetry is checked symbolically and the Jacobi identity
  π^{il}∂_lπ^{jk} + π^{jl}∂_lπ^{ki} + π^{kl}∂_lπ^{ij} = 0 at seeded random points: a bracket
  that fails is refused with an error naming the failing triple (i, j, k).
- The order-n realization (canonical {x^i, p_j} = δ^i_j, convention ẋ = π∇H):
  β = x + β_1 + … + β_n, β_k of degree k in p, solved order by order from the realization
  condition with the homotopy formula of the Poincaré lemma (:meth:`PolynomialBivector.
  realization_terms`); β_1 = −½π p, β_2 = (1/12)π^{lm}∂_lπ^{ij}p_m p_j; α(x, p) = β(x, −p).
  {β^i, β^j} − π^{ij}(β), {α^i, α^j} + π^{ij}(α) and {α^i, β^j} are then O(|p|^n), and a
  Casimir C has C(β) − C(α) = O(|p|^{n+1}) (n even) or O(|p|^{n+2}) (n odd: the defect is odd
  in p).
- The Taylor-HJ series S = Σ_{k≤m} t^k S_k of ∂S/∂t + H(β(x, ∇S)) = 0 is derived with sympy
  (:func:`hj_series`, truncated power series in t); a step solves α(x, ∇S(h, x)) = x_k by
  Newton and returns β(x, ∇S(h, x)). The scheme is symmetric: measured global order
  min(n, m) rounded up to even (m = 3 on n = 3: 4; m = 5 on n = 5: 6; any m on n = 2: 2).
- Nambu structures on R³, {f, g} = ∇C·(∇f × ∇g), i.e. π^{ij} = ε_ijk ∂_k C, satisfy Jacobi for
  any C and keep C: :meth:`PolynomialBivector.nambu`.
- Bounded work: every polynomial (an entry, H, a Casimir; text from a scene or a model file) is
  walked before sympy sees it, and refused, naming the field, past degree ``MAX_DEGREE``,
  :data:`MAX_TERMS` terms, :data:`MAX_EXPANSION_WORK` products or |coefficient|
  :data:`MAX_COEFFICIENT`; each step of the realization and of the Taylor-HJ series is
  estimated from the terms already built and refused past :data:`MAX_STEP_WORK`.
- A bracket that is in fact Lie–Poisson, affine or log-canonical is recognised
  (:mod:`poisson_rs.structures.recognition`): :meth:`PolynomialPoissonSystem.exact_system`.
"""

from __future__ import annotations

import ast
import itertools
import json
import math
import numbers
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from ..protocols import BracketTerms, JetRealization, PoissonSystemBase, provided
from ..taylor import MAX_WORK
from .lie_poisson import MAX_DEGREE

FloatArray = NDArray[np.float64]
#: Highest order of the approximate realization built here (the recursion has no limit; sympy's
#: cost does: order 5 takes about 5 s on a cubic Nambu bracket, order 6 about 8 s).
MAX_REALIZATION_ORDER = 6
#: Highest Taylor-HJ order built on a realization (sympy's series cost).
MAX_TAYLOR_ORDER = 5

_REALIZATION_TERMS: dict[tuple[int, tuple[str, ...]], list[list[Any]]] = {}
_HJ_SERIES: dict[tuple[Any, ...], list[Any]] = {}


def _symbols(n: int) -> tuple[Any, ...]:
    import sympy

    return tuple(sympy.symbols(f"x1:{n + 1}", real=True))


def _lambdify(args: Sequence[Any], exprs: Sequence[Any]) -> Callable[..., FloatArray]:
    """A vectorised f(*columns) → (B, len(exprs)) from sympy expressions (constants broadcast)."""
    import sympy

    funcs = [sympy.lambdify(args, e, "numpy") for e in exprs]

    def f(*cols: FloatArray) -> FloatArray:
        shape = np.shape(cols[0])
        return np.stack([np.broadcast_to(g(*cols), shape).astype(np.float64) for g in funcs], -1)

    return f


# --- bounded parsing -----------------------------------------------------------------------------
#
# sympy expands whatever it is given, without a bound: `9**9**9**9` never finishes and
# `(x1+x2+x3)**3000` fills memory. Every polynomial (an entry of π, H, a Nambu Casimir) is
# first walked here, without sympy, and its degree, its expanded size and the work of expanding
# it are bounded from above before sympy sees it.

#: Most terms a polynomial may expand to (an upper estimate: a + b for a sum, a·b for a
#: product, capped by the number of monomials of its degree). sympy spends about a millisecond
#: per term of a 10-variable polynomial; a learned H of degree 4 on R¹⁰ has 1001.
MAX_TERMS = 2_000
#: Most monomial products an expansion may cost (the same ceiling of a few seconds as
#: :data:`~poisson_rs.taylor.MAX_WORK`, at sympy's ~100 µs per product instead of ~0.5 µs for
#: exact fractions).
MAX_EXPANSION_WORK = MAX_WORK // 400
#: Largest |coefficient|: a product of two (π·∂π in the Jacobi check, π·∇H in the field)
#: stays finite in float64 (1e150² = 1e300 < 1.8e308).
MAX_COEFFICIENT = 1e150
#: Longest polynomial text accepted (the model-file loader's bound).
MAX_TEXT = 100_000
#: Largest |exponent| of a constant base (the value itself is bounded by float64 below).
_MAX_CONSTANT_EXPONENT = 1024


#: The classical integrators of a polynomial-bivector system: (order, Poisson map).
VECTOR_FIELD_METHODS: dict[str, tuple[int, bool]] = {
    "rk4": (4, False),
    "midpoint": (2, False),
    "dop853": (8, False),
}


class _Size:
    """Upper estimates for one subexpression: total degree, expanded terms, and its value when
    it is a constant (no variable)."""

    __slots__ = ("degree", "terms", "value")

    def __init__(self, degree: int, terms: int, value: float | None) -> None:
        self.degree, self.terms, self.value = degree, terms, value


class _Budget:
    """Counts the estimated expansion work of one polynomial; ValueError naming ``field``."""

    def __init__(self, field: str, n: int) -> None:
        self.field, self.n, self.work = field, n, 0

    def fail(self, why: str) -> ValueError:
        return ValueError(f"{self.field}: {why}")

    def cap(self, degree: int) -> int:
        if degree > MAX_DEGREE:
            raise self.fail(f"degree {degree} (or more) exceeds the largest allowed, {MAX_DEGREE}")
        return math.comb(degree + self.n, self.n)

    def terms(self, count: int, degree: int) -> int:
        count = min(count, self.cap(degree))
        if count > MAX_TERMS:
            raise self.fail(
                f"expands to about {count} terms, more than the {MAX_TERMS} allowed; "
                "give fewer or lower-degree terms"
            )
        return count

    def charge(self, products: int) -> None:
        self.work += products
        if self.work > MAX_EXPANSION_WORK:
            raise self.fail(
                f"expanding it costs more than {MAX_EXPANSION_WORK} monomial products; "
                "give it expanded, or with fewer terms"
            )

    def constant(self, value: Any) -> float:
        try:
            v = float(value)
        except (OverflowError, TypeError, ValueError, ZeroDivisionError):
            raise self.fail(f"the constant {str(value)[:40]} is not a finite real number") from None
        if not math.isfinite(v) or abs(v) > MAX_COEFFICIENT:
            raise self.fail(f"the constant {v:.3g} is not finite or exceeds {MAX_COEFFICIENT:.0e}")
        return v

    def add(self, a: _Size, b: _Size, sign: float) -> _Size:
        value = None
        if a.value is not None and b.value is not None:
            value = self.constant(a.value + sign * b.value)
        degree = max(a.degree, b.degree)
        return _Size(degree, self.terms(a.terms + b.terms, degree), value)

    def mul(self, a: _Size, b: _Size) -> _Size:
        value = None
        if a.value is not None and b.value is not None:
            value = self.constant(a.value * b.value)
        degree = a.degree + b.degree
        self.cap(degree)
        self.charge(a.terms * b.terms)
        return _Size(degree, self.terms(a.terms * b.terms, degree), value)

    def div(self, a: _Size, b: _Size) -> _Size:
        if b.value is None:
            raise self.fail("is not a polynomial: only division by a constant is allowed")
        if b.value == 0.0:
            raise self.fail("divides by zero")
        value = None if a.value is None else self.constant(a.value / b.value)
        return _Size(a.degree, a.terms, value)

    def pow(self, a: _Size, e: _Size) -> _Size:
        if e.value is None or not float(e.value).is_integer():
            raise self.fail("is not a polynomial: exponents must be integer constants")
        k = int(e.value)
        if a.value is not None:
            if abs(k) > _MAX_CONSTANT_EXPONENT:
                raise self.fail(f"the exponent {k} of a constant exceeds {_MAX_CONSTANT_EXPONENT}")
            if a.value == 0.0 and k < 0:
                raise self.fail("divides by zero (0 to a negative power)")
            try:
                value = self.constant(a.value**k)
            except OverflowError:
                raise self.fail(f"the constant {a.value:.3g}**{k} overflows") from None
            return _Size(0, 1, value)
        if not 0 <= k <= MAX_DEGREE:
            raise self.fail(
                f"is not a polynomial of degree <= {MAX_DEGREE}: the exponent {k} of a variable "
                f"must lie in 0..={MAX_DEGREE}"
            )
        if k == 0:
            return _Size(0, 1, 1.0)
        degree = a.degree * k
        self.cap(degree)
        # Repeated multiplication: the k-th power of a t-term sum has at most C(t + k − 1, k)
        # terms (monomials of degree k in t symbols).
        terms = a.terms
        for j in range(2, k + 1):
            self.charge(terms * a.terms)
            terms = self.terms(math.comb(a.terms + j - 1, j), a.degree * j)
        return _Size(degree, terms, None)


_BINOPS: dict[type, str] = {ast.Add: "+", ast.Sub: "-", ast.Mult: "*", ast.Div: "/", ast.Pow: "**"}


def _text_size(text: str, names: Mapping[str, int], budget: _Budget) -> _Size:
    """Walks the Python syntax tree of ``text`` (iteratively: long sums nest deeply) allowing
    only numbers, the variables in ``names``, + - * / ** and parentheses; the bounds as it goes."""
    allowed = ", ".join(list(names)[:3]) + (", …" if len(names) > 3 else "")
    if len(text) > MAX_TEXT:
        raise budget.fail(f"is {len(text)} characters long, more than {MAX_TEXT}")
    try:
        tree = ast.parse(text.strip(), mode="eval").body
    except (SyntaxError, ValueError):
        raise budget.fail(f"{text[:60]!r} is not a polynomial expression") from None
    except RecursionError:
        raise budget.fail("is nested too deeply (too many terms in one sum?)") from None
    stack: list[tuple[ast.AST, bool]] = [(tree, False)]
    out: list[_Size] = []
    while stack:
        node, ready = stack.pop()
        if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
            if not ready:
                stack += [(node, True), (node.right, False), (node.left, False)]
                continue
            b, a = out.pop(), out.pop()
            op = _BINOPS[type(node.op)]
            if op in "+-":
                out.append(budget.add(a, b, 1.0 if op == "+" else -1.0))
            elif op == "*":
                out.append(budget.mul(a, b))
            elif op == "/":
                out.append(budget.div(a, b))
            else:
                out.append(budget.pow(a, b))
        elif isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
            if not ready:
                stack += [(node, True), (node.operand, False)]
                continue
            a = out.pop()
            sign = -1.0 if isinstance(node.op, ast.USub) else 1.0
            out.append(_Size(a.degree, a.terms, None if a.value is None else sign * a.value))
        elif isinstance(node, ast.Constant) and type(node.value) in (int, float):
            out.append(_Size(0, 1, budget.constant(node.value)))
        elif isinstance(node, ast.Name) and node.id in names:
            out.append(_Size(1, 1, None))
        elif isinstance(node, ast.Name):
            raise budget.fail(
                f"is not a polynomial in {allowed}: unknown name {node.id!r} "
                f"(the variables are x1..x{len(names)})"
            )
        else:
            raise budget.fail(
                f"is not a polynomial in {allowed}: {ast.unparse(node)[:40]!r} is not allowed "
                "(only numbers, the variables, + - * / ** and parentheses)"
            )
    return out[0]


def _expr_size(expr: Any, symbols: Sequence[Any], budget: _Budget) -> _Size:
    """The same bounds for a sympy expression (its tree is flat: Add and Mul hold many args)."""
    import sympy

    if not expr.free_symbols:
        return _Size(0, 1, budget.constant(expr))
    if expr.is_Symbol:
        if expr not in symbols:
            raise budget.fail(
                f"is not a polynomial in x1..x{len(symbols)}: unknown symbol {str(expr)!r}"
            )
        return _Size(1, 1, None)
    if isinstance(expr, sympy.Add | sympy.Mul):
        parts = [_expr_size(a, symbols, budget) for a in expr.args]
        acc = parts[0]
        for part in parts[1:]:
            acc = budget.add(acc, part, 1.0) if expr.is_Add else budget.mul(acc, part)
        return acc
    if expr.is_Pow:
        base = _expr_size(expr.base, symbols, budget)
        return budget.pow(base, _expr_size(expr.exp, symbols, budget))
    raise budget.fail(f"is not a polynomial in x1..x{len(symbols)}: {type(expr).__name__} term")


def _polynomial(raw: Any, symbols: Sequence[Any], field: str) -> Any:
    """``raw`` (text, a real number or a sympy expression) as an expanded sympy polynomial in
    ``symbols``, after the bounds above; ValueError/TypeError naming ``field`` otherwise.
    Coefficients must be finite with magnitude <= :data:`MAX_COEFFICIENT`."""
    import sympy

    n = len(symbols)
    budget = _Budget(field, n)
    names = {str(s): i for i, s in enumerate(symbols)}
    if isinstance(raw, str):
        _text_size(raw, names, budget)
        try:
            expr = sympy.sympify(raw.strip(), locals=dict(zip(names, symbols, strict=True)))
        except (sympy.SympifyError, SyntaxError, TypeError, ValueError, RecursionError):
            raise budget.fail(f"{raw[:60]!r} is not a polynomial expression") from None
    elif isinstance(raw, bool) or not isinstance(raw, numbers.Real | sympy.Basic):
        raise TypeError(
            f"{field} must be a polynomial (a string in x1..x{n}, a real number or a sympy "
            f"expression), got {type(raw).__name__}"
        )
    elif isinstance(raw, numbers.Real):
        value = budget.constant(raw)
        expr = sympy.Integer(int(raw)) if isinstance(raw, numbers.Integral) else sympy.Float(value)
    else:
        if not isinstance(raw, sympy.Expr):
            raise TypeError(f"{field} must be a sympy expression, got {type(raw).__name__}")
        # The caller's own symbols named x1.. (without real=True) are the variables too.
        expr = raw.xreplace(
            {s: symbols[names[s.name]] for s in raw.free_symbols if str(s) in names}
        )
        _expr_size(expr, symbols, budget)
    expr = sympy.expand(expr)
    if not expr.free_symbols <= set(symbols) or not expr.is_polynomial(*symbols):
        raise budget.fail(f"{str(raw)[:60]!r} is not a polynomial in x1..x{n}")
    poly = sympy.Poly(expr, *symbols)
    for coef in poly.coeffs():
        budget.constant(coef)
    if not all(c.is_Rational or c.is_Float for c in poly.coeffs()):
        # sqrt(2), pi, …: as the 15-digit floats sympy prints, so that the text form (to_dict,
        # pickling) parses back to the same system.
        def exact(c: Any) -> Any:
            return c if c.is_Rational or c.is_Float else sympy.Float(f"{float(c):.15g}")

        expr = sympy.Add(
            *(
                exact(c) * sympy.Mul(*(v**e for v, e in zip(symbols, m, strict=True)))
                for m, c in poly.terms()
            )
        )
    return expr


# --- work bounds of the realization and of the Taylor-HJ series ---------------------------------
#
# Their cost is not a function of the degrees alone (sparse brackets are cheap), so each step is
# estimated just before it runs, from the sizes of the terms already built: an upper bound on
# the monomial products sympy will form.

#: Most estimated monomial products one step of the realization or of the Taylor-HJ series may
#: cost (a step of the order-6 realization of the cubic Nambu bracket is about 80,000: ~15 s).
MAX_STEP_WORK = MAX_WORK // 200


def _total_degree(expr: Any, gens: Sequence[Any]) -> int:
    """Total degree of a sympy polynomial in ``gens``."""
    import sympy

    return int(sympy.Poly(expr, *gens).total_degree())


def _n_terms(expr: Any) -> int:
    import sympy

    return len(sympy.Add.make_args(expr)) if expr != 0 else 0


def _bracket_label(structure: PolynomialBivector) -> str:
    if structure.casimir is not None:
        return f"casimir {str(structure.casimir)[:60]!r}"
    degree = max(
        (_total_degree(e, structure.x) for e in structure.pi if e != 0),
        default=0,
    )
    return f"the bracket (entries of degree up to {degree})"


def _check_realization_work(
    structure: PolynomialBivector, terms: Sequence[Sequence[Any]], k: int
) -> None:
    """Step k of :meth:`PolynomialBivector.realization_terms` expands π^{ij}(x + b) with
    b = β_1 + … + β_{k−1}: a monomial Π x_l^{e_l} becomes at most Π_l C(T_l + e_l − 1, e_l)
    products (T_l the terms of x_l + b_l), each weighed 15 (measured: a substituted term costs
    sympy about 15 times a product of {b^i, b^j}, which costs about 2n T_i T_j). ValueError
    naming the bracket and the order."""
    import sympy

    n = structure.dim
    t = [1 + sum(_n_terms(step[v]) for step in terms[: k - 1]) for v in range(n)]
    work = 0
    for i in range(n):
        for j in range(i + 1, n):
            if structure.pi[i, j] == 0:
                continue
            for exps in sympy.Poly(structure.pi[i, j], *structure.x).monoms():
                work += 15 * math.prod(math.comb(t[v] + e - 1, e) for v, e in enumerate(exps))
            work += 2 * n * t[i] * t[j]
    if work > MAX_STEP_WORK:
        raise ValueError(
            f"{_bracket_label(structure)}: its realization of order {k} would cost about "
            f"{work} monomial products, more than the {MAX_STEP_WORK} allowed; "
            + (
                f"use a realization order < {k} (a lower Taylor order) or a lower-degree bracket"
                if k > matched_realization_order(1)
                else "no Taylor-HJ integrator fits it: use a lower-degree bracket, or a "
                "classical method (rk4, midpoint)"
            )
        )


def _count_mul(a: list[int], b: list[int], top: int) -> list[int]:
    """Term counts of a product of two truncated series, from the counts of their coefficients."""
    out = [0] * (top + 1)
    for i, ai in enumerate(a[: top + 1]):
        if ai:
            for j, bj in enumerate(b[: top + 1 - i]):
                out[i + j] += ai * bj
    return out


def _check_hj_work(
    system: PolynomialPoissonSystem,
    beta: Sequence[Any],
    p: Sequence[Any],
    s_terms: Sequence[Any],
    k: int,
) -> None:
    """Step k of :func:`hj_series` composes β(x, ∇S) and H(β) as series in t truncated at
    t^{k−1}: the products formed are bounded by the same compositions on term counts
    (a coefficient of c terms times one of d terms: c·d products). ValueError naming the
    Hamiltonian, the bracket and the order."""
    import sympy

    x, top = system.structure.x, k - 1
    grad = [[0] + [_n_terms(sympy.diff(s, xi)) for s in s_terms] for xi in x]
    work = 0

    def compose(poly: Any, gens: Sequence[Any], series: Sequence[list[int]]) -> list[int]:
        nonlocal work
        out = [0] * (top + 1)
        for exps, coeff in sympy.Poly(poly, *gens).terms():
            # β's coefficients are polynomials in x: their terms multiply the count.
            term = [_n_terms(coeff)]
            for g, e in zip(series, exps, strict=True):
                for _ in range(e):
                    term = _count_mul(term, g, top)
                    work += sum(term)
            out = [a + b for a, b in zip(out, term + [0] * (top + 1 - len(term)), strict=True)]
        return out

    beta_counts = [compose(b, p, grad) for b in beta]
    compose(system.h, x, beta_counts)
    if work > MAX_STEP_WORK:
        raise ValueError(
            f"hamiltonian {str(system.h)[:60]!r} on {_bracket_label(system.structure)}: the "
            f"Taylor-HJ term S_{k} would cost about {work} monomial products, more than the "
            f"{MAX_STEP_WORK} allowed; use a Taylor order < {k} or lower degrees"
        )


class PolynomialBivector:
    """A polynomial Poisson bivector π on R^n.

    ``entries``: mapping (i, j) → polynomial (sympy expression or string in x1, …, xn) for the
    entries above the diagonal (i < j; an entry given at (j, i) must be the negative of
    (i, j)). Raises ValueError for a non-polynomial entry, a broken antisymmetry, or a failure
    of the Jacobi identity at seeded random points in [−2, 2]^n (naming the triple).
    """

    def __init__(self, dim: int, entries: Mapping[tuple[int, int], Any], *, seed: int = 0) -> None:
        import sympy

        if isinstance(dim, bool) or not isinstance(dim, int) or not 2 <= dim <= 10:
            raise ValueError(f"dim must be an integer in 2..=10, got {dim!r}")
        x = _symbols(dim)
        pi = sympy.zeros(dim, dim)
        given: dict[tuple[int, int], Any] = {}
        if not isinstance(entries, Mapping):
            raise TypeError(
                f"entries must be a mapping (i, j) -> polynomial, got {type(entries).__name__}"
            )
        for key, raw in entries.items():
            if (
                not isinstance(key, tuple)
                or len(key) != 2
                or any(isinstance(k, bool) or not isinstance(k, numbers.Integral) for k in key)
            ):
                raise TypeError(f"entry key {key!r} must be a pair (i, j) of integers")
            i, j = int(key[0]), int(key[1])
            if not (0 <= i < dim and 0 <= j < dim) or i == j:
                raise ValueError(f"entry {key!r}: indices must be distinct and in 0..{dim - 1}")
            given[(i, j)] = _polynomial(raw, x, f"entry {key!r}")
        for (i, j), e in given.items():
            if (j, i) in given and sympy.expand(given[(j, i)] + e) != 0:
                raise ValueError(
                    f"pi must be antisymmetric: pi[{i},{j}] = {e} but pi[{j},{i}] = {given[(j, i)]}"
                )
            pi[i, j], pi[j, i] = e, -e
        self.dim = dim
        self.x = x
        self.pi = pi
        self._pi_num = _lambdify(x, list(pi))
        self._key = (dim, tuple(str(e) for e in pi))
        # Shared by every bivector with the same entries: the terms depend on π alone.
        self._realization_terms = _REALIZATION_TERMS.setdefault(self._key, [])
        self._check_jacobi(seed)

    @classmethod
    def nambu(cls, casimir: Any) -> PolynomialBivector:
        """π^{ij} = ε_ijk ∂_k C on R³ ({f, g} = ∇C·(∇f × ∇g)); C (in x1, x2, x3) is a Casimir."""
        import sympy

        x = _symbols(3)
        c = _polynomial(casimir, x, "casimir")
        grad = [sympy.diff(c, s) for s in x]
        if all(g == 0 for g in grad):
            raise ValueError(
                f"casimir {str(casimir)[:60]!r} is constant: its Nambu bracket is zero"
            )
        out = cls(3, {(0, 1): grad[2], (1, 2): grad[0], (0, 2): -grad[1]})
        out.casimir = c
        return out

    casimir: Any = None

    def __reduce__(self) -> tuple[Any, ...]:
        # The lambdified functions do not pickle; the entries (exact sympy text) rebuild them,
        # and a Nambu bracket is rebuilt from its Casimir so that it keeps it.
        if self.casimir is not None:
            return (PolynomialBivector.nambu, (str(self.casimir),))
        entries = {
            (i, j): str(self.pi[i, j]) for i in range(self.dim) for j in range(i + 1, self.dim)
        }
        return (PolynomialBivector, (self.dim, entries))

    def jacobiator(self) -> list[tuple[tuple[int, int, int], Any]]:
        """The Jacobi expressions J^{ijk} for i < j < k, symbolic."""
        import sympy

        pi, x, n = self.pi, self.x, self.dim
        out = []
        for i, j, k in itertools.combinations(range(n), 3):
            expr = sum(
                pi[a, m] * sympy.diff(pi[b, c], x[m])
                for (a, b, c) in ((i, j, k), (j, k, i), (k, i, j))
                for m in range(n)
            )
            out.append(((i, j, k), expr))
        return out

    def _check_jacobi(self, seed: int) -> None:
        """J^{ijk} = Σ_m π^{im}∂_mπ^{jk} + cyclic at seeded points in [−2, 2]^n, relative to the
        largest Σ_m |π^{im}||∂_mπ^{jk}| + cyclic there: both scale as π², so the verdict does
        not depend on π's scale (π/max|π| keeps the products finite)."""
        import sympy

        n = self.dim
        if n < 3:
            return
        rng = np.random.default_rng(seed)
        pts = rng.uniform(-2.0, 2.0, size=(16, n))
        upper = [(i, j) for i in range(n) for j in range(i + 1, n)]
        exprs = [self.pi[i, j] for i, j in upper]
        exprs += [sympy.diff(self.pi[i, j], xm) for xm in self.x for i, j in upper]
        f = sympy.lambdify(self.x, exprs, "numpy")
        values = np.array(
            [np.broadcast_to(np.asarray(v, dtype=np.float64), (len(pts),)) for v in f(*pts.T)]
        )
        u = len(upper)
        pi = np.zeros((len(pts), n, n))
        dpi = np.zeros((len(pts), n, n, n))  # [b, m, i, j] = ∂_m π^{ij}
        for a, (i, j) in enumerate(upper):
            pi[:, i, j], pi[:, j, i] = values[a], -values[a]
            for m in range(n):
                d = values[u + m * u + a]
                dpi[:, m, i, j], dpi[:, m, j, i] = d, -d
        size = float(np.abs(pi).max())
        if size == 0.0:
            return
        pi, dpi = pi / size, dpi / size
        t = np.einsum("bim,bmjk->bijk", pi, dpi)
        a_t = np.einsum("bim,bmjk->bijk", np.abs(pi), np.abs(dpi))
        jac = t + t.transpose(0, 2, 3, 1) + t.transpose(0, 3, 1, 2)
        mag = a_t + a_t.transpose(0, 2, 3, 1) + a_t.transpose(0, 3, 1, 2)
        triples = list(itertools.combinations(range(n), 3))
        scale = max(float(mag[:, i, j, k].max()) for i, j, k in triples)
        worst = np.abs(jac).max(axis=0)
        for i, j, k in triples:
            if worst[i, j, k] > 1e-9 * scale:
                raise ValueError(
                    f"pi fails the Jacobi identity for the triple (i, j, k) = {(i, j, k)}: "
                    f"|J^ijk| = {worst[i, j, k] / scale:.3g} relative to the size of its "
                    "terms at a random point"
                )

    def __call__(self, x: FloatArray) -> FloatArray:
        """π(x). x: (B, n) → (B, n, n)."""
        x = np.asarray(x, dtype=np.float64)
        return self._pi_num(*x.T).reshape(*x.shape[:-1], self.dim, self.dim)

    def realization(self, order: int = 2) -> tuple[list[Any], list[Any], tuple[Any, ...]]:
        """(β, α, p): sympy expressions of the order-``order`` realization in (x, p), and p's
        symbols, for ``order`` in 1..=:data:`MAX_REALIZATION_ORDER`.

        β = x + Σ_{k≤order} β_k with β_k homogeneous of degree k in p, built by
        :meth:`realization_terms`; α(x, p) = β(x, −p). Order 1 is x ∓ ½π p; order 2 adds
        (1/12)π^{lm}∂_lπ^{ij}p_m p_j. The realization conditions then hold to O(|p|^order).
        """
        import sympy

        if isinstance(order, bool) or not isinstance(order, int):
            raise ValueError(f"realization order must be an integer, got {order!r}")
        if not 1 <= order <= MAX_REALIZATION_ORDER:
            raise ValueError(
                f"realization order must be in 1..={MAX_REALIZATION_ORDER}, got {order!r}"
            )
        terms, p = self.realization_terms(order)
        beta = [sympy.expand(xi + sum(t[i] for t in terms[:order])) for i, xi in enumerate(self.x)]
        flip = {pj: -pj for pj in p}
        alpha = [sympy.expand(b.subs(flip, simultaneous=True)) for b in beta]
        return beta, alpha, p

    def realization_terms(self, order: int) -> tuple[list[list[Any]], tuple[Any, ...]]:
        """([β_1, …, β_order], p): the homogeneous terms of β in p, each a list of n sympy
        expressions, computed once per bivector and cached.

        With b = β_1 + … + β_{k−1} and the canonical bracket {x^i, p_j} = δ^i_j, the
        degree-(k−1) part of {β^i, β^j} − π^{ij}(β) = 0 reads

            ∂β_k^j/∂p_i − ∂β_k^i/∂p_j = Q^{ij},   Q^{ij} = [π^{ij}(x + b) − {b^i, b^j}]_{k−1}.

        Q is a closed 2-form in p (Jacobi and the lower orders make it so), homogeneous of
        degree k − 1, and the homotopy formula of the Poincaré lemma solves it in the radial
        gauge p_j β_k^j = 0: β_k^j = p_i Q^{ij} / (k + 1). k = 1 gives −½π p, k = 2 the
        (1/12) term; on a linear (Lie–Poisson) π the recursion returns the Bernoulli series
        of the exact groupoid (β_3 = 0). Taking α(x, p) = β(x, −p) (β for −π) makes
        {α^i, β^j} vanish to the same order (measured in the tests).
        """
        import sympy

        n, x, pi = self.dim, self.x, self.pi
        p = tuple(sympy.symbols(f"p1:{n + 1}", real=True))
        eps = sympy.Dummy("eps")
        scale = {pj: eps * pj for pj in p}
        terms = self._realization_terms
        for k in range(len(terms) + 1, order + 1):
            _check_realization_work(self, terms, k)
            b = [sum((t[i] for t in terms), sympy.Integer(0)) for i in range(n)]
            shift = {x[i]: x[i] + b[i] for i in range(n)}
            q = sympy.zeros(n, n)
            for i in range(n):
                for j in range(i + 1, n):
                    bracket = sum(
                        sympy.diff(b[i], x[c]) * sympy.diff(b[j], p[c])
                        - sympy.diff(b[i], p[c]) * sympy.diff(b[j], x[c])
                        for c in range(n)
                    )
                    e = pi[i, j].subs(shift, simultaneous=True) - bracket
                    e = sympy.expand(sympy.expand(e).subs(scale, simultaneous=True))
                    q[i, j] = e.coeff(eps, k - 1)
                    q[j, i] = -q[i, j]
            terms.append(
                [sympy.expand(sum(p[i] * q[i, j] for i in range(n)) / (k + 1)) for j in range(n)]
            )
        return terms[:order], p

    _realization_terms: list[list[Any]]


class PolynomialPoissonSystem(PoissonSystemBase):
    """A polynomial bivector with a polynomial Hamiltonian: ẋ = π(x)∇H(x). The studies'
    system interface: ``dim``, ``hamiltonian``, ``vector_field``, ``casimirs`` (the Nambu
    function when known, else None), ``component_names``, ``to_dict``."""

    kind = "polynomial_bivector"

    def __init__(
        self, structure: PolynomialBivector, hamiltonian: Any, *, name: str | None = None
    ) -> None:
        import sympy

        if not isinstance(structure, PolynomialBivector):
            raise TypeError(
                f"structure must be a PolynomialBivector, got {type(structure).__name__}"
            )
        x = structure.x
        h = _polynomial(hamiltonian, x, "hamiltonian")
        if name is not None and not isinstance(name, str):
            raise ValueError(f"name must be a string or None, got {name!r}")
        self.name = name
        self.structure = structure
        self.h = sympy.expand(h)
        self.component_names = tuple(str(s) for s in x)
        grad = [sympy.diff(self.h, s) for s in x]
        field = [
            sum(structure.pi[i, j] * grad[j] for j in range(structure.dim))
            for i in range(structure.dim)
        ]
        self._h = _lambdify(x, [self.h])
        self._f = _lambdify(x, field)
        # The field's terms for the core's classical steppers (index, coeffs, exponents).
        self.field_table = _term_table([sympy.expand(f) for f in field], x)
        self._c = None if structure.casimir is None else _lambdify(x, [structure.casimir])

    def __reduce__(self) -> tuple[Any, ...]:
        return (_system, (self.structure, str(self.h), self.name))

    def __repr__(self) -> str:
        from .recognition import recognize

        c = self.structure.casimir
        bracket = f"nambu={str(c)!r}" if c is not None else f"dim={self.dim}"
        found = recognize(self.structure)
        exact = (found.kind or "none").replace("_", "-")
        return (
            f"PolynomialPoissonSystem({bracket}, hamiltonian={str(self.h)!r}, "
            f"exact realization: {exact})"
        )

    def exact_system(self, tol: float = 1e-10) -> Any:
        """The equivalent system with an exact realization, or None: a
        :class:`~poisson_rs.LiePoissonSystem` (π linear), an
        :class:`~poisson_rs.AffinePoissonSystem` (linear plus constant) or a
        :class:`~poisson_rs.LogCanonicalSystem` (π_ij = c_ij x_i x_j) with the same H, when
        :func:`~poisson_rs.structures.recognition.recognize` finds π to be of that form to
        ``tol``; its integrators keep the Casimirs to round-off where the order-n realization
        keeps them to O(h^{n+1}) a step."""
        from .recognition import exact_system

        return exact_system(self, tol)

    @property
    def dim(self) -> int:
        return self.structure.dim

    def hamiltonian(self, x: Any) -> FloatArray:
        x = np.asarray(x, dtype=np.float64)
        return self._h(*np.moveaxis(x, -1, 0))[..., 0]

    def vector_field(self, x: Any) -> FloatArray:
        x = np.asarray(x, dtype=np.float64)
        return self._f(*np.moveaxis(x, -1, 0))

    @property
    def casimir_degrees(self) -> tuple[int, ...]:
        """0: the Nambu function need not be homogeneous, so its drift is reported absolute."""
        return () if self._c is None else (0,)

    @property
    def casimir_label(self) -> str:
        if self.structure.casimir is None:
            return "no Casimir known (drift n/a)"
        return f"C = {self.structure.casimir} (absolute drift)"

    def casimirs(self, x: Any) -> FloatArray | None:
        if self._c is None:
            return None
        x = np.asarray(x, dtype=np.float64)
        return self._c(*np.moveaxis(x, -1, 0))

    # --- the PoissonSystem protocol (poisson_rs.protocols) ---------------------------------

    def bracket_terms(self) -> BracketTerms:
        """π's entries above the diagonal, expanded."""
        s = self.structure
        upper = [s.pi[i, j] for i in range(s.dim) for j in range(i + 1, s.dim)]
        return BracketTerms(*_term_table(upper, s.x))

    def jet_realization(self, order: int) -> JetRealization:
        """The realization of order n matched to ``order``, at most
        :data:`MAX_REALIZATION_ORDER` (exact where π is constant: its terms past the first
        vanish)."""
        n = min(matched_realization_order(order), MAX_REALIZATION_ORDER)
        beta, alpha, p = self.structure.realization(n)
        gens = (*p, *self.structure.x)
        exact = all(e.is_number for e in self.structure.pi)
        return JetRealization(
            dim=self.dim,
            label=f"realization{n}",
            exact=exact,
            sou=_term_table(beta, gens),
            tar=_term_table(alpha, gens),
        )

    def bivector(self, x: Any) -> FloatArray:
        """π(x). x: (..., n) → (..., n, n)."""
        x = np.asarray(x, dtype=np.float64)
        flat = self.structure(x.reshape(-1, self.dim))
        return flat.reshape(*x.shape[:-1], self.dim, self.dim)

    @property
    def title(self) -> str:
        nambu = self.structure.casimir
        what = f"Nambu bracket of C = {nambu}" if nambu is not None else "polynomial bivector"
        return f"{self.name or 'polynomial Poisson system'}: {what}, H = {self.h}"

    def _exact(self) -> Any:
        """:meth:`exact_system`, computed once (the system is immutable)."""
        if "_exact_cache" not in self.__dict__:
            self.__dict__["_exact_cache"] = self.exact_system()
        return self.__dict__["_exact_cache"]

    def taylor_charts(self) -> tuple[str, ...]:
        """Where π is recognised as linear, affine or log-canonical, the exact system's charts
        first (its Casimirs kept to round-off); then "realization" (the order matched to the
        Taylor order, see :func:`matched_realization_order`) and "realization1" …
        "realization6" for one order."""
        exact = self._exact()
        own = (
            "realization",
            *(f"realization{n}" for n in range(1, MAX_REALIZATION_ORDER + 1)),
        )
        return (*exact.taylor_charts(), *own) if exact is not None else own

    def taylor_orders(self, wanted: Sequence[int]) -> tuple[int, ...]:
        """At most 5 on a realization (the sympy series grows fast beyond); any on an exact
        groupoid."""
        if self._exact() is not None:
            return tuple(wanted)
        return tuple(k for k in wanted if k <= MAX_TAYLOR_ORDER)

    def taylor_integrator(
        self, order: int, chart: str | None = None, *, tol: float, max_iter: int
    ) -> Any:
        chart = self.chart_or_default(chart)
        if not chart.startswith("realization"):
            # The exact groupoid of the recognised structure, on the same states x.
            return self._exact().taylor_integrator(order, chart, tol=tol, max_iter=max_iter)
        tail = chart.removeprefix("realization")
        return provided("polynomial.RealizationTaylorIntegrator")(
            self, order, int(tail) if tail else None, tol=tol, max_iter=max_iter
        )

    def learn_modes(self) -> tuple[str, ...]:
        """H through Taylor-HJ on the realization ("map" and "hj+data" learn on T*G of a Lie
        algebra)."""
        return ("auto", "hamiltonian")

    def learn_orders(self) -> tuple[int, ...]:
        return tuple(range(1, MAX_TAYLOR_ORDER + 1))

    def hamiltonian_family(self, degree: int, order: int | None = None) -> Any:
        """Polynomials in x of ``degree`` (no constant) on this bracket, stepped by Taylor-HJ of
        ``order`` (default 3) in the first chart: the exact groupoid where π is recognised as
        linear or affine, else the realization of matched order, its S_k computed in floating
        point (:class:`~poisson_rs.steppers.polynomial.SeriesRealizationIntegrator`)."""
        from ..hamiltonian_family import MonomialFamily, monomial_exponents, polynomial_text

        structure, names, n = self.structure, self.component_names, self.dim
        k = order or 3
        exact = self._exact()
        inner = (
            exact.hamiltonian_family(degree, k)
            if exact is not None and exact.learn_modes()
            else None
        )

        def build(terms: Mapping[tuple[int, ...], float]) -> PolynomialPoissonSystem:
            return PolynomialPoissonSystem(structure, polynomial_text(terms, names))

        def fit_stepper(terms: Mapping[tuple[int, ...], float], system: Any) -> Any:
            if inner is not None:
                # The recognised structure's exact groupoid, on the same states x.
                return inner.stepper([terms.get(e, 0.0) for e in inner.exponents])
            e = np.array(list(terms), dtype=np.int64).reshape(len(terms), n)
            c = np.array(list(terms.values()), dtype=np.float64)
            return provided("polynomial.SeriesRealizationIntegrator")(
                structure, (e, c), k, system=system
            )

        casimir = self.structure.casimir
        return MonomialFamily(
            n,
            monomial_exponents(n, degree),
            order=k,
            build=build,
            fit_stepper=fit_stepper,
            gauge=(
                f"a function of the Casimir C = {casimir}"
                if casimir is not None
                else "a Casimir of the bracket"
            ),
            variables=names,
        )

    def classical_methods(self) -> list[str]:
        return list(VECTOR_FIELD_METHODS)

    def classical(self, name: str, *, tol: float, max_iter: int) -> Any:
        return provided("polynomial.VectorFieldIntegrator")(self, name, tol=tol, max_iter=max_iter)

    def reference_solution(
        self,
        x0: Any,
        times: Any,
        *,
        rtol: float = 1e-13,
        atol: float = 1e-13,
        failures: Literal["raise", "nan"] = "raise",
    ) -> FloatArray:
        """DOP853 on the vector field."""
        field_reference = provided("field_reference")
        field = self.vector_field
        return field_reference(
            lambda y: field(y[None])[0],
            self.dim,
            x0,
            times,
            rtol=rtol,
            atol=atol,
            failures=failures,
        )

    def to_dict(self) -> dict[str, Any]:
        s = self.structure
        return {
            "kind": self.kind,
            "dim": s.dim,
            "entries": [[i, j, str(s.pi[i, j])] for i in range(s.dim) for j in range(i + 1, s.dim)],
            "hamiltonian": str(self.h),
            "casimir": None if s.casimir is None else str(s.casimir),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> PolynomialPoissonSystem:
        if not isinstance(data, Mapping) or data.get("kind") != cls.kind:
            raise ValueError(f"expected a {cls.kind!r} system dictionary, got {str(data)[:80]}")
        if "hamiltonian" not in data:
            raise ValueError("a polynomial_bivector system dictionary needs a 'hamiltonian' entry")
        if data.get("casimir") is not None:
            structure = PolynomialBivector.nambu(data["casimir"])
        else:
            dim, entries = data.get("dim"), data.get("entries")
            if isinstance(dim, bool) or not isinstance(dim, int):
                raise ValueError(f"system 'dim' must be an integer, got {str(dim)[:40]}")
            if not isinstance(entries, list) or not all(
                isinstance(e, list | tuple) and len(e) == 3 for e in entries
            ):
                raise ValueError("system 'entries' must be a list of [i, j, polynomial] triples")
            structure = PolynomialBivector(dim, {(i, j): e for i, j, e in entries})
        return cls(structure, data["hamiltonian"])

    def __eq__(self, other: object) -> bool:
        """Equal when :meth:`to_dict` is: the same bracket (entries, or Nambu Casimir) and the
        same H, as sympy writes them expanded; the name is ignored, as for the other systems."""
        if not isinstance(other, PolynomialPoissonSystem):
            return NotImplemented
        return self.to_dict() == other.to_dict()

    def __hash__(self) -> int:
        return hash(json.dumps(self.to_dict(), sort_keys=True))


def matched_realization_order(order: int) -> int:
    """The realization order that lets Taylor-HJ of ``order`` reach its full order: the odd
    n ≥ max(3, order). With α(x, p) = β(x, −p) the scheme is symmetric, so the global order is
    min(n, m) rounded up to even (measured: n = 3 gives 4, n = 5 gives 6), and an odd n costs
    less than the even n + 1 for the same order. n = 3 for m = 1 keeps C to O(h⁵) a step
    instead of O(h³) for little extra work."""
    return max(3, order + 1 - order % 2)


def _term_table(
    polys: Sequence[Any], gens: Sequence[Any]
) -> tuple[NDArray[np.int64], FloatArray, NDArray[np.int64]]:
    """(index, coeffs, exponents): every term of every polynomial in ``polys`` over ``gens``,
    index naming its polynomial, for the core."""
    import sympy

    index, coeffs, exponents = [], [], []
    for i, poly in enumerate(polys):
        for exps, coef in sympy.Poly(poly, *gens).terms():
            index.append(i)
            coeffs.append(float(coef))
            exponents.append(exps)
    return (
        np.array(index, dtype=np.int64),
        np.array(coeffs, dtype=np.float64),
        np.array(exponents, dtype=np.int64).reshape(len(coeffs), len(gens)),
    )


Series = list[Any]


def _series_mul(a: Series, b: Series, top: int) -> Series:
    """Product of two truncated power series in t (coefficient lists), kept to degree ``top``."""
    import sympy

    out = [sympy.Integer(0)] * (top + 1)
    for i, ai in enumerate(a):
        if ai == 0:
            continue
        for j, bj in enumerate(b[: top + 1 - i]):
            if bj != 0:
                out[i + j] += ai * bj
    return [sympy.expand(c) for c in out]


def _series_compose(poly: Any, gens: Sequence[Any], values: Sequence[Series], top: int) -> Series:
    """poly(values) as a truncated series in t: ``poly`` a sympy polynomial in ``gens`` (its
    coefficients may hold other symbols), each value a coefficient list in t."""
    import sympy

    out = [sympy.Integer(0)] * (top + 1)
    powers: dict[tuple[int, int], Series] = {}

    def power(i: int, e: int) -> Series:
        if (i, e) not in powers:
            powers[(i, e)] = (
                [sympy.Integer(1)] if e == 0 else _series_mul(power(i, e - 1), values[i], top)
            )
        return powers[(i, e)]

    for exps, coef in sympy.Poly(poly, *gens).terms():
        term: Series = [coef]
        for i, e in enumerate(exps):
            if e:
                term = _series_mul(term, power(i, e), top)
        for d, c in enumerate(term):
            out[d] += c
    return [sympy.expand(c) for c in out]


def hj_series(system: PolynomialPoissonSystem, order: int, realization_order: int) -> list[Any]:
    """[S_1, …, S_order]: the Taylor terms of S(t, x) = Σ t^k S_k solving
    ∂S/∂t + H(β(x, ∇S)) = 0 on the order-``realization_order`` realization (S_1 = −H).

    S_k = −[H(β(x, ∇S_{<k}))]_{t^{k−1}} / k. Every quantity is carried as a power series in t
    truncated at t^{order−1}, so the work grows with the orders kept, not with the expanded
    composition (whose full expansion is what made the direct substitution slow).
    """
    import sympy

    key = (system.structure._key, str(system.h), order, realization_order)
    if key in _HJ_SERIES:
        return list(_HJ_SERIES[key])
    x = system.structure.x
    beta, _, p = system.structure.realization(realization_order)
    s_terms: list[Any] = [-system.h]
    for k in range(2, order + 1):
        _check_hj_work(system, beta, p, s_terms, k)
        # ∇S_{<k} = Σ_j t^j ∇S_j: a series with zero constant term.
        grad = [[sympy.Integer(0)] + [sympy.diff(s, xi) for s in s_terms] for xi in x]
        # β(x, ∇S) as series: β is polynomial in p with x-dependent coefficients.
        beta_t = [_series_compose(b, p, grad, k - 1) for b in beta]
        h_t = _series_compose(system.h, x, beta_t, k - 1)
        s_terms.append(sympy.expand(-h_t[k - 1] / k))
    _HJ_SERIES[key] = list(s_terms)
    return s_terms


# Pickling (Dask ships steppers to worker processes): sympy text in, the same objects out.
def _system(structure: PolynomialBivector, h: str, name: str | None) -> PolynomialPoissonSystem:
    return PolynomialPoissonSystem(structure, h, name=name)


def _scene_table(raw: Mapping[str, Any]) -> PolynomialPoissonSystem:
    """A ``kind = "nambu"`` [system] table: the Nambu bracket {f, g} = ∇C·(∇f × ∇g) on R³ of the
    polynomial ``casimir`` C, with the polynomial ``hamiltonian`` (strings in x1, x2, x3),
    optional ``name``."""
    from ..tables import only_keys, optional_name, polynomial_text, required
    from ..untrusted import parsing

    only_keys(raw, ("kind", "casimir", "hamiltonian", "name"), "nambu")
    required(raw, "casimir", "hamiltonian")
    casimir = polynomial_text(raw["casimir"], "system.casimir")
    hamiltonian = polynomial_text(raw["hamiltonian"], "system.hamiltonian")
    name = optional_name(raw)
    with parsing("scene", "system.casimir"):
        structure = PolynomialBivector.nambu(casimir)
    with parsing("scene", "system.hamiltonian"):
        return PolynomialPoissonSystem(structure, hamiltonian, name=name)


def _bivector_scene_table(raw: Mapping[str, Any]) -> PolynomialPoissonSystem:
    """A ``kind = "bivector"`` [system] table: ``dim``, ``entries`` (a list of [i, j, text]:
    π_ij = the polynomial text in x1 … xn, i < j, 0-based) and the polynomial ``hamiltonian``,
    optional ``name``."""
    from ..tables import only_keys, optional_name, polynomial_text, required
    from ..untrusted import parsing

    only_keys(raw, ("kind", "dim", "entries", "hamiltonian", "name"), "bivector")
    required(raw, "dim", "entries", "hamiltonian")
    dim, entries = raw["dim"], raw["entries"]
    if isinstance(dim, bool) or not isinstance(dim, int):
        raise ValueError(f"scene key 'system.dim' must be an integer, got {dim!r}")
    if not isinstance(entries, list) or not all(
        isinstance(e, list) and len(e) == 3 and all(isinstance(k, int) for k in e[:2])
        for e in entries
    ):
        raise ValueError("scene key 'system.entries' must be a list of [i, j, polynomial]")
    table = {
        (e[0], e[1]): polynomial_text(e[2], f"system.entries[{k}]") for k, e in enumerate(entries)
    }
    hamiltonian = polynomial_text(raw["hamiltonian"], "system.hamiltonian")
    with parsing("scene", "system.entries"):
        structure = PolynomialBivector(dim, table)
    with parsing("scene", "system.hamiltonian"):
        return PolynomialPoissonSystem(structure, hamiltonian, name=optional_name(raw))


#: The kinds of system dictionaries and scene [system] tables this module reads.
SYSTEM_KINDS = {PolynomialPoissonSystem.kind: PolynomialPoissonSystem.from_dict}
SCENE_KINDS = {"nambu": _scene_table, "bivector": _bivector_scene_table}


_MOVED = ("RealizationTaylorIntegrator", "VectorFieldIntegrator")


def __getattr__(name: str) -> Any:
    # The steppers live in poisson_rs.steppers.polynomial now; importable from here one release.
    if name in _MOVED:
        return provided(f"polynomial.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _polynomial_brackets(degree: int) -> Callable[[int], Any]:
    """Every bivector with entries polynomials of ``degree`` (constants included): Jacobi
    projected, the order-n realization (or the exact one where the result is recognised)."""

    def family(dim: int) -> Any:
        from ..bracket_family import BracketFamily
        from ..hamiltonian_family import monomial_exponents, polynomial_text

        if not 2 <= dim <= 10:
            return None
        monomials = [(0,) * dim, *monomial_exponents(dim, degree)]
        terms = [(i, j, e) for i in range(dim) for j in range(i + 1, dim) for e in monomials]
        names = [str(s) for s in _symbols(dim)]

        def build(theta: NDArray[np.float64]) -> PolynomialPoissonSystem:
            entries: dict[tuple[int, int], dict[tuple[int, ...], float]] = {}
            for (i, j, e), t in zip(terms, theta, strict=True):
                if t != 0.0:
                    entries.setdefault((i, j), {})[e] = float(t)
            texts = {key: polynomial_text(v, names) for key, v in entries.items()}
            return PolynomialPoissonSystem(PolynomialBivector(dim, texts), "0", name="learned")

        return BracketFamily(
            f"poly{degree}-bivector",
            dim,
            terms,
            build=build,
            description=f"π_ij polynomials of degree ≤ {degree} (Jacobi projected)",
        )

    return family


BRACKET_FAMILIES = {f"poly{d}-bivector": _polynomial_brackets(d) for d in (2, 3)}

"""A charged particle in a static magnetic field: the structure of PNN's Lorentz-force system.

States z = (x, v) ∈ R^{2d}, position and velocity (unit charge and mass), d = 2 (planar, B a
scalar field B(x₁, x₂) normal to the plane) or d = 3 (B a divergence-free vector field), with

    {x_i, v_j} = δ_ij,   {v_i, v_j} = ε_ijk B_k(x)   (planar: {v₁, v₂} = B(x)),   ż = π(z)∇H(z),

so that for H = |v|²/2 + φ(x): ẋ = v and v̇ = v × B − ∇φ. Jacobi holds iff div B = 0.

The realization is exact and global: with a vector potential A (curl A = B), p = v + A(x) makes
the bracket canonical, {x_i, p_j} = δ_ij and {p_i, p_j} = 0. A constant bivector's order-1
realization is its symplectic groupoid (every higher term of the realization vanishes), so
Taylor-HJ runs on the canonical system (x, p) with H̃(x, p) = H(x, p − A(x)), in the Rust core's
polynomial-realization stepper, and its steps are symplectic maps of (x, v). For a polynomial B
the potential is polynomial: planar A = (0, ∫₀^{x₁} B(s, x₂) ds); in 3-D the radial gauge
A(x) = (∫₀¹ t B(tx) dt) × x. The classical methods (RK4, the implicit midpoint rule, DOP853) run
on the field in (x, v) itself.

B, H and A may also be expressions (:mod:`poisson_rs.expressions`: sqrt, exp, log, ...), as
PNN's B = |x|, A = |x|/3 (−x₂, x₁), H = |v|²/2 + 1/(100|x|). A non-polynomial B needs its
potential given (``potential=``), checked to satisfy curl A = B at seeded points. Taylor-HJ then
runs by jets (:class:`~poisson_rs.structures.expression_system.ExpressionSystem`) on the
canonical system with H̃ = H(x, p − A(x)) written as an expression, the classical methods on the
(x, v) field written as one program (π's B(x) entries included), and the domain is where H, A
and the field are finite (B = |x| with 1/|x| in H: not x = 0).

Everything here goes through the structure protocol (:class:`poisson_rs.PoissonSystem`): no other
module of the package names this one.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..bracket_family import BracketFamily
from ..distance_sums import DistanceTerms, distance_terms
from ..expressions import Expression
from ..protocols import NEWTON_MAX_ITER, NEWTON_TOL, PoissonSystemBase, provided
from .polynomial import (
    MAX_TAYLOR_ORDER,
    PolynomialBivector,
    PolynomialPoissonSystem,
    _lambdify,
    _symbols,
)

FloatArray = NDArray[np.float64]

#: The chart of the exact realization: Taylor-HJ in the canonical coordinates (x, p = v + A(x)).
CANONICAL_CHART = "canonical"
#: Texts sympy may read (numbers, x1…x9, + − * / ** and parentheses): any other text goes to
#: the expression grammar alone, never to sympy.
_SYMPY_TEXT = re.compile(r"(?:x[1-9]|[0-9.eE+\-*/() ])+")
#: curl A = B is checked at these many seeded points per scale |x| ∈ CURL_SCALES, to this
#: relative tolerance (derivatives of A exact, by the core's jets).
CURL_POINTS, CURL_SCALES, CURL_RTOL = 16, (0.3, 1.0, 3.0), 1e-12
#: Highest degree of a polynomial B, H or potential (sympy expands them).
MAX_DEGREE = 16


def _is_polynomial_text(text: str, names: Sequence[str], field: str) -> bool:
    """Whether ``text`` is for the polynomial (sympy) route: it reads as a polynomial by the
    expression grammar (no division by a variable, no negative power). A text the grammar
    refuses is refused here with its error: sympy never sees a text outside the grammar's
    bounds (``2**2**2**2**2**2`` would keep it busy for ever)."""
    from ..expressions import parse_program

    if not _SYMPY_TEXT.fullmatch(text):
        return False
    program = parse_program(text, names, field)
    polynomial = all(
        n[0] in ("var", "const", "add", "sub", "mul", "neg")
        or (n[0] == "powi" and n[2] >= 0)
        or (n[0] == "div" and program[n[2]][0] == "const")
        for n in program
    )
    # sympy expands a polynomial text, and (x1 + x2)**64**… would not end: its degree first.
    if polynomial and (degree := _program_degree(program)) > MAX_DEGREE:
        raise ValueError(f"{field}: degree {degree} is above {MAX_DEGREE}")
    return polynomial


def _program_degree(program: Sequence[tuple[Any, ...]]) -> int:
    """The total degree of a polynomial program (its last node), node by node."""
    deg: list[int] = []
    for op, *args in program:
        if op == "var":
            deg.append(1)
        elif op == "const":
            deg.append(0)
        elif op == "mul":
            deg.append(deg[args[0]] + deg[args[1]])
        elif op == "powi":
            deg.append(deg[args[0]] * args[1])
        elif op in ("add", "sub"):
            deg.append(max(deg[args[0]], deg[args[1]]))
        else:  # neg, and division by a constant
            deg.append(deg[args[0]])
    return deg[-1] if deg else 0


def _field_texts(field: Any, d: int) -> list[str]:
    """B's entries as texts: one (planar) or three (3-D)."""
    raw = [field] if d == 2 else list(field) if isinstance(field, (list, tuple)) else None
    if raw is None or len(raw) != (1 if d == 2 else 3):
        raise ValueError(
            f"field must be one polynomial B(x1, x2) (planar) or three, (B1, B2, B3)(x1, x2, x3); "
            f"got {field!r}"
        )
    for k, entry in enumerate(raw):
        if not isinstance(entry, (str, int, float)) or isinstance(entry, bool):
            raise ValueError(f"field[{k}] must be a polynomial (a string), got {entry!r}")
    return [str(entry) for entry in raw]


def _field_exprs(field: Any, d: int) -> list[Any]:
    """B as sympy polynomials in x1..xd: one entry (planar) or three (3-D)."""
    import sympy

    x = _symbols(2 * d)[:d]
    local = {f"x{i + 1}": s for i, s in enumerate(x)}
    out = []
    for k, entry in enumerate(_field_texts(field, d)):
        expr = sympy.sympify(entry, locals=local)
        if not expr.free_symbols <= set(x) or not expr.is_polynomial(*x):
            raise ValueError(f"field[{k}] = {entry!r} is not a polynomial in x1..x{d}")
        out.append(sympy.expand(expr))
    if d == 3 and sympy.expand(sum(sympy.diff(out[k], x[k]) for k in range(3))) != 0:
        raise ValueError(f"field = {field!r} is not divergence-free: no Poisson bracket has it")
    return out


def _potential_texts(potential: Any, d: int) -> list[str] | None:
    """The given vector potential's d entries as texts (None: not given)."""
    if potential is None:
        return None
    if (
        not isinstance(potential, (list, tuple))
        or len(potential) != d
        or not all(isinstance(a, (str, int, float)) and not isinstance(a, bool) for a in potential)
    ):
        raise ValueError(
            f"potential must be {d} expressions [A1, …, A{d}] in x1..x{d}, got {potential!r}"
        )
    return [str(a) for a in potential]


def _curl(jac: FloatArray) -> FloatArray:
    """curl A from its Jacobian jac[..., i, j] = ∂_j A_i: (...,) planar, (..., 3) in space."""
    if jac.shape[-1] == 2:
        return jac[..., 1, 0] - jac[..., 0, 1]
    return np.stack(
        [
            jac[..., 2, 1] - jac[..., 1, 2],
            jac[..., 0, 2] - jac[..., 2, 0],
            jac[..., 1, 0] - jac[..., 0, 1],
        ],
        axis=-1,
    )


def _check_curl(b: Sequence[Expression], a: Sequence[Expression], d: int) -> None:
    """ValueError naming ``potential`` unless curl A = B (expressions in x1..xd) at seeded points
    at the scales :data:`CURL_SCALES`, to :data:`CURL_RTOL` of the derivatives' size (points where
    B or A is not finite, e.g. x = 0 for 1/|x|, are left out)."""
    from .. import _core

    rng = np.random.default_rng(20240607)
    x = np.concatenate([r * rng.normal(size=(CURL_POINTS, d)) for r in CURL_SCALES])
    x = np.ascontiguousarray(x)
    with np.errstate(all="ignore"):
        jac = np.stack([_core.expression_jets(*e.tape(), x)[1] for e in a], axis=1)
        bx = np.stack([_core.expression_jets(*e.tape(), x)[0] for e in b], axis=-1)
    curl = _curl(jac).reshape(len(x), -1)
    ok = np.isfinite(curl).all(axis=1) & np.isfinite(bx).all(axis=1)
    if ok.sum() < CURL_POINTS:
        raise ValueError("potential: curl A = B cannot be checked: B or A is not finite almost "
                         "anywhere")  # fmt: skip
    scale = np.abs(jac[ok]).reshape(int(ok.sum()), -1).sum(axis=1) + np.abs(bx[ok]).sum(axis=1)
    gap = np.abs(curl[ok] - bx[ok]).max(axis=1)
    worst = int(np.argmax(gap / np.maximum(scale, 1e-300)))
    if gap[worst] > CURL_RTOL * scale[worst]:
        where = x[ok][worst]
        raise ValueError(
            f"potential: curl A ≠ B (∂₁A₂ − ∂₂A₁ = B planar): at x = {where.tolist()} curl A = "
            f"{curl[ok][worst].tolist()}, B = {bx[ok][worst].tolist()}"
        )


@functools.lru_cache(maxsize=2)
def _canonical_bracket(d: int) -> PolynomialPoissonSystem:
    """{x_i, p_j} = δ_ij: the bracket an expression H̃(x, p) is stepped on by jets (one per d:
    its realization is built once)."""
    return PolynomialPoissonSystem(
        PolynomialBivector(2 * d, {(i, d + i): 1 for i in range(d)}), "0"
    )


def _potential(b: Sequence[Any], d: int) -> list[Any]:
    """A vector potential of B with curl A = B (planar: ∂₁A₂ − ∂₂A₁ = B), polynomial."""
    import sympy

    x = _symbols(2 * d)[:d]
    t = sympy.Symbol("t")
    if d == 2:
        s = sympy.Symbol("s")
        a2 = sympy.integrate(b[0].subs(x[0], s), (s, 0, x[0]))
        return [sympy.Integer(0), sympy.expand(a2)]
    g = [
        sympy.integrate(t * bk.subs({xi: t * xi for xi in x}, simultaneous=True), (t, 0, 1))
        for bk in b
    ]
    return [
        sympy.expand(g[1] * x[2] - g[2] * x[1]),
        sympy.expand(g[2] * x[0] - g[0] * x[2]),
        sympy.expand(g[0] * x[1] - g[1] * x[0]),
    ]


class ChargedParticle(PoissonSystemBase):
    """A charged particle in the static magnetic field B (see the module docstring).

    Parameters
    ----------
    field : str or sequence of 3 str
        B: one entry, in x1, x2, for the planar particle (states of dimension 4); three, in x1,
        x2, x3 and divergence-free, in space (dimension 6). Polynomials, or any expressions of
        :mod:`poisson_rs.expressions` when ``potential`` is given.
    hamiltonian : str, optional
        H in x1…x2d, where x_{d+i} is v_i (default: |v|²/2): a polynomial or an expression.
    potential : sequence of d str, optional
        The vector potential A(x) with curl A = B (planar: ∂₁A₂ − ∂₂A₁ = B), checked at seeded
        points; required where B is not a polynomial, derived (polynomial) where it is.
    name : str, optional
    """

    kind = "charged_particle"

    def __init__(
        self,
        field: Any,
        hamiltonian: str | None = None,
        *,
        potential: Sequence[str] | None = None,
        name: str | None = None,
    ):
        from ..expressions import default_names

        d = 3 if isinstance(field, (list, tuple)) else 2
        if hamiltonian is None:
            hamiltonian = " + ".join(f"x{d + i + 1}**2/2" for i in range(d))
        if name is not None and not isinstance(name, str):
            raise ValueError(f"name must be a string or None, got {name!r}")
        texts, given = _field_texts(field, d), _potential_texts(potential, d)
        xs, zs = default_names(d), default_names(2 * d)
        self.d, self.name, self.given_potential = d, name, given
        self.component_names = tuple(f"{c}{chr(0x2080 + i + 1)}" for c in "xv" for i in range(d))
        #: The (x, v) system of a polynomial B, H and A (None: the expression route).
        self.direct: PolynomialPoissonSystem | None = None
        if (
            all(_is_polynomial_text(t, xs, "field") for t in texts)
            and (not isinstance(hamiltonian, str) or _is_polynomial_text(hamiltonian, zs, "h"))
            and all(_is_polynomial_text(t, xs, "potential") for t in given or ())
        ):
            self._polynomial_route(field, hamiltonian, given)
        else:
            self._expression_route(texts, str(hamiltonian), given)

    def _polynomial_route(self, field: Any, hamiltonian: Any, given: list[str] | None) -> None:
        """B, H and A polynomials: sympy, the polynomial-realization stepper."""
        import sympy

        d = self.d
        b = _field_exprs(field, d)
        z = _symbols(2 * d)
        entries: dict[tuple[int, int], Any] = {(i, d + i): 1 for i in range(d)}
        if d == 2:
            entries[(2, 3)] = b[0]
        else:
            entries.update({(3, 4): b[2], (4, 5): b[0], (3, 5): -b[1]})
        self.field = tuple(str(e) for e in b)
        # (x, v): the field, the classical methods and the reference.
        self.direct = PolynomialPoissonSystem(PolynomialBivector(2 * d, entries), hamiltonian)
        self.h = self.direct.h
        # (x, p = v + A(x)): canonical, where Taylor-HJ runs on the exact realization.
        if given is None:
            a = _potential(b, d)
        else:
            local = {str(v): v for v in z[:d]}
            a = [sympy.expand(sympy.sympify(t, locals=local)) for t in given]
            jac = np.array([[sympy.diff(ai, xj) for xj in z[:d]] for ai in a], dtype=object)
            curl = _curl(jac)
            if any(sympy.expand(c - bk) != 0 for c, bk in zip(np.atleast_1d(curl), b, strict=True)):
                raise ValueError(f"potential: curl A ≠ B for A = {given!r}, B = {self.field!r}")
        self.potential = tuple(str(e) for e in a)
        shift = {z[d + i]: z[d + i] - a[i] for i in range(d)}
        h_canonical = sympy.expand(self.h.subs(shift, simultaneous=True))
        canonical = PolynomialBivector(2 * d, {(i, d + i): 1 for i in range(d)})
        self.canonical: Any = PolynomialPoissonSystem(canonical, h_canonical)
        self._a = _lambdify(z[:d], a)

    def _expression_route(
        self, texts: list[str], hamiltonian: str, given: list[str] | None
    ) -> None:
        """B, H or A not polynomial: expressions, Taylor-HJ by jets on the canonical system."""
        from ..expressions import (
            Expression,
            default_names,
            field_program,
            parse_program,
            substitute,
        )
        from .expression_system import ExpressionSystem

        d = self.d
        xs, zs = default_names(d), default_names(2 * d)
        for k, t in enumerate(texts):
            parse_program(t, xs, f"field[{k}]")
        if given is None:
            if not all(_is_polynomial_text(t, xs, "field") for t in texts):
                raise ValueError(
                    f"potential: B = {', '.join(texts)} is not a polynomial, so its vector "
                    f"potential must be given: potential=[A1, …, A{d}] in x1..x{d} with curl A = B"
                )
            given_or_derived = [
                str(e) for e in _potential(_field_exprs(texts[0] if d == 2 else texts, d), d)
            ]
        else:
            given_or_derived = given
        for k, t in enumerate(given_or_derived):
            parse_program(t, xs, f"potential[{k}]")
        b = [Expression(t, xs) for t in texts]
        a = [Expression(t, xs) for t in given_or_derived]
        if given is not None:
            _check_curl(b, a, d)
        self.field, self.potential = tuple(texts), tuple(given_or_derived)
        self.h = hamiltonian
        self.hamiltonian_expression = Expression(hamiltonian, self.component_names, aliases=zs)
        self._b, self._a_exprs = b, a
        # H̃(x, p) = H(x, p − A(x)) as an expression, on the constant canonical bracket.
        shifted = [zs[i] for i in range(d)] + [f"{zs[d + i]} - ({a[i].text})" for i in range(d)]
        h_canonical = substitute(hamiltonian, self.component_names, shifted, aliases=zs)
        self.canonical = ExpressionSystem(_canonical_bracket(d), h_canonical)
        # (x, v): π's constant (and polynomial) entries as terms, a non-polynomial B as programs
        # of the one field program; the midpoint's Newton takes its Jacobian from the terms.
        polynomial_b = all(_is_polynomial_text(t, xs, "field") for t in texts)
        entries: dict[tuple[int, int], Any] = {(i, d + i): 1 for i in range(d)}
        programs: dict[tuple[int, int], tuple[Any, ...]] = {}
        pairs = [(2, 3)] if d == 2 else [(4, 5), (3, 5), (3, 4)]
        signs = [1.0] if d == 2 else [1.0, -1.0, 1.0]
        bx = _field_exprs(texts[0] if d == 2 else texts, d) if polynomial_b else None
        for k, (pair, sign) in enumerate(zip(pairs, signs, strict=True)):
            if bx is not None:
                entries[pair] = sign * bx[k]
            else:
                prog = b[k].program
                programs[pair] = prog if sign > 0 else (*prog, ("neg", len(prog) - 1))
        self.terms = PolynomialPoissonSystem(
            PolynomialBivector(2 * d, entries), "0"
        ).bracket_terms()
        self.tape = self.hamiltonian_expression.tape()
        self.field_program = field_program(
            self.hamiltonian_expression, *self.terms.tables(), entries=programs
        )
        # The compiled gradient of a sum over distances meets π through its polynomial terms
        # only: a bracket with entries that are programs (B not polynomial) keeps the program.
        self.distances: DistanceTerms | None = (
            None if programs else distance_terms(self.hamiltonian_expression.program, 2 * d)
        )

    @property
    def dim(self) -> int:
        return 2 * self.d

    def potential_at(self, x: ArrayLike) -> FloatArray:
        """A(x) for positions (..., d) → (..., d)."""
        x = np.asarray(x, dtype=np.float64)
        if self.direct is None:
            with np.errstate(all="ignore"):
                return np.stack([a.evaluate(x) for a in self._a_exprs], axis=-1)
        out = self._a(*np.moveaxis(x, -1, 0))
        return np.broadcast_to(out, x.shape).copy() if out.shape != x.shape else out

    def to_canonical(self, z: ArrayLike) -> FloatArray:
        """(x, v) ↦ (x, p = v + A(x)), (..., 2d) → (..., 2d)."""
        z = np.array(z, dtype=np.float64)
        z[..., self.d :] += self.potential_at(z[..., : self.d])
        return z

    def from_canonical(self, w: ArrayLike) -> FloatArray:
        """(x, p) ↦ (x, v = p − A(x))."""
        w = np.array(w, dtype=np.float64)
        w[..., self.d :] -= self.potential_at(w[..., : self.d])
        return w

    # --- the PoissonSystem protocol -----------------------------------------------------------

    def hamiltonian(self, z: Any) -> Any:
        """H at z (..., 2d); with an expression H a torch tensor in gives a differentiable
        tensor out."""
        if self.direct is not None:
            return self.direct.hamiltonian(z)
        if type(z).__module__.startswith("torch"):
            import torch

            return self.hamiltonian_expression.evaluate(z, torch)
        with np.errstate(all="ignore"):
            return self.hamiltonian_expression.evaluate(np.asarray(z, dtype=np.float64))

    def vector_field(self, z: Any) -> FloatArray:
        """ẋ = ∂H/∂v, v̇ = −∂H/∂x + B(x) × ∂H/∂v at z (..., 2d) → (..., 2d)."""
        if self.direct is not None:
            return self.direct.vector_field(z)
        from .. import _core

        arr = np.asarray(z, dtype=np.float64)
        flat = np.ascontiguousarray(arr.reshape(-1, self.dim))
        out = _core.hamiltonian_field(*self.tape, *self.terms.tables(), flat,
                                      program=self.field_program)  # fmt: skip
        return np.asarray(out).reshape(arr.shape)

    def bivector(self, z: Any) -> FloatArray:
        """π(z), (..., 2d) → (..., 2d, 2d)."""
        if self.direct is not None:
            return self.direct.bivector(z)
        z = np.asarray(z, dtype=np.float64)
        d = self.d
        out = np.zeros((*z.shape[:-1], 2 * d, 2 * d))
        for i in range(d):
            out[..., i, d + i], out[..., d + i, i] = 1.0, -1.0
        b = [e.evaluate(z) for e in self._b]
        pairs = [((2, 3), b[0])] if d == 2 else [((4, 5), b[0]), ((3, 5), -b[1]), ((3, 4), b[2])]
        for (i, j), value in pairs:
            out[..., i, j], out[..., j, i] = value, -value
        return out

    def in_domain(self, x: np.ndarray) -> np.ndarray:
        """(n,) bool: finite states where H, A and the field are finite (B = |x| with
        1/(100|x|) in H: every x ≠ 0)."""
        ok = np.asarray(np.isfinite(np.asarray(x, dtype=np.float64)).all(axis=-1))
        if self.direct is None and ok.any():
            y = np.asarray(x, dtype=np.float64)[ok]
            with np.errstate(all="ignore"):
                sane = (
                    np.isfinite(self.hamiltonian(y))
                    & np.isfinite(self.vector_field(y)).all(axis=-1)
                    & np.isfinite(self.potential_at(y[:, : self.d])).all(axis=-1)
                )
            ok[ok] = sane
        return np.asarray(ok)

    def domain_text(self) -> str:
        if self.direct is not None:
            return "finite"
        return "finite, with H, the potential A and the vector field finite (no singularity)"

    def casimirs(self, z: Any) -> None:
        """None: the bracket is symplectic (non-degenerate), it has no Casimir."""
        return None

    casimir_degrees: tuple[int, ...] = ()
    casimir_label = "no Casimir (a symplectic bracket): drift n/a"

    @property
    def field_argument(self) -> str | list[str]:
        """B as the constructor takes it: one text in the plane, three in space."""
        return self.field[0] if self.d == 2 else list(self.field)

    @property
    def title(self) -> str:
        where = "in the plane" if self.d == 2 else "in space"
        return (
            f"{self.name or 'charged particle'} {where}, B = {', '.join(self.field)}, H = {self.h}"
        )

    def taylor_charts(self) -> tuple[str, ...]:
        """("canonical",): the exact realization through p = v + A(x)."""
        return (CANONICAL_CHART,)

    def taylor_orders(self, wanted: Sequence[int]) -> tuple[int, ...]:
        """At most 5 for the realization stepper (its sympy series grows fast beyond); by jets
        at most the studies' 3, a jet step costing ~10× more per two orders
        (``taylor_integrator`` builds jets to order 8)."""
        if self.direct is None:
            return tuple(self.canonical.taylor_orders(wanted))
        return tuple(k for k in wanted if k <= MAX_TAYLOR_ORDER)

    def taylor_integrator(
        self,
        order: int,
        chart: str | None = None,
        *,
        tol: float = NEWTON_TOL,
        max_iter: int = NEWTON_MAX_ITER,
    ) -> CanonicalChartStepper:
        chart = self.chart_or_default(chart)
        # The order-1 realization of a constant bivector is exact (so is the one jets use).
        inner_chart = "realization1" if self.direct is not None else "jets"
        inner = self.canonical.taylor_integrator(order, inner_chart, tol=tol, max_iter=max_iter)
        return CanonicalChartStepper(self, inner, f"taylor{order}-{chart}", order)

    def learn_modes(self) -> tuple[str, ...]:
        """H through Taylor-HJ on the exact realization (no Lie algebra for the other modes)."""
        return ("auto", "hamiltonian")

    def learn_orders(self) -> tuple[int, ...]:
        return tuple(range(1, MAX_TAYLOR_ORDER + 1))

    def learn_degrees(self) -> tuple[int, ...]:
        """(2, 3, 4); by jets only the degrees whose full polynomial, written in (x, p − A(x)),
        fits the core's expression tape (MAX_INSTRUCTIONS)."""
        if self.direct is None:
            return tuple(d for d in (2, 3, 4) if self._family_fits(d))
        return (2, 3, 4)

    def _family_fits(self, degree: int) -> bool:
        from ..hamiltonian_family import monomial_exponents, polynomial_text

        exps = monomial_exponents(self.dim, degree)
        # Distinct coefficients, so that no two constants share a register of the program.
        terms = {e: 1.0 + k / 997 for k, e in enumerate(exps)}
        names = [f"x{i + 1}" for i in range(self.dim)]
        field = self.field_argument
        try:
            ChargedParticle(field, polynomial_text(terms, names), potential=list(self.potential))
        except ValueError:
            return False
        return True

    def hamiltonian_family(self, degree: int, order: int | None = None) -> Any:
        """Polynomials in (x, v) of ``degree`` (no constant) in this field B, stepped by
        Taylor-HJ of ``order`` (default 5) in the canonical chart: each monomial φ(x, v) is
        written once as φ(x, p − A(x)), so H̃_θ is a sum and its S_k are computed in floating
        point (:class:`~poisson_rs.steppers.polynomial.SeriesRealizationIntegrator`) at every
        iterate of a fit."""
        import sympy

        from ..hamiltonian_family import MonomialFamily, monomial_exponents, polynomial_text
        from ..steppers.polynomial import SeriesRealizationIntegrator, realization_tables
        from .polynomial import _term_table

        d, n, k = self.d, self.dim, order or 5
        if self.direct is None:
            # By jets, order 3 by default: a jet step of order 5 costs ~10× more, at every iterate.
            return self._expression_family(degree, order or 3)
        z = _symbols(n)
        local = {str(s): s for s in z}
        shift = {z[d + i]: z[d + i] - sympy.sympify(a, locals=local) for i, a in
                 enumerate(self.potential)}  # fmt: skip
        exponents = monomial_exponents(n, degree)
        canonical: dict[tuple[int, ...], tuple[Any, Any]] = {}
        for e in exponents:
            mono = sympy.Mul(*[s**p for s, p in zip(z, e, strict=True)])
            _, coeffs, exps = _term_table([sympy.expand(mono.subs(shift, simultaneous=True))], z)
            canonical[e] = (exps, coeffs)
        structure = self.canonical.structure
        realization_tables(structure, 1)  # derived once, before the fit's first step
        field = self.field[0] if d == 2 else list(self.field)
        names = [str(s) for s in z]

        def build(terms: Mapping[tuple[int, ...], float]) -> ChargedParticle:
            return ChargedParticle(field, polynomial_text(terms, names), name="learned")

        def fit_stepper(terms: Mapping[tuple[int, ...], float], system: Any) -> Any:
            exps = np.concatenate([canonical[e][0] for e in terms])
            coeffs = np.concatenate([c * canonical[e][1] for e, c in terms.items()])
            from ..realizations.numeric_hj import combine

            inner = SeriesRealizationIntegrator(structure, combine(exps, coeffs), k, 1)
            # The coordinates p = v + A(x) depend on B alone: this system's serve the fit.
            return CanonicalChartStepper(system or self, inner, f"taylor{k}-{CANONICAL_CHART}", k)

        return MonomialFamily(
            n,
            exponents,
            order=k,
            build=build,
            fit_stepper=fit_stepper,
            gauge="nothing else (the bracket is symplectic: no Casimir)",
            variables=names,
        )

    def _expression_family(self, degree: int, order: int) -> Any:
        """Polynomials in (x, v) of ``degree`` on this B and A (given), each H_θ stepped by
        Taylor-HJ by jets of ``order`` on H̃_θ(x, p) = H_θ(x, p − A(x))."""
        from ..expressions import default_names
        from ..hamiltonian_family import MonomialFamily, monomial_exponents, polynomial_text

        names = list(default_names(self.dim))
        field = self.field_argument
        potential = list(self.potential)

        def build(terms: Mapping[tuple[int, ...], float]) -> ChargedParticle:
            h = polynomial_text(terms, names)
            return ChargedParticle(field, h, potential=potential, name="learned")

        return MonomialFamily(
            self.dim,
            monomial_exponents(self.dim, degree),
            order=order,
            build=build,
            gauge="nothing else (the bracket is symplectic: no Casimir)",
            variables=names,
            chart=CANONICAL_CHART,
        )

    def steps_expressions_by_jets(self) -> bool:
        """Always: an expression H is stepped by jets on the canonical system (x, p = v + A(x))
        (:meth:`expression_system`)."""
        return True

    def expression_system(self, hamiltonian: str, *, name: str | None = None) -> ChargedParticle:
        """The same field B and potential A with the expression H(x, v) ``hamiltonian``: a
        charged particle again (by jets on H̃(x, p) = H(x, p − A(x)) where H or B is not a
        polynomial)."""
        field = self.field_argument
        return ChargedParticle(field, hamiltonian, potential=list(self.potential), name=name)

    def classical_methods(self) -> list[str]:
        if self.direct is None:
            from .expression_system import FIELD_METHODS

            return list(FIELD_METHODS)
        return self.direct.classical_methods()

    def classical(
        self, name: str, *, tol: float = NEWTON_TOL, max_iter: int = NEWTON_MAX_ITER
    ) -> Any:
        # On the field in (x, v) itself (the same bracket written as a polynomial bivector).
        if self.direct is not None:
            return self.direct.classical(name, tol=tol, max_iter=max_iter)
        # The expression program of the field; the midpoint's Newton takes its Jacobian from
        # π's polynomial entries and ∇²H (a non-polynomial B's own terms left out: the same
        # fixed point, reached by a simplified Newton).
        inner = provided("expression.FieldIntegrator")(self, name, tol=tol, max_iter=max_iter)
        return CheckedStepper(self, inner)

    def reference_solution(
        self,
        x0: ArrayLike,
        times: ArrayLike,
        *,
        rtol: float = 1e-13,
        atol: float = 1e-13,
        failures: Literal["raise", "nan"] = "raise",
    ) -> FloatArray:
        if self.direct is not None:
            return self.direct.reference_solution(
                x0, times, rtol=rtol, atol=atol, failures=failures
            )
        self.check_states(x0, "x0")
        field = self.vector_field
        return provided("field_reference")(
            lambda y: field(y[None])[0], self.dim, x0, times,
            rtol=rtol, atol=atol, failures=failures,
        )  # fmt: skip

    def to_dict(self) -> dict[str, Any]:
        out = {
            "kind": self.kind,
            "field": self.field_argument,
            "hamiltonian": str(self.h),
            "name": self.name,
        }
        if self.given_potential is not None:
            out["potential"] = list(self.given_potential)
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ChargedParticle:
        if not isinstance(data, Mapping) or data.get("kind") != cls.kind:
            raise ValueError(f"expected a {cls.kind!r} system dictionary, got {data!r}")
        if "field" not in data:
            raise ValueError("a charged-particle system needs a 'field' entry")
        return cls(
            data["field"], data.get("hamiltonian"), potential=data.get("potential"),
            name=data.get("name"),
        )  # fmt: skip

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ChargedParticle) and self.to_dict() == other.to_dict()

    def __hash__(self) -> int:
        return hash((self.kind, self.field, str(self.h)))

    def __reduce__(self) -> tuple[Any, ...]:
        return (ChargedParticle.from_dict, (self.to_dict(),))

    def __repr__(self) -> str:
        given = "" if self.given_potential is None else f", potential={self.given_potential!r}"
        return (
            f"ChargedParticle(field={self.to_dict()['field']!r}, hamiltonian={str(self.h)!r}"
            f"{given})"
        )


class CanonicalChartStepper:
    """A stepper of the canonical system (x, p) run on (x, v): states go to p = v + A(x), the
    inner stepper rolls them out, and every record comes back to v = p − A(x)."""

    def __init__(self, system: ChargedParticle, inner: Any, name: str, order: int) -> None:
        self.system, self.inner, self.name, self.order = system, inner, name, order
        self.poisson = True

    @property
    def dim(self) -> int:
        return self.system.dim

    @property
    def tol(self) -> float:
        """The inner stepper's Newton tolerance (relative update)."""
        return float(self.inner.tol)

    @property
    def max_iter(self) -> int:
        """The inner stepper's Newton iteration cap."""
        return int(self.inner.max_iter)

    def rollout(
        self, x0: np.ndarray, h: float, n_steps: int, every: int
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        # A state off the domain (x = 0 for B = |x|) is refused here, not rolled out as NaN.
        self.system.check_states(x0, "x0")
        w0 = np.ascontiguousarray(self.system.to_canonical(x0))
        traj, info = self.inner.rollout(w0, h, n_steps, every)
        return np.ascontiguousarray(self.system.from_canonical(traj)), dict(info)

    def __reduce__(self) -> tuple[Any, ...]:
        return (_taylor, (self.system, self.order, self.tol, self.max_iter))

    def __repr__(self) -> str:
        return f"CanonicalChartStepper({self.name!r}, system={self.system!r})"


def _taylor(system: ChargedParticle, order: int, tol: float, max_iter: int) -> Any:
    return system.taylor_integrator(order, tol=tol, max_iter=max_iter)


class CheckedStepper:
    """A classical method on the (x, v) field of an expression B or H, refusing states off the
    domain (ValueError naming x0) before it steps."""

    def __init__(self, system: ChargedParticle, inner: Any) -> None:
        self.system, self.inner = system, inner
        self.name, self.order, self.poisson = inner.name, inner.order, inner.poisson
        self.tol, self.max_iter = inner.tol, inner.max_iter

    @property
    def dim(self) -> int:
        return self.system.dim

    def rollout(
        self, x0: np.ndarray, h: float, n_steps: int, every: int
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        self.system.check_states(x0, "x0")
        traj, info = self.inner.rollout(x0, h, n_steps, every)
        return traj, dict(info)

    def __reduce__(self) -> tuple[Any, ...]:
        return (_classical, (self.system, self.name, self.tol, self.max_iter))

    def __repr__(self) -> str:
        return f"CheckedStepper({self.name!r}, system={self.system!r})"


def _classical(system: ChargedParticle, name: str, tol: float, max_iter: int) -> Any:
    return system.classical(name, tol=tol, max_iter=max_iter)


def charged_particle(
    field: Any,
    hamiltonian: str | None = None,
    *,
    potential: Sequence[str] | None = None,
    name: str | None = None,
) -> ChargedParticle:
    """A charged particle in the static magnetic field ``field`` (see :class:`ChargedParticle`).

    >>> import poisson_rs as pr
    >>> particle = pr.structures.charged_particle.charged_particle("1 + x1**2/4")
    >>> pr.integrate(pr.taylor_integrator(particle, 3), [0.1, 0.2, 1.0, 0.0], 0.1, 10).shape
    (11, 4)
    """
    return ChargedParticle(field, hamiltonian, potential=potential, name=name)


def _text(value: Any, key: str) -> str:
    """A scene's expression text (polynomial or not): a string of at most MAX_CHARS; the
    grammar (or, for a polynomial-only text, sympy) checks the rest."""
    from ..expressions import MAX_CHARS

    if not isinstance(value, str) or not 0 < len(value) <= MAX_CHARS:
        raise ValueError(f"scene key '{key}' must be an expression (a string of 1 to {MAX_CHARS} "
                         "characters)")  # fmt: skip
    return value


def _scene_table(raw: Mapping[str, Any]) -> ChargedParticle:
    """A ``kind = "charged_particle"`` [system] table: ``field`` (B in x1, x2, or a list of
    three in x1, x2, x3), optional ``hamiltonian`` (in x1…x2d, v_i = x_{d+i}), ``potential``
    (a list of d expressions, required for a B that is not a polynomial) and ``name``."""
    from ..tables import only_keys, optional_name, required
    from ..untrusted import parsing

    only_keys(raw, ("kind", "field", "hamiltonian", "potential", "name"), "charged_particle")
    required(raw, "field")
    field = raw["field"]
    if isinstance(field, list):
        field = [_text(f, f"system.field[{k}]") for k, f in enumerate(field)]
    else:
        field = _text(field, "system.field")
    h = raw.get("hamiltonian")
    if h is not None:
        h = _text(h, "system.hamiltonian")
    potential = raw.get("potential")
    if potential is not None:
        if not isinstance(potential, list):
            raise ValueError("scene key 'system.potential' must be a list of expressions")
        potential = [_text(a, f"system.potential[{k}]") for k, a in enumerate(potential)]
    name = optional_name(raw)
    with parsing("scene", "system"):
        return ChargedParticle(field, h, potential=potential, name=name)


# --- the magnetic bracket family (structure discovery) -----------------------------------------

#: B's candidate terms for discovery: homogeneous in x of degree k (> −2), so that the radial
#: gauge gives the potential in closed form, A = b(x)/(k + 2)·(−x₂, x₁) (curl A = b), with its
#: value and gradient on NumPy arrays x (..., 2). |x| and |x|⁻¹ are PNN's B's and its kin.
MAGNETIC_TERMS: tuple[tuple[str, int, Any, Any], ...] = (
    ("1", 0, lambda x: np.ones(x.shape[:-1]), lambda x: np.zeros(x.shape)),
    ("x1", 1, lambda x: x[..., 0], lambda x: np.stack([np.ones(x.shape[:-1]), 0 * x[..., 0]], -1)),
    ("x2", 1, lambda x: x[..., 1], lambda x: np.stack([0 * x[..., 0], np.ones(x.shape[:-1])], -1)),
    ("sqrt(x1**2 + x2**2)", 1, lambda x: np.linalg.norm(x, axis=-1),
     lambda x: x / np.linalg.norm(x, axis=-1, keepdims=True)),
    ("x1**2", 2, lambda x: x[..., 0] ** 2,
     lambda x: np.stack([2 * x[..., 0], 0 * x[..., 0]], -1)),
    ("x1*x2", 2, lambda x: x[..., 0] * x[..., 1], lambda x: x[..., ::-1].copy()),
    ("x2**2", 2, lambda x: x[..., 1] ** 2,
     lambda x: np.stack([0 * x[..., 0], 2 * x[..., 1]], -1)),
    ("1/sqrt(x1**2 + x2**2)", -1, lambda x: 1.0 / np.linalg.norm(x, axis=-1),
     lambda x: -x / np.linalg.norm(x, axis=-1, keepdims=True) ** 3),
)  # fmt: skip


class MagneticFamily(BracketFamily):
    """Planar charged-particle brackets on (x₁, x₂, v₁, v₂): {x_i, v_i} = θ₀ and
    {v₁, v₂} = Σ_k θ_k b_k(x) over :data:`MAGNETIC_TERMS`. Every θ obeys Jacobi (a planar B is
    closed whatever it is), so nothing is projected. The system θ builds is the charged particle
    with B = Σ_k (θ_k/θ₀) b_k, i.e. π_θ/θ₀ (the gauge π → λπ, H → H/λ fixed at {x_i, v_i} = 1),
    and :meth:`text` writes the bracket in that gauge."""

    def __init__(self) -> None:
        self.name, self.dim = "magnetic", 4
        self.description = (
            "{x_i, v_i} = 1, {v₁, v₂} = B(x) with B a combination of 1, x₁, x₂, |x|, x₁², "
            "x₁x₂, x₂², |x|⁻¹ (a planar charged particle; Jacobi holds for every B)"
        )
        # Placeholder entries: the family's basis is its own (see basis()).
        zero: tuple[int, ...] = (0, 0, 0, 0)
        self.terms = [(0, 2, zero)] + [(2, 3, zero)] * len(MAGNETIC_TERMS)
        self.jacobi_free, self._domain = True, _off_origin
        self._build = _magnetic_system
        self._template = np.zeros(len(self.terms))
        self._template[0] = self._template[4] = 1.0  # B = |x|: the expression route
        self._exps = np.zeros((len(self.terms), 4), dtype=np.int64)

    @property
    def degree(self) -> int:
        return 2

    def basis(self, x: Any) -> FloatArray:
        """Π_a(x), (B, 4, 4, P): θ₀ in {x₁, v₁} and {x₂, v₂}, b_k(x) in {v₁, v₂}."""
        x = np.atleast_2d(np.asarray(x, dtype=np.float64))
        out = np.zeros((x.shape[0], 4, 4, len(self)))
        for i in range(2):
            out[:, i, 2 + i, 0], out[:, 2 + i, i, 0] = 1.0, -1.0
        with np.errstate(all="ignore"):
            for a, (_, _, value, _) in enumerate(MAGNETIC_TERMS, start=1):
                b = value(x[:, :2])
                out[:, 2, 3, a], out[:, 3, 2, a] = b, -b
        return out

    def basis_derivative(self, x: Any) -> FloatArray:
        """∂_l Π_a(x)_ij, (B, 4, 4, 4, P) indexed [b, i, j, l, a]."""
        x = np.atleast_2d(np.asarray(x, dtype=np.float64))
        out = np.zeros((x.shape[0], 4, 4, 4, len(self)))
        with np.errstate(all="ignore"):
            for a, (_, _, _, grad) in enumerate(MAGNETIC_TERMS, start=1):
                g = grad(x[:, :2])
                out[:, 2, 3, :2, a], out[:, 3, 2, :2, a] = g, -g
        return out

    def text(self, theta: Any, names: Sequence[str], digits: int = 10) -> str:
        """ "{x₁, v₁} = {x₂, v₂} = 1; {v₁, v₂} = 1.0*sqrt(x₁**2 + x₂**2)", in the gauge θ₀ = 1
        (θ₀ = 0: the raw coefficients)."""
        theta = np.asarray(theta, dtype=np.float64)
        scale = theta[0] if theta[0] != 0 else 1.0
        parts = []
        for (label, _, _, _), t in zip(MAGNETIC_TERMS, theta[1:] / scale, strict=True):
            if t != 0.0:
                label = label.replace("x1", names[0]).replace("x2", names[1])
                parts.append(f"{t:.{digits}g}" + ("" if label == "1" else f"*{label}"))
        b = " + ".join(parts).replace("+ -", "- ") if parts else "0"
        head = f"{{{names[0]}, {names[2]}}} = {{{names[1]}, {names[3]}}}"
        return f"{head} = {1 if theta[0] != 0 else 0}; {{{names[2]}, {names[3]}}} = {b}"


def _off_origin(states: FloatArray) -> str | None:
    """Why the magnetic family cannot describe ``states``: |x| is not smooth at x = 0."""
    if not np.all(np.linalg.norm(np.asarray(states)[:, :2], axis=1) > 0):
        return "a state has x = 0, where |x| and |x|⁻¹ are not smooth"
    return None


def _magnetic_system(theta: FloatArray) -> ChargedParticle:
    """The charged particle of :class:`MagneticFamily`'s θ (B = Σ θ_k/θ₀ b_k, H = 0)."""
    if not (np.isfinite(theta).all() and theta[0] != 0):
        raise ValueError("{x_i, v_i} = 0 or a coefficient is not finite: not a charged particle")
    field, scaled, polynomial = [], [], True
    for (label, degree, _, _), t in zip(MAGNETIC_TERMS, theta[1:] / theta[0], strict=True):
        if t != 0.0:
            field.append(f"({float(t)!r})*({label})")
            scaled.append(f"({float(t) / (degree + 2)!r})*({label})")
            polynomial = polynomial and "sqrt" not in label
    b = " + ".join(field) or "0"
    g = " + ".join(scaled) or "0"
    # A polynomial B gets its potential derived exactly (sympy would compare the radial
    # gauge's rounded coefficients exactly); |x| and |x|⁻¹ take the radial gauge's, checked.
    potential = None if polynomial else [f"-({g})*x2", f"({g})*x1"]
    return ChargedParticle(b, "0", potential=potential, name="learned")


def _magnetic_brackets(dim: int) -> MagneticFamily | None:
    return MagneticFamily() if dim == 4 else None


#: The kinds of system dictionaries and scene [system] tables this module reads, and the
#: bracket family structure discovery searches.
SYSTEM_KINDS = {ChargedParticle.kind: ChargedParticle.from_dict}
SCENE_KINDS = {ChargedParticle.kind: _scene_table}
BRACKET_FAMILIES = {"magnetic": _magnetic_brackets}

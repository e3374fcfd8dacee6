"""A term library of Hamiltonians beyond polynomials, H_θ = Σ_m θ_m φ_m with φ_m monomials of
degree ≤ d and sin x_i, cos x_i of each coordinate, or monomials of degree ≤ d and the
log-distances ln|z_a − z_b|² of planar points, on any structure that steps expression
Hamiltonians by jets (:meth:`poisson_rs.protocols.PoissonSystemBase.jet_realization`).

Planar points: where the dimension n is even, the coordinates are read as n/2 consecutive pairs,
z_a = (x_{2a+1}, x_{2a+2}) for a = 0 … n/2 − 1 (0-based a, 1-based coordinates as in x1 … xn), and
the log-distance terms are ln((x_{2a+1} − x_{2b+1})² + (x_{2a+2} − x_{2b+2})²) for each pair a < b.
That is the only pairing tried (it is a rule on positions, not a guess at the system); where n is
odd or below 4 there are no such terms and a family asking for them is refused.

It offers what :func:`poisson_rs.learn.structure_fit.fit_structure_hamiltonian` asks of a
family (as :class:`poisson_rs.hamiltonian_family.MonomialFamily` does): the gradients of the φ_m
(so the vector field is linear in θ), the structure's integrator of H_θ (here Taylor-HJ by jets
of H_θ written as an expression: built in about a millisecond), the learned system, and a text.
A term is named by its key: an exponent tuple for a monomial, ``("sin", i)`` or ``("cos", i)``
for the trigonometric ones (i the 0-based coordinate), ``("logdist", a, b)`` for ln|z_a − z_b|²
(a < b, 0-based points). Nothing here names a structure.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .hamiltonian_family import monomial_exponents
from .protocols import NEWTON_MAX_ITER, NEWTON_TOL

__all__ = [
    "LIBRARY_DEGREES",
    "LIBRARY_DISTANCE_DEGREES",
    "LIBRARY_ORDER",
    "LibraryFamily",
    "distance_pairs",
    "library_families",
    "supports_library",
]

FloatArray = NDArray[np.float64]
Key = Any  # tuple[int, ...] | tuple[str, int] | tuple[str, int, int]

#: Taylor-HJ order (by jets) of the library's integrator: order 3 costs ~0.3 ms a step on a
#: 3-D affine bracket, order 5 ~3.5 ms (docs/hamiltonians.md).
LIBRARY_ORDER = 5
#: Polynomial degrees of the library tried by ``pr.learn``, after the polynomial families.
LIBRARY_DEGREES = (2, 3)
#: Polynomial degrees of the log-distance library tried by ``pr.learn``, after the trigonometric
#: ones and only where the dimension is even and ≥ 4: degree 2 also covers a uniform or linear
#: background flow (the linear and angular impulses are of degree ≤ 2).
LIBRARY_DISTANCE_DEGREES = (2,)
#: Two points closer than this, relative to 1 + |z_a| + |z_b|, count as coinciding: ln|z_a − z_b|²
#: and its gradient ~1/|z_a − z_b| are then no longer representable to any useful accuracy.
COINCIDE_RTOL = 1e-12


def supports_library(structure: Any) -> bool:
    """Whether ``structure`` steps expression Hamiltonians by jets (an exact or order-n jet
    realization)."""
    try:
        structure.jet_realization(LIBRARY_ORDER)
    except (AttributeError, NotImplementedError, ValueError):
        return False
    return True


def distance_pairs(dim: int) -> list[tuple[int, int]]:
    """The pairs (a, b), a < b, of planar points z_a = (x_{2a+1}, x_{2a+2}) of an even ``dim``
    ≥ 4 (0-based point indices). ValueError for an odd ``dim`` or one below 4."""
    if dim % 2 or dim < 4:
        raise ValueError(
            "log-distance terms read the coordinates as planar points (x1, x2), (x3, x4), …: "
            f"the dimension must be even and at least 4, got {dim}"
        )
    k = dim // 2
    return [(a, b) for a in range(k) for b in range(a + 1, k)]


def library_families(structure: Any, order: int | None, top: int) -> list[LibraryFamily]:
    """The term libraries ``pr.learn`` tries on ``structure`` after its polynomials, smallest
    first: poly+trig of :data:`LIBRARY_DEGREES`, then, where the dimension is even and ≥ 4,
    poly+logdist of :data:`LIBRARY_DISTANCE_DEGREES` (degrees above ``top`` left out; none
    where the structure does not step expressions by jets)."""
    if not supports_library(structure):
        return []
    out = [LibraryFamily(structure, d, order) for d in LIBRARY_DEGREES if d <= top]
    dim = int(structure.dim)
    if dim % 2 == 0 and dim >= 4:
        out += [
            LibraryFamily(structure, d, order, trig=False, log_distances=True)
            for d in LIBRARY_DISTANCE_DEGREES
            if d <= top
        ]
    # H_θ with every term must be one expression (its integrator steps that text): in high
    # dimensions the larger libraries exceed the expression limits and could never be fitted.
    return [f for f in out if f.writable()]


def _number(c: float) -> str:
    return f"({float(c)!r})"


class LibraryFamily:
    """H_θ over monomials of degree ≤ ``degree`` (no constant), sin and cos of each coordinate
    (``trig``) and the log-distances ln|z_a − z_b|² of planar points (``log_distances``; see the
    module docstring: ValueError where the dimension is odd or below 4), on the bracket of
    ``structure``, stepped by Taylor-HJ by jets of ``order``.

    ``keys`` restricts the family to those terms (see :meth:`restrict`).
    """

    def __init__(
        self,
        structure: Any,
        degree: int,
        order: int | None = None,
        *,
        keys: Sequence[Key] | None = None,
        trig: bool = True,
        log_distances: bool = False,
    ) -> None:
        self.structure = structure
        self.dim = int(structure.dim)
        self.variables = tuple(str(v) for v in structure.component_names)
        self.order = order or LIBRARY_ORDER
        self.chart = "jets"
        self._degree = degree
        self.trig, self.log_distances = bool(trig), bool(log_distances)
        every: list[Key] = list(monomial_exponents(self.dim, degree))
        if self.trig:
            every += [(f, i) for i in range(self.dim) for f in ("sin", "cos")]
        if self.log_distances:
            every += [("logdist", a, b) for a, b in distance_pairs(self.dim)]
        self.exponents: list[Key] = every if keys is None else [self._key(k) for k in keys]
        if not self.exponents or any(k not in every for k in self.exponents):
            raise ValueError(f"keys must be terms of the library {self.name}")
        self.gauge = "a Casimir of the bracket"

    @staticmethod
    def _key(k: Any) -> Key:
        return tuple(k) if not isinstance(k, tuple) else k

    def __len__(self) -> int:
        return len(self.exponents)

    @property
    def degree(self) -> int:
        return self._degree

    @property
    def name(self) -> str:
        return (
            f"poly{self._degree}"
            + ("+trig" if self.trig else "")
            + ("+logdist" if self.log_distances else "")
        )

    @property
    def description(self) -> str:
        extra = []
        if self.trig:
            extra.append("sin and cos of each coordinate")
        if self.log_distances:
            points = ", ".join(
                f"({a}, {b})"
                for a, b in zip(self.variables[::2], self.variables[1::2], strict=True)
            )
            extra.append(f"ln|z_a − z_b|² of the points {points}")
        return (
            f"a polynomial in ({', '.join(self.variables)}) of degree ≤ {self._degree} without "
            f"constant term plus {' and '.join(extra)} ({len(self)} terms)"
        )

    def restrict(self, keys: Sequence[Key]) -> LibraryFamily:
        """The same library on fewer terms."""
        return LibraryFamily(
            self.structure,
            self._degree,
            self.order,
            keys=list(keys),
            trig=self.trig,
            log_distances=self.log_distances,
        )

    def writable(self) -> bool:
        """Whether H_θ with every term fits the expression limits
        (:data:`poisson_rs.expressions.MAX_INSTRUCTIONS`), as its integrator needs."""
        from .expressions import Expression, ExpressionError

        try:
            # Distinct coefficients: equal ones would share one constant instruction.
            Expression(self.text(1.0 + np.arange(len(self))), self.variables)
        except ExpressionError:
            return False
        return True

    def _pairs(self) -> list[tuple[int, int]]:
        return [(k[1], k[2]) for k in self.exponents if k[0] == "logdist"]

    def check_states(self, x: Any, name: str = "trajectories") -> None:
        """ValueError naming ``name`` where a state of ``x`` (B, n) has two points of a
        log-distance term at the same place (within :data:`COINCIDE_RTOL`): ln|z_a − z_b|² is
        singular there. Nothing to check for the other terms, defined everywhere."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, self.dim)
        for a, b in self._pairs():
            za, zb = x[:, 2 * a : 2 * a + 2], x[:, 2 * b : 2 * b + 2]
            gap = np.linalg.norm(za - zb, axis=1)
            bad = gap <= COINCIDE_RTOL * (
                1.0 + np.linalg.norm(za, axis=1) + np.linalg.norm(zb, axis=1)
            )
            if bad.any():
                k = int(np.argmax(bad))
                va, vb = self.variables[2 * a : 2 * a + 2], self.variables[2 * b : 2 * b + 2]
                raise ValueError(
                    f"{name}: {int(bad.sum())} record(s) put points {a + 1} and {b + 1} at the "
                    f"same place, e.g. ({', '.join(va)}) = ({', '.join(vb)}) = "
                    f"({za[k, 0]:.6g}, {za[k, 1]:.6g}) in the state {x[k].tolist()}: the term "
                    f"library {self.name}'s ln|z_{a + 1} − z_{b + 1}|² is singular there"
                )

    def gradients(self, x: Any) -> FloatArray:
        """∇φ_m at states (B, n) → (B, n, P)."""
        x = np.asarray(x, dtype=np.float64)
        out = np.zeros((len(x), self.dim, len(self)))
        for m, key in enumerate(self.exponents):
            if key[0] == "logdist":
                # ∇ ln r² = 2 (z_a − z_b)/r² on z_a, the opposite on z_b.
                _, a, b = key
                d = x[:, 2 * a : 2 * a + 2] - x[:, 2 * b : 2 * b + 2]
                g = 2.0 * d / np.sum(d * d, axis=1, keepdims=True)
                out[:, 2 * a : 2 * a + 2, m] = g
                out[:, 2 * b : 2 * b + 2, m] = -g
                continue
            if isinstance(key[0], str):
                f, i = key
                out[:, i, m] = np.cos(x[:, i]) if f == "sin" else -np.sin(x[:, i])
                continue
            e = np.array(key, dtype=np.int64)
            for i in range(self.dim):
                if e[i] == 0:
                    continue
                lowered = e.copy()
                lowered[i] -= 1
                out[:, i, m] = e[i] * np.prod(x**lowered, axis=1)
        return out

    def terms(self, theta: Any) -> dict[Key, float]:
        """θ as {key: coefficient}, zeros dropped."""
        return {k: float(t) for k, t in zip(self.exponents, theta, strict=True) if t != 0.0}

    def _term_text(self, key: Key) -> str:
        if key[0] == "logdist":
            v, a, b = self.variables, 2 * key[1], 2 * key[2]
            return f"log(({v[a]} - {v[b]})**2 + ({v[a + 1]} - {v[b + 1]})**2)"
        if isinstance(key[0], str):
            return f"{key[0]}({self.variables[key[1]]})"
        return "*".join(
            f"{v}**{p}" if p > 1 else v for v, p in zip(self.variables, key, strict=True) if p
        )

    def text(self, theta: Any) -> str:
        """H_θ as an expression in the component names (floats by repr, which round-trips)."""
        parts = [f"{_number(c)}*{self._term_text(k)}" for k, c in self.terms(theta).items()]
        return " + ".join(parts) or "0"

    def system(self, theta: Any) -> Any:
        """The structure's bracket with H = H_θ (an expression system)."""
        from .structures.expression_system import with_hamiltonian

        return with_hamiltonian(self.structure, self.text(theta), name="learned")

    def stepper(self, theta: Any, system: Any = None) -> Any:
        """Taylor-HJ by jets of :attr:`order` for H_θ."""
        built = system if system is not None else self.system(theta)
        return built.taylor_integrator(self.order, tol=NEWTON_TOL, max_iter=NEWTON_MAX_ITER)

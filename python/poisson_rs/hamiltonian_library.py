"""A term library of Hamiltonians beyond polynomials, H_θ = Σ_m θ_m φ_m with φ_m monomials of
degree ≤ d and sin x_i, cos x_i of each coordinate, on any structure that steps expression
Hamiltonians by jets (:meth:`poisson_rs.protocols.PoissonSystemBase.jet_realization`).

It offers what :func:`poisson_rs.learn.structure_fit.fit_structure_hamiltonian` asks of a
family (as :class:`poisson_rs.hamiltonian_family.MonomialFamily` does): the gradients of the φ_m
(so the vector field is linear in θ), the structure's integrator of H_θ (here Taylor-HJ by jets
of H_θ written as an expression: built in about a millisecond), the learned system, and a text.
A term is named by its key: an exponent tuple for a monomial, ``("sin", i)`` or ``("cos", i)``
for the trigonometric ones. Nothing here names a structure.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .hamiltonian_family import monomial_exponents
from .protocols import NEWTON_MAX_ITER, NEWTON_TOL

__all__ = ["LIBRARY_DEGREES", "LIBRARY_ORDER", "LibraryFamily", "supports_library"]

FloatArray = NDArray[np.float64]
Key = Any  # tuple[int, ...] | tuple[str, int]

#: Taylor-HJ order (by jets) of the library's integrator: order 3 costs ~0.3 ms a step on a
#: 3-D affine bracket, order 5 ~3.5 ms (docs/hamiltonians.md).
LIBRARY_ORDER = 5
#: Polynomial degrees of the library tried by ``pr.learn``, after the polynomial families.
LIBRARY_DEGREES = (2, 3)


def supports_library(structure: Any) -> bool:
    """Whether ``structure`` steps expression Hamiltonians by jets (an exact or order-n jet
    realization)."""
    try:
        structure.jet_realization(LIBRARY_ORDER)
    except (AttributeError, NotImplementedError, ValueError):
        return False
    return True


def _number(c: float) -> str:
    return f"({float(c)!r})"


class LibraryFamily:
    """H_θ over monomials of degree ≤ ``degree`` (no constant) and sin, cos of each coordinate,
    on the bracket of ``structure``, stepped by Taylor-HJ by jets of ``order``.

    ``keys`` restricts the family to those terms (see :meth:`restrict`).
    """

    def __init__(
        self,
        structure: Any,
        degree: int,
        order: int | None = None,
        *,
        keys: Sequence[Key] | None = None,
    ) -> None:
        self.structure = structure
        self.dim = int(structure.dim)
        self.variables = tuple(str(v) for v in structure.component_names)
        self.order = order or LIBRARY_ORDER
        self.chart = "jets"
        self._degree = degree
        every: list[Key] = list(monomial_exponents(self.dim, degree))
        every += [(f, i) for i in range(self.dim) for f in ("sin", "cos")]
        self.exponents: list[Key] = every if keys is None else [self._key(k) for k in keys]
        if not self.exponents or any(k not in every for k in self.exponents):
            raise ValueError(f"keys must be terms of the library poly{degree}+trig")
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
        return f"poly{self._degree}+trig"

    @property
    def description(self) -> str:
        return (
            f"a polynomial in ({', '.join(self.variables)}) of degree ≤ {self._degree} without "
            f"constant term plus sin and cos of each coordinate ({len(self)} terms)"
        )

    def restrict(self, keys: Sequence[Key]) -> LibraryFamily:
        """The same library on fewer terms."""
        return LibraryFamily(self.structure, self._degree, self.order, keys=list(keys))

    def gradients(self, x: Any) -> FloatArray:
        """∇φ_m at states (B, n) → (B, n, P)."""
        x = np.asarray(x, dtype=np.float64)
        out = np.zeros((len(x), self.dim, len(self)))
        for m, key in enumerate(self.exponents):
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

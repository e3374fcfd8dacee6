"""A family of Hamiltonians H_θ = Σ_m θ_m φ_m on a fixed Poisson structure, as
:func:`poisson_rs.learn` fits it on any structure (see
:meth:`poisson_rs.protocols.PoissonSystemBase.hamiltonian_family`).

The learner asks the family only for what is linear in θ (the gradients of the φ_m, so the
vector field π∇H_θ is a design matrix times θ), for the structure's own Taylor-HJ integrator of
H_θ (fast, called at every iterate) and for the learned system. What the φ_m are, which chart
and order the integrator uses and how a system is rebuilt from θ is the structure's business:
this module names none.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .protocols import NEWTON_MAX_ITER, NEWTON_TOL

__all__ = ["MonomialFamily", "monomial_exponents", "polynomial_text"]

FloatArray = NDArray[np.float64]
Terms = Mapping[tuple[int, ...], float]


def monomial_exponents(n: int, degree: int, min_degree: int = 1) -> list[tuple[int, ...]]:
    """Exponent tuples of the monomials in n variables of total degree in [min_degree,
    degree], by degree, then reverse-lexicographically (x₁² before x₁x₂)."""
    import itertools

    out = []
    for d in range(min_degree, degree + 1):
        for combo in itertools.combinations_with_replacement(range(n), d):
            e = [0] * n
            for i in combo:
                e[i] += 1
            out.append(tuple(e))
    return out


def polynomial_text(terms: Terms, names: Sequence[str]) -> str:
    """Σ c·x^e as text sympy reads back exactly (floats by repr, which round-trips)."""
    parts = []
    for e, c in terms.items():
        factors = [repr(float(c))] + [
            f"{v}**{k}" if k > 1 else v for v, k in zip(names, e, strict=True) if k
        ]
        parts.append("*".join(factors))
    return " + ".join(parts) or "0"


def monomial_gradients(x: Any, exponents: Any) -> FloatArray:
    """∇x^{e_m} at states x (B, n) for the exponents (P, n) → (B, n, P)."""
    x = np.asarray(x, dtype=np.float64)
    e = np.asarray(exponents, dtype=np.int64).reshape(-1, x.shape[1])
    out = np.zeros((len(x), x.shape[1], len(e)))
    for i in range(x.shape[1]):
        lowered = e.copy()
        lowered[:, i] -= 1
        ok = lowered[:, i] >= 0
        vals = np.prod(x[:, None, :] ** np.maximum(lowered, 0)[None], axis=2)
        out[:, i, :] = np.where(ok, e[:, i] * vals, 0.0)
    return out


class MonomialFamily:
    """H_θ = Σ_m θ_m x^{e_m} over the monomials ``exponents`` (no constant: it moves nothing).

    ``build(terms)`` makes the structure's system with H = Σ terms[e]·x^e;
    ``fit_stepper(terms, system)`` (optional) its Taylor-HJ integrator of ``order`` built fast
    (``system`` is the built system or None during the fit; by default the built system's own
    integrator); ``gauge`` says what H is identifiable up to besides a constant;
    ``variables`` names the coordinates (:attr:`description` names the family in reports).
    """

    def __init__(
        self,
        dim: int,
        exponents: Sequence[tuple[int, ...]],
        *,
        order: int,
        build: Callable[[Terms], Any],
        gauge: str,
        variables: Sequence[str],
        fit_stepper: Callable[[Terms, Any], Any] | None = None,
        chart: str | None = None,
    ) -> None:
        self.dim = dim
        self.exponents = [tuple(int(v) for v in e) for e in exponents]
        if not self.exponents or any(len(e) != dim or sum(e) == 0 for e in self.exponents):
            raise ValueError(f"exponents must be non-constant monomials in {dim} variables")
        self.order, self.chart = order, chart
        self._build, self._fit_stepper = build, fit_stepper
        self.gauge = gauge
        self.variables = tuple(variables)
        self._e = np.array(self.exponents, dtype=np.int64)

    @property
    def degree(self) -> int:
        return max(sum(e) for e in self.exponents)

    @property
    def name(self) -> str:
        return f"poly{self.degree}"

    @property
    def description(self) -> str:
        return (
            f"a polynomial in ({', '.join(self.variables)}) of degree ≤ {self.degree} without "
            f"constant term ({len(self.exponents)} monomials)"
        )

    def __len__(self) -> int:
        return len(self.exponents)

    def restrict(self, exponents: Sequence[tuple[int, ...]]) -> MonomialFamily:
        """The same family on fewer monomials."""
        return type(self)(
            self.dim,
            exponents,
            order=self.order,
            build=self._build,
            gauge=self.gauge,
            variables=self.variables,
            fit_stepper=self._fit_stepper,
            chart=self.chart,
        )

    def gradients(self, x: Any) -> FloatArray:
        """∇x^{e_m} at states (B, n) → (B, n, P)."""
        return monomial_gradients(x, self._e)

    def terms(self, theta: Any) -> dict[tuple[int, ...], float]:
        """θ as {exponents: coefficient}, zeros dropped."""
        return {e: float(t) for e, t in zip(self.exponents, theta, strict=True) if t != 0.0}

    def text(self, theta: Any) -> str:
        """H_θ as text (for the report)."""
        return polynomial_text(self.terms(theta), self.variables)

    def system(self, theta: Any) -> Any:
        """The structure's system with H = H_θ."""
        return self._build(self.terms(theta))

    def stepper(self, theta: Any, system: Any = None) -> Any:
        """The structure's Taylor-HJ integrator of H_θ, built fast (the fit calls it at every
        iterate); ``system``, when given, is :meth:`system` of θ, for the stepper to carry."""
        terms = self.terms(theta)
        if self._fit_stepper is not None:
            return self._fit_stepper(terms, system)
        built = system if system is not None else self._build(terms)
        return built.taylor_integrator(
            self.order, self.chart, tol=NEWTON_TOL, max_iter=NEWTON_MAX_ITER
        )

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

Everything here goes through the structure protocol (:class:`poisson_rs.PoissonSystem`): no other
module of the package names this one.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..protocols import NEWTON_MAX_ITER, NEWTON_TOL, PoissonSystemBase
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


def _field_exprs(field: Any, d: int) -> list[Any]:
    """B as sympy polynomials in x1..xd: one entry (planar) or three (3-D)."""
    import sympy

    x = _symbols(2 * d)[:d]
    local = {f"x{i + 1}": s for i, s in enumerate(x)}
    raw = [field] if d == 2 else list(field) if isinstance(field, (list, tuple)) else None
    if raw is None or len(raw) != (1 if d == 2 else 3):
        raise ValueError(
            f"field must be one polynomial B(x1, x2) (planar) or three, (B1, B2, B3)(x1, x2, x3); "
            f"got {field!r}"
        )
    out = []
    for k, entry in enumerate(raw):
        if not isinstance(entry, (str, int, float)) or isinstance(entry, bool):
            raise ValueError(f"field[{k}] must be a polynomial (a string), got {entry!r}")
        expr = sympy.sympify(str(entry), locals=local)
        if not expr.free_symbols <= set(x) or not expr.is_polynomial(*x):
            raise ValueError(f"field[{k}] = {entry!r} is not a polynomial in x1..x{d}")
        out.append(sympy.expand(expr))
    if d == 3 and sympy.expand(sum(sympy.diff(out[k], x[k]) for k in range(3))) != 0:
        raise ValueError(f"field = {field!r} is not divergence-free: no Poisson bracket has it")
    return out


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
        B as polynomials: one, in x1, x2, for the planar particle (states of dimension 4); three,
        in x1, x2, x3 and divergence-free, in space (dimension 6).
    hamiltonian : str, optional
        H as a polynomial in x1…x2d, where x_{d+i} is v_i (default: |v|²/2).
    name : str, optional
    """

    kind = "charged_particle"

    def __init__(self, field: Any, hamiltonian: str | None = None, *, name: str | None = None):
        import sympy

        d = 3 if isinstance(field, (list, tuple)) else 2
        b = _field_exprs(field, d)
        z = _symbols(2 * d)
        if hamiltonian is None:
            hamiltonian = " + ".join(f"x{d + i + 1}**2/2" for i in range(d))
        if name is not None and not isinstance(name, str):
            raise ValueError(f"name must be a string or None, got {name!r}")
        entries: dict[tuple[int, int], Any] = {(i, d + i): 1 for i in range(d)}
        if d == 2:
            entries[(2, 3)] = b[0]
        else:
            entries.update({(3, 4): b[2], (4, 5): b[0], (3, 5): -b[1]})
        self.d, self.name, self.field = d, name, tuple(str(e) for e in b)
        # (x, v): the field, the classical methods and the reference.
        self.direct = PolynomialPoissonSystem(PolynomialBivector(2 * d, entries), hamiltonian)
        self.h = self.direct.h
        # (x, p = v + A(x)): canonical, where Taylor-HJ runs on the exact realization.
        a = _potential(b, d)
        self.potential = tuple(str(e) for e in a)
        shift = {z[d + i]: z[d + i] - a[i] for i in range(d)}
        h_canonical = sympy.expand(self.h.subs(shift, simultaneous=True))
        canonical = PolynomialBivector(2 * d, {(i, d + i): 1 for i in range(d)})
        self.canonical = PolynomialPoissonSystem(canonical, h_canonical)
        self._a = _lambdify(z[:d], a)
        self.component_names = tuple(f"{c}{chr(0x2080 + i + 1)}" for c in "xv" for i in range(d))

    @property
    def dim(self) -> int:
        return 2 * self.d

    def potential_at(self, x: ArrayLike) -> FloatArray:
        """A(x) for positions (..., d) → (..., d)."""
        x = np.asarray(x, dtype=np.float64)
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

    def hamiltonian(self, z: Any) -> FloatArray:
        return self.direct.hamiltonian(z)

    def vector_field(self, z: Any) -> FloatArray:
        return self.direct.vector_field(z)

    def bivector(self, z: Any) -> FloatArray:
        return self.direct.bivector(z)

    def casimirs(self, z: Any) -> None:
        """None: the bracket is symplectic (non-degenerate), it has no Casimir."""
        return None

    casimir_degrees: tuple[int, ...] = ()
    casimir_label = "no Casimir (a symplectic bracket): drift n/a"

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
        """At most 5, the realization stepper's (its sympy series grows fast beyond)."""
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
        # The order-1 realization of a constant bivector is exact.
        inner = self.canonical.taylor_integrator(order, "realization1", tol=tol, max_iter=max_iter)
        return CanonicalChartStepper(self, inner, f"taylor{order}-{chart}", order)

    def learn_modes(self) -> tuple[str, ...]:
        """H through Taylor-HJ on the exact realization (no Lie algebra for the other modes)."""
        return ("auto", "hamiltonian")

    def learn_orders(self) -> tuple[int, ...]:
        return tuple(range(1, MAX_TAYLOR_ORDER + 1))

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

    def classical_methods(self) -> list[str]:
        return self.direct.classical_methods()

    def classical(
        self, name: str, *, tol: float = NEWTON_TOL, max_iter: int = NEWTON_MAX_ITER
    ) -> Any:
        # On the field in (x, v) itself (the same bracket written as a polynomial bivector).
        return self.direct.classical(name, tol=tol, max_iter=max_iter)

    def reference_solution(
        self,
        x0: ArrayLike,
        times: ArrayLike,
        *,
        rtol: float = 1e-13,
        atol: float = 1e-13,
        failures: Literal["raise", "nan"] = "raise",
    ) -> FloatArray:
        return self.direct.reference_solution(x0, times, rtol=rtol, atol=atol, failures=failures)

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "field": self.field[0] if self.d == 2 else list(self.field),
            "hamiltonian": str(self.h),
            "name": self.name,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ChargedParticle:
        if not isinstance(data, Mapping) or data.get("kind") != cls.kind:
            raise ValueError(f"expected a {cls.kind!r} system dictionary, got {data!r}")
        if "field" not in data:
            raise ValueError("a charged-particle system needs a 'field' entry")
        return cls(data["field"], data.get("hamiltonian"), name=data.get("name"))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ChargedParticle) and self.to_dict() == other.to_dict()

    def __hash__(self) -> int:
        return hash((self.kind, self.field, str(self.h)))

    def __reduce__(self) -> tuple[Any, ...]:
        return (ChargedParticle.from_dict, (self.to_dict(),))

    def __repr__(self) -> str:
        return f"ChargedParticle(field={self.to_dict()['field']!r}, hamiltonian={str(self.h)!r})"


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
        w0 = np.ascontiguousarray(self.system.to_canonical(x0))
        traj, info = self.inner.rollout(w0, h, n_steps, every)
        return np.ascontiguousarray(self.system.from_canonical(traj)), dict(info)

    def __reduce__(self) -> tuple[Any, ...]:
        return (_taylor, (self.system, self.order, self.tol, self.max_iter))

    def __repr__(self) -> str:
        return f"CanonicalChartStepper({self.name!r}, system={self.system!r})"


def _taylor(system: ChargedParticle, order: int, tol: float, max_iter: int) -> Any:
    return system.taylor_integrator(order, tol=tol, max_iter=max_iter)


def charged_particle(
    field: Any, hamiltonian: str | None = None, *, name: str | None = None
) -> ChargedParticle:
    """A charged particle in the static magnetic field ``field`` (see :class:`ChargedParticle`).

    >>> import poisson_rs as pr
    >>> particle = pr.structures.charged_particle.charged_particle("1 + x1**2/4")
    >>> pr.integrate(pr.taylor_integrator(particle, 3), [0.1, 0.2, 1.0, 0.0], 0.1, 10).shape
    (11, 4)
    """
    return ChargedParticle(field, hamiltonian, name=name)


def _scene_table(raw: Mapping[str, Any]) -> ChargedParticle:
    """A ``kind = "charged_particle"`` [system] table: ``field`` (a polynomial B in x1, x2, or a
    list of three in x1, x2, x3), optional ``hamiltonian`` (in x1…x2d, v_i = x_{d+i}) and
    ``name``."""
    from ..tables import only_keys, optional_name, polynomial_text, required
    from ..untrusted import parsing

    only_keys(raw, ("kind", "field", "hamiltonian", "name"), "charged_particle")
    required(raw, "field")
    field = raw["field"]
    if isinstance(field, list):
        field = [polynomial_text(f, f"system.field[{k}]") for k, f in enumerate(field)]
    else:
        field = polynomial_text(field, "system.field", "x1, x2")
    h = raw.get("hamiltonian")
    if h is not None:
        h = polynomial_text(h, "system.hamiltonian", "x1 … x6")
    name = optional_name(raw)
    with parsing("scene", "system"):
        return ChargedParticle(field, h, name=name)


#: The kinds of system dictionaries and scene [system] tables this module reads.
SYSTEM_KINDS = {ChargedParticle.kind: ChargedParticle.from_dict}
SCENE_KINDS = {ChargedParticle.kind: _scene_table}

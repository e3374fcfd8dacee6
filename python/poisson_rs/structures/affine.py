"""Affine Poisson structures: a Lie–Poisson bracket plus a constant 2-cocycle, integrated as
Lie–Poisson systems on a central extension at level 1.

The bracket on Rⁿ is {x_i, x_j} = −Σ_k c[i,j,k] x_k + ω_ij, with c the structure constants of a
Lie algebra g (the package's convention: the Lie–Poisson part is that of
:class:`~poisson_rs.LiePoissonSystem`, μ̇_j = Σ_{i,k} c[i,j,k] ∂_iH μ_k) and ω a constant
antisymmetric matrix. Jacobi holds if and only if ω is a 2-cocycle of g:

    Σ_l (c[j,k,l] ω_il + c[k,i,l] ω_jl + c[i,j,l] ω_kl) = 0   for every triple (i, j, k).

Then ĝ = g ⊕ R z with [e_i, e_j] = Σ_k c[i,j,k] e_k − ω_ij z and z central is a Lie algebra (the
central extension by ω), μ_z is a Casimir of ĝ*, and on the hyperplane μ_z = 1 the Lie–Poisson
bracket of ĝ* is the affine bracket above. So every Lie–Poisson integrator of ĝ* (Taylor-HJ on
the exact groupoid, RK4, the midpoint rule, DOP853) integrates the affine system: lift x to
(x, 1), step on ĝ*, drop the last component. μ_z = 1 is linear, so every one of them keeps it to
round-off; the Taylor-HJ steps keep the other Casimirs of ĝ* as well.

PNN's extended pendulum is {u, v} = −1, {u, r} = −2v, {v, r} = 2u: g = e(2) (r rotates the
translations u, v), ω_uv = −1, and ĝ is the oscillator algebra. Its Casimir on μ_z = 1 is
r − u² − v².
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..protocols import (
    NEWTON_MAX_ITER,
    NEWTON_TOL,
    BracketTerms,
    JetRealization,
    PoissonSystemBase,
    Stepper,
    provided,
)
from .lie_poisson import LieAlgebra, LiePoissonSystem, Polynomial, linear_bracket_terms

FloatArray = NDArray[np.float64]

#: Largest dimension of the extension the core is compiled for (``poisson_rs._core.MAX_DIM``).
MAX_DIM = 10
#: Cocycle residual allowed, relative to max|c|·max|ω|.
COCYCLE_RTOL = 1e-12
#: Largest |ω_ij|. ω enters the extension's structure constants, and its Taylor-HJ term S_k
#: multiplies k − 1 of them: with |ω| <= 1e15 the exact terms still convert to finite float64
#: through order 10 (1e100 overflows at order 3, 1e300 at once).
MAX_COCYCLE = 1e15


def _check_cocycle(c: FloatArray, cocycle: ArrayLike) -> FloatArray:
    """ω as a finite antisymmetric (n, n) float64 array that is a 2-cocycle of c; ValueError
    naming 'cocycle' (and the failing triple) otherwise."""
    n = c.shape[0]
    arr = np.asarray(cocycle)
    if arr.dtype == object or arr.dtype.kind not in "fiu":
        raise TypeError(f"cocycle must be an array of real numbers, got dtype {arr.dtype}")
    w = np.array(arr, dtype=np.float64)
    if w.shape != (n, n):
        raise ValueError(f"cocycle must be an ({n}, {n}) matrix for this algebra, got {w.shape}")
    if not np.isfinite(w).all():
        raise ValueError("cocycle holds NaN or infinite values")
    if np.abs(w).max(initial=0.0) > MAX_COCYCLE:
        i, j = np.argwhere(np.abs(w) > MAX_COCYCLE)[0]
        raise ValueError(
            f"cocycle[{i}, {j}] = {w[i, j]:.3g} exceeds {MAX_COCYCLE:.0e} in magnitude (the "
            "Taylor-HJ terms of the central extension would overflow float64)"
        )
    if not np.array_equal(w, -w.T):
        i, j = np.argwhere(w != -w.T)[0]
        raise ValueError(
            f"cocycle must be antisymmetric (w_ij = -w_ji): w[{i},{j}] = {w[i, j]} but "
            f"w[{j},{i}] = {w[j, i]}"
        )
    scale = max(float(np.abs(c).max(initial=0.0)) * float(np.abs(w).max(initial=0.0)), 1e-300)
    for i, j, k in itertools.combinations(range(n), 3):
        r = c[j, k] @ w[i] + c[k, i] @ w[j] + c[i, j] @ w[k]
        if abs(r) > COCYCLE_RTOL * scale * n:
            raise ValueError(
                f"cocycle is not a 2-cocycle of the algebra (the bracket fails the Jacobi "
                f"identity) for the triple (i, j, k) = ({i}, {j}, {k}): "
                f"Σ_l (c[j,k,l] w_il + c[k,i,l] w_jl + c[i,j,l] w_kl) = {r:.3g}"
            )
    return w


def central_extension(algebra: LieAlgebra, cocycle: ArrayLike) -> LieAlgebra:
    """ĝ = g ⊕ R z, [e_i, e_j] = Σ_k c[i,j,k] e_k − ω_ij z, z central: (n+1)-dimensional, so that
    its Lie–Poisson bracket at μ_z = 1 is {x_i, x_j} = −Σ_k c[i,j,k] x_k + ω_ij."""
    if not isinstance(algebra, LieAlgebra):
        raise TypeError(f"algebra must be a LieAlgebra, got {type(algebra).__name__}")
    c = algebra.c
    n = c.shape[0]
    if n + 1 > MAX_DIM:
        raise ValueError(f"the extension has dimension {n + 1}, more than {MAX_DIM}")
    w = _check_cocycle(c, cocycle)
    ext = np.zeros((n + 1, n + 1, n + 1))
    ext[:n, :n, :n] = c
    ext[:n, :n, n] = -w
    return LieAlgebra(ext, name=None)


def _lift_polynomial(h: Polynomial) -> Polynomial:
    """H(x) as a polynomial on Rⁿ⁺¹ that does not depend on the last variable."""
    return Polynomial({(*e, 0): a for e, a in h.terms.items()} or {(0,) * (h.dim + 1): 0.0})


class AffinePoissonSystem(PoissonSystemBase):
    """An affine Poisson system on Rⁿ: {x_i, x_j} = −Σ_k c[i,j,k] x_k + ω_ij with a polynomial
    H, ẋ = π(x)∇H(x). Integrated on its central extension at level 1 (:attr:`extension`, a
    :class:`~poisson_rs.LiePoissonSystem` of dimension n + 1); see the module docstring.

    The system interface of the studies: ``dim``, ``hamiltonian``, ``vector_field``,
    ``casimirs`` (those of the extension that are not constant on μ_z = 1, or None),
    ``component_names``, ``to_dict``/``from_dict``.
    """

    kind = "affine"

    def __init__(
        self,
        algebra: LieAlgebra,
        cocycle: ArrayLike,
        hamiltonian: Polynomial,
        *,
        name: str | None = None,
        component_names: Sequence[str] | None = None,
    ) -> None:
        if not isinstance(hamiltonian, Polynomial):
            raise TypeError(f"hamiltonian must be a Polynomial, got {type(hamiltonian).__name__}")
        ext_algebra = central_extension(algebra, cocycle)
        n = algebra.dim
        if hamiltonian.dim != n:
            raise ValueError(f"the algebra has dimension {n}, the Hamiltonian {hamiltonian.dim}")
        if name is not None and not isinstance(name, str):
            raise ValueError(f"name must be a string or None, got {name!r}")
        names = (
            tuple(component_names)
            if component_names is not None
            else tuple(f"x{chr(0x2080 + i + 1) if i < 9 else i + 1}" for i in range(n))
        )
        if len(names) != n or not all(isinstance(s, str) for s in names):
            raise ValueError(f"component_names must be {n} strings, got {component_names!r}")
        self.algebra = algebra
        self.cocycle = np.array(cocycle, dtype=np.float64)
        self.cocycle.flags.writeable = False
        self.polynomial = hamiltonian
        self.name = name
        self.component_names: tuple[str, ...] = names
        self.extension = LiePoissonSystem(ext_algebra, _lift_polynomial(hamiltonian), name=name)
        self._casimir_columns: list[int] | None = None

    @property
    def dim(self) -> int:
        return self.algebra.dim

    def lift(self, x: Any) -> FloatArray:
        """(x, 1): states (..., n) → (..., n + 1) on the extension's level-1 hyperplane."""
        x = np.asarray(x, dtype=np.float64)
        if x.ndim == 0 or x.shape[-1] != self.dim:
            raise ValueError(f"x must have shape (..., {self.dim}), got {x.shape}")
        return np.concatenate([x, np.ones((*x.shape[:-1], 1))], axis=-1)

    def hamiltonian(self, x: Any) -> FloatArray:
        """H(x). x: (..., n) → (...,)."""
        return np.asarray(self.polynomial(np.asarray(x, dtype=np.float64)), dtype=np.float64)

    def bracket_terms(self) -> BracketTerms:
        """π_ij = −Σ_k c[i,j,k] x_k + ω_ij (affine)."""
        return linear_bracket_terms(self.algebra.c, self.cocycle)

    def jet_realization(self, order: int) -> JetRealization:
        """The exact groupoid of the central extension at level 1, exponential chart."""
        ext = central_extension(self.algebra, self.cocycle)
        return JetRealization(
            dim=self.dim + 1, label="exp", exact=True, lie_constants=np.array(ext.c)
        )

    def bivector(self, x: Any) -> FloatArray:
        """π(x)_ij = −Σ_k c[i,j,k] x_k + ω_ij. x: (..., n) → (..., n, n)."""
        x = np.asarray(x, dtype=np.float64)
        return -np.einsum("ijk,...k->...ij", self.algebra.c, x) + self.cocycle

    def vector_field(self, x: Any) -> FloatArray:
        """ẋ = π(x)∇H(x), the first n components of the extension's field at (x, 1)."""
        return np.asarray(self.extension.vector_field(self.lift(x)))[..., : self.dim]

    def _casimir_fn(self) -> Any:
        from ..casimirs import system_casimirs

        return system_casimirs(self.extension)

    def _columns(self) -> list[int]:
        """The extension's Casimirs that vary on μ_z = 1 (μ_z itself and its powers do not)."""
        if self._casimir_columns is None:
            fn = self._casimir_fn()
            cols: list[int] = []
            if fn is not None:
                rng = np.random.default_rng(0)
                values = fn(self.lift(rng.normal(size=(16, self.dim))))
                spread = values.max(axis=0) - values.min(axis=0)
                cols = [int(k) for k in np.flatnonzero(spread > 1e-9 * (1 + np.abs(values).max()))]
            self._casimir_columns = cols
        return self._casimir_columns

    def casimirs(self, x: Any) -> FloatArray | None:
        """The extension's polynomial Casimirs at (x, 1) that are not constant there:
        (..., n) → (..., m), or None when there is none (r − u² − v² up to scale for PNN's
        extended pendulum)."""
        cols = self._columns()
        if not cols:
            return None
        return np.asarray(self._casimir_fn()(self.lift(x)))[..., cols]

    @property
    def casimir_degrees(self) -> tuple[int, ...]:
        """The degree of each Casimir on the extension (homogeneous there): the studies scale
        its drift by |x₀|^d."""
        from ..casimirs import casimir_degrees

        degrees = casimir_degrees(self.extension) or ()
        return tuple(degrees[k] for k in self._columns())

    @property
    def casimir_label(self) -> str:
        m = len(self._columns())
        if m == 0:
            return "no Casimir known (drift n/a)"
        return f"{m} Casimir{'s' if m != 1 else ''} of the central extension, at level 1"

    # --- the PoissonSystem protocol (poisson_rs.protocols): the extension's, at level 1 -----

    @property
    def title(self) -> str:
        return f"{self.name or 'affine system'}: Lie–Poisson + constant cocycle, dim {self.dim}"

    def step_angles(self, states: np.ndarray, h: float) -> FloatArray:
        """The extension's step angles at (x, 1)."""
        return self.extension.step_angles(np.ascontiguousarray(self.lift(states)), h)

    def taylor_charts(self) -> tuple[str, ...]:
        """("exp",): the exponential chart of the extension's groupoid."""
        return ("exp",)

    def taylor_integrator(
        self, order: int, chart: str | None = None, *, tol: float, max_iter: int
    ) -> Stepper:
        """Taylor-HJ of ``order`` on the extension's exact groupoid, run at level 1: a Poisson
        map that keeps μ_z = 1 and every Casimir of the extension to round-off."""
        chart = self.chart_or_default(chart)
        inner = self.extension.taylor_integrator(order, chart, tol=tol, max_iter=max_iter)
        return provided("affine.AffineIntegrator")(self, inner, f"taylor{order}-{chart}")

    def learn_modes(self) -> tuple[str, ...]:
        """H through Taylor-HJ on the extension's groupoid ("map" and "hj+data" learn on T*G
        of a Lie algebra, not at level 1 of an extension)."""
        return ("auto", "hamiltonian")

    def hamiltonian_family(self, degree: int, order: int | None = None) -> Any:
        """Polynomials in x of ``degree`` (no constant) on this bracket, stepped by the
        extension's Taylor-HJ of ``order`` at level 1. The default order is what the exact
        series builds in well under a second at every iterate of a fit: 7 for degree ≤ 2, 5
        for 3, 3 above (a dense quartic's order-5 terms take 1.4 s)."""
        from ..hamiltonian_family import MonomialFamily, monomial_exponents

        algebra, cocycle, names = self.algebra, self.cocycle, self.component_names
        k = order or (7 if degree <= 2 else 5 if degree == 3 else 3)

        def build(terms: Mapping[tuple[int, ...], float]) -> AffinePoissonSystem:
            poly = Polynomial(dict(terms) or {(0,) * len(names): 0.0})
            return AffinePoissonSystem(
                algebra, cocycle, poly, name="learned", component_names=names
            )

        return MonomialFamily(
            self.dim,
            monomial_exponents(self.dim, degree),
            order=k,
            chart="exp",
            build=build,
            gauge=f"a Casimir of the bracket ({self.casimir_label})",
            variables=names,
        )

    def classical_methods(self) -> list[str]:
        return self.extension.classical_methods()

    def classical(self, name: str, *, tol: float, max_iter: int) -> Stepper:
        """The extension's classical integrator ``name``, run at level 1."""
        inner = self.extension.classical(name, tol=tol, max_iter=max_iter)
        return provided("affine.AffineIntegrator")(self, inner, name)

    def reference_solution(
        self,
        x0: ArrayLike,
        times: ArrayLike,
        *,
        rtol: float = 1e-13,
        atol: float = 1e-13,
        failures: Literal["raise", "nan"] = "raise",
    ) -> FloatArray:
        """DOP853 on the central extension at level 1 (μ_z = 1 is kept), its first n
        components."""
        lifted = self.lift(self.check_states(x0))
        out = self.extension.reference_solution(
            lifted, times, rtol=rtol, atol=atol, failures=failures
        )
        return np.ascontiguousarray(out[..., : self.dim])

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "name": self.name,
            "algebra": self.algebra.to_dict(),
            "cocycle": self.cocycle.tolist(),
            "hamiltonian": self.polynomial.to_dict(),
            "component_names": list(self.component_names),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> AffinePoissonSystem:
        if not isinstance(data, Mapping) or data.get("kind") != cls.kind:
            raise ValueError(f"expected an {cls.kind!r} system dictionary, got {data!r}")
        for key in ("algebra", "cocycle", "hamiltonian"):
            if key not in data:
                raise ValueError(f"an affine system needs an {key!r} entry")
        return cls(
            LieAlgebra.from_dict(data["algebra"]),
            data["cocycle"],
            Polynomial.from_dict(data["hamiltonian"]),
            name=data.get("name"),
            component_names=data.get("component_names"),
        )

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, AffinePoissonSystem)
            and self.extension == other.extension
            and self.dim == other.dim
        )

    def __hash__(self) -> int:
        return hash(("affine", self.extension))

    def __reduce__(self) -> tuple[Any, ...]:
        return (_from_dict, (self.to_dict(),))

    def __repr__(self) -> str:
        label = f"name={self.name!r}, " if self.name else ""
        return f"AffinePoissonSystem({label}dim={self.dim}, cocycle={self.cocycle.tolist()})"


def _from_dict(data: Mapping[str, Any]) -> AffinePoissonSystem:
    return AffinePoissonSystem.from_dict(data)


def affine_poisson_system(
    c: ArrayLike | LieAlgebra,
    cocycle: ArrayLike,
    hamiltonian: Polynomial | Mapping[tuple[int, ...], float],
    *,
    name: str | None = None,
    component_names: Sequence[str] | None = None,
) -> AffinePoissonSystem:
    """The affine Poisson system {x_i, x_j} = −Σ_k c[i,j,k] x_k + ω_ij with Hamiltonian H.

    ``c``: structure constants (n, n, n) of a Lie algebra (or a LieAlgebra), in the convention of
    :class:`~poisson_rs.LieAlgebra`; ``cocycle``: ω, (n, n), antisymmetric and a 2-cocycle of c
    (ValueError naming the failing triple otherwise); ``hamiltonian``: a Polynomial on Rⁿ or its
    terms {exponents: coefficient}.

    PNN's extended pendulum ({u, v} = −1, {u, r} = −2v, {v, r} = 2u)::

        c = np.zeros((3, 3, 3))
        c[0, 2, 1], c[2, 0, 1] = 2, -2     # {u, r} = −2v
        c[1, 2, 0], c[2, 1, 0] = -2, 2     # {v, r} = 2u
        w = [[0, -1, 0], [1, 0, 0], [0, 0, 0]]
        pr.affine_poisson_system(c, w, {(2, 0, 0): 0.5, (0, 2, 0): 0.5, (0, 4, 0): -1 / 24})
    """
    algebra = c if isinstance(c, LieAlgebra) else LieAlgebra(c)
    poly = hamiltonian if isinstance(hamiltonian, Polynomial) else Polynomial(dict(hamiltonian))
    return AffinePoissonSystem(algebra, cocycle, poly, name=name, component_names=component_names)


def affine_taylor(
    system: AffinePoissonSystem,
    order: int = 3,
    *,
    tol: float = NEWTON_TOL,
    max_iter: int = NEWTON_MAX_ITER,
) -> Stepper:
    """Deprecated alias of ``pr.taylor_integrator(system, order)`` (kept one release)."""
    return system.taylor_integrator(order, tol=tol, max_iter=max_iter)


def _scene_table(raw: Mapping[str, Any]) -> AffinePoissonSystem:
    """A ``kind = "affine"`` [system] table: ``algebra`` (a name of a standard algebra or a
    LieAlgebra.to_dict() table), ``cocycle`` (n × n, antisymmetric, a 2-cocycle),
    ``hamiltonian`` (a Polynomial.to_dict() table), optional ``name`` and
    ``component_names``."""
    from ..tables import only_keys, optional_name, required
    from ..untrusted import parsing
    from .lie_poisson import NAMED_ALGEBRAS

    allowed = ("kind", "algebra", "cocycle", "hamiltonian", "name", "component_names")
    only_keys(raw, allowed, "affine")
    required(raw, "algebra", "cocycle", "hamiltonian")
    with parsing("scene", "system.algebra"):
        algebra = raw["algebra"]
        if isinstance(algebra, str):
            if algebra not in NAMED_ALGEBRAS:
                raise ValueError(f"{algebra!r} is not one of {NAMED_ALGEBRAS}")
            algebra = getattr(LieAlgebra, algebra)()
        else:
            algebra = LieAlgebra.from_dict(algebra)
    with parsing("scene", "system.hamiltonian"):
        hamiltonian = Polynomial.from_dict(raw["hamiltonian"])
    names = raw.get("component_names")
    if names is not None and not (
        isinstance(names, list) and all(isinstance(v, str) and v for v in names)
    ):
        raise ValueError(f"scene key 'system.component_names' must be a list of names: {names!r}")
    name = optional_name(raw)
    with parsing("scene", "system.cocycle"):
        return AffinePoissonSystem(
            algebra, raw["cocycle"], hamiltonian, name=name, component_names=names
        )


#: The kinds of system dictionaries and scene [system] tables this module reads.
SYSTEM_KINDS = {AffinePoissonSystem.kind: AffinePoissonSystem.from_dict}
SCENE_KINDS = {"affine": _scene_table}


def __getattr__(name: str) -> Any:
    # AffineIntegrator (and affine_learned, affine_classical) live with the steppers now;
    # importable from here for one release.
    if name in ("AffineIntegrator", "affine_learned", "affine_classical"):
        return provided(f"affine.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _affine_brackets(dim: int) -> Any:
    """π_ij = −Σ_k c_ijk x_k + ω_ij: θ the linear part's −c_ijk, then the constants ω_ij."""
    from ..bracket_family import BracketFamily

    if not 2 <= dim <= 9:
        return None
    pairs = [(i, j) for i in range(dim) for j in range(i + 1, dim)]
    linear = [(i, j, tuple(int(m == k) for m in range(dim))) for i, j in pairs for k in range(dim)]
    constant = [(i, j, (0,) * dim) for i, j in pairs]

    def build(theta: NDArray[np.float64]) -> AffinePoissonSystem:
        c = np.zeros((dim,) * 3)
        for (i, j, e), t in zip(linear, theta, strict=False):
            k = e.index(1)
            c[i, j, k], c[j, i, k] = -t, t
        w = np.zeros((dim, dim))
        for (i, j), t in zip(pairs, theta[len(linear) :], strict=True):
            w[i, j], w[j, i] = t, -t
        zero = Polynomial({(0,) * dim: 0.0})
        return AffinePoissonSystem(LieAlgebra(c), w, zero, name="learned")

    return BracketFamily(
        "affine",
        dim,
        linear + constant,
        build=build,
        description="π_ij = −Σ_k c_ijk x_k + ω_ij, a Lie algebra and a constant 2-cocycle",
    )


BRACKET_FAMILIES = {"affine": _affine_brackets}

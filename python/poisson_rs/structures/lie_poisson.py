"""Lie–Poisson systems on the dual g* of a finite-dimensional Lie algebra g.

A Lie algebra is given by its structure constants, [e_i, e_j] = Σ_k c[i,j,k] e_k, and a system by
a polynomial Hamiltonian H on g* ≅ Rⁿ. The dynamics follow the rigid body's convention (on so(3),
c = ε, they read μ̇ = μ × ∇H):

    μ̇_j = Σ_{i,k} c[i,j,k] ∂H/∂μ_i μ_k = (ad_{∇H}ᵀ μ)_j,   with (ad_x)_{kj} = Σ_i c[i,j,k] x_i.

Named systems: :class:`RigidBody` on so(3)* (H = ½ Σ μᵢ²/Iᵢ) and :class:`HeavyTop` on se(3)*
(μ = (M, Γ), H = ½ Σ Mᵢ²/Iᵢ + mgl χ·Γ). Units are the caller's: μ is a momentum, H an energy, and
time is whatever unit makes μ̇ = {μ, H} consistent with them.

Every class evaluates on NumPy arrays and, differentiably, on torch tensors; torch is imported only
when a tensor arrives.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..protocols import BracketTerms, JetRealization, PoissonSystemBase, provided
from ..untrusted import parsing

__all__ = ["HeavyTop", "LieAlgebra", "LiePoissonSystem", "Polynomial", "RigidBody"]

from .algebra import (  # noqa: F401 (imported from here by other modules)
    MAX_DEGREE,
    FloatArray,
    LieAlgebra,
    Polynomial,
    _as_states,
    _constant,
    _einsum,
    _frozen,
    _inertia,
    _is_tensor,
    _real,
    _real_triple,
    linear_bracket_terms,
)

# --- Lie–Poisson systems -------------------------------------------------------------------------


#: Order of accuracy and whether the step is a Poisson map, for each classical integrator of the
#: rigid body.
CLASSICAL_METHODS: dict[str, tuple[int, bool]] = {
    "rk4": (4, False),
    "midpoint": (2, True),
    "splitting": (2, True),
    "splitting4": (4, True),
    "dmv": (2, True),
    "splitting_casimir": (2, True),
    "dop853": (8, False),
}


#: The same for any other Lie–Poisson system ("splitting": the heavy top only). The implicit
#: midpoint rule keeps quadratic Casimirs and is a Poisson map for quadratic Hamiltonians only.
LIE_POISSON_METHODS: dict[str, tuple[int, bool]] = {
    "rk4": (4, False),
    "midpoint": (2, False),
    "splitting": (2, True),
    "dop853": (8, False),
}


class LiePoissonSystem(PoissonSystemBase):
    """A Lie–Poisson system on g*: an algebra and a polynomial Hamiltonian H on g* ≅ Rⁿ.

    μ̇_j = Σ_{i,k} c[i,j,k] ∂H/∂μ_i μ_k (on so(3): μ̇ = μ × ∇H). Immutable, hashable; equality
    compares the kind, the algebra and H (not the name).

    Parameters
    ----------
    algebra : LieAlgebra
    hamiltonian : Polynomial
        H, with ``hamiltonian.dim == algebra.dim``.
    name : str, optional
    """

    kind: ClassVar[str] = "lie_poisson"
    __setattr__ = _frozen
    __delattr__ = _frozen  # type: ignore[assignment]

    def __init__(
        self, algebra: LieAlgebra, hamiltonian: Polynomial, name: str | None = None
    ) -> None:
        if not isinstance(algebra, LieAlgebra):
            raise TypeError(f"algebra must be a LieAlgebra, got {type(algebra).__name__}")
        if not isinstance(hamiltonian, Polynomial):
            raise TypeError(f"hamiltonian must be a Polynomial, got {type(hamiltonian).__name__}")
        if name is not None and not isinstance(name, str):
            raise ValueError(f"name must be a string or None, got {name!r}")
        self._init_system(algebra, hamiltonian, name)

    def _init_system(self, algebra: LieAlgebra, hamiltonian: Polynomial, name: str | None) -> None:
        if hamiltonian.dim != algebra.dim:
            raise ValueError(
                f"the Hamiltonian has {hamiltonian.dim} variables but the algebra has dimension "
                f"{algebra.dim}"
            )
        object.__setattr__(self, "_algebra", algebra)
        object.__setattr__(self, "_polynomial", hamiltonian)
        object.__setattr__(self, "_name", name)

    @property
    def algebra(self) -> LieAlgebra:
        return self._algebra  # type: ignore[attr-defined,no-any-return]

    @property
    def polynomial(self) -> Polynomial:
        """The Hamiltonian H as a :class:`Polynomial`."""
        return self._polynomial  # type: ignore[attr-defined,no-any-return]

    @property
    def name(self) -> str | None:
        return self._name  # type: ignore[attr-defined,no-any-return]

    @property
    def dim(self) -> int:
        return self.algebra.dim

    @property
    def component_names(self) -> tuple[str, ...]:
        """Names of the state's components, for tables and figures: (M₁, M₂, M₃, Γ₁, Γ₂, Γ₃) on
        se(3)*, (μ_h, μ_e, μ_f) on sl(2)*, else (μ₁, …, μₙ)."""
        kind = _known_algebra(self.algebra)
        if kind == "se3":
            return tuple(f"{b}{_subscript(i)}" for b in ("M", "Γ") for i in range(1, 4))
        if kind == "sl2":
            return ("μ_h", "μ_e", "μ_f")
        return tuple(f"μ{_subscript(i)}" for i in range(1, self.dim + 1))

    def _states(self, mu: Any) -> Any:
        return _as_states(mu, self.dim, "mu")

    def hamiltonian(self, mu: Any) -> Any:
        """H(μ). mu: (..., n) array or torch tensor (differentiable) → (...,)."""
        return self.polynomial(self._states(mu))

    def grad_hamiltonian(self, mu: Any) -> Any:
        """∇H(μ), exact. mu: (..., n) array or torch tensor → (..., n)."""
        return self.polynomial.gradient(self._states(mu))

    def poisson_tensor(self, mu: Any) -> Any:
        """Π(μ) with μ̇ = Π(μ) ∇H: Π_{ji} = Σ_k c[i,j,k] μ_k. mu: (..., n) → (..., n, n)."""
        mu = self._states(mu)
        return _einsum(mu, "ijk,...k->...ji", _constant(mu, self.algebra.c), mu)

    def vector_field(self, mu: Any) -> Any:
        """μ̇_j = Σ_{i,k} c[i,j,k] ∂H/∂μ_i μ_k. mu: (..., n) array or tensor → (..., n)."""
        mu = self._states(mu)
        grad = self.polynomial.gradient(mu)
        return _einsum(mu, "ijk,...i,...k->...j", _constant(mu, self.algebra.c), grad, mu)

    def casimirs(self, mu: Any) -> Any:
        """The known Casimirs at μ, or None when none is known for this algebra.

        so(3): |μ|²; se(3), μ = (M, Γ): (|Γ|², M·Γ); sl(2), μ = (μ_h, μ_e, μ_f): μ_h² + 4μ_eμ_f.

        Parameters
        ----------
        mu : array_like or torch.Tensor, shape (..., n)

        Returns
        -------
        ndarray or torch.Tensor, shape (..., m), or None
        """
        mu = self._states(mu)
        kind = _known_algebra(self.algebra)
        if kind is None:
            return None
        if kind == "so3":
            values = [(mu * mu).sum(-1)]
        elif kind == "se3":
            m, g = mu[..., :3], mu[..., 3:]
            values = [(g * g).sum(-1), (m * g).sum(-1)]
        else:
            values = [mu[..., 0] * mu[..., 0] + 4.0 * mu[..., 1] * mu[..., 2]]
        if _is_tensor(mu):
            import torch

            return torch.stack(values, -1)
        return np.stack(values, -1)

    # --- the PoissonSystem protocol (poisson_rs.protocols) ---------------------------------

    state_symbol: ClassVar[str] = "μ"
    #: A learned S can be trained for it (``poisson_rs.train``, the PINN on T*G).
    trainable: ClassVar[bool] = True

    @property
    def file_inertia(self) -> tuple[float, ...] | None:
        """The principal moments a model file records under "inertia" (its readers before the
        "system" key took the body from them), or None where the file has no such entry."""
        return None

    def bracket_terms(self) -> BracketTerms:
        """π_ij = −Σ_k c[i,j,k] μ_k (linear)."""
        return linear_bracket_terms(self.algebra.c)

    def jet_realization(self, order: int) -> JetRealization:
        """The exact groupoid T*G ⇉ g* in the exponential chart."""
        return JetRealization(
            dim=self.dim, label="exp", exact=True, lie_constants=np.array(self.algebra.c)
        )

    def bivector(self, mu: Any) -> Any:
        """π(μ) = :meth:`poisson_tensor`: (..., n) → (..., n, n)."""
        return self.poisson_tensor(mu)

    def found_casimirs(self, max_degree: int | None = None) -> list[Polynomial]:
        """The polynomial Casimirs of its algebra up to ``max_degree`` (a null space, searched
        once per algebra; see :mod:`poisson_rs.casimirs`), for when :meth:`casimirs` knows
        no closed form."""
        from ..casimirs import DEFAULT_DEGREE, algebra_casimirs

        return algebra_casimirs(self.algebra, DEFAULT_DEGREE if max_degree is None else max_degree)

    @property
    def casimir_label(self) -> str:
        """ "C = |μ|²" (so(3)), "C = |Γ|², M·Γ" (se(3)), "C = μ_h² + 4μ_eμ_f" (sl(2)), or the
        formulas of the polynomial Casimirs the search found ("C = μ₄, μ₁² + μ₂² + μ₃²")."""
        if self.casimirs(np.ones((1, self.dim))) is not None:
            known = {"so3": "C = |μ|²", "se3": "C = |Γ|², M·Γ", "sl2": "C = μ_h² + 4μ_eμ_f"}
            return known.get(_known_algebra(self.algebra) or "", "the system's Casimirs")
        found = self.found_casimirs()
        if not found:
            return "no Casimir known (drift n/a)"
        # By formula: a count alone does not say which invariants the drift measures.
        names = self.component_names
        return "C = " + ", ".join(p.formula(names) for p in found)

    @property
    def title(self) -> str:
        """The system for titles and messages: its name and algebra."""
        name = self.name or type(self).__name__
        pretty = {"so3": "so(3)", "se3": "se(3)", "sl2": "sl(2)"}
        algebra = self.algebra.name
        if algebra in pretty:
            return f"{name} on {pretty[algebra]}*"
        return f"{name} on {algebra}*" if algebra else f"{name} on a {self.dim}-dimensional g*"

    @property
    def demo_states(self) -> FloatArray:
        """Two states for demos: on se(3)* a slow precession and a fast top with |Γ| = 1,
        else the base's two seeded states of norm 2."""
        if _known_algebra(self.algebra) == "se3":
            return np.array([[0.3, -0.8, 1.2, 0.6, 0.0, 0.8], [2.0, 0.5, -1.0, 0.0, 0.6, 0.8]])
        return super().demo_states

    def core_arrays(self) -> tuple[FloatArray, NDArray[np.int64], FloatArray]:
        """Structure constants (n, n, n) and the Hamiltonian's (powers, coeffs) as the Rust core
        takes them, computed once (the system is immutable)."""
        cached = self.__dict__.get("_core_arrays")
        if cached is None:
            powers, coeffs = self.polynomial.to_arrays()
            cached = (np.ascontiguousarray(self.algebra.c, dtype=np.float64), powers, coeffs)
            object.__setattr__(self, "_core_arrays", cached)
        return cached  # type: ignore[no-any-return]

    def step_angles(self, states: np.ndarray, h: float) -> FloatArray:
        """h × the local rate max(‖ad_∇H(μ)‖_F/√2, ‖∂f/∂μ‖_F) at each state (n, n) → (n,),
        in radians (see :attr:`poisson_rs.RolloutInfo.step_angle`)."""
        from .. import _core

        c, powers, coeffs = self.core_arrays()
        return _core.step_angles(c, powers, coeffs, states, h)  # type: ignore[no-any-return]

    def taylor_charts(self) -> tuple[str, ...]:
        """("exp",): the exponential chart of T*G exists for every algebra."""
        return ("exp",)

    def taylor_integrator(
        self, order: int, chart: str | None = None, *, tol: float, max_iter: int
    ) -> Any:
        chart = self.chart_or_default(chart)
        return provided("lie_poisson.taylor")(self, order, chart, tol=tol, max_iter=max_iter)

    def learn_modes(self) -> tuple[str, ...]:
        """Every mode of :func:`poisson_rs.learn`: H through Taylor-HJ on T*G, the time-h map's
        generating function, a correction to a known H."""
        return ("auto", "hamiltonian", "map", "hj+data")

    def hamiltonian_family(self, degree: int, order: int | None = None) -> Any:
        """Polynomials in μ of ``degree`` (no constant), stepped by Taylor-HJ of ``order``
        (default 7 for degree ≤ 2, else 5) in the exponential chart."""
        from ..hamiltonian_family import MonomialFamily, monomial_exponents

        algebra, n = self.algebra, self.algebra.dim
        k = order or (7 if degree <= 2 else 5)

        def build(terms: Mapping[tuple[int, ...], float]) -> LiePoissonSystem:
            return LiePoissonSystem(algebra, Polynomial(dict(terms) or {(0,) * n: 0.0}))

        return MonomialFamily(
            n,
            monomial_exponents(n, degree),
            order=k,
            chart="exp",
            build=build,
            gauge="a Casimir of the algebra",
            variables=[f"μ{i + 1}" for i in range(n)],
        )

    @property
    def method_table(self) -> Mapping[str, tuple[int, bool]]:
        """Each classical integrator's (order, whether a step is a Poisson map) for this system:
        the generic methods ("splitting" belongs to the systems that have one)."""
        return {m: v for m, v in LIE_POISSON_METHODS.items() if m != "splitting"}

    def classical_methods(self) -> list[str]:
        return list(self.method_table)

    @property
    def splitting_parameters(self) -> tuple[Any, ...] | None:
        """What the core's explicit splitting of this system takes, or None where it has none."""
        return None

    def classical_rollout(
        self,
        name: str,
        mu0: Any,
        h: float,
        n_steps: int,
        every: int,
        tol: float,
        max_iter: int,
        lazy: bool,
    ) -> tuple[np.ndarray, Any] | None:
        """The core's rollout of classical integrator ``name`` (not "dop853"): ``(traj,
        diagnostics)``, None where ``mu0`` is a list that is not one state of plain numbers."""
        return self._core_classical(name)(  # type: ignore[no-any-return]
            mu0, h, n_steps, every, tol, max_iter, lazy
        )

    def _core_classical(self, name: str) -> Callable[..., Any]:
        """The core's rollout of ``name`` for this system, taking (mu0, h, n_steps, every, tol,
        max_iter, lazy): the generic Lie–Poisson kernels (and the system's own splitting)."""
        from .. import _core

        c, powers, coeffs = self.core_arrays()
        top = self.splitting_parameters if name == "splitting" else None

        def run(mu0: Any, h: float, n: int, every: int, tol: float, it: int, lazy: bool) -> Any:
            return _core.rollout_lie_poisson(
                name, c, powers, coeffs, mu0, h, n, every, tol, it, top, lazy
            )

        return run

    def classical(self, name: str, *, tol: float, max_iter: int) -> Any:
        return provided("lie_poisson.classical")(self, name, tol=tol, max_iter=max_iter)

    def reference_solution(
        self,
        x0: ArrayLike,
        times: ArrayLike,
        *,
        rtol: float = 1e-13,
        atol: float = 1e-13,
        failures: Literal["raise", "nan"] = "raise",
    ) -> FloatArray:
        return provided("lie_poisson_reference")(
            self, x0, times, rtol=rtol, atol=atol, failures=failures
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form with a "kind" key ("lie_poisson", "rigid_body" or "heavy_top")."""
        return {
            "kind": self.kind,
            "name": self.name,
            "algebra": self.algebra.to_dict(),
            "hamiltonian": self.polynomial.to_dict(),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> LiePoissonSystem:
        """Rebuild any system from :meth:`to_dict`; called on a subclass, the kind must match."""
        with parsing("system dictionary"):
            return cls._from_dict(data)

    @classmethod
    def _from_dict(cls, data: Mapping[str, Any]) -> LiePoissonSystem:
        if not isinstance(data, Mapping) or "kind" not in data:
            raise ValueError("a system dictionary needs a 'kind' entry")
        kinds: dict[str, type[LiePoissonSystem]] = {
            "lie_poisson": LiePoissonSystem,
            "rigid_body": RigidBody,
            "heavy_top": HeavyTop,
        }
        kind = data["kind"]
        if kind not in kinds:
            raise ValueError(f"unknown system kind {kind!r}; expected one of {tuple(kinds)}")
        if cls is not LiePoissonSystem and kinds[kind] is not cls:
            raise ValueError(f"expected a {cls.kind!r} dictionary, got kind {kind!r}")
        try:
            if kind == "rigid_body":
                return RigidBody(data["inertia"])
            if kind == "heavy_top":
                return HeavyTop(data["inertia"], data["mgl"], data["com"])
            return LiePoissonSystem(
                LieAlgebra.from_dict(data["algebra"]),
                Polynomial.from_dict(data["hamiltonian"]),
                name=data.get("name"),
            )
        except KeyError as exc:
            raise ValueError(f"a {kind!r} dictionary needs a {exc.args[0]!r} entry") from None

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, LiePoissonSystem):
            return NotImplemented
        return (
            type(self) is type(other)
            and self.algebra == other.algebra
            and self.polynomial == other.polynomial
        )

    def __hash__(self) -> int:
        return hash((type(self).__name__, self.algebra, self.polynomial))

    def __repr__(self) -> str:
        return (
            f"LiePoissonSystem({self.algebra!r}, degree-{self.polynomial.degree} Hamiltonian with "
            f"{len(self.polynomial.terms)} terms, name={self.name!r})"
        )


def _subscript(i: int) -> str:
    """``i`` in subscript digits: 12 → "₁₂"."""
    return str(i).translate(str.maketrans("0123456789", "₀₁₂₃₄₅₆₇₈₉"))


def _known_algebra(algebra: LieAlgebra) -> str | None:
    """ "so3", "se3" or "sl2" when ``algebra`` has exactly those constants, else None."""
    for name in ("so3", "se3", "sl2"):
        if algebra == _STANDARD[name]:
            return name
    return None


_STANDARD = {"so3": LieAlgebra.so3(), "se3": LieAlgebra.se3(), "sl2": LieAlgebra.sl2()}


@dataclass(frozen=True)
class RigidBody(LiePoissonSystem):
    """Free rigid body on so(3)*: H(μ) = ½ Σ μᵢ²/Iᵢ, μ̇ = μ × (μ/I).

    Attributes
    ----------
    inertia : tuple[float, float, float]
        Principal moments of inertia (I₁, I₂, I₃), any order, all > 0; stored as a tuple of
        floats. Equality and hashing go by it.
    """

    kind: ClassVar[str] = "rigid_body"
    inertia: tuple[float, float, float] = (1.5, 2.0, 2.5)

    @property
    def file_inertia(self) -> tuple[float, ...] | None:
        return self.inertia

    def __post_init__(self) -> None:
        values = _inertia(self.inertia)
        object.__setattr__(self, "inertia", values)
        weights = [1.0 / v for v in values]
        self._init_system(_STANDARD["so3"], Polynomial.quadratic_diagonal(weights), "rigid_body")

    def _inverse_inertia(self) -> FloatArray:
        return 1.0 / np.asarray(self.inertia, dtype=np.float64)

    def hamiltonian(self, mu: Any) -> Any:
        """Kinetic energy H(μ) = ½ Σ μᵢ²/Iᵢ.

        Parameters
        ----------
        mu : array_like or torch.Tensor, shape (..., 3)
            Body angular momenta.

        Returns
        -------
        ndarray or torch.Tensor, shape (...,)
        """
        m = _as_states(mu, 3)
        inv = _constant(m, self._inverse_inertia())
        return 0.5 * (m * m * inv).sum(-1)

    def casimir(self, mu: Any) -> Any:
        """Casimir C(μ) = |μ|². mu: (..., 3) → (...,)."""
        m = _as_states(mu, 3)
        return (m * m).sum(-1)

    def grad_hamiltonian(self, mu: Any) -> Any:
        """Angular velocity ∇H(μ) = μ/I (elementwise). mu: (..., 3) → (..., 3)."""
        m = _as_states(mu, 3)
        return m * _constant(m, self._inverse_inertia())

    def vector_field(self, mu: Any) -> Any:
        """Euler's equations μ̇ = μ × (μ/I). mu: (..., 3) → (..., 3)."""
        m = _as_states(mu, 3)
        if _is_tensor(m):
            import torch

            return torch.linalg.cross(m, self.grad_hamiltonian(m), dim=-1)
        return np.cross(m, m * self._inverse_inertia())

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "inertia": list(self.inertia)}

    def _directions(self) -> dict[str, FloatArray]:
        """Circulating about the smallest- and the largest-inertia axis, and within 1e-2 of the
        separatrix (on the smallest-axis side), as unit vectors."""
        i1, i2, i3 = self.inertia
        # On the unit sphere the separatrix is d₁²(I₂/I₁ − 1) = d₃²(1 − I₂/I₃) (with d₂ small).
        a, c = abs(i2 / i1 - 1.0), abs(1.0 - i2 / i3)
        out = {
            "axis 1 side": np.array([0.9, 0.3, 0.3]),
            "axis 3 side": np.array([0.3, 0.3, 0.9]),
            "separatrix": np.array([1.0, 0.05, np.sqrt(a / c) * (1.0 - 1e-2)]),
        }
        return {k: v / np.linalg.norm(v) for k, v in out.items()}

    @property
    def title(self) -> str:
        return f"free rigid body, I = {tuple(float(i) for i in self.inertia)}"

    @property
    def demo_states(self) -> FloatArray:
        """The paper's two states, (1, 1, 2) and (3, 2, 0)."""
        return np.array([[1.0, 1.0, 2.0], [3.0, 2.0, 0.0]])

    def taylor_charts(self) -> tuple[str, ...]:
        """("cayley", "exp"): the Cayley chart's closed forms exist for the rigid body only."""
        return ("cayley", "exp")

    @property
    def method_table(self) -> Mapping[str, tuple[int, bool]]:
        """The rigid body's own splittings and DMV beside the generic methods, and the midpoint
        rule a Poisson map (H is quadratic)."""
        return CLASSICAL_METHODS

    def _core_classical(self, name: str) -> Callable[..., Any]:
        """The core's closed-form rigid-body kernels (Euler's equations written out)."""
        from .. import _core

        return functools.partial(_core.rollout_classical, name, self.inertia)

    def reference_solution(
        self,
        x0: ArrayLike,
        times: ArrayLike,
        *,
        rtol: float = 1e-13,
        atol: float = 1e-13,
        failures: Literal["raise", "nan"] = "raise",
    ) -> FloatArray:
        """DOP853 on Euler's equations written out (:func:`~poisson_rs.dop853_solution`)."""
        return provided("dop853_solution")(self, x0, times, rtol, atol, failures=failures)

    def reference(self, x0: np.ndarray, times: ArrayLike) -> FloatArray:
        """The closed form in Jacobi elliptic functions."""
        return provided("exact_solution")(self, x0, times)

    reference_name: ClassVar[str] = "exact flow"


@dataclass(frozen=True)
class HeavyTop(LiePoissonSystem):
    """Heavy top on se(3)*, μ = (M, Γ) ∈ R⁶: body angular momentum M and the direction of gravity
    in the body frame Γ.

    H = ½ Σ Mᵢ²/Iᵢ + mgl χ·Γ, so Ṁ = M × Ω + mgl Γ × χ and Γ̇ = Γ × Ω with Ω = M/I. Casimirs |Γ|²
    and M·Γ.

    Attributes
    ----------
    inertia : tuple[float, float, float]
        Principal moments of inertia about the fixed point, all > 0.
    mgl : float
        Mass × gravity × distance from the fixed point to the centre of mass (energy), ≥ 0.
    com : tuple[float, float, float]
        χ, the unit-less direction of the centre of mass in the body frame (finite).
    """

    kind: ClassVar[str] = "heavy_top"
    inertia: tuple[float, float, float] = (1.0, 1.5, 2.0)
    mgl: float = 0.981
    com: tuple[float, float, float] = (0.0, 0.0, 1.0)

    def __post_init__(self) -> None:
        inertia = _inertia(self.inertia)
        mgl = _real(self.mgl, "mgl")
        if mgl < 0.0:
            raise ValueError(f"mgl must be non-negative, got {mgl}")
        com = _real_triple(self.com, "com")
        if not all(math.isfinite(v) for v in com):
            raise ValueError(f"com entries must be finite, got {com}")
        object.__setattr__(self, "inertia", inertia)
        object.__setattr__(self, "mgl", mgl)
        object.__setattr__(self, "com", com)
        terms: dict[tuple[int, ...], float] = {}
        for i in range(3):
            terms[tuple(2 if j == i else 0 for j in range(6))] = 0.5 / inertia[i]
            terms[tuple(1 if j == 3 + i else 0 for j in range(6))] = mgl * com[i]
        self._init_system(_STANDARD["se3"], Polynomial(terms), "heavy_top")

    @property
    def title(self) -> str:
        return f"heavy top, I = {self.inertia}, mgl = {self.mgl:g}, χ = {self.com}"

    @property
    def method_table(self) -> Mapping[str, tuple[int, bool]]:
        """The generic methods and the heavy top's own explicit Poisson splitting."""
        return LIE_POISSON_METHODS

    @property
    def splitting_parameters(self) -> tuple[Any, ...] | None:
        """(inertia, mgl, χ): the splitting's free rotor and gravity flows."""
        return (self.inertia, self.mgl, self.com)

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "inertia": list(self.inertia),
            "mgl": self.mgl,
            "com": list(self.com),
        }


#: Standard algebras a table may name instead of giving structure constants.
NAMED_ALGEBRAS = ("so3", "se3", "sl2")

#: The keys a scene [system] table of each Lie–Poisson kind takes.
_SCENE_KEYS = {
    "rigid_body": ("kind", "inertia"),
    "heavy_top": ("kind", "inertia", "mgl", "com"),
    "lie_poisson": ("kind", "name", "algebra", "hamiltonian"),
}


def _scene_table(raw: Mapping[str, Any]) -> LiePoissonSystem:
    """A Lie–Poisson [system] table: ``kind = "rigid_body"`` (``inertia``), ``"heavy_top"``
    (``inertia``, ``mgl``, ``com``) or ``"lie_poisson"`` (``algebra``: a name of
    :data:`NAMED_ALGEBRAS` or a LieAlgebra.to_dict() table, ``hamiltonian``: a
    Polynomial.to_dict() table, optional ``name``)."""
    from functools import partial

    from ..tables import number, only_keys, required
    from ..untrusted import parsing

    kind = raw.get("kind", "lie_poisson" if "algebra" in raw else "rigid_body")
    only_keys(raw, _SCENE_KEYS[kind], kind)
    if kind == "rigid_body":
        required(raw, "inertia")
    for key in ("inertia", "com"):
        if key in raw:
            value = raw[key]
            if not isinstance(value, list) or len(value) != 3:
                raise ValueError(f"scene key 'system.{key}' must be 3 numbers, got {value!r}")
            number_ = number if key == "inertia" else partial(number, positive=False)
            raw = {**raw, key: [number_(v, f"system.{key}") for v in value]}
    if isinstance(raw.get("algebra"), str):
        name = raw["algebra"]
        if name not in NAMED_ALGEBRAS:
            raise ValueError(
                f"scene key 'system.algebra' = {name!r} is not one of {NAMED_ALGEBRAS}; give "
                "the structure constants as a table instead"
            )
        raw = {**raw, "algebra": getattr(LieAlgebra, name)().to_dict()}
    with parsing("scene", "system"):
        return LiePoissonSystem.from_dict({**raw, "kind": kind})


#: The kinds of system dictionaries and scene [system] tables this module reads.
SYSTEM_KINDS = {
    kind: LiePoissonSystem.from_dict for kind in ("lie_poisson", "rigid_body", "heavy_top")
}
SCENE_KINDS = {kind: _scene_table for kind in _SCENE_KEYS}


def _lie_brackets(dim: int) -> Any:
    """π_ij = −Σ_k c_ijk x_k (θ = −c_ijk, i < j, every k): Jacobi is the algebra's."""
    from ..bracket_family import BracketFamily

    if not 2 <= dim <= 10:
        return None
    terms = [
        (i, j, tuple(int(m == k) for m in range(dim)))
        for i in range(dim)
        for j in range(i + 1, dim)
        for k in range(dim)
    ]

    def build(theta: NDArray[np.float64]) -> LiePoissonSystem:
        c = np.zeros((dim,) * 3)
        for (i, j, e), t in zip(terms, theta, strict=True):
            k = e.index(1)
            c[i, j, k], c[j, i, k] = -t, t
        return LiePoissonSystem(LieAlgebra(c), Polynomial({(0,) * dim: 0.0}), name="learned")

    return BracketFamily(
        "lie-poisson",
        dim,
        terms,
        build=build,
        description="π_ij = −Σ_k c_ijk x_k, c the structure constants of a Lie algebra",
    )


BRACKET_FAMILIES = {"lie-poisson": _lie_brackets}

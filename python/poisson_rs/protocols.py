"""The two protocols the package is written against: a Poisson system and a stepper.

Generic code (``integrate``, the studies, the scenes, the CLI, ``reference_solution``) never
names a structure: it asks a :class:`PoissonSystem` what it is (dimension, bivector, H,
Casimirs, domain, labels) and what it has (Taylor-HJ integrators in its charts, classical
methods, a reference flow), and drives any :class:`Stepper` through :meth:`Stepper.rollout`.
Every structure of the package implements :class:`PoissonSystem` once, in its own module
(:mod:`poisson_rs.structures`); a user's own stepper implements :class:`Stepper` and runs through
``integrate``, ``chart``, ``stability`` and ``select`` like the package's own.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal, Protocol, TypeVar, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: Newton's defaults for every implicit step of every structure: accept a step once the
#: relative Newton update is below ``NEWTON_TOL`` (round-off), give up after ``NEWTON_MAX_ITER``
#: updates.
NEWTON_TOL = 1e-12
NEWTON_MAX_ITER = 50

#: Keys of the diagnostics a rollout returns, each an array of shape (n,) (see
#: :class:`poisson_rs.RolloutInfo`); a stepper may leave out any of them and ``integrate`` fills
#: in what it can infer from the trajectory (non-finite states), "unknown" (NaN) elsewhere.
ROLLOUT_KEYS = (
    "converged",
    "failed_step",
    "failure_code",
    "newton_iterations",
    "max_newton_iterations",
    "max_residual",
    "step_angle",
)


# A structure module sits below its steppers and its reference solution, yet its methods
# (``taylor_integrator``, ``classical``, ``reference_solution``) build them: the modules that
# define those register them here by name, so that imports point one way (structures up to
# steppers) and a structure finds its builders at call time. The package's ``__init__`` imports
# every registering module before any method can be called.
_PROVIDED: dict[str, Callable[..., Any]] = {}

_F = TypeVar("_F", bound=Callable[..., Any])


def provides(name: str) -> Callable[[_F], _F]:
    """Registers the decorated function or class as the builder ``name`` (e.g.
    "lie_poisson.taylor"); RuntimeError for a name registered twice."""

    def register(f: _F) -> _F:
        if name in _PROVIDED:
            raise RuntimeError(f"builder {name!r} is registered twice")
        _PROVIDED[name] = f
        return f

    return register


def provided(name: str) -> Callable[..., Any]:
    """The builder registered as ``name``."""
    try:
        return _PROVIDED[name]
    except KeyError:
        raise RuntimeError(f"no builder {name!r} is registered (import poisson_rs)") from None


def system_label(system: Any) -> str:
    """The system for titles and messages: its ``title`` (kind and parameters, or its name)."""
    title = getattr(system, "title", None)
    return (
        title
        if isinstance(title, str)
        else f"{getattr(system, 'name', None) or type(system).__name__}"
    )


@runtime_checkable
class Stepper(Protocol):
    """Anything :func:`poisson_rs.integrate` can drive.

    ``dim`` is the state dimension. ``rollout(x0, h, n_steps, every)`` advances ``x0`` (n, dim)
    float64, already checked (finite, in range), by ``n_steps`` steps of size ``h`` and returns
    ``(traj, info)``: ``traj`` (n, n_steps // every + 1, dim) float64 with the states 0, every,
    2·every, ... (a trajectory that fails is NaN from its failure on), and ``info`` a dict of
    (n,) arrays keyed by :data:`ROLLOUT_KEYS` (any subset, possibly empty). Optional
    attributes the tools read when present: ``name`` (str), ``order`` (int), ``poisson``
    (bool), ``system`` (a :class:`PoissonSystem`), ``h_max`` (float).
    """

    @property
    def dim(self) -> int: ...

    def rollout(
        self, x0: np.ndarray, h: float, n_steps: int, every: int
    ) -> tuple[np.ndarray, Mapping[str, np.ndarray]]: ...


@runtime_checkable
class PoissonSystem(Protocol):
    """A Hamiltonian system on a Poisson manifold, ẋ = π(x)∇H(x), as every tool sees it.

    States are float64 arrays (dim,) or (n, dim); every method taking states accepts both and
    answers per state. "n/a" is ``None``: a system that knows no Casimir returns ``None`` from
    :meth:`casimirs`, never zeros.
    """

    @property
    def kind(self) -> str:
        """A short name of the structure family ("lie_poisson", "log_canonical", ...), as
        scenes and files spell it."""
        ...

    @property
    def dim(self) -> int: ...

    @property
    def component_names(self) -> tuple[str, ...]:
        """A name per coordinate, for tables and figures."""
        ...

    @property
    def state_symbol(self) -> str:
        """The symbol of a state in labels: "μ" on g*, "x" elsewhere."""
        ...

    def hamiltonian(self, x: Any) -> Any: ...

    def vector_field(self, x: Any) -> Any: ...

    def bivector(self, x: Any) -> Any:
        """π(x), (…, dim, dim), antisymmetric, with ẋ = π(x)∇H(x)."""
        ...

    def casimirs(self, x: Any) -> Any:
        """The known Casimirs at x, (…, k), or None when none is known ("n/a")."""
        ...

    @property
    def casimir_label(self) -> str:
        """How figures name the Casimirs ("|μ|²", "u v⁻²", ...); "" when none is known."""
        ...

    @property
    def title(self) -> str:
        """The system for titles and messages: its kind and parameters, or its name."""
        ...

    @property
    def demo_states(self) -> np.ndarray:
        """Two states for demos, (2, dim), in the domain."""
        ...

    @property
    def sample_radii(self) -> tuple[float, ...]:
        """The sizes :meth:`sample_states` takes by default."""
        ...

    def domain_text(self) -> str:
        """The domain in words, for messages ("finite", "open positive orthant ...")."""
        ...

    def check_states(self, x: ArrayLike, name: str = "x0") -> np.ndarray:
        """``x`` as a float64 array of states, ValueError naming ``name`` for a state outside
        the system's domain (e.g. the positive orthant) or not finite."""
        ...

    def in_domain(self, x: np.ndarray) -> np.ndarray:
        """(n,) bool: which states (n, dim) lie in the system's domain."""
        ...

    def sample_states(self, radii: Sequence[float]) -> tuple[np.ndarray, list[str]]:
        """Test states for stability studies, at the given sizes, and their labels."""
        ...

    def taylor_charts(self) -> tuple[str, ...]:
        """The charts of the realization its Taylor-HJ integrators are built in; the first is
        the default."""
        ...

    def taylor_orders(self, wanted: Sequence[int]) -> tuple[int, ...]:
        """The orders of ``wanted`` its Taylor-HJ series is built for."""
        ...

    def taylor_integrator(
        self, order: int, chart: str | None = None, *, tol: float, max_iter: int
    ) -> Stepper:
        """The Taylor-HJ integrator of ``order`` in ``chart`` (default: the first chart)."""
        ...

    def classical_methods(self) -> list[str]:
        """The names :meth:`classical` accepts, exactly."""
        ...

    def classical(self, name: str, *, tol: float, max_iter: int) -> Stepper:
        """The classical integrator ``name`` (``tol`` is DOP853's rtol = atol there)."""
        ...

    def reference_solution(
        self,
        x0: ArrayLike,
        times: ArrayLike,
        *,
        rtol: float,
        atol: float,
        failures: Literal["raise", "nan"],
    ) -> np.ndarray:
        """The flow at ``times`` by DOP853, (T, dim) or (n, T, dim)."""
        ...

    def reference(self, x0: np.ndarray, times: ArrayLike) -> np.ndarray:
        """The best reference flow the system has (closed form where there is one, else
        DOP853 at 1e-13), (n, T, dim) for states (n, dim)."""
        ...

    @property
    def reference_name(self) -> str:
        """What :meth:`reference` is, for labels ("exact flow", "DOP853")."""
        ...

    def to_dict(self) -> dict[str, Any]: ...


def as_system(system: Any, name: str = "system") -> PoissonSystem:
    """``system`` itself when it implements :class:`PoissonSystem`, else one TypeError naming
    ``name`` and the first missing member."""
    missing = [m for m in _SYSTEM_MEMBERS if not hasattr(system, m)]
    if missing:
        raise TypeError(
            f"{name} must be a Poisson system (poisson_rs.PoissonSystem), got "
            f"{type(system).__name__}, which has no {missing[0]!r}"
        )
    return system


def as_stepper(stepper: Any, name: str = "stepper") -> Stepper:
    """``stepper`` itself when it implements :class:`Stepper`, else one TypeError naming
    ``name``."""
    if not (hasattr(stepper, "rollout") and hasattr(stepper, "dim")):
        raise TypeError(
            f"{name} must be an integrator (poisson_rs.Stepper: a `dim` and a "
            f"`rollout(x0, h, n_steps, every)`), got {type(stepper).__name__}"
        )
    return stepper


_SYSTEM_MEMBERS = (
    "dim",
    "kind",
    "hamiltonian",
    "vector_field",
    "bivector",
    "casimirs",
    "taylor_integrator",
    "classical_methods",
    "classical",
    "reference_solution",
)


def unit_directions(dim: int, count: int = 3) -> dict[str, np.ndarray]:
    """``count`` fixed unit directions in R^dim (seeded, the same on every call), labelled
    "direction 1", ...: the test directions of a system without special geometry."""
    rng = np.random.default_rng(20240601)
    out = {f"direction {k + 1}": rng.normal(size=dim) for k in range(count)}
    return {k: v / np.linalg.norm(v) for k, v in out.items()}


#: (index, coeffs, exponents) of polynomials for the core.
TermTable = tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.int64]]


@dataclass(frozen=True)
class BracketTerms:
    """π's upper triangle (π_ij, i < j, row by row) as one term table for the core: term m adds
    ``coeffs[m] · x^exponents[m]`` to entry ``index[m]``; exponents (M, dim)."""

    index: NDArray[np.int64]
    coeffs: NDArray[np.float64]
    exponents: NDArray[np.int64]

    @classmethod
    def from_terms(
        cls, dim: int, terms: Sequence[tuple[int, int, Sequence[int], float]]
    ) -> BracketTerms:
        """From (i, j, exponents, coefficient) with i < j."""
        pair = {(i, j): k for k, (i, j) in enumerate(itertools.combinations(range(dim), 2))}
        rows = [(pair[(i, j)], c, list(e)) for i, j, e, c in terms if c != 0.0]
        return cls(
            np.array([r[0] for r in rows], dtype=np.int64),
            np.array([r[1] for r in rows], dtype=np.float64),
            np.array([r[2] for r in rows], dtype=np.int64).reshape(len(rows), dim),
        )

    def tables(self) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.int64]]:
        return self.index, self.coeffs, self.exponents


@dataclass(frozen=True)
class JetRealization:
    """The realization Taylor-HJ by jets steps a system on: ``lie_constants`` (dim, dim, dim)
    of a Lie algebra (its exact groupoid, exponential chart), or the polynomial maps ``sou``
    (β) and ``tar`` (α) as (index, coeffs, exponents (M, 2·dim)) tables in (p, x). ``dim`` may
    exceed the system's: the extra coordinates are central, held at 1 (an affine bracket's
    extension); H sees the system's own coordinates only. ``exact``: whether it is an exact
    realization (Casimirs kept to round-off)."""

    dim: int
    label: str
    exact: bool
    lie_constants: NDArray[np.float64] | None = None
    sou: TermTable | None = None
    tar: TermTable | None = None


class PoissonSystemBase:
    """What most structures share of :class:`PoissonSystem`, for a structure to inherit and
    override: states anywhere finite in R^dim, three seeded test directions, every Taylor
    order, DOP853 as the reference. A subclass supplies ``dim``, ``taylor_charts`` and the
    methods that make integrators."""

    #: How labels write a state.
    state_symbol = "x"
    #: What :meth:`reference` is.
    reference_name = "DOP853"
    #: Whether a learned S can be trained for it with ``poisson_rs.train``.
    trainable = False
    #: Sizes of the states a stability study starts from (|x| for most structures).
    sample_radii: tuple[float, ...] = (1.0, 2.5, 4.0, 6.0)

    @property
    def dim(self) -> int:
        raise NotImplementedError

    def in_domain(self, x: np.ndarray) -> np.ndarray:
        """(n,) bool: finite states (the whole of R^dim)."""
        return np.asarray(np.isfinite(np.asarray(x, dtype=np.float64)).all(axis=-1))

    def domain_text(self) -> str:
        """The domain in words, for error messages."""
        return "finite"

    def check_states(self, x: ArrayLike, name: str = "x0") -> np.ndarray:
        arr = np.asarray(x, dtype=np.float64)
        if arr.ndim not in (1, 2) or arr.shape[-1] != self.dim:
            raise ValueError(
                f"{name} must have shape ({self.dim},) or (n, {self.dim}), got {arr.shape}"
            )
        ok = self.in_domain(arr.reshape(-1, self.dim))
        if not ok.all():
            k = int(np.flatnonzero(~ok)[0])
            raise ValueError(
                f"{name} must be {self.domain_text()} states: state {k} is "
                f"{arr.reshape(-1, self.dim)[k].tolist()}"
            )
        return arr

    def _directions(self) -> dict[str, np.ndarray]:
        return unit_directions(self.dim)

    def sample_states(self, radii: Sequence[float]) -> tuple[np.ndarray, list[str]]:
        """Every direction of :meth:`_directions` at every radius |x| = r in ``radii``."""
        rows, labels = [], []
        for r in radii:
            for label, d in self._directions().items():
                rows.append(r * d)
                labels.append(f"|{self.state_symbol}|={r:g}, {label}")
        return np.array(rows), labels

    @property
    def demo_states(self) -> np.ndarray:
        """Two states for demos, (2, dim): seeded, of norm 2 (the same on every run)."""
        rng = np.random.default_rng(20240601)
        states = rng.normal(size=(2, self.dim))
        return 2.0 * states / np.linalg.norm(states, axis=1, keepdims=True)

    @property
    def title(self) -> str:
        """The system for titles and messages."""
        return str(getattr(self, "name", None) or type(self).__name__)

    def taylor_charts(self) -> tuple[str, ...]:
        raise NotImplementedError

    def taylor_orders(self, wanted: Sequence[int]) -> tuple[int, ...]:
        return tuple(wanted)

    def chart_or_default(self, chart: str | None) -> str:
        """``chart`` when the system has it, the first of :meth:`taylor_charts` for None;
        ValueError naming the charts it has otherwise."""
        charts = self.taylor_charts()
        if chart is None:
            return charts[0]
        if chart not in charts:
            raise ValueError(
                f"chart {chart!r} is not available for {self!r}; its charts: {', '.join(charts)}"
            )
        return chart

    def learn_modes(self) -> tuple[str, ...]:
        """The modes of :func:`poisson_rs.learn` that apply to this structure, "auto" first;
        () where none does (H cannot be fitted on it through its integrator)."""
        return ()

    def hamiltonian_family(self, degree: int, order: int | None = None) -> Any:
        """The Hamiltonians :func:`poisson_rs.learn` fits on this structure (its own H is
        ignored): a :class:`poisson_rs.hamiltonian_family.MonomialFamily`-like value of
        total ``degree``, stepped by the structure's Taylor-HJ integrator of ``order``
        (default: the structure's choice). ValueError where :meth:`learn_modes` is empty."""
        raise ValueError(
            f"structure: H cannot be learned on {self.title} (it offers no Hamiltonian family)"
        )

    def learn_degrees(self) -> tuple[int, ...]:
        """The degrees of :meth:`hamiltonian_family` mode "auto" tries, smallest first."""
        return (2, 3, 4)

    def learn_orders(self) -> tuple[int, ...]:
        """The Taylor-HJ orders :meth:`hamiltonian_family` accepts."""
        return tuple(self.taylor_orders(range(1, 13)))

    def reference(self, x0: np.ndarray, times: ArrayLike) -> np.ndarray:
        """DOP853 at rtol = atol = 1e-13."""
        return self.reference_solution(x0, times)  # type: ignore[attr-defined]

    def bracket_terms(self) -> BracketTerms:
        """π as polynomials, for a Hamiltonian given as an expression
        (:func:`poisson_rs.with_hamiltonian`); NotImplementedError where π is not polynomial."""
        raise NotImplementedError(
            f"{self.title} does not give its bracket as polynomials, so it takes no expression "
            "Hamiltonian"
        )

    def jet_realization(self, order: int) -> JetRealization:
        """The realization Taylor-HJ by jets of ``order`` steps on; NotImplementedError where
        the structure has none for jets."""
        raise NotImplementedError(
            f"{self.title} has no realization for Taylor-HJ by jets; its classical methods "
            "(rk4, midpoint, dop853) take an expression Hamiltonian"
        )

    def steps_expressions_by_jets(self) -> bool:
        """Whether :meth:`expression_system` steps an expression H by Taylor-HJ by jets (the
        term libraries of ``pr.learn`` need it): here, where :meth:`jet_realization` exists."""
        try:
            self.jet_realization(1)
        except (NotImplementedError, ValueError):
            return False
        return True

    def expression_system(self, hamiltonian: str, *, name: str | None = None) -> Any:
        """This bracket with the expression ``hamiltonian`` (in the component names or
        x1 … xn), where the structure builds it as its own kind (a charged particle in a
        non-polynomial field keeps B and A). NotImplementedError here: the generic wrapper
        :func:`poisson_rs.with_hamiltonian` builds it from :meth:`bracket_terms` and
        :meth:`jet_realization` instead."""
        raise NotImplementedError(f"{self.title} has no expression systems of its own kind")

"""Any structure with a Hamiltonian that is not a polynomial: H as an expression
(:mod:`poisson_rs.expressions`) on the bracket of another system.

The bracket comes from the structure through the protocol (:meth:`bracket_terms` for the vector
field ẋ = π(x)∇H(x), :meth:`jet_realization` for Taylor-HJ by jets); nothing here names a family.
The Casimirs are the structure's (they belong to the bracket, not to H). Every classical method
(RK4 and the implicit midpoint rule in the Rust core, DOP853) runs on the field; Taylor-HJ of
any order runs by jets on the structure's realization (exact on Lie–Poisson and affine brackets
and on constant ones).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..distance_sums import DistanceTerms, distance_terms
from ..expressions import (
    Expression,
    ExpressionError,
    FieldProgram,
    default_names,
    field_program,
)
from ..protocols import (
    NEWTON_MAX_ITER,
    NEWTON_TOL,
    BracketTerms,
    JetRealization,
    PoissonSystemBase,
    Stepper,
    as_system,
    provided,
)

FloatArray = NDArray[np.float64]

#: Highest Taylor order by jets (the core's ``MAX_JET_ORDER``).
MAX_JET_ORDER = 8
#: Highest order the studies (demo, chart, select) run by default: a jet step costs about 10×
#: more per two orders (docs/hamiltonians.md).
STUDY_JET_ORDER = 3
#: The classical methods on the field: (order, Poisson map).
FIELD_METHODS: dict[str, tuple[int, bool]] = {
    "rk4": (4, False),
    "midpoint": (2, False),
    "dop853": (8, False),
}


class ExpressionSystem(PoissonSystemBase):
    """The bracket of ``structure`` (any system) with the Hamiltonian ``hamiltonian``: an
    expression in the structure's component names or x1 … xn (see
    :mod:`poisson_rs.expressions`). ValueError naming 'hamiltonian' for a text outside the
    grammar; ValueError naming 'structure' for one whose bracket is not polynomial.

    ``distances``: H read as a sum over distances (:mod:`poisson_rs.distance_sums`), whose
    gradient the core runs as compiled code for RK4 and the midpoint rule, or None (the field
    program is interpreted)."""

    kind = "expression"

    def __init__(
        self,
        structure: Any,
        hamiltonian: str | Expression | Callable[[Any], Any],
        *,
        name: str | None = None,
    ) -> None:
        base = as_system(structure, "structure")
        names = tuple(base.component_names)
        if isinstance(hamiltonian, Expression):
            text = hamiltonian.text
        elif callable(hamiltonian):
            from ..expression_tracing import trace_hamiltonian, tracing_names

            text = trace_hamiltonian(hamiltonian, tracing_names(names))
        else:
            text = hamiltonian
        self.base = base
        self.h = Expression(text, names, aliases=default_names(base.dim))
        try:
            self.terms: BracketTerms = base.bracket_terms()  # type: ignore[attr-defined]
        except (AttributeError, NotImplementedError) as err:
            raise ValueError(f"structure: {err}") from None
        self.name = name
        #: H's program as the core's table (code, a, b, c).
        self.tape = self.h.tape()
        self._jets: dict[int, JetRealization] = {}
        # π∇H as one program (∇H written out): the core's fast path for the field. None where it
        # exceeds the core's program size (a long H: its gradient is several times its length):
        # the core then differentiates H's tape in lanes and applies π, the same field, slower.
        self.field_program: FieldProgram | None
        try:
            self.field_program = field_program(self.h, *self.terms.tables())
        except ExpressionError:
            self.field_program = None
        # A sum over distances (vortices, Kepler): ∇H compiled in the core, faster still.
        self.distances: DistanceTerms | None = distance_terms(self.h.program, self.dim)

    # --- the PoissonSystem protocol ---------------------------------------------------------

    @property
    def dim(self) -> int:
        return int(self.base.dim)

    @property
    def component_names(self) -> tuple[str, ...]:
        return tuple(self.base.component_names)

    @property
    def state_symbol(self) -> str:  # type: ignore[override]
        return str(self.base.state_symbol)

    def hamiltonian(self, x: Any) -> Any:
        """H at x (..., dim): NumPy in, NumPy out; a torch tensor in, a differentiable tensor
        out."""
        if type(x).__module__.startswith("torch"):
            import torch

            return self.h.evaluate(x, torch)
        return self.h.evaluate(np.asarray(x, dtype=np.float64))

    def hamiltonian_jets(self, x: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        """H, ∇H and ∇²H at the states x (n, dim), exactly, from the Rust core."""
        from .. import _core

        x = np.ascontiguousarray(np.atleast_2d(np.asarray(x, dtype=np.float64)))
        return _core.expression_jets(*self.tape, x)

    def vector_field(self, x: Any) -> Any:
        """π(x)∇H(x) at x (..., dim), from the Rust core (NumPy) or autograd (torch)."""
        if type(x).__module__.startswith("torch"):
            import torch

            xg = x.detach().requires_grad_(True)
            (g,) = torch.autograd.grad(self.h.evaluate(xg, torch).sum(), xg, create_graph=True)
            return torch.einsum("...ij,...j->...i", self.base.bivector(x), g)
        from .. import _core

        arr = np.asarray(x, dtype=np.float64)
        flat = np.ascontiguousarray(arr.reshape(-1, self.dim))
        out = _core.hamiltonian_field(
            *self.tape, *self.terms.tables(), flat, program=self.field_program,
            distances=None if self.distances is None else self.distances.table(),
        )  # fmt: skip
        return out.reshape(arr.shape)

    def bivector(self, x: Any) -> Any:
        return self.base.bivector(x)

    def bracket_terms(self) -> BracketTerms:
        """The structure's π as polynomials (the bracket is the structure's, whatever H is)."""
        return self.terms

    def casimirs(self, x: Any) -> Any:
        return self.base.casimirs(x)

    @property
    def casimir_label(self) -> str:
        return str(self.base.casimir_label)

    @property
    def title(self) -> str:
        return f"{self.name or 'H = ' + self.h.text} (bracket of {self.base.title})"

    @property
    def demo_states(self) -> np.ndarray:
        return np.asarray(self.base.demo_states)

    @property
    def sample_radii(self) -> tuple[float, ...]:  # type: ignore[override]
        return tuple(self.base.sample_radii)

    def domain_text(self) -> str:
        return str(self.base.domain_text())

    def in_domain(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(self.base.in_domain(x))

    def check_states(self, x: ArrayLike, name: str = "x0") -> np.ndarray:
        return np.asarray(self.base.check_states(x, name))

    def sample_states(self, radii: Sequence[float]) -> tuple[np.ndarray, list[str]]:
        return self.base.sample_states(radii)

    def jet_realization(self, order: int) -> JetRealization:
        """The structure's realization for Taylor-HJ by jets (NotImplementedError where it has
        none)."""
        # Built once per order: a polynomial bracket's realization is a sympy expansion.
        if order not in self._jets:
            self._jets[order] = self.base.jet_realization(order)  # type: ignore[attr-defined]
        return self._jets[order]

    def taylor_charts(self) -> tuple[str, ...]:
        """("jets",): Taylor-HJ by jets on the structure's realization; () where the
        structure has none for jets."""
        try:
            self.jet_realization(1)
        except NotImplementedError:
            return ()
        return ("jets",)

    def taylor_orders(self, wanted: Sequence[int]) -> tuple[int, ...]:
        """The orders of ``wanted`` up to :data:`STUDY_JET_ORDER`: a study's default set stops
        there, since a jet step's cost grows steeply with the order (``taylor_integrator``
        builds any order to :data:`MAX_JET_ORDER`)."""
        return tuple(m for m in wanted if 1 <= m <= STUDY_JET_ORDER)

    def taylor_integrator(
        self,
        order: int,
        chart: str | None = None,
        *,
        tol: float = NEWTON_TOL,
        max_iter: int = NEWTON_MAX_ITER,
    ) -> Stepper:
        if chart not in (None, "jets"):
            raise ValueError(f"chart {chart!r} is not available for {self.title}; its charts: jets")
        try:
            stepper: Stepper = provided("expression.JetTaylorIntegrator")(
                self, order, tol=tol, max_iter=max_iter
            )
            return stepper
        except NotImplementedError as err:
            raise ValueError(str(err)) from None

    def classical_methods(self) -> list[str]:
        return list(FIELD_METHODS)

    def classical(
        self, name: str, *, tol: float = NEWTON_TOL, max_iter: int = NEWTON_MAX_ITER
    ) -> Stepper:
        stepper: Stepper = provided("expression.FieldIntegrator")(
            self, name, tol=tol, max_iter=max_iter
        )
        return stepper

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
        field = self.vector_field
        return provided("field_reference")(
            lambda y: field(y[None])[0],
            self.dim,
            x0,
            times,
            rtol=rtol,
            atol=atol,
            failures=failures,
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "name": self.name,
            "hamiltonian": self.h.text,
            "structure": self.base.to_dict(),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ExpressionSystem:
        from . import system_from_dict

        structure = data.get("structure")
        if not isinstance(structure, Mapping):
            raise ValueError("an expression system needs a 'structure' table")
        return cls(system_from_dict(structure), data.get("hamiltonian"), name=data.get("name"))  # type: ignore[arg-type]

    def __reduce__(self) -> tuple[Any, ...]:
        return (_rebuild, (self.base, self.h.text, self.name))

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, ExpressionSystem)
            and self.h.text == other.h.text
            and self.base.to_dict() == other.base.to_dict()
        )

    def __hash__(self) -> int:
        return hash(self.h.text)

    def __repr__(self) -> str:
        return f"ExpressionSystem(hamiltonian={self.h.text!r}, structure={self.base!r})"


def _rebuild(base: Any, text: str, name: str | None) -> ExpressionSystem:
    return ExpressionSystem(base, text, name=name)


def with_hamiltonian(
    structure: Any, hamiltonian: str | Expression | Callable[[Any], Any], *, name: str | None = None
) -> PoissonSystemBase:
    """The bracket of ``structure`` (any system) with ``hamiltonian``, an expression in its
    component names or x1 … xn, e.g. ``with_hamiltonian(pendulum, "u**2/2 - cos(v)")``, or a
    callable on torch tensors traced into one (``lambda x: x[..., 0]**2/2 - torch.cos(x[...,
    1])``; :mod:`poisson_rs.expression_tracing`): the structure's own kind where it builds one
    (``structure.expression_system``: a charged particle keeps its B and A), else an
    :class:`ExpressionSystem` on its polynomial bracket."""
    if callable(hamiltonian) and not isinstance(hamiltonian, (str, Expression)):
        from ..expression_tracing import trace_hamiltonian, tracing_names

        base = as_system(structure, "structure")
        hamiltonian = trace_hamiltonian(hamiltonian, tracing_names(base.component_names))
    if isinstance(hamiltonian, str):
        try:
            return structure.expression_system(hamiltonian, name=name)
        except NotImplementedError:
            pass
    return ExpressionSystem(structure, hamiltonian, name=name)


def _scene_table(raw: Mapping[str, Any]) -> ExpressionSystem:
    """[system] kind = "expression": ``hamiltonian`` (a string) on the bracket of the
    [system.structure] table (a scene system table of any other kind; its own Hamiltonian is
    not used)."""
    from . import system_from_scene_table

    structure = raw.get("structure")
    if not isinstance(structure, Mapping):
        raise ValueError("scene key 'system.structure' must be a table (the bracket's system)")
    if structure.get("kind") == "expression":
        raise ValueError("scene key 'system.structure.kind' cannot itself be 'expression'")
    base = system_from_scene_table(structure, "lie_poisson")
    h = raw.get("hamiltonian")
    if not isinstance(h, str):
        raise ValueError("scene key 'system.hamiltonian' must be a string (an expression)")
    return ExpressionSystem(base, h, name=raw.get("name"))


SYSTEM_KINDS = {ExpressionSystem.kind: ExpressionSystem.from_dict}
SCENE_KINDS = {ExpressionSystem.kind: _scene_table}

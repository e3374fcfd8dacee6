"""The steppers of an expression Hamiltonian (:class:`~poisson_rs.structures.expression_system.
ExpressionSystem`): Taylor-HJ by jets on the structure's realization, and the classical methods
on the vector field, all in the Rust core (DOP853 in SciPy)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from ..protocols import NEWTON_MAX_ITER, NEWTON_TOL, provides

if TYPE_CHECKING:
    from ..structures.expression_system import ExpressionSystem

FloatArray = NDArray[np.float64]


@provides("expression.JetTaylorIntegrator")
class JetTaylorIntegrator:
    """Taylor-HJ of order ``order`` for any smooth H: S(t, p) = Σ_{k≤order} t^k S_k(p) from the
    HJ recursion in truncated power series at each Newton iterate (``rust/jet_hj.rs``), on the
    structure's realization (:meth:`jet_realization`). Newton stops at |δ|∞ ≤ tol ·
    max(|p|∞, 1) or fails the trajectory after ``max_iter`` updates."""

    poisson = True

    def __init__(
        self,
        system: ExpressionSystem,
        order: int,
        *,
        tol: float = NEWTON_TOL,
        max_iter: int = NEWTON_MAX_ITER,
    ) -> None:
        from ..structures.expression_system import MAX_JET_ORDER

        if isinstance(order, bool) or not isinstance(order, int) or not 1 <= order <= MAX_JET_ORDER:
            raise ValueError(f"order must be an integer in 1..={MAX_JET_ORDER}, got {order!r}")
        self.system, self.order = system, order
        self.tol, self.max_iter = float(tol), int(max_iter)
        self.realization = system.jet_realization(order)
        # Order m + 1 where S_{m+1} vanishes is not claimed: m is what the series carries.
        self.name = f"taylor{order}-jets"

    @property
    def dim(self) -> int:
        return self.system.dim

    def __reduce__(self) -> tuple[Any, ...]:
        return (
            _jet_integrator,
            (self.system, self.order, self.tol, self.max_iter),
        )

    def rollout(
        self, x0: FloatArray, h: float, n_steps: int, every: int
    ) -> tuple[FloatArray, dict[str, np.ndarray]]:
        from .. import _core

        r = self.realization
        n = self.system.dim
        lifted = np.ones((len(x0), r.dim))
        lifted[:, :n] = x0
        lifted = np.ascontiguousarray(lifted)
        code, a, b, c = self.system.tape
        if r.lie_constants is not None:
            traj, info = _core.rollout_jets_lie(
                code, a, b, c, n, self.order, np.ascontiguousarray(r.lie_constants), lifted,
                float(h), int(n_steps), int(every), self.tol, self.max_iter,
            )  # fmt: skip
        else:
            if r.sou is None or r.tar is None:
                raise ValueError(
                    f"the realization {r.label!r} gives neither a Lie algebra nor maps"
                )
            traj, info = _core.rollout_jets_polynomial(
                code, a, b, c, n, self.order, *r.sou, *r.tar, lifted,
                float(h), int(n_steps), int(every), self.tol, self.max_iter,
            )  # fmt: skip
        return np.ascontiguousarray(traj[..., :n]), info

    def __repr__(self) -> str:
        return f"JetTaylorIntegrator(order={self.order}, realization={self.realization.label!r})"


def _jet_integrator(
    system: ExpressionSystem, order: int, tol: float, max_iter: int
) -> JetTaylorIntegrator:
    return JetTaylorIntegrator(system, order, tol=tol, max_iter=max_iter)


@provides("expression.FieldIntegrator")
class FieldIntegrator:
    """A classical method on ẋ = π(x)∇H(x): "rk4" and "midpoint" in the Rust core (SIMD lanes;
    the midpoint's Newton with the exact Jacobian, |δ|∞ ≤ tol · max(|m|∞, 1e-300)), "dop853" by
    SciPy at rtol = atol = ``tol``."""

    poisson = False

    def __init__(
        self,
        system: ExpressionSystem,
        name: str,
        *,
        tol: float = NEWTON_TOL,
        max_iter: int = NEWTON_MAX_ITER,
    ) -> None:
        from ..structures.expression_system import FIELD_METHODS

        if name not in FIELD_METHODS:
            raise ValueError(
                f"unknown method {name!r} for an expression Hamiltonian; valid: "
                f"{', '.join(FIELD_METHODS)}"
            )
        self.system, self.name = system, name
        self.order = FIELD_METHODS[name][0]
        self.tol, self.max_iter = float(tol), int(max_iter)

    @property
    def dim(self) -> int:
        return self.system.dim

    def __reduce__(self) -> tuple[Any, ...]:
        return (_field_integrator, (self.system, self.name, self.tol, self.max_iter))

    @property
    def torch_graph(self) -> bool:
        """Whether :meth:`torch_step` is one graph (no data-dependent control flow), which
        ``torch.compile`` fuses on a device: RK4's is."""
        return self.name == "rk4"

    def torch_step(self, mu: Any, h: float) -> Any:
        """One RK4 step in torch on mu's device and dtype, the field evaluated from the core's
        own program (:func:`~poisson_rs.expressions.evaluate_table`: straight-line, no
        autograd). mu: (B, n) → (B, n)."""
        import torch

        from ..expressions import MAX_FIELD_INSTRUCTIONS, evaluate_table
        from .classical_torch import require_torch_method, rk4_step

        require_torch_method(self.name, "the classical integrator")
        if self.system.field_program is None:
            raise ValueError(
                "hamiltonian: π∇H of this H is longer than the core's field program "
                f"({MAX_FIELD_INSTRUCTIONS} instructions), which the torch step evaluates; "
                "step it in the core (no device)"
            )
        code, a, b, c, outputs = self.system.field_program
        table = (code, a, b, c)
        return rk4_step(lambda x: evaluate_table(table, outputs, x, torch), mu, float(h))

    def rollout(
        self, x0: FloatArray, h: float, n_steps: int, every: int
    ) -> tuple[FloatArray, dict[str, np.ndarray]]:
        if self.name == "dop853":
            from ..rollout import dop853_rollout

            return dop853_rollout(self.system, x0, h, n_steps, every, self.tol)
        from .. import _core

        return _core.rollout_hamiltonian_field(
            self.name,
            *self.system.tape,
            *self.system.terms.tables(),
            np.ascontiguousarray(x0, dtype=np.float64),
            float(h),
            int(n_steps),
            int(every),
            self.tol,
            self.max_iter,
            program=self.system.field_program,
            distances=None if self.system.distances is None else self.system.distances.table(),
        )

    def __repr__(self) -> str:
        return f"FieldIntegrator(name={self.name!r})"


def _field_integrator(
    system: ExpressionSystem, name: str, tol: float, max_iter: int
) -> FieldIntegrator:
    return FieldIntegrator(system, name, tol=tol, max_iter=max_iter)

"""The Lie–Poisson family's steppers: Taylor-HJ on T*G through the model-file stepper, and the
classical baselines (RK4, the midpoint rule, the rigid body's splittings and DMV, the heavy
top's splitting, DOP853)."""

from __future__ import annotations

import numbers
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..export import (
    model_bytes,
)
from ..model_files import (
    TaylorIntegrator,
)
from ..protocols import (
    NEWTON_MAX_ITER,
    NEWTON_TOL,
    provides,
)
from ..rollout import (
    dop853_rollout,
)
from ..structures.lie_poisson import (  # noqa: F401 (the tables, re-exported)
    CLASSICAL_METHODS,
    LIE_POISSON_METHODS,
    LiePoissonSystem,
)


@provides("lie_poisson.taylor")
def lie_poisson_taylor(
    body: LiePoissonSystem,
    order: int,
    chart: str,
    *,
    tol: float = NEWTON_TOL,
    max_iter: int = NEWTON_MAX_ITER,
) -> TaylorIntegrator:
    """Taylor-HJ on the groupoid T*G of a Lie–Poisson system in ``chart`` ("cayley": the rigid
    body only; "exp": any algebra), through the learned models' Newton stepper."""
    from ..taylor import system_taylor_terms

    if isinstance(order, bool) or not isinstance(order, numbers.Integral) or order < 1:
        raise ValueError(f"order must be an integer >= 1, got {order!r}")
    powers, coeffs = system_taylor_terms(body, int(order), chart)
    data = model_bytes(
        powers=powers,
        coeffs=coeffs,
        layers=[],
        mlp_power=1,
        chart=chart,
        system=body,
        h_max=float("inf"),
        domain={"kind": "all"},
        taylor_order=int(order),
        record={"name": f"taylor{order}-{chart}"},
    )
    return TaylorIntegrator(data, tol=tol, max_iter=max_iter)


@provides("lie_poisson.classical")
class ClassicalIntegrator:
    """A classical baseline for a Lie–Poisson system, driven by :func:`integrate`.

    Build one with :func:`classical`. Every method but "dop853" takes fixed steps of size ``h`` in
    the Rust core, through the same parallel rollout as the bisection integrators, so timings
    compare like for like. For the rigid body μ̇ = μ × (μ/I):

    - "rk4": classical explicit Runge–Kutta, order 4; not Poisson (C and H drift).
    - "midpoint": implicit midpoint, order 2, Newton with the exact Jacobian; keeps C and H up
      to the Newton tolerance (both are quadratic).
    - "splitting": McLachlan's Lie–Poisson splitting H = Σ μᵢ²/(2Iᵢ), Strang-composed
      H₁(h/2) H₂(h/2) H₃(h) H₂(h/2) H₁(h/2); explicit, order 2, keeps C to round-off.
    - "splitting4": Suzuki's 5-stage composition of that Strang step, weights
      (p, p, 1 − 4p, p, p) with p = 1/(4 − 4^{1/3}); order 4, keeps C to round-off.
    - "dmv": the discrete Moser–Veselov algorithm, order 2, Newton for its rotation; keeps C and
      H to round-off.
    - "splitting_casimir": the Casimir split off first (Fassò; McLachlan): H = C/(2I_r) +
      Σ_{i≠r} ½(1/Iᵢ − 1/I_r)μᵢ² with I_r the median moment, the Casimir's flow the identity, the
      other two axis flows Strang-composed; order 2, 3 rotations a step, keeps C to round-off.
      For a nearly symmetric body its error nearly vanishes, where "splitting"'s does not.
    - "dop853": SciPy's adaptive DOP853 (:func:`~poisson_rs.reference.dop853_solution`, one
      trajectory at a time, in Python) with rtol = atol = ``tol``. It chooses its own steps:
      ``h`` sets only where the output is sampled (t = k·h), not the accuracy or the cost.

    For any other system: "rk4", "midpoint" (exact Jacobian by forward-mode dual numbers; keeps
    quadratic Casimirs), "dop853" (:func:`~poisson_rs.reference.reference_solution` with rtol =
    atol = ``tol``), and for the heavy top "splitting": Strang's V(h/2) K(h) V(h/2) of the
    potential flow (Γ fixed, Ṁ = mgl Γ × χ, exact) and the kinetic flow (the rigid body's
    splitting, turning M and Γ together); order 2, keeps |Γ|² and M·Γ to round-off.

    ``tol`` and ``max_iter`` set the Newton solve of the implicit methods (relative update
    tolerance and iteration cap, as for the bisection integrators); for "dop853" ``tol`` is its
    rtol and atol.
    """

    body: LiePoissonSystem
    name: str
    tol: float
    max_iter: int
    _dim: int

    def __init__(
        self,
        body: LiePoissonSystem,
        name: str,
        *,
        tol: float = NEWTON_TOL,
        max_iter: int = NEWTON_MAX_ITER,
    ) -> None:
        if not isinstance(body, LiePoissonSystem):
            raise TypeError(f"body must be a LiePoissonSystem, got {type(body).__name__}")
        names = body.classical_methods()
        if not (isinstance(name, str) and name in names):
            raise ValueError(
                f"unknown classical integrator {name!r} for {body!r}; valid names: "
                f"{', '.join(names)}"
            )
        if isinstance(tol, bool) or not (isinstance(tol, numbers.Real) and 0 < tol < 1):
            raise ValueError(f"tol must lie in (0, 1), got {tol!r}")
        if isinstance(max_iter, bool) or not isinstance(max_iter, numbers.Integral) or max_iter < 1:
            raise ValueError(f"max_iter must be an integer >= 1, got {max_iter!r}")
        self.body = body
        self.name = name
        self.tol = float(tol)
        self.max_iter = int(max_iter)
        self._dim = int(body.dim)  # systems are immutable; read on every integrate() call

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickles as the system, the method's name and the options; unpickling checks them."""
        return (_restore_classical, (type(self), self.body, self.name, self.tol, self.max_iter))

    @property
    def torch_graph(self) -> bool:
        """Whether :meth:`torch_step` is one graph (no data-dependent control flow), which
        ``torch.compile`` fuses on a device: RK4's is."""
        return self.name == "rk4"

    def torch_step(self, mu: Any, h: float) -> Any:
        """One step in torch on mu's device and dtype (RK4 only: the device rollouts'
        :func:`~poisson_rs.on_device`). mu: (B, n) tensor → (B, n)."""
        from .classical_torch import require_torch_method, rk4_step

        require_torch_method(self.name, "the classical integrator")
        return rk4_step(self.body.vector_field, mu, float(h))

    @property
    def system(self) -> LiePoissonSystem:
        return self.body

    @property
    def dim(self) -> int:
        return self._dim

    def _table(self) -> Mapping[str, tuple[int, bool]]:
        return self.body.method_table

    @property
    def order(self) -> int:
        """Order of accuracy (8 for DOP853, whose error is set by ``tol`` rather than h)."""
        return self._table()[self.name][0]

    @property
    def poisson(self) -> bool:
        """Whether a step is a Poisson map (keeps every Casimir to round-off)."""
        return self._table()[self.name][1]

    @property
    def adaptive(self) -> bool:
        """Whether it chooses its own steps (DOP853): ``h`` then only spaces the output."""
        return self.name == "dop853"

    @property
    def _core_rollout(self) -> Any:
        """The rollout in the Rust core that checks the states itself (NaN/∞ included) and
        returns ``(traj, _core.RolloutDiagnostics)``, for :func:`integrate`'s thin path; None
        for DOP853 (SciPy)."""
        return None if self.name == "dop853" else self._rust_rollout

    def _rust_rollout(
        self, mu0: np.ndarray | list[Any], h: float, n_steps: int, every: int, lazy: bool = True
    ) -> tuple[np.ndarray, Any] | None:
        """``(traj, diagnostics)`` from the core; mu0 an (n, dim) float64 array, or a list of
        dim plain numbers (one state; None where the list holds anything else)."""
        return self.body.classical_rollout(
            self.name, mu0, h, n_steps, every, self.tol, self.max_iter, lazy
        )

    def rollout(
        self, mu0: np.ndarray, h: float, n_steps: int, every: int
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        body = self.body
        if self.name != "dop853":
            result = self._rust_rollout(mu0, h, n_steps, every, lazy=False)
            assert result is not None  # an array always gives one
            return result
        return dop853_rollout(body, mu0, h, n_steps, every, self.tol)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(name={self.name!r}, system={self.body!r}, "
            f"order={self.order}, poisson={self.poisson})"
        )


def _restore_classical(
    cls: type[ClassicalIntegrator], body: LiePoissonSystem, name: str, tol: float, max_iter: int
) -> ClassicalIntegrator:
    """Unpickles a :class:`ClassicalIntegrator` (see its ``__reduce__``)."""
    return cls(body, name, tol=tol, max_iter=max_iter)

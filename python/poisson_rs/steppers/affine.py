"""The affine family's stepper: any integrator of the central extension run at level 1."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..model_files import BisectionIntegrator
from ..protocols import NEWTON_MAX_ITER, NEWTON_TOL, provides
from ..structures.affine import AffinePoissonSystem


@provides("affine.AffineIntegrator")
class AffineIntegrator:
    """An integrator of an :class:`AffinePoissonSystem`: ``inner`` (any integrator of its
    :attr:`~AffinePoissonSystem.extension`) run from (x, 1), returning the first n components.
    Built by :func:`affine_taylor` and :func:`affine_classical`; driven by
    :func:`~poisson_rs.integrate`."""

    def __init__(self, system: AffinePoissonSystem, inner: Any, name: str) -> None:
        if not isinstance(system, AffinePoissonSystem):
            raise TypeError(f"system must be an AffinePoissonSystem, got {type(system).__name__}")
        self.system = system
        self.inner = inner
        self.name = name

    @property
    def dim(self) -> int:
        return self.system.dim

    @property
    def order(self) -> int | None:
        return getattr(self.inner, "order", None)

    def rollout(
        self, mu0: np.ndarray, h: float, n_steps: int, every: int
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        lifted = np.ascontiguousarray(self.system.lift(mu0))
        traj, raw = self.inner.rollout(lifted, h, n_steps, every)
        return np.ascontiguousarray(traj[..., : self.dim]), dict(raw)

    @property
    def tol(self) -> float:
        """The inner stepper's Newton tolerance (relative update)."""
        return float(self.inner.tol)

    @property
    def max_iter(self) -> int:
        """The inner stepper's Newton iteration cap."""
        return int(self.inner.max_iter)

    @property
    def adaptive(self) -> bool:
        return bool(getattr(self.inner, "adaptive", False))

    def __repr__(self) -> str:
        return f"AffineIntegrator({self.name!r}, system={self.system!r})"


@provides("affine.affine_learned")
def affine_learned(
    system: AffinePoissonSystem, model: Any, name: str = "learned"
) -> AffineIntegrator:
    """A learned generating function of the extension (a model trained with
    ``TrainConfig(system=system.extension, chart="exp", inputs="t,p", ...)`` and loaded by
    :func:`~poisson_rs.load_model`, or any :class:`~poisson_rs.integrators.BisectionIntegrator`
    of it), run at level 1: a Poisson map on the extension's exact groupoid whatever the network
    learned, so μ_z = 1 and the Casimirs stay at round-off. ValueError for a model of another
    system."""
    if not isinstance(model, BisectionIntegrator):
        raise TypeError(
            f"model must be a BisectionIntegrator (pr.load_model), got {type(model).__name__}"
        )
    if model.system.to_dict() != system.extension.to_dict():
        raise ValueError(
            f"model integrates {model.system!r}, not this system's central extension "
            f"{system.extension!r}: train it with TrainConfig(system=system.extension, ...)"
        )
    return AffineIntegrator(system, model, name)


@provides("affine.affine_classical")
def affine_classical(
    system: AffinePoissonSystem,
    name: str,
    *,
    tol: float = NEWTON_TOL,
    max_iter: int = NEWTON_MAX_ITER,
) -> AffineIntegrator:
    """Deprecated alias of ``pr.classical(system, name)`` (kept one release)."""
    from ..integrators import classical

    return classical(system, name, tol=tol, max_iter=max_iter)  # type: ignore[return-value]

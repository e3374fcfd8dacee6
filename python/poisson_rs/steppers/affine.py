"""The affine family's stepper: any integrator of the central extension run at level 1."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..structures.affine import AffinePoissonSystem


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

"""A learned time-h map: a stepper valid at the one step size it was fitted for.

Mode "map" learns S(h, ·) of the time-h map from pairs h apart; its model file writes
S(t, p) = (t/h)²·S(h, p) (or a network trained at t = h only), which is a Poisson map at any t
but the flow's map at t = h alone: at h/2 it is O(1) wrong. ``h_max`` only refuses larger steps,
so :class:`FixedStepIntegrator` refuses every h but the fitted one.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..integrators import LearnedIntegrator
from ..rollout import STEP_RTOL, check_step

__all__ = ["STEP_RTOL", "FixedStepIntegrator", "check_step"]


class FixedStepIntegrator(LearnedIntegrator):
    """A :class:`~poisson_rs.integrators.LearnedIntegrator` of a learned time-h map: steps at
    :attr:`step_h` (the data's h, recorded in the file as ``step_h``) only; any other h is refused
    (ValueError) by :func:`poisson_rs.integrate` and :meth:`torch_step`."""

    @property
    def step_h(self) -> float:
        """The one step size the map was fitted for (time units): the file's ``step_h``."""
        return float(self.metadata["step_h"])

    def rollout(
        self, mu0: np.ndarray, h: float, n_steps: int, every: int
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        check_step(h, self.step_h, self.name)
        return super().rollout(mu0, h, n_steps, every)

    def torch_step(self, mu: Any, h: float) -> Any:
        check_step(h, self.step_h, self.name)
        return super().torch_step(mu, h)

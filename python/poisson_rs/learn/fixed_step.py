"""A learned time-h map: a stepper valid at the one step size it was fitted for.

Mode "map" learns S(h, ·) of the time-h map from pairs h apart; its model file writes
S(t, p) = (t/h)²·S(h, p) (or a network trained at t = h only), which is a Poisson map at any t
but the flow's map at t = h alone: at h/2 it is O(1) wrong. ``h_max`` only refuses larger steps,
so :class:`FixedStepIntegrator` refuses every h but the fitted one.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..integrators import LearnedIntegrator

__all__ = ["STEP_RTOL", "FixedStepIntegrator", "check_step"]

#: Relative difference from the fitted h still taken as that h (a few ulps: h read back from
#: text, or computed as T/n).
STEP_RTOL = 1e-12


def check_step(h: Any, fitted: float, name: str) -> None:
    """ValueError naming ``h`` and ``fitted`` unless h is ``fitted`` (to :data:`STEP_RTOL`)."""
    try:
        hv = float(h)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"h must be a real number, got {h!r}") from None
    if not (math.isfinite(hv) and abs(hv - fitted) <= STEP_RTOL * fitted):
        raise ValueError(
            f"h = {h!r}: {name!r} is a learned time-h map fitted for h = {fitted!r} (the data's "
            "record spacing) and steps at that h only; at any other h it is not the flow's map"
        )


class FixedStepIntegrator(LearnedIntegrator):
    """A :class:`~poisson_rs.integrators.LearnedIntegrator` of a learned time-h map: steps at
    :attr:`step_h` (the data's h, recorded in the file as ``step_h``) only; any other h is refused
    (ValueError) by :func:`poisson_rs.integrate` and :meth:`torch_step`."""

    @property
    def step_h(self) -> float:
        """The one step size the map was fitted for (time units): the file's ``step_h``."""
        return float(self.metadata["step_h"])

    def _rollout(
        self, mu0: np.ndarray, h: float, n_steps: int, every: int
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        check_step(h, self.step_h, self.name)
        return super()._rollout(mu0, h, n_steps, every)

    def torch_step(self, mu: Any, h: float) -> Any:
        check_step(h, self.step_h, self.name)
        return super().torch_step(mu, h)

"""Classical steps in torch on any device: what a stepper's ``torch_step`` runs for the device
rollouts (:mod:`poisson_rs.device_rollout`), the same formulas as the core's."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

#: The methods with a torch step, by the name the steppers use.
TORCH_METHODS = ("rk4",)


def rk4_step(field: Callable[[Any], Any], x: Any, h: float) -> Any:
    """One classical RK4 step of ẋ = field(x): x (B, n) → (B, n), in x's dtype and device.
    Summed as the core sums it: x + h/6 · (k₁ + 2(k₂ + k₃) + k₄)."""
    half = 0.5 * h
    k1 = field(x)
    k2 = field(x + half * k1)
    k3 = field(x + half * k2)
    k4 = field(x + h * k3)
    return x + (h / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)


def require_torch_method(name: str, owner: str) -> None:
    """ValueError naming ``owner``'s method unless it has a torch step."""
    if name not in TORCH_METHODS:
        raise ValueError(
            f"{owner} {name!r} has no torch step (device rollouts); methods with one: "
            f"{', '.join(TORCH_METHODS)}, and the Taylor-HJ and learned integrators"
        )

"""The symplectic groupoid T*SO(3) ⇉ so(3)* in torch: source and target maps in two charts.

Coordinates (x, p) ∈ R³×R³; x is a chart of SO(3) near the identity, p its conjugate momentum.
Units are x = 0, where sou = tar = p. ``sou`` is the spatial momentum, ``tar`` the body one, and
|sou(x, p)| = |tar(x, p)| in both charts, which is why every bisection map keeps the Casimir.

The maps take NumPy arrays or torch tensors (differentiably) alike; torch is imported only when a
tensor arrives, so stepping and diagnostics in NumPy never load it.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Literal, TypeVar

import numpy as np

if TYPE_CHECKING:
    import torch

Array = TypeVar("Array", np.ndarray, "torch.Tensor")

ChartName = Literal["cayley", "exp"]
CHARTS: tuple[str, ...] = ("cayley", "exp")

# Largest |x| the exponential chart accepts; its coefficient c(θ) has a pole at θ = 2π.
EXP_CHART_MAX_ANGLE = 2.0 * math.pi - 0.1

# c(θ) = (1 − (θ/2)cot(θ/2))/θ² = Σ |B₂ₙ|/(2n)! θ^(2n−2), used for θ² < 1 where the closed form
# cancels catastrophically.
_C_SERIES = (
    1.0 / 12.0,
    1.0 / 720.0,
    1.0 / 30240.0,
    1.0 / 1209600.0,
    1.0 / 47900160.0,
    691.0 / 1307674368000.0,
    1.0 / 74724249600.0,
    3617.0 / 10670622842880000.0,
    43867.0 / 5109094217170944000.0,
    174611.0 / 802857662698291200000.0,
    77683.0 / 14101100039391805440000.0,
    236364091.0 / 1693824136731743669452800000.0,
)


def check_chart(chart: str) -> str:
    """Returns ``chart`` if it names a supported chart, else raises ValueError."""
    if chart not in CHARTS:
        raise ValueError(f"unknown chart {chart!r}; expected one of {CHARTS}")
    return chart


def _namespace(x: Any) -> Any:
    """torch for a tensor, NumPy otherwise."""
    if type(x).__module__.partition(".")[0] == "torch":
        import torch

        return torch
    return np


def _cross(xp: Any, a: Array, b: Array) -> Array:
    return xp.linalg.cross(a, b, dim=-1) if xp is not np else np.cross(a, b)


def exp_chart_coefficient(s: Array) -> Array:
    """c as a function of s = θ² (any shape), differentiable everywhere below the pole; NaN from
    θ = EXP_CHART_MAX_ANGLE on, where the chart is refused."""
    xp = _namespace(s)
    small = s < 1.0
    s_series = xp.where(small, s, xp.zeros_like(s))
    series = xp.zeros_like(s)
    for a in reversed(_C_SERIES):
        series = series * s_series + a
    # Keep the closed form's argument away from 0 so its (discarded) branch stays finite, and
    # its gradient too.
    s_closed = xp.where(small, xp.ones_like(s), s)
    th = xp.sqrt(s_closed)
    closed = 1.0 / s_closed - 1.0 / (2.0 * th * xp.tan(0.5 * th))
    c = xp.where(small, series, closed)
    return xp.where(s < EXP_CHART_MAX_ANGLE**2, c, xp.full_like(c, math.nan))


def _apply(chart: str, x: Array, p: Array, sign: float) -> Array:
    xp = _namespace(x)
    xcp = _cross(xp, x, p)
    if chart == "cayley":
        # p ± ½ x×p + ¼ x (x·p)
        return p + (0.5 * sign) * xcp + 0.25 * x * (x * p).sum(-1)[..., None]
    if chart == "exp":
        # p ± ½ x×p + c(|x|²) x×(x×p)
        c = exp_chart_coefficient((x * x).sum(-1)[..., None])
        return p + (0.5 * sign) * xcp + c * _cross(xp, x, xcp)
    raise ValueError(f"unknown chart {chart!r}; expected one of {CHARTS}")


def sou(chart: str, x: Array, p: Array) -> Array:
    """Source map (spatial momentum). x, p: (..., 3) arrays or tensors → (..., 3)."""
    return _apply(chart, x, p, 1.0)


def tar(chart: str, x: Array, p: Array) -> Array:
    """Target map (body momentum). x, p: (..., 3) arrays or tensors → (..., 3)."""
    return _apply(chart, x, p, -1.0)

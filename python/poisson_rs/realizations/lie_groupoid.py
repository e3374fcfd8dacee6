"""The symplectic groupoid T*G ⇉ g*: source and target maps in a chart of G near the identity.

Coordinates (x, p) ∈ g × g* ≅ Rⁿ×Rⁿ; x is a chart of G near the identity, p its conjugate
momentum. Units are x = 0, where sou = tar = p.

- so(3) (``algebra=None`` or c = ε) has two closed-form charts, "cayley" and "exp". ``sou`` is the
  spatial momentum, ``tar`` the body one, and |sou(x, p)| = |tar(x, p)|, which is why every
  bisection map keeps the Casimir.
- Any other algebra uses the exponential chart, with A = ad_xᵀ, (ad_xᵀ)_{jk} = Σ_i c[i,j,k] x_i:
  sou(x, p) = β = (ad_x/(e^{ad_x} − 1))ᵀ p = Σₙ (Bₙ/n!) Aⁿ p and
  tar(x, p) = α = (ad_x/(1 − e^{−ad_x}))ᵀ p = Σₙ (Bₙ/n!) (−A)ⁿ p (B₁ = −½), so α − β = A p.
  ad_x is singular (x ∈ ker ad_x), so these are summed as series, never as quotients. α and β lie
  on one coadjoint orbit, so every bisection map keeps every Casimir. The series converge for a
  spectral radius of ad_x below 2π; rows at or beyond ``EXP_SERIES_MAX_RADIUS`` come back NaN.

The maps take NumPy arrays or torch tensors (differentiably) alike; torch is imported only when a
tensor arrives, so stepping and diagnostics in NumPy never load it.
"""

from __future__ import annotations

import math
from functools import cache
from typing import TYPE_CHECKING, Any, Literal, TypeVar, cast

import numpy as np

from ..structures.lie_poisson import LieAlgebra

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


# Spectral radius of ad_x from which the generic exponential chart refuses a point: the Bernoulli
# series has radius 2π, and at 0.9·2π its terms still shrink like 0.9ⁿ, reaching round-off
# within MAX_SERIES_TERMS.
EXP_SERIES_MAX_RADIUS = 0.9 * 2.0 * math.pi
#: Most terms of the generic Bernoulli series; rows not converged by then come back NaN.
MAX_SERIES_TERMS = 400


def check_chart(chart: str, algebra: LieAlgebra | None = None) -> str:
    """Returns ``chart`` if it names a chart supported for ``algebra`` (None: so(3)), else
    raises ValueError: "cayley" exists for so(3) only."""
    if chart not in CHARTS:
        raise ValueError(f"unknown chart {chart!r}; expected one of {CHARTS}")
    if algebra is not None:
        if not isinstance(algebra, LieAlgebra):
            raise TypeError(f"algebra must be a LieAlgebra or None, got {type(algebra).__name__}")
        if chart != "exp" and not algebra.is_so3():
            label = algebra.name or f"{algebra.dim}-dimensional algebra"
            raise ValueError(
                f"the {chart!r} chart exists for so(3) only; use the 'exp' chart for {label}"
            )
    return chart


def _namespace(x: Any) -> Any:
    """torch for a tensor, NumPy otherwise."""
    if type(x).__module__.partition(".")[0] == "torch":
        import torch

        return torch
    return np


def _cross(xp: Any, a: Array, b: Array) -> Array:
    # xp is NumPy exactly when the arrays are NumPy's: the cast restates what the branch shows.
    return cast(Array, xp.linalg.cross(a, b, dim=-1) if xp is not np else np.cross(a, b))


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


@cache
def _bernoulli_over_factorial() -> tuple[float, ...]:
    """Bₙ/n! for n = 0 … MAX_SERIES_TERMS (B₁ = −½, odd n > 1 vanish), as the Rust core has them:
    B₂ₖ/(2k)! = (−1)^{k+1} |c_k| with the exact ratios of _C_SERIES first, then
    (−1)^{k+1} 2ζ(2k)/(2π)^{2k} (ζ summed to 12 terms: exact in float64 from 2k = 26 on)."""
    b = [0.0] * (MAX_SERIES_TERMS + 1)
    b[0], b[1] = 1.0, -0.5
    two_pi = 2.0 * math.pi
    for k in range(1, MAX_SERIES_TERMS // 2 + 1):
        if k <= len(_C_SERIES):
            magnitude = _C_SERIES[k - 1]
        else:
            zeta = sum(float(m) ** (-2 * k) for m in range(1, 13))
            magnitude = 2.0 * zeta * (1.0 / two_pi) ** (2 * k)  # (2π)^400 would overflow
        b[2 * k] = magnitude if k % 2 == 1 else -magnitude
    return tuple(b)


def _exp_series(c: np.ndarray, x: Any, p: Any, sign: float) -> Any:
    """Σₙ (Bₙ/n!) (sign · ad_xᵀ)ⁿ p for the algebra with structure constants c (n, n, n).

    x, p: (..., n) arrays or tensors (broadcast together) → (..., n). Summed until two
    consecutive non-zero terms are below 1e-17 of the sum (max norm) in every row; rows whose
    ad_x has a spectral radius ≥ EXP_SERIES_MAX_RADIUS, or that contain NaN/inf, or that did not
    converge within MAX_SERIES_TERMS terms, come back NaN. Differentiable in torch elsewhere.
    Typed Any: x and p are converted to one array kind below, which ever the caller passed.
    """
    xp = _namespace(x) if _namespace(x) is not np else _namespace(p)
    n = c.shape[0]
    if xp is np:
        x, p = np.asarray(x, dtype=np.float64), np.asarray(p, dtype=np.float64)
        ct = c
    else:
        x, p = xp.as_tensor(x), xp.as_tensor(p)
        dtype = x.dtype if x.is_floating_point() else xp.float64
        x, p = x.to(dtype), p.to(dtype=dtype, device=x.device)
        ct = xp.tensor(c, dtype=dtype, device=x.device)  # a copy: c is read-only
    if x.ndim == 0 or p.ndim == 0 or x.shape[-1] != n or p.shape[-1] != n:
        raise ValueError(
            f"x and p must have shape (..., {n}), got {tuple(x.shape)} and {tuple(p.shape)}"
        )
    a = xp.einsum("ijk,...i->...jk", ct, x)  # ad_xᵀ, (..., n, n)
    # Where the series cannot converge: refuse the row (NaN) and run it at x = 0, so that it
    # neither overflows nor holds up the batch, and autograd sees finite values there.
    a_np = a.detach().cpu().numpy() if xp is not np else a
    finite = np.isfinite(a_np).all(axis=(-2, -1))
    radius = np.full(finite.shape, np.inf)
    # ρ ≤ ‖A‖_F: eigenvalues are needed only for the rows the cheap bound cannot clear.
    with np.errstate(over="ignore", invalid="ignore"):
        bound = np.sqrt(np.square(a_np).sum(axis=(-2, -1)))
    cleared = finite & (bound < EXP_SERIES_MAX_RADIUS)
    radius[cleared] = bound[cleared]
    unclear = finite & ~cleared
    if unclear.any():
        radius[unclear] = np.abs(np.linalg.eigvals(a_np[unclear])).max(axis=-1)
    ok_np = radius < EXP_SERIES_MAX_RADIUS
    ok = ok_np if xp is np else xp.as_tensor(ok_np, device=x.device)
    a = xp.where(ok[..., None, None], a, xp.zeros_like(a))
    shape = tuple(np.broadcast_shapes(tuple(a.shape[:-2]), tuple(p.shape[:-1])))
    term = p
    out = p
    prev_small = np.zeros(shape, dtype=bool)
    converged = np.zeros(shape, dtype=bool)
    for k, bk in enumerate(_bernoulli_over_factorial()[1:], start=1):
        term = (a @ term[..., None])[..., 0]
        if bk == 0.0:
            continue
        out = out + (sign * bk if k % 2 else bk) * term
        size_t = np.abs(_numpy(term)).max(axis=-1, initial=0.0) * abs(bk)
        size_out = np.abs(_numpy(out)).max(axis=-1, initial=0.0)
        small = np.broadcast_to(size_t <= 1e-17 * size_out, shape)
        converged = converged | (small & prev_small)
        prev_small = small
        if converged.all():
            break
    good_np = np.broadcast_to(ok_np, shape) & converged
    good = good_np if xp is np else xp.as_tensor(good_np, device=x.device)
    out = xp.broadcast_to(out, (*shape, n))
    return xp.where(good[..., None], out, xp.full_like(out, math.nan))


def _numpy(v: Any) -> np.ndarray:
    return v.detach().cpu().numpy() if not isinstance(v, np.ndarray) else v


def _dispatch(chart: str, x: Array, p: Array, sign: float, algebra: LieAlgebra | None) -> Array:
    if algebra is None or (isinstance(algebra, LieAlgebra) and algebra.is_so3()):
        return _apply(chart, x, p, sign)
    check_chart(chart, algebra)
    return _exp_series(algebra.c, x, p, sign)


def sou(chart: str, x: Array, p: Array, algebra: LieAlgebra | None = None) -> Array:
    """Source map (spatial momentum) β(x, p).

    Parameters
    ----------
    chart : "cayley" or "exp"
        "cayley" only for so(3).
    x, p : ndarray or torch.Tensor, shape (..., n)
        Chart coordinate x ∈ g and momentum p ∈ g*.
    algebra : LieAlgebra, optional
        None or so(3): the closed forms (n = 3); otherwise the Bernoulli series.

    Returns
    -------
    ndarray or torch.Tensor, shape (..., n); NaN rows where the exp chart is refused.
    """
    return _dispatch(chart, x, p, 1.0, algebra)


def tar(chart: str, x: Array, p: Array, algebra: LieAlgebra | None = None) -> Array:
    """Target map (body momentum) α(x, p); α − β = ad_xᵀ p. Same arguments as :func:`sou`."""
    return _dispatch(chart, x, p, -1.0, algebra)

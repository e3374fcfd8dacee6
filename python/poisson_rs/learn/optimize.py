"""Levenberg–Marquardt on residuals, the one least-squares loop of the fits in this package
(polynomial H through the Taylor-HJ step, shooting, the polynomial map)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

#: ``evaluate(x, jacobian)`` → residuals r (m,) and, when ``jacobian``, ∂r/∂x (m, len(x)).
Residuals = Callable[[np.ndarray, bool], tuple[np.ndarray, np.ndarray | None]]


@dataclass
class LMResult:
    """The last accepted point ``x``, its residuals ``r`` and Jacobian ``jac``, the mean
    squared residual ``cost`` and its ``history`` (one entry at the start and one per accepted
    step)."""

    x: np.ndarray
    r: np.ndarray
    jac: np.ndarray
    cost: float
    history: list[float]


def levenberg_marquardt(
    evaluate: Residuals,
    x0: np.ndarray,
    *,
    max_iter: int,
    lam: float = 1e-6,
    rel_tol: float = 1e-4,
    cost_floor: float = 1e-30,
    floor: float = 1e-300,
    label: str = "LM",
    verbose: bool = False,
) -> LMResult:
    """Minimises mean(r(x)²) from ``x0``. Each iteration solves
    (JᵀJ + λ diag(diag(JᵀJ) + floor)) δ = −Jᵀr, multiplying λ by 10 (at most 12 times) until
    the cost falls, then dividing it by 10 (not below 1e-12). Stops when no trial lowers the
    cost, when the cost changes by less than ``rel_tol`` relative, or falls below
    ``cost_floor``. A non-finite residual rejects the trial (a step out of the chart)."""
    x = np.asarray(x0, dtype=np.float64)
    r, jac = evaluate(x, True)
    assert jac is not None
    cost = float(np.mean(r * r))
    history = [cost]
    for it in range(max_iter):
        if not np.isfinite(cost):
            break
        jtj = jac.T @ jac
        g = jac.T @ r
        improved = False
        for _ in range(12):
            try:
                step = -np.linalg.solve(jtj + lam * np.diag(np.diag(jtj) + floor), g)
            except np.linalg.LinAlgError:  # singular even damped (non-finite entries): stop
                break
            r_new, _ = evaluate(x + step, False)
            c_new = float(np.mean(r_new * r_new))
            if np.isfinite(c_new) and c_new < cost:
                improved = True
                break
            lam *= 10.0
        if not improved:
            break
        rel = abs(cost - c_new) / max(cost, 1e-300)
        x = x + step
        lam = max(lam / 10.0, 1e-12)
        r, jac = evaluate(x, True)
        assert jac is not None
        cost = float(np.mean(r * r))
        history.append(cost)
        if verbose:
            print(f"  {label} {it}: cost {cost:.3e} lambda {lam:.1e}")
        if rel < rel_tol or cost < cost_floor:
            break
    return LMResult(x, r, jac, cost, history)

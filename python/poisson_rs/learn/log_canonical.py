"""Learning a Lotka–Volterra Hamiltonian on a known log-canonical structure from trajectories.

In q = ln x the bracket is the constant matrix c, and for H = Σ_i (a_i x_i − b_i ln x_i) the
vector field q̇ = c ∇_q H = c (a ∘ x − b) is linear in (a, b). So (a, b) is a linear
least-squares fit of finite-difference velocities of ln x (central differences of order up to 8,
as :func:`poisson_rs.learn.hamiltonian.velocities`), and the learned system is integrated with the
package's log-canonical Taylor-HJ integrator (:func:`poisson_rs.log_canonical_taylor`), which keeps
the Casimirs of c exactly (in exact arithmetic; to round-off in floating point).

The vector-field fit is then refined through the integrator (``through_integrator=True``, the
default): (a, b) minimise the misfit, in ln x, of the integrator's own rollouts of ``window``
steps from every record against the records that follow (Levenberg–Marquardt on a
finite-difference Jacobian of the Rust rollouts; 2n parameters). The learned H is then the one
whose integrator reproduces the data's time-h map, not the one whose vector field matches finite
differences: on PNN's protocol its error at T = 100 sits at the true H's through the same
integrator (``benches/data_protocols.py --lotka-volterra``). Directions of b in the null space of
c (the Casimirs' ln-form) do not change the flow and are set to zero (minimal norm).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..structures.log_canonical import LogCanonical, LogCanonicalSystem, LogPolynomial
from .hamiltonian import velocities

__all__ = ["LotkaVolterraFit", "fit_lotka_volterra"]


@dataclass
class LotkaVolterraFit:
    """``a``, ``b`` (n,) of H = Σ (a_i x_i − b_i ln x_i); ``system`` the learned
    :class:`LogCanonicalSystem`; ``stepper`` its Taylor-HJ integrator of ``order``;
    ``residual`` the RMS velocity residual (units of ln x per time); ``seconds``."""

    a: np.ndarray
    b: np.ndarray
    system: LogCanonicalSystem
    stepper: Any
    order: int
    residual: float
    seconds: float

    @property
    def n_parameters(self) -> int:
        return int(np.count_nonzero(self.a) + np.count_nonzero(self.b))


def fit_lotka_volterra(
    trajectories: Any,
    h: float,
    c: Any,
    *,
    order: int = 5,
    through_integrator: bool = True,
    window: int = 10,
) -> LotkaVolterraFit:
    """Fits H = Σ (a_i x_i − b_i ln x_i) on the log-canonical structure ``c`` (n, n,
    antisymmetric) to ``trajectories`` (a list of (records, n) arrays or an array (m, records,
    n), states in the open positive orthant, records ``h`` apart): the vector-field fit, then
    (``through_integrator``) refined through the Taylor-HJ integrator of ``order`` on rollouts
    of ``window`` steps (see the module docstring)."""
    from ..integrators import log_canonical_taylor

    t0 = time.perf_counter()
    structure = LogCanonical(c)
    n = structure.dim
    if isinstance(h, bool) or not isinstance(h, (int, float)) or not 0 < h < np.inf:
        raise ValueError(f"h must be finite and > 0, got {h!r}")
    trajs = [np.asarray(t, dtype=np.float64) for t in trajectories]
    for i, t in enumerate(trajs):
        if t.ndim != 2 or t.shape[1] != n or len(t) < 2:
            raise ValueError(
                f"trajectories[{i}]: expected (records >= 2, {n}) states, got shape {t.shape}"
            )
        if not np.isfinite(t).all() or (t <= 0).any():
            raise ValueError(
                f"trajectories[{i}]: states must be finite and positive (log-canonical "
                "structures live in the open positive orthant)"
            )
    cm = np.asarray(structure.c, dtype=np.float64)
    x, qdot = velocities([np.log(t) for t in trajs], float(h))
    xs = np.exp(x)
    # q̇_j = Σ_i c_ji (a_i x_i − b_i): columns for a_i, then for b_i.
    design = np.concatenate(
        [cm[None, :, :] * xs[:, None, :], -np.broadcast_to(cm, (len(xs), n, n))], 2
    )
    coef, *_ = np.linalg.lstsq(design.reshape(-1, 2 * n), qdot.reshape(-1), rcond=1e-12)
    a, b = coef[:n], coef[n:]
    resid = design.reshape(-1, 2 * n) @ coef - qdot.reshape(-1)
    if isinstance(window, bool) or not isinstance(window, int) or window < 1:
        raise ValueError(f"window must be an integer >= 1, got {window!r}")
    if through_integrator:
        a, b, resid = _through_integrator(trajs, float(h), structure, a, b, order, window)
    terms: dict[Sequence[int], float] = {
        tuple(int(i == j) for j in range(n)): float(a[i]) for i in range(n)
    }
    system = LogCanonicalSystem(structure, LogPolynomial(terms, b), name="learned")
    return LotkaVolterraFit(
        a=a,
        b=b,
        system=system,
        stepper=log_canonical_taylor(system, order),
        order=order,
        residual=float(np.sqrt(np.mean(resid**2))),
        seconds=time.perf_counter() - t0,
    )


def _system(structure: LogCanonical, a: np.ndarray, b: np.ndarray) -> LogCanonicalSystem:
    n = structure.dim
    terms = {tuple(int(i == j) for j in range(n)): float(a[i]) for i in range(n)}
    return LogCanonicalSystem(structure, LogPolynomial(terms, b), name="learned")


def _through_integrator(
    trajs: list[np.ndarray],
    h: float,
    structure: LogCanonical,
    a: np.ndarray,
    b: np.ndarray,
    order: int,
    window: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(a, b) minimising the ln-x misfit of the integrator's ``window``-step rollouts from
    every record (that has ``window`` records after it) against those records, and the final
    residuals."""
    import warnings

    from scipy.optimize import least_squares

    from ..steppers.log_canonical import LogCanonicalTaylorIntegrator

    w = max(1, min(window, min(len(t) for t in trajs) - 1))
    starts = np.concatenate([t[: len(t) - w] for t in trajs])
    targets = np.log(
        np.concatenate([np.stack([t[k + 1 : k + w + 1] for k in range(len(t) - w)]) for t in trajs])
    )
    n = structure.dim
    # Directions of b along the Casimirs (c k = 0) do not move the flow: kept at zero.
    null = structure.casimir_vectors.astype(np.float64)
    keep = np.eye(n) - (null.T @ np.linalg.pinv(null.T) if len(null) else 0.0)

    def residual(theta: np.ndarray) -> np.ndarray:
        system = _system(structure, theta[:n], keep @ theta[n:])
        stepper = LogCanonicalTaylorIntegrator(system, order)
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            traj, _ = stepper.rollout(starts, h, w, 1)
            out = np.log(traj[:, 1:]) - targets
        # A rollout that failed or left the orthant: a large, finite misfit.
        return np.nan_to_num(out, nan=1e3, posinf=1e3, neginf=-1e3).ravel()

    theta0 = np.concatenate([a, b])
    fit = least_squares(residual, theta0, method="lm", x_scale="jac", xtol=1e-15, ftol=1e-15)
    theta = fit.x if np.linalg.norm(fit.fun) <= np.linalg.norm(residual(theta0)) else theta0
    return theta[:n], keep @ theta[n:], residual(theta)

"""Learning a Lotka–Volterra Hamiltonian on a known log-canonical structure from trajectories.

In q = ln x the bracket is the constant matrix c, and for H = Σ_i (a_i x_i − b_i ln x_i) the
vector field q̇ = c ∇_q H = c (a ∘ x − b) is linear in (a, b). So (a, b) is a linear
least-squares fit of finite-difference velocities of ln x (central differences of order up to 8,
as :func:`poisson_rs.learn.hamiltonian.velocities`), and the learned system is integrated with the
package's log-canonical Taylor-HJ integrator (:func:`poisson_rs.log_canonical_taylor`), which keeps
the Casimirs of c exactly (in exact arithmetic; to round-off in floating point).

This is the vector-field fit only: unlike :func:`poisson_rs.learn` on Lie algebras, the step
map is not fitted through the integrator (no shooting, no IFT), because ``learn/step.py`` holds
the Lie–Poisson groupoid only. Directions of b in the null space of c (the Casimirs' ln-form) do
not change the vector field and are set to zero (minimal norm).
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


def fit_lotka_volterra(trajectories: Any, h: float, c: Any, *, order: int = 5) -> LotkaVolterraFit:
    """Fits H = Σ (a_i x_i − b_i ln x_i) on the log-canonical structure ``c`` (n, n,
    antisymmetric) to ``trajectories`` (a list of (records, n) arrays or an array (m, records,
    n), states in the open positive orthant, records ``h`` apart)."""
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

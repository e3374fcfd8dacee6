"""Learning H on any Poisson structure through the structure's own Taylor-HJ integrator.

The structure supplies a family H_θ = Σ_m θ_m φ_m
(:meth:`poisson_rs.protocols.PoissonSystemBase.hamiltonian_family`): the gradients of the φ_m
and its integrator of H_θ. Nothing here names a structure.

1. Warm start: the vector field π(x)∇H_θ(x) is linear in θ, so θ₀ is a linear least-squares fit
   of finite-difference velocities (as :mod:`poisson_rs.learn.hamiltonian`).
2. Gauge: H is identifiable only up to a constant and Casimirs, whose vector fields vanish; the
   directions the data cannot see are projected out by an SVD of the (column-normalised)
   design matrix.
3. Through the integrator: the residuals Φ_θ(x_k) − x_{k+1} of the structure's own one-step
   map are driven down by Gauss–Newton with the chord Jacobian h·π(x̄)∇φ(x̄) at the midpoints
   x̄ = (x_k + x_{k+1})/2. A symmetric one-step map is x + hX_θ(x̄) + O(h³), so that Jacobian is
   the true one to O(h²) relative and each iterate gains about that factor; the integrator is
   built once per iterate (no derivative of the step is ever formed, which is what lets any
   structure's integrator serve).
4. Sparsity: terms whose share of the vector field is below what the data resolve are dropped
   and the rest refitted (kept when the fit is as good).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .data import TrajectoryData
from .scoring import one_step

__all__ = ["StructureFit", "fit_structure_hamiltonian", "velocities"]

#: Singular values of the column-normalised design below this fraction of the largest are gauge
#: directions (constants, Casimirs) and are projected out.
GAUGE_RTOL = 1e-8
#: Gauss–Newton stops once an iterate lowers the cost by less than this fraction.
GN_RTOL = 1e-3


def velocities(trajs: list[np.ndarray], h: float) -> tuple[np.ndarray, np.ndarray]:
    """(states, velocities) by central differences of order up to 8 at interior records (the
    midpoint rule for a two-record trajectory)."""
    from .hamiltonian import velocities as fd

    return fd(trajs, h)


@dataclass
class StructureFit:
    """A fitted H_θ: ``family`` (the structure's, restricted to the kept terms), ``theta``,
    ``system`` the structure's system with H_θ, ``stepper`` its Taylor-HJ integrator (the one
    fitted through), ``history`` the cost (mean squared relative one-step residual) per
    iterate, ``seconds``, ``gauge_dropped`` (directions no data see)."""

    family: Any
    theta: np.ndarray
    system: Any
    stepper: Any
    history: list[float] = field(default_factory=list)
    seconds: float = 0.0
    gauge_dropped: int = 0

    @property
    def n_parameters(self) -> int:
        return int(np.count_nonzero(self.theta))


def _design(structure: Any, family: Any, x: np.ndarray) -> np.ndarray:
    """Column m: the vector field π(x)∇φ_m(x) at each state, (B, n, P)."""
    return np.asarray(structure.bivector(x)) @ family.gradients(x)


def _one_step(family: Any, theta: np.ndarray, starts: np.ndarray, h: float) -> np.ndarray:
    """Φ_θ(starts), (B, n): NaN where a step failed or the integrator cannot be built."""
    try:
        stepper = family.stepper(theta)
    except (ValueError, FloatingPointError, OverflowError):
        return np.full_like(starts, np.nan)
    return one_step(stepper, starts, h)


def fit_structure_hamiltonian(
    data: TrajectoryData,
    structure: Any,
    degree: int,
    *,
    order: int | None = None,
    max_iter: int = 30,
    family: Any = None,
    sparse: bool = True,
    verbose: bool = False,
) -> StructureFit:
    """Fits H_θ of ``structure``'s family of total degree ≤ ``degree`` (or ``family``, a
    restriction of it) to ``data.train`` through the structure's Taylor-HJ integrator of
    ``order`` (the structure's default when None); see the module docstring. ``max_iter``:
    Gauss–Newton iterates."""
    t0 = time.perf_counter()
    fam = family if family is not None else structure.hamiltonian_family(degree, order)
    # A family whose terms are singular somewhere (log-distances) refuses records there with
    # one ValueError naming the input, rather than fitting NaNs.
    check = getattr(fam, "check_states", None)
    if check is not None:
        check(np.concatenate(data.train + data.test), "trajectories")
    p = len(fam)
    x, v = velocities(data.train, data.h)
    w = 1.0 / np.linalg.norm(x, axis=1).clip(1e-300)
    a2 = (_design(structure, fam, x) * w[:, None, None]).reshape(-1, p)
    col = np.linalg.norm(a2, axis=0)
    col[col == 0] = 1.0
    u, sv, vt = np.linalg.svd(a2 / col, full_matrices=False)
    keep = sv > GAUGE_RTOL * sv[0]
    q = vt[keep].T / col[:, None]  # θ = q z
    rhs = (v * w[:, None]).reshape(-1)
    z = (u[:, keep].T @ rhs) / sv[keep]
    starts, targets = data.pairs("train")
    scale = np.linalg.norm(starts, axis=1).clip(1e-300)[:, None]
    mid = 0.5 * (starts + targets)
    chord = (data.h * _design(structure, fam, mid) / scale[..., None]).reshape(-1, p) @ q
    solve = np.linalg.pinv(chord)

    def residual(zz: np.ndarray) -> tuple[np.ndarray, float]:
        r = ((_one_step(fam, q @ zz, starts, data.h) - targets) / scale).reshape(-1)
        cost = float(np.mean(r * r))
        return r, (cost if math.isfinite(cost) else math.inf)

    r, cost = residual(z)
    history = [cost]
    for it in range(max_iter):
        if not math.isfinite(cost) or cost <= 1e-30:
            break
        dz = -(solve @ r)
        lam, improved = 1.0, False
        while lam >= 1.0 / 64:
            r_new, c_new = residual(z + lam * dz)
            if c_new < cost:
                improved = True
                break
            lam /= 2
        if not improved:
            break
        gain = (cost - c_new) / cost
        z, r, cost = z + lam * dz, r_new, c_new
        history.append(cost)
        if verbose:
            print(f"  Gauss–Newton {it + 1}: cost {cost:.3e} (step {lam:g})")
        if gain < GN_RTOL:
            break
    theta = q @ z
    if sparse and p > 1 and math.isfinite(cost):
        # Terms whose share of the vector field is below what the data resolve are dropped
        # and the rest refitted once (sequential thresholding, as in sparse regression).
        share = np.abs(theta) * col / max(float(np.linalg.norm(rhs)), 1e-300)
        sigma = data.noise if math.isfinite(data.noise) else math.sqrt(cost / 2.0)
        floor = max(10.0 * sigma, 1e-9)
        kept = [e for e, s in zip(fam.exponents, share, strict=True) if s > floor]
        if kept and len(kept) < p:
            sub = fit_structure_hamiltonian(
                data,
                structure,
                degree,
                family=fam.restrict(kept),
                max_iter=max_iter,
                sparse=False,
                verbose=verbose,
            )
            if sub.history[-1] <= 1.5 * cost + 1e-28:
                sub.seconds = time.perf_counter() - t0
                return sub
    system = fam.system(theta)
    return StructureFit(
        family=fam,
        theta=theta,
        system=system,
        stepper=fam.stepper(theta, system),
        history=history,
        seconds=time.perf_counter() - t0,
        gauge_dropped=int((~keep).sum()),
    )

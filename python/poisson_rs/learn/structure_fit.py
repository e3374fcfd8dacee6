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
4. Sparsity: terms whose share of the vector field is below what the data resolve are dropped;
   then, on the linearised residual (the chord Jacobian at the fit), terms are removed one at
   a time (each time the one missed least) and, separately, added one at a time from none
   (each time the one that helps most), and the support of smallest Bayesian information
   criterion N·log(RSS/N) + k·log N on either path is kept, every support within the gauge of
   step 2 (a term only a Casimir could stand in for stays). The rest is refitted through the
   integrator and kept when the fit is as good, or when it reaches the data's noise level
   (mean squared residual ≤ 2σ̂², σ̂ the records' noise bound). The second stage is what noisy
   records need: a library whose terms nearly coincide on the leaves the data visit fits the
   noise with every term (each with a large share of the field); the criterion asks each term
   to pay for itself.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .data import TrajectoryData
from .scoring import one_step

__all__ = ["StructureFit", "bic_support", "fit_structure_hamiltonian", "velocities"]

#: Singular values of the column-normalised design below this fraction of the largest are gauge
#: directions (constants, Casimirs) and are projected out.
GAUGE_RTOL = 1e-8
#: A mean squared relative one-step residual below this (rms 1e-12) is round-off: a smaller
#: support that fits exact records to it fits them as well as any.
ROUND_OFF_COST = 1e-24
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


def bic_support(
    jac: np.ndarray,
    residual: np.ndarray,
    theta: np.ndarray,
    start: list[int],
    basis: np.ndarray | None = None,
) -> list[int]:
    """The support, among the terms ``start``, of the linearised residual
    r(θ') ≈ r + J(θ' − θ) (``jac`` J, (N, P); ``residual`` r, (N,); ``theta`` θ, (P,)) that
    the data pay for: two greedy paths (backward elimination from ``start``, each time the
    term whose removal raises the least-squares residual least; forward selection from none,
    each time the term that lowers it most), and of all their supports the one of smallest
    Bayesian information criterion N·log(RSS/N) + k·log N (ties: the smaller). Returns term
    indices, ascending.

    ``basis`` (P, r): θ' is confined to its columns' span (the gauge fixed: the directions
    whose vector field vanishes are left out), so a term the gauge could stand in for is
    dropped only where the field itself does without it; None: θ' is free.

    One QR of [J | Jθ − r] reduces every subset's least squares to a (P + 1)-row problem, so
    the residual stays accurate where it is many orders below the records (exact data)."""
    n = len(residual)
    if n <= len(start):
        return list(start)
    p = jac.shape[1]
    col = np.linalg.norm(jac, axis=0)
    col[col == 0] = 1.0
    target = jac @ theta - residual
    _, rr = np.linalg.qr(np.column_stack([jac / col, target]), mode="reduced")
    a, c = rr[:, :-1] / col, rr[:, -1]  # a θ' ≈ c, in the reduced rows
    tiny = 1e-300

    def rss(support: list[int]) -> float:
        free = set(support)
        zero = [m for m in range(p) if m not in free]
        if basis is None:
            design = a[:, support]
        elif not zero:
            design = a @ basis
        else:
            # θ' = basis·N·w, with N spanning the null space of basis' zeroed rows.
            _, sv, vh = np.linalg.svd(basis[zero], full_matrices=True)
            rank = int(np.count_nonzero(sv > 1e-12 * max(float(sv[0]), tiny)))
            design = a @ basis @ vh[rank:].T
        if design.shape[1] == 0:
            return float(c @ c)
        x, *_ = np.linalg.lstsq(design, c, rcond=1e-12)
        e = c - design @ x
        return float(e @ e)

    def bic(value: float, k: int) -> float:
        # Plain BIC: consistent where the terms are few against the records (P ≪ N, the
        # extended criterion's γ = 0 regime); a stronger penalty drops true terms whose
        # share is near the noise.
        return n * math.log(max(value, tiny) / n) + k * math.log(n)

    # Both greedy paths: where one term nearly stands in for a combination of others,
    # backward elimination may strand the combination; forward selection finds the single
    # term first.
    paths: list[list[int]] = []
    support = sorted(start)
    paths.append(list(support))
    while len(support) > 1:
        drop = min(support, key=lambda j: (rss([m for m in support if m != j]), j))
        support = [m for m in support if m != drop]
        paths.append(list(support))
    support = []
    while len(support) < len(start) - 1:
        add = min((j for j in start if j not in support), key=lambda j: (rss([*support, j]), j))
        support = sorted([*support, add])
        paths.append(list(support))
    scores = [(bic(rss(s), len(s)), len(s), s) for s in paths]
    return min(scores, key=lambda t: (t[0], t[1]))[2]


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
    jac = (data.h * _design(structure, fam, mid) / scale[..., None]).reshape(-1, p)
    chord = jac @ q
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
        # (sequential thresholding, as in sparse regression), then the information criterion
        # prunes what is left; the smaller support refitted first.
        share = np.abs(theta) * col / max(float(np.linalg.norm(rhs)), 1e-300)
        sigma = data.noise if math.isfinite(data.noise) else math.sqrt(cost / 2.0)
        floor = max(10.0 * sigma, 1e-9)
        # A one-step residual of noise σ at both ends has mean square 2σ² per component.
        explained = 2.0 * data.noise**2 if math.isfinite(data.noise) else 0.0
        above = [m for m in range(p) if share[m] > floor]
        lean = bic_support(jac, r, theta, above, basis=q) if above else []
        tried: list[list[int]] = []
        for support in (lean, above):
            if not support or len(support) == p or support in tried:
                continue
            tried.append(support)
            sub = fit_structure_hamiltonian(
                data,
                structure,
                degree,
                family=fam.restrict([fam.exponents[m] for m in support]),
                max_iter=max_iter,
                sparse=False,
                verbose=verbose,
            )
            if verbose:
                kept_cost = sub.history[-1]
                print(f"  {len(support)} of {p} terms: cost {kept_cost:.3e} (all: {cost:.3e})")
            # Kept when it fits as well, or to the data's noise level: on exact records the
            # spare terms absorb a little of the integrator's truncation error (a cost far below
            # the noise bound), and a spare exp(x_i) near zero still grows without bound where
            # a rollout leaves the records' range.
            if sub.history[-1] <= max(1.5 * cost, explained) + ROUND_OFF_COST:
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

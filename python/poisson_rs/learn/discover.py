"""Structure discovery: the bracket and H both learned from trajectories
(``pr.learn(trajectories, h, structure="discover")``).

Every structure module offers bivector families linear in their parameters θ
(:func:`poisson_rs.structures.bracket_families`, smallest first); each offers Hamiltonian
families linear in φ. The vector field π_θ(x)∇H_φ(x) is bilinear in (θ, φ), so for each pair
(bracket family, H degree):

1. Velocity-level fit: the finite-difference velocities of the training records are fitted by
   variable projection (φ eliminated by least squares, θ by Levenberg–Marquardt) from a lifted
   start (the rank-1 part of the least-squares fit of the products θ_aφ_m) and seeded random
   starts. Where the records' own velocity error estimates (order-8 against order-6
   differences, a running median along the trajectory) span a decade, a record above the median
   counts less, in proportion (:func:`velocity_weights`), so that a fast passage, where the
   differences are poor, does not set the bracket's error. The relative residual screens the
   pairs: one far above the records' own velocity error (:func:`velocity_floor`, in the same
   weights) cannot explain the data and is not fitted further.
2. Gauge: the field is unchanged by π → λπ with H → H/λ, by H → H + a Casimir, and by
   π → π + N where N∇H ≡ 0 (on so(3)* with a quadratic H, the brackets ε·∇(C + αH)). Fixed
   here: θ is the least-norm one among those the data cannot tell apart, scaled so that its
   largest coefficient is +1; the structure's H fit drops the Casimir directions. With noisy
   records, directions seen no better than the noise join them where the round-off gauge
   lost the fit (:func:`_unseen_below`).
3. Jacobi: a family whose θ does not obey Jacobi identically (Lie–Poisson, affine,
   polynomial) is projected onto it (least-norm Gauss–Newton on the quadratic residual at the
   data's states); the residual before and after is reported.
4. Through the integrator: the projected bracket becomes the structure's own system, and H is
   fitted through its Taylor-HJ integrator (:mod:`poisson_rs.learn.structure_fit`), bracket
   and H refined jointly, and the bracket snapped to twelfths where it explains the records
   as well (within a tolerance that follows their noise level, :func:`snap_tolerance`; along
   its one unseen direction where it does not snap by itself, :func:`_snap_in_orbit`), scored
   by the held-out one-step error. Pairs are tried smallest first; the first that reaches the
   data's noise level is kept. Where none does, the data are reported as explained by no family
   tried (a warning, and ``report.explained`` False): a Poisson integrator of the best is still
   returned, marked so.
5. Noisy records: where a pair's structure learns on T*G (a Lie–Poisson system) and its
   one-step error is within :data:`OWN_PATH_WITHIN` of the noise level, H (a polynomial of the
   pair's degree) is fitted again by that path's shooting windows (``given``, the
   structure-given ``pr.learn``), kept where it explains the held-out records at the noise
   level (or, the pair kept, rolls out closer).

Nothing here names a structure: the families come from the structure modules' tables.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..bracket_family import JACOBI_RTOL
from ..hamiltonian_library import (
    LIBRARY_DEGREES,
    LIBRARY_DISTANCE_DEGREES,
    LIBRARY_DISTANCE_POWERS,
    LibraryFamily,
    supports_library,
)
from .data import TrajectoryData

__all__ = [
    "MAX_BRACKET_PARAMETERS",
    "BracketFit",
    "NotExplainedWarning",
    "bilinear_fit",
    "fit_bracket",
]

#: Bracket families larger than this are not searched (their θ outnumber what the data tell).
MAX_BRACKET_PARAMETERS = 120
#: A pair's velocity-level residual must be within this factor of the best to be fitted
#: through the integrator.
SCREEN_FACTOR = 30.0
#: Starts of the bilinear fit: at least, and at most (see :func:`bilinear_fit`).
RESTARTS = 8
MAX_RESTARTS = 24
#: Levenberg–Marquardt iterates of the variable-projection fit, per start.
VARPRO_ITER = 200
#: Singular values below this fraction of the largest are gauge directions.
GAUGE_RTOL = 1e-9
#: A bracket direction whose singular value, relative to the largest, is below this many times
#: the velocity fit's relative residual is seen no better than the noise: gauge (see
#: :func:`_unseen_below`).
UNSEEN_FACTOR = 3.0
#: The noise-level gauge is tried where the bracket settled with the round-off gauge fits the
#: velocities worse than this many times the bilinear fit did.
RELAX_ABOVE = 2.0
#: A learned bracket coefficient this close (relative to the largest) to a multiple of 1/12 is
#: tried at it.
SNAP_RTOL = 1e-5
#: With noisy records a coefficient is tried at its twelfth within this many times the records'
#: relative noise level, at most :data:`SNAP_MAX` (the snapped bracket is kept only where it
#: passes the snap rule, as on exact data).
SNAP_NOISE = 10.0
SNAP_MAX = 1e-2
#: When the snapped bracket replaces the learned one: where H refitted on it explains the
#: records at the noise level or fits them as well ("noise"), fits them as well ("fit"), never.
SNAPS = ("noise", "fit", "off")
#: With noisy records, a pair whose held-out one-step error is within this factor of the noise
#: threshold has H fitted again on T*G where its structure learns there (step 5).
OWN_PATH_WITHIN = 10.0
#: Records of the running median of the velocities' error estimates (:func:`velocity_errors`).
ERROR_WINDOW = 9
#: The velocities are weighted by their error estimates only where some estimate is this many
#: times their median (:func:`velocity_weights`).
ERROR_SPREAD = 10.0
#: The distance libraries tried after poly+trig where the dimension is even and ≥ 4 (the
#: coordinates read as planar points): log-distances, then the powers of distances.
DISTANCE_LIBRARIES: tuple[dict[str, Any], ...] = (
    {"trig": False, "log_distances": True},
    {"trig": False, "distance_powers": LIBRARY_DISTANCE_POWERS},
)
#: Gauss–Newton iterates of the joint refinement through the integrator.
REFINE_ITER = 12
#: Bracket coefficients below these (relative to the largest, +1) are tried at zero, the
#: largest level that keeps the fit first.
SPARSE_LEVELS = (1e-3, 1e-4, 1e-5, 1e-6, 1e-7)
SPARSE_RTOL = SPARSE_LEVELS[-1]


class NotExplainedWarning(UserWarning):
    """No bracket family tried explains the data to their noise level."""


@dataclass
class BracketFit:
    """A velocity-level fit of one (bracket family, H family) pair, gauge-fixed.

    ``theta``: the bracket's coefficients (largest +1); ``phi``: H's (in the H family's
    exponents); ``velocity_residual``: relative RMS residual of the weighted velocities;
    ``jacobi_fit``/``jacobi``: the Jacobi residual before and after the projection;
    ``gauge_null``: bracket directions the data cannot see (dropped), ``null_directions``
    those directions (largest entry +1), ``weak_directions`` those seen no better than the
    noise (largest entry +1; where they were not freed, tried by the orbit snap alone);
    ``seconds``.
    """

    family: Any
    hamiltonians: Any
    theta: np.ndarray
    phi: np.ndarray
    velocity_residual: float
    jacobi_fit: float
    jacobi: float
    gauge_null: int
    seconds: float
    null_directions: list[np.ndarray] = field(default_factory=list)
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    weak_directions: list[np.ndarray] = field(default_factory=list)


def _lstsq(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.lstsq(a, b, rcond=GAUGE_RTOL)[0]


def bilinear_fit(
    t: np.ndarray, rhs: np.ndarray, rng: np.random.Generator, restarts: int = RESTARTS
) -> tuple[np.ndarray, np.ndarray, float]:
    """min ‖Σ_{a,m} θ_a φ_m t[:, a, m] − rhs‖ over (θ, φ), t: (K, P, M), rhs: (K,) → θ (P,)
    of unit norm, φ (M,), relative residual.

    Variable projection: φ(θ) is the least-squares solution for each θ, and θ alone is fitted
    by Levenberg–Marquardt on the projected residual (Jacobian (I − AA⁺)·t·φ, Kaufman's form),
    whose basins are much wider than alternating least squares'. The problem still has local
    minima: after a lifted start (the rank-1 part of the least-squares products, where there
    are enough equations) seeded random starts follow, at least ``restarts`` of them, until the
    best residual has been reached twice (within 2×), :data:`MAX_RESTARTS` at most."""
    k, p, m = t.shape
    norm_rhs = max(float(np.linalg.norm(rhs)), 1e-300)
    by_theta = np.ascontiguousarray(t.transpose(0, 2, 1))  # (K, M, P): by_theta @ θ = A(θ)

    def project(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        a = by_theta @ theta
        phi = _lstsq(a, rhs)
        return a, phi, a @ phi - rhs

    def run(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        theta = theta / max(float(np.linalg.norm(theta)), 1e-300)
        a, phi, r = project(theta)
        cost, mu = float(r @ r), 1e-3
        for _ in range(VARPRO_ITER):
            q, _ = np.linalg.qr(a)
            d = t @ phi  # (K, P)
            jac = d - q @ (q.T @ d)
            g, hess = jac.T @ r, jac.T @ jac
            damp = np.diag(np.diag(hess)) + 1e-300
            while mu <= 1e10:
                step = np.linalg.solve(hess + mu * damp, -g)
                trial = theta + step
                trial = trial / max(float(np.linalg.norm(trial)), 1e-300)
                a2, phi2, r2 = project(trial)
                c2 = float(r2 @ r2)
                if c2 < cost:
                    break
                mu *= 4.0
            else:
                break
            gain = (cost - c2) / max(cost, 1e-300)
            theta, a, phi, r, cost, mu = trial, a2, phi2, r2, c2, max(mu / 3.0, 1e-12)
            if gain < 1e-10:
                break
        return theta, phi, math.sqrt(cost) / norm_rhs

    results = []
    if p * m <= 4000 and k >= p * m:
        w = _lstsq(t.reshape(k, p * m), rhs).reshape(p, m)
        u, _, _ = np.linalg.svd(w)
        results.append(run(u[:, 0]))
    while len(results) < MAX_RESTARTS:
        results.append(run(np.asarray(rng.normal(size=p), dtype=np.float64)))
        best = min(r[2] for r in results)
        hits = sum(r[2] <= 2.0 * best for r in results)
        if len(results) >= restarts and hits >= 2:
            break
    return min(results, key=lambda r: r[2])


def _unseen_below(sv: np.ndarray, residual: float) -> float:
    """The singular value of the bracket's design matrix A(φ) (``sv``, largest first) below
    which a direction of θ counts as unseen by the data, hence gauge: round-off
    (:data:`GAUGE_RTOL`), or, with noisy velocities, :data:`UNSEEN_FACTOR` × the fit's
    relative residual ``residual``. On the heavy top at σ = 1e-4 three directions of the exact
    data's gauge orbit (singular values 0 there) come out at 1e-5 relative: kept as seen, the
    Jacobi projection moved θ along them to a bracket 0.9 off the velocities."""
    if not sv.size or not sv[0] > 0:
        return math.inf
    return max(GAUGE_RTOL, UNSEEN_FACTOR * residual) * float(sv[0])


def fit_bracket(
    data: TrajectoryData,
    family: Any,
    hamiltonians: Any,
    x: np.ndarray,
    v: np.ndarray,
    seed: int,
    weights: np.ndarray | None = None,
) -> BracketFit:
    """The velocity-level fit of ``family`` × ``hamiltonians`` (a Hamiltonian family of the
    family's template system) to velocities ``v`` at states ``x`` (B, n), gauge-fixed and
    Jacobi-projected; see the module docstring. ``weights`` (B,): each velocity's weight
    (:func:`velocity_weights`; default 1), beside 1/|x|."""
    t0 = time.perf_counter()
    w = 1.0 / np.linalg.norm(x, axis=1).clip(1e-300)
    if weights is not None:
        w = w * weights
    basis = family.basis(x)  # (B, n, n, P)
    grads = hamiltonians.gradients(x)  # (B, n, M)
    t = np.einsum("bija,bjm->biam", basis, grads) * w[:, None, None, None]
    t = t.reshape(-1, len(family), len(hamiltonians))
    rhs = (v * w[:, None]).reshape(-1)
    # Column scales: monomials of different degrees differ by orders of magnitude.
    sp = np.linalg.norm(t, axis=(0, 2))
    sm = np.linalg.norm(t, axis=(0, 1))
    sp[sp == 0] = 1.0
    sm[sm == 0] = 1.0
    rng = np.random.default_rng(seed)
    # fitted: the bilinear fit's relative residual, before gauge, Jacobi and sparsity
    ts, ps, fitted = bilinear_fit(t / sp[None, :, None] / sm[None, None, :], rhs, rng)
    theta, phi = ts / sp, ps / sm
    a = np.einsum("kam,m->ka", t, phi)
    _, sv, vt = np.linalg.svd(a, full_matrices=False)
    pts = family.jacobi_points(data.lo, data.hi, seed)

    def refit(th: np.ndarray) -> tuple[np.ndarray, float]:
        ph = _lstsq(np.einsum("kam,a->km", t, th), rhs)
        r = np.einsum("kam,a,m->k", t, th, ph) - rhs
        return ph, float(np.linalg.norm(r)) / max(float(np.linalg.norm(rhs)), 1e-300)

    def settle(keep: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float, float]:
        """Gauge, Jacobi and sparsity with the directions ``~keep`` free: θ, φ, the relative
        residual, Jacobi before and after the projection."""
        # Gauge: the least-norm θ among those giving the same field with this H.
        th = vt[keep].T @ (vt[keep] @ theta)
        jacobi_fit = family.jacobi_residual(th, pts)
        if jacobi_fit > 1e-12 and not keep.all():
            # The least-norm θ may sit far from every Poisson bracket of its orbit: the
            # nearest one along the directions the data cannot see first, then the (small)
            # projection.
            th, _ = family.jacobi_in_subspace(th, vt[~keep].T, pts, seed)
        th, jacobi = family.project(th, pts, free=vt[~keep].T)
        big = int(np.argmax(np.abs(th)))
        th = th / (th[big] if th[big] != 0 else 1.0)
        ph, res = refit(th)
        # Sparsity: coefficients the fit cannot tell from zero are dropped (and Jacobi
        # imposed again), at the largest threshold where the fit stays as good.
        for level in SPARSE_LEVELS:
            small = np.abs(th) < level
            if not small.any() or small.all():
                continue
            start = np.where(small, 0.0, th)
            sparse, jac_sparse = family.project(start, pts, support=np.flatnonzero(start))
            sparse[np.abs(sparse) < 1e-15] = 0.0
            ph_s, res_s = refit(sparse)
            if res_s <= 1.5 * res + 1e-14 and jac_sparse <= max(jacobi, JACOBI_RTOL):
                th, jacobi, ph, res = sparse, jac_sparse, ph_s, res_s
                break
        return th, ph, res, jacobi_fit, jacobi

    # The directions the data cannot see at all are gauge. Where the bracket settled along
    # them lost the fit (noisy records: directions the exact data cannot see come out seen at
    # the noise level, and a Jacobi bracket along the rest may be far off), those seen no better
    # than the noise are freed too, and the better fit of the two is kept.
    keep = sv > _unseen_below(sv, 0.0)
    theta_, phi_, rel_, jacobi_fit, jacobi = settle(keep)
    loose = sv > _unseen_below(sv, fitted)
    if rel_ > RELAX_ABOVE * fitted and (~loose).sum() > (~keep).sum():
        other = settle(loose)
        if other[2] < rel_:
            keep = loose
            theta_, phi_, rel_, jacobi_fit, jacobi = other
    theta, phi, rel = theta_, phi_, rel_
    null = [n / n[np.argmax(np.abs(n))] for n in vt[~keep]]
    weak = [n / n[np.argmax(np.abs(n))] for n in vt[~loose]]
    return BracketFit(
        family=family,
        hamiltonians=hamiltonians,
        theta=theta,
        phi=phi,
        velocity_residual=rel,
        jacobi_fit=jacobi_fit,
        jacobi=jacobi,
        gauge_null=int((~keep).sum()),
        null_directions=null,
        points=pts,
        seconds=time.perf_counter() - t0,
        weak_directions=weak,
    )


@dataclass
class Refined:
    """A bracket and H refined jointly through the found structure's integrator."""

    theta: np.ndarray
    phi: np.ndarray
    family: Any
    system: Any
    stepper: Any
    jacobi: float
    history: list[float]


def refine_through_integrator(
    data: TrajectoryData,
    family: Any,
    theta: np.ndarray,
    hamiltonians: Any,
    phi: np.ndarray,
    make: Any,
    points: np.ndarray,
    max_iter: int = REFINE_ITER,
) -> Refined | None:
    """Gauss–Newton on the one-step residuals of the structure's own integrator over the
    bracket's non-zero coefficients (the largest held at +1: the scale gauge) and H's, with
    the chord Jacobian at the midpoints x̄ (h·Π_a(x̄)∇H(x̄) for θ_a, h·π(x̄)∇φ_m(x̄) for φ_m)
    and Jacobi imposed again after each step. The velocity-level bracket carries the
    finite-difference error of the records' velocities; this removes it. None where no
    iterate improved on the start. ``make``: a system → its Hamiltonian family (of which
    ``hamiltonians`` is a restriction). None too where the start's integrator fails on a
    training record."""
    from .scoring import one_step

    starts, targets = data.pairs("train")
    scale = np.linalg.norm(starts, axis=1).clip(1e-300)[:, None]
    mid = 0.5 * (starts + targets)
    exps = hamiltonians.exponents
    support = np.flatnonzero(theta)
    pinned = int(np.argmax(np.abs(theta)))
    free = support[support != pinned]

    def build(th: np.ndarray, ph: np.ndarray) -> tuple[Any, Any, Any] | None:
        try:
            system = family.system(th)
            hf = make(system).restrict(exps)
            return hf, hf.stepper(ph), system
        except (ValueError, FloatingPointError, np.linalg.LinAlgError):
            return None

    def residual(th: np.ndarray, ph: np.ndarray) -> tuple[np.ndarray, float, Any]:
        built = build(th, ph)
        if built is None:
            return np.zeros(0), math.inf, None
        r = ((one_step(built[1], starts, data.h) - targets) / scale).reshape(-1)
        cost = float(np.mean(r * r))
        return r, (cost if math.isfinite(cost) else math.inf), built

    r, cost, built = residual(theta, phi)
    if built is None or not math.isfinite(cost):
        # A step failed on some record (NaN in r): no chord step can be solved from it.
        return None
    start_cost, history = cost, [cost]
    jacobi = family.jacobi_residual(theta, points)
    for _ in range(max_iter):
        hf = built[0]
        grads = hf.gradients(mid)  # (B, n, M)
        j_phi = data.h * (family.bivector(mid, theta) @ grads) / scale[..., None]
        grad_h = grads @ phi
        j_th = np.einsum("bija,bj->bia", family.basis(mid)[..., free], grad_h)
        j_th = data.h * j_th / scale[..., None]
        jac = np.concatenate([j_th, j_phi], axis=2).reshape(-1, len(free) + len(phi))
        step = _lstsq(jac, -r)
        lam, improved = 1.0, False
        while lam >= 1.0 / 16:
            th = theta.copy()
            th[free] += lam * step[: len(free)]
            th, jac_res = family.project(th, points, support=support)
            if not (np.isfinite(th[pinned]) and abs(th[pinned]) > 0):
                # The projection took the scale-gauge coefficient to 0: a shorter step.
                lam /= 2
                continue
            th = th / th[pinned]
            ph = phi + lam * step[len(free) :]
            r_new, c_new, b_new = residual(th, ph)
            if c_new < cost:
                improved = True
                break
            lam /= 2
        if not improved:
            break
        gain = (cost - c_new) / max(cost, 1e-300)
        theta, phi, r, cost, built, jacobi = th, ph, r_new, c_new, b_new, jac_res
        history.append(cost)
        if gain < 1e-3:
            break
    if cost >= start_cost:
        return None
    hf = built[0]
    final_system = hf.system(phi)
    return Refined(
        theta=theta,
        phi=phi,
        family=hf,
        system=final_system,
        stepper=hf.stepper(phi, final_system),
        jacobi=jacobi,
        history=history,
    )


def velocity_errors(trajs: list[np.ndarray], h: float) -> np.ndarray:
    """Each velocity's own relative error estimate, in the order of
    :func:`~poisson_rs.learn.structure_fit.velocities`: |v_{2q} − v_{2q−2}| / |v_{2q}|, central
    differences of orders 2q and 2q − 2 at the record (q ≤ 4), its running median over the
    :data:`ERROR_WINDOW` records about it on the trajectory; NaN where a trajectory is too short
    for two orders (q < 2). Truncation error changes smoothly along a trajectory and the running
    median follows it; noise changes from record to record and the median levels it out."""
    from .hamiltonian import _fd_weights

    out = []
    for t in trajs:
        q = min(4, (len(t) - 1) // 2)
        if q < 2:
            out.append(np.full(len(t) - 1 if q == 0 else len(t) - 2 * q, np.nan))
            continue
        m = len(t) - 2 * q
        hi, lo = _fd_weights(np.arange(-q, q + 1)), _fd_weights(np.arange(-q + 1, q))
        v_hi = sum(hi[j] * t[j : j + m] for j in range(2 * q + 1)) / h
        v_lo = sum(lo[j] * t[j + 1 : j + 1 + m] for j in range(2 * q - 1)) / h
        e = np.linalg.norm(v_hi - v_lo, axis=1) / np.linalg.norm(v_hi, axis=1).clip(1e-300)
        half = min(ERROR_WINDOW // 2, (m - 1) // 2)
        padded = np.pad(e, half, mode="edge")
        window = np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1)
        out.append(np.median(window, axis=1))
    return np.concatenate(out) if out else np.zeros(0)


def velocity_weights(errors: np.ndarray) -> np.ndarray:
    """A weight per velocity, med/max(e, med) for its error estimate e (:func:`velocity_errors`)
    and their median med; 1 where e is not defined. Records whose differences are poorer than
    the rest (a fast passage: on PNN's charged particle 3e-4 there, 2e-6 at the median) count as
    what they are worth instead of setting the bracket's error. All weights are 1 where no
    estimate reaches :data:`ERROR_SPREAD` × the median (noise, whose estimates the running
    median levels, or a trajectory without fast passages)."""
    seen = np.isfinite(errors)
    if not seen.any():
        return np.ones(errors.shape)
    med = max(float(np.median(errors[seen])), 1e-300)
    if float(np.max(errors[seen])) < ERROR_SPREAD * med:
        # Errors alike (noise, or a slow trajectory): weights would only cost efficiency
        # (discovery on DPNN's heavy top at σ = 1e-4 stops snapping to se(3)* with them).
        return np.ones(errors.shape)
    return np.where(seen, med / np.maximum(np.where(seen, errors, med), med), 1.0)


def velocity_floor(
    x: np.ndarray, v: np.ndarray, errors: np.ndarray, weights: np.ndarray | None = None
) -> float:
    """The records' own velocity error, relative, in the fits' weights (1/|x| times
    ``weights``): √(Σ (w e |v|)² / Σ (w |v|)²) over the velocities ``v`` at states ``x`` whose
    error estimate ``errors`` (:func:`velocity_errors`) is defined; NaN where none is."""
    seen = np.isfinite(errors)
    if not seen.any():
        return math.nan
    w = 1.0 / np.linalg.norm(x, axis=1).clip(1e-300)
    if weights is not None:
        w = w * weights
    size = (np.linalg.norm(v, axis=1) * w)[seen]
    den = float(np.sum(size**2))
    return math.sqrt(float(np.sum((errors[seen] * size) ** 2)) / den) if den > 0 else math.nan


class UnknownStructure:
    """What the data are checked against before a structure is found: a dimension, no
    Casimirs known, no domain."""

    title = "unknown (to be discovered)"

    def __init__(self, dim: int) -> None:
        self.dim = dim

    def casimirs(self, x: Any) -> None:
        return None


def warn_not_explained(best: str, error: float, threshold: float) -> None:
    warnings.warn(
        f"structure discovery: no bracket family tried explains the data (the best, {best}, "
        f"has one-step error {error:.2e} above the noise level {threshold:.2e}); the data may "
        "not come from a Poisson system of these families (damping, forcing, or a larger "
        "bracket); report.explained is False",
        NotExplainedWarning,
        stacklevel=3,
    )


def learn_discover(
    trajectories: Any,
    h: float,
    *,
    mode: str = "auto",
    degree: int | None = None,
    max_degree: int | None = None,
    order: int | None = None,
    test_fraction: float = 0.2,
    seed: int = 0,
    max_iter: int = 30,
    verbose: bool = False,
    progress: bool | None = None,
    refine: bool = True,
    snap: str = "noise",
    refit: bool = True,
    given: Callable[[Any, int], tuple[Any, Any]] | None = None,
    max_seconds: float | None = None,
) -> tuple[Any, Any]:
    """:func:`poisson_rs.learn` with ``structure="discover"``: see the module docstring.
    ``refine``: refine the bracket and H jointly through the found structure's integrator
    (:func:`refine_through_integrator`). ``snap``: when the bracket snapped to twelfths
    replaces the learned one (:data:`SNAPS`): "noise" (default) where H refitted on it fits the
    training records at least as well or explains them at the noise level, "fit" where it fits
    at least as well only, "off" never. ``refit``: once a pair explains the data, H's
    coefficients on the kept bracket are fitted again on every record, held-out ones included
    (the choice and the errors in the report stay the held-out ones). ``given``: learns H of
    a degree with a structure given (``pr.learn(..., structure=found, degree=d)``, the same
    split and options), for step 5 of the module docstring (:func:`_through_own_path`); None:
    step 5 is skipped. ``max_seconds``: no pair after the first is started once this many
    seconds have passed (the rest are listed as not tried)."""
    from ..structures import bracket_families
    from .data import _as_list, check_seed, prepare, refuse_drift
    from .options import EXACT_LEVEL, MAX_DEGREE, check_bool, check_int, check_seconds
    from .report import Candidate, LearnReport
    from .scoring import all_records, errors, progress_bar
    from .structure_fit import fit_structure_hamiltonian, velocities

    if mode not in ("auto", "hamiltonian"):
        raise ValueError(
            f"mode {mode!r} does not apply to structure discovery; the modes that apply to it: "
            "'auto', 'hamiltonian'"
        )
    if degree is not None:
        degree = check_int(degree, "degree", 1, MAX_DEGREE)
    if max_degree is not None:
        max_degree = check_int(max_degree, "max_degree", 1, MAX_DEGREE)
    if snap not in SNAPS:
        raise ValueError(f"snap must be one of {SNAPS}, got {snap!r}")
    max_iter = check_int(max_iter, "max_iter", 1, 10_000)
    max_seconds = check_seconds(max_seconds, "max_seconds")
    refit = check_bool(refit, "refit")
    seed = check_seed(seed)
    verbose = check_bool(verbose, "verbose")
    if progress is not None:
        progress = check_bool(progress, "progress")
    trajs = _as_list(trajectories)
    data = prepare(
        trajs, h, None, test_fraction=test_fraction, seed=seed,
        system=UnknownStructure(_dimension(trajs)),
    )  # fmt: skip
    refuse_drift(data)
    offered = bracket_families(data.dim)
    threshold = 1.5 * math.sqrt(2 * data.dim) * data.noise + 1e-12
    snap_tol = snap_tolerance(data.noise)

    def reaches_noise(one_step: float) -> bool:
        """Whether a one-step error explains the records: at their noise level, or below
        EXACT_LEVEL where the noise level is unknown."""
        return one_step <= (threshold if math.isfinite(threshold) else EXACT_LEVEL)

    held = bool(data.test)
    err = "held-out one-step error" if held else "training one-step error (nothing held out)"
    x, v = velocities(data.train, data.h)
    verr = velocity_errors(data.train, data.h)
    vw = velocity_weights(verr)
    states = np.concatenate(data.train + data.test)

    # The (bracket family, H degree) pairs, smallest first.
    candidates: list[Candidate] = []
    pairs: list[tuple[Any, Any, int, Any]] = []
    for family in offered:
        why = family.applies(states)
        if why is None and len(family) > MAX_BRACKET_PARAMETERS:
            why = f"{len(family)} bracket coefficients, above {MAX_BRACKET_PARAMETERS}"
        if why is not None:
            candidates.append(_row(Candidate, family.name, len(family), f"not searched: {why}"))
            continue
        template = family.template_system()
        tried = template.learn_degrees()
        top = max_degree or MAX_DEGREE
        degrees = [degree] if degree is not None else [d for d in tried if d <= top] or [top]
        makes = [(d, _polynomials(d, order)) for d in degrees]
        if degree is None and supports_library(template):
            makes += [(d, _library(d, order)) for d in LIBRARY_DEGREES if d <= top]
            if data.dim % 2 == 0 and data.dim >= 4:
                # Planar points (x₁, x₂), (x₃, x₄), …: the distance libraries, as pr.learn
                # tries them with the structure given (PNN's charged particle: 1/|x| in H).
                makes += [
                    (d, _library(d, order, **options))
                    for options in DISTANCE_LIBRARIES
                    for d in LIBRARY_DISTANCE_DEGREES
                    if d <= top
                ]
        pairs += [(family, make(template), d, make) for d, make in makes]
    if not pairs:
        raise ValueError(
            "trajectories: no bracket family applies to these states ("
            + "; ".join(f"{c.family}: {c.reason}" for c in candidates)
            + ")"
        )
    pairs.sort(key=lambda item: len(item[0]) + len(item[1]))

    finals: dict[int, tuple[Any, Any, Any]] = {}

    def integrator_candidate(fit: BracketFit, d: int, make: Any) -> Candidate:
        name = f"{fit.family.name}/{fit.hamiltonians.name}"
        t0 = time.perf_counter()
        try:
            structure = fit.family.system(fit.theta)
            sfit = fit_structure_hamiltonian(
                data, structure, d, max_iter=max_iter, verbose=verbose, family=make(structure)
            )
        except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
            cand = _row(Candidate, name, len(fit.family) + len(fit.hamiltonians), "")
            cand.reason = f"the projected bracket was refused: {exc}"
            return cand
        hfam, phi, system, stepper = sfit.family, sfit.theta, sfit.system, sfit.stepper
        if refine:
            better = refine_through_integrator(
                data, fit.family, fit.theta, hfam, phi, make, fit.points
            )
            if better is not None:
                fit.theta, fit.jacobi = better.theta, better.jacobi
                hfam, phi, system, stepper = (
                    better.family,
                    better.phi,
                    better.system,
                    better.stepper,
                )
                if verbose:
                    print(f"{name}: refined through the integrator, cost {better.history}")
        # Brackets of physical systems have simple coefficients: the learned θ snapped to
        # twelfths where it lies within snap_tol of one, kept if Jacobi holds exactly and H
        # refitted on it fits the training records at least as well, or explains them at the
        # noise level: the refinement's bracket may absorb the integrator's own error (a better
        # one-step fit, a worse structure), and the simpler bracket that explains the data wins.
        # Where one direction N of the bracket is unseen (N∇H ≡ 0 on the data), or, with noisy
        # records, seen no better than the noise, the simple bracket may lie along it: the
        # rigid body's least-norm θ is not so(3)*, θ + αN is.
        snapped = _snap(fit.theta, snap_tol) if snap != "off" else None
        if snap != "off" and not _simple(snapped if snapped is not None else fit.theta, 0.0):
            along = None
            for directions in (fit.null_directions, fit.weak_directions):
                if along is None and len(directions) == 1:
                    along = _snap_in_orbit(fit.theta, directions[0], snap_tol)
            snapped = along if along is not None else snapped
        if snapped is not None and fit.family.jacobi_residual(snapped, fit.points) <= JACOBI_RTOL:
            try:
                structure = fit.family.system(snapped)
                sfit2 = fit_structure_hamiltonian(
                    data, structure, d, max_iter=max_iter, family=make(structure)
                )
            except (ValueError, FloatingPointError, np.linalg.LinAlgError):
                sfit2 = None
            if sfit2 is not None and (
                train_cost(sfit2.stepper, data) <= train_cost(stepper, data)
                or (snap == "noise" and reaches_noise(errors(sfit2.stepper, data)[0]))
            ):
                fit.theta, fit.jacobi = snapped, fit.family.jacobi_residual(snapped, fit.points)
                hfam, phi = sfit2.family, sfit2.theta
                system, stepper = sfit2.system, sfit2.stepper
                if verbose:
                    print(f"{name}: bracket snapped to twelfths")
        one, roll = errors(stepper, data)
        # What the refit on every record needs: the kept bracket's structure and H's family.
        final = (fit.family.system(fit.theta), hfam, phi)
        cand = Candidate(
            family=name,
            parameters=int(np.count_nonzero(fit.theta)) + int(np.count_nonzero(phi)),
            order=hfam.order,
            seconds=fit.seconds + time.perf_counter() - t0,
            one_step=one,
            rollout=roll,
            stepper=stepper,
            system=system,
            hamiltonian_family=hfam.description,
            hamiltonian_text=hfam.text(phi),
            gauge=_GAUGE.format(casimir=hfam.gauge),
            fit=sfit,
            bracket_family=fit.family.description,
            bracket_text=_bracket_text(fit, list(system.component_names)),
            jacobi_residual=fit.jacobi,
            velocity_residual=fit.velocity_residual,
            casimirs_text=str(getattr(system, "casimir_label", "n/a")),
            null_directions=list(fit.null_directions),
        )
        finals[id(cand)] = final
        return cand

    def judge_on_own_path(
        cand: Candidate, kept: Candidate | None, candidates: list[Candidate]
    ) -> Candidate | None:
        """With noisy records (a noise threshold and the pair's one-step error above
        EXACT_LEVEL), a pair within :data:`OWN_PATH_WITHIN` of the noise level is tried with H
        fitted again on its structure's own path where it learns on T*G: shooting windows
        average the noise over each window where the one-step fit regresses on noisy starts.
        Where both explain the held-out records at the noise level their errors cannot tell
        them apart (DPNN's heavy top at σ = 1e-4: rollouts 6.1e-4 against 5.9e-4, the T*G fit 7×
        closer to the exact flow), so the T*G fit is kept where it reaches the noise level, or,
        with the pair kept, where its rollout is closer. Returns the kept candidate."""
        # Not on exact records (a fit to round-off has nothing to gain), nor far from the
        # noise level (no refit of H turns a wrong bracket into the right one).
        noisy = math.isfinite(threshold) and min(threshold, cand.one_step) > EXACT_LEVEL
        near = cand.one_step <= OWN_PATH_WITHIN * threshold
        if given is None or id(cand) not in finals or not (noisy and near):
            return kept
        structure, hfam, phi = finals[id(cand)]
        own = _through_own_path(cand, structure, hfam.degree, int(np.count_nonzero(phi)), given)
        if own is None:
            return kept
        candidates.append(own)
        if reaches_noise(own.one_step) or (kept is cand and own.rollout < cand.rollout):
            own.reason = (
                f"the pair above, H fitted again on T*G (noisy records): held-out one-step "
                f"{own.one_step:.2e}, rollout {own.rollout:.2e} against {cand.rollout:.2e}"
                + ("; H's coefficients refitted on all records" if held and refit else "")
            )
            cand.reason += "; H fitted again on T*G below"
            return own
        own.reason = (
            f"H fitted again on T*G: {err} {own.one_step:.2e} above the noise level, rollout "
            f"{own.rollout:.2e} not below the pair's {cand.rollout:.2e}"
        )
        return kept

    kept: Candidate | None = None
    best_v = math.inf
    skipped: list[tuple[BracketFit, int, Any, int]] = []
    floor = velocity_floor(x, v, verr, vw)
    screen_level = SCREEN_FACTOR * max(floor, 1e-10) if math.isfinite(floor) else math.nan
    bar = progress_bar(len(pairs), progress)
    started, unsearched = time.perf_counter(), len(candidates)
    try:
        for family, hams, d, make in pairs:
            name = f"{family.name}/{hams.name}"
            # The first pair always runs: something is fitted, however small the budget.
            spent = (
                max_seconds is not None
                and len(candidates) > unsearched
                and time.perf_counter() - started >= max_seconds
            )
            if kept is not None or spent:
                why = (
                    "not tried: a smaller pair was kept"
                    if kept is not None
                    else f"not tried: the time budget (max_seconds = {max_seconds:g}) was spent"
                )
                candidates.append(_row(Candidate, name, len(family) + len(hams), why))
                continue
            bar.set_postfix_str(name)
            fit = fit_bracket(data, family, hams, x, v, seed, weights=vw)
            best_v = min(best_v, fit.velocity_residual)
            if verbose:
                print(
                    f"{name}: velocity residual {fit.velocity_residual:.2e}, Jacobi "
                    f"{fit.jacobi_fit:.1e} → {fit.jacobi:.1e}"
                )
            # Screened out: far above the records' own velocity error (order-8 against
            # order-6 differences), or, where that cannot be told, above a smaller pair.
            limit = screen_level if math.isfinite(screen_level) else SCREEN_FACTOR * best_v
            if fit.velocity_residual > max(limit, 1e-10):
                what = (
                    f"the records' velocity error ({floor:.2e})"
                    if math.isfinite(screen_level)
                    else f"a smaller pair's ({best_v:.2e})"
                )
                cand = _row(
                    Candidate,
                    name,
                    len(family) + len(hams),
                    f"velocity fit {fit.velocity_residual:.2e}, above {SCREEN_FACTOR:g}× "
                    f"{what}: not fitted through the integrator",
                )
                skipped.append((fit, d, make, len(candidates)))
                cand.velocity_residual, cand.jacobi_residual = fit.velocity_residual, fit.jacobi
                cand.seconds = fit.seconds
                candidates.append(cand)
                bar.update(1)
                continue
            cand = integrator_candidate(fit, d, make)
            bar.update(1)
            candidates.append(cand)
            if verbose:
                print(f"{cand.family}: one-step {cand.one_step:.3e}")
            if cand.stepper is None:
                continue
            if math.isfinite(threshold) and reaches_noise(cand.one_step):
                kept = cand
                cand.reason = f"the smallest pair whose {err} reaches the data's noise level"
            elif reaches_noise(cand.one_step):
                kept = cand
                cand.reason = f"noise level unknown; {err} below {EXACT_LEVEL:g} (exact data)"
            else:
                cand.reason = f"{err} {cand.one_step:.2e} above the noise level {threshold:.2e}"
            kept = judge_on_own_path(cand, kept, candidates)
        # Nothing came near the velocity floor: the best pairs whose integrator can be built
        # are still fitted through it, so that the report shows how far they are.
        skipped.sort(key=lambda item: item[0].velocity_residual)
        for fit, d, make, index in skipped:
            if kept is not None or any(c.stepper is not None for c in candidates):
                break
            cand = integrator_candidate(fit, d, make)
            if cand.stepper is not None:
                cand.reason = candidates[index].reason.replace(
                    "not fitted through the integrator", "the best velocity fit"
                )
                candidates[index] = cand
        bar.total = bar.n
        bar.refresh()
    finally:
        bar.close()
    for c in candidates:
        if c.stepper is not None and c is not kept and not c.reason:
            c.reason = "a smaller pair was kept"
    explained = kept is not None
    if kept is None:
        scored = [c for c in candidates if c.stepper is not None]
        if not scored:
            raise ValueError(
                "structure discovery: no bracket family could be fitted to these data ("
                + "; ".join(f"{c.family}: {c.reason}" for c in candidates)
                + ")"
            )
        kept = min(scored, key=lambda c: c.one_step)
        kept.reason = f"NOT EXPLAINED: no pair reached the noise level; the best {err}"
        warn_not_explained(kept.family, kept.one_step, threshold)
    if explained and held and refit and id(kept) in finals:
        _refit_on_all_records(kept, finals[id(kept)], all_records(data), max_iter)
    kept.kept = True
    report = LearnReport.of(
        data,
        mode=f"discover/{mode}",
        candidates=candidates,
        kept=kept,
        threshold=threshold,
        seed=seed,
        explained=explained,
    )
    return kept.stepper, report


_GAUGE = (
    "{casimir}; the bracket up to π → λπ with H → H/λ (fixed: its largest coefficient is +1) "
    "and π → π + N with N∇H ≡ 0 (fixed: the least-norm bracket the data allow)"
)


def _bracket_text(fit: BracketFit, names: list[str]) -> str:
    """The bracket, and the directions N (N∇H ≡ 0 on the data) it may be moved along."""
    text = fit.family.text(fit.theta, names, digits=10)
    if len(fit.null_directions) > 2:
        return text + (
            f"  [+ any combination of {len(fit.null_directions)} directions N with N∇H ≡ 0 "
            "on the data: report.kept.null_directions]"
        )
    for n in fit.null_directions:
        n = np.where(np.abs(n) < SPARSE_RTOL, 0.0, n)
        text += f"  [+ α·({fit.family.text(n, names, digits=6)}) for any α: N∇H ≡ 0]"
    return text


def _through_own_path(
    kept: Any,
    structure: Any,
    degree: int,
    h_parameters: int,
    given: Callable[[Any, int], tuple[Any, Any]],
) -> Any | None:
    """The kept bracket with H fitted by the found structure's own learning path, as a
    candidate, or None where it has none (only a structure that learns on T*G has one besides
    :mod:`~poisson_rs.learn.structure_fit`) or the fit fails. With noisy records the T*G path's
    fit through shooting windows can be the better one (on DPNN's heavy top at σ = 1e-4 the
    one-step fit of the discovery is 7× the T*G fit's error at the horizon)."""
    if not getattr(structure, "trainable", False):
        return None
    t0 = time.perf_counter()
    try:
        stepper, report = given(structure, degree)
    except (ValueError, FloatingPointError, np.linalg.LinAlgError):
        return None
    their = report.kept
    if their.stepper is None or not math.isfinite(their.rollout):
        return None
    return dataclasses.replace(
        kept,
        family=f"{kept.family} → T*G/{their.family}",
        parameters=kept.parameters - h_parameters + int(their.parameters),
        order=their.order,
        seconds=time.perf_counter() - t0,
        one_step=their.one_step,
        rollout=their.rollout,
        reason="",
        stepper=stepper,
        model_bytes=their.model_bytes,
        system=report.system,
        hamiltonian_family="",
        hamiltonian_text="",
        gauge=_GAUGE.format(casimir="a Casimir of the algebra"),
        fit=their.fit,
    )


def _refit_on_all_records(
    kept: Any, final: tuple[Any, Any, Any], whole: TrajectoryData, max_iter: int
) -> None:
    """H's nonzero terms on the kept bracket fitted again on every record: the held-out share
    (a whole trajectory of three) adds what it saw of the flow. Kept as it was where the fit
    fails."""
    from .structure_fit import fit_structure_hamiltonian

    structure, hfam, phi = final
    terms = [e for e, t in zip(hfam.exponents, phi, strict=True) if t != 0]
    if not terms:
        return
    try:
        fit = fit_structure_hamiltonian(
            whole, structure, hfam.degree, family=hfam.restrict(terms), max_iter=max_iter,
            sparse=False,
        )  # fmt: skip
    except (ValueError, FloatingPointError, np.linalg.LinAlgError):
        return
    kept.stepper, kept.system, kept.fit = fit.stepper, fit.system, fit
    kept.hamiltonian_text = fit.family.text(fit.theta)
    kept.reason += "; H's coefficients refitted on all records"


def snap_tolerance(noise: float) -> float:
    """How close (relative to the largest coefficient) a coefficient must be to a twelfth to be
    tried at it: :data:`SNAP_RTOL`, or :data:`SNAP_NOISE` × the records' relative noise level
    ``noise`` where that is larger, capped at :data:`SNAP_MAX`. On the heavy top at σ = 1e-4
    the refined se(3)* coefficients sit 3e-4 from ±1: tried at ±1 they explain the records."""
    if not math.isfinite(noise):
        return SNAP_RTOL
    return max(SNAP_RTOL, min(SNAP_NOISE * noise, SNAP_MAX))


def _near_twelfths(theta: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Each coefficient's nearest multiple of 1/12, and whether it lies within ``tol``
    (relative to the largest coefficient) of it."""
    near = np.round(theta * 12.0) / 12.0
    return near, np.abs(theta - near) <= tol * max(float(np.max(np.abs(theta))), 1e-300)


def _snap(theta: np.ndarray, tol: float = SNAP_RTOL) -> np.ndarray | None:
    """θ with every coefficient within ``tol`` (relative to the largest, +1) of a multiple of
    1/12 set to it; None where nothing moves."""
    near, close = _near_twelfths(theta, tol)
    out = np.where(close, near, theta)
    return None if np.array_equal(out, theta) else out


def _simple(theta: np.ndarray, tol: float) -> bool:
    """Whether every coefficient lies within ``tol`` (relative to the largest) of a twelfth."""
    return bool(np.all(_near_twelfths(theta, tol)[1]))


def _snap_in_orbit(theta: np.ndarray, direction: np.ndarray, tol: float) -> np.ndarray | None:
    """A bracket (θ + αN)/s, N = ``direction``, whose every coefficient is a twelfth and whose
    largest is +1, where one lies within ``tol`` of θ's orbit (the simplest; None where none
    does). Two coefficients i, j set to twelfths v_i, v_j fix (α, s):
    θ_i + αN_i = s v_i, θ_j + αN_j = s v_j; every pair and every v in [−1, 1] is tried."""
    support = np.flatnonzero((np.abs(theta) > 0) | (np.abs(direction) > 0))
    if support.size < 2 or support.size > 40:
        return None
    grid = np.arange(-12, 13) / 12.0
    # every pair (v_i, v_j) of twelfths in [−1, 1]
    vi, vj = np.repeat(grid, grid.size), np.tile(grid, grid.size)
    best: tuple[tuple[int, int, float], np.ndarray] | None = None
    for a_, i in enumerate(support):
        for j in support[a_ + 1 :]:
            # [N_i, −v_i; N_j, −v_j] (α, s) = (−θ_i, −θ_j)
            det = -direction[i] * vj + vi * direction[j]
            ok = np.abs(det) > 1e-12
            if not ok.any():
                continue
            alpha = (theta[i] * vj - vi * theta[j])[ok] / det[ok]
            scale = (theta[i] * direction[j] - direction[i] * theta[j]) / det[ok]
            good = np.abs(scale) > 1e-12
            if not good.any():
                continue
            cands = (theta[None, :] + alpha[good, None] * direction[None, :]) / scale[good, None]
            # the scale gauge of fit_bracket: the (first) largest coefficient +1
            big = np.argmax(np.abs(cands), axis=1)
            cands = cands / cands[np.arange(len(cands)), big][:, None]
            dist = np.max(np.abs(cands - np.round(cands * 12.0) / 12.0), axis=1)
            # The simplest of those in the orbit: the smallest sum of denominators, then the
            # fewest coefficients moved to 0, then the closest. The rigid body with rational
            # inertia has many brackets of twelfths along N: so(3)* (all ±1) and the one
            # with a zero and H = |μ|²/4 tie on denominators; so(3)* is the first.
            twelfths = np.round(cands * 12.0).astype(np.int64)
            # ties of the largest |coefficient| broken on the rounded values, not on noise
            lead = twelfths[np.arange(len(twelfths)), np.argmax(np.abs(twelfths), axis=1)]
            twelfths = twelfths * np.sign(lead)[:, None]
            denominators = np.sum(12 // np.gcd(twelfths, 12), axis=1)
            zeros = np.sum(twelfths[:, support] == 0, axis=1)
            for k in np.flatnonzero(dist <= tol):
                key = (int(denominators[k]), int(zeros[k]), float(dist[k]))
                if best is None or key < best[0]:
                    best = (key, twelfths[k] / 12.0)
    return None if best is None else best[1]


def train_cost(stepper: Any, data: TrajectoryData) -> float:
    """Mean squared relative one-step residual of ``stepper`` on the training pairs (inf where a
    step fails)."""
    from .scoring import one_step

    starts, targets = data.pairs("train")
    out = one_step(stepper, starts, data.h)
    r = (out - targets) / np.linalg.norm(starts, axis=1).clip(1e-300)[:, None]
    cost = float(np.mean(r * r))
    return cost if math.isfinite(cost) else math.inf


def _polynomials(degree: int, order: int | None) -> Any:
    """system → its polynomial Hamiltonians of ``degree``."""
    return lambda system: system.hamiltonian_family(degree, order)


def _library(degree: int, order: int | None, **options: Any) -> Any:
    """system → the term library of ``degree`` (and ``options``, :class:`LibraryFamily`'s) on
    its bracket (Taylor-HJ by jets)."""
    return lambda system: LibraryFamily(system, degree, order, **options)


def _row(candidate: Any, family: str, parameters: int, reason: str) -> Any:
    """A candidate that was not fitted through an integrator (no errors: n/a)."""
    return candidate(
        family=family,
        parameters=parameters,
        order=0,
        seconds=0.0,
        one_step=math.nan,
        rollout=math.nan,
        reason=reason,
    )


def _dimension(trajs: list[np.ndarray]) -> int:
    """The records' dimension, read before the full checks (which need it)."""
    if not trajs:
        raise ValueError("trajectories: got no trajectories")
    first = np.asarray(trajs[0])
    if first.ndim != 2 or not 2 <= first.shape[1] <= 10:
        raise ValueError(
            f"trajectories[0]: a trajectory must be (n_records, dim) with dim in 2..=10, got "
            f"shape {first.shape}"
        )
    return int(first.shape[1])

"""Learning a polynomial Hamiltonian H_θ = Σ_e θ_e μ^e from trajectories.

1. Warm start: the vector field is linear in θ (μ̇ = Π(μ)∇H_θ), so θ₀ is a linear least-squares
   fit of finite-difference velocities (central differences of order up to 8 along each
   trajectory; the midpoint rule for pairs).
2. Gauge: H is identifiable only up to a constant and Casimir functions, whose vector fields
   vanish. The constant is not in the family; the directions whose vector field is (numerically)
   zero on the data are projected out by an SVD of the warm-start design matrix, so θ lives in
   the orthogonal complement (for so(3) and a quadratic family, the |μ|² direction goes).
3. Levenberg–Marquardt on the residuals of the package's Poisson integrator for H_θ (Taylor-HJ
   of order K in the exponential chart) against the data, over one step and over a few steps,
   with Jacobians by the implicit function theorem (:mod:`.step`) and the chain rule through
   the Taylor coefficients (:mod:`.series`).
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch

from ..structures.lie_poisson import LieAlgebra, LiePoissonSystem, Polynomial
from .data import TrajectoryData
from .optimize import levenberg_marquardt
from .series import MonomialBasis, basis, monomials, series_jacobian, taylor_series
from .step import bisection_step

__all__ = ["PolynomialFit", "default_order", "fit_polynomial", "vector_field_design"]

#: Singular values of the (column-normalised) design matrix below this fraction of the largest
#: are gauge directions (constants, Casimirs) and are projected out.
GAUGE_RTOL = 1e-8
#: Records per shooting window (see :func:`shooting_refine`): long enough that the phase over
#: the window pins the frequencies, short enough that the rollout stays near the records.
SHOOTING_LENGTH = 128
#: Trajectories shorter than this are fitted by one- and multi-step residuals only.
SHOOTING_MIN_RECORDS = 8


def default_order(degree: int, dim: int) -> int:
    """Taylor-HJ order K fitted for a family of ``degree``: high enough that its discretisation
    error at the data's h sits below what exact data tell (K = 7 for a quadratic H on a
    3-dimensional algebra), low enough that the dense series (degree K(d − 1) + 1) stays small."""
    if degree <= 2:
        return 7 if dim <= 3 else 5
    return 5 if dim <= 3 else 3


def vector_field_design(algebra: LieAlgebra, family: list[tuple[int, ...]], mu: np.ndarray):
    """Column m: the vector field of μ^{family[m]} at each state, (B, n, P)."""
    n = algebra.dim
    d = max(sum(e) for e in family)
    b = basis(n, d)
    idx = [b.index[e] for e in family]
    _, dphi, _ = b.features(torch.as_tensor(mu, dtype=torch.float64))
    grads = dphi[:, :, idx].numpy()  # (B, n_i, P)
    # μ̇_j = Σ_{i,k} c[i,j,k] ∂H/∂μ_i μ_k
    return np.einsum("ijk,bip,bk->bjp", algebra.c, grads, mu)


def _fd_weights(offsets: np.ndarray) -> np.ndarray:
    """First-derivative weights on integer offsets (exact for polynomials up to len − 1)."""
    m = len(offsets)
    v = np.vander(offsets.astype(np.float64), m, increasing=True).T
    rhs = np.zeros(m)
    rhs[1] = 1.0
    return np.linalg.solve(v, rhs)


def velocities(trajs: list[np.ndarray], h: float) -> tuple[np.ndarray, np.ndarray]:
    """(states, velocities) from central differences of order up to 8 at interior records; a
    two-record trajectory gives its midpoint and (μ₁ − μ₀)/h."""
    xs, vs = [], []
    for t in trajs:
        q = min(4, (len(t) - 1) // 2)
        if q == 0:
            xs.append(0.5 * (t[:-1] + t[1:]))
            vs.append((t[1:] - t[:-1]) / h)
            continue
        w = _fd_weights(np.arange(-q, q + 1))
        m = len(t) - 2 * q
        v = sum(w[j] * t[j : j + m] for j in range(2 * q + 1)) / h
        xs.append(t[q : q + m])
        vs.append(v)
    return np.concatenate(xs), np.concatenate(vs)


@dataclass
class PolynomialFit:
    """A fitted polynomial Hamiltonian.

    ``family`` the exponents, ``theta`` their coefficients (gauge-fixed), ``order`` the Taylor-HJ
    order K, ``system`` the learned :class:`LiePoissonSystem`, ``history`` the training cost per
    LM iteration (mean squared relative residual), ``seconds`` the training time.
    """

    family: list[tuple[int, ...]]
    theta: np.ndarray
    order: int
    system: LiePoissonSystem
    history: list[float] = field(default_factory=list)
    seconds: float = 0.0
    gauge_dropped: int = 0
    correction: np.ndarray | None = None

    @property
    def hamiltonian(self) -> Polynomial:
        return self.system.polynomial

    @property
    def n_parameters(self) -> int:
        return int(np.count_nonzero(self.theta if self.correction is None else self.correction))


class _Model:
    """θ ↦ S(h, ·) coefficients and their Jacobian, and the residuals of the Taylor-HJ map."""

    def __init__(self, algebra: LieAlgebra, family, order: int, h: float) -> None:
        self.algebra = algebra
        self.c = algebra.c
        self.family = family
        self.order = order
        self.h = h
        self._cache: tuple | None = None
        # Newton's last solutions per call site: (μ, p), the start of the next solve there.
        self._newton: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}

    def _step(self, key: tuple, b, s, mu, jacobian: bool, ds=None):
        """:func:`bisection_step` from mu, Newton started from the solution p of the last
        evaluation with derivatives (the Levenberg–Marquardt iterate) at the same call site,
        shifted by the change of μ: trials and the next iterate lie near it, so Newton needs
        fewer iterations; the solution is the same."""
        key = (*key, tuple(mu.shape))
        p0 = None
        if key in self._newton:
            mu_old, p_old = self._newton[key]
            p0 = p_old + (mu - mu_old)
        step = bisection_step(b, self.c, s, mu, derivatives=jacobian, coeff_jacobian=ds, p0=p0)
        assert step.p is not None
        if jacobian:
            self._newton[key] = (mu, step.p)
        return step

    def coeffs(self, theta: np.ndarray, jacobian: bool):
        """(basis, S(h, ·) coefficients (N,), their Jacobian in θ (N, P) or None)."""
        key = theta.tobytes()
        if self._cache is not None and self._cache[0] == key:
            # A Jacobian evaluation serves the plain one too (its real part is the series).
            if not jacobian or self._cache[1][2] is not None:
                return self._cache[1]
        out: tuple[MonomialBasis, torch.Tensor, torch.Tensor | None]
        if jacobian:
            out = series_jacobian(self.c, self.family, theta, self.order, self.h)
        else:
            b, sk = taylor_series(self.c, self.family, torch.as_tensor(theta), self.order)
            powers = torch.tensor(
                [self.h**k for k in range(1, self.order + 1)], dtype=torch.float64
            )
            out = (b, powers @ sk, None)
        self._cache = (key, out)
        return out

    def residuals(self, theta, starts, targets, horizon: int, jacobian: bool):
        """Residuals Φ^L(μ_k) − μ_{k+L}, L = 1..horizon, relative to |μ|: (B·horizon·n,)
        and their Jacobian (B·horizon·n, P)."""
        b, s, ds = self.coeffs(theta, jacobian)
        mu = torch.as_tensor(starts)
        scale = torch.linalg.norm(mu, dim=1, keepdim=True).clamp_min(1e-300)
        dmu = None
        res, jac = [], []
        for ell in range(horizon):
            step = self._step(("residuals", horizon, ell), b, s, mu, jacobian, ds)
            if jacobian:
                assert step.d_coeffs is not None and step.d_state is not None
                dnew = step.d_coeffs  # (B, n, P)
                if dmu is not None:
                    dnew = dnew + step.d_state @ dmu
                dmu = dnew
                jac.append((dmu / scale[..., None]).reshape(-1, ds.shape[1]))
            mu = step.out
            res.append(((mu - torch.as_tensor(targets[:, ell])) / scale).reshape(-1))
        r = torch.cat(res).numpy()
        return r, (torch.cat(jac).numpy() if jacobian else None)

    def states(self, theta, starts, steps: int) -> np.ndarray:
        """Φ^k(starts), k = 0..steps, (B, steps + 1, n): the Rust integrator of S(h, ·) (the
        same map as :func:`bisection_step`, to round-off), so the sequential part is fast."""
        from ..export import model_bytes
        from ..integrators import LearnedIntegrator, integrate

        b, s, _ = self.coeffs(theta, False)
        n = b.n
        powers = np.concatenate([np.full((b.size, 1), 2, np.int64), b.powers], axis=1)
        # S(t, p) = (t/h)²·S(h, p): exact at t = h, and with no t¹ term the file's system
        # (H = 0, a map at the one h) loads without the first-order check against −t·H.
        coeffs = s.detach().numpy() / self.h**2
        nz = coeffs != 0.0
        raw = model_bytes(
            powers=powers[nz],
            coeffs=coeffs[nz],
            layers=[],
            mlp_power=1,
            chart="exp",
            system=LiePoissonSystem(self.algebra, Polynomial({(0,) * n: 0.0})),
            h_max=self.h,
            domain={"kind": "all"},
        )
        start = np.asarray(starts, dtype=np.float64)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out = integrate(LearnedIntegrator(raw), start, self.h, steps, on_failure="ignore")
        return np.asarray(out).reshape(len(start), steps + 1, n)

    def rollout(self, theta, starts, steps: int):
        """Φ^k(starts), k = 0..steps, with derivatives in θ and in the start states:
        (B, steps + 1, n), (B, steps + 1, n, P), (B, steps + 1, n, n). The states come from
        :meth:`states`; the derivatives from one batched implicit-function step at all of them,
        chained."""
        b, s, ds = self.coeffs(theta, True)
        traj = self.states(theta, starts, steps)
        bsz, _, n = traj.shape
        flat = torch.as_tensor(traj[:, :-1].reshape(-1, n))
        step = self._step(("rollout",), b, s, flat, True, ds)
        assert step.d_coeffs is not None and step.d_state is not None
        dc = step.d_coeffs.reshape(bsz, steps, n, -1)
        dsx = step.d_state.reshape(bsz, steps, n, n)
        dth = torch.zeros(bsz, n, ds.shape[1], dtype=torch.float64)
        dst = torch.eye(n, dtype=torch.float64).expand(bsz, n, n).clone()
        dths, dsts = [dth], [dst]
        for k in range(steps):
            dth = dc[:, k] + dsx[:, k] @ dth
            dst = dsx[:, k] @ dst
            dths.append(dth)
            dsts.append(dst)
        return torch.as_tensor(traj), torch.stack(dths, 1), torch.stack(dsts, 1)


def _rejected(p: int, jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """The residuals of a point where the step map is undefined: infinite (LM rejects it)."""
    return np.full(1, np.inf), (np.zeros((1, p)) if jacobian else None)


def _shooting_windows(trajs: list[np.ndarray], length: int) -> list[np.ndarray]:
    """Consecutive windows of at most ``length`` records (≥ 2) covering every trajectory."""
    out = []
    for t in trajs:
        k = 0
        while len(t) - k >= 2:
            out.append(t[k : k + length])
            k += length - 1
    return out


def shooting_refine(
    model: _Model,
    q: np.ndarray,
    z: np.ndarray,
    trajs: list[np.ndarray],
    *,
    length: int = SHOOTING_LENGTH,
    max_iter: int = 30,
    verbose: bool = False,
    offset: np.ndarray | float = 0.0,
) -> tuple[np.ndarray, float, int]:
    """Maximum likelihood under white noise on every record: θ = offset + q z and one free start
    state per window of ``length`` records are fitted so that the rollout Φ^k(start) matches
    every record of the window (residuals relative to |record|). Errors-in-variables, where
    one-step residuals put the noise of μ_k into the model; and a window's k-th record
    constrains H with weight k·h, so the long-time phase (the error at large T) is fitted from
    the whole span. Levenberg–Marquardt from z and the recorded starts; returns (z, RMS residual
    per coordinate, residuals count)."""
    wins = _shooting_windows(trajs, length)
    groups: dict[int, list[int]] = {}
    for i, w in enumerate(wins):
        groups.setdefault(len(w), []).append(i)
    n = wins[0].shape[1]
    pz = len(z)
    starts = np.array([w[0] for w in wins])

    def evaluate(zz, st, jacobian):
        rs, rows = [], []
        for ln, idx in groups.items():
            tg = np.stack([wins[i] for i in idx])  # (G, ln, n)
            if jacobian:
                out, dth, dst = model.rollout(offset + q @ zz, st[idx], ln - 1)
            else:
                out = torch.as_tensor(model.states(offset + q @ zz, st[idx], ln - 1))
            scale = np.linalg.norm(tg, axis=2, keepdims=True).clip(1e-300)
            rs.append(((out.numpy() - tg) / scale).reshape(-1))
            if jacobian:
                jt = (dth.numpy() @ q) / scale[..., None]  # (G, ln, n, pz)
                js = dst.numpy() / scale[..., None]  # (G, ln, n, n)
                block = np.zeros((len(idx), ln, n, pz + n * len(wins)))
                block[..., :pz] = jt
                for g, i in enumerate(idx):
                    block[g, :, :, pz + n * i : pz + n * (i + 1)] = js[g]
                rows.append(block.reshape(-1, block.shape[-1]))
        r = np.concatenate(rs)
        return r, (np.concatenate(rows) if jacobian else None)

    def guarded(x: np.ndarray, jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
        try:
            return evaluate(x[:pz], x[pz:].reshape(-1, n), jacobian)
        except FloatingPointError:  # a rollout that left the chart: the trial is rejected
            return _rejected(len(x), jacobian)

    fit = levenberg_marquardt(
        guarded,
        np.concatenate([z, starts.reshape(-1)]),
        max_iter=max_iter,
        rel_tol=1e-4,
        cost_floor=1e-30,
        label="shooting LM",
        verbose=verbose,
    )
    z, r, jac = fit.x[:pz], fit.r, fit.jac
    # Unbiased noise per coordinate: residual dof = residuals − fitted parameters.
    dof = max(len(r) - jac.shape[1], 1)
    return z, math.sqrt(float(r @ r) / dof), len(r)


def _windows(trajs: list[np.ndarray], horizon: int) -> tuple[np.ndarray, np.ndarray]:
    """Start states (B, n) and the next ``horizon`` records (B, horizon, n), for every record
    that has them."""
    starts, targets = [], []
    for t in trajs:
        m = len(t) - horizon
        for k in range(max(m, 0)):
            starts.append(t[k])
            targets.append(t[k + 1 : k + 1 + horizon])
    if not starts:
        return np.zeros((0, trajs[0].shape[1])), np.zeros((0, horizon, trajs[0].shape[1]))
    return np.array(starts), np.array(targets)


def fit_polynomial(
    data: TrajectoryData,
    algebra: LieAlgebra,
    degree: int,
    *,
    order: int | None = None,
    horizon: int = 4,
    max_iter: int = 30,
    family: list[tuple[int, ...]] | None = None,
    verbose: bool = False,
    sparse: bool = True,
    shooting: bool = True,
    known: Polynomial | None = None,
) -> PolynomialFit:
    """Fits H_θ of total degree ≤ ``degree`` (no constant) to ``data.train``; see the module
    docstring. ``horizon``: the longest multi-step residual (records permitting); ``sparse``:
    drop the terms the data do not resolve and refit (kept when the fit is as good);
    ``shooting``: refine by :func:`shooting_refine` where trajectories are long enough;
    ``known``: a known part of H, fixed: H = known + H_θ and only the correction H_θ is
    learned (mode "hj+data")."""
    t0 = time.perf_counter()
    n = algebra.dim
    family = family or monomials(n, degree, min_degree=1)
    known_terms = {} if known is None else {e: c for e, c in known.terms.items() if sum(e) > 0}
    full = list(family) + [e for e in known_terms if e not in family]
    offset = np.array([known_terms.get(e, 0.0) for e in full])
    embed = np.eye(len(full))[:, : len(family)]  # correction coefficients → full family
    order = order or default_order(max(sum(e) for e in full), n)
    x, v = velocities(data.train, data.h)
    if known_terms:
        # The correction fits what the known part leaves of the velocities.
        v = v - np.einsum("bjp,p->bj", vector_field_design(algebra, full, x), offset)
    a = vector_field_design(algebra, family, x)  # (B, n, P)
    w = 1.0 / np.linalg.norm(x, axis=1).clip(1e-300)
    a2 = (a * w[:, None, None]).reshape(-1, len(family))
    col = np.linalg.norm(a2, axis=0)
    col[col == 0] = 1.0
    u, sv, vt = np.linalg.svd(a2 / col, full_matrices=False)
    keep = sv > GAUGE_RTOL * sv[0]
    q = (vt[keep].T) / col[:, None]  # θ = q z
    z = (u[:, keep].T @ (v * w[:, None]).reshape(-1)) / sv[keep]
    qf = embed @ q  # H's coefficients over ``full``: offset + qf z
    model = _Model(algebra, full, order, data.h)
    # Residuals: one step over every pair, several steps over windows.
    s1, t1 = _windows(data.train, 1)
    sets = [(s1, t1, 1)]
    if horizon > 1 and max(len(t) for t in data.train) > horizon:
        sh, th = _windows(data.train, horizon)
        stride = max(1, horizon)
        sets.append((sh[::stride], th[::stride], horizon))

    def evaluate(zz, jacobian):
        rs, js = [], []
        try:
            for st, tg, hz in sets:
                r, j = model.residuals(offset + qf @ zz, st, tg, hz, jacobian)
                rs.append(r)
                js.append(j)
        except FloatingPointError:
            # A step that leaves the chart (|ad_x| near 2π): the trial is rejected, and a
            # start there ends the fit with an infinite cost (a candidate that fits nothing).
            return _rejected(len(zz), jacobian)
        r = np.concatenate(rs)
        return r, (np.concatenate(js) @ qf if jacobian else None)

    fit = levenberg_marquardt(
        evaluate, z, max_iter=max_iter, rel_tol=1e-3, cost_floor=1e-28, verbose=verbose
    )
    z, r, cost, history = fit.x, fit.r, fit.cost, fit.history
    shoot_sigma = math.nan
    if shooting and any(len(t) >= SHOOTING_MIN_RECORDS for t in data.train) and np.isfinite(cost):
        z, shoot_sigma, _ = shooting_refine(
            model,
            qf,
            z,
            [t for t in data.train if len(t) >= SHOOTING_MIN_RECORDS],
            offset=offset,
            max_iter=max_iter,
            verbose=verbose,
        )
        r, _ = evaluate(z, False)
        history.append(float(np.mean(r * r)))
    theta = q @ z
    if sparse and len(family) > 1:
        # Terms whose share of the vector field is below what the data resolve are dropped and
        # the rest refitted once (sequential thresholding, as in sparse regression).
        share = np.abs(theta) * col / max(float(np.linalg.norm(v * w[:, None])), 1e-300)
        # Noise per coordinate: the finite-difference estimate, or, where the records are too
        # few for it (pairs), the fit's own residual (one-step RMS ≈ √2 σ per coordinate).
        # With shooting, the fit's own residual per coordinate (consistent, where the
        # finite-difference estimate is only an upper bound).
        sigma = (
            shoot_sigma
            if math.isfinite(shoot_sigma)
            else data.noise
            if math.isfinite(data.noise)
            else math.sqrt(history[-1] / 2.0)
        )
        floor = max(10.0 * sigma, 1e-9)
        kept = [e for e, s in zip(family, share, strict=True) if s > floor]
        if kept and len(kept) < len(family):
            sub = fit_polynomial(
                data,
                algebra,
                degree,
                order=order,
                horizon=horizon,
                max_iter=max_iter,
                family=kept,
                verbose=verbose,
                sparse=False,
                shooting=shooting,
                known=known,
            )
            if sub.history[-1] <= 1.5 * history[-1] + 1e-28:
                sub.seconds = time.perf_counter() - t0
                return sub
    theta_full = offset + embed @ theta
    poly = Polynomial({e: float(t) for e, t in zip(full, theta_full, strict=True) if t != 0.0})
    system = LiePoissonSystem(algebra, poly, name="learned")
    return PolynomialFit(
        family=list(full),
        theta=theta_full,
        correction=theta if known_terms else None,
        order=order,
        system=system,
        history=history,
        seconds=time.perf_counter() - t0,
        gauge_dropped=int((~keep).sum()),
    )


def relative_field_error(
    learned: LiePoissonSystem, truth: LiePoissonSystem, states: np.ndarray
) -> float:
    """max |X_learned − X_true| / max |X_true| over ``states``: the gauge-free comparison."""
    a = np.asarray(learned.vector_field(states))
    b = np.asarray(truth.vector_field(states))
    return float(np.max(np.linalg.norm(a - b, axis=-1)) / np.max(np.linalg.norm(b, axis=-1)))

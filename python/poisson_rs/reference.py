"""Reference solutions of the free rigid body on so(3)* ≅ R³.

The body angular momentum μ evolves under the minus Lie–Poisson bracket with the kinetic energy
H(μ) = ½ Σ μᵢ²/Iᵢ, i.e. μ̇ = μ × ∇H(μ) = μ × (μ/I); the Casimir C(μ) = |μ|² and H are conserved.

:func:`exact_solution` evaluates the closed-form flow in Jacobi elliptic functions and
:func:`dop853_solution` integrates the same equations with SciPy's adaptive DOP853, as an
independent oracle and as the adaptive baseline.

Closed form (derived here, signs checked against DOP853). For I₁ < I₂ < I₃ write

    A = 2H I₃ − C = μ₁²(I₃−I₁)/I₁ + μ₂²(I₃−I₂)/I₂ ≥ 0,
    B = C − 2H I₁ = μ₂²(I₂−I₁)/I₂ + μ₃²(I₃−I₁)/I₃ ≥ 0,
    Δ = 2H I₂ − C = μ₁²(I₂−I₁)/I₁ − μ₃²(I₃−I₂)/I₃,

each evaluated as written on the right, which is free of cancellation except for Δ (whose sign is
the genuinely ill-conditioned question "which side of the separatrix"). With a₁² = I₁A/(I₃−I₁)
and a₃² = I₃B/(I₃−I₁):

    Δ ≥ 0 (circulation about the axis of smallest inertia, "d" = 1, "c" = 3):
        a₂² = I₂B/(I₂−I₁),  m = (I₃−I₂)B/((I₂−I₁)A),  1−m = (I₃−I₁)Δ/((I₂−I₁)A),
        λ² = (I₂−I₁)A/(I₁I₂I₃);
    Δ < 0 (circulation about the axis of largest inertia, "d" = 3, "c" = 1):
        a₂² = I₂A/(I₃−I₂),  m = (I₂−I₁)A/((I₃−I₂)B),  1−m = (I₃−I₁)|Δ|/((I₃−I₂)B),
        λ² = (I₃−I₂)B/(I₁I₂I₃);

and in both cases, with τ = λt + τ₀, p = sign μ_d, r = sign μ_c (constant along the orbit),

    μ_d = p a_d dn(τ|m),   μ₂ = p r a₂ sn(τ|m),   μ_c = r a_c cn(τ|m).

The same sign pattern holds on both sides of the separatrix. τ₀ ∈ [−K, K] is recovered from
sn τ₀ = p r μ₂/a₂, cn τ₀ = |μ_c|/a_c ≥ 0, dn τ₀ = |μ_d|/a_d through Carlson's form
F(φ|m) = sin φ · R_F(cos²φ, 1 − m sin²φ, 1), which needs neither m nor an arcsine and stays
accurate next to the separatrix. On the separatrix (Δ = 0, m = 1) the formulas hold with
sn = tanh, cn = dn = sech. Unsorted inertias are handled by sorting: for a permutation matrix P,
Pa × Pb = det(P) P(a × b), so an odd permutation reverses time. Two equal moments give a uniform
rotation about the symmetry axis; principal axes (and μ = 0) are equilibria.

Reference: E. Celledoni, F. Fassò, N. Säfström, A. Zanna, "The exact computation of the free
rigid body motion and its use in splitting methods", SIAM J. Sci. Comput. 30 (2008).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .protocols import provides
from .structures.lie_poisson import LiePoissonSystem, RigidBody

__all__ = ["RigidBody", "dop853_solution", "exact_solution", "reference_solution"]

FloatArray = NDArray[np.float64]

#: Cap on Landen/AGM steps; convergence is quadratic, even 1 − m = 1e-300 needs about 15.
_MAX_AGM_STEPS = 64


def _check_states_and_times(
    mu0: ArrayLike, times: ArrayLike, dim: int
) -> tuple[FloatArray, FloatArray, bool]:
    """Validate and return (states (m, dim), times (T,), single) where single means mu0 was
    (dim,)."""
    if np.iscomplexobj(mu0):
        raise ValueError("mu0 must be an array of real numbers, got complex values")
    try:
        states = np.asarray(mu0, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError("mu0 must be an array of real numbers") from exc
    if states.shape != (dim,) and (states.ndim != 2 or states.shape[1] != dim):
        raise ValueError(f"mu0 must have shape ({dim},) or (n, {dim}), got shape {states.shape}")
    if not np.all(np.isfinite(states)):
        raise ValueError("mu0 must be finite (found NaN or inf)")
    if np.iscomplexobj(times):
        raise ValueError("times must be an array of real numbers, got complex values")
    try:
        t = np.asarray(times, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError("times must be an array of real numbers") from exc
    if t.ndim != 1:
        raise ValueError(f"times must be a 1-D array, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError("times must be finite (found NaN or inf)")
    single = states.ndim == 1
    return np.atleast_2d(states), t, single


def _check_inputs(
    body: RigidBody, mu0: ArrayLike, times: ArrayLike
) -> tuple[FloatArray, FloatArray, bool]:
    """Validate and return (states (n, 3), times (T,), single) where single means mu0 was (3,)."""
    if not isinstance(body, RigidBody):
        raise TypeError(f"body must be a RigidBody, got {type(body).__name__}")
    return _check_states_and_times(mu0, times, 3)


def _jacobi_sn_cn_dn(
    u: FloatArray, m: FloatArray, m1: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Jacobi elliptic functions sn, cn, dn (u | m) for 0 ≤ m ≤ 1.

    Descending Landen transformation (arithmetic–geometric mean), as in Cephes ``ellpj``, but
    fed with the complementary parameter ``m1`` = 1 − m given separately: near the separatrix
    1 − m cannot be recovered from m in floating point, and ``scipy.special.ellipj`` switches to
    a non-periodic series for 1 − m < 1e-10. m1 = 0 gives tanh, sech, sech.

    Parameters
    ----------
    u : ndarray, shape (n, T)
        Arguments.
    m, m1 : ndarray, shape (n,)
        Parameter and complementary parameter (m + m1 = 1, each accurate on its own).

    Returns
    -------
    sn, cn, dn : ndarray, shape (n, T)
    """
    hyperbolic = m1 <= 0.0
    # Hyperbolic rows get dummy circular values so that the AGM loop terminates.
    b = np.where(hyperbolic, 1.0, np.sqrt(np.maximum(m1, 0.0)))
    a = np.ones_like(m)
    c = np.where(hyperbolic, 0.0, np.sqrt(m))
    steps = []  # (c_n/a_n, b_n/a_n) for n = 1 .. N; (c_n/a_n)² + (b_n/a_n)² = 1
    eps = np.finfo(np.float64).eps
    for _ in range(_MAX_AGM_STEPS):
        if np.all(np.abs(c) <= eps * a):
            break
        a_next = 0.5 * (a + b)
        c = c * c / (4.0 * a_next)  # = (a − b)/2 without cancellation
        b = np.sqrt(a * b)
        a = a_next
        steps.append(((c / a)[:, None], (b / a)[:, None]))
    phi = (2.0 ** len(steps) * a)[:, None] * u
    for k, k_comp in reversed(steps):
        # arcsin(k sin φ) as an atan2 with 1 − k² sin²φ = cos²φ + k'² sin²φ: plain arcsin loses
        # half the digits when k rounds to 1 (1 − m below ~1e-32).
        sin, cos = np.sin(phi), np.cos(phi)
        phi = 0.5 * (np.arctan2(k * sin, np.sqrt(cos * cos + (k_comp * sin) ** 2)) + phi)
    sn = np.sin(phi)
    cn = np.cos(phi)
    # dn² = 1 − m sn² = cn² + m1 sn²: a sum of non-negative terms, accurate when dn is small.
    dn = np.sqrt(cn * cn + m1[:, None] * sn * sn)
    if np.any(hyperbolic):
        uh = u[hyperbolic]
        sech = 1.0 / np.cosh(uh)
        sn[hyperbolic] = np.tanh(uh)
        cn[hyperbolic] = sech
        dn[hyperbolic] = sech
    return sn, cn, dn


def _flow_sorted(
    inertia: FloatArray, nu0: FloatArray, times: FloatArray, rate: FloatArray
) -> FloatArray:
    """Exact flow for strictly increasing inertia, away from equilibria.

    Parameters
    ----------
    inertia : ndarray, shape (3,)
        I₁ < I₂ < I₃.
    nu0 : ndarray, shape (n, 3)
        Initial momenta, scaled so that max |ν₀ᵢ| is of order one, each with at least two
        components whose squares are non-zero (otherwise it is an equilibrium).
    times : ndarray, shape (T,)
        Times at which to evaluate.
    rate : ndarray, shape (n,)
        Factor applied to each trajectory's λ (undoes the scaling of ``nu0``).

    Returns
    -------
    ndarray, shape (n, T, 3)
        Trajectories in units of ``nu0``.
    """
    from scipy.special import elliprf

    i1, i2, i3 = (float(v) for v in inertia)
    s1, s2, s3 = (nu0 * nu0).T
    a_term = s1 * ((i3 - i1) / i1) + s2 * ((i3 - i2) / i2)
    b_term = s2 * ((i2 - i1) / i2) + s3 * ((i3 - i1) / i3)
    delta = s1 * ((i2 - i1) / i1) - s3 * ((i3 - i2) / i3)
    about_1 = delta >= 0.0

    amp1 = np.sqrt(i1 * a_term / (i3 - i1))
    amp3 = np.sqrt(i3 * b_term / (i3 - i1))
    amp2 = np.where(about_1, np.sqrt(i2 * b_term / (i2 - i1)), np.sqrt(i2 * a_term / (i3 - i2)))
    m = np.where(
        about_1,
        (i3 - i2) * b_term / ((i2 - i1) * a_term),
        (i2 - i1) * a_term / ((i3 - i2) * b_term),
    )
    m1 = np.where(
        about_1,
        (i3 - i1) * delta / ((i2 - i1) * a_term),
        -(i3 - i1) * delta / ((i3 - i2) * b_term),
    )
    lam = np.sqrt(np.where(about_1, (i2 - i1) * a_term, (i3 - i2) * b_term) / (i1 * i2 * i3))

    x_d = np.where(about_1, nu0[:, 0], nu0[:, 2])
    x_c = np.where(about_1, nu0[:, 2], nu0[:, 0])
    amp_d = np.where(about_1, amp1, amp3)
    amp_c = np.where(about_1, amp3, amp1)
    p = np.where(x_d >= 0.0, 1.0, -1.0)
    r = np.where(x_c >= 0.0, 1.0, -1.0)
    sn0 = p * r * nu0[:, 1] / amp2
    cn0 = np.abs(x_c) / amp_c
    dn0 = np.abs(x_d) / amp_d
    tau0 = sn0 * elliprf(cn0 * cn0, dn0 * dn0, 1.0)

    tau = (lam * rate)[:, None] * times[None, :] + tau0[:, None]
    sn, cn, dn = _jacobi_sn_cn_dn(tau, m, m1)
    col_d = (p * amp_d)[:, None] * dn
    col_c = (r * amp_c)[:, None] * cn
    side = about_1[:, None]
    col_2 = (p * r * amp2)[:, None] * sn
    return np.stack([np.where(side, col_d, col_c), col_2, np.where(side, col_c, col_d)], axis=-1)


def _flow_symmetric(inertia: FloatArray, mu0: FloatArray, times: FloatArray) -> FloatArray:
    """Exact flow when exactly two moments of inertia are equal.

    With symmetry axis s and (s, a, b) cyclic, μ̇ = Ω μ × e_s, Ω = μ_s (1/I_s − 1/I_a), so
    μ_s is constant and (μ_a, μ_b) rotates uniformly.

    Parameters
    ----------
    inertia : ndarray, shape (3,)
    mu0 : ndarray, shape (n, 3)
    times : ndarray, shape (T,)

    Returns
    -------
    ndarray, shape (n, T, 3)
    """
    counts = [int(np.count_nonzero(inertia == v)) for v in inertia]
    s = counts.index(1)
    a, b = (s + 1) % 3, (s + 2) % 3
    omega = mu0[:, s] * (1.0 / inertia[s] - 1.0 / inertia[a])
    angle = omega[:, None] * times[None, :]
    cos, sin = np.cos(angle), np.sin(angle)
    out = np.empty((mu0.shape[0], times.size, 3))
    out[:, :, s] = mu0[:, s, None]
    out[:, :, a] = mu0[:, a, None] * cos + mu0[:, b, None] * sin
    out[:, :, b] = mu0[:, b, None] * cos - mu0[:, a, None] * sin
    return out


@provides("exact_solution")
def exact_solution(body: RigidBody, mu0: ArrayLike, times: ArrayLike) -> FloatArray:
    """Exact free rigid body flow μ(t) from μ(0) = mu0, in Jacobi elliptic functions.

    Valid for any ordering of the inertia, both sides of the separatrix, the separatrix itself
    (1 − m = 0 exactly in floating point), equilibria, and two or three equal moments.

    Parameters
    ----------
    body : RigidBody
    mu0 : array_like, shape (3,) or (n, 3)
        Initial body angular momenta.
    times : array_like, shape (T,)
        Evaluation times (same time unit as the inertia implies); any sign and order.

    Returns
    -------
    ndarray, float64, shape (T, 3) if mu0 has shape (3,), else (n, T, 3)

    Raises
    ------
    ValueError
        If mu0 or times has the wrong shape or contains NaN/inf.
    """
    states, t, single = _check_inputs(body, mu0, times)
    # The elliptic functions hold about a dozen (n, T) arrays besides the (n, T, 3) output.
    check_reference_memory(states.shape[0], t.size, 3, "the exact flow", temporaries=12)
    inertia = np.asarray(body.inertia, dtype=np.float64)
    n_distinct = np.unique(inertia).size
    if n_distinct == 2:
        out = _flow_symmetric(inertia, states, t)
    else:
        # Equilibria (and everything, for a spherical body) stay put.
        out = np.broadcast_to(states[:, None, :], (states.shape[0], t.size, 3)).copy()
    if n_distinct == 3:
        perm = np.argsort(inertia)
        # Parity of perm: (Pa) × (Pb) = det(P) P(a × b), so an odd permutation reverses time.
        inversions = sum(perm[i] > perm[j] for i in range(3) for j in range(i + 1, 3))
        direction = -1.0 if inversions % 2 else 1.0
        # Scale each state by a power of two (exact) to keep squares clear of over/underflow;
        # the flow is homogeneous: μ(t; s ν₀) = s ν(s t; ν₀).
        _, exponent = np.frexp(np.max(np.abs(states), axis=1))
        scale = np.ldexp(1.0, exponent)
        nu0 = states[:, perm] / scale[:, None]
        # At most one component with a non-zero square: a principal axis or the origin.
        moving = np.count_nonzero(nu0 * nu0, axis=1) >= 2
        if np.any(moving):
            flow = _flow_sorted(inertia[perm], nu0[moving], direction * t, scale[moving])
            unsorted = np.empty_like(flow)
            unsorted[..., perm] = flow * scale[moving, None, None]
            out[moving] = unsorted
    return out[0] if single else out


#: Steps DOP853 takes per radian of the local rate, times rtol^(1/8) (an 8th-order method's step
#: scales as rtol^(1/8)/rate). With 0.1 the estimate came out 0.6–1.5x the steps taken on the
#: rigid body (4 states, rtol 1e-13 and 1e-8, T = 100) and 1.6x on a quartic so(3) system. A run
#: is refused up front only when its estimate exceeds the budget _DOP853_ESTIMATE_SLACK times.
_DOP853_STEPS_PER_RADIAN = 0.1
_DOP853_ESTIMATE_SLACK = 4.0


def _local_rate(rhs: Callable[[FloatArray], FloatArray], y: FloatArray) -> float:
    """How fast the flow moves near y, in radians per time unit: the larger of |f(y)|/|y| and the
    norm of the Jacobian of f (central differences, 2n evaluations). For a quadratic H both are
    about the rotation rate; for a higher-degree H the Jacobian also sees the Hessian's part.
    Inf where f overflows."""
    with np.errstate(over="ignore", invalid="ignore"):
        f = rhs(y)
        size = float(np.linalg.norm(y))
        if not np.isfinite(f).all() or not math.isfinite(size):
            return math.inf
        if size == 0.0:
            return 0.0
        rate = float(np.linalg.norm(f)) / size
        eps = 1e-6 * size
        cols = []
        for i in range(y.size):
            e = np.zeros_like(y)
            e[i] = eps
            cols.append((rhs(y + e) - rhs(y - e)) / (2 * eps))
        jac = float(np.linalg.norm(np.array(cols)))
    return max(rate, jac) if math.isfinite(jac) else math.inf


def reference_bytes(n_states: int, n_times: int, dim: int, temporaries: int = 0) -> float:
    """Bytes a reference of ``n_states`` trajectories at ``n_times`` times in dimension
    ``dim`` holds at once: its output and one converted copy (exp of q, the affine slice, the
    rollout's contiguous array), one trajectory's dense output from ``solve_ivp`` and its
    reordered copy, the times (given, sorted, their order), and ``temporaries`` more (n, T)
    arrays."""
    per_time = dim * (2 * n_states + 2) + 4 + temporaries * n_states
    return 8.0 * n_times * per_time


def check_reference_memory(
    n_states: int, n_times: int, dim: int, what: str, temporaries: int = 0
) -> None:
    """MemoryError, before any work, where a reference's arrays (:func:`reference_bytes`)
    would not fit in the memory this process may use (the estimate the core applies to its
    rollouts: :func:`poisson_rs.memory.check_fits`)."""
    from .memory import check_fits

    need = reference_bytes(n_states, n_times, dim, temporaries)
    check_fits(
        need,
        f"{what} of {n_states} states at {n_times} times",
        "record fewer times (a larger every, or fewer steps) or fewer states at once",
    )


class NoReferenceError(RuntimeError, ValueError):
    """DOP853 could not compute a trajectory (over its step budget, or overflowing): a
    RuntimeError as documented, and a ValueError too, since the states or the horizon asked
    for are what is out of reach (the CLI reports it in one line, exit status 2)."""


def _dop853_estimate(
    rhs: Callable[[FloatArray], FloatArray], y0: FloatArray, span: float, rtol: float
) -> float:
    """Steps DOP853 would take over a time ``span`` from y0, from the local rate (an estimate, a
    few times off either way; inf where f overflows)."""
    rate = _local_rate(rhs, y0)
    return _DOP853_STEPS_PER_RADIAN * rate * span / rtol ** (1 / 8)


def _dop853(
    rhs: Callable[[FloatArray], FloatArray],
    states: FloatArray,
    t: FloatArray,
    rtol: float,
    atol: float,
    failures: Literal["raise", "nan"] = "raise",
) -> FloatArray:
    """DOP853 runs of ẏ = rhs(y) from each row of ``states`` (m, n) to ``times`` (T,) → (m, T, n).

    Each trajectory runs forward from t = 0 for the positive times and backward for the negative
    ones, under a budget of ``_DOP853_MAX_STEPS`` steps (a module-level override for tests).
    Before it runs, its work is estimated from the local rate of the flow at its initial state
    times the span of ``times``: one far over the budget (|μ| = 1e30, say) is refused at once
    instead of after the whole budget. ``failures``: "raise" raises RuntimeError naming the
    trajectory when one is refused, spends the budget or overflows; "nan" leaves that
    trajectory NaN (past t = 0) and goes on with the others.
    """
    from scipy.integrate import solve_ivp

    check_reference_memory(states.shape[0], t.size, states.shape[1], "DOP853")
    # Work bound, in right-hand sides (DOP853 takes 12 per step).
    max_steps = int(globals().get("_DOP853_MAX_STEPS", 200_000))
    max_rhs = 12 * max_steps
    calls = [0]

    class _Abort(Exception):
        """Raised from the right-hand side to stop solve_ivp: over budget or non-finite."""

    def fun(_t: float, y: FloatArray) -> FloatArray:
        calls[0] += 1
        if calls[0] > max_rhs:
            raise _Abort(f"over the budget of {max_steps} steps (|mu|*T too large)")
        with np.errstate(over="ignore", invalid="ignore"):
            f = rhs(y)
        if not np.isfinite(f).all():
            raise _Abort("non-finite right-hand side (|mu| too large for float64)")
        return f

    out = np.empty((states.shape[0], t.size, states.shape[1]))
    out[:, t == 0.0, :] = states[:, None, :]
    branches = []
    for mask in (t > 0.0, t < 0.0):
        if np.any(mask):
            idx = np.flatnonzero(mask)
            # solve_ivp wants t_eval strictly monotone along the integration direction.
            t_eval, inverse = np.unique(np.abs(t[idx]), return_inverse=True)
            sign = 1.0 if t[idx[0]] > 0.0 else -1.0
            branches.append((idx, sign * t_eval, inverse))
    failed: list[tuple[int, str]] = []
    for k, y0 in enumerate(states):
        for idx, t_eval, inverse in branches:
            calls[0] = 0
            try:
                estimate = _dop853_estimate(rhs, y0, abs(float(t_eval[-1])), rtol)
                if not math.isfinite(estimate):
                    raise _Abort("non-finite right-hand side (|mu| too large for float64)")
                if estimate > _DOP853_ESTIMATE_SLACK * max_steps:
                    raise _Abort(
                        f"would take about {estimate:.3g} steps, over the budget of "
                        f"{max_steps} steps (|mu|*T too large)"
                    )
                sol = solve_ivp(
                    fun,
                    (0.0, t_eval[-1]),
                    y0,
                    method="DOP853",
                    t_eval=t_eval,
                    rtol=rtol,
                    atol=atol,
                )
                if not sol.success:
                    raise _Abort(str(sol.message))
            except _Abort as e:
                if failures == "raise":
                    raise NoReferenceError(
                        f"no reference: DOP853 failed for trajectory {k}: {e}"
                    ) from None
                failed.append((k, str(e)))
                out[k, idx, :] = np.nan
                continue
            out[k, idx, :] = sol.y.T[inverse]
    if failed:
        k, why = failed[0]
        warnings.warn(
            f"DOP853 gave up on {len({f[0] for f in failed})} of {len(states)} trajectories, "
            f"left NaN (first: trajectory {k}: {why})",
            RuntimeWarning,
            stacklevel=3,
        )
    return out


def _check_tolerances(rtol: float, atol: float) -> tuple[float, float]:
    out = []
    for name, v in (("rtol", rtol), ("atol", atol)):
        if isinstance(v, bool) or not isinstance(v, int | float | np.floating | np.integer):
            raise ValueError(f"{name} must be a real number, got {v!r}")
        if not (np.isfinite(v) and v > 0.0):
            raise ValueError(f"{name} must be finite and > 0, got {v!r}")
        out.append(float(v))
    return out[0], out[1]


@provides("dop853_solution")
def dop853_solution(
    body: RigidBody,
    mu0: ArrayLike,
    times: ArrayLike,
    rtol: float = 1e-13,
    atol: float = 1e-13,
    *,
    failures: Literal["raise", "nan"] = "raise",
) -> FloatArray:
    """Numerical flow from ``scipy.integrate.solve_ivp`` (DOP853, dense output at ``times``).

    Each trajectory is integrated separately, forward from t = 0 for positive times and
    backward for negative ones.

    Parameters
    ----------
    body : RigidBody
    mu0 : array_like, shape (3,) or (n, 3)
        Initial body angular momenta.
    times : array_like, shape (T,)
        Evaluation times; any sign and order.
    rtol, atol : float
        Tolerances passed to ``solve_ivp``.
    failures : "raise" or "nan", keyword-only
        What a trajectory that cannot be computed does: raise RuntimeError (the default), or
        come back NaN (past t = 0) while the others are computed.

    Returns
    -------
    ndarray, float64, shape (T, 3) if mu0 has shape (3,), else (n, T, 3)

    Raises
    ------
    ValueError
        If mu0 or times has the wrong shape or contains NaN/inf.
    RuntimeError
        If the integrator fails, or a trajectory would take more than 200,000 steps (about
        2.4 million right-hand sides, a minute in Python): the cost grows with |μ|·T, and states
        like |μ| = 1e10 would otherwise never return. The work is estimated first (local rate
        times T), so such states fail at once, as do non-finite values (overflow of |μ|²).
    """
    if failures not in ("raise", "nan"):
        raise ValueError(f"failures must be 'raise' or 'nan', got {failures!r}")
    states, t, single = _check_inputs(body, mu0, times)
    j1, j2, j3 = (1.0 / v for v in body.inertia)

    def rhs(y: FloatArray) -> FloatArray:
        # Euler's equations written out: a third of the cost of np.cross on a (3,) array.
        w1, w2, w3 = y[0] * j1, y[1] * j2, y[2] * j3
        return np.array([y[1] * w3 - y[2] * w2, y[2] * w1 - y[0] * w3, y[0] * w2 - y[1] * w1])

    out = _dop853(rhs, states, t, rtol, atol, failures)
    return out[0] if single else out


def _system_rhs(system: LiePoissonSystem) -> Callable[[FloatArray], FloatArray]:
    """ẏ = f(y) for one state y (n,), with the per-call overhead of the generic
    :meth:`LiePoissonSystem.vector_field` (validation, einsum parsing) taken out."""
    powers, _ = system.polynomial.to_arrays()
    n = system.dim
    degree = system.polynomial.degree
    # Gradient terms: ∂_j of a·μ^e is a·e_j·μ^(e − δ_j); `select` sums them into component j.
    rows, cols = np.nonzero(powers)
    _, coeffs = system.polynomial.to_arrays()
    dpowers = powers[rows].copy()
    dpowers[np.arange(rows.size), cols] -= 1
    dcoeffs = coeffs[rows] * powers[rows, cols]
    select = np.zeros((n, rows.size))
    select[cols, np.arange(rows.size)] = dcoeffs
    var = np.arange(n)
    c_flat = system.algebra.c.reshape(n, n * n)  # [i, (j, k)]

    def rhs(y: FloatArray) -> FloatArray:
        table = np.empty((degree + 1, n))
        table[0] = 1.0
        for d in range(1, degree + 1):
            table[d] = table[d - 1] * y
        grad = select @ np.prod(table[dpowers, var], axis=1)
        # μ̇_j = Σ_{i,k} c[i,j,k] ∂_iH μ_k
        return (grad @ c_flat).reshape(n, n) @ y

    return rhs


def reference_solution(
    system: Any,
    mu0: ArrayLike,
    times: ArrayLike,
    *,
    rtol: float = 1e-13,
    atol: float = 1e-13,
    failures: Literal["raise", "nan"] = "raise",
) -> FloatArray:
    """Flow of any Poisson system (:class:`poisson_rs.PoissonSystem`) by SciPy's DOP853, each
    trajectory integrated separately with dense output at ``times``: forward from t = 0 for the
    positive times, backward for negative ones (any order is accepted; t = 0 returns mu0). Each
    structure integrates in its own coordinates (a log-canonical system in q = ln x, an affine
    one on its central extension).

    Parameters
    ----------
    system : PoissonSystem
        Of dimension n.
    mu0 : array_like, shape (n,) or (m, n)
        Initial states, finite and in the system's domain.
    times : array_like, shape (T,)
        Evaluation times, finite, in the time unit of the system.
    rtol, atol : float, keyword-only
        Tolerances passed to ``solve_ivp`` (finite, > 0).
    failures : "raise" or "nan", keyword-only
        As for :func:`dop853_solution`.

    Returns
    -------
    ndarray, float64, shape (T, n) if mu0 has shape (n,), else (m, T, n)

    Raises
    ------
    TypeError
        If ``system`` is not a Poisson system.
    ValueError
        If mu0, times or the tolerances are malformed or not finite.
    RuntimeError
        If the integrator fails, a trajectory would take more than 200,000 steps (the cost grows
        with the state's size times T), or the right-hand side overflows (fails at once).
    """
    from .protocols import as_system

    if failures not in ("raise", "nan"):
        raise ValueError(f"failures must be 'raise' or 'nan', got {failures!r}")
    return as_system(system).reference_solution(mu0, times, rtol=rtol, atol=atol, failures=failures)


@provides("field_reference")
def field_reference(
    field: Callable[[FloatArray], FloatArray],
    dim: int,
    mu0: ArrayLike,
    times: ArrayLike,
    *,
    rtol: float,
    atol: float,
    failures: Literal["raise", "nan"],
) -> FloatArray:
    """DOP853 on ẏ = field(y) for one state y (dim,): the reference of a structure with no
    better coordinates. Shapes as :func:`reference_solution`."""
    rtol, atol = _check_tolerances(rtol, atol)
    states, t, single = _check_states_and_times(mu0, times, dim)
    out = _dop853(field, states, t, rtol, atol, failures)
    return out[0] if single else out


@provides("lie_poisson_reference")
def lie_poisson_reference(
    system: LiePoissonSystem,
    mu0: ArrayLike,
    times: ArrayLike,
    *,
    rtol: float = 1e-13,
    atol: float = 1e-13,
    failures: Literal["raise", "nan"] = "raise",
) -> FloatArray:
    """:func:`reference_solution` of a Lie–Poisson system, μ̇_j = Σ_{i,k} c[i,j,k] ∂H/∂μ_i μ_k."""
    if failures not in ("raise", "nan"):
        raise ValueError(f"failures must be 'raise' or 'nan', got {failures!r}")
    return field_reference(
        _system_rhs(system), system.dim, mu0, times, rtol=rtol, atol=atol, failures=failures
    )

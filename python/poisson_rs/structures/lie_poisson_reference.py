"""Reference flows of Lie–Poisson systems: DOP853 on μ̇ = ad*-field of any Lie–Poisson system,
and for the free rigid body on so(3)* ≅ R³ its closed form and DOP853 on Euler's equations.

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

from collections.abc import Callable
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..protocols import provides
from ..reference import (
    check_reference_memory,
    check_states_and_times,
    dop853,
    field_reference,
)
from .lie_poisson import LiePoissonSystem, RigidBody

__all__ = ["dop853_solution", "exact_solution", "lie_poisson_reference"]

FloatArray = NDArray[np.float64]

#: Cap on Landen/AGM steps; convergence is quadratic, even 1 − m = 1e-300 needs about 15.
_MAX_AGM_STEPS = 64


def _check_inputs(
    body: RigidBody, mu0: ArrayLike, times: ArrayLike
) -> tuple[FloatArray, FloatArray, bool]:
    """Validate and return (states (n, 3), times (T,), single) where single means mu0 was (3,)."""
    if not isinstance(body, RigidBody):
        raise TypeError(f"body must be a RigidBody, got {type(body).__name__}")
    return check_states_and_times(mu0, times, 3)


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

    out = dop853(rhs, states, t, rtol, atol, failures)
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

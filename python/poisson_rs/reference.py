"""Reference solutions of any Poisson system: SciPy's DOP853 with dense output, each trajectory
integrated on its own, with its work estimated first (a state whose flow would take more than
200,000 steps fails at once) and its memory checked.

:func:`reference_solution` asks the system (:class:`poisson_rs.PoissonSystem`) for its own
reference: each structure integrates in its own coordinates and may have a closed form (the free
rigid body's elliptic functions live with the Lie–Poisson structure, in
:mod:`poisson_rs.structures.lie_poisson_reference`). :func:`field_reference` is the DOP853 engine
a structure with no better coordinates uses.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .protocols import provides

__all__ = [
    "NoReferenceError",
    "check_reference_memory",
    "check_states_and_times",
    "check_tolerances",
    "dop853",
    "field_reference",
    "reference_bytes",
    "reference_solution",
]

FloatArray = NDArray[np.float64]


def check_states_and_times(
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


def dop853(
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


def check_tolerances(rtol: float, atol: float) -> tuple[float, float]:
    out = []
    for name, v in (("rtol", rtol), ("atol", atol)):
        if isinstance(v, bool) or not isinstance(v, int | float | np.floating | np.integer):
            raise ValueError(f"{name} must be a real number, got {v!r}")
        if not (np.isfinite(v) and v > 0.0):
            raise ValueError(f"{name} must be finite and > 0, got {v!r}")
        out.append(float(v))
    return out[0], out[1]


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
    rtol, atol = check_tolerances(rtol, atol)
    states, t, single = check_states_and_times(mu0, times, dim)
    out = dop853(field, states, t, rtol, atol, failures)
    return out[0] if single else out

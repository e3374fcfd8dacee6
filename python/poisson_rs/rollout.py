"""The rollout: ``integrate()`` drives any :class:`~poisson_rs.Stepper` over batches of
initial states, checks its arguments, completes and reports its diagnostics (failures, steps
that do not resolve the motion, states outside a learned model's domain)."""

from __future__ import annotations

import math
import numbers
import pickle
import sys
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, overload

import numpy as np

from .protocols import (
    ROLLOUT_KEYS,
    Stepper,
    as_stepper,
)

if TYPE_CHECKING:
    import dask.array as da


#: Smallest step accepted: the least normal float64 (2.2e-308). Below it 1/h and T/h overflow.
MIN_STEP = sys.float_info.min


#: Largest step count (n_steps, every) accepted: 2**53, the last integer float64 holds exactly,
#: so every recorded time k·h is the float it should be; a rollout that long would take
#: centuries, and past 2**64 the count does not even fit the core's integers.
MAX_COUNT = 2**53


def _check_step(h: Any, name: str = "h") -> float:
    """``h`` as a float: TypeError unless a real number (int, float, Fraction, Decimal, NumPy
    scalar; not a bool), ValueError unless finite and in [MIN_STEP, ∞) — ``10**400`` and 1e-320
    included, which would otherwise overflow later as OverflowError."""
    if isinstance(h, (bool, np.bool_)) or not isinstance(h, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {type(h).__name__}")
    try:
        value = float(h)
    except (OverflowError, ValueError, TypeError):
        raise ValueError(
            f"{name} must be finite and > 0, got a number too large for float64"
        ) from None
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be finite and > 0, got {value}")
    if value < MIN_STEP:
        raise ValueError(f"{name} = {value:g} is below {MIN_STEP:g}, the smallest step accepted")
    return value


def _check_time(t: Any, name: str = "t") -> float:
    """A time t >= 0 as a float: TypeError unless a real number (not a bool), ValueError unless
    finite (``10**400`` included, which float() would turn into OverflowError)."""
    if isinstance(t, (bool, np.bool_)) or not isinstance(t, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {type(t).__name__}")
    try:
        value = float(t)
    except (OverflowError, ValueError, TypeError):
        raise ValueError(f"{name} must be finite, got a number too large for float64") from None
    if not (math.isfinite(value) and value >= 0):
        raise ValueError(f"{name} must be finite and >= 0, got {value}")
    return value


def _check_count(name: str, value: Any, low: int = 0) -> int:
    """``value`` as an int in [low, MAX_COUNT]: TypeError unless an integer (Python or NumPy;
    not a bool, not a float), ValueError naming ``name`` outside the range (2**64 included,
    which would otherwise overflow as OverflowError on the way into the core)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name} must be an integer, got {type(value).__name__}")
    count = int(value)
    if count < low:
        raise ValueError(f"{name} must be >= {low}, got {count}")
    if count > MAX_COUNT:
        raise ValueError(f"{name} must be <= 2**53, got {count}")
    return count


#: Meaning of :attr:`RolloutInfo.failure_code` (0: no failure).
FAILURE_CODES: dict[int, str] = {
    1: "no convergence",
    2: "singular Jacobian",
    3: "non-finite value",
    4: "chart singular",
    5: "left the domain",
}


@dataclass(frozen=True)
class RolloutInfo:
    """Per-trajectory diagnostics of a rollout; every field has shape (n,)."""

    converged: np.ndarray
    """True when every step's Newton solve converged."""
    failed_step: np.ndarray
    """Index of the step that failed (state k → k+1), or −1."""
    failure_code: np.ndarray
    """0 none, 1 no convergence, 2 singular Jacobian, 3 non-finite value, 4 chart singular,
    5 left the domain (a log-canonical state left the positive orthant)."""
    newton_iterations: np.ndarray
    """Newton updates summed over the trajectory."""
    max_newton_iterations: np.ndarray
    """Most Newton updates in one step."""
    max_residual: np.ndarray
    """Largest accepted residual |tar(∂S/∂p, p) − μ|∞ over the steps."""
    out_of_domain: np.ndarray
    """int64: recorded states (the kept ones, every ``every``-th, the initial one included)
    outside the model's training domain; states between records are not checked, NaN states
    after a failure are not counted. Zeros for methods without a domain (Taylor, classical)."""
    step_angle: np.ndarray
    """float64, radians: h times the local rate at the initial state, max(‖ad_∇H(μ)‖_F/√2,
    ‖∂f/∂μ‖_F) with f the vector field (the Frobenius norm of the Jacobian carries the Hessian
    of H and bounds its spectral norm). Above :data:`MAX_STEP_ANGLE` no fixed-step method
    resolves the motion. NaN where it does not apply (adaptive DOP853, a stepper without a
    Lie–Poisson system)."""


#: Trajectory-states per block of :func:`count_out_of_domain`: its temporaries stay a few MB
#: whatever the size of the rollout.
_DOMAIN_BLOCK = 1 << 16


def count_out_of_domain(domain: Mapping[str, Any] | None, traj: np.ndarray) -> np.ndarray:
    """States of ``traj`` (n, records, dim) outside a training ``domain``, per trajectory: (n,)
    int64.

    Shell: |μ| outside [r_min, r_max]; cube: some |μᵢ| > half_width; top (μ = (M, Γ)): some
    |Mᵢ| > half_width or |Γ| outside [r_min, r_max]; "all" or None: none.
    NaN states (after a Newton failure) compare false and are not counted. Works through the
    trajectory in blocks, so its memory does not grow with the output.
    """
    kind = None if domain is None else domain.get("kind")
    counts = np.zeros(traj.shape[0], dtype=np.int64)
    if domain is None or kind not in ("shell", "cube", "top") or traj.size == 0:
        return counts
    rows = max(1, _DOMAIN_BLOCK // max(1, traj.shape[1]))
    for start in range(0, traj.shape[0], rows):
        block = traj[start : start + rows]
        if kind == "shell":
            r2 = np.einsum("nrd,nrd->nr", block, block)
            outside = (r2 < domain["r_min"] ** 2) | (r2 > domain["r_max"] ** 2)
        elif kind == "top":
            g2 = np.einsum("nrd,nrd->nr", block[..., 3:], block[..., 3:])
            outside = (np.abs(block[..., :3]) > domain["half_width"]).any(axis=-1)
            outside |= (g2 < domain["r_min"] ** 2) | (g2 > domain["r_max"] ** 2)
        else:
            outside = (np.abs(block) > domain["half_width"]).any(axis=-1)
        counts[start : start + rows] = outside.sum(axis=1, dtype=np.int64)
    return counts


def _describe_domain(domain: Mapping[str, Any]) -> str:
    if domain["kind"] == "shell":
        return f"the shell {domain['r_min']:g} <= |mu| <= {domain['r_max']:g}"
    if domain["kind"] == "top":
        return (
            f"|M_i| <= {domain['half_width']:g} and "
            f"{domain['r_min']:g} <= |Gamma| <= {domain['r_max']:g}"
        )
    return f"the cube |mu_i| <= {domain['half_width']:g}"


#: NumPy's native float64 dtype (one object: compared by identity on the fast path).
_FLOAT64 = np.dtype(np.float64)


def _as_states(
    mu0: Any, what: str = "mu0", dim: int = 3, *, check_finite: bool = True
) -> tuple[np.ndarray, bool]:
    """(n, dim) C-contiguous float64 array of an array-like of states (mu0 itself where it is
    one already), and whether it was one state. ``check_finite=False`` leaves the NaN/∞ check
    to a caller whose core makes it (with the same message)."""
    if type(mu0) is np.ndarray:
        arr = mu0
    else:
        if isinstance(mu0, np.ma.MaskedArray):
            # np.asarray would drop the mask and step the masked values as if they were data.
            raise TypeError(
                f"{what} is a numpy masked array, whose mask would be ignored; pass plain data "
                "(e.g. the unmasked rows, or .filled(value))"
            )
        arr = np.asarray(mu0)
    dtype = arr.dtype
    if dtype is not _FLOAT64:
        if dtype.kind not in "fiu":  # object, bool, complex, strings, ...
            raise TypeError(f"{what} must be an array of real numbers, got dtype {dtype}")
        arr = arr.astype(np.float64)
    shape = arr.shape
    if shape == (dim,):
        single = True
        arr = arr.reshape(1, dim)
    elif len(shape) == 2 and shape[1] == dim:
        single = False
    else:
        raise ValueError(f"{what} must have shape ({dim},) or (n, {dim}), got {shape}")
    if not arr.flags.c_contiguous:
        arr = np.ascontiguousarray(arr)
    if check_finite and not np.isfinite(arr).all():
        raise ValueError(f"{what} holds NaN or infinite values")
    return arr, single


@overload
def integrate(
    stepper: Stepper,
    mu0: Any,
    h: float,
    n_steps: int,
    *,
    every: int = ...,
    return_info: Literal[False] = ...,
    on_failure: Literal["warn", "raise", "ignore"] = ...,
    strict: bool = ...,
    device: Any = ...,
) -> np.ndarray: ...


@overload
def integrate(
    stepper: Stepper,
    mu0: Any,
    h: float,
    n_steps: int,
    *,
    every: int = ...,
    return_info: Literal[True],
    on_failure: Literal["warn", "raise", "ignore"] = ...,
    strict: bool = ...,
    device: Any = ...,
) -> tuple[np.ndarray, RolloutInfo]: ...


def integrate(
    stepper: Stepper,
    mu0: Any,
    h: float,
    n_steps: int,
    *,
    every: int = 1,
    return_info: bool = False,
    on_failure: Literal["warn", "raise", "ignore"] = "warn",
    strict: bool = True,
    device: Any = None,
) -> np.ndarray | tuple[np.ndarray, RolloutInfo]:
    """Advances initial states ``n_steps`` steps of size ``h``, keeping every ``every``-th state.

    Parameters
    ----------
    stepper: an integrator, e.g. from :func:`load_model`.
    mu0: (dim,) or (n, dim) array-like of states in g* (angular momenta for the rigid body, dim
        = 3; (M, Γ) for the heavy top, dim = 6).
    h: step size (time units), finite and > 0.
    n_steps: number of steps, >= 0.
    every: keep states 0, every, 2·every, ... (bounds memory on long horizons).
    return_info: also return a :class:`RolloutInfo`.
    on_failure: a trajectory whose Newton solve fails stops there and its later states are NaN;
        "warn" (default) warns once per call, "raise" raises RuntimeError, "ignore" stays silent.
    strict: a learned model refuses steps beyond the h_max it was trained for (ValueError);
        ``strict=False`` lets it extrapolate.
    device: None (default) steps in the Rust core on the CPU; a torch device ("cuda",
        "cuda:N") runs the stepper's torch step there, "cpu" its torch reference path: see
        :func:`poisson_rs.on_device` (which also sets the dtype). Refused before any work for a
        stepper without a torch step or a device torch does not see.

    Returns
    -------
    float64 array (n_steps // every + 1, dim) for one state, (n, n_steps // every + 1, dim) for
    n. A ``dask.array.Array`` mu0 gives a lazy dask array chunked as mu0 along axis 0 (and the
    info as dask arrays), bit-identical once computed: see
    :func:`poisson_rs.ensembles.integrate_dask`.

    A model that records its training domain (a shell or a cube of states) is checked against
    it: ``info.out_of_domain`` counts, per trajectory, the recorded states (only the kept ones,
    every ``every``-th) outside it, and one RuntimeWarning per call says so when any are. Its
    ``hj_residual`` tells how well it solves its equation there. Ctrl-C interrupts a long
    rollout (KeyboardInterrupt) within a fraction of a second.

    When ``every`` does not divide ``n_steps`` the last recorded state is step
    ``n_steps - n_steps % every``, NOT the final one (n_steps = 10, every = 3 keeps steps 0, 3,
    6, 9): choose ``every`` dividing ``n_steps`` to keep the final state.
    """
    if device is not None:
        from .device_rollout import on_device

        stepper = on_device(stepper, device)
    # A stepper whose core checks the states and keeps its diagnostics until asked for (see
    # ClassicalIntegrator._core_rollout).
    core_rollout = getattr(stepper, "_core_rollout", None)
    if (
        core_rollout is not None
        and (type(mu0) is list or type(mu0) is np.ndarray)
        and type(h) is float
        and MIN_STEP <= h < math.inf
        and type(n_steps) is int
        and 0 <= n_steps <= MAX_COUNT
        and type(every) is int
        and 1 <= every <= MAX_COUNT
        and not n_steps % every
        and not return_info
    ):
        # The thin path of a small call: every argument of a built-in type in range, no info
        # asked for; nothing else to check but on_failure, and nothing to report unless the
        # core's summary says so.
        if on_failure not in _ON_FAILURE:
            raise ValueError(f"on_failure must be 'warn', 'raise' or 'ignore', got {on_failure!r}")
        # A list of plain numbers, one state, goes to the core as it is (NumPy's conversion
        # of a short list costs more than the step); the core returns None for another list.
        result = core_rollout(mu0, h, n_steps, every) if type(mu0) is list else None
        if result is None:
            arr, single = _as_states(mu0, dim=stepper.dim, check_finite=False)
            result = core_rollout(arr, h, n_steps, every)
        else:
            single = True
        traj, diagnostics = result
        summary = diagnostics.summary()
        if summary[0] or summary[4] > MAX_STEP_ANGLE:  # NaN compares false
            _report(stepper, h, len(traj), summary, on_failure)
        return traj[0] if single else traj
    if core_rollout is None:
        as_stepper(stepper)
    # A dask array exists only once dask.array is imported (and is no list or ndarray).
    if type(mu0) is not list and type(mu0) is not np.ndarray and "dask.array" in sys.modules:
        if is_dask_array(mu0):
            return integrate_dask(  # type: ignore[return-value]
                stepper,
                mu0,
                h,
                n_steps,
                every=every,
                return_info=return_info,
                on_failure=on_failure,
                strict=strict,
            )
    arr, single = _as_states(
        mu0, dim=int(getattr(stepper, "dim", 3)), check_finite=core_rollout is None
    )
    # Exact built-in types in range take the short path: the abstract-number checks cost more
    # than a small rollout. Anything else (Fraction, NumPy scalars, 10**400, 2**64, tiny h) gets
    # the full checks, which name the argument.
    if not (type(h) is float and MIN_STEP <= h < math.inf):
        h = _check_step(h)
    if not (type(n_steps) is int and 0 <= n_steps <= MAX_COUNT):
        n_steps = _check_count("n_steps", n_steps)
    if not (type(every) is int and 1 <= every <= MAX_COUNT):
        every = _check_count("every", every, 1)
    if n_steps % every:
        warnings.warn(
            f"every = {every} does not divide n_steps = {n_steps}: the last "
            f"{n_steps % every} steps are taken but their final state is not recorded",
            RuntimeWarning,
            stacklevel=2,
        )
    if on_failure not in _ON_FAILURE:
        raise ValueError(f"on_failure must be 'warn', 'raise' or 'ignore', got {on_failure!r}")
    # A learned stepper knows the largest step it was trained for and, for some, the states.
    h_max = getattr(stepper, "h_max", math.inf)
    if strict and isinstance(h_max, float) and math.isfinite(h_max) and h > h_max:
        raise ValueError(
            f"h = {h} exceeds h_max = {h_max}, the largest step "
            f"{getattr(stepper, 'name', type(stepper).__name__)!r} was trained for; pass "
            "strict=False to extrapolate (poisson-rs demo: --no-strict)"
        )
    # A learned time-h map steps at the one h it was fitted for (its ``step_h``).
    step_h = getattr(stepper, "step_h", None)
    if isinstance(step_h, float):
        check_step(h, step_h, getattr(stepper, "name", type(stepper).__name__))
    domain = getattr(stepper, "domain", None)
    if not isinstance(domain, Mapping):
        domain = None
    h = float(h)
    raw: dict[str, np.ndarray] | None
    if core_rollout is not None:
        traj, diagnostics = core_rollout(arr, h, int(n_steps), int(every))
        summary = diagnostics.summary()
        raw = diagnostics.arrays() if return_info else None
    else:
        traj, raw = _checked_rollout(stepper, arr, h, int(n_steps), int(every))
        if "step_angle" not in raw:
            raw["step_angle"] = _step_angles(stepper, arr, h)
        summary = _summary(raw)
    out_of_domain = None
    if domain is not None:
        # Vectorised over the recorded states: cheap next to the rollout that made them.
        out_of_domain = count_out_of_domain(domain, traj)
    _report(stepper, h, len(arr), summary, on_failure, domain, out_of_domain)
    out = traj[0] if single else traj
    if not return_info:
        return out
    assert raw is not None
    if out_of_domain is None:
        out_of_domain = np.zeros(len(arr), dtype=np.int64)
    return out, RolloutInfo(**raw, out_of_domain=out_of_domain)


_ON_FAILURE = ("warn", "raise", "ignore")


#: Relative difference from a learned map's fitted h still taken as that h (a few ulps: h read
#: back from text, or computed as T/n).
STEP_RTOL = 1e-12


def check_step(h: Any, fitted: float, name: str) -> None:
    """ValueError naming ``h`` and ``fitted`` unless h is ``fitted`` (to :data:`STEP_RTOL`): a
    learned time-h map is the flow's map at that h only."""
    try:
        hv = float(h)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"h must be a real number, got {h!r}") from None
    if not (math.isfinite(hv) and abs(hv - fitted) <= STEP_RTOL * fitted):
        raise ValueError(
            f"h = {h!r}: {name!r} is a learned time-h map fitted for h = {fitted!r} (the data's "
            "record spacing) and steps at that h only; at any other h it is not the flow's map"
        )


def dop853_rollout(
    system: Any, x0: np.ndarray, h: float, n_steps: int, every: int, tol: float
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The rollout of every structure's "dop853": ``system.reference_solution`` at rtol = atol
    = ``tol`` sampled at t = k·every·h. A trajectory DOP853 cannot finish (over its budget,
    overflowing) is NaN from there on and reported like a failed step (code 1), the others
    are kept; no Newton solve, no step angle (it chooses its own steps). MemoryError, before
    any work, where the output would not fit (the check the core's rollouts make)."""
    from .reference import check_reference_memory

    # Before the times are made: they alone are a third of a single 3D trajectory's output.
    check_reference_memory(x0.shape[0], n_steps // every + 1, x0.shape[1], "dop853")
    times = h * np.arange(0, n_steps // every + 1, dtype=np.float64) * every
    # DOP853's own warning says why a trajectory was given up (its budget, an overflow).
    traj = system.reference_solution(x0, times, rtol=tol, atol=tol, failures="nan")
    n = x0.shape[0]
    finite = np.isfinite(traj).all(axis=-1)
    converged = finite.all(axis=1)
    first_bad = np.where(converged, -1, np.argmin(finite, axis=1) * every - 1)
    return traj, {
        "converged": converged,
        "failed_step": first_bad.astype(np.int64),
        "failure_code": np.where(converged, 0, 1).astype(np.int8),
        "newton_iterations": np.zeros(n, dtype=np.uint64),
        "max_newton_iterations": np.zeros(n, dtype=np.uint32),
        "max_residual": np.full(n, np.nan),
        "step_angle": np.full(n, np.nan),
    }


def _checked_rollout(
    stepper: Stepper, x0: np.ndarray, h: float, n_steps: int, every: int
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """``stepper.rollout`` with its result checked against the :class:`Stepper` contract and
    its diagnostics completed: a key a stepper leaves out is inferred from the trajectory
    where it can be (a trajectory with a non-finite record failed, code 3, at the step of its
    first one) and unknown (NaN, or 0 Newton updates) elsewhere."""
    n, records = len(x0), n_steps // every + 1
    out = stepper.rollout(x0, h, n_steps, every)
    traj, info = out if isinstance(out, tuple) and len(out) == 2 else (out, {})
    traj = np.asarray(traj)
    if traj.shape != (n, records, x0.shape[1]) or not isinstance(info, Mapping):
        raise TypeError(
            f"{_stepper_name(stepper)}.rollout must return (traj, info) with traj of shape "
            f"{(n, records, x0.shape[1])} and info a dict; got "
            f"{getattr(traj, 'shape', type(traj).__name__)} and {type(info).__name__}"
        )
    raw = dict(info)
    for key, value in raw.items():
        if key in ROLLOUT_KEYS and getattr(value, "shape", None) != (n,):
            raw[key] = value = np.asarray(value)
            if value.shape != (n,):
                raise TypeError(
                    f"{_stepper_name(stepper)}.rollout: info[{key!r}] must have shape ({n},), "
                    f"got {value.shape}"
                )
    if len(raw) >= 6 and all(k in raw for k in ROLLOUT_KEYS[:6]):
        return np.ascontiguousarray(traj, dtype=np.float64), raw  # the package's own steppers
    if "converged" not in raw:
        bad = ~np.isfinite(traj).all(axis=2)  # (n, records)
        first = np.where(bad.any(axis=1), bad.argmax(axis=1), -1)
        raw["converged"] = first < 0
        raw.setdefault("failed_step", np.where(first < 0, -1, np.maximum(first - 1, 0) * every))
        raw.setdefault("failure_code", np.where(first < 0, 0, 3))
    defaults = {
        "failed_step": lambda: np.full(n, -1, dtype=np.int64),
        "failure_code": lambda: np.zeros(n, dtype=np.int64),
        "newton_iterations": lambda: np.zeros(n, dtype=np.int64),
        "max_newton_iterations": lambda: np.zeros(n, dtype=np.int64),
        "max_residual": lambda: np.full(n, np.nan),
    }
    for key, make in defaults.items():
        if key not in raw:
            raw[key] = make()
    return np.ascontiguousarray(traj, dtype=np.float64), raw


def _report(
    stepper: Any,
    h: float,
    n: int,
    summary: tuple[int, int, int, int, float, int],
    on_failure: str,
    domain: Mapping[str, Any] | None = None,
    out_of_domain: np.ndarray | None = None,
) -> None:
    """The warnings of :func:`integrate` (called from it: stacklevel 3 names its caller), in
    this order: a step that does not resolve the motion, recorded states outside a model's
    training domain, failed trajectories (RuntimeError with ``on_failure="raise"``).
    ``summary`` is (n_failed, first failed, its step, its code, max step angle, its index), as
    :func:`_summary` and ``_core.RolloutDiagnostics.summary()`` give it."""
    n_failed, first, failed_step, code, top, worst = summary
    if top > MAX_STEP_ANGLE:  # NaN (no angle known) compares false
        _warn_angle(stepper, top, worst, h, stacklevel=4)
    if domain is not None and out_of_domain is not None:
        n_outside = int(out_of_domain.sum())
        if n_outside:
            n_traj = int((out_of_domain > 0).sum())
            warnings.warn(
                f"{_stepper_name(stepper)}: {n_outside} recorded states of {n_traj} of "
                f"{len(out_of_domain)} trajectories lie outside the training domain "
                f"({_describe_domain(domain)}); the model extrapolates there (see "
                "info.out_of_domain and hj_residual)",
                RuntimeWarning,
                stacklevel=3,
            )
    if n_failed and on_failure != "ignore":
        msg = (
            f"{_stepper_name(stepper)}: {n_failed} of {n} trajectories failed "
            f"(first: trajectory {first} at step {failed_step}: "
            f"{FAILURE_CODES.get(code, f'code {code}')}); their later states are NaN"
        )
        if on_failure == "raise":
            raise RuntimeError(msg)
        warnings.warn(msg, RuntimeWarning, stacklevel=3)


def _summary(raw: Mapping[str, np.ndarray]) -> tuple[int, int, int, int, float, int]:
    """What :func:`integrate` warns about, from the diagnostic arrays of a rollout: as
    ``_core.RolloutDiagnostics.summary()``, (n_failed, first failed trajectory, its failed
    step, its failure code, the largest step angle ignoring NaN, its index); −1 and NaN for
    none."""
    converged = raw["converged"]
    n_failed = 0 if converged.all() else int((~converged).sum())
    first = step = code = -1
    if n_failed:
        first = int(np.flatnonzero(~converged)[0])
        step, code = int(raw["failed_step"][first]), int(raw["failure_code"][first])
    angle = raw["step_angle"]
    if not len(angle) or np.isnan(angle).all():
        return n_failed, first, step, code, math.nan, -1
    worst = int(np.nanargmax(angle))
    return n_failed, first, step, code, float(angle[worst]), worst


#: Largest angle h·ρ a step may turn the state by (ρ the local rate, see
#: :attr:`RolloutInfo.step_angle`; |ω| for the rigid body) before :func:`integrate` warns: beyond
#: a quarter turn no fixed-step method resolves the motion (fewer than 4 steps a revolution), and
#: a Taylor series is beyond its range.
MAX_STEP_ANGLE = 0.5 * math.pi


def _step_angles(stepper: Any, states: np.ndarray, h: float) -> np.ndarray:
    """h × the local rate at each of ``states`` (n, dim) (see :attr:`RolloutInfo.step_angle`),
    from the stepper's system (``system.step_angles``); NaN for an adaptive stepper, which
    chooses its own steps, and for a system that does not know its rate."""
    angles = getattr(getattr(stepper, "system", None), "step_angles", None)
    if angles is None or getattr(stepper, "adaptive", False):
        return np.full(len(states), np.nan)
    return np.asarray(angles(states, h), dtype=np.float64)


def _warn_unresolved(stepper: Any, angle: np.ndarray, h: float) -> None:
    """Warns when a step of size h turns some initial state by more than MAX_STEP_ANGLE: the
    result would be O(1) wrong while every step "converged" (a fixed-step method cannot see it).
    ``angle`` is :attr:`RolloutInfo.step_angle`, one per trajectory (every state is checked);
    NaN angles (DOP853) are skipped."""
    if not len(angle) or np.isnan(angle).all():
        return
    worst = int(np.nanargmax(angle))
    if angle[worst] > MAX_STEP_ANGLE:
        _warn_angle(stepper, float(angle[worst]), worst, h, stacklevel=4)


def _warn_angle(stepper: Any, top: float, worst: int, h: float, stacklevel: int = 3) -> None:
    """The warning of :func:`_warn_unresolved`: state ``worst`` turns by ``top`` rad a step."""
    rate = top / h
    warnings.warn(
        f"{_stepper_name(stepper)}: a step of h = {h:g} turns state {worst} by "
        f"{top:.3g} rad (h × the local rate max(‖ad_∇H‖_F/√2, ‖∂f/∂μ‖_F)), more than a "
        f"quarter turn: no fixed-step method resolves this motion and the result can be O(1) "
        f"wrong with every step converged; use h <= {MAX_STEP_ANGLE / rate:.3g} (see "
        "info.step_angle)",
        RuntimeWarning,
        stacklevel=stacklevel,
    )


def _stepper_name(stepper: Any) -> str:
    """How warnings name an integrator: its name ("learned" model, Taylor, classical method)."""
    name = getattr(stepper, "name", None)
    return f"{type(stepper).__name__} {name!r}" if name else type(stepper).__name__


# --- Dask arrays ---------------------------------------------------------------------------------
# Here rather than in :mod:`poisson_rs.ensembles` (which builds on ``integrate``), so that
# ``integrate`` reaches them without importing a module above it.

#: Fields of :class:`~poisson_rs.integrators.RolloutInfo`, in order.
INFO_FIELDS = (*ROLLOUT_KEYS[:6], "out_of_domain", "step_angle")
_EXTRA = "pip install 'poisson_rs[distributed]'"


def is_dask_array(x: Any) -> bool:
    """Whether ``x`` is a ``dask.array.Array``, without importing dask (an array of one cannot
    exist unless dask.array was imported)."""
    module = sys.modules.get("dask.array")
    return module is not None and isinstance(x, module.Array)


def _rollout_block(
    stepper: Stepper,
    block: np.ndarray,
    h: float,
    n_steps: int,
    every: int,
    strict: bool,
    raise_on_failure: bool,
    offset: int,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """One chunk's rollout, in a worker: (rows, records, dim) and the info fields (rows,).

    Warnings would land in a worker's log, unseen: failures, out-of-domain states and steps too
    large to resolve the motion (``step_angle``) are in the info instead. ``offset``: the
    chunk's first row in the whole array, for the error message.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        traj, info = integrate(
            stepper,
            np.asarray(block),
            h,
            n_steps,
            every=every,
            return_info=True,
            on_failure="ignore",
            strict=strict,
        )
    if raise_on_failure and not info.converged.all():
        first = int(np.flatnonzero(~info.converged)[0])
        raise RuntimeError(
            f"{stepper!r}: {int((~info.converged).sum())} of {len(info.converged)} trajectories "
            f"of the chunk at row {offset} failed (first: trajectory {offset + first} at step "
            f"{int(info.failed_step[first])}); their later states are NaN"
        )
    return traj, {k: getattr(info, k) for k in INFO_FIELDS}


def integrate_dask(
    stepper: Stepper,
    mu0: da.Array,
    h: float,
    n_steps: int,
    *,
    every: int = 1,
    return_info: bool = False,
    on_failure: Literal["warn", "raise", "ignore"] = "warn",
    strict: bool = True,
) -> da.Array | tuple[da.Array, RolloutInfo]:
    """:func:`~poisson_rs.integrate` on a dask array of initial states: a lazy rollout.

    mu0: dask array (n, dim) (or (dim,)) of real numbers, chunked along axis 0 (chunks along
    axis 1 are merged). Returns a float64 dask array (n, n_steps // every + 1, dim) with mu0's
    chunks along axis 0, and with ``return_info`` a :class:`~poisson_rs.integrators.RolloutInfo`
    whose fields are dask arrays (n,) with the same chunks. Computing the trajectories and the
    info together (``dask.compute(traj, info.converged, ...)``) runs each chunk's rollout once.

    Everything but the states is checked now (h, n_steps, every, h_max); non-finite states raise
    ValueError when their chunk is computed. Failures are reported in the info:
    ``on_failure="raise"`` makes a chunk with a failed trajectory raise RuntimeError when
    computed, "warn" and "ignore" warn nothing (a worker's warnings would go unseen), and
    out-of-domain states are counted in ``info.out_of_domain`` and every state's step angle is
    in ``info.step_angle`` (above ``integrators.MAX_STEP_ANGLE`` the step does not resolve the
    motion), without a warning.

    Each chunk's task receives the stepper once (a pickle of its model bytes and options, kept
    once in the graph and shared by every chunk).
    """
    import dask
    import dask.array as da

    dim = int(getattr(stepper, "dim", 3))
    # The empty call checks every argument but the states, and gives the info's dtypes.
    _, empty = integrate(
        stepper,
        np.empty((0, dim)),
        h,
        n_steps,
        every=every,
        return_info=True,
        on_failure=on_failure,
        strict=strict,
    )
    if mu0.dtype == object or mu0.dtype.kind not in "fiu":
        raise TypeError(f"mu0 must be an array of real numbers, got dtype {mu0.dtype}")
    single = mu0.shape == (dim,)
    if single:
        mu0 = mu0.reshape(1, dim)
    if mu0.ndim != 2 or mu0.shape[1] != dim:
        raise ValueError(f"mu0 must have shape ({dim},) or (n, {dim}), got {mu0.shape}")
    if any(np.isnan(c) for c in mu0.chunks[0]):
        raise ValueError("mu0 has unknown chunk sizes; call mu0.compute_chunk_sizes() first")
    if len(mu0.chunks[1]) > 1:
        mu0 = mu0.rechunk({1: -1})
    records = int(n_steps) // int(every) + 1
    token = dask.base.tokenize(pickle.dumps(stepper, protocol=pickle.HIGHEST_PROTOCOL))
    # One graph node holds the stepper; every chunk's task refers to it by key.
    shared = dask.delayed(stepper, name=f"poisson-rs-stepper-{token}")
    run = dask.delayed(_rollout_block, pure=True, nout=2)
    trajs, infos = [], []
    offset = 0
    for block, rows in zip(mu0.to_delayed().ravel(), mu0.chunks[0], strict=True):
        rows = int(rows)
        traj_d, info_d = run(
            shared, block, float(h), int(n_steps), int(every), strict, on_failure == "raise", offset
        )
        trajs.append(da.from_delayed(traj_d, shape=(rows, records, dim), dtype=np.float64))
        infos.append(
            {
                k: da.from_delayed(info_d[k], shape=(rows,), dtype=getattr(empty, k).dtype)
                for k in INFO_FIELDS
            }
        )
        offset += rows
    if trajs:
        traj = da.concatenate(trajs, axis=0)
        fields = {k: da.concatenate([i[k] for i in infos]) for k in INFO_FIELDS}
    else:  # n = 0: nothing to run
        traj = da.zeros((0, records, dim), dtype=np.float64)
        fields = {k: da.from_array(getattr(empty, k)) for k in INFO_FIELDS}
    info = RolloutInfo(**fields)
    out = traj[0] if single else traj
    return (out, info) if return_info else out

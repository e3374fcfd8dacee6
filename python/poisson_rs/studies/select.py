"""The cheapest integrator and step that meet an accuracy target on given states: ``select``.

The target bounds one of three metrics (``metric``): "error", the pointwise relative error at T
(below); "energy", the largest relative energy error max |H − H₀|/|H₀| over [0, T]; or
"casimir", the largest Casimir drift max |C − C₀|/|μ₀|^d over [0, T] (every Casimir known or
found, of degree d). Over a chaotic horizon no method keeps a pointwise error, but the energy and
the Casimirs stay meaningful; when nothing meets a pointwise target the message says which
candidates keep them best. Energy and Casimirs are read at about 100 recorded states of each
rollout (and the final one), not at every step.

Every candidate the package has for a system is measured on the caller's states, on this
machine:

- the Taylor-HJ integrators of odd order K = 1, 3, 5, 7 in every chart the system has (Cayley and
  exp on so(3), exp elsewhere);
- the classical methods of :func:`~poisson_rs.classical_methods` (fixed step h);
- DOP853 (adaptive): h only spaces its output, so its knob is its tolerance rtol = atol, swept
  over 1e-3 … 1e-11 (two decades above the reference's own 1e-13, which it would otherwise match
  by construction);
- the learned models (shipped ones, or those passed in) trained for this very system, at steps no
  larger than their h_max, and only when every initial state lies in their training domain and
  no recorded state of the rollout leaves it.

Each fixed-step candidate walks a ladder of steps h = T/n, n = n₀·2^k (coarse to fine), and stops
at the first h that meets the target: its cheapest passing h, since the cost of a fixed-step
rollout grows with its number of steps. Error: max over the states of |μ(T) − μ_ref(T)| / |μ₀|
against :func:`~poisson_rs.exact_solution` (rigid body) or
:func:`~poisson_rs.reference_solution` (DOP853, rtol = atol = 1e-13). A rung where a Newton solve
fails, a state turns non-finite or a learned model leaves its domain does not pass. Cost: the
measured wall time of ``integrate`` on all the states to T (best of several calls when one is
short), not a formula.
"""

from __future__ import annotations

import math
import os
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ..integrators import (
    FAILURE_CODES,
    Stepper,
    _describe_domain,
    classical,
    classical_methods,
    count_out_of_domain,
    integrate,
    list_models,
    load_model,
    taylor_integrator,
)
from ..protocols import PoissonSystem, as_stepper, as_system
from .methods import taylor_charts, taylor_orders

__all__ = ["CandidateResult", "NoCandidateError", "SelectionReport", "Trial", "select"]

#: What each metric measures (for tables and messages).
METRICS = {
    "error": "max |x(T) - x_ref(T)|/|x0|",
    "energy": "max |H - H0|/|H0| over [0, T]",
    "casimir": "max |C - C0|/|x0|^d over [0, T] (d = 0, absolute, for log-form Casimirs)",
}
#: Recorded states per rollout from which energy and Casimir drifts are read.
RECORDS = 100
#: Steps of the probe that prices a rung before it runs.
PROBE_STEPS = 16

#: Taylor-HJ orders tried (odd: for a quadratic H the even terms vanish).
ORDERS = (1, 3, 5, 7)
#: Coarsest step of the ladder (time units); a learned model starts at its h_max if smaller.
H_START = 1.0
#: Finest rung: at most this many steps to T.
MAX_STEPS = 1 << 20
#: DOP853 tolerances tried (rtol = atol), loosest first.
DOP853_TOLERANCES = tuple(10.0**-k for k in range(3, 12))
#: A rung whose error is not at least this many times below the previous one's has stalled
#: (round-off, Newton tolerance, or the reference's own error); two stalls in a row end a ladder.
STALL_RATIO = 2.0
#: A ladder also ends once a rung costs this many times the cheapest passing candidate so far:
#: its finer rungs cannot win.
PRUNE_FACTOR = 100.0
#: Per-candidate wall-clock budget (seconds): the next rung (about twice the last one's time)
#: must fit in what is left.
BUDGET_S = 20.0


@dataclass(frozen=True)
class Trial:
    """One rung of a ladder: a step h (or a tolerance) measured on every state."""

    h: float
    tol: float | None
    error: float
    """The metric's value (for "error": max |μ(T) − μ_ref(T)| / |μ₀| over the states); inf
    when a trajectory failed."""
    seconds: float
    """Wall time of ``integrate`` on all the states to T (best of the timed calls)."""
    passed: bool
    failure: str = ""
    """Why a rung fails apart from its error: Newton failure, non-finite state, left domain."""
    energy: float = math.nan
    """max |H − H₀| / |H₀| over the recorded states (inf when a trajectory failed)."""
    casimir: float = math.nan
    """max |C − C₀| / |μ₀|^d over the recorded states; NaN when no Casimir is known."""


@dataclass
class CandidateResult:
    """One candidate's outcome: its cheapest passing rung, or why it has none."""

    name: str
    family: str
    """"taylor", "classical", "adaptive" (DOP853) or "learned"."""
    trials: list[Trial] = field(default_factory=list)
    excluded: str = ""
    """Why the candidate was never measured (other system, outside its domain, h > h_max)."""
    reason: str = ""
    """Why it is not the winner (filled in once every candidate is measured)."""
    winner: bool = False
    stopped: str = ""
    """Why the ladder ended short of a pass: "stalled", "budget", "pruned" or "max_steps"."""
    stepper: Stepper | None = field(default=None, repr=False)
    metric: str = "error"
    """The metric its trials measured (see :func:`select`)."""

    @property
    def passing(self) -> Trial | None:
        """The cheapest passing rung (the ladder stops at the first one), or None."""
        return next((t for t in self.trials if t.passed), None)

    @property
    def best(self) -> Trial | None:
        """The rung with the smallest error, passing or not (None: nothing measured)."""
        finite = [t for t in self.trials if math.isfinite(t.error)]
        return min(finite, key=lambda t: t.error) if finite else None


@dataclass
class SelectionReport:
    """What :func:`select` measured; ``str(report)`` is the table."""

    system: PoissonSystem
    T: float
    target: float
    n_states: int
    reference: str
    results: list[CandidateResult]
    seconds: float = 0.0
    """Wall time of the whole selection."""
    metric: str = "error"

    @property
    def winner(self) -> CandidateResult | None:
        return next((r for r in self.results if r.winner), None)

    def rows(self) -> list[dict[str, Any]]:
        """One JSON-ready dict per candidate (h, error, seconds of its cheapest passing rung)."""
        out = []
        for r in self.results:
            p = r.passing
            best = r.best
            out.append(
                {
                    "candidate": r.name,
                    "family": r.family,
                    "winner": r.winner,
                    "h": p.h if p else None,
                    "tol": p.tol if p else None,
                    "error": p.error if p else None,
                    "seconds": p.seconds if p else None,
                    "best_error": best.error if best else None,
                    "rungs": len(r.trials),
                    "reason": r.excluded or r.reason,
                    "T": self.T,
                    "metric": self.metric,
                    "target": self.target,
                    "n_states": self.n_states,
                }
            )
        return out

    def table(self) -> str:
        """The report as a fixed-width table, winner marked with '*'."""
        head = ["", "candidate", "h / tol", self.metric, "cost [s]", "note"]
        cells = []
        for r in self.results:
            p = r.passing
            if p is None:
                knob, err, cost = "-", "-", "-"
            else:
                knob = f"tol={p.tol:.0e}" if p.tol is not None else f"{p.h:.6g}"
                err, cost = f"{p.error:.2e}", f"{p.seconds:.2e}"
            note = "selected" if r.winner else (r.excluded or r.reason)
            cells.append(["*" if r.winner else "", r.name, knob, err, cost, note])
        widths = [max(len(h), *(len(c[i]) for c in cells)) for i, h in enumerate(head)]
        widths[-1] = len(head[-1])  # the last column is left ragged
        fmt = lambda row: "  ".join(v.ljust(w) for v, w in zip(row, widths, strict=True))  # noqa: E731
        name = type(self.system).__name__
        lines = [
            f"select: {name} {_params(self.system)}, {self.n_states} states, T = {self.T:g}, "
            f"target {METRICS[self.metric]} <= {self.target:.0e} (reference: "
            f"{self.reference}); cost = wall time of integrate() on all states to T",
            fmt(head).rstrip(),
            "-" * (sum(widths[:-1]) + 2 * (len(widths) - 1) + 4),
            *(fmt(c).rstrip() for c in cells),
        ]
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.table()


class NoCandidateError(ValueError):
    """No candidate meets the target; ``report`` holds what was measured."""

    def __init__(self, message: str, report: SelectionReport) -> None:
        super().__init__(message)
        self.report = report


def _params(system: PoissonSystem) -> str:
    d = system.to_dict()
    keys = [k for k in ("inertia", "mgl", "com") if k in d]
    if not keys:
        name = getattr(system, "name", None)
        return f"({name}, dim {system.dim})" if name else f"(dim {system.dim})"
    return "(" + ", ".join(f"{k} = {d[k]}" for k in keys) + ")"


@dataclass(frozen=True)
class _Candidate:
    name: str
    family: str
    stepper: Stepper | None = None
    tolerances: dict[float, Stepper] | None = None
    h_max: float = math.inf
    excluded: str = ""


#: The last few references computed (a DOP853 run to T = 1000 takes a minute): several targets on
#: the same states share one.
_REFERENCES: dict[tuple[Any, ...], tuple[np.ndarray, str]] = {}


def _reference(system: PoissonSystem, states: np.ndarray, T: float) -> tuple[np.ndarray, str]:
    """μ_ref(T) for each state, (n, dim), and how it was computed (the system's best
    reference)."""
    key = (system, states.shape, states.tobytes(), T)
    if key not in _REFERENCES:
        name = system.reference_name
        if name == "DOP853":
            name = "DOP853 rtol = atol = 1e-13"
        _REFERENCES[key] = (system.reference(states, [T])[:, 0], name)
        while len(_REFERENCES) > 8:
            del _REFERENCES[next(iter(_REFERENCES))]
    ref, name = _REFERENCES[key]
    return ref.copy(), name


def _model_candidates(
    system: PoissonSystem,
    mu0: np.ndarray,
    models: Sequence[str | os.PathLike[str] | Stepper] | None,
    h: float | None,
) -> list[_Candidate]:
    """Learned (or the caller's own) candidates, each either usable or with the reason it is
    excluded: a shipped or saved model by name or path, or any :class:`~poisson_rs.Stepper`."""
    out = []
    for spec in list_models() if models is None else models:
        model: Any = load_model(spec) if isinstance(spec, (str, os.PathLike)) else spec
        as_stepper(model, "each of models")
        name = f"learned:{getattr(model, 'name', type(model).__name__)}"
        h_max = float(getattr(model, "h_max", math.inf))
        domain = getattr(model, "domain", None)
        own = getattr(model, "system", None)
        why = ""
        if own is not None and own != system:
            why = f"trained for {own!r}"
        elif model.dim != system.dim:
            why = f"integrates states of dimension {model.dim}, not {system.dim}"
        elif h is not None and h > h_max:
            why = f"h = {h:g} > its h_max = {h_max:g}"
        elif isinstance(domain, dict):
            outside = int((count_out_of_domain(domain, mu0[:, None, :]) > 0).sum())
            if outside:
                why = (
                    f"{outside} of {len(mu0)} states outside its training domain "
                    f"({_describe_domain(domain)})"
                )
        out.append(_Candidate(name, "learned", None if why else model, None, h_max, why))
    return out


def _candidates(
    system: PoissonSystem,
    mu0: np.ndarray,
    models: Sequence[str | os.PathLike[str] | Stepper] | None,
    h: float | None,
) -> list[_Candidate]:
    """Cheap-per-step families first, so the pruning bound is set early."""
    names = classical_methods(system)
    out = [
        _Candidate(name, "classical", classical(system, name)) for name in names if name != "dop853"
    ]
    for chart in taylor_charts(system):
        for k in taylor_orders(system, ORDERS):
            out.append(
                _Candidate(f"taylor{k}-{chart}", "taylor", taylor_integrator(system, k, chart))
            )
    out += _model_candidates(system, mu0, models, h)
    if "dop853" in names:
        tols = {tol: classical(system, "dop853", tol=tol) for tol in DOP853_TOLERANCES}
        out.append(_Candidate("dop853", "adaptive", tolerances=tols))
    return out


def _timed_rollout(
    stepper: Stepper, mu0: np.ndarray, h: float, n: int, every: int, *, repeat: bool
) -> tuple[np.ndarray, Any, float]:
    """One rollout to step n (failures and domain warnings left to the caller), and its wall
    time: the best of several calls while they are short (< 50 ms), against scheduler noise."""

    def call() -> tuple[np.ndarray, Any]:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            return integrate(stepper, mu0, h, n, every=every, return_info=True, on_failure="ignore")

    t0 = time.perf_counter()
    traj, info = call()
    best = time.perf_counter() - t0
    total, count = best, 1
    while repeat and best < 0.05 and total < 0.3 and count < 20:
        t0 = time.perf_counter()
        call()
        dt = time.perf_counter() - t0
        best, total, count = min(best, dt), total + dt, count + 1
    return traj, info, best


def _every(n: int, records: int = RECORDS) -> int:
    """The record stride: the largest divisor of n not above n // records (so the final state
    is recorded), at least 1."""
    top = max(1, n // records)
    for every in range(top, 0, -1):
        if n % every == 0:
            return every
    return 1


def _trial(
    stepper: Stepper,
    mu0: np.ndarray,
    ref: np.ndarray | None,
    T: float,
    n: int,
    tol: float | None,
    target: float,
    *,
    learned: bool,
    metric: str = "error",
) -> Trial:
    """Measures one rung: n steps of h = T/n on every state (DOP853: n output points). Energy
    and Casimir drifts are read on about RECORDS recorded states (a learned model's domain, too)."""
    from ..casimirs import max_casimir_drift

    h = T / n
    every = _every(n)
    traj, info, seconds = _timed_rollout(stepper, mu0, h, n, every, repeat=tol is None)
    system = getattr(stepper, "system", None)
    final = traj[:, -1]
    norm0 = np.linalg.norm(mu0, axis=1)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        if ref is not None:
            rel = np.linalg.norm(final - ref, axis=1) / norm0
        else:
            rel = np.where(np.isfinite(final).all(axis=1), np.nan, np.inf)
    failure = ""
    bad = ~info.converged | ~np.isfinite(final).all(axis=1)
    if ref is not None:
        bad |= ~np.isfinite(rel)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        code = int(info.failure_code[i])
        why = FAILURE_CODES.get(code, f"code {code}") if code else "non-finite state"
        failure = f"{int(bad.sum())} of {len(mu0)} trajectories failed ({why})"
        rel = np.where(bad, np.inf, rel)
    elif learned and int(np.sum(info.out_of_domain)):
        failure = "the rollout leaves the training domain"
    energy = casimir = math.inf
    if not bad.any() and system is not None:
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            e = system.hamiltonian(traj)
            energy = float(np.max(np.abs(e - e[:, :1]) / np.abs(e[:, :1])))
            dc = max_casimir_drift(system, traj)
        casimir = float(np.max(dc)) if np.isfinite(dc).all() else math.nan
    value = {"error": float(rel.max()), "energy": energy, "casimir": casimir}[metric]
    if bad.any():
        value = math.inf
    passed = not failure and value <= target
    return Trial(h, tol, value, seconds, passed, failure, energy, casimir)


def _probe_rate(stepper: Stepper, mu0: np.ndarray, h: float, n: int) -> tuple[float, float]:
    """(seconds per step, seconds spent) from a short timed rollout of min(n, PROBE_STEPS)
    steps: the price of a rung before it runs, so a budget holds inside one rollout too."""
    k = max(1, min(n, PROBE_STEPS))
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        integrate(stepper, mu0, h, k, every=k, on_failure="ignore", strict=False)
    spent = time.perf_counter() - t0
    return spent / k, spent


def _ladder(h_cap: float, T: float, max_steps: int) -> list[int]:
    """Step counts n₀·2^k to T, n₀ the fewest with T/n₀ ≤ h_cap, up to max_steps."""
    n0 = max(1, math.ceil(T / h_cap * (1 - 1e-12)))
    out = []
    n = n0
    while n <= max_steps:
        out.append(n)
        n *= 2
    return out  # empty when even the coarsest step needs more than max_steps


def _run_candidate(
    cand: _Candidate,
    mu0: np.ndarray,
    ref: np.ndarray | None,
    T: float,
    target: float,
    *,
    h: float | None,
    max_steps: int,
    budget_s: float,
    best_cost: float,
    metric: str = "error",
) -> CandidateResult:
    res = CandidateResult(cand.name, cand.family, excluded=cand.excluded)
    if cand.excluded:
        return res
    learned = cand.family == "learned"
    t_start = time.perf_counter()

    def affordable(stepper: Stepper, n: int) -> bool:
        """Whether n steps fit in what is left of the budget, priced by a probe (or by the
        last rung's rate): a rung is never started that the budget cannot pay for."""
        spent = time.perf_counter() - t_start
        if res.trials and res.trials[-1].tol is None and cand.tolerances is None:
            last = res.trials[-1]
            rate = last.seconds / max(1, round(T / last.h))
        else:
            rate, _ = _probe_rate(stepper, mu0, T / n, n)
            spent = time.perf_counter() - t_start
        return spent + rate * n <= budget_s

    if cand.tolerances is not None:
        ladder = _ladder(min(H_START, T), T, max_steps)
        if h is None and not ladder:
            res.stopped = "max_steps"
            return res
        n0 = ladder[0] if h is None else round(T / h)
        for tol, stepper in cand.tolerances.items():
            if not affordable(stepper, n0):
                res.stopped = "budget"
                break
            trial = _trial(stepper, mu0, ref, T, n0, tol, target, learned=False, metric=metric)
            res.trials.append(trial)
            if trial.passed:
                res.stepper = stepper
                break
            if trial.seconds * 2 > budget_s or trial.seconds > PRUNE_FACTOR * best_cost:
                res.stopped = "budget" if trial.seconds * 2 > budget_s else "pruned"
                break
        else:
            res.stopped = "max_steps"
        return res
    assert cand.stepper is not None
    steps = [round(T / h)] if h is not None else _ladder(min(H_START, cand.h_max), T, max_steps)
    if not steps:
        res.stopped = "max_steps"
        return res
    spent, stalls = 0.0, 0
    for n in steps:
        if not affordable(cand.stepper, n):
            res.stopped = "budget"
            break
        trial = _trial(cand.stepper, mu0, ref, T, n, None, target, learned=learned, metric=metric)
        prev = res.best
        res.trials.append(trial)
        spent += trial.seconds
        if trial.passed:
            res.stepper = cand.stepper
            break
        # In the asymptotic regime (error < 1e-2) an error that no longer halves has stalled.
        if prev is not None and prev.error < 1e-2 and trial.error > prev.error / STALL_RATIO:
            stalls += 1
        else:
            stalls = 0
        if stalls >= 2:
            res.stopped = "stalled"
            break
        if trial.seconds > PRUNE_FACTOR * best_cost:
            res.stopped = "pruned"
            break
        if spent + 2 * trial.seconds > budget_s:
            res.stopped = "budget"
            break
    else:
        res.stopped = "max_steps" if h is None else ""
    return res


def _explain(res: CandidateResult, winner: CandidateResult | None, target: float) -> str:
    """Why ``res`` is not the winner."""
    p = res.passing
    if p is not None:
        assert winner is not None and winner.passing is not None
        ratio = p.seconds / winner.passing.seconds
        return f"meets the target but costs {ratio:.3g}x the selected"
    if not res.trials:
        if res.stopped == "budget":
            return "not run: its first rung costs more than the time budget"
        if res.stopped == "max_steps":
            return "not run: its coarsest step needs more than max_steps steps"
        return "not measured"
    last = res.trials[-1]
    best = res.best
    if best is None:
        return f"fails at every step tried: {last.failure}"
    knob = f"tol = {best.tol:.0e}" if best.tol is not None else f"h = {best.h:.4g}"
    why = f"best {res.metric} {best.error:.2e} at {knob}"
    failed = [t for t in res.trials if t.failure]
    if failed:
        why += f"; fails at {len(failed)} of the steps tried ({failed[0].failure})"
    if res.stopped == "stalled":
        why += "; the error stalls (round-off, Newton tolerance or the reference's accuracy)"
    elif res.stopped == "pruned" and winner is not None and winner.passing is not None:
        why += f"; stopped at {last.seconds / winner.passing.seconds:.0f}x the selected's cost"
    elif res.stopped == "budget":
        why += f"; stopped at its time budget ({last.seconds:.2g} s for the last rung)"
    elif res.stopped == "max_steps":
        why += "; no finer step on the ladder"
    return why


def select(
    system: PoissonSystem,
    mu0: ArrayLike,
    *,
    T: float,
    target: float,
    metric: str = "error",
    h: float | None = None,
    models: Sequence[str | os.PathLike[str] | Stepper] | None = None,
    reference: ArrayLike | None = None,
    max_steps: int = MAX_STEPS,
    budget_s: float = BUDGET_S,
    progress: Callable[[str], None] | None = None,
) -> tuple[Stepper, float, SelectionReport]:
    """The cheapest integrator and step that keep ``metric`` ≤ ``target`` on the states.

    Parameters
    ----------
    system : PoissonSystem
        Any structure's system, e.g. ``RigidBody()``, ``HeavyTop()``, a Lotka–Volterra.
    mu0 : array_like, shape (n, dim) or (dim,)
        Initial states (finite, non-zero).
    T : float
        Horizon (time units), > 0.
    target : float
        Largest value of the metric allowed, > 0 (unit-less).
    metric : {"error", "energy", "casimir"}
        "error": max |μ(T) − μ_ref(T)| / |μ₀| (pointwise, at T); "energy": max |H − H₀| / |H₀|
        over [0, T]; "casimir": max |C − C₀| / |μ₀|^d over [0, T] (ValueError when the system
        has no known Casimir). The last two need no reference solution.
    h : float, optional
        Measure every candidate at this step only (T/h must be whole); default: a ladder
        h = T/n, n = n₀·2^k, from min(1, T, the model's h_max) down to T/``max_steps``.
    models : sequence of names, paths, loaded models or any steppers, optional
        Learned (or your own) candidates (default: every shipped model,
        :func:`~poisson_rs.list_models`); a model counts only for this system (when it names
        one), at h ≤ its h_max, with every μ₀ in its domain.
    reference : array_like, shape (n, dim), optional
        μ_ref(T) for each state, if already computed; default: the exact flow for a rigid body,
        else DOP853 at rtol = atol = 1e-13.
    max_steps, budget_s : ladder bounds: most steps to T, and seconds per candidate (a rung is
        priced by a short probe before it runs, and not run when the budget cannot pay for it).
    progress : called with one line per candidate measured.

    Returns
    -------
    (stepper, h, report): the selected integrator (for DOP853: ``classical(system, "dop853",
    tol=...)``, whose h only spaces the output), the step to use with :func:`integrate`, and a
    :class:`SelectionReport` whose ``str`` is the table.

    Raises
    ------
    NoCandidateError (a ValueError)
        "no candidate meets 1e-14 at T = 10; best was ...", with ``.report`` attached.
    TypeError, ValueError
        For a malformed system, states, horizon, target or step.
    """
    t_start = time.perf_counter()
    system = as_system(system)
    for what, v in (("T", T), ("target", target)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < math.inf:
            raise ValueError(f"{what} must be a finite number > 0, got {v!r}")
    T, target = float(T), float(target)
    if metric not in METRICS:
        raise ValueError(f"metric must be one of {tuple(METRICS)}, got {metric!r}")
    if isinstance(max_steps, bool) or not isinstance(max_steps, int) or max_steps < 1:
        raise ValueError(f"max_steps must be an integer >= 1, got {max_steps!r}")
    for what, v in (("budget_s", budget_s),):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < math.inf:
            raise ValueError(f"{what} must be a finite number > 0, got {v!r}")
    if metric == "casimir":
        from ..casimirs import system_casimirs

        if system_casimirs(system) is None:
            raise ValueError(
                f"metric='casimir': no Casimir is known for {system.title} "
                f"({system.casimir_label}); choose metric='error' or 'energy' (on a Lie–Poisson "
                "system, poisson_rs.casimirs.set_casimirs(algebra, [...]) registers your own)"
            )
    if h is not None:
        if isinstance(h, bool) or not isinstance(h, (int, float)) or not 0 < h < math.inf:
            raise ValueError(f"h must be a finite number > 0, got {h!r}")
        n = round(T / h)
        if n < 1 or abs(n * h - T) > 1e-9 * T:
            raise ValueError(f"T = {T:g} must be a whole number of steps h = {h:g}")
        h = float(h)
    states = np.asarray(mu0, dtype=np.float64)
    if states.ndim == 1:
        states = states[None, :]
    if states.ndim != 2 or states.shape[1] != system.dim or len(states) == 0:
        raise ValueError(f"mu0 must have shape (n, {system.dim}), got {np.shape(mu0)}")
    if not np.isfinite(states).all() or (np.linalg.norm(states, axis=1) == 0).any():
        raise ValueError("mu0 must hold finite, non-zero states")
    system.check_states(states, "mu0")
    states = np.ascontiguousarray(states)
    ref: np.ndarray | None
    if metric != "error":
        ref, ref_name = None, "none needed"
    elif reference is None:
        ref, ref_name = _reference(system, states, T)
    else:
        ref = np.asarray(reference, dtype=np.float64).reshape(states.shape)
        ref_name = "given"
    results = []
    best_cost = math.inf
    for cand in _candidates(system, states, models, h):
        t0 = time.perf_counter()
        res = _run_candidate(
            cand,
            states,
            ref,
            T,
            target,
            h=h,
            max_steps=max_steps,
            budget_s=budget_s,
            best_cost=best_cost,
            metric=metric,
        )
        res.metric = metric
        if res.passing is not None:
            best_cost = min(best_cost, res.passing.seconds)
        results.append(res)
        if progress is not None:
            p = res.passing
            what = (
                res.excluded
                or (p and f"passes at h = {p.h:.4g}, error {p.error:.2e}, {p.seconds:.2e} s")
                or "does not pass"
            )
            progress(f"{cand.name}: {what} ({time.perf_counter() - t0:.1f} s)")
    passing = [r for r in results if r.passing is not None]
    winner = min(passing, key=lambda r: r.passing.seconds) if passing else None  # type: ignore[union-attr]
    if winner is not None:
        winner.winner = True
    for r in results:
        if not r.winner and not r.excluded:
            r.reason = _explain(r, winner, target)
    report = SelectionReport(
        system, T, target, len(states), ref_name, results, time.perf_counter() - t_start, metric
    )
    if winner is None:
        measured = [r for r in results if r.best is not None]
        if measured:
            top = min(measured, key=lambda r: r.best.error)  # type: ignore[union-attr]
            b = top.best
            assert b is not None
            knob = f"tol = {b.tol:.0e}" if b.tol is not None else f"h = {b.h:.4g}"
            best = f"{top.name} with {b.error:.2e} at {knob}"
        else:
            best = "nothing (every candidate failed or was excluded)"
        raise NoCandidateError(
            f"no candidate meets {target:.0e} at T = {T:g}; best was {best}"
            + (_long_horizon_hint(results) if metric == "error" else ""),
            report,
        )
    p = winner.passing
    assert p is not None and winner.stepper is not None
    return winner.stepper, p.h, report


def _long_horizon_hint(results: Sequence[CandidateResult]) -> str:
    """When no pointwise target is met: the candidates that keep the energy and the Casimirs
    best (over a chaotic horizon nearby orbits separate, so a pointwise error at T says little,
    while these invariants stay meaningful)."""
    parts = []
    for key, label in (("energy", "energy"), ("casimir", "casimir")):
        scored = []
        for r in results:
            vals = [getattr(t, key) for t in r.trials if math.isfinite(getattr(t, key))]
            if vals:
                t = min((t for t in r.trials if math.isfinite(getattr(t, key))),
                        key=lambda t: getattr(t, key))  # fmt: skip
                knob = f"tol = {t.tol:.0e}" if t.tol is not None else f"h = {t.h:.4g}"
                scored.append((min(vals), f"{r.name} {min(vals):.1e} ({knob}, {t.seconds:.1e} s)"))
        if scored:
            best = ", ".join(text for _, text in sorted(scored)[:3])
            parts.append(f"best by {label}: {best}")
    if not parts:
        return ""
    return (
        ". Over a long or chaotic horizon no method keeps a pointwise error; select by "
        "metric='energy' or 'casimir' (--metric) instead; " + "; ".join(parts)
    )

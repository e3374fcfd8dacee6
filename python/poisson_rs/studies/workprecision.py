"""Work–precision measurements: accuracy per unit of cost for every integrator, same machine, on
any system (the rigid body, the heavy top, any Lie–Poisson scene).

Every method steps behind the same :func:`~poisson_rs.integrate`, so costs compare like with like.
For each scene, method and step size h (or tolerance, for an adaptive method) one row records the
error at the horizon T against :func:`~poisson_rs.exact_solution`, the largest relative energy
and Casimir deviations over [0, T], Newton failures and the wall-clock seconds per trajectory.
A long run records |ΔH|/H against time over 10⁵ steps. Rows are plain dicts (CSV/JSON ready);
plotting lives in :mod:`poisson_rs.studies.figures`.

Conventions: errors are Euclidean norms |μ − μ_ref| (max over the scene's states; the reference is
the exact flow for a rigid body, else DOP853 at rtol = atol = 1e-13); ΔH/H is |H − H₀|/|H₀| and
ΔC is |C − C₀|/|μ₀|^d for each Casimir of degree d (for the rigid body |C − C₀|/C₀), max over
states and output times, and NaN when the system has no known Casimir; a setting where any
trajectory fails has ``failed = True`` and no accuracy numbers (never dropped silently). A
learned model is also measured past the largest step it was trained for (``extrapolated``).
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..casimirs import casimir_degrees, casimir_label, max_casimir_drift, system_casimirs
from ..integrators import (
    FAILURE_CODES,
    RolloutInfo,
    Stepper,
    classical,
    classical_methods,
    integrate,
    shipped_models,
    taylor_integrator,
)
from ..protocols import PoissonSystem
from ..structures.lie_poisson import RigidBody
from .methods import taylor_charts, taylor_orders

Row = dict[str, Any]
Progress = Callable[[str], None]

PAPER_INERTIA = (1.5, 2.0, 2.5)
HORIZON = 10.0
#: Step counts to T = 10: h = 1, 0.4, 0.2, ..., 0.0015625. h = 1 is past the default model's
#: training range (h ≤ 0.1) and where the DESIGN notes say the Taylor series break down.
FULL_STEPS = (10, 25, 50, 100, 200, 400, 800, 1600, 3200, 6400)
QUICK_STEPS = (50, 100, 200)
#: The paper-configuration network costs ~1.7 ms a step: only a few step sizes.
SLOW_STEPS = (25, 50, 100, 200)
TAYLOR_ORDERS = (1, 3, 5, 7)
CHARTS = ("cayley", "exp")
#: rtol = atol of the adaptive DOP853 sweep; its h only sets the output spacing.
DOP853_TOLERANCES = tuple(10.0**-k for k in range(4, 13))
DOP853_SPACING = 0.1
LEVELS = (1e-3, 1e-6, 1e-9)
#: A learned model refuses h > h_max unless ``strict=False``: the chart measures past it on
#: purpose, flagging those rows as ``extrapolated``.
_LENIENT: dict[str, Any] = {"strict": False}


def _integrate(stepper: Stepper, mu0: Any, h: float, n_steps: int, **kw: Any) -> Any:
    """``integrate`` with failures left to the caller: no warnings, no h_max refusal.

    Failures are read from the returned info; states outside a model's training domain are
    counted in ``info.out_of_domain`` (where integrate has it) rather than warned about.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return integrate(stepper, mu0, h, n_steps, on_failure="ignore", **_LENIENT, **kw)


@dataclass(frozen=True)
class Scene:
    """Initial states of one system integrated together. states: (n, dim); horizon T in time
    units. ``system``: any system with ``dim``, ``hamiltonian`` and ``casimirs``."""

    name: str
    system: PoissonSystem
    states: np.ndarray
    T: float = HORIZON
    description: str = ""

    @property
    def body(self) -> PoissonSystem:
        """The system (the name the rigid-body-only version used)."""
        return self.system


def reference_at(system: PoissonSystem, states: np.ndarray, times: Any) -> np.ndarray:
    """The reference at ``times`` for each state, (n, len(times), dim): the system's best
    (:meth:`~poisson_rs.PoissonSystem.reference`: the exact flow for a rigid body, else DOP853
    at rtol = atol = 1e-13)."""
    return system.reference(np.asarray(states, dtype=np.float64), times)


def steps_to(T: float, counts: Sequence[int]) -> tuple[int, ...]:
    """Step counts to horizon T from ``counts`` given per HORIZON (= 10) time units: the same
    step sizes h = HORIZON / count on every horizon."""
    return tuple(dict.fromkeys(max(1, round(n * T / HORIZON)) for n in counts))


@dataclass(frozen=True)
class Method:
    """An integrator and its cost knob.

    Fixed-step methods sweep h over ``steps`` (step counts to T; None: the sweep's default).
    An adaptive method gives ``tolerances`` (tol → stepper, tol = rtol = atol) and is run at
    output spacing ``spacing``; its ΔH is then sampled at that spacing only.
    """

    name: str
    family: str
    """One of "learned", "taylor", "classical" or "adaptive"."""
    stepper: Stepper
    steps: tuple[int, ...] | None = None
    tolerances: dict[float | None, Stepper] | None = None
    """tol → stepper; the key None marks a single point at the method's own tolerance."""
    spacing: float = DOP853_SPACING
    long_run_budget_s: float | None = None
    """Wall-clock cap for the long run (None: the run's default)."""


@dataclass
class ChartData:
    """Everything ``poisson-rs chart`` measures."""

    rows: list[Row]
    long_rows: list[Row]
    notes: list[str]
    call_overhead_s: float
    """Seconds of an ``integrate`` call on the paper scene that takes no step (fixed cost)."""
    scenes: list[Scene] = field(default_factory=list)
    long_h: float = 0.1
    """Step size of the long run."""
    casimir_label: str = ""
    """What the Casimir drift measures, for axis labels (or that none is known)."""


def paper_scene(body: RigidBody | None = None) -> Scene:
    """The paper's scene: I = (1.5, 2, 2.5), states (1, 1, 2) and (3, 2, 0), T = 10."""
    body = RigidBody(PAPER_INERTIA) if body is None else body
    states = np.array([[1.0, 1.0, 2.0], [3.0, 2.0, 0.0]])
    return Scene("paper", body, states, HORIZON, "the paper's states (1,1,2) and (3,2,0)")


def separatrix_state(body: RigidBody, eps: float, mu2: float = 3.0, mu3: float = 0.5) -> np.ndarray:
    """The state (μ₁ > 0, mu2, mu3) at relative distance Δ/C = eps from the separatrix. (3,)

    Δ = 2H·I₂ − C vanishes on the separatrix through the intermediate axis; Δ > 0 orbits
    circulate about the axis of smallest inertia, Δ < 0 about the largest. Needs I₁ < I₂ < I₃.
    """
    i1, i2, i3 = body.inertia
    if not i1 < i2 < i3:
        raise ValueError(f"separatrix_state needs I1 < I2 < I3, got {body.inertia}")
    # Δ = μ₁²(I₂−I₁)/I₁ − μ₃²(I₃−I₂)/I₃ and C = μ₁² + μ₂² + μ₃²; Δ = εC is linear in μ₁².
    a, c = (i2 - i1) / i1, (i3 - i2) / i3
    mu1_sq = (eps * (mu2**2 + mu3**2) + c * mu3**2) / (a - eps)
    if mu1_sq <= 0:
        raise ValueError(f"no state at Δ/C = {eps} with μ₂ = {mu2}, μ₃ = {mu3}")
    return np.array([math.sqrt(mu1_sq), mu2, mu3])


def separatrix_scene(
    body: RigidBody | None = None, offsets: Sequence[float] = (1e-3, -1e-3, 1e-2)
) -> Scene:
    """States near the intermediate axis, at Δ/C = ``offsets`` from its separatrix, T = 10.

    Starting at μ ≈ (0.4, 3, 0.5), all leave the unstable axis within T; the Δ/C = ±1e-3 pair
    ends 2.9 apart (one per side) and the exact flow amplifies a perturbation about 40-fold.
    """
    body = RigidBody(PAPER_INERTIA) if body is None else body
    states = np.array([separatrix_state(body, e) for e in offsets])
    desc = "Δ/C = " + ", ".join(f"{e:+.0e}" for e in offsets) + " from the separatrix"
    return Scene("separatrix", body, states, HORIZON, desc)


def default_methods(
    body: PoissonSystem,
    *,
    quick: bool = False,
    include_paper: bool = True,
    notes: list[str] | None = None,
) -> list[Method]:
    """The shipped learned models trained for ``body`` (any system), Taylor K ∈ {1,3,5,7} in
    every chart the system has (Cayley and exp on so(3), exp elsewhere), and the classical
    methods the system has.

    Classical methods come from ``poisson_rs.classical`` when it exists; one that is missing
    is skipped with a line in ``notes``. ``quick`` keeps a handful of cheap methods (tests).
    """

    notes = [] if notes is None else notes
    methods: list[Method] = []
    # A model of another system would be scored against the wrong flow: only this system's.
    mine = shipped_models(body)
    for name, model in mine.items():
        if name == "paper":
            if include_paper and not quick:
                # 253k parameters: a few step sizes only, and a shorter long run.
                methods.append(
                    Method(
                        "learned:paper", "learned", model, steps=SLOW_STEPS, long_run_budget_s=30.0
                    )
                )
            continue
        if quick and name != "default" and len(mine) > 1 and "default" in mine:
            continue
        methods.append(Method(f"learned:{name}", "learned", model))
    if not mine:
        notes.append("no shipped learned model integrates this system: none charted")
    orders = (3, 5) if quick else TAYLOR_ORDERS
    charts = taylor_charts(body)
    for chart in charts[:1] if quick else charts:
        for k in taylor_orders(body, orders):
            methods.append(
                Method(f"taylor{k}-{chart}", "taylor", taylor_integrator(body, k, chart))
            )
    if quick and len(charts) > 1:
        methods.append(
            Method(f"taylor3-{charts[1]}", "taylor", taylor_integrator(body, 3, charts[1]))
        )

    # Quick runs (tests) keep the fixed-step methods, in the core, and leave out DOP853.
    for name in classical_methods(body):
        if quick and name == "dop853":
            continue
        try:
            stepper = classical(body, name)
            # One step, so that a method whose Rust side is not built yet is skipped here
            # rather than aborting the sweep (from a state inside the positive orthant, where
            # a log-canonical system lives).
            _integrate(stepper, np.full(body.dim, 0.5), 0.1, 1)
        except Exception as e:  # any reason at all: skip it, say why
            notes.append(f"classical {name!r} not available: {type(e).__name__}: {e}")
            continue
        if name != "dop853":
            methods.append(Method(name, "classical", stepper))
            continue
        tols = (1e-6, 1e-10) if quick else DOP853_TOLERANCES
        tolerances: dict[float | None, Stepper] = {
            tol: classical(body, "dop853", tol=tol) for tol in tols
        }
        # Python-side solve_ivp: a much slower long run, capped by its budget.
        methods.append(
            Method(name, "adaptive", stepper, tolerances=tolerances, long_run_budget_s=60.0)
        )
    return methods


def _describe_failure(info: RolloutInfo, finite: np.ndarray) -> str:
    """One line: how many trajectories failed, where and why."""
    bad = ~info.converged | ~finite
    parts = []
    for i in np.flatnonzero(bad):
        code = int(info.failure_code[i])
        why = FAILURE_CODES.get(code, f"code {code}") if code else "non-finite state"
        step = int(info.failed_step[i])
        parts.append(f"#{i} {why}" + (f" at step {step}" if step >= 0 else ""))
    return "; ".join(parts)


def _best_seconds(
    call: Callable[[], object],
    *,
    min_repeats: int = 7,
    max_repeats: int = 50,
    min_total: float = 0.25,
    cap: float = 3.0,
) -> tuple[float, float, int]:
    """Best wall-clock seconds of ``call``, the CPU seconds of that best call, and the count.

    Repeats until both ``min_repeats`` timings and ``min_total`` seconds are reached (so cheap
    calls get many tries against scheduler noise), but stops once ``cap`` seconds are spent.
    CPU time is the whole process's, so it adds up rayon's threads.
    """
    best, best_cpu, total, n = math.inf, math.inf, 0.0, 0
    while n < max_repeats and (n < 1 or total < cap) and (n < min_repeats or total < min_total):
        t0, c0 = time.perf_counter(), time.process_time()
        call()
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
        if dt < best:
            best, best_cpu = dt, dc
        total, n = total + dt, n + 1
    return best, best_cpu, n


def measure(
    scene: Scene,
    method: str,
    family: str,
    stepper: Stepper,
    h: float,
    n_steps: int,
    exact: np.ndarray,
    *,
    tol: float | None = None,
    repeats: bool = True,
    min_call_s: float = 0.03,
    max_batch: int = 4096,
) -> Row:
    """One work–precision point. exact: (n_states, records, dim), of which only the last record,
    μ_ref(T), is read.

    Accuracy comes from one run of the scene's states with every state kept. The cost is timed
    separately: ``integrate`` on the scene's states tiled k times (k chosen so that a call lasts
    at least ``min_call_s``, at most ``max_batch`` trajectories), keeping only the final state,
    best of several calls, divided by the batch size. Tiling amortises the ~40 µs fixed cost of
    an ``integrate`` call, which would otherwise swamp the cheapest methods (RK4 takes ~20 ns a
    step). ``seconds_per_traj`` is wall-clock (rayon runs a Rust batch on all cores; DOP853 in
    SciPy runs one trajectory at a time), ``cpu_seconds_per_traj`` CPU time summed over threads.
    Without ``repeats``: one untiled call, as is (quick runs).
    """
    n = len(scene.states)

    def call() -> tuple[np.ndarray, RolloutInfo]:
        return _integrate(stepper, scene.states, h, n_steps, return_info=True)

    row: Row = {
        "scene": scene.name,
        "method": method,
        "family": family,
        "h": h,
        "tol": tol,
        "n_steps": n_steps,
        "n_states": n,
        "T": h * n_steps,
        "error_T": None,
        "max_rel_dH": None,
        "max_rel_dC": None,
        "failed": False,
        "n_failed": 0,
        "failure": "",
        "extrapolated": h > float(getattr(stepper, "h_max", math.inf)),
        "out_of_domain": None,
        "seconds_per_traj": None,
        "cpu_seconds_per_traj": None,
        "timing_batch": n,
        "repeats": 1,
        "newton_iters_per_step": None,
    }
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        traj, info = call()
    except (RuntimeError, ValueError, ArithmeticError) as e:
        # An adaptive solver (or a method refusing the step size) raising is a failure too.
        row.update(failed=True, n_failed=n, failure=f"{type(e).__name__}: {e}"[:200], repeats=0)
        return row
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    if repeats:
        k = int(min(max(math.ceil(min_call_s / max(wall, 1e-9)), 1), max(max_batch // n, 1)))
        batch = np.tile(scene.states, (k, 1))
        every = max(n_steps, 1)

        def timed() -> object:
            return _integrate(stepper, batch, h, n_steps, every=every)

        wall, cpu, count = _best_seconds(timed)
        row.update(timing_batch=k * n, repeats=count)
    batch_size = row["timing_batch"]
    row.update(seconds_per_traj=wall / batch_size, cpu_seconds_per_traj=cpu / batch_size)
    if n_steps:
        row["newton_iters_per_step"] = float(np.mean(info.newton_iterations)) / n_steps
    if getattr(info, "out_of_domain", None) is not None:
        row["out_of_domain"] = int(np.sum(info.out_of_domain))

    finite = np.isfinite(traj).all(axis=(1, 2))
    if not (info.converged.all() and finite.all()):
        failed = int((~info.converged | ~finite).sum())
        row.update(failed=True, n_failed=failed, failure=_describe_failure(info, finite))
        return row
    system = scene.system
    h0 = system.hamiltonian(traj[:, :1])
    dc = max_casimir_drift(system, traj)
    row.update(
        error_T=float(np.linalg.norm(traj[:, -1] - exact[:, -1], axis=-1).max()),
        max_rel_dH=float((np.abs(system.hamiltonian(traj) - h0) / np.abs(h0)).max()),
        # NaN when the system has no known Casimir: "n/a", never a zero drift.
        max_rel_dC=float(np.max(dc)) if np.isfinite(dc).all() else float("nan"),
    )
    return row


def _settings(
    method: Method, steps: Sequence[int], T: float
) -> list[tuple[float, int, float | None, Stepper]]:
    """(h, n_steps, tol, stepper) for every point of ``method``'s sweep to horizon T; ``steps``
    are counts per HORIZON time units (the same step sizes on every horizon)."""
    if method.tolerances is not None:
        n = max(1, round(T / method.spacing))
        return [(T / n, n, tol, s) for tol, s in method.tolerances.items()]
    return [(T / n, n, None, method.stepper) for n in steps_to(T, method.steps or steps)]


def call_overhead(scene: Scene, stepper: Stepper) -> float:
    """Seconds of an ``integrate`` call on the scene's states that takes no step (best of 50)."""
    best = math.inf
    for _ in range(50):
        t0 = time.perf_counter()
        integrate(stepper, scene.states, 0.1, 0)
        best = min(best, time.perf_counter() - t0)
    return best


def sweep(
    scenes: Iterable[Scene],
    methods: Sequence[Method],
    steps: Sequence[int] = FULL_STEPS,
    *,
    repeats: bool = True,
    progress: Progress | None = None,
    client: Any = None,
) -> list[Row]:
    """Work–precision rows for every scene × method × step size (or tolerance). See measure.

    ``client``: a ``distributed.Client`` that runs the points as futures, each timed in a
    worker (one point at a time per worker thread); a progress bar follows them.
    """
    rows: list[Row] = []
    scenes = list(scenes)
    total, done = len(scenes) * len(methods), 0
    measured: Iterator[Row] | None = None
    if client is not None:
        from ..ensembles import run_all

        jobs = []
        for scene in scenes:
            scene_ref = reference_at(scene.system, scene.states, [scene.T])
            for m in methods:
                for h, n, tol, stepper in _settings(m, steps, scene.T):
                    args = (scene, m.name, m.family, stepper, h, n, scene_ref)
                    jobs.append((args, {"tol": tol, "repeats": repeats}))
        measured = iter(run_all(client, measure, jobs, desc="points", progress=bool(progress)))
    for scene in scenes:
        # Only μ_ref(T) is compared: one reference per scene (h·n = T for every setting).
        ref: np.ndarray | None = (
            reference_at(scene.system, scene.states, [scene.T]) if measured is None else None
        )
        for m in methods:
            t0 = time.perf_counter()
            settings = _settings(m, steps, scene.T)
            for h, n, tol, stepper in settings:
                if measured is not None:
                    rows.append(next(measured))
                    continue
                assert ref is not None
                row = measure(
                    scene, m.name, m.family, stepper, h, n, ref, tol=tol,
                    repeats=repeats,
                )  # fmt: skip
                rows.append(row)
            done += 1
            if progress is not None:
                n_failed = sum(r["failed"] for r in rows[-len(settings) :])
                fails = f", {n_failed} failed" if n_failed else ""
                progress(
                    f"[{done:2d}/{total}] {scene.name}: {m.name} "
                    f"({len(settings)} points{fails}) {time.perf_counter() - t0:.1f} s"
                )
    return rows


def window_edges(n_steps: int, n_windows: int = 200) -> np.ndarray:
    """Geometrically growing window ends 1 = e₀ < e₁ < ... = n_steps (step indices)."""
    edges = np.unique(np.round(np.geomspace(1, n_steps, n_windows)).astype(np.int64))
    return edges[edges >= 1]


def long_run(
    scene: Scene,
    methods: Sequence[Method],
    h: float = 0.1,
    n_steps: int = 100_000,
    *,
    budget_s: float = 20.0,
    n_windows: int = 200,
    progress: Progress | None = None,
    notes: list[str] | None = None,
) -> list[Row]:
    """|ΔH|/H and |ΔC|/C against time: one row per (method, state, window).

    Each row holds the maximum over the steps of a window (window ends grow geometrically, so a
    log time axis is evenly covered). Taking the max over every step, not a sample every k-th
    one, keeps the envelope honest: a stroboscopic sample can alias with the orbit's period.
    The run goes in chunks with only the current chunk's states in memory; a one-step map
    restarted from its last state is bit-identical to an unbroken run (DOP853 resets its step
    size controller at each restart). A method that exceeds its wall-clock budget
    (``Method.long_run_budget_s`` or ``budget_s``) stops early, with a line in ``notes``.
    """
    notes = [] if notes is None else notes
    edges = window_edges(n_steps, n_windows)
    rows: list[Row] = []
    body = scene.system
    casimirs = system_casimirs(body)
    degrees = np.asarray(casimir_degrees(body) or (), dtype=np.float64)
    norm0 = np.linalg.norm(scene.states, axis=1)
    labels = ["(" + ", ".join(f"{v:g}" for v in s) + ")" for s in scene.states]
    for idx, m in enumerate(methods):
        budget = m.long_run_budget_s if m.long_run_budget_s is not None else budget_s
        stepper = m.stepper
        tols = [t for t in (m.tolerances or {}) if t is not None]
        tol = min(tols) if tols else None
        if tol is not None and m.tolerances is not None:  # adaptive: at its tightest tolerance
            stepper = m.tolerances[tol]
            notes.append(f"long run: {m.name} at rtol = atol = {tol:.0e}")
        n_states = len(scene.states)
        dh = np.full((n_states, n_steps + 1), np.nan)
        dc = np.full((n_states, n_steps + 1), np.nan)
        # H₀ with its sign (a heavy top's is negative where the potential dominates): the
        # error is |H − H₀| / |H₀|, never |H − |H₀||.
        h0 = np.asarray(body.hamiltonian(scene.states), dtype=np.float64)
        c0 = casimirs(scene.states) if casimirs is not None else None  # (n, m)
        dh[:, 0] = 0.0
        dc[:, 0] = 0.0 if c0 is not None else np.nan
        state = scene.states.copy()
        alive = np.ones(n_states, dtype=bool)
        done, t0, chunk = 0, time.perf_counter(), 1000
        while done < n_steps and alive.any():
            spent = time.perf_counter() - t0
            if done and spent > 0:
                # Size the next chunk to the budget left, from the speed so far.
                rate = done / spent
                chunk = int(min(20_000, (budget - spent) * rate))
            chunk = min(chunk, n_steps - done)
            if chunk < 1:
                break
            traj, info = _integrate(stepper, state[alive], h, chunk, return_info=True)
            ids = np.flatnonzero(alive)
            seg = slice(done + 1, done + chunk + 1)
            dh[ids, seg] = np.abs(body.hamiltonian(traj[:, 1:]) - h0[ids, None]) / np.abs(
                h0[ids, None]
            )
            if casimirs is not None and c0 is not None:
                # |C − C₀| / |μ₀|^d, max over the Casimirs (rigid body: |C − C₀| / C₀).
                drift = np.abs(casimirs(traj[:, 1:]) - c0[ids, None, :])
                scale = norm0[ids, None, None] ** degrees
                dc[ids, seg] = (drift / scale).max(axis=-1)
            ok = info.converged & np.isfinite(traj[:, -1]).all(axis=1)
            for j in np.flatnonzero(~ok):
                step = done + max(int(info.failed_step[j]), 0)
                notes.append(f"long run: {m.name} from {labels[ids[j]]} failed at step {step}")
            state[ids[ok]] = traj[ok, -1]
            alive[ids[~ok]] = False
            done += chunk
        elapsed = time.perf_counter() - t0
        if done < n_steps and alive.any():
            notes.append(
                f"long run: {m.name} stopped at {done} of {n_steps} steps (t = {done * h:g}) "
                f"after its {budget:g} s budget"
            )
        # Window ends up to the last step run; a run cut short by its budget ends on the step
        # where it stopped, so the figure's "to t = ..." is the t of the note, not the last
        # full window before it.
        ends = [int(e) for e in edges if e <= done]
        if done >= 1 and (not ends or ends[-1] != done):
            ends.append(done)
        for i in range(n_states):
            lo = 1
            for e in ends:
                win_h, win_c = dh[i, lo : e + 1], dc[i, lo : e + 1]
                lo = e + 1
                if not np.isfinite(win_h).all():
                    break  # past a failure
                rows.append(
                    {
                        "scene": scene.name,
                        "method": m.name,
                        "family": m.family,
                        "state": labels[i],
                        "h": h,
                        "tol": tol,
                        "step": int(e),
                        "t": float(e * h),
                        "max_rel_dH": float(win_h.max()),
                        "max_rel_dC": float(win_c.max()) if np.isfinite(win_c).all() else math.nan,
                    }
                )
        if progress is not None:
            progress(
                f"[{idx + 1:2d}/{len(methods)}] long run: {m.name} {done} steps {elapsed:.1f} s"
            )
    return rows


def _knob_order(row: Row) -> tuple[float, float]:
    """Coarse to fine: h descending, then tolerance descending."""
    tol = row["tol"]
    return (-row["h"], -(tol if tol is not None else 0.0))


def rank_at_level(
    rows: Iterable[Row],
    level: float,
    *,
    scene: str | None = None,
    metric: str = "error_T",
    interpolate: bool = True,
) -> list[Row]:
    """Methods that reach ``metric`` ≤ ``level`` on ``scene``, cheapest first.

    ``scene``: the scene's name; None when the rows hold one scene only (ValueError when they
    hold several: the ranking is per scene). Each result: method, seconds (per trajectory), h,
    tol, interpolated. Candidates are the
    measured points at or below the level and, with ``interpolate``, the crossings of the level
    between consecutive points of a method's curve (coarse to fine), with log(seconds)
    interpolated linearly in log(metric). Nothing is extrapolated past measured points, and
    no curve is interpolated across a failed point.
    """
    rows = list(rows)
    if scene is None:
        names = list(dict.fromkeys(r["scene"] for r in rows))
        if len(names) > 1:
            raise ValueError(f"the rows hold scenes {names}: give scene=one of them")
        scene = names[0] if names else None
    by_method: dict[str, list[Row]] = {}
    for r in rows:
        if r["scene"] == scene:
            by_method.setdefault(r["method"], []).append(r)
    best: list[Row] = []
    for pts in by_method.values():
        pts.sort(key=_knob_order)
        cands: list[Row] = []
        for i, p in enumerate(pts):
            if p["failed"] or p[metric] is None or p["seconds_per_traj"] is None:
                continue
            if not math.isfinite(p[metric]):
                continue  # not known (NaN): it reaches no level
            if p[metric] <= level:
                cands.append({**_pick(p), "seconds": p["seconds_per_traj"], "interpolated": False})
            q = pts[i - 1] if i else None
            if q is None or q["failed"] or q[metric] is None:
                continue
            if interpolate and q[metric] > level >= p[metric] > 0:
                f = (math.log(level) - math.log(q[metric])) / (
                    math.log(p[metric]) - math.log(q[metric])
                )
                lc = math.log(q["seconds_per_traj"]) + f * (
                    math.log(p["seconds_per_traj"]) - math.log(q["seconds_per_traj"])
                )
                cands.append({**_pick(p), "seconds": math.exp(lc), "interpolated": True})
        if cands:
            best.append(min(cands, key=lambda c: c["seconds"]))
    return sorted(best, key=lambda c: c["seconds"])


def _pick(row: Row) -> Row:
    return {"method": row["method"], "h": row["h"], "tol": row["tol"]}


def fastest_at_level(
    rows: Iterable[Row],
    level: float,
    *,
    scene: str | None = None,
    metric: str = "error_T",
    interpolate: bool = True,
) -> Row | None:
    """The cheapest method reaching ``metric`` ≤ ``level`` (see rank_at_level), or None.
    ``scene`` may be left out when the rows hold one scene."""
    ranked = rank_at_level(rows, level, scene=scene, metric=metric, interpolate=interpolate)
    return ranked[0] if ranked else None


def run_chart(
    *,
    quick: bool = False,
    include_paper: bool = True,
    progress: Progress | None = None,
    client: Any = None,
    models: Sequence[Stepper] = (),
    scene: Scene | None = None,
) -> ChartData:
    """The measurements behind ``poisson-rs chart``: sweeps on both scenes and the long run.

    ``quick``: a tiny sweep (three step sizes, a few methods, a 2000-step long run) for tests.
    ``client``: a ``distributed.Client`` for the sweep's points (the long run stays here).
    ``models``: the user's own learned models, charted beside the others; each must have been
    trained for the scene's system (ValueError otherwise: another system's reference would
    score it against the wrong flow). ``scene``: chart this scene of any system instead of the
    paper's and the separatrix one.
    """
    notes: list[str] = []
    scenes = [paper_scene(), separatrix_scene()] if scene is None else [scene]
    system = scenes[0].system
    for model in models:  # checked before any work
        if getattr(model, "system", None) != system:
            from .figures import system_label

            raise ValueError(
                f"model {getattr(model, 'name', model)!r} integrates "
                f"{system_label(getattr(model, 'system', None))}, not the chart's "
                f"{system_label(system)}"
            )
    methods = default_methods(system, quick=quick, include_paper=include_paper, notes=notes)
    for model in models:
        methods.append(Method(f"learned:{model.name}", "learned", model))  # type: ignore[attr-defined]
    for line in notes:
        if progress is not None:
            progress(f"note: {line}")
    overhead = call_overhead(scenes[0], methods[0].stepper)  # the first method: the baseline
    rows = sweep(
        scenes,
        methods,
        QUICK_STEPS if quick else FULL_STEPS,
        repeats=not quick,
        progress=progress,
        client=client,
    )
    long_rows = long_run(
        scenes[0],
        methods,
        n_steps=2000 if quick else 100_000,
        budget_s=5.0 if quick else 20.0,
        progress=progress,
        notes=notes,
    )
    return ChartData(rows, long_rows, notes, overhead, scenes, 0.1, casimir_label(system))

"""Stability map: where each integrator breaks as the step size grows, over many initial states,
for any system.

For every method, step size h and initial state the rollout runs to a fixed horizon T and records
the relative error |μ(T) − μ_ref(T)| / |μ₀| (the exact flow for a rigid body, else DOP853 at
rtol = atol = 1e-13), the largest relative energy error |H − H₀|/|H₀| and Casimir drift
|C − C₀|/|μ₀|^d over [0, T] (NaN when the system has no known Casimir), and Newton failures (a
failed trajectory is recorded as failed, never as a number). For the rigid body the states lie
on spheres of several radii, some beyond the default model's training shell (1 ≤ |μ| ≤ 4), on
both sides of the separatrix through the intermediate axis and close to it; for any other system
they are the scene's states (or fixed directions at the same radii).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterator, Sequence
from functools import partial
from typing import Any

import numpy as np

from ..casimirs import max_casimir_drift
from ..integrators import (
    FAILURE_CODES,
    RolloutInfo,
    Stepper,
    classical,
    classical_methods,
    integrate,
    load_model,
    shipped_models,
    taylor_integrator,
)
from ..reference import RigidBody, exact_solution, reference_solution
from ..structures.lie_poisson import LiePoissonSystem
from .methods import (
    LOG_CHART,
    classical_names,
    classical_stepper,
    default_chart,
    is_log_canonical,
    is_positive_orthant,
)
from .methods import taylor as taylor_stepper

Row = dict[str, Any]

STEP_SIZES = (0.01, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0)
QUICK_STEP_SIZES = (0.1, 1.0)
RADII = (1.0, 2.5, 4.0, 6.0)
HORIZON = 20.0
#: Log distances |ln x − ln x*| of the states of a log-canonical system from its equilibrium.
LOG_RADII = (0.25, 0.5, 1.0, 1.5)


def directions(body: RigidBody) -> dict[str, np.ndarray]:
    """Unit initial directions: circulating about the smallest- and the largest-inertia axis, and
    within 1e-2 of the separatrix (on the smallest-axis side)."""
    i1, i2, i3 = body.inertia
    # On the unit sphere the separatrix is d₁²(I₂/I₁ − 1) = d₃²(1 − I₂/I₃) (with d₂ small).
    a, c = abs(i2 / i1 - 1.0), abs(1.0 - i2 / i3)
    near = np.array([1.0, 0.05, np.sqrt(a / c) * (1.0 - 1e-2)])
    out = {
        "axis 1 side": np.array([0.9, 0.3, 0.3]),
        "axis 3 side": np.array([0.3, 0.3, 0.9]),
        "separatrix": near,
    }
    return {k: v / np.linalg.norm(v) for k, v in out.items()}


def generic_directions(system: LiePoissonSystem) -> dict[str, np.ndarray]:
    """Three fixed unit directions in Rⁿ (seeded) for a system without the rigid body's
    separatrix geometry."""
    rng = np.random.default_rng(20240601)
    out = {f"direction {k + 1}": rng.normal(size=system.dim) for k in range(3)}
    return {k: v / np.linalg.norm(v) for k, v in out.items()}


def states(body: LiePoissonSystem, radii: Sequence[float] = RADII) -> tuple[np.ndarray, list[str]]:
    """(n, dim) initial states and their labels, every direction at every radius (the rigid
    body's :func:`directions`, else :func:`generic_directions`)."""
    if is_positive_orthant(body):
        return log_states(body, LOG_RADII if tuple(radii) == RADII else radii)
    rows, labels = [], []
    found = directions(body) if isinstance(body, RigidBody) else generic_directions(body)
    for r in radii:
        for name, d in found.items():
            rows.append(r * d)
            labels.append(f"|μ|={r:g}, {name}")
    return np.array(rows), labels


def log_states(system: Any, radii: Sequence[float] = LOG_RADII) -> tuple[np.ndarray, list[str]]:
    """States of a log-canonical system (n, dim), all in the open positive orthant: x = x* ∘
    exp(ρ d) for each fixed unit direction d of :func:`generic_directions` and each log
    distance ρ in ``radii`` from x* = b, the equilibrium of a Lotka–Volterra H = Σ (x_i −
    b_i ln x_i) (x* = 1 when b is not positive)."""
    b = np.asarray(system.log_hamiltonian.b, dtype=np.float64)
    center = b if (b > 0).all() else np.ones_like(b)
    rows, labels = [], []
    for r in radii:
        for name, d in generic_directions(system).items():
            rows.append(center * np.exp(r * d))
            labels.append(f"|ln x − ln x*|={r:g}, {name}")
    return np.array(rows), labels


def _loader(name: str) -> Callable[[], Stepper]:
    return lambda: load_model(name)


def default_methods(body: LiePoissonSystem) -> dict[str, Callable[[], Stepper]]:
    """Methods of the map, built lazily: the shipped learned models trained for ``body`` (but the
    253k-parameter paper configuration, too slow for the grid), Taylor series (Cayley and exp on
    so(3), exp elsewhere) and the classical ones the system has. A model of another system would
    be scored against the wrong flow, so it is left out."""
    if is_log_canonical(body):
        # Taylor-HJ on the exact groupoid, the log splittings (explicit, Poisson) and the
        # non-Poisson RK4 and midpoint rule in x.
        log: dict[str, Callable[[], Stepper]] = {
            f"taylor{k}-{LOG_CHART}": partial(taylor_stepper, body, k, LOG_CHART) for k in (3, 5)
        }
        for name in ("log_splitting", "log_splitting4", "midpoint", "rk4"):
            log[name] = partial(classical_stepper, body, name)
        return log
    if not isinstance(body, LiePoissonSystem):
        # Another structure (affine: on its central extension): Taylor-exp and the classical
        # methods it has.
        other: dict[str, Callable[[], Stepper]] = {
            f"taylor{k}-{default_chart(body)}": partial(
                taylor_stepper, body, k, default_chart(body)
            )
            for k in (3, 5)
        }
        for name in ("midpoint", "rk4"):
            if name in classical_names(body):
                other[name] = partial(classical_stepper, body, name)
        return other
    learned = {f"learned:{n}": _loader(n) for n in shipped_models(body) if n != "paper"}
    methods: dict[str, Callable[[], Stepper]] = dict(learned)
    if body.algebra.is_so3():
        methods["taylor3-cayley"] = lambda: taylor_integrator(body, 3, "cayley")
        methods["taylor5-cayley"] = lambda: taylor_integrator(body, 5, "cayley")
        methods["taylor3-exp"] = lambda: taylor_integrator(body, 3, "exp")
    else:
        methods["taylor3-exp"] = lambda: taylor_integrator(body, 3, "exp")
        methods["taylor5-exp"] = lambda: taylor_integrator(body, 5, "exp")
    available = classical_methods(body)
    for name in ("splitting", "midpoint", "rk4"):
        if name in available:
            methods[name] = partial(classical, body, name)
    return methods


def stability_map(
    body: LiePoissonSystem | None = None,
    step_sizes: Sequence[float] = STEP_SIZES,
    radii: Sequence[float] = RADII,
    horizon: float = HORIZON,
    methods: dict[str, Callable[[], Stepper]] | None = None,
    progress: Callable[[str], None] | None = None,
    client: Any = None,
    states: tuple[np.ndarray, Sequence[str]] | None = None,
) -> list[Row]:
    """One row per (method, h, state); see the module docstring for the fields.

    ``body``: any system (default: the paper's rigid body). ``states``: (mu0 (n, dim), labels)
    instead of the grid of :func:`states` over ``radii``.

    ``client``: a ``distributed.Client`` that runs the (method, h) rollouts as futures (a
    progress bar follows them instead of ``progress``); the rows are the same as in process.
    """
    body = RigidBody() if body is None else body
    if states is not None:
        mu0, labels = np.asarray(states[0], dtype=np.float64), list(states[1])
    else:
        mu0, labels = _grid_states(body, radii)
    methods = default_methods(body) if methods is None else methods
    rows: list[Row] = []
    done: Iterator[tuple[np.ndarray, RolloutInfo]] | None = None
    if client is not None:
        from ..ensembles import run_all

        jobs = [
            ((make(), mu0, h, max(1, round(horizon / h))), {})
            for h in step_sizes
            for make in methods.values()
        ]
        done = iter(run_all(client, _rollout, jobs, desc="stability", progress=bool(progress)))
    for h in step_sizes:
        n_steps = max(1, round(horizon / h))
        T = n_steps * h
        if isinstance(body, RigidBody):
            exact = exact_solution(body, mu0, [T])[:, 0]
        else:
            exact = reference_solution(body, mu0, [T])[:, 0]
        for name, make in methods.items():
            if done is not None:
                traj, info = next(done)
            else:
                if progress is not None:
                    progress(f"{name} h={h:g}")
                traj, info = _rollout(make(), mu0, h, n_steps)
            e = body.hamiltonian(traj)
            dc = max_casimir_drift(body, traj)  # NaN where no Casimir is known
            for i, label in enumerate(labels):
                ok = bool(info.converged[i])
                r0 = float(np.linalg.norm(mu0[i]))
                rows.append(
                    {
                        "method": name,
                        "h": h,
                        "state": label,
                        "radius": r0,
                        "T": T,
                        "converged": ok,
                        "failed_step": int(info.failed_step[i]),
                        "failure": FAILURE_CODES.get(int(info.failure_code[i]), ""),
                        "rel_error": float(np.linalg.norm(traj[i, -1] - exact[i]) / r0)
                        if ok
                        else float("nan"),
                        "max_rel_dH": _nanmax(np.abs(e[i] - e[i, 0]) / abs(e[i, 0])),
                        "max_rel_dC": _nanmax(dc[i]),
                        "out_of_domain_states": int(info.out_of_domain[i]),
                    }
                )
    return rows


_grid_states = states


def _nanmax(values: np.ndarray) -> float:
    """The largest finite value, or NaN when none is (not known, or every record failed)."""
    finite = values[np.isfinite(values)]
    return float(finite.max()) if finite.size else float("nan")


def _rollout(
    stepper: Stepper, mu0: np.ndarray, h: float, n_steps: int
) -> tuple[np.ndarray, RolloutInfo]:
    """One cell of the map (in this process or a worker): (n, n_steps + 1, 3) and the info."""
    with warnings.catch_warnings():
        # Failures and out-of-domain states are recorded in the rows, not warned about.
        warnings.simplefilter("ignore", RuntimeWarning)
        # strict=False: the map exists to show models beyond their training h_max.
        return integrate(
            stepper, mu0, h, n_steps, return_info=True, on_failure="ignore", strict=False
        )


def first_failures(rows: Sequence[Row], threshold: float = 0.1) -> list[Row]:
    """Per method, the smallest h at which some state fails or its relative error exceeds
    ``threshold``, and how (sorted from the first to break)."""
    out = []
    for method in dict.fromkeys(r["method"] for r in rows):
        mine = sorted((r for r in rows if r["method"] == method), key=lambda r: r["h"])
        broken = [r for r in mine if not r["converged"] or not r["rel_error"] <= threshold]
        if broken:
            h0 = broken[0]["h"]
            at = [r for r in broken if r["h"] == h0]
            fails = [r for r in at if not r["converged"]]
            n_states = sum(r["h"] == h0 for r in mine)
            how = (
                f"Newton failure ({fails[0]['failure']}) in {len(fails)} of {n_states} states"
                if fails
                else f"error > {threshold:g} in {len(at)} of {n_states} states"
            )
            out.append({"method": method, "h_breaks": h0, "how": how})
        else:
            out.append({"method": method, "h_breaks": float("inf"), "how": "never, on this grid"})
    return sorted(out, key=lambda r: r["h_breaks"])

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
from ..protocols import PoissonSystem
from ..structures.lie_poisson import RigidBody
from .methods import taylor_charts, taylor_orders

Row = dict[str, Any]

STEP_SIZES = (0.01, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0)
QUICK_STEP_SIZES = (0.1, 1.0)
HORIZON = 20.0


def directions(body: PoissonSystem) -> dict[str, np.ndarray]:
    """The system's unit test directions: for the rigid body, circulating about the smallest-
    and the largest-inertia axis and within 1e-2 of the separatrix; three seeded directions
    otherwise."""
    return body._directions()  # type: ignore[attr-defined]


def states(
    body: PoissonSystem, radii: Sequence[float] | None = None
) -> tuple[np.ndarray, list[str]]:
    """(n, dim) initial states and their labels, every direction of the system at every size
    in ``radii`` (default: the system's ``sample_radii``; |μ| on g*, log distances from the
    equilibrium on a log-canonical system)."""
    radii = body.sample_radii if radii is None else radii
    return body.sample_states(radii)


def _loader(name: str) -> Callable[[], Stepper]:
    return lambda: load_model(name)


def default_methods(body: PoissonSystem) -> dict[str, Callable[[], Stepper]]:
    """Methods of the map, built lazily: the shipped learned models trained for ``body`` (but the
    253k-parameter paper configuration, too slow for the grid), Taylor-HJ of orders 3 and 5 in
    the system's first chart and of order 3 in its second (the orders the system offers a study:
    jets stop at 3, a fifth-order jet step costing 125 ms on the four vortices), and its
    fixed-step classical methods. A model of another system would be scored against the wrong
    flow, so it is left out."""
    methods: dict[str, Callable[[], Stepper]] = {
        f"learned:{n}": _loader(n) for n in shipped_models(body) if n != "paper"
    }
    charts = taylor_charts(body)
    orders = taylor_orders(body, (3, 5))
    pairs = [*((k, charts[0]) for k in orders), *((3, c) for c in charts[1:2] if 3 in orders)]
    for k, chart in pairs:
        methods[f"taylor{k}-{chart}"] = partial(taylor_integrator, body, k, chart)
    for name in classical_methods(body):
        if name != "dop853":  # adaptive: it has no step size to break at
            methods[name] = partial(classical, body, name)
    return methods


def stability_map(
    body: PoissonSystem | None = None,
    step_sizes: Sequence[float] = STEP_SIZES,
    radii: Sequence[float] | None = None,
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

        jobs: list[tuple[tuple[Any, ...], dict[str, Any]]] = [
            ((make(), mu0, h, max(1, round(horizon / h))), {})
            for h in step_sizes
            for make in methods.values()
        ]
        done = iter(run_all(client, rollout, jobs, desc="stability", progress=bool(progress)))
    for h in step_sizes:
        n_steps = max(1, round(horizon / h))
        T = n_steps * h
        exact = body.reference(mu0, [T])[:, 0]
        for name, make in methods.items():
            if done is not None:
                traj, info = next(done)
            else:
                if progress is not None:
                    progress(f"{name} h={h:g}")
                traj, info = rollout(make(), mu0, h, n_steps)
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


def rollout(
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
                f"step failure ({fails[0]['failure']}) in {len(fails)} of {n_states} states"
                if fails
                else f"error > {threshold:g} in {len(at)} of {n_states} states"
            )
            out.append({"method": method, "h_breaks": h0, "how": how})
        else:
            out.append({"method": method, "h_breaks": float("inf"), "how": "never, on this grid"})
    return sorted(out, key=lambda r: r["h_breaks"])

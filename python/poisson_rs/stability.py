"""Stability map: where each integrator breaks as the step size grows, over many initial states.

For every method, step size h and initial state the rollout runs to a fixed horizon T and records
the relative error |μ(T) − μ_exact(T)| / |μ₀|, the largest relative energy and Casimir deviations
over [0, T], and Newton failures (a failed trajectory is recorded as failed, never as a number).
States lie on spheres of several radii, some beyond the default model's training shell
(1 ≤ |μ| ≤ 4), on both sides of the separatrix through the intermediate axis and close to it.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np

from .integrators import (
    FAILURE_CODES,
    RolloutInfo,
    Stepper,
    classical,
    integrate,
    load_model,
    shipped_models,
    taylor_integrator,
)
from .reference import RigidBody, exact_solution

Row = dict[str, Any]

STEP_SIZES = (0.01, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0)
QUICK_STEP_SIZES = (0.1, 1.0)
RADII = (1.0, 2.5, 4.0, 6.0)
HORIZON = 20.0


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


def states(body: RigidBody, radii: Sequence[float] = RADII) -> tuple[np.ndarray, list[str]]:
    """(n, 3) initial states and their labels, every direction at every radius."""
    rows, labels = [], []
    for r in radii:
        for name, d in directions(body).items():
            rows.append(r * d)
            labels.append(f"|μ|={r:g}, {name}")
    return np.array(rows), labels


def _loader(name: str) -> Callable[[], Stepper]:
    return lambda: load_model(name)


def default_methods(body: RigidBody) -> dict[str, Callable[[], Stepper]]:
    """Methods of the map, built lazily: the shipped learned models trained for ``body`` (but the
    253k-parameter paper configuration, too slow for the grid), Taylor series and classical ones.
    A model of another body would be scored against the wrong flow, so it is left out."""
    learned = {f"learned:{n}": _loader(n) for n in shipped_models(body) if n != "paper"}
    return {
        **learned,
        "taylor3-cayley": lambda: taylor_integrator(body, 3, "cayley"),
        "taylor5-cayley": lambda: taylor_integrator(body, 5, "cayley"),
        "taylor3-exp": lambda: taylor_integrator(body, 3, "exp"),
        "splitting": lambda: classical(body, "splitting"),
        "midpoint": lambda: classical(body, "midpoint"),
        "rk4": lambda: classical(body, "rk4"),
    }


def stability_map(
    body: RigidBody | None = None,
    step_sizes: Sequence[float] = STEP_SIZES,
    radii: Sequence[float] = RADII,
    horizon: float = HORIZON,
    methods: dict[str, Callable[[], Stepper]] | None = None,
    progress: Callable[[str], None] | None = None,
    client: Any = None,
) -> list[Row]:
    """One row per (method, h, state); see the module docstring for the fields.

    ``client``: a ``distributed.Client`` that runs the (method, h) rollouts as futures (a
    progress bar follows them instead of ``progress``); the rows are the same as in process.
    """
    body = RigidBody() if body is None else body
    mu0, labels = states(body, radii)
    methods = default_methods(body) if methods is None else methods
    rows: list[Row] = []
    done: Iterator[tuple[np.ndarray, RolloutInfo]] | None = None
    if client is not None:
        from .ensembles import run_all

        jobs = [
            ((make(), mu0, h, max(1, round(horizon / h))), {})
            for h in step_sizes
            for make in methods.values()
        ]
        done = iter(run_all(client, _rollout, jobs, desc="stability", progress=bool(progress)))
    for h in step_sizes:
        n_steps = max(1, round(horizon / h))
        T = n_steps * h
        exact = exact_solution(body, mu0, [T])[:, 0]
        for name, make in methods.items():
            if done is not None:
                traj, info = next(done)
            else:
                if progress is not None:
                    progress(f"{name} h={h:g}")
                traj, info = _rollout(make(), mu0, h, n_steps)
            e = body.hamiltonian(traj)
            c = body.casimir(traj)
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
                        "max_rel_dH": float(np.nanmax(np.abs(e[i] - e[i, 0])) / e[i, 0]),
                        "max_rel_dC": float(np.nanmax(np.abs(c[i] - c[i, 0])) / c[i, 0]),
                        "out_of_domain_states": int(info.out_of_domain[i]),
                    }
                )
    return rows


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

"""The demo: rollouts of several integrators measured against the exact solution.

The paper's scene is the default: rigid body with I = (1.5, 2, 2.5); initial states (1, 1, 2)
and (3, 2, 0); 10,000 steps of h = 0.1. Any other Lie–Poisson system works too, measured against a
tight DOP853 reference, from the system's ``demo_states``. Errors are Euclidean norms
|μ − μ_ref|; ΔH is relative to |H₀|, ΔC (every Casimir known or found, of degree d) relative to
|μ₀|^d, and NaN when no Casimir is known.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..protocols import PoissonSystem, Stepper
from ..rollout import integrate
from ..structures.lie_poisson import RigidBody

PAPER_STATES = np.array([[1.0, 1.0, 2.0], [3.0, 2.0, 0.0]])
PAPER_H = 0.1
PAPER_STEPS = 10_000


@dataclass
class Run:
    """One integrator's rollout of a scene."""

    name: str
    traj: np.ndarray
    """(n_states, n_steps + 1, dim)"""
    seconds: float
    """Wall-clock time of the rollout (all states together)."""
    info: Any = None


@dataclass
class SceneResult:
    body: PoissonSystem
    """The system (a RigidBody for the paper's scene)."""
    states: np.ndarray
    h: float
    times: np.ndarray
    """(n_steps + 1,)"""
    exact: np.ndarray
    """(n_states, n_steps + 1, dim): the exact solution, or a DOP853 reference."""
    runs: list[Run] = field(default_factory=list)

    def errors(self, run: Run) -> np.ndarray:
        """|μ − μ_exact| per state and step: (n_states, n_steps + 1)."""
        return np.linalg.norm(run.traj - self.exact, axis=-1)

    def worst_error(self, run: Run) -> float:
        """The largest |μ − μ_exact| over every state and record; inf where a record is not
        finite (a failed trajectory is never the most accurate)."""
        err = self.errors(run)
        return float(err.max()) if err.size and np.isfinite(err).all() else math.inf

    def most_accurate(self) -> Run:
        """The run with the smallest :meth:`worst_error` (the first of equals): the one an
        orbit figure shows, whatever order the methods were given in."""
        if not self.runs:
            raise ValueError("the scene has no runs")
        return min(self.runs, key=self.worst_error)

    def energy_drift(self, run: Run) -> np.ndarray:
        """|H − H₀| / |H₀| per state and step."""
        e = self.body.hamiltonian(run.traj)
        return np.abs(e - e[:, :1]) / np.abs(e[:, :1])

    def casimir_drift(self, run: Run) -> np.ndarray:
        """Largest |C − C₀| / |μ₀|^d over the system's Casimirs (degree d; known in closed form
        or found by :mod:`poisson_rs.casimirs`), per state and step; NaN where none is known
        (for the rigid body, C = |μ|², so this is |C − C₀| / C₀)."""
        from ..casimirs import max_casimir_drift

        return max_casimir_drift(self.body, run.traj)

    def metrics(self, horizons: tuple[float, ...] = (10.0, 1000.0)) -> list[dict[str, Any]]:
        """One row per (method, state, horizon): error at T and max ΔH, ΔC over [0, T]."""
        rows = []
        for run in self.runs:
            err, dh, dc = self.errors(run), self.energy_drift(run), self.casimir_drift(run)
            for T in horizons:
                k = round(T / self.h)
                if k >= len(self.times):
                    continue
                for i, mu0 in enumerate(self.states):
                    rows.append(
                        {
                            "method": run.name,
                            "state": "(" + ", ".join(f"{v:g}" for v in mu0) + ")",
                            "T": T,
                            "error": float(err[i, k]),
                            "max_rel_dH": float(np.nanmax(dh[i, : k + 1])),
                            # NaN (no Casimir known) stays NaN: "n/a", never 0.
                            "max_rel_dC": _max_or_nan(dc[i, : k + 1]),
                            "steps_per_s": len(self.states) * (len(self.times) - 1) / run.seconds,
                        }
                    )
        return rows


def _max_or_nan(values: np.ndarray) -> float:
    """The largest finite value, or NaN when there is none."""
    finite = values[np.isfinite(values)]
    return float(finite.max()) if finite.size else float("nan")


def demo_states(system: PoissonSystem) -> np.ndarray:
    """Initial states of the demo for ``system`` (n, dim): its ``demo_states`` (the paper's two
    for the rigid body, a slow precession and a fast top on se(3)*, two seeded states elsewhere)."""
    return np.array(system.demo_states, dtype=np.float64)


def run_scene(
    methods: dict[str, Stepper],
    body: PoissonSystem | None = None,
    states: np.ndarray = PAPER_STATES,
    h: float = PAPER_H,
    n_steps: int = PAPER_STEPS,
    *,
    strict: bool = True,
) -> SceneResult:
    """Rolls every method out from ``states`` (n, dim) and computes the exact solution alongside
    (a DOP853 reference, rtol = atol = 1e-13, for systems without a closed form); ``strict=False``
    lets learned models step beyond their h_max (see ``integrate``)."""
    body = RigidBody() if body is None else body
    times = h * np.arange(n_steps + 1)
    states = np.asarray(states, float)
    exact = body.reference(states, times)
    result = SceneResult(body, states, h, times, exact)
    for name, method in methods.items():
        t0 = time.perf_counter()
        traj, info = integrate(
            method, states, h, n_steps, return_info=True, on_failure="warn", strict=strict
        )
        result.runs.append(Run(name, traj, time.perf_counter() - t0, info))
    return result

"""What one step of every stepper of the package costs, in one process, one thread:
``RAYON_NUM_THREADS=1 taskset -c 0 python benches/step_costs.py``.

For the rigid body (I = (1.5, 2, 2.5)), the heavy top (I = (1, 1.5, 2), mgl = 0.981, χ = e₃) and
Lotka–Volterra (PNN's 2D system, the 3D one of ``scenes/lotka_volterra_3d.toml`` and a 5D one),
h = 0.1, a batch of seeded states (``--batch``, default 4096): every fixed-step classical method
(``pr.classical_methods``, or RK4, the midpoint rule and the log splittings on Lotka–Volterra;
DOP853 left out: it is adaptive and in SciPy), Taylor-HJ K = 3 and 5 in each chart the system has
(the exact log-canonical groupoid for Lotka–Volterra), and the shipped learned models of that
system. ``--system`` picks one system. Each stepper rolls the
batch forward for a fixed amount of work and keeps only the final state; a cell is the median of
``--rounds`` timed rollouts after a warm-up, rounds alternating the steppers. Reported: ns per
trajectory-step, the ratio to the package's own RK4 step in the same run, and the mean Newton
updates per step of the implicit ones (from ``integrate(..., return_info=True)``). ``--json
FILE`` writes the numbers.

A step's cost is only half of the choice: what it buys in accuracy is charted by ``poisson-rs
select`` and the work–precision charts; this table says where the time of a step goes.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
import warnings
from pathlib import Path
from typing import Any

os.environ.setdefault("RAYON_NUM_THREADS", "1")

import numpy as np

import poisson_rs as pr
from poisson_rs.files import atomic_write_bytes, check_output_path

H = 0.1
#: A 5-D Lotka–Volterra system (c of rank 4: one Casimir), for the dimensions above 3.
LV5_C = [
    [0.0, 1.0, -1.0, 1.0, 0.0],
    [-1.0, 0.0, 1.0, 0.0, 1.0],
    [1.0, -1.0, 0.0, 1.0, -1.0],
    [-1.0, 0.0, -1.0, 0.0, 1.0],
    [0.0, -1.0, 1.0, -1.0, 0.0],
]
LV5_B = [1.0, 2.0, 1.5, 0.5, 1.0]
#: Trajectory-steps per timed rollout.
WORK = 200_000


def rigid_states(batch: int, rng: np.random.Generator) -> np.ndarray:
    """On spheres of radius 1 to 3 (inside the default model's shell 1 ≤ |μ| ≤ 4)."""
    d = rng.normal(size=(batch, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(1.0, 3.0, (batch, 1))


def top_states(batch: int, rng: np.random.Generator) -> np.ndarray:
    """M in [−1.5, 1.5]³ and Γ a unit vector (inside the learned model's top domain)."""
    g = rng.normal(size=(batch, 3))
    return np.concatenate(
        [rng.uniform(-1.5, 1.5, (batch, 3)), g / np.linalg.norm(g, axis=1, keepdims=True)], axis=1
    )


def lotka_volterra_states(batch: int, rng: np.random.Generator, b: np.ndarray) -> np.ndarray:
    """Within a log distance of 0.4 of the equilibrium x* = b (inside the learned model's box)."""
    return np.exp(rng.uniform(-0.4, 0.4, (batch, len(b)))) * b


def steppers(system: Any, learned: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if isinstance(system, pr.LogCanonicalSystem):
        for name in ("rk4", "midpoint", "log_splitting", "log_splitting4"):
            out[name] = pr.log_canonical_classical(system, name)
        for order in (3, 5):
            out[f"taylor{order}-log"] = pr.log_canonical_taylor(system, order)
        for name in learned:
            out[f"learned:{name}"] = pr.load_model(name)
        return out
    for name in pr.classical_methods(system):
        if name != "dop853":
            out[name] = pr.classical(system, name)
    charts = ("exp", "cayley") if isinstance(system, pr.RigidBody) else ("exp",)
    for order in (3, 5):
        for chart in charts:
            out[f"taylor{order}-{chart}"] = pr.taylor_integrator(system, order=order, chart=chart)
    for name in learned:
        out[f"learned:{name}"] = pr.load_model(name)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=4096)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument(
        "--system", choices=("all", "rigid-body", "heavy-top", "lotka-volterra"), default="all"
    )
    args = parser.parse_args()
    if args.batch < 1 or args.rounds < 1:
        raise SystemExit("--batch and --rounds must be at least 1")
    if args.json is not None:
        check_output_path(args.json)
    # A learned model's orbits may leave its training domain over the rollout: that changes its
    # accuracy, not the cost of a step, and the warning would only clutter the table.
    warnings.filterwarnings("ignore", message=".*outside the training domain.*")
    rng = np.random.default_rng(42)
    cases = [
        ("rigid body", pr.RigidBody((1.5, 2.0, 2.5)), rigid_states(args.batch, rng), ["default"]),
        (
            "heavy top",
            pr.HeavyTop((1.0, 1.5, 2.0), 0.981, (0.0, 0.0, 1.0)),
            top_states(args.batch, rng),
            ["heavy_top_h05"],
        ),
    ]
    pnn = pr.lotka_volterra([[0.0, 1.0], [-1.0, 0.0]], [1.0, 2.0])
    lv3 = pr.lotka_volterra([[0.0, 1.0, 1.0], [-1.0, 0.0, 1.0], [-1.0, -1.0, 0.0]], [1.0, 2.0, 1.0])
    cases += [
        (
            "lotka-volterra",
            pnn,
            lotka_volterra_states(args.batch, rng, np.array([1.0, 2.0])),
            ["lotka_volterra_h01"],
        ),
        (
            "lotka-volterra 3d",
            lv3,
            lotka_volterra_states(args.batch, rng, np.array([1.0, 2.0, 1.0])),
            [],
        ),
        (
            "lotka-volterra 5d",
            pr.lotka_volterra(LV5_C, LV5_B),
            lotka_volterra_states(args.batch, rng, np.array(LV5_B)),
            [],
        ),
    ]
    if args.system != "all":
        dims = (" 3d", " 5d")
        cases = [
            c
            for c in cases
            if c[0].replace(dims[0], "").replace(dims[1], "").replace(" ", "-") == args.system
        ]
    rows: list[dict[str, Any]] = []
    for label, system, mu0, learned in cases:
        table = steppers(system, learned)
        n_steps = {name: max(1, WORK // args.batch) for name in table}
        # Cheap explicit steps take more steps a rollout, so every timing is well above noise.
        for name in ("rk4", "splitting", "splitting_casimir", "log_splitting"):
            if name in n_steps:
                n_steps[name] *= 20
        updates: dict[str, float] = {}
        for name, s in table.items():
            _, info = pr.integrate(s, mu0, H, n_steps[name], every=n_steps[name], return_info=True)
            if not np.all(info.converged):
                raise SystemExit(f"{label}, {name}: a step failed in the bench rollout")
            total = float(np.sum(info.newton_iterations))
            updates[name] = total / (len(mu0) * n_steps[name]) if total else float("nan")
        times: dict[str, list[float]] = {name: [] for name in table}
        for _ in range(args.rounds):
            for name, s in table.items():
                start = time.perf_counter()
                pr.integrate(s, mu0, H, n_steps[name], every=n_steps[name])
                times[name].append((time.perf_counter() - start) / (len(mu0) * n_steps[name]))
        base = statistics.median(times["rk4"])
        for name in table:
            ns = statistics.median(times[name]) * 1e9
            u = updates[name]
            rows.append(
                {
                    "system": label,
                    "stepper": name,
                    "batch": args.batch,
                    "ns_per_step": ns,
                    "vs_rk4": ns / (base * 1e9),
                    "newton_updates_per_step": None if np.isnan(u) else u,
                }
            )
            note = "" if np.isnan(u) else f", {u:.2f} Newton updates/step"
            print(
                f"{label:17s} {name:24s} {ns:9.1f} ns/trajectory-step "
                f"{ns / (base * 1e9):7.1f}x RK4{note}",
                flush=True,
            )
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; load average {load}")
    if args.json is not None:
        meta = {"h": H, "batch": args.batch, "rounds": args.rounds, "load_average": load}
        atomic_write_bytes(args.json, json.dumps({**meta, "rows": rows}, indent=1).encode())


if __name__ == "__main__":
    main()

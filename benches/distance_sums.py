"""RK4 on an H that is a sum over distances, its gradient compiled (the core's distance terms)
against its field program interpreted, in one process.

The three point vortices (``scenes/point_vortices.toml``), one vortex pair (one term) and a
quadratic H (six squares, interpreted: what the rest of the step costs) on the same bracket;
batch 4096 within 0.2 of the scene's first state, h = 0.05, 200 steps, contenders alternated,
medians of ``--rounds``. Run it on one pinned thread::

    PYTHONPATH=python RAYON_NUM_THREADS=1 taskset -c 0 python benches/distance_sums.py \\
        --json docs/distance_sums.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

os.environ.setdefault("RAYON_NUM_THREADS", "1")

import poisson_rs as pr
from poisson_rs import _core
from poisson_rs.scenes import load_scene

SCENE = Path(__file__).resolve().parent.parent / "scenes" / "point_vortices.toml"
BATCH, STEPS, H = 4096, 200, 0.05


def runner(system: pr.ExpressionSystem, compiled: bool, x0: np.ndarray) -> Callable[[], object]:
    """RK4 through the core with the distance terms (compiled) or without (the program)."""
    tables = (*system.tape, *system.terms.tables())
    distances = None
    if compiled:
        assert system.distances is not None, "H is not a sum over distances"
        distances = system.distances.table()

    def run() -> object:
        return _core.rollout_hamiltonian_field(
            "rk4", *tables, x0, H, STEPS, STEPS, program=system.field_program, distances=distances
        )

    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5, help="timed rounds per contender")
    parser.add_argument("--json", type=Path, help="write the numbers here")
    args = parser.parse_args()
    vortices = load_scene(SCENE).system
    pair = pr.with_hamiltonian(vortices.base, "-log((x1 - x3)**2 + (x2 - x4)**2)")
    quadratic = pr.with_hamiltonian(vortices.base, " + ".join(f"x{i}**2" for i in range(1, 7)))
    rng = np.random.default_rng(0)
    first = np.array([1.0, 0.0, -0.5, 0.6, -0.3, -0.8])
    x0 = first + rng.uniform(-0.2, 0.2, (BATCH, 6))
    contenders = {
        "three vortices, compiled": runner(vortices, True, x0),
        "three vortices, interpreted": runner(vortices, False, x0),
        "one pair, compiled": runner(pair, True, x0),
        "one pair, interpreted": runner(pair, False, x0),
        "quadratic H, interpreted": runner(quadratic, False, x0),
    }
    samples: dict[str, list[float]] = {k: [] for k in contenders}
    for run in contenders.values():
        run()  # warm-up
    for _ in range(max(3, args.rounds)):
        for name, run in contenders.items():
            start = time.perf_counter()
            run()
            samples[name].append(time.perf_counter() - start)
    ns = {k: statistics.median(v) / (BATCH * STEPS) * 1e9 for k, v in samples.items()}
    for name, value in ns.items():
        print(f"{name:30s} {value:6.1f} ns / step")
    if args.json:
        args.json.write_text(
            json.dumps(
                {
                    "batch": BATCH,
                    "steps": STEPS,
                    "h": H,
                    "ns_per_step": ns,
                    "load_average": os.getloadavg(),
                },
                indent=2,
            )
            + "\n"
        )


if __name__ == "__main__":
    main()

"""Ensemble throughput: the default model on 10⁶ trajectories × 100 steps, in process (rayon over
every core) and on a Dask LocalCluster of single-threaded worker processes.

    python benches/ensemble_throughput.py [--quick] [--workers 2] [--json out.json]

Reports trajectory steps per second for each and the overhead ratio (Dask wall time over
in-process wall time, same states, bit-identical results). Only the final states are kept
(``every = n_steps``), so the output stays 2 records per trajectory and the time is the
stepping's plus Dask's: graph, scheduling, shipping the states and results. Cluster start-up is
timed apart. ``--quick``: 10⁵ trajectories.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

import poisson_rs as pr
from poisson_rs.files import atomic_write_bytes, check_output_path


def states(n: int, seed: int = 0) -> np.ndarray:
    """n seeded states with |μ| uniform in [1.5, 3.5], inside the default model's shell: (n, 3)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * rng.uniform(1.5, 3.5, size=(n, 1))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="10^5 trajectories instead of 10^6")
    p.add_argument("--n", type=int, default=None, help="trajectories (overrides --quick)")
    p.add_argument("--steps", type=int, default=100, help="steps per trajectory (default 100)")
    p.add_argument("--h", type=float, default=0.1, help="step size (default 0.1)")
    p.add_argument("--workers", type=int, default=2, help="Dask worker processes (default 2)")
    p.add_argument("--chunks", type=int, default=16, help="chunks of the states (default 16)")
    p.add_argument("--json", type=Path, default=None, help="write the results here")
    args = p.parse_args(argv)
    if args.json is not None:
        check_output_path(args.json)  # before minutes of rollouts

    import dask.array as da
    from distributed import Client, LocalCluster

    n = args.n if args.n is not None else (100_000 if args.quick else 1_000_000)
    model = pr.load_model()
    mu0 = states(n)
    steps_total = n * args.steps

    pr.integrate(model, mu0[:64], args.h, 1)  # starts rayon's pool
    t0 = time.perf_counter()
    local = pr.integrate(model, mu0, args.h, args.steps, every=args.steps)
    t_local = time.perf_counter() - t0
    print(f"in process (rayon, {os.cpu_count()} cores): {t_local:.2f} s, "
          f"{steps_total / t_local:.3g} steps/s", flush=True)  # fmt: skip

    t0 = time.perf_counter()
    with (
        LocalCluster(
            n_workers=args.workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            env={"RAYON_NUM_THREADS": "1"},  # one core per worker
        ) as cluster,
        Client(cluster),  # the default client: compute() runs on the cluster
    ):
        t_start = time.perf_counter() - t0
        # Warm-up: every worker imports poisson_rs and loads the model once.
        warm = pr.integrate(model, da.from_array(mu0[:256], chunks=16), args.h, 1)
        warm.compute()
        chunk = -(-n // args.chunks)
        lazy = pr.integrate(model, da.from_array(mu0, chunks=(chunk, 3)), args.h, args.steps,
                            every=args.steps)  # fmt: skip
        t0 = time.perf_counter()
        spread = lazy.compute()
        t_dask = time.perf_counter() - t0
    same = spread.tobytes() == local.tobytes()
    ratio = t_dask / t_local
    print(f"Dask, {args.workers} workers x 1 thread: {t_dask:.2f} s, "
          f"{steps_total / t_dask:.3g} steps/s (cluster start {t_start:.1f} s)")  # fmt: skip
    print(f"overhead ratio (Dask / in process): {ratio:.2f}; bit-identical: {same}")
    result = {
        "n_trajectories": n,
        "n_steps": args.steps,
        "h": args.h,
        "model": model.name,
        "cores": os.cpu_count(),
        "workers": args.workers,
        "chunks": args.chunks,
        "in_process_seconds": t_local,
        "in_process_steps_per_s": steps_total / t_local,
        "dask_seconds": t_dask,
        "dask_steps_per_s": steps_total / t_dask,
        "cluster_start_seconds": t_start,
        "overhead_ratio": ratio,
        "bit_identical": same,
        "python": platform.python_version(),
        "command": "python benches/ensemble_throughput.py " + " ".join(sys.argv[1:]),
    }
    if args.json is not None:
        atomic_write_bytes(args.json, (json.dumps(result, indent=2) + "\n").encode())
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())

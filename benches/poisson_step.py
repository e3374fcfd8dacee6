"""The cost of one bisection (Poisson) step against one JAX RK4 step, in one process, one thread:
``taskset -c 0 python benches/poisson_step.py``.

Rows (rigid body, I = (1.5, 2, 2.5), h = 0.1, batches 1, 64 and 4096):

- Taylor-exp K=5: ``taylor_integrator(order=5, chart="exp")`` (13 polynomial terms of S in the
  exponential chart);
- the shipped ``default`` learned model (Cayley chart, −tH plus a 4-8-8-1 tanh MLP with
  homogeneous inputs);
- the reference: JAX ``jit(vmap(lax.scan))`` RK4 (float64), the same 20 lines as
  ``benches/peers.py``.

Each contender rolls the batch out for a fixed number of steps and keeps only the final state;
the cell is the median of ``--rounds`` (≥ 5) timed rollouts after a warm-up, rounds alternating
the contenders, and is reported as seconds per trajectory-step and as a ratio to the JAX RK4
step of the same run. With ``--baseline LABEL=PATH`` (repeatable) the ``_core`` extension of an
earlier build is loaded beside this one and timed on the same rows (what each change bought).
JAX installs with ``pip install 'poisson_rs[bench]'``; without it the ratios are skipped with a
message.
``--json FILE`` writes the numbers. The Newton iterations per step (from the rollout's
diagnostics) are printed too.
"""

from __future__ import annotations

import argparse
import importlib.machinery
import importlib.util
import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

os.environ.setdefault("RAYON_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault(
    "XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
)

import numpy as np

import poisson_rs as pr
from poisson_rs.files import atomic_write_bytes, check_output_path

H = 0.1
RIGID_I = (1.5, 2.0, 2.5)
BATCHES = (1, 64, 4096)
#: Trajectory-steps per timed rollout of a bisection stepper (JAX takes 20× more: it is faster).
WORK = 131_072

Runner = Callable[[np.ndarray, int], np.ndarray]


def states(batch: int) -> np.ndarray:
    """Seeded states on spheres of radius 1 to 3 (inside the default model's shell 1 ≤ |μ| ≤ 4,
    and within the cube [−3, 3]³ of peers.py)."""
    rng = np.random.default_rng(42)
    d = rng.normal(size=(batch, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(1.0, 3.0, (batch, 1))


def jax_runner() -> Runner | None:
    try:
        import jax
        import jax.numpy as jnp
    except ImportError:
        print(
            "jax is not installed: ratios skipped (pip install 'poisson_rs[bench]')",
            file=sys.stderr,
        )
        return None
    jax.config.update("jax_enable_x64", True)
    inv = jnp.array([1.0 / v for v in RIGID_I])

    def field(mu: Any) -> Any:
        return jnp.cross(mu, mu * inv)

    def step(mu: Any, _: Any) -> tuple[Any, None]:
        k1 = field(mu)
        k2 = field(mu + 0.5 * H * k1)
        k3 = field(mu + 0.5 * H * k2)
        k4 = field(mu + H * k3)
        return mu + H / 6.0 * (k1 + 2.0 * (k2 + k3) + k4), None

    compiled: dict[int, Any] = {}

    def run(mu0: np.ndarray, n: int) -> np.ndarray:
        if n not in compiled:
            one = lambda mu: jax.lax.scan(step, mu, None, length=n)[0]  # noqa: E731
            compiled[n] = jax.jit(jax.vmap(one))
        return np.asarray(compiled[n](mu0).block_until_ready())

    return run


def load_core(path: Path) -> ModuleType:
    """An earlier build's ``_core`` extension, loaded beside this one."""
    loader = importlib.machinery.ExtensionFileLoader("baseline_core._core", str(path))
    spec = importlib.util.spec_from_file_location("baseline_core._core", path, loader=loader)
    if spec is None:
        raise SystemExit(f"cannot load {path}")
    module = importlib.util.module_from_spec(spec)
    loader.exec_module(module)
    return module


def bisection_runner(
    stepper: pr.BisectionIntegrator, core: ModuleType | None = None
) -> tuple[Runner, Callable[[np.ndarray, int], float]]:
    """A rollout keeping the final state only, through this build's core or ``core``; and a
    function giving the mean Newton updates per step."""
    model = stepper._core if core is None else core.Model.from_bytes(stepper._bytes)
    rollout = pr._core.rollout_model if core is None else core.rollout_model
    simplified = stepper.newton == "simplified"

    def run(mu0: np.ndarray, n: int) -> np.ndarray:
        traj, _ = rollout(model, mu0, H, n, n, stepper.tol, stepper.max_iter, simplified)
        return np.asarray(traj[:, -1])

    def iterations(mu0: np.ndarray, n: int) -> float:
        _, info = rollout(model, mu0, H, n, n, stepper.tol, stepper.max_iter, simplified)
        if not np.asarray(info["converged"]).all():
            raise SystemExit(f"{stepper.name}: a step failed in the bench rollout")
        return float(np.asarray(info["newton_iterations"]).sum()) / (len(mu0) * n)

    return run, iterations


def timed(run: Runner, mu0: np.ndarray, n: int) -> float:
    start = time.perf_counter()
    run(mu0, n)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=7, help="timed rounds per cell (>= 5)")
    parser.add_argument(
        "--baseline",
        action="append",
        default=[],
        metavar="LABEL=PATH",
        help="an earlier build's _core extension, timed beside this one (repeatable)",
    )
    parser.add_argument("--json", type=Path, help="write the numbers here")
    parser.add_argument(
        "--only",
        choices=("taylor5-exp", "default"),
        help="time this bisection stepper only (with JAX and the baselines)",
    )
    args = parser.parse_args()
    if args.json:  # before minutes of work, not after
        check_output_path(args.json)
    rounds = max(5, args.rounds)
    baselines: dict[str, ModuleType] = {}
    for spec in args.baseline:
        label, sep, path = spec.partition("=")
        if not sep or not label or not path:
            raise SystemExit(f"--baseline wants LABEL=PATH, got {spec!r}")
        baselines[label] = load_core(Path(path))
    steppers = {
        "taylor5-exp": pr.taylor_integrator(order=5, chart="exp"),
        "default": pr.load_model("default"),
    }
    if args.only:
        steppers = {args.only: steppers[args.only]}
    jax_run = jax_runner()
    rows: list[dict[str, Any]] = []
    for batch in BATCHES:
        mu0 = states(batch)
        n = max(1, WORK // batch)
        runners: dict[str, tuple[Runner, int]] = {}
        per_step: dict[str, float] = {}
        for name, stepper in steppers.items():
            run, iterations = bisection_runner(stepper)
            runners[name] = (run, n)
            per_step[name] = iterations(mu0, n)
            for label, core in baselines.items():
                base_run, base_iterations = bisection_runner(stepper, core)
                runners[f"{name} ({label})"] = (base_run, n)
                per_step[f"{name} ({label})"] = base_iterations(mu0, n)
                diff = float(np.abs(base_run(mu0, n) - run(mu0, n)).max())
                print(f"{name} batch {batch}: max |this - {label}| after {n} steps {diff:.1e}")
        if jax_run is not None:
            runners["jax rk4"] = (jax_run, 20 * n)
        for run, steps in runners.values():  # warm-up (JAX compiles here)
            run(mu0, steps)
        samples: dict[str, list[float]] = {k: [] for k in runners}
        for _ in range(rounds):
            for name, (run, steps) in runners.items():
                samples[name].append(timed(run, mu0, steps) / (batch * steps))
        cost = {k: statistics.median(v) for k, v in samples.items()}
        ref = cost.get("jax rk4")
        ratio = {k: v / ref for k, v in cost.items()} if ref else {}
        for name, seconds in cost.items():
            r = f"{ratio[name]:7.1f}x JAX RK4" if ratio else "(no JAX)"
            it = f", {per_step[name]:.2f} Newton updates/step" if name in per_step else ""
            print(f"batch {batch:5d} {name:34s} {seconds * 1e9:9.1f} ns/trajectory-step {r}{it}")
        rows.append(
            {
                "batch": batch,
                "steps": n,
                "seconds_per_trajectory_step": cost,
                "ratio_to_jax_rk4": ratio,
                "newton_updates_per_step": per_step,
            }
        )
    load = os.getloadavg()
    machine = f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores"
    print(f"machine: {machine}; load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    if args.json:
        data = {"rows": rows, "load": load, "machine": machine}
        atomic_write_bytes(args.json, json.dumps(data, indent=1).encode())


if __name__ == "__main__":
    main()

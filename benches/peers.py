"""RK4 rollouts of poisson_rs against the 20 lines a user would write in JAX and numba, in one
process, one thread: ``taskset -c 0 python benches/peers.py``.

Workloads (h = 0.1, final state only, so no contender pays for storing a trajectory):

- the rigid body, I = (1.5, 2, 2.5), batches 1, 64 and 4096;
- the heavy top, I = (1, 1.5, 2), mgl = 0.981, χ = e₃, batches 64 and 4096;
- PNN's Lotka–Volterra system (u̇ = u(v − 2), v̇ = v(1 − u), a log-canonical bracket), batches 64
  and 4096;
- ``integrate()`` of one state for one step: the cost of one call, in µs.

Contenders: poisson_rs (``pr.integrate`` with ``every=n_steps``), JAX ``jit(vmap(lax.scan))``
RK4 (float64) and numba ``@njit`` RK4 (a loop over trajectories and steps), and, with
``--baseline PATH``, the ``_core`` extension of an earlier build loaded beside this one (e.g. the
main checkout's, to say what a change bought). Rounds alternate the contenders; each cell is the
median of ``--rounds`` (≥ 5) timed runs after a warm-up (JAX compiles there). A missing peer is
skipped with a message. Every contender's final states are checked against poisson_rs's: numba
gives the same bits, JAX agrees to 1e-10 or better (the same RK4, summed in a different order),
except on the heavy top's 10⁴ steps, where chaotic orbits amplify that order to O(1).

Peers install with ``pip install 'poisson_rs[bench]'``. Pin one thread: the script sets
``RAYON_NUM_THREADS=1``, XLA's and numba's thread counts to 1 before importing them; run it
under ``taskset -c 0`` as well. ``--json FILE`` writes the numbers.
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
os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault(
    "XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
)

import numpy as np

import poisson_rs as pr
from poisson_rs.files import atomic_write_bytes, check_output_path

H = 0.1
RIGID_I = (1.5, 2.0, 2.5)
TOP_I = (1.0, 1.5, 2.0)
MGL = 0.981
COM = (0.0, 0.0, 1.0)
#: PNN's Lotka–Volterra: ẋ_i = x_i Σ_j c_ij (x_j − b_j).
LV_C = ((0.0, 1.0), (-1.0, 0.0))
LV_B = (1.0, 2.0)

#: (system, batch, steps): about 1e6 trajectory-steps each (RK4 at 1e7–1e8 steps/s).
WORKLOADS = [
    ("rigid body", 1, 200_000),
    ("rigid body", 64, 10_000),
    ("rigid body", 4096, 200),
    ("heavy top", 64, 10_000),
    ("heavy top", 4096, 200),
    ("lotka-volterra", 64, 10_000),
    ("lotka-volterra", 4096, 200),
]

Runner = Callable[[np.ndarray, int], np.ndarray]


def states(system: str, batch: int) -> np.ndarray:
    """Seeded initial states: |μ| ≤ 3 for the rigid body; M in [−1, 1]³ and |Γ| = 1 for the
    top; within a log distance of 0.5 of the equilibrium (1, 2) for Lotka–Volterra."""
    rng = np.random.default_rng(42)
    if system == "rigid body":
        return rng.uniform(-3.0, 3.0, (batch, 3))
    if system == "lotka-volterra":
        return np.exp(rng.uniform(-0.5, 0.5, (batch, 2))) * np.array(LV_B)
    m = rng.uniform(-1.0, 1.0, (batch, 3))
    g = rng.normal(size=(batch, 3))
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    return np.concatenate([m, g], axis=1)


def poisson_rs_runner(system: str, core: ModuleType | None = None) -> Runner:
    """RK4 through ``pr.integrate`` (``core``: call that extension's rollout directly, for a
    baseline build)."""
    if system == "lotka-volterra":
        lv = pr.lotka_volterra(LV_C, LV_B)
        if core is None:
            rk4 = pr.log_canonical_classical(lv, "rk4")
            return lambda x0, n: pr.integrate(rk4, x0, H, n, every=n)[:, -1]
        powers, coeffs, b = lv.log_hamiltonian.to_arrays()
        c = np.ascontiguousarray(LV_C)
        return lambda x0, n: core.rollout_log_classical("rk4", c, powers, coeffs, b, x0, H, n, n)[
            0
        ][:, -1]
    body: pr.LiePoissonSystem = (
        pr.RigidBody(RIGID_I) if system == "rigid body" else pr.HeavyTop(TOP_I, MGL, COM)
    )
    stepper = pr.classical(body, "rk4")
    if core is None:
        return lambda mu0, n: pr.integrate(stepper, mu0, H, n, every=n)[:, -1]
    if system == "rigid body":
        return lambda mu0, n: core.rollout_classical("rk4", RIGID_I, mu0, H, n, n)[0][:, -1]
    powers, coeffs = body.polynomial.to_arrays()
    c = np.ascontiguousarray(body.algebra.c)
    return lambda mu0, n: core.rollout_lie_poisson("rk4", c, powers, coeffs, mu0, H, n, n)[0][:, -1]


def jax_runner(system: str) -> Runner | None:
    try:
        import jax
        import jax.numpy as jnp
    except ImportError:
        print("jax is not installed: skipped (pip install 'poisson_rs[bench]')", file=sys.stderr)
        return None
    jax.config.update("jax_enable_x64", True)
    inv = jnp.array([1.0 / v for v in (RIGID_I if system == "rigid body" else TOP_I)])
    arm = MGL * jnp.array(COM)

    lv_c, lv_b = jnp.array(LV_C), jnp.array(LV_B)

    def field(mu: Any) -> Any:
        if system == "lotka-volterra":
            return mu * (lv_c @ (mu - lv_b))
        if system == "rigid body":
            return jnp.cross(mu, mu * inv)
        m, g = mu[:3], mu[3:]
        w = m * inv
        return jnp.concatenate([jnp.cross(m, w) + jnp.cross(g, arm), jnp.cross(g, w)])

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


def numba_runner(system: str) -> Runner | None:
    try:
        import numba
    except ImportError:
        print("numba is not installed: skipped (pip install 'poisson_rs[bench]')", file=sys.stderr)
        return None
    inv = np.array([1.0 / v for v in (RIGID_I if system == "rigid body" else TOP_I)])
    arm = MGL * np.array(COM)
    dim = {"rigid body": 3, "heavy top": 6, "lotka-volterra": 2}[system]
    lv = dim == 2
    c01, c10, b0, b1 = LV_C[0][1], LV_C[1][0], LV_B[0], LV_B[1]

    @numba.njit(cache=False, fastmath=False)
    def field(mu: np.ndarray, out: np.ndarray) -> None:
        if lv:
            out[0] = mu[0] * (c01 * (mu[1] - b1))
            out[1] = mu[1] * (c10 * (mu[0] - b0))
            return
        w0, w1, w2 = mu[0] * inv[0], mu[1] * inv[1], mu[2] * inv[2]
        out[0] = mu[1] * w2 - mu[2] * w1
        out[1] = mu[2] * w0 - mu[0] * w2
        out[2] = mu[0] * w1 - mu[1] * w0
        if dim == 6:
            g0, g1, g2 = mu[3], mu[4], mu[5]
            out[0] += g1 * arm[2] - g2 * arm[1]
            out[1] += g2 * arm[0] - g0 * arm[2]
            out[2] += g0 * arm[1] - g1 * arm[0]
            out[3] = g1 * w2 - g2 * w1
            out[4] = g2 * w0 - g0 * w2
            out[5] = g0 * w1 - g1 * w0

    @numba.njit(cache=False, fastmath=False)
    def run(mu0: np.ndarray, n: int) -> np.ndarray:
        out = mu0.copy()
        k1, k2, k3, k4, y = (
            np.empty(dim),
            np.empty(dim),
            np.empty(dim),
            np.empty(dim),
            np.empty(dim),
        )
        for b in range(out.shape[0]):
            mu = out[b]
            for _ in range(n):
                field(mu, k1)
                for i in range(dim):
                    y[i] = mu[i] + 0.5 * H * k1[i]
                field(y, k2)
                for i in range(dim):
                    y[i] = mu[i] + 0.5 * H * k2[i]
                field(y, k3)
                for i in range(dim):
                    y[i] = mu[i] + H * k3[i]
                field(y, k4)
                for i in range(dim):
                    mu[i] += H / 6.0 * (k1[i] + 2.0 * (k2[i] + k3[i]) + k4[i])
        return out

    return run  # type: ignore[no-any-return]


def load_core(path: Path) -> ModuleType:
    """An earlier build's ``_core`` extension, loaded beside this one."""
    loader = importlib.machinery.ExtensionFileLoader("baseline_core._core", str(path))
    spec = importlib.util.spec_from_file_location("baseline_core._core", path, loader=loader)
    if spec is None:
        raise SystemExit(f"cannot load {path}")
    module = importlib.util.module_from_spec(spec)
    loader.exec_module(module)
    return module


def timed(run: Runner, mu0: np.ndarray, n: int) -> tuple[float, np.ndarray]:
    start = time.perf_counter()
    out = run(mu0, n)
    return time.perf_counter() - start, out


def call_cost(fn: Callable[[], Any], rounds: int) -> float:
    """Median seconds of one call, over ``rounds`` batches of calls of about 50 ms."""
    fn()
    calls = 1
    while True:
        start = time.perf_counter()
        for _ in range(calls):
            fn()
        if time.perf_counter() - start > 0.05:
            break
        calls *= 2
    samples = []
    for _ in range(rounds):
        start = time.perf_counter()
        for _ in range(calls):
            fn()
        samples.append((time.perf_counter() - start) / calls)
    return statistics.median(samples)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=7, help="timed rounds per cell (>= 5)")
    parser.add_argument("--baseline", type=Path, help="an earlier build's _core extension")
    parser.add_argument("--json", type=Path, help="write the numbers here")
    args = parser.parse_args()
    if args.json:  # before minutes of work, not after
        check_output_path(args.json)
    rounds = max(5, args.rounds)
    baseline = load_core(args.baseline) if args.baseline else None
    rows: list[dict[str, Any]] = []
    for system, batch, n in WORKLOADS:
        mu0 = states(system, batch)
        runners: dict[str, Runner | None] = {
            "poisson_rs": poisson_rs_runner(system),
            "jax": jax_runner(system),
            "numba": numba_runner(system),
        }
        if baseline is not None:
            runners["baseline"] = poisson_rs_runner(system, baseline)
        live = {k: r for k, r in runners.items() if r is not None}
        ref = live["poisson_rs"](mu0, n)
        agree = {}
        for name, run in live.items():  # warm-up (JIT compiles) and agreement
            agree[name] = float(np.abs(run(mu0, n) - ref).max())
        samples: dict[str, list[float]] = {k: [] for k in live}
        for _ in range(rounds):
            for name, run in live.items():
                samples[name].append(timed(run, mu0, n)[0])
        rate = {k: batch * n / statistics.median(v) for k, v in samples.items()}
        row = {"system": system, "batch": batch, "steps": n, "rate": rate, "agree": agree}
        rows.append(row)
        print(
            f"{system:14s} batch {batch:5d}: "
            + ", ".join(f"{k} {v:.2e}" for k, v in rate.items())
            + " trajectory-steps/s; max |diff| "
            + ", ".join(f"{k} {v:.1e}" for k, v in agree.items() if k != "poisson_rs"),
            flush=True,
        )
    # One call, one state, one step.
    rk4 = pr.classical(pr.RigidBody(RIGID_I), "rk4")
    one = np.array([1.0, 1.0, 2.0])
    calls: dict[str, float] = {
        "poisson_rs": call_cost(lambda: pr.integrate(rk4, [1.0, 1.0, 2.0], H, 1), rounds)
    }
    jax_run = jax_runner("rigid body")
    if jax_run is not None:
        calls["jax"] = call_cost(lambda: jax_run(one[None], 1), rounds)
    numba_run = numba_runner("rigid body")
    if numba_run is not None:
        calls["numba"] = call_cost(lambda: numba_run(one[None], 1), rounds)
    core = poisson_rs_runner("rigid body", pr._core)
    calls["poisson_rs (_core call only)"] = call_cost(lambda: core(one[None], 1), rounds)
    lazy = pr._core.rollout_classical
    calls["poisson_rs (_core call, lazy diagnostics)"] = call_cost(
        lambda: lazy("rk4", RIGID_I, one[None], H, 1, 1, lazy=True), rounds
    )
    if baseline is not None:
        b = poisson_rs_runner("rigid body", baseline)
        calls["baseline (_core call only)"] = call_cost(lambda: b(one[None], 1), rounds)
    print(
        "one call, one state, one step: "
        + ", ".join(f"{k} {v * 1e6:.2f} us" for k, v in calls.items())
    )
    load = os.getloadavg()
    machine = f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores"
    print(f"machine: {machine}; load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    if args.json:
        data = {"workloads": rows, "call_seconds": calls, "load": load, "machine": machine}
        atomic_write_bytes(args.json, json.dumps(data, indent=1).encode())


if __name__ == "__main__":
    main()

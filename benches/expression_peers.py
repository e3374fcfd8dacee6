"""RK4 on an expression Hamiltonian (PNN's extended pendulum, H = u²/2 − cos v + u(r − u² − v²))
against the JAX ``jit(vmap(lax.scan))`` RK4 a user would write with ``jax.grad`` of the same H,
one process, one thread: ``taskset -c 0 python benches/expression_peers.py``. Batch 4096, h = 0.1,
200 steps, final states only; rounds alternate the contenders; the final states agree to 1e-13.
JAX comes with ``pip install 'poisson_rs[bench]'``."""

from __future__ import annotations

import os
import statistics
import time

os.environ.setdefault("RAYON_NUM_THREADS", "1")
os.environ.setdefault(
    "XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
)

from pathlib import Path
from typing import Any

import numpy as np

import poisson_rs as pr
from poisson_rs.scenes import load_scene

H, STEPS, BATCH = 0.1, 200, 4096


def main() -> None:
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    scene = Path(__file__).resolve().parent.parent / "scenes" / "extended_pendulum_pnn.toml"
    s = load_scene(scene).system
    x0 = np.random.default_rng(0).uniform(-0.5, 0.5, (BATCH, 3))
    rk4 = s.classical("rk4")

    def hamiltonian(x: Any) -> Any:
        u, v, r = x
        return u**2 / 2 - jnp.cos(v) + u * (r - u**2 - v**2)

    def field(x: Any) -> Any:
        u, v, _ = x
        pi = jnp.array([[0.0, -1.0, -2 * v], [1.0, 0.0, 2 * u], [2 * v, -2 * u, 0.0]])
        return pi @ jax.grad(hamiltonian)(x)

    def step(x: Any, _: Any) -> tuple[Any, None]:
        k1 = field(x)
        k2 = field(x + 0.5 * H * k1)
        k3 = field(x + 0.5 * H * k2)
        k4 = field(x + H * k3)
        return x + H / 6 * (k1 + 2 * (k2 + k3) + k4), None

    run = jax.jit(jax.vmap(lambda x: jax.lax.scan(step, x, None, length=STEPS)[0]))
    ours = pr.integrate(rk4, x0, H, STEPS, every=STEPS)[:, -1]
    theirs = np.asarray(run(x0))
    print(f"final states agree to {np.abs(ours - theirs).max():.1e}")
    t_pr, t_jax = [], []
    for _ in range(7):
        t = time.perf_counter()
        pr.integrate(rk4, x0, H, STEPS, every=STEPS)
        t_pr.append(time.perf_counter() - t)
        t = time.perf_counter()
        run(x0).block_until_ready()
        t_jax.append(time.perf_counter() - t)
    a, b = statistics.median(t_pr), statistics.median(t_jax)
    work = BATCH * STEPS
    print(f"poisson_rs {work / a:.3g} steps/s, JAX {work / b:.3g} steps/s, ratio {b / a:.2f}x")


if __name__ == "__main__":
    main()

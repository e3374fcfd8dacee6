"""Rollout throughput: the Rust core against the same model's pure-torch step map.

For each model and batch size it prints steps/s of the Rust rollout and of ``torch_step`` (eager
autograd Newton, float64), their ratio, the Rust kernel's achieved GFLOP/s (each MLP weight costs
20 flops per value/gradient/Hessian pass, one per Newton update, and 8 in the final
value/gradient pass), NumPy's
float64 matrix-multiply rate measured in the same run as the ceiling, and the 1 → 2 thread
speed-up. Ratios within one run are what count; absolute numbers are noisy on a shared machine.

Usage: ``python benches/bench_step.py [--models default paper] [--json FILE]``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import subprocess
import sys
import time
import warnings
from collections.abc import Callable

import numpy as np
import torch

import poisson_rs as pr

BATCHES = (1, 64, 4096)


def best_of(fn: Callable[..., object], *args: object, repeats: int = 3) -> float:
    """Smallest wall-clock time of ``repeats`` calls ``fn(*args)`` (seconds)."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn(*args)
        times.append(time.perf_counter() - t0)
    return min(times)


def torch_rollout(model: pr.LearnedIntegrator, mu: torch.Tensor, n_steps: int) -> torch.Tensor:
    for _ in range(n_steps):
        mu = model.torch_step(mu, 0.1)
    return mu


def gemm_gflops(n: int = 1024) -> float:
    """NumPy float64 matrix-multiply rate (GFLOP/s), best of 5."""
    a, b = np.random.default_rng(0).random((2, n, n))
    return 2 * n**3 / best_of(np.matmul, a, b, repeats=5) / 1e9


def states(batch: int, seed: int = 0) -> np.ndarray:
    """``batch`` states on spheres of radius 1 to 4 (inside the default model's shell)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(batch, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(1, 4, (batch, 1))


def weights(model: pr.LearnedIntegrator) -> int:
    """MLP weights (biases excluded): the flop count of a pass is 20 per weight."""
    widths = [4, *model.metadata["widths"], 1]
    return sum(a * b for a, b in itertools.pairwise(widths))


def rust_rate(model: pr.LearnedIntegrator, batch: int, budget: float) -> tuple[float, float]:
    """(steps/s, GFLOP/s) of the Rust rollout at ``batch`` over about ``budget`` seconds."""
    mu = states(batch)
    n = 1
    while True:  # grow the step count until one call lasts long enough to time
        t = best_of(pr.integrate, model, mu, 0.1, n, repeats=1)
        if t > budget / 4 or n > 1_000_000:
            break
        n *= 4
    t0 = time.perf_counter()
    _, info = pr.integrate(model, mu, 0.1, n, return_info=True)
    t = min(time.perf_counter() - t0, best_of(pr.integrate, model, mu, 0.1, n, repeats=2))
    # Each Newton update costs a value/gradient/Hessian pass (20 flops per weight), the final
    # evaluation a value/gradient one (8 flops per weight).
    flops = (20 * float(info.newton_iterations.sum()) + 8 * batch * n) * weights(model)
    return batch * n / t, flops / t / 1e9


def thread_speedup(model_name: str) -> float:
    """Steps/s with RAYON_NUM_THREADS=2 over =1, batch 64, each in a fresh process."""
    code = (
        "import sys, time, numpy as np, poisson_rs as pr;"
        "m = pr.load_model(sys.argv[1]); rng = np.random.default_rng(0);"
        "mu = rng.normal(size=(64, 3)) * 1.5; pr.integrate(m, mu, 0.1, 2);"
        "t = min((lambda t0: (pr.integrate(m, mu, 0.1, N), time.perf_counter() - t0)[1])"
        "(time.perf_counter()) for _ in range(3)); print(t)"
    )
    n = "400" if model_name == "default" else "3"
    rates = []
    for threads in ("1", "2"):
        env = dict(os.environ, RAYON_NUM_THREADS=threads)
        out = subprocess.run(
            [sys.executable, "-c", code.replace("N", n), model_name],
            env=env,
            capture_output=True,
            text=True,
            check=True,
        )
        rates.append(1.0 / float(out.stdout.strip().splitlines()[-1]))
    return rates[1] / rates[0]


def main() -> None:
    # Random states leave the paper model's training cube; that is not what is measured here.
    warnings.simplefilter("ignore", RuntimeWarning)
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--models", nargs="+", default=["default", "paper"])
    ap.add_argument("--budget", type=float, default=1.0, help="seconds per Rust measurement")
    ap.add_argument("--json", default=None, help="also write the rows as JSON")
    args = ap.parse_args()
    ceiling = gemm_gflops()
    print(f"NumPy float64 GEMM: {ceiling:.1f} GFLOP/s; torch threads {torch.get_num_threads()}")
    rows = []
    for name in args.models:
        model = pr.load_model(name)
        speedup = thread_speedup(name)
        print(f"\n{model!r}: 1 -> 2 threads {speedup:.2f}x")
        print(
            f"{'batch':>6} {'rust steps/s':>13} {'torch steps/s':>14} {'ratio':>8} "
            f"{'GFLOP/s':>8} {'% GEMM':>7}"
        )
        for batch in BATCHES:
            rust, gflops = rust_rate(model, batch, args.budget)
            n_torch = 2 if batch > 1 or name != "default" else 20
            mu_t = torch.tensor(states(batch))
            t_torch = best_of(torch_rollout, model, mu_t, n_torch, repeats=2) / (batch * n_torch)
            row = {
                "model": name,
                "batch": batch,
                "rust_steps_per_s": rust,
                "torch_steps_per_s": 1 / t_torch,
                "rust_over_torch": rust * t_torch,
                "rust_gflops": gflops,
                "gemm_gflops": ceiling,
                "threads_speedup_1_to_2": speedup,
            }
            rows.append(row)
            print(
                f"{batch:>6} {rust:>13.4g} {1 / t_torch:>14.4g} {rust * t_torch:>7.0f}x "
                f"{gflops:>8.2f} {100 * gflops / ceiling:>6.1f}%"
            )
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()

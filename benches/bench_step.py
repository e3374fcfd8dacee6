"""Rollout throughput: the Rust core against the same model's pure-torch step map.

For each model and batch size it prints steps/s of the Rust rollout (its default, simplified
Newton where the model is solved in batches, and full Newton), of ``torch_step`` (eager autograd
Newton, float64) and their ratio; the Rust kernel's achieved GFLOP/s under full Newton, where the
flops are known exactly (each MLP weight costs 20 flops per value/gradient/Hessian pass, one per
Newton update, and in the final value/gradient pass 8 one trajectory at a time or 4 in reverse
mode when batched); NumPy's float64 matrix-multiply rate measured in the same run as the ceiling;
and the 1 → 2 thread speed-up. torch.compile of the step map is tried once per model and its
failure, if any, reported. Ratios within one run are what count; absolute numbers are noisy on
a shared machine.

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
from poisson_rs.files import atomic_write_bytes, check_output_path

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


def torch_rollout_with(
    step: Callable[[torch.Tensor], torch.Tensor], mu: torch.Tensor, n_steps: int
) -> torch.Tensor:
    for _ in range(n_steps):
        mu = step(mu)
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
    """MLP weights (biases excluded): a value/gradient/Hessian pass costs 20 flops per weight."""
    widths = [4, *model.metadata["widths"], 1]
    return sum(a * b for a, b in itertools.pairwise(widths))


def rust_rate(model: pr.LearnedIntegrator, batch: int, budget: float) -> tuple[float, float]:
    """(steps/s, GFLOP/s) of the Rust rollout at ``batch`` over about ``budget`` seconds; the
    flop rate is exact under full Newton only (simplified Newton mixes pass kinds)."""
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
    final = 4 if model.batch > 1 else 8  # reverse-mode gradient when batched, else forward
    flops = (20 * float(info.newton_iterations.sum()) + final * batch * n) * weights(model)
    return batch * n / t, flops / t / 1e9


def try_compile(model: pr.LearnedIntegrator) -> Callable[[torch.Tensor], torch.Tensor] | str:
    """``torch.compile`` of the step map, checked on one batch; or why it does not work here."""
    from poisson_rs.generating import bisection_step

    s_fn = model.generating

    def step(mu: torch.Tensor) -> torch.Tensor:
        return bisection_step(s_fn, mu, 0.1, chart=model.chart, tol=model.tol)

    compiled = torch.compile(step)
    mu = torch.tensor(states(8))
    try:
        out = compiled(mu)
    except Exception as e:  # any failure is the finding
        return f"{type(e).__name__}: {str(e).splitlines()[0][:100]}"
    if not torch.allclose(out, model.torch_step(mu, 0.1), rtol=0, atol=1e-12):
        return "compiled step map disagrees with eager"
    return compiled


def thread_speedup(model_name: str) -> float:
    """Steps/s with RAYON_NUM_THREADS=2 over =1 on 256 states, each in fresh processes run
    alternately twice, best of five calls each: the shared machine only ever adds time."""
    code = (
        "import sys, time, numpy as np, poisson_rs as pr;"
        "m = pr.load_model(sys.argv[1]); rng = np.random.default_rng(0);"
        "mu = rng.normal(size=(256, 3)) * 1.5; pr.integrate(m, mu, 0.1, 1);"
        "t = min((lambda t0: (pr.integrate(m, mu, 0.1, N), time.perf_counter() - t0)[1])"
        "(time.perf_counter()) for _ in range(5)); print(t)"
    )
    n = "400" if model_name == "default" else "4"
    best = {"1": float("inf"), "2": float("inf")}
    for threads in ("1", "2", "1", "2"):
        env = dict(os.environ, RAYON_NUM_THREADS=threads)
        out = subprocess.run(
            [sys.executable, "-c", code.replace("N", n), model_name],
            env=env,
            capture_output=True,
            text=True,
            check=True,
        )
        best[threads] = min(best[threads], float(out.stdout.strip().splitlines()[-1]))
    return best["1"] / best["2"]


def main() -> None:
    # Random states leave the paper model's training cube; that is not what is measured here.
    warnings.simplefilter("ignore", RuntimeWarning)
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--models", nargs="+", default=["default", "paper"])
    ap.add_argument("--budget", type=float, default=1.0, help="seconds per Rust measurement")
    ap.add_argument("--json", default=None, help="also write the rows as JSON")
    args = ap.parse_args()
    if args.json:  # before the work, not after
        check_output_path(args.json)
    ceiling = gemm_gflops()
    print(f"NumPy float64 GEMM: {ceiling:.1f} GFLOP/s; torch threads {torch.get_num_threads()}")
    rows = []
    for name in args.models:
        model = pr.load_model(name)
        full = pr.load_model(name, newton="full")
        speedup = thread_speedup(name)
        compiled = try_compile(model)
        print(f"\n{model!r}, batched {model.batch}: 1 -> 2 threads {speedup:.2f}x")
        if isinstance(compiled, str):
            print(f"torch.compile of the step map: fails here ({compiled})")
        print(
            f"{'batch':>6} {'rust steps/s':>13} {'full Newton':>12} {'torch steps/s':>14} "
            f"{'compiled':>9} {'ratio':>8} {'GFLOP/s':>8} {'% GEMM':>7}"
        )
        for batch in BATCHES:
            rust, _ = rust_rate(model, batch, args.budget)
            rust_full, gflops = rust_rate(full, batch, args.budget)
            n_torch = 2 if batch > 1 or name != "default" else 20
            mu_t = torch.tensor(states(batch))
            t_torch = best_of(torch_rollout, model, mu_t, n_torch, repeats=2) / (batch * n_torch)
            t_compiled = float("nan")
            if not isinstance(compiled, str):
                t_compiled = best_of(torch_rollout_with, compiled, mu_t, n_torch, repeats=2) / (
                    batch * n_torch
                )
            best_torch = min(t_torch, t_compiled) if t_compiled == t_compiled else t_torch
            row = {
                "model": name,
                "batch": batch,
                "rust_steps_per_s": rust,
                "rust_full_newton_steps_per_s": rust_full,
                "torch_steps_per_s": 1 / t_torch,
                "torch_compiled_steps_per_s": 1 / t_compiled,
                "torch_compile": "ok" if not isinstance(compiled, str) else compiled,
                "rust_over_torch": rust * best_torch,
                "rust_full_newton_gflops": gflops,
                "gemm_gflops": ceiling,
                "threads_speedup_1_to_2": speedup,
            }
            rows.append(row)
            print(
                f"{batch:>6} {rust:>13.4g} {rust_full:>12.4g} {1 / t_torch:>14.4g} "
                f"{1 / t_compiled:>9.4g} {rust * best_torch:>7.0f}x "
                f"{gflops:>8.2f} {100 * gflops / ceiling:>6.1f}%"
            )
    if args.json:
        atomic_write_bytes(args.json, json.dumps(rows, indent=1).encode())


if __name__ == "__main__":
    main()

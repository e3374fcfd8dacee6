"""Rollout throughput: the Rust core against the same model's pure-torch step map.

Ratios within one run on one machine are what count; absolute numbers are noisy on a shared
machine. Usage: ``python benches/bench_step.py [--model NAME_OR_PATH] [--json FILE]``.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable

import numpy as np
import torch

import poisson_rs as pr


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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--model", default=None)
    ap.add_argument("--json", default=None, help="also write the table as JSON")
    args = ap.parse_args()
    model = pr.load_model(args.model)
    rng = np.random.default_rng(0)
    rows = []
    print(f"{model!r}, torch threads {torch.get_num_threads()}")
    print(f"{'batch':>6} {'rust steps/s':>14} {'torch steps/s':>14} {'speed-up':>9}")
    for batch in (1, 64, 4096):
        d = rng.normal(size=(batch, 3))
        mu = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(1, 4, (batch, 1))
        n_rust = max(10, 200_000 // batch)
        t_rust = best_of(pr.integrate, model, mu, 0.1, n_rust) / (batch * n_rust)
        n_torch = 3 if batch > 1 else 20
        t_torch = best_of(torch_rollout, model, torch.tensor(mu), n_torch, repeats=2)
        t_torch /= batch * n_torch
        rows.append(
            {
                "batch": batch,
                "rust_steps_per_s": 1 / t_rust,
                "torch_steps_per_s": 1 / t_torch,
                "speedup": t_torch / t_rust,
            }
        )
        print(f"{batch:>6} {1 / t_rust:>14.4g} {1 / t_torch:>14.4g} {t_torch / t_rust:>9.1f}x")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()

"""Seconds per training iteration of a preset, on CPU or CUDA.

Usage: ``python benches/train_speed.py --preset paper --device cuda --iterations 20``.
The first iterations (warm-up, allocator growth) are excluded from the timing.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import torch

from poisson_rs.generating import HJ_DERIVATIVES
from poisson_rs.train import PRESETS, TrainConfig, train


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--preset", default="paper", choices=sorted(PRESETS))
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument(
        "--derivatives", choices=HJ_DERIVATIVES, help="the trainer's ∂S method (preset's default)"
    )
    args = ap.parse_args()
    cfg = TrainConfig(**PRESETS[args.preset])
    cfg = dataclasses.replace(cfg, device=args.device, iterations=args.warmup + args.iterations)
    if args.derivatives:
        cfg = dataclasses.replace(cfg, derivatives=args.derivatives)
    stamps: list[float] = []

    def tick(i: int, loss: float) -> None:
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()
        stamps.append(time.perf_counter())

    train(cfg, progress=False, log_every=1, callback=tick)
    per_it = (stamps[-1] - stamps[args.warmup - 1]) / args.iterations
    name = torch.cuda.get_device_name() if args.device.startswith("cuda") else "cpu"
    row = {
        "preset": args.preset,
        "device": name,
        "threads": torch.get_num_threads(),
        "derivatives": cfg.derivatives,
        "seconds_per_iteration": per_it,
        "iterations_timed": args.iterations,
    }
    print(json.dumps(row))


if __name__ == "__main__":
    main()

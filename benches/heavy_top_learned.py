"""Learned heavy-top models against their own Taylor terms: the table in docs/heavy_top.md.

Each run trains exact Taylor terms K (exp chart) plus t^(K+2) · MLP(t, p) on the HJ residual for
t ∈ [0, h] (seed 0, Adam, the network starting at zero output), then measures the error at
T = 10 and step h on 8 held-out states (M uniform in [−1.2, 1.2]³, Γ a random unit vector; seed
123) against a DOP853 reference, for the model and for the same Taylor terms alone.

    python benches/heavy_top_learned.py --sampling uniform --widths 16 16 --iterations 3000
    python benches/heavy_top_learned.py --sampling orbits --widths 16 16 --iterations 3000
    python benches/heavy_top_learned.py --sampling orbits --widths 32 32 --iterations 6000 --lr 2e-3

"uniform": the cube |μᵢ| ≤ 2 of R⁶; "orbits": 90 % of the points near the orbits of 16 training
states (seed 7, drawn like the held-out ones; noise 5 %), 10 % the cube. ``--out`` keeps the
model file.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch

import poisson_rs as pr
from poisson_rs.files import check_output_path
from poisson_rs.train import TrainConfig, save_result, train

T = 10.0


def states(seed: int, n: int) -> np.ndarray:
    """n heavy-top states (M, Γ): M uniform in [−1.2, 1.2]³, Γ a random unit vector."""
    rng = np.random.default_rng(seed)
    m = rng.uniform(-1.2, 1.2, (n, 3))
    g = rng.normal(size=(n, 3))
    return np.hstack([m, g / np.linalg.norm(g, axis=1, keepdims=True)])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sampling", choices=["uniform", "orbits"], default="orbits")
    ap.add_argument("--widths", type=int, nargs="+", default=[16, 16])
    ap.add_argument("--iterations", type=int, default=3000)
    ap.add_argument("--lr", type=float, default=3e-3)
    ap.add_argument("--taylor-order", dest="order", type=int, default=3)
    ap.add_argument("--h", type=float, default=0.5)
    ap.add_argument("--out", type=Path, default=None, help="keep the model file here")
    args = ap.parse_args(argv)
    if args.out is not None:
        check_output_path(args.out)
    torch.set_num_threads(1)
    top = pr.HeavyTop()
    scene: dict[str, object] = {}
    if args.sampling == "orbits":
        scene = {
            "sampling": "scene",
            "sampling_fraction": 0.9,
            "sampling_states": tuple(map(tuple, states(7, 16).tolist())),
            "sampling_horizon": T,
            "sampling_noise": 0.05,
        }
    cfg = TrainConfig(
        system=top.to_dict(),
        chart="exp",
        inputs="t,p",
        taylor_order=args.order,
        widths=tuple(args.widths),
        domain="cube",
        half_width=2.0,
        h_max=args.h,
        batch=1024,
        iterations=args.iterations,
        lr=args.lr,
        seed=0,
        **scene,
    )
    t0 = time.perf_counter()
    result = train(cfg, progress=False)
    seconds = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        path = args.out or Path(tmp) / "model.safetensors"
        save_result(result, path, name="heavy_top_learned", command=" ".join(sys.argv))
        model = pr.load_model(path)
        mu0 = states(123, 8)
        n = round(T / args.h)
        ref = pr.reference_solution(top, mu0, np.array([0.0, T]))[:, -1]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # held-out states may leave the cube
            learned = np.abs(pr.integrate(model, mu0, args.h, n)[:, -1] - ref).max(axis=1)
            base = pr.taylor_integrator(top, args.order)
            taylor = np.abs(pr.integrate(base, mu0, args.h, n)[:, -1] - ref).max(axis=1)
    row = {
        "sampling": args.sampling,
        "widths": args.widths,
        "iterations": args.iterations,
        "train_seconds": round(seconds, 1),
        "final_loss": result.final_loss,
        "median_error_learned": float(np.median(learned)),
        "median_error_taylor": float(np.median(taylor)),
        "median_ratio_taylor_over_learned": float(np.median(taylor / learned)),
    }
    print(json.dumps(row, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

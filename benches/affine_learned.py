"""Learned S on an affine bracket (PNN's extended pendulum), trained on its central extension,
against the same Taylor terms without the network.

Trains S = Taylor-3 + t^m·MLP (exp chart, inputs (t, p), cube |x| ≤ 2, h_max = 0.1, seed 0) on
the extension's Hamilton–Jacobi residual, then reports the held-out RMS residual of the Taylor
terms alone and of the trained S, the training time, and on the scene's states (500 steps of
h = 0.1, ``pr.affine_learned`` against ``pr.affine_taylor(system, 3)``): the largest error
against DOP853 (rtol = atol = 1e-13), the largest |ΔH| and the largest drift of the Casimir
r − u² − v², and steps/s.

Usage: ``taskset -c 0 python benches/affine_learned.py [--iterations 300] [--widths 8 8]``
(about 30 s).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import poisson_rs as pr
from poisson_rs.integrators import BisectionIntegrator
from poisson_rs.scenes import load_scene
from poisson_rs.train import TrainConfig, export_bytes, train

SCENE = Path(__file__).resolve().parent.parent / "scenes" / "extended_pendulum.toml"


def scene_numbers(system: pr.AffinePoissonSystem, stepper: object, x0: np.ndarray) -> str:
    n, h = 500, 0.1
    start = time.perf_counter()
    traj = pr.integrate(stepper, x0, h, n)
    rate = len(x0) * n / (time.perf_counter() - start)
    ref = pr.reference_solution(system, x0, h * np.arange(n + 1))
    c = system.casimirs(traj)
    dh = system.hamiltonian(traj) - system.hamiltonian(traj[:, :1])
    return (
        f"error {np.abs(traj - ref).max():.2e}, max |ΔH| {np.abs(dh).max():.2e}, "
        f"max |ΔC| {np.abs(c - c[:, :1]).max():.2e}, {rate:.3g} steps/s"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--widths", type=int, nargs="+", default=[8, 8])
    args = ap.parse_args(argv)
    scene = load_scene(SCENE)
    system = scene.lie_system
    cfg = TrainConfig(
        system=system.extension,
        chart="exp",
        inputs="t,p",
        domain="cube",
        half_width=2.0,
        widths=tuple(args.widths),
        taylor_order=3,
        iterations=args.iterations,
        h_max=0.1,
        seed=0,
    )
    result = train(cfg, progress=False)
    print(
        f"held-out RMS HJ residual: Taylor-3 {result.baseline_rms:.3e}, trained "
        f"{result.validation_rms:.3e} ({result.seconds:.1f} s of training)"
    )
    learned = pr.affine_learned(system, BisectionIntegrator(export_bytes(result.model, cfg)))
    x0 = np.asarray(scene.states(), dtype=np.float64)
    print("Taylor-3 alone:", scene_numbers(system, pr.affine_taylor(system, 3), x0))
    print("learned:       ", scene_numbers(system, learned, x0))
    return 0


if __name__ == "__main__":
    sys.exit(main())

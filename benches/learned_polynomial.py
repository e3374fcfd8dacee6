"""The learned generating function on the order-n realization of the cubic Nambu scene
(scenes/nambu_cubic.toml) against its own Taylor base on the same realization, Taylor-HJ of the
next orders and RK4: error at the horizon against DOP853 (rtol = atol = 1e-13), Casimir drift,
energy drift, steps per second and the one-step error (median and max over 200 seeded states
in [−0.5, 0.5]³), for several seeds.

    taskset -c 0 .venv/bin/python benches/learned_polynomial.py --taylor-order 3 \\
        --realization-order 5 --seeds 0 1 --widths 16 16 --iterations 600 --lbfgs 400 \\
        --out docs/learned_polynomial.json

Writes the table as JSON (and CSV beside it) and prints it. ``--save-model PATH`` keeps the
model of the first seed. ``--h`` changes the step (the model is trained for h_max = h).
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

import poisson_rs as pr
from poisson_rs.integrators import LearnedPolynomialIntegrator
from poisson_rs.realizations import polynomial_hj as hj
from poisson_rs.structures.polynomial import (
    PolynomialBivector,
    PolynomialPoissonSystem,
    RealizationTaylorIntegrator,
    VectorFieldIntegrator,
)

STATES = np.array([[0.3, 0.5, -0.4], [0.1, -0.6, 0.3]])
SYSTEM = PolynomialPoissonSystem(
    PolynomialBivector.nambu("x1**2/2 + x2**2/2 + x3**2/2 + x1**3/3"),
    "x1**2/2 + x2**2/3 + x3**2/4",
)


#: 200 seeded states in [−0.5, 0.5]³ for the one-step error.
POINTS = np.random.default_rng(0).uniform(-0.5, 0.5, (200, 3))


def _row(
    name: str,
    stepper: Any,
    ref: np.ndarray,
    h: float,
    n_steps: int,
    repeats: int,
    one_step: np.ndarray,
) -> dict[str, Any]:
    traj = pr.integrate(stepper, STATES, h=h, n_steps=n_steps)
    step_err = np.abs(pr.integrate(stepper, POINTS, h=h, n_steps=1)[:, 1] - one_step).max(axis=1)
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        pr.integrate(stepper, STATES, h=h, n_steps=n_steps)
        best = min(best, time.perf_counter() - t0)
    c = SYSTEM.casimirs(traj)[..., 0]
    energy = SYSTEM.hamiltonian(traj)
    return {
        "method": name,
        "err_final": float(np.abs(traj[:, -1] - ref[:, -1]).max()),
        "err_max": float(np.abs(traj - ref).max()),
        "casimir_drift": float(np.abs(c - c[:, :1]).max()),
        "energy_drift": float(np.abs(energy - energy[:, :1]).max()),
        "steps_per_s": len(STATES) * n_steps / best,
        "one_step_err_median": float(np.median(step_err)),
        "one_step_err_max": float(step_err.max()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--taylor-order", type=int, default=3)
    ap.add_argument("--realization-order", type=int, default=5)
    ap.add_argument("--h", type=float, default=0.1)
    ap.add_argument("--horizon", type=float, default=10.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--widths", type=int, nargs="+", default=[16, 16])
    ap.add_argument("--iterations", type=int, default=600)
    ap.add_argument("--lbfgs", type=int, default=400, help="L-BFGS iterations after Adam")
    ap.add_argument("--batch", type=int, default=512)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--save-model", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    h, m, n = args.h, args.taylor_order, args.realization_order
    n_steps = round(args.horizon / h)
    times = h * np.arange(n_steps + 1)
    ref = pr.reference_solution(SYSTEM, STATES, times)
    one = pr.reference_solution(SYSTEM, POINTS, np.array([0.0, h]))[:, 1]
    rows = []
    for k, order in sorted({(m, n), (m + 2, max(n, m + 2))}):
        if k <= hj.MAX_TAYLOR_ORDER:
            stepper = RealizationTaylorIntegrator(SYSTEM, k, order)
            rows.append(_row(f"taylor{k} n={order}", stepper, ref, h, n_steps, args.repeats, one))
    rows.append(_row("rk4", VectorFieldIntegrator(SYSTEM, "rk4"), ref, h, n_steps, 1, one))
    for seed in args.seeds:
        cfg = hj.PolynomialTrainConfig(
            SYSTEM,
            taylor_order=m,
            realization_order=n,
            widths=tuple(args.widths),
            iterations=args.iterations,
            batch=args.batch,
            h_max=h,
            seed=seed,
            lbfgs_iterations=args.lbfgs,
        )
        result = hj.train_polynomial(cfg, progress=False)
        model = LearnedPolynomialIntegrator(hj.model_bytes(result.model, cfg))
        row = _row(f"learned{m} n={n} seed {seed}", model, ref, h, n_steps, args.repeats, one)
        row.update(
            parameters=model.n_parameters,
            train_seconds=round(result.seconds, 1),
            rms_residual=result.validation_rms,
            taylor_rms_residual=result.baseline_rms,
        )
        rows.append(row)
        if args.save_model is not None and seed == args.seeds[0]:
            command = (
                "taskset -c 0 .venv/bin/python benches/learned_polynomial.py --taylor-order "
                f"{m} --realization-order {n} --h {h} --seeds {seed} --widths "
                f"{' '.join(map(str, args.widths))} --iterations {args.iterations} --lbfgs "
                f"{args.lbfgs} --batch {args.batch} --save-model {args.save_model}"
            )
            hj.save_result(result, args.save_model, name=args.save_model.stem, command=command)
    for r in rows:
        print(
            f"{r['method']:>22}  err@T {r['err_final']:.2e}  max err {r['err_max']:.2e}  "
            f"ΔC {r['casimir_drift']:.1e}  ΔH {r['energy_drift']:.1e}  "
            f"{r['steps_per_s']:.3g} steps/s  1-step median {r['one_step_err_median']:.1e} "
            f"max {r['one_step_err_max']:.1e}"
            + (
                f"  ({r['parameters']} params, {r['train_seconds']} s, HJ rms "
                f"{r['rms_residual']:.2e} vs {r['taylor_rms_residual']:.2e})"
                if "parameters" in r
                else ""
            )
        )
    if args.out is not None:
        meta = {
            "states": STATES.tolist(),
            "h": h,
            "n_steps": n_steps,
            "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        }
        args.out.write_text(json.dumps({"scene": meta, "rows": rows}, indent=1) + "\n")
        keys = sorted({k for r in rows for k in r}, key=lambda k: (k != "method", k))
        with open(args.out.with_suffix(".csv"), "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=keys)
            w.writeheader()
            w.writerows(rows)


if __name__ == "__main__":
    main()

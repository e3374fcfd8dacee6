"""The learned generating function on PNN's Lotka–Volterra scene against its own Taylor base and
the classical integrators: error at the PNN horizon (1500 steps of h = 0.1) against DOP853
(rtol = atol = 1e-13), energy drift, and steps per second, for several seeds.

    taskset -c 0 .venv/bin/python benches/learned_log_canonical.py --seeds 0 1 2 \\
        --widths 8 8 --iterations 3000 --lbfgs 2000 --out docs/learned_log_canonical.json

Writes the table as JSON (and CSV beside it) and prints it. ``--save-model PATH`` keeps the
model of the first seed.
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
from poisson_rs.integrators import LearnedLogCanonicalIntegrator
from poisson_rs.realizations import log_canonical_hj as hj

STATES = np.array([[1.0, 0.8], [1.0, 1.0], [1.0, 1.2]])
H, N_STEPS = 0.1, 1500


def _row(name: str, stepper: Any, ref: np.ndarray, system: Any, repeats: int) -> dict[str, Any]:
    traj = pr.integrate(stepper, STATES, h=H, n_steps=N_STEPS)
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        pr.integrate(stepper, STATES, h=H, n_steps=N_STEPS)
        best = min(best, time.perf_counter() - t0)
    energy = system.hamiltonian(traj)
    return {
        "method": name,
        "err_final": float(np.abs(traj[:, -1] - ref[:, -1]).max()),
        "err_max": float(np.abs(traj - ref).max()),
        "energy_drift": float(np.abs(energy - energy[:, :1]).max()),
        "steps_per_s": len(STATES) * N_STEPS / best,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--widths", type=int, nargs="+", default=[8, 8])
    ap.add_argument("--iterations", type=int, default=6000)
    ap.add_argument("--taylor-order", type=int, default=3)
    ap.add_argument("--lbfgs", type=int, default=0, help="L-BFGS iterations after Adam")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--save-model", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    system = pr.lotka_volterra([[0, 1], [-1, 0]], [1, 2])
    dop = pr.log_canonical_classical(system, "dop853", tol=1e-13)
    ref = pr.integrate(dop, STATES, h=H, n_steps=N_STEPS)
    k = args.taylor_order
    rows = [
        _row(f"taylor{k}", pr.log_canonical_taylor(system, k), ref, system, args.repeats),
        _row(f"taylor{k + 2}", pr.log_canonical_taylor(system, k + 2), ref, system, args.repeats),
    ]
    for name in ("rk4", "log_splitting", "log_splitting4"):
        rows.append(_row(name, pr.log_canonical_classical(system, name), ref, system, args.repeats))
    for seed in args.seeds:
        cfg = hj.LogCanonicalTrainConfig(
            system,
            taylor_order=k,
            widths=tuple(args.widths),
            iterations=args.iterations,
            seed=seed,
            lbfgs_iterations=args.lbfgs,
        )
        result = hj.train_log_canonical(cfg, progress=False)
        model = LearnedLogCanonicalIntegrator(hj.model_bytes(result.model, cfg))
        row = _row(f"learned seed {seed}", model, ref, system, args.repeats)
        row.update(
            parameters=model.n_parameters,
            train_seconds=round(result.seconds, 1),
            rms_residual=result.validation_rms,
            taylor_rms_residual=result.baseline_rms,
        )
        rows.append(row)
        if args.save_model is not None and seed == args.seeds[0]:
            command = (
                "taskset -c 0 .venv/bin/python benches/learned_log_canonical.py --seeds "
                f"{seed} --widths {' '.join(map(str, args.widths))} --iterations "
                f"{args.iterations} --lbfgs {args.lbfgs} --taylor-order {k} "
                f"--save-model {args.save_model}"
            )
            hj.save_result(result, args.save_model, name=args.save_model.stem, command=command)
    for r in rows:
        print(
            f"{r['method']:>18}  err@T {r['err_final']:.2e}  max err {r['err_max']:.2e}  "
            f"ΔH {r['energy_drift']:.2e}  {r['steps_per_s']:.3g} steps/s"
            + (
                f"  ({r['parameters']} params, {r['train_seconds']} s, HJ rms "
                f"{r['rms_residual']:.2e} vs {r['taylor_rms_residual']:.2e})"
                if "parameters" in r
                else ""
            )
        )
    if args.out is not None:
        meta = {"states": STATES.tolist(), "h": H, "n_steps": N_STEPS, "args": vars(args)}
        meta["args"] = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
        args.out.write_text(json.dumps({"scene": meta, "rows": rows}, indent=1) + "\n")
        keys = sorted({k for r in rows for k in r}, key=lambda k: (k != "method", k))
        with open(args.out.with_suffix(".csv"), "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=keys)
            w.writeheader()
            w.writerows(rows)


if __name__ == "__main__":
    main()

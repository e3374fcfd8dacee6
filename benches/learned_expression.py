"""The learned S for a non-polynomial H on a work–precision chart: PNN's extended pendulum
(H = u²/2 − cos v + u(r − u² − v²), affine bracket, Casimir r − u² − v²), one process, one
thread:

    taskset -c 0 python benches/learned_expression.py --out docs/hamiltonians/learned_s

For each amplitude (the scene's three states scaled by 1 and by 0.25):

- the learned S (:mod:`poisson_rs.realizations.expression_hj`: Taylor-3 terms of the degree-4
  least-squares surrogate H_d on the order-3 realization, plus t · s_out · N with a 16-16 tanh
  network trained on the true H's HJ residual, seed 0, h_max = 0.2, box = the orbits' 10 %
  wider) and its Taylor base alone (the network's last layer zero);
- Taylor-HJ by jets m = 1 and 3 on the true H (exact groupoid), RK4 and the implicit midpoint
  rule on its vector field;

each at h = 0.05, 0.1, 0.2: error at T = 10 against DOP853 at 1e-13 (max over the states and
components), the Casimir's largest drift, and the cost of one step (µs per trajectory-step, 64
states, the methods alternated over 3 rounds, the median kept). Writes ``OUT.json``,
``OUT.csv`` and ``OUT_error.png`` (error against µs per unit of time, a curve per method).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import os
import statistics
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("RAYON_NUM_THREADS", "1")

import numpy as np
import torch

import poisson_rs as pr
from poisson_rs.files import atomic_write_bytes, check_output_path
from poisson_rs.realizations import expression_hj, polynomial_hj
from poisson_rs.scenes import load_scene
from poisson_rs.steppers.learned_realization import LearnedPolynomialIntegrator

SCENE = Path(__file__).resolve().parent.parent / "scenes" / "extended_pendulum_pnn.toml"
HS = (0.05, 0.1, 0.2)
HORIZON = 10.0
AMPLITUDES = (1.0, 0.25)
COST_STATES = 64


def box(s: Any, x0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The orbits' box (DOP853 over the horizon at the smallest h), 10 % wider plus 0.05."""
    ref = s.reference(x0, np.arange(round(HORIZON / HS[0]) + 1) * HS[0]).reshape(-1, s.dim)
    lo, hi = ref.min(0), ref.max(0)
    pad = 0.1 * (hi - lo) + 0.05
    return lo - pad, hi + pad


def train(s: Any, x0: np.ndarray, iterations: int, lbfgs: int) -> tuple[Any, Any, dict[str, Any]]:
    """The learned S and its Taylor base as steppers, and the training record."""
    lo, hi = box(s, x0)
    cfg = expression_hj.ExpressionTrainConfig.of(
        s, x_min=lo, x_max=hi, surrogate_degree=4, taylor_order=3, h_max=max(HS),
        widths=(16, 16), iterations=iterations, lbfgs_iterations=lbfgs, batch=512, seed=0,
    )  # fmt: skip
    sur = cfg.surrogate()
    result = expression_hj.train_expression(cfg, progress=False)
    learned = LearnedPolynomialIntegrator(
        polynomial_hj.model_bytes(result.model, cfg), tol=1e-13, max_iter=50
    )
    base_model = polynomial_hj.build_model(cfg)
    base = LearnedPolynomialIntegrator(
        polynomial_hj.model_bytes(base_model, cfg), tol=1e-13, max_iter=50
    )
    record = {
        "surrogate": sur.text,
        "surrogate_terms": sur.text.count("+") + 1,
        "surrogate_rms": sur.rms,
        "surrogate_max": sur.max,
        "box": [lo.tolist(), hi.tolist()],
        "parameters": result.model.n_parameters(),
        "train_seconds": round(result.seconds, 1),
        "hj_rms_base": result.baseline_rms,
        "hj_rms_learned": result.validation_rms,
        "realization_order": cfg.resolved_realization_order(),
    }
    return learned, base, record


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="output stem: OUT.json, OUT.csv, OUT_error.png")
    ap.add_argument("--iterations", type=int, default=1500)
    ap.add_argument("--lbfgs", type=int, default=300)
    args = ap.parse_args()
    stem = Path(args.out)
    for suffix in (".json", ".csv", "_error.png"):
        check_output_path(stem.with_name(stem.name + suffix))
    torch.set_num_threads(1)
    s = load_scene(SCENE).system
    points = np.asarray(load_scene(SCENE).points, dtype=np.float64)
    rows: list[dict[str, Any]] = []
    records: dict[str, Any] = {}
    for amp in AMPLITUDES:
        x0 = amp * points
        learned, base, rec = train(s, x0, args.iterations, args.lbfgs)
        records[str(amp)] = rec
        print(f"amplitude {amp}: trained in {rec['train_seconds']} s, HJ rms "
              f"{rec['hj_rms_base']:.2e} -> {rec['hj_rms_learned']:.2e}")  # fmt: skip
        methods = {
            "learned S": learned,
            "surrogate Taylor-3 (no network)": base,
            "jets m=1": s.taylor_integrator(1),
            "jets m=3": s.taylor_integrator(3),
            "RK4": s.classical("rk4", tol=1e-13, max_iter=50),
            "midpoint": s.classical("midpoint", tol=1e-13, max_iter=50),
        }
        big = np.resize(x0, (COST_STATES, s.dim))
        for h in HS:
            n = round(HORIZON / h)
            ref = s.reference(x0, np.arange(n + 1) * h)
            c0 = np.asarray(s.casimirs(x0.reshape(-1, s.dim))).reshape(len(x0), -1)
            errs: dict[str, tuple[float, float]] = {}
            for name, st in methods.items():
                traj = pr.integrate(st, x0, h, n)
                c = np.asarray(s.casimirs(traj.reshape(-1, s.dim))).reshape(*traj.shape[:2], -1)
                drift = float(np.abs(c - c0[:, None]).max() / max(np.abs(c0).max(), 1.0))
                errs[name] = (float(np.abs(traj - ref).max()), drift)
            steps = round(2.0 / h)  # enough that the call overhead is small against RK4
            times: dict[str, list[float]] = {k: [] for k in methods}
            for _ in range(3):
                for name, st in methods.items():
                    t0 = time.perf_counter()
                    pr.integrate(st, big, h, steps, every=steps)
                    times[name].append((time.perf_counter() - t0) / steps / COST_STATES * 1e6)
            for name in methods:
                us = statistics.median(times[name])
                rows.append({
                    "amplitude": amp, "method": name, "h": h, "error": errs[name][0],
                    "casimir_drift": errs[name][1], "us_per_step": us,
                    "us_per_unit_time": us / h,
                })  # fmt: skip
                print(f"  {name:32s} h={h:<5} err {errs[name][0]:.2e}  C {errs[name][1]:.1e}  "
                      f"{us:8.2f} us/step")  # fmt: skip
    payload = {
        "command": "taskset -c 0 python benches/learned_expression.py --out " + args.out,
        "scene": "extended_pendulum_pnn",
        "horizon": HORIZON,
        "cost_states": COST_STATES,
        "training": records,
        "rows": rows,
    }
    atomic_write_bytes(stem.with_name(stem.name + ".json"), json.dumps(payload, indent=1).encode())
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]))
    w.writeheader()
    w.writerows(rows)
    atomic_write_bytes(stem.with_name(stem.name + ".csv"), buf.getvalue().encode())
    chart(rows, stem.with_name(stem.name + "_error.png"))


def chart(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    amps = sorted({r["amplitude"] for r in rows}, reverse=True)
    fig, axes = plt.subplots(1, len(amps), figsize=(6 * len(amps), 4.5), squeeze=False)
    for ax, amp in zip(axes[0], amps, strict=True):
        for name in dict.fromkeys(r["method"] for r in rows):
            pts = sorted(
                (r["us_per_unit_time"], r["error"])
                for r in rows
                if r["amplitude"] == amp and r["method"] == name
            )
            ax.loglog(*zip(*pts, strict=True), "o-", label=name)
        ax.set_xlabel("µs per trajectory per unit of time")
        ax.set_ylabel(f"max error at T = {HORIZON:g}")
        ax.set_title(f"extended pendulum (PNN's H), states × {amp:g}")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


if __name__ == "__main__":
    main()

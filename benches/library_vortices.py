"""``pr.learn`` finds the log-distance Hamiltonian of three point vortices (the term library's
poly2+logdist), from exact records on the bracket of ``scenes/point_vortices.toml``.

Records: 3 trajectories of 101 records (h = 0.05, T = 5; DOP853 at rtol = atol = 1e-13) from the
scene's two states and (0.9, −0.2, −0.4, 0.7, −0.5, −0.6). ``pr.learn(records, h,
structure=<the scene's bracket>, seed=0)`` in mode "auto" (every family it tries is listed with
its held-out one-step error and seconds). Then:

- the coefficients against the true ones, −Γ_aΓ_b/(4π) on ln|z_a − z_b|² (the bracket is
  symplectic: H is identifiable up to a constant, which the library has no term for), and every
  other term's coefficient (zero when sparsity dropped it);
- the error at T = 100 (2000 steps) from the three training starts and the unseen start
  (0.7, 0.4, −0.7, 0.3, 0.2, −1.0), max |x(T) − x_ref(T)| over the states, for the learned
  stepper and for the true H through the same integrator (Taylor-HJ by jets, the kept order).

Usage: ``taskset -c 0 python benches/library_vortices.py`` (about 10 min on one core); writes
``docs/learning/library_vortices.json``.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

import poisson_rs as pr
from poisson_rs.protocols import NEWTON_MAX_ITER, NEWTON_TOL
from poisson_rs.scenes import load_scene

ROOT = Path(__file__).resolve().parent.parent
H, RECORDS, T = 0.05, 101, 100.0
GAMMA = (1.0, 1.0, 0.5)
EXTRA_START = [0.9, -0.2, -0.4, 0.7, -0.5, -0.6]
UNSEEN_START = [0.7, 0.4, -0.7, 0.3, 0.2, -1.0]


def true_coefficients() -> dict[tuple[str, int, int], float]:
    """{("logdist", a, b): −Γ_aΓ_b/(4π)} for the scene's H."""
    return {
        ("logdist", a, b): -GAMMA[a] * GAMMA[b] / (4 * math.pi)
        for a in range(3)
        for b in range(a + 1, 3)
    }


def main() -> None:
    scene = load_scene(ROOT / "scenes" / "point_vortices.toml")
    system = scene.system
    starts = np.vstack([scene.states(), [EXTRA_START]])
    trajs = np.asarray(pr.reference_solution(system, starts, np.arange(RECORDS) * H))
    t0 = time.perf_counter()
    stepper, report = pr.learn(list(trajs), H, structure=system.base, seed=0, progress=False)
    seconds = time.perf_counter() - t0
    fit = report.kept.fit
    learned = dict(zip(fit.family.exponents, fit.theta.tolist(), strict=True))
    truth = true_coefficients()
    scale = max(abs(c) for c in truth.values())
    coefficient_error = max(abs(learned.get(k, 0.0) - c) for k, c in truth.items()) / scale
    extra = {str(k): c for k, c in learned.items() if k not in truth}

    x0 = np.vstack([starts, [UNSEEN_START]])
    steps = round(T / H)
    ref = np.asarray(pr.reference_solution(system, x0, [0.0, T]))[:, -1]
    true_stepper = system.taylor_integrator(
        report.kept.order, tol=NEWTON_TOL, max_iter=NEWTON_MAX_ITER
    )
    t1 = time.perf_counter()
    end_learned = pr.integrate(stepper, x0, H, steps, every=steps)[:, -1]
    t2 = time.perf_counter()
    end_true = pr.integrate(true_stepper, x0, H, steps, every=steps)[:, -1]
    t3 = time.perf_counter()
    row = {
        "scene": "point_vortices",
        "records": [len(trajs), RECORDS],
        "h": H,
        "candidates": [
            {"family": c.family, "one_step": c.one_step, "seconds": round(c.seconds, 1)}
            for c in report.candidates
        ],
        "family": report.kept.family,
        "order": report.kept.order,
        "terms": {str(k): c for k, c in learned.items() if c != 0.0},
        "coefficient_error": coefficient_error,
        "other_terms": extra,
        "threshold": report.threshold,
        "learn_seconds": round(seconds, 1),
        "T": T,
        "error_T_learned": float(np.max(np.abs(end_learned - ref))),
        "error_T_true": float(np.max(np.abs(end_true - ref))),
        "rollout_seconds": [round(t2 - t1, 1), round(t3 - t2, 1)],
    }
    print(json.dumps(row, indent=1))
    out = ROOT / "docs" / "learning" / "library_vortices.json"
    out.write_text(json.dumps(row, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()

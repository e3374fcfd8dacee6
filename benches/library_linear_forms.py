"""``pr.learn`` finds Hamiltonians made of functions of linear forms (the term library's poly2+exp
and poly2+trig+trigdiff) and of products of coordinates with them (poly2+trig+xtrig), from exact
records on canonical brackets {q_i, p_i} = 1:

- Lotka–Volterra in log coordinates (q, p) = (ln x, ln y) of ẋ = x(1 − y), ẏ = y(x − 1):
  H = p − exp(p) + q − exp(q) on the 2-D canonical bracket (exp of each coordinate);
- the periodic Toda pair on (q1, q2, p1, p2): H = |p|²/2 + exp(q1 − q2) + exp(q2 − q1)
  (exp of the differences);
- two coupled pendula: H = |p|²/2 − 2 cos q1 − cos q2 − ½ cos(q1 − q2) (cos of a difference);
- a pendulum on a spring: H = |p|²/2 − (1 + ½q2) cos q1 + q2² (the product q2 cos q1,
  poly2+trig+xtrig).

Records: 3 states each, 41 records (h = 0.1, T = 4; DOP853 at rtol = atol = 1e-13 through
``pr.reference_solution``). ``pr.learn(records, h, structure=<the canonical bracket>, seed=0)`` in
mode "auto": every family tried is listed with its held-out one-step error and seconds. Then

- the coefficients against the true ones (every other term of the kept library 0): the bracket is
  symplectic, so H is fixed up to a constant, for which the library has no term;
- from the training starts and an unseen state, the error max |x(T) − x_ref(T)| at T = 10 and
  100 for the learned stepper and for the true H through the same integrator (Taylor-HJ by jets,
  the kept order), and the largest drift of the true H along those rollouts.

Usage: ``PYTHONPATH=python taskset -c 0 .venv/bin/python benches/library_linear_forms.py``
(``--systems lotka-volterra toda``: a subset); writes ``docs/learning/library_linear_forms.json``
(the systems run are replaced in it, the others kept).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from library_kepler import horizon_errors, search_rows

import poisson_rs as pr
from poisson_rs.protocols import NEWTON_MAX_ITER, NEWTON_TOL

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "learning" / "library_linear_forms.json"
H, RECORDS, HORIZONS = 0.1, 41, (10.0, 100.0)
SEED = 0


def canonical_bracket(n: int) -> Any:
    """The constant bracket {q_i, p_i} = 1 on (q_1 … q_n, p_1 … p_n) = (x1 … x2n) (its own
    quadratic H is not used)."""
    structure = pr.PolynomialBivector(2 * n, {(i, n + i): "1" for i in range(n)})
    name = f"canonical, {n} degree(s) of freedom"
    return pr.PolynomialPoissonSystem(structure, "x1**2", name=name)


SYSTEMS: dict[str, dict[str, Any]] = {
    "lotka-volterra": {
        "title": "Lotka–Volterra in log coordinates, H = p − exp(p) + q − exp(q) on (q, p)",
        "freedom": 1,
        "text": "x2 - exp(x2) + x1 - exp(x1)",
        "truth": {(1, 0): 1.0, (0, 1): 1.0, ("exp", (1, 0)): -1.0, ("exp", (0, 1)): -1.0},
        "starts": [[0.5, 0.0], [-0.4, 0.3], [0.2, -0.7]],
        "unseen": [0.8, 0.4],
    },
    "toda": {
        "title": "the periodic Toda pair, H = |p|²/2 + exp(q1 − q2) + exp(q2 − q1)",
        "freedom": 2,
        "text": "0.5*(x3**2 + x4**2) + exp(x1 - x2) + exp(x2 - x1)",
        "truth": {
            (0, 0, 2, 0): 0.5,
            (0, 0, 0, 2): 0.5,
            ("exp", (1, -1, 0, 0)): 1.0,
            ("exp", (-1, 1, 0, 0)): 1.0,
        },
        "starts": [[0.0, 0.5, 0.3, -0.2], [0.4, -0.3, -0.5, 0.1], [-0.2, 0.1, 0.6, 0.5]],
        "unseen": [0.3, 0.0, -0.2, 0.6],
    },
    "coupled-pendula": {
        "title": "coupled pendula, H = |p|²/2 − 2 cos q1 − cos q2 − ½ cos(q1 − q2)",
        "freedom": 2,
        "text": "0.5*(x3**2 + x4**2) - 2*cos(x1) - cos(x2) - 0.5*cos(x1 - x2)",
        "truth": {
            (0, 0, 2, 0): 0.5,
            (0, 0, 0, 2): 0.5,
            ("cos", 0): -2.0,
            ("cos", 1): -1.0,
            ("cos", (1, -1, 0, 0)): -0.5,
        },
        "starts": [[0.5, -0.3, 0.2, 0.4], [-0.8, 0.6, 0.1, -0.3], [0.2, 1.0, -0.4, 0.0]],
        "unseen": [1.2, -0.5, 0.0, 0.3],
    },
    "spring-pendulum": {
        "title": "a pendulum on a spring, H = |p|²/2 − (1 + ½q2) cos q1 + q2²",
        "freedom": 2,
        "text": "0.5*(x3**2 + x4**2) - (1 + 0.5*x2)*cos(x1) + x2**2",
        "truth": {
            (0, 0, 2, 0): 0.5,
            (0, 0, 0, 2): 0.5,
            (0, 2, 0, 0): 1.0,
            ("cos", 0): -1.0,
            ("xcos", 1, 0): -0.5,
        },
        "starts": [[0.5, -0.3, 0.2, 0.4], [-0.8, 0.6, 0.1, -0.3], [0.2, 0.4, -0.4, 0.0]],
        "unseen": [1.0, -0.2, 0.1, 0.3],
    },
}


def run(spec: dict[str, Any]) -> dict[str, Any]:
    """pr.learn on the records of one system, then the errors and drifts (one row)."""
    base = canonical_bracket(spec["freedom"])
    system = pr.with_hamiltonian(base, spec["text"], name="truth")
    starts = np.array(spec["starts"], dtype=np.float64)
    trajs = np.asarray(pr.reference_solution(system, starts, np.arange(RECORDS) * H))
    t0 = time.perf_counter()
    stepper, report = pr.learn(list(trajs), H, structure=base, seed=SEED, progress=False)
    seconds = time.perf_counter() - t0
    fit = report.kept.fit
    learned = dict(zip(fit.family.exponents, fit.theta.tolist(), strict=True))
    truth = spec["truth"]
    keys = set(truth) | set(learned)
    coefficient_error = max(abs(learned.get(k, 0.0) - truth.get(k, 0.0)) for k in keys)

    x0 = np.vstack([starts, [spec["unseen"]]])
    true_stepper = system.taylor_integrator(
        report.kept.order, tol=NEWTON_TOL, max_iter=NEWTON_MAX_ITER
    )
    steps = round(HORIZONS[-1] / H)
    roll_learned = np.asarray(pr.integrate(stepper, x0, H, steps))
    roll_true = np.asarray(pr.integrate(true_stepper, x0, H, steps))
    ref = np.asarray(pr.reference_solution(system, x0, [0.0, *HORIZONS]))
    errors = horizon_errors({"learned": roll_learned, "true": roll_true}, ref, HORIZONS, H)
    drifts = {}
    for name, roll in (("learned", roll_learned), ("true", roll_true)):
        e = np.asarray(system.hamiltonian(roll.reshape(-1, roll.shape[-1]))).reshape(roll.shape[:2])
        drifts[f"energy_drift_{name}"] = float(np.max(np.abs(e - e[:, :1])))
    return {
        "system": spec["title"],
        "records": [len(trajs), RECORDS],
        "h": H,
        "candidates": search_rows(report),
        "family": report.kept.family,
        "order": report.kept.order,
        "hamiltonian": report.hamiltonian_text,
        "terms": {str(k): c for k, c in learned.items() if c != 0.0},
        "coefficient_error": coefficient_error,
        "threshold": report.threshold,
        "explained": report.explained,
        "fit_seconds": round(report.kept.seconds, 1),
        "learn_seconds": round(seconds, 1),
        **errors,
        "T_drift": HORIZONS[-1],
        **drifts,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--systems", nargs="+", choices=sorted(SYSTEMS), default=list(SYSTEMS))
    args = parser.parse_args()
    old = json.loads(OUT.read_text(encoding="utf-8")) if OUT.exists() else {"runs": {}}
    runs = dict(old.get("runs", {}))
    for name in args.systems:
        runs[name] = run(SYSTEMS[name])
        print(json.dumps({name: runs[name]}, indent=1, ensure_ascii=False), flush=True)
    row = {
        "command": "PYTHONPATH=python taskset -c 0 .venv/bin/python " + " ".join(sys.argv),
        "seed": SEED,
        "runs": {name: runs[name] for name in SYSTEMS if name in runs},
    }
    OUT.write_text(json.dumps(row, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()

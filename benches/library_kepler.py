"""``pr.learn`` finds planar Kepler's H = |p|²/2 − 1/|q| (the term library's poly2+dist^-1), from
exact records on the canonical bracket {q_i, p_i} = 1 in the coordinates (q1, q2, p1, p2).

The library reads consecutive coordinate pairs as planar points, so z_0 = q and z_1 = p: the
potential is the term |z_0|^−1 = ``("radius", -1, 0)``; |p|^−1 and |q − p|^−1 are offered too
(the rule is on positions, not a guess at the system) and should come out zero.

Records: 3 bound orbits of semi-major axis 1 and eccentricities 0.1, 0.2, 0.3, each started at
periapsis (rotated by 0, 1.3, 2.6 rad), 101 records each (h = 0.1, T = 10, more than one period
2π; DOP853 at rtol = atol = 1e-13 through ``pr.reference_solution``); a second run on
eccentricities 0.1, 0.25, 0.4, where the order-5 integrator's truncation at the closer periapsis
is larger. ``pr.learn(records, h, structure=<the canonical bracket>, seed=0)`` in mode "auto"
(every family tried is listed with its held-out one-step error and seconds). Then:

- the coefficients against the true ones (½ on p1², p2²; −1 on |q|^−1; every other term 0): the
  bracket is symplectic, so H is fixed up to a constant, for which the library has no term;
- from the three training starts and an unseen orbit (a = 1.2, e = 0.5, periapsis at 2.0 rad), the
  error max |x(T) − x_ref(T)| at T = 10 and 100 (100 and 1000 steps) for the learned stepper and
  for the true H through the same integrator (Taylor-HJ by jets, the kept order), and along those
  rollouts to T = 100 the largest drift of the true H and of the angular momentum q1p2 − q2p1.

Usage: ``PYTHONPATH=python taskset -c 0 .venv/bin/python benches/library_kepler.py`` (a few
minutes on one core, most of it the learned H's rollouts: 17 terms in its jets); writes
``docs/learning/library_kepler.json``.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

import poisson_rs as pr
from poisson_rs.protocols import NEWTON_MAX_ITER, NEWTON_TOL

ROOT = Path(__file__).resolve().parent.parent
H, RECORDS, HORIZONS = 0.1, 101, (10.0, 100.0)
SEED = 0
#: (semi-major axis, eccentricity, angle of the periapsis) of the training orbits, then the
#: unseen one.
RUNS = {
    "e <= 0.3": [(1.0, 0.1, 0.0), (1.0, 0.2, 1.3), (1.0, 0.3, 2.6)],
    "e <= 0.4": [(1.0, 0.1, 0.0), (1.0, 0.25, 1.3), (1.0, 0.4, 2.6)],
}
UNSEEN = (1.2, 0.5, 2.0)
TRUE_TEXT = "0.5*(x3**2 + x4**2) - (x1**2 + x2**2)**(-0.5)"


def canonical_bracket() -> Any:
    """The constant bracket {q_i, p_i} = 1 on (q1, q2, p1, p2) = (x1, x2, x3, x4) (its own
    quadratic H is not used)."""
    structure = pr.PolynomialBivector(4, {(0, 2): "1", (1, 3): "1"})
    return pr.PolynomialPoissonSystem(structure, "x1**2 + x2**2", name="canonical (q, p)")


def periapsis(a: float, e: float, angle: float) -> np.ndarray:
    """(q1, q2, p1, p2) at periapsis of the Kepler orbit (GM = 1) of semi-major axis ``a`` and
    eccentricity ``e`` whose periapsis lies at ``angle`` (rad), moving counter-clockwise."""
    r, v = a * (1 - e), math.sqrt((1 + e) / (a * (1 - e)))
    c, s = math.cos(angle), math.sin(angle)
    return np.array([r * c, r * s, -v * s, v * c])


def true_coefficients() -> dict[Any, float]:
    return {(0, 0, 2, 0): 0.5, (0, 0, 0, 2): 0.5, ("radius", -1, 0): -1.0}


def kepler_energy(x: np.ndarray) -> np.ndarray:
    return 0.5 * (x[..., 2] ** 2 + x[..., 3] ** 2) - 1.0 / np.hypot(x[..., 0], x[..., 1])


def angular_momentum(x: np.ndarray) -> np.ndarray:
    return x[..., 0] * x[..., 3] - x[..., 1] * x[..., 2]


def search_rows(report: Any) -> list[dict[str, Any]]:
    """Every family ``pr.learn`` tried: its held-out one-step error and seconds."""
    return [
        {"family": c.family, "one_step": c.one_step, "seconds": round(c.seconds, 1)}
        for c in report.candidates
    ]


def horizon_errors(
    rolls: dict[str, np.ndarray], ref: np.ndarray, horizons: tuple[float, ...], h: float
) -> dict[str, Any]:
    """max |x(T) − x_ref(T)| per state and over them, at each T of ``horizons``, for each named
    rollout (B, steps + 1, n) of step ``h``; ``ref`` (B, 1 + len(horizons), n) from t = 0."""
    errors: dict[str, Any] = {}
    for j, t in enumerate(horizons):
        k = round(t / h)
        for name, roll in rolls.items():
            per_state = np.max(np.abs(roll[:, k] - ref[:, j + 1]), axis=1)
            errors[f"error_T{t:g}_{name}"] = float(per_state.max())
            errors[f"error_T{t:g}_{name}_per_state"] = per_state.tolist()
    return errors


def run(train: list[tuple[float, float, float]]) -> dict[str, Any]:
    """pr.learn on records from the orbits ``train``, then the errors and drifts (one row)."""
    base = canonical_bracket()
    system = pr.with_hamiltonian(base, TRUE_TEXT, name="planar Kepler")
    starts = np.array([periapsis(*o) for o in train])
    trajs = np.asarray(pr.reference_solution(system, starts, np.arange(RECORDS) * H))
    t0 = time.perf_counter()
    stepper, report = pr.learn(list(trajs), H, structure=base, seed=SEED, progress=False)
    seconds = time.perf_counter() - t0
    fit = report.kept.fit
    learned = dict(zip(fit.family.exponents, fit.theta.tolist(), strict=True))
    truth = true_coefficients()
    keys = set(truth) | set(learned)
    coefficient_error = max(abs(learned.get(k, 0.0) - truth.get(k, 0.0)) for k in keys)

    x0 = np.vstack([starts, [periapsis(*UNSEEN)]])
    true_stepper = system.taylor_integrator(
        report.kept.order, tol=NEWTON_TOL, max_iter=NEWTON_MAX_ITER
    )
    steps = round(HORIZONS[-1] / H)
    t1 = time.perf_counter()
    roll_learned = np.asarray(pr.integrate(stepper, x0, H, steps))
    t2 = time.perf_counter()
    roll_true = np.asarray(pr.integrate(true_stepper, x0, H, steps))
    t3 = time.perf_counter()
    ref = np.asarray(pr.reference_solution(system, x0, [0.0, *HORIZONS]))
    errors = horizon_errors({"learned": roll_learned, "true": roll_true}, ref, HORIZONS, H)
    drifts = {}
    for name, roll in (("learned", roll_learned), ("true", roll_true)):
        e, ell = kepler_energy(roll), angular_momentum(roll)
        drifts[f"energy_drift_{name}"] = float(np.max(np.abs(e - e[:, :1])))
        drifts[f"angular_momentum_drift_{name}"] = float(np.max(np.abs(ell - ell[:, :1])))
    return {
        "orbits_train": [{"a": a, "e": e, "periapsis_angle": w} for a, e, w in train],
        "orbit_unseen": dict(zip(("a", "e", "periapsis_angle"), UNSEEN, strict=True)),
        "records": [len(trajs), RECORDS],
        "h": H,
        "candidates": search_rows(report),
        "family": report.kept.family,
        "order": report.kept.order,
        "hamiltonian": report.hamiltonian_text,
        "terms": {str(k): c for k, c in learned.items() if c != 0.0},
        "coefficient_error": coefficient_error,
        "threshold": report.threshold,
        "fit_seconds": round(report.kept.seconds, 1),
        "learn_seconds": round(seconds, 1),
        **errors,
        "T_drift": HORIZONS[-1],
        **drifts,
        "rollout_seconds": [round(t2 - t1, 1), round(t3 - t2, 1)],
    }


def main() -> None:
    row = {
        "system": "planar Kepler, H = |p|²/2 − 1/|q| on (q1, q2, p1, p2) = (x1, x2, x3, x4)",
        "command": "PYTHONPATH=python taskset -c 0 .venv/bin/python " + " ".join(sys.argv),
        "seed": SEED,
        "runs": {name: run(train) for name, train in RUNS.items()},
    }
    print(json.dumps(row, indent=1, ensure_ascii=False))
    out = ROOT / "docs" / "learning" / "library_kepler.json"
    out.write_text(json.dumps(row, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()

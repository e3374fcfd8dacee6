"""Structure discovery, ``pr.learn(trajectories, h, structure="discover")``: H and the bracket
both unknown, on exact records of five systems, with the error of the learned stepper against
DOP853 beside the true system through its own integrator.

Cases (seeded; exact records from DOP853 at rtol = atol = 1e-13):

- PNN's Lotka–Volterra protocol (u̇ = u(v − 2), v̇ = v(1 − u); h = 0.1, 100 steps from
  (1, 0.8), (1, 1), (1, 1.2)); test states (1, 0.9), (1, 1.1) to T = 100;
- the rigid body I = (2, 1, 2/3), 8 unit states × 40 steps, h = 0.1; 3 test states to T = 100;
- PNN's extended pendulum with the degree-4 H (affine bracket), 8 states × 30 steps;
  3 test states to T = 10;
- a damped oscillator (not Poisson): must be reported as not explained;
- the heavy top (se(3)*), 8 states × 30 steps, H of degree 2; 3 test states to T = 100;
- PNN's extended pendulum with its own H = ½u² − cos v + u(r − u² − v²) (the term library),
  PNN's 3 states × 100 steps; tested from the ends of the training data to T = 100.

    PYTHONPATH=python taskset -c 0 .venv/bin/python benches/discover_structures.py
    PYTHONPATH=python taskset -c 0 .venv/bin/python benches/discover_structures.py --noise

Writes docs/learning/discover.json; ``--noise``: the noise study instead (PNN's Lotka–Volterra
protocol with Gaussian noise of relative σ on every training record, 3 draws each; error over
the 100 steps after the training span, from the exact state there), docs/learning/
discover_noise.json.
"""

from __future__ import annotations

import json
import math
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

import poisson_rs as pr
from poisson_rs.scenes import load_scene

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "learning" / "discover.json"


def _lv(t, z):
    return [z[0] * (z[1] - 2), z[1] * (1 - z[0])]


def _solve(f, z0, h, n):
    sol = solve_ivp(
        f, (0, n * h), z0, t_eval=np.arange(n + 1) * h, method="DOP853", rtol=1e-13, atol=1e-13
    )
    return sol.y.T


def _rollout_error(stepper, truth, h):
    worst = 0.0
    for t in truth:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            roll = pr.integrate(stepper, t[0], h, len(t) - 1, on_failure="ignore")
        e = float(np.max(np.linalg.norm(roll - t, axis=1) / np.linalg.norm(t, axis=1)))
        worst = max(worst, e if math.isfinite(e) else math.inf)
    return worst


def case(name, trajs, h, tests, true_stepper=None, **kwargs):
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            stepper, report = pr.learn(trajs, h, structure="discover", progress=False, **kwargs)
        except ValueError as exc:
            return {"case": name, "refused": str(exc), "seconds": time.perf_counter() - t0}
    seconds = time.perf_counter() - t0
    print(report)
    row = {
        "case": name,
        "kept": report.kept.family,
        "explained": report.explained,
        "bracket": report.bracket,
        "casimirs": report.kept.casimirs_text,
        "hamiltonian": report.hamiltonian_text,
        "parameters": report.kept.parameters,
        "held_out_one_step": report.kept.one_step,
        "test_rollout": _rollout_error(stepper, tests, h),
        "true_h_same_structure_rollout": (
            _rollout_error(true_stepper, tests, h) if true_stepper is not None else "n/a"
        ),
        "jacobi_residual": report.kept.jacobi_residual,
        "seconds": round(seconds, 2),
        "warnings": [str(w.message)[:200] for w in caught],
        "candidates": report.rows(),
    }
    return row


def noise_study() -> None:
    h = 0.1
    exact = [_solve(_lv, z0, h, 200) for z0 in ((1, 0.8), (1, 1), (1, 1.2))]
    train, tests = [t[:101] for t in exact], [t[100:] for t in exact]
    rows = []
    for sigma in (0.0, 1e-6, 1e-4, 1e-2):
        for draw in range(3 if sigma else 1):
            rng = np.random.default_rng(draw)
            noisy = [
                t + sigma * np.linalg.norm(t, axis=1)[:, None] * rng.normal(size=t.shape)
                for t in train
            ]
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                try:
                    stepper, report = pr.learn(noisy, h, structure="discover", progress=False)
                except ValueError as exc:
                    rows.append({"sigma": sigma, "draw": draw, "refused": str(exc)})
                    continue
            row = {
                "sigma": sigma,
                "draw": draw,
                "kept": report.kept.family,
                "explained": report.explained,
                "bracket": report.bracket,
                "error_test_horizon": _rollout_error(stepper, tests, h),
                "seconds": round(time.perf_counter() - t0, 2),
            }
            print(row)
            rows.append(row)
    out = OUT.with_name("discover_noise.json")
    out.write_text(json.dumps(rows, indent=1) + "\n")


def main() -> None:
    rows = []
    h = 0.1
    # Lotka–Volterra, PNN's protocol.
    train = [_solve(_lv, z0, h, 100) for z0 in ((1, 0.8), (1, 1), (1, 1.2))]
    tests = [_solve(_lv, z0, h, 1000) for z0 in ((1, 0.9), (1, 1.1))]
    lv = pr.lotka_volterra([[0, 1], [-1, 0]], [1, 2])
    true_lv = pr.taylor_integrator(lv, 5)
    rows.append(case("lotka_volterra_pnn", train, h, tests, true_lv))
    # Rigid body.
    rb = pr.RigidBody((2.0, 1.0, 2.0 / 3.0))
    rng = np.random.default_rng(0)
    x0 = rng.normal(size=(8, 3))
    x0 /= np.linalg.norm(x0, axis=1)[:, None]
    trajs = list(np.asarray(pr.reference_solution(rb, x0, np.arange(41) * h)))
    t0 = rng.normal(size=(3, 3))
    t0 /= np.linalg.norm(t0, axis=1)[:, None]
    tests = list(np.asarray(pr.reference_solution(rb, t0, np.arange(1001) * h)))
    rows.append(case("rigid_body", trajs, h, tests, pr.taylor_integrator(rb, 7)))
    # Extended pendulum (affine), degree-4 H.
    ep = load_scene(ROOT / "scenes" / "extended_pendulum.toml").system
    rng = np.random.default_rng(1)
    trajs = list(
        np.asarray(pr.reference_solution(ep, rng.normal(size=(8, 3)) * 0.5, np.arange(31) * h))
    )
    tests = list(
        np.asarray(pr.reference_solution(ep, rng.normal(size=(3, 3)) * 0.5, np.arange(101) * h))
    )
    rows.append(case("extended_pendulum_poly4", trajs, h, tests, pr.taylor_integrator(ep, 3)))
    # Damped oscillator: not Poisson.
    rng = np.random.default_rng(2)
    damped = [
        _solve(lambda t, z: [z[1], -z[0] - 0.1 * z[1]], z0, h, 30) for z0 in rng.normal(size=(6, 2))
    ]
    rows.append(case("damped_oscillator", damped, h, damped[:1], None, degree=2))
    # Heavy top: se(3)*; 3 fresh states to T = 100.
    ht = pr.HeavyTop()
    rng = np.random.default_rng(1)
    trajs = list(
        np.asarray(pr.reference_solution(ht, rng.normal(size=(8, 6)) * 0.5, np.arange(31) * h))
    )
    tests = list(
        np.asarray(pr.reference_solution(ht, rng.normal(size=(3, 6)) * 0.5, np.arange(1001) * h))
    )
    rows.append(case("heavy_top", trajs, h, tests, pr.taylor_integrator(ht, 5), degree=2))
    # PNN's extended pendulum with its own H (−cos v: the term library), PNN's three states;
    # tested from the end of each training trajectory on to 10× PNN's test horizon.
    epp = load_scene(ROOT / "scenes" / "extended_pendulum_pnn.toml").system
    states = np.array([[0.0, 1.0, 1.0], [0.0, 1.5, 2.35], [0.0, 2.0, 4.2]])
    trajs = list(np.asarray(pr.reference_solution(epp, states, np.arange(101) * h)))
    ends = np.array([t[-1] for t in trajs])
    tests = list(np.asarray(pr.reference_solution(epp, ends, np.arange(1001) * h)))
    rows.append(case("extended_pendulum_pnn", trajs, h, tests, pr.taylor_integrator(epp, 5)))
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(rows, indent=1, default=str) + "\n")
    for r in rows:
        print(
            r["case"],
            r.get("kept", "refused"),
            r.get("explained"),
            r.get("test_rollout"),
            r.get("true_h_same_structure_rollout"),
            r["seconds"],
        )


if __name__ == "__main__":
    import sys

    if "--noise" in sys.argv[1:]:
        noise_study()
    else:
        main()

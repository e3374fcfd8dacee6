"""Non-polynomial Hamiltonians: the shipped expression scenes measured, one process, one thread:
``taskset -c 0 python benches/hamiltonians.py --json docs/hamiltonians.json``.

For each scene (PNN's extended pendulum, the rigid body in a potential, three point vortices):

- fitted orders of Taylor-HJ by jets m = 1, 3, 5 (errors at T = 1 from the scene's first state
  against DOP853 at 1e-13, h = 0.2, 0.1, 0.05);
- the Casimirs' largest relative drift (the vortices: the linear and angular impulses') over
  10⁴ steps of h = the scene's, jets m = 1 and 3 against RK4 and the midpoint rule;
- the cost of one step (µs per trajectory-step, 64 states, median of 3 runs) of jets m = 1, 3, 5,
  RK4 and the midpoint rule, and each one's error at T = 10;
- on the extended pendulum, the error at T = 100 of the polynomial truncation of H that the
  shipped ``extended_pendulum`` scene used (−cos v → −1 + v²/2 − v⁴/24) against the flow of
  PNN's H, beside jets m = 3 on the true H.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("RAYON_NUM_THREADS", "1")

import numpy as np

import poisson_rs as pr
from poisson_rs.files import atomic_write_bytes, check_output_path
from poisson_rs.scenes import load_scene

SCENES = Path(__file__).resolve().parent.parent / "scenes"
NAMES = ("extended_pendulum_pnn", "rigid_body_potential", "point_vortices")
GAMMA = np.array([1.0, 1.0, 0.5])


def invariants(name: str, s: Any, traj: np.ndarray) -> np.ndarray:
    """(n, T, k): the Casimirs, or the vortices' impulses."""
    if name != "point_vortices":
        c = s.casimirs(traj.reshape(-1, s.dim))
        return np.asarray(c).reshape(*traj.shape[:2], -1)
    xs, ys = traj[..., 0::2], traj[..., 1::2]
    return np.stack(
        [(GAMMA * xs).sum(-1), (GAMMA * ys).sum(-1), (GAMMA * (xs**2 + ys**2)).sum(-1)], -1
    )


def orders(s: Any, x0: np.ndarray) -> dict[str, float]:
    hs = np.array([0.2, 0.1, 0.05])
    ref = s.reference_solution(x0, np.array([0.0, 1.0]))[:, -1]
    out = {}
    for m in (1, 3, 5):
        errs = [
            np.abs(pr.integrate(s.taylor_integrator(m), x0, h, round(1 / h))[:, -1] - ref).max()
            for h in hs
        ]
        out[f"jets{m}"] = float(np.polyfit(np.log(hs), np.log(errs), 1)[0])
    return out


def steppers(s: Any) -> dict[str, Any]:
    return {
        "jets1": s.taylor_integrator(1),
        "jets3": s.taylor_integrator(3),
        "jets5": s.taylor_integrator(5),
        "rk4": s.classical("rk4"),
        "midpoint": s.classical("midpoint"),
    }


def drift(name: str, s: Any, x0: np.ndarray, h: float) -> dict[str, float]:
    out = {}
    for label, st in steppers(s).items():
        if label == "jets5":
            continue
        traj = pr.integrate(st, x0, h, 10_000, every=100)
        inv = invariants(name, s, traj)
        out[label] = float(np.abs(inv - inv[:, :1]).max() / np.abs(inv[:, 0]).max())
    return out


def costs(s: Any, x0: np.ndarray, h: float) -> dict[str, dict[str, float]]:
    n = round(10.0 / h)
    ref = s.reference_solution(x0, np.array([0.0, 10.0]))[:, -1]
    out = {}
    for label, st in steppers(s).items():
        steps = n if label != "jets5" else n // 4
        times = []
        for _ in range(3):
            t = time.perf_counter()
            traj = pr.integrate(st, x0, h, steps, every=steps)
            times.append(time.perf_counter() - t)
        us = statistics.median(times) / (len(x0) * steps) * 1e6
        err = float(np.abs(traj[:, -1] - ref).max()) if steps == n else float("nan")
        out[label] = {"us_per_step": us, "error_T10": err}
    return out


#: −cos v truncated after v⁴ (the shipped polynomial scene's) and after v⁶.
TRUNCATIONS = {
    "degree4": "u**2/2 - 1 + v**2/2 - v**4/24 + u*(r - u**2 - v**2)",
    "degree6": "u**2/2 - 1 + v**2/2 - v**4/24 + v**6/720 + u*(r - u**2 - v**2)",
}


def truncation(h: float) -> dict[str, Any]:
    """The extended pendulum at T = 100 from the scene's states: the flow of PNN's H against
    the flows of its polynomial truncations (exact, by DOP853; None where an orbit escapes:
    −v⁴/24 makes H unbounded below), and jets m = 3 on the true H."""
    scene = load_scene(SCENES / "extended_pendulum_pnn.toml")
    s = scene.system
    x0 = np.asarray(scene.points)
    t = np.array([0.0, 100.0])
    true = s.reference_solution(x0, t)[:, -1]
    out: dict[str, Any] = {}
    for label, text in TRUNCATIONS.items():
        cut = pr.with_hamiltonian(s.base, text)
        flow = cut.reference_solution(x0, t, failures="nan")[:, -1]
        err = np.abs(flow - true).max(axis=1)
        out[f"{label}_truncation_error_T100"] = [
            None if not np.isfinite(e) else float(e) for e in err
        ]
    jets = pr.integrate(s.taylor_integrator(3), x0, h, round(100 / h))[:, -1]
    out["jets3_h01_true_H_error_T100"] = np.abs(jets - true).max(axis=1).tolist()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    if args.json is not None:
        check_output_path(args.json)
    results: dict[str, Any] = {}
    rng = np.random.default_rng(7)
    for name in NAMES:
        scene = load_scene(SCENES / f"{name}.toml")
        s, h = scene.system, scene.h[0]
        x0 = np.asarray(scene.points)
        batch = x0[rng.integers(0, len(x0), 64)] * rng.uniform(0.9, 1.1, (64, 1))
        results[name] = {
            "orders": orders(s, x0[:1]),
            "drift_1e4_steps": drift(name, s, x0, h),
            "cost": costs(s, batch, h),
        }
        print(name, json.dumps(results[name], indent=1))
    results["extended_pendulum_truncation"] = truncation(0.1)
    print(results["extended_pendulum_truncation"])
    if args.json is not None:
        atomic_write_bytes(args.json, (json.dumps(results, indent=2) + "\n").encode())


if __name__ == "__main__":
    main()

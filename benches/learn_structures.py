"""``pr.learn(..., structure=...)`` on the structures beyond Lie–Poisson, from exact records.

For each structure (affine: PNN's extended pendulum, H of degree 4; polynomial bivector: the cubic
Nambu bracket, H of degree 2; charged particle: B = 1 + x₁²/4, H = |v|²/2 + |x|²/8): 6
trajectories of 41 records (h = 0.1, DOP853 at rtol = atol = 1e-13) from the scene's states
moved by 0.1·N(0, 1) (seed 0), learned with mode "hamiltonian" at the true degree; then the
largest relative vector-field error at the records of 3 held-out trajectories (seed 1), and the
largest error of 400-step rollouts from their starts (T = 40) for the learned stepper and for the
true H through the same integrator (order and chart). The same data and settings as
``tests/test_learn_structures.py``. Then PNN's Lotka–Volterra protocol (mode "auto"), errors at
T = 100 on its hidden states.

Usage: ``taskset -c 0 python benches/learn_structures.py`` (about 20 s); writes
``docs/learning/structures.json``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

import poisson_rs as pr
from poisson_rs.scenes import load_scene
from poisson_rs.structures.charged_particle import charged_particle

ROOT = Path(__file__).resolve().parent.parent
H, RECORDS, LONG = 0.1, 41, 400
CASES = {
    # name: (scene states, degree, Taylor order)
    "extended_pendulum": ([[0.8, -0.5, 2.0], [0.0, 1.0, 0.5], [1.2, 0.3, 1.0]], 4, 3),
    "nambu_cubic": ([[0.3, 0.5, -0.4], [0.1, -0.6, 0.3]], 2, 3),
    "charged_particle": (
        [[0.3, -0.2, 1.0, 0.5], [0.0, 0.0, 0.5, 0.5], [1.0, 0.5, -0.3, 0.8]],
        2,
        5,
    ),
}


def system_of(name: str) -> object:
    if name == "charged_particle":
        return charged_particle("1 + x1**2/4", "x3**2/2 + x4**2/2 + x1**2/8 + x2**2/8")
    return load_scene(ROOT / "scenes" / f"{name}.toml").system


def starts(points: list[list[float]], count: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = np.array(points)
    return pts[rng.integers(len(pts), size=count)] + 0.1 * rng.normal(size=(count, pts.shape[1]))


def lotka_volterra() -> dict[str, object]:
    """PNN's protocol: u̇ = u(v − 2), v̇ = v(1 − u), h = 0.1, 100 steps from each of (1, 0.8),
    (1, 1), (1, 1.2); errors on the hidden states (1, 0.9), (1, 1.1), (0.8, 1) at T = 100."""
    lv = pr.lotka_volterra([[0, 1], [-1, 0]], [1.0, 2.0])
    trajs = lv.reference_solution(np.array([[1, 0.8], [1, 1.0], [1, 1.2]]), np.arange(101) * H)
    t0 = time.perf_counter()
    stepper, report = pr.learn(trajs, H, structure=lv)
    seconds = time.perf_counter() - t0
    hidden = np.array([[1, 0.9], [1, 1.1], [0.8, 1.0]])
    ref = lv.reference_solution(hidden, np.arange(1001) * H)
    true = pr.integrate(pr.taylor_integrator(lv, report.kept.order), hidden, H, 1000)
    learned = pr.integrate(stepper, hidden, H, 1000)
    return {
        "structure": "lotka_volterra_pnn",
        "kind": lv.kind,
        "family": report.kept.family,
        "order": report.kept.order,
        "parameters": report.kept.parameters,
        "rollout_learned": float(np.max(np.abs(learned - ref))),
        "rollout_true": float(np.max(np.abs(true - ref))),
        "train_seconds": round(seconds, 2),
    }


def main() -> None:
    rows = []
    for name, (points, degree, order) in CASES.items():
        system = system_of(name)
        trajs = system.reference_solution(starts(points, 6, 0), np.arange(RECORDS) * H)
        t0 = time.perf_counter()
        stepper, report = pr.learn(
            trajs, H, structure=system, mode="hamiltonian", degree=degree, order=order
        )
        seconds = time.perf_counter() - t0
        x0 = starts(points, 3, 1)
        held = system.reference_solution(x0, np.arange(RECORDS) * H).reshape(-1, system.dim)
        a, b = report.system.vector_field(held), system.vector_field(held)
        field = float(np.max(np.linalg.norm(a - b, axis=1)) / np.max(np.linalg.norm(b, axis=1)))
        ref = system.reference_solution(x0, np.arange(LONG + 1) * H)
        true = pr.integrate(pr.taylor_integrator(system, report.kept.order), x0, H, LONG)
        learned = pr.integrate(stepper, x0, H, LONG)
        row = {
            "structure": name,
            "kind": system.kind,
            "family": report.kept.family,
            "order": report.kept.order,
            "parameters": report.kept.parameters,
            "field_error": field,
            "rollout_learned": float(np.max(np.abs(learned - ref))),
            "rollout_true": float(np.max(np.abs(true - ref))),
            "train_seconds": round(seconds, 2),
        }
        rows.append(row)
        print(json.dumps(row))
    rows.append(lotka_volterra())
    print(json.dumps(rows[-1]))
    out = ROOT / "docs" / "learning" / "structures.json"
    out.write_text(json.dumps(rows, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()

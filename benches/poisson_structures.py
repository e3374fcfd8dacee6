"""Log-canonical (Lotka–Volterra) scenes: every integrator against DOP853 in one table, plus
fitted orders and Casimir drifts, for docs/poisson_structures.md.

For each scene TOML (``scenes/lotka_volterra_pnn.toml``, ``scenes/lotka_volterra_3d.toml``):
the largest |x − x_ref|∞ over all steps and states (and at the last step) for Taylor-HJ m = 1, 3,
5 on the exact groupoid, RK4, the implicit midpoint rule and the log splittings (Strang, order 2;
Suzuki, order 4), against DOP853 in q = ln x (rtol = atol = 1e-13); the largest energy error
|H − H₀|; the largest drift of the monomial Casimirs Σ k_i ln x_i ("n/a" when c is invertible);
and steps/s (trajectory-steps a second, best of 3 timed runs of the scene's states tiled to 240
trajectories; pin with
``taskset -c 0``: the ratios within one run are what to compare).

Fitted orders: slope of log error against log h at T = 2 from h = T/10, T/20, T/40 on PNN's
states (1, 0.8) and (1, 1.2). Casimir drift over 10⁴ steps of h = 0.1 on the 3D scene.

Affine bracket (``scenes/extended_pendulum.toml``, on its central extension at level 1): for
Taylor-HJ m = 1, 3, 5, 7 (exp chart), RK4 and the midpoint rule, the fitted order (same fit, the
scene's states, against DOP853), the largest error over the scene (200 steps of h = 0.1), the
drift of its Casimir over 10⁴ steps of h = 0.1, and steps/s.

Usage: ``python benches/poisson_structures.py [--json docs/poisson_structures.json]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

import poisson_rs as pr
from poisson_rs import scenes
from poisson_rs.files import atomic_write_bytes, check_output_path

ROOT = Path(__file__).resolve().parent.parent
SCENES = [ROOT / "scenes" / "lotka_volterra_pnn.toml", ROOT / "scenes" / "lotka_volterra_3d.toml"]
METHODS = [
    "taylor1",
    "taylor3",
    "taylor5",
    "rk4",
    "midpoint",
    "log_splitting",
    "log_splitting4",
]


def load_scene(path: Path) -> tuple[str, pr.LogCanonicalSystem, np.ndarray, float, int]:
    """(name, system, states (n, dim), h, n_steps) of a Lotka–Volterra scene TOML, read by
    :func:`poisson_rs.scenes.load_scene` (its checks: c antisymmetric, states in the orthant)."""
    scene = scenes.load_scene(path)
    h = scene.h[0]
    return scene.name, scene.lie_system, scene.states(), h, scene.n_steps(h)


def make(method: str, system: pr.LogCanonicalSystem) -> object:
    if method.startswith("taylor"):
        return pr.log_canonical_taylor(system, int(method.removeprefix("taylor")))
    return pr.log_canonical_classical(system, method)


def steps_per_second(stepper: object, x0: np.ndarray, h: float, n_steps: int) -> float:
    """Trajectory-steps a second over the scene's states tiled to 240 trajectories (enough work
    that the call's fixed cost does not count)."""
    x0 = np.tile(x0, (240 // len(x0), 1))
    best = np.inf
    for _ in range(3):
        start = time.perf_counter()
        pr.integrate(stepper, x0, h, n_steps)
        best = min(best, time.perf_counter() - start)
    return len(x0) * n_steps / best


def scene_rows(path: Path) -> list[dict[str, object]]:
    name, system, x0, h, n_steps = load_scene(path)
    times = h * np.arange(n_steps + 1)
    ref = pr.reference_solution(system, x0, times)
    h0 = system.hamiltonian(x0)
    c0 = system.casimirs(x0)
    rows: list[dict[str, object]] = []
    for method in METHODS:
        stepper = make(method, system)
        traj, info = pr.integrate(stepper, x0, h, n_steps, return_info=True, on_failure="ignore")
        err = np.abs(traj - ref).max(axis=-1)
        row: dict[str, object] = {
            "scene": name,
            "method": method,
            "converged": bool(info.converged.all()),
            "max_error": float(err.max()),
            "final_error": float(err[:, -1].max()),
            "max_energy_error": float(np.abs(system.hamiltonian(traj) - h0[:, None]).max()),
            "casimir_drift": (
                None if c0 is None else float(np.abs(system.casimirs(traj) - c0[:, None, :]).max())
            ),
            "steps_per_second": steps_per_second(stepper, x0, h, n_steps),
        }
        rows.append(row)
    return rows


def fitted_orders() -> list[dict[str, object]]:
    system = pr.lotka_volterra([[0.0, 1.0], [-1.0, 0.0]], [1.0, 2.0])
    x0 = np.array([[1.0, 0.8], [1.0, 1.2]])
    t_end = 2.0
    ref = pr.reference_solution(system, x0, [t_end])[:, -1]
    rows: list[dict[str, object]] = []
    for method in METHODS:
        hs, errs = [], []
        for n in (10, 20, 40):
            traj = pr.integrate(make(method, system), x0, t_end / n, n)
            hs.append(t_end / n)
            errs.append(float(np.abs(traj[:, -1] - ref).max()))
        slope = float(np.polyfit(np.log(hs), np.log(errs), 1)[0])
        rows.append({"method": method, "order": slope, "errors": errs, "h": hs})
    return rows


def casimir_drifts() -> list[dict[str, object]]:
    _, system, x0, h, _ = load_scene(SCENES[1])
    c0 = system.casimirs(x0)
    rows: list[dict[str, object]] = []
    for method in METHODS:
        traj = pr.integrate(make(method, system), x0, h, 10_000, every=10)
        drift = float(np.abs(system.casimirs(traj) - c0[:, None, :]).max())
        rows.append({"method": method, "casimir_drift_1e4_steps": drift})
    return rows


def approximate_realization() -> dict[str, object]:
    """The order-2 realization of a general polynomial π against the exact groupoid.

    1. Cubic Nambu bracket C = |x|²/2 + x₁³/3, H = x₁²/2 + x₂²/3 + x₃²/4, Taylor-HJ m = 1, 3:
       fitted global order (T = 1, h = 1/10, 1/20, 1/40, against DOP853) and the slope of the
       one-step Casimir defect over h = 0.2, 0.1, 0.05.
    2. The 3D log-canonical π = c_ij x_i x_j written as a polynomial bivector, H = x₁ + x₂ + x₃:
       Casimir drift over 1000 steps of h = 0.1 on the order-2 realization (NumPy) and on the
       exact groupoid (Rust), Taylor m = 3 on both.
    """
    from scipy.integrate import solve_ivp

    from poisson_rs.structures.polynomial import (
        PolynomialBivector,
        PolynomialPoissonSystem,
        RealizationTaylorIntegrator,
    )

    nambu = PolynomialPoissonSystem(
        PolynomialBivector.nambu("x1**2/2 + x2**2/2 + x3**2/2 + x1**3/3"),
        "x1**2/2 + x2**2/3 + x3**2/4",
    )
    x0 = np.array([[0.3, 0.5, -0.4], [0.1, -0.6, 0.3]])
    ref = np.array(
        [
            solve_ivp(
                lambda _t, y: nambu.vector_field(y[None])[0],
                (0.0, 1.0),
                y,
                method="DOP853",
                rtol=1e-13,
                atol=1e-13,
            ).y[:, -1]
            for y in x0
        ]
    )
    xr = np.random.default_rng(0).uniform(-0.6, 0.6, (10, 3))
    out: dict[str, object] = {"nambu": []}
    for m in (1, 3):
        integ = RealizationTaylorIntegrator(nambu, m, 2)
        errs = [
            np.abs(pr.integrate(integ, x0, 1.0 / n, n)[:, -1] - ref).max() for n in (10, 20, 40)
        ]
        hs = [0.2, 0.1, 0.05]
        defects = []
        for h in hs:
            c = nambu.casimirs(pr.integrate(integ, xr, h, 1))
            defects.append(float(np.abs(c[:, 1] - c[:, 0]).max()))
        out["nambu"].append(  # type: ignore[union-attr]
            {
                "m": m,
                "order": float(np.polyfit(np.log([0.1, 0.05, 0.025]), np.log(errs), 1)[0]),
                "casimir_defect_per_step": defects,
                "casimir_slope": float(np.polyfit(np.log(hs), np.log(defects), 1)[0]),
            }
        )
    c3 = [[0.0, 1.0, 1.0], [-1.0, 0.0, 1.0], [-1.0, -1.0, 0.0]]
    entries = {(i, j): f"{c3[i][j]}*x{i + 1}*x{j + 1}" for i in range(3) for j in range(i + 1, 3)}
    poly = PolynomialPoissonSystem(PolynomialBivector(3, entries), "x1 + x2 + x3")
    exact = pr.LogCanonicalSystem(
        pr.LogCanonical(c3), pr.LogPolynomial({(1, 0, 0): 1, (0, 1, 0): 1, (0, 0, 1): 1}, [0, 0, 0])
    )
    x0 = np.array([[1.2, 0.7, 1.6]])
    k = np.array([1.0, -1.0, 1.0])
    drifts = {}
    for label, stepper in (
        ("order-2 realization", RealizationTaylorIntegrator(poly, 3, 2)),
        ("exact groupoid", pr.log_canonical_taylor(exact, 3)),
    ):
        traj = pr.integrate(stepper, x0, 0.1, 1000)
        cas = np.log(traj) @ k
        drifts[label] = float(np.abs(cas - cas[..., :1]).max())
    out["log_canonical_casimir_drift_1000_steps"] = drifts
    return out


AFFINE_SCENE = ROOT / "scenes" / "extended_pendulum.toml"
AFFINE_METHODS = ["taylor1", "taylor3", "taylor5", "taylor7", "rk4", "midpoint"]


def affine_rows() -> list[dict[str, object]]:
    """The extended pendulum: fitted order, scene error, Casimir drift over 10⁴ steps, steps/s."""
    name, system, x0, h, n_steps = load_scene(AFFINE_SCENE)
    ref = pr.reference_solution(system, x0, h * np.arange(n_steps + 1))
    t_end = 2.0
    ref_t = pr.reference_solution(system, x0, [t_end])[:, -1]
    c0 = system.casimirs(x0)
    rows: list[dict[str, object]] = []
    for method in AFFINE_METHODS:
        if method.startswith("taylor"):
            stepper = pr.affine_taylor(system, int(method.removeprefix("taylor")))
        else:
            stepper = pr.affine_classical(system, method)
        hs, errs = [], []
        for n in (10, 20, 40):
            traj = pr.integrate(stepper, x0, t_end / n, n)
            hs.append(t_end / n)
            errs.append(float(np.abs(traj[:, -1] - ref_t).max()))
        traj = pr.integrate(stepper, x0, h, n_steps)
        long = pr.integrate(stepper, x0, h, 10_000, every=10)
        rows.append(
            {
                "scene": name,
                "method": f"{method}-exp" if method.startswith("taylor") else method,
                "order": float(np.polyfit(np.log(hs), np.log(errs), 1)[0]),
                "max_error": float(np.abs(traj - ref).max()),
                "casimir_drift_1e4_steps": float(
                    np.abs(system.casimirs(long) - c0[:, None, :]).max()
                ),
                "steps_per_second": steps_per_second(stepper, x0, h, n_steps),
            }
        )
    return rows


def fmt(v: object) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        return f"{v:.2e}"
    return str(v)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path, default=None, help="write all numbers here")
    args = ap.parse_args(argv)
    if args.json is not None:
        check_output_path(args.json)
    scenes = [row for path in SCENES for row in scene_rows(path)]
    print("| scene | method | max error | final error | max ΔH | Casimir drift | steps/s |")
    print("|---|---|---|---|---|---|---|")
    for r in scenes:
        print(
            f"| {r['scene']} | {r['method']} | {fmt(r['max_error'])} | {fmt(r['final_error'])} "
            f"| {fmt(r['max_energy_error'])} | {fmt(r['casimir_drift'])} "
            f"| {r['steps_per_second']:.3g} |",
            flush=True,
        )
    orders = fitted_orders()
    drifts = casimir_drifts()
    print("\n| method | fitted order (PNN, T = 2) | Casimir drift, 3D, 10⁴ steps |")
    print("|---|---|---|")
    for o, d in zip(orders, drifts, strict=True):
        print(f"| {o['method']} | {o['order']:.2f} | {fmt(d['casimir_drift_1e4_steps'])} |")
    approx = approximate_realization()
    print("\n| cubic Nambu, order-2 realization | fitted order | Casimir defect/step slope |")
    print("|---|---|---|")
    for r in approx["nambu"]:  # type: ignore[union-attr]
        print(f"| Taylor m = {r['m']} | {r['order']:.2f} | {r['casimir_slope']:.2f} |")
    for label, d in approx["log_canonical_casimir_drift_1000_steps"].items():  # type: ignore[union-attr]
        print(f"3D log-canonical, Taylor m = 3, {label}: Casimir drift over 1000 steps {d:.2e}")
    affine = affine_rows()
    print(
        "\n| extended pendulum (affine) | fitted order | max error, 200 steps | "
        "Casimir drift, 10⁴ steps | steps/s |"
    )
    print("|---|---|---|---|---|")
    for r in affine:
        print(
            f"| {r['method']} | {r['order']:.2f} | {fmt(r['max_error'])} "
            f"| {fmt(r['casimir_drift_1e4_steps'])} | {r['steps_per_second']:.3g} |"
        )
    if args.json is not None:
        doc = {
            "scenes": scenes,
            "fitted_orders": orders,
            "casimir_drifts": drifts,
            "approximate_realization": approx,
            "affine": affine,
        }
        atomic_write_bytes(args.json, (json.dumps(doc, indent=1) + "\n").encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())

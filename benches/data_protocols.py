"""The learned peers' rigid-body protocols (LocSympNets, Bajārs 2023), reproduced, with pr.learn
beside honest baselines.

Protocols (data generated as their code does: scipy RK45, rtol = atol = 1e-12):

- single trajectory: I = (2, 1, 2/3), y₀ = (cos 1.1, 0, sin 1.1), τ = 0.1, 120 pairs on
  t ∈ [0, 12]; predict 10⁴ steps; error |y(T) − y_exact(T)| at T = 1000 (exact: Jacobi elliptic
  functions);
- whole dynamics: 300 random points on the unit sphere, one step of τ = 0.1 each; 12 random test
  states, 1000 steps; error at T = 100 (max over the 12).

Methods: pr.learn mode "auto" and mode "map"; baselines: H fitted through RK4 and rolled out with
RK4 (the Hamiltonian-network recipe), SINDy (pysindy, polynomial library of degree 2, its own
differentiation, rolled out with DOP853; skipped with a message when pysindy is absent), and a
least-squares quadratic vector field from finite differences (order 8; the midpoint rule for
pairs) rolled out with DOP853. The noise study adds Gaussian noise of σ (relative to |y|) to every
record of the training data.

    python benches/data_protocols.py                 # both protocols, noise study, charts
    python benches/data_protocols.py --quick         # fewer map iterations, no charts

Writes docs/learning/protocols.json, noise.json, curves.csv and the charts (PNG).
"""

from __future__ import annotations

import argparse
import json
import math
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from scipy.integrate import solve_ivp
from scipy.optimize import least_squares

import poisson_rs as pr
from poisson_rs.learn.hamiltonian import vector_field_design, velocities
from poisson_rs.learn.series import monomials

torch.set_num_threads(1)

BODY = pr.RigidBody((2.0, 1.0, 2.0 / 3.0))
TAU = 0.1
OUT = Path(__file__).resolve().parents[1] / "docs" / "learning"

#: The peers' published figures (from their code and figures; see docs/learning.md).
PEERS = {
    "single": [
        ("LocSympNets", "0.35–0.42", "≤ 0.032", "thousands"),
        ("SymLocSympNets", "0.010–0.016", "≤ 0.0024", "thousands"),
    ],
    "whole": [
        ("LocSympNets", "0.6–0.75", "drifts to 0.065", "thousands"),
        ("SymLocSympNets", "0.035", "drifts to 0.003", "thousands"),
    ],
}


def rk45(y0: np.ndarray, times: np.ndarray) -> np.ndarray:
    """The peers' data generator: scipy RK45, rtol = atol = 1e-12. y0 (3,) → (len(times), 3)."""
    sol = solve_ivp(
        lambda t, y: BODY.vector_field(y),
        (times[0], times[-1]),
        y0,
        method="RK45",
        t_eval=times,
        rtol=1e-12,
        atol=1e-12,
    )
    return sol.y.T


def sphere(rng: np.random.Generator, m: int) -> np.ndarray:
    x = rng.normal(size=(m, 3))
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def single_data() -> tuple[list[np.ndarray], np.ndarray, float, int]:
    y0 = np.array([math.cos(1.1), 0.0, math.sin(1.1)])
    return [rk45(y0, TAU * np.arange(121))], y0[None, :], 1000.0, 10_000


def whole_data(seed: int = 0) -> tuple[list[np.ndarray], np.ndarray, float, int]:
    rng = np.random.default_rng(seed)
    starts = sphere(rng, 300)
    trajs = [rk45(y, np.array([0.0, TAU])) for y in starts]
    return trajs, sphere(rng, 12), 100.0, 1000


def add_noise(trajs: list[np.ndarray], sigma: float, seed: int) -> list[np.ndarray]:
    if sigma == 0:
        return trajs
    rng = np.random.default_rng(seed)
    return [
        t + sigma * np.linalg.norm(t, axis=1, keepdims=True) * rng.normal(size=t.shape)
        for t in trajs
    ]


# --- baselines ------------------------------------------------------------------------------------


def quadratic_system(theta: np.ndarray) -> pr.LiePoissonSystem:
    family = monomials(3, 2, min_degree=1)
    return pr.LiePoissonSystem(
        pr.LieAlgebra.so3(),
        pr.Polynomial({e: float(t) for e, t in zip(family, theta, strict=True)}),
    )


def lsq_field(trajs: list[np.ndarray]) -> tuple[np.ndarray, float]:
    """Least-squares quadratic H from finite-difference velocities (minimal norm)."""
    t0 = time.perf_counter()
    family = monomials(3, 2, min_degree=1)
    x, v = velocities(trajs, TAU)
    a = vector_field_design(pr.LieAlgebra.so3(), family, x).reshape(-1, len(family))
    theta, *_ = np.linalg.lstsq(a, v.reshape(-1), rcond=1e-10)
    return theta, time.perf_counter() - t0


def rk4_fit(trajs: list[np.ndarray], theta0: np.ndarray) -> tuple[np.ndarray, float]:
    """Quadratic H fitted so that one RK4 step of its vector field reproduces each pair."""
    t0 = time.perf_counter()
    family = monomials(3, 2, min_degree=1)
    algebra = pr.LieAlgebra.so3()
    mu0 = np.concatenate([t[:-1] for t in trajs])
    mu1 = np.concatenate([t[1:] for t in trajs])

    def field(theta: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.einsum("bjp,p->bj", vector_field_design(algebra, family, y), theta)

    def residual(theta: np.ndarray) -> np.ndarray:
        k1 = field(theta, mu0)
        k2 = field(theta, mu0 + 0.5 * TAU * k1)
        k3 = field(theta, mu0 + 0.5 * TAU * k2)
        k4 = field(theta, mu0 + TAU * k3)
        return (mu0 + TAU / 6 * (k1 + 2 * k2 + 2 * k3 + k4) - mu1).ravel()

    sol = least_squares(residual, theta0, xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return sol.x, time.perf_counter() - t0


def sindy_fit(trajs: list[np.ndarray]):
    try:
        import pysindy as ps
    except ImportError:
        print("pysindy is not installed (pip install 'poisson_rs[bench]'): SINDy skipped")
        return None, math.nan
    t0 = time.perf_counter()
    model = ps.SINDy(
        optimizer=ps.STLSQ(threshold=1e-3), feature_library=ps.PolynomialLibrary(degree=2)
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if min(len(t) for t in trajs) < 3:
            # Pairs are too short for SINDy's own differentiation: the midpoint rule, second
            # order, as the least-squares baseline uses.
            x = np.concatenate([0.5 * (t[:-1] + t[1:]) for t in trajs])
            xdot = np.concatenate([np.diff(t, axis=0) / TAU for t in trajs])
            model.fit(x, t=TAU, x_dot=xdot)
        else:
            model.fit(trajs, t=TAU)
    return model, time.perf_counter() - t0


def dop853(rhs, y0: np.ndarray, times: np.ndarray) -> np.ndarray:
    out = []
    for y in y0:
        sol = solve_ivp(
            lambda t, z: rhs(z),
            (0.0, times[-1]),
            y,
            method="DOP853",
            t_eval=times,
            rtol=1e-13,
            atol=1e-13,
        )
        out.append(sol.y.T if sol.success else np.full((len(times), 3), np.nan))
    return np.stack(out)


# --- metrics --------------------------------------------------------------------------------------


def metrics(traj: np.ndarray, exact: np.ndarray) -> dict[str, float]:
    """traj, exact: (m, records, 3). Error at the last record (max over states) and the max
    relative energy (true H) and Casimir errors along the way."""
    err = np.linalg.norm(traj - exact, axis=-1)
    e0 = BODY.hamiltonian(traj[:, :1])
    c0 = np.sum(traj[:, :1] ** 2, -1)
    with np.errstate(invalid="ignore"):
        de = np.abs(BODY.hamiltonian(traj) - e0) / np.abs(e0)
        dc = np.abs(np.sum(traj**2, -1) - c0) / c0
    return {
        "error_T": float(np.max(err[:, -1])),
        "energy": float(np.max(de)),
        "casimir": float(np.max(dc)),
        "curve_error": np.max(err, axis=0),
        "curve_casimir": np.max(dc, axis=0),
    }


def run_protocol(
    name: str, trajs, tests, horizon, n_steps, *, map_steps, sigma=0.0, seed=0, methods=None
):
    trajs = add_noise(trajs, sigma, seed + 1)
    every = max(1, n_steps // 200)
    times = TAU * np.arange(0, n_steps + 1, every)
    exact = pr.exact_solution(BODY, tests, times)
    exact = exact[None] if exact.ndim == 2 else exact
    rows = {}
    methods = methods or ("auto", "map", "map-mlp", "rk4-fit", "sindy", "lsq+dop853")

    def record(method, traj, params, seconds, extra=""):
        m = metrics(traj, exact)
        m.update({"parameters": params, "seconds": seconds, "note": extra})
        rows[method] = m
        print(
            f"  {name:<6} σ={sigma:<6g} {method:<11} err@T {m['error_T']:.2e}  "
            f"ΔE {m['energy']:.1e}  ΔC {m['casimir']:.1e}  params {params}  {seconds:.1f} s"
        )

    if "auto" in methods:
        t0 = time.perf_counter()
        stepper, report = pr.learn(trajs, TAU, algebra="so3", mode="auto", seed=seed)
        seconds = time.perf_counter() - t0
        print(report)
        traj = pr.integrate(stepper, tests, TAU, n_steps, every=every)
        record(
            "auto", traj.reshape(exact.shape), report.kept.parameters, seconds, report.kept.family
        )
    if "map" in methods:
        t0 = time.perf_counter()
        stepper, report = pr.learn(trajs, TAU, algebra="so3", mode="map", seed=seed)
        seconds = time.perf_counter() - t0
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            traj = pr.integrate(stepper, tests, TAU, n_steps, every=every, on_failure="ignore")
        record(
            "map", traj.reshape(exact.shape), report.kept.parameters, seconds, report.kept.family
        )
    if "map-mlp" in methods:
        t0 = time.perf_counter()
        stepper, report = pr.learn(
            trajs,
            TAU,
            algebra="so3",
            mode="map",
            seed=seed,
            map_options={"kind": "network", **map_steps},
        )
        seconds = time.perf_counter() - t0
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            traj = pr.integrate(stepper, tests, TAU, n_steps, every=every, on_failure="ignore")
        record("map-mlp", traj.reshape(exact.shape), report.kept.parameters, seconds)
    theta_lsq, t_lsq = lsq_field(trajs)
    if "rk4-fit" in methods:
        theta, seconds = rk4_fit(trajs, theta_lsq)
        stepper = pr.classical(quadratic_system(theta), "rk4")
        traj = pr.integrate(stepper, tests, TAU, n_steps, every=every)
        record("rk4-fit", traj.reshape(exact.shape), 9, seconds)
    if "sindy" in methods:
        model, seconds = sindy_fit(trajs)
        if model is not None:
            coef = model.coefficients()
            traj = dop853(lambda z: model.predict(z[None])[0], tests, times)
            record("sindy", traj, int(np.count_nonzero(coef)), seconds)
    if "lsq+dop853" in methods:
        system = quadratic_system(theta_lsq)
        traj = dop853(system.vector_field, tests, times)
        record("lsq+dop853", traj, 9, t_lsq)
    return rows, times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--no-noise", action="store_true")
    parser.add_argument(
        "--noise-seeds",
        type=int,
        default=0,
        help="only re-run auto's rows (and the single trajectory's noisy baselines) over this "
        "many noise draws, patching the JSON files",
    )
    parser.add_argument("--heavy-top", action="store_true", help="only the heavy-top protocol")
    parser.add_argument(
        "--map-only",
        action="store_true",
        help="only re-run mode map's rows (polynomial S); the MLP rows move to 'map-mlp'",
    )
    parser.add_argument(
        "--lotka-volterra", action="store_true", help="only PNN's Lotka–Volterra protocol"
    )
    args = parser.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    if args.lotka_volterra:
        lotka_volterra_protocol()
        return
    if args.map_only:
        protocols = json.loads((OUT / "protocols.json").read_text())
        for name, make in (("single", single_data), ("whole", whole_data)):
            trajs, tests, horizon, n_steps = make()
            rows, _ = run_protocol(
                name, trajs, tests, horizon, n_steps, map_steps={}, methods=("map",)
            )
            old = protocols[name].pop("map", None)
            protocols[name]["map"] = {
                f: v for f, v in rows["map"].items() if not f.startswith("curve")
            }
            if old is not None and "map-mlp" not in protocols[name]:
                protocols[name]["map-mlp"] = old
        (OUT / "protocols.json").write_text(json.dumps(protocols, indent=1))
        print_tables(protocols, {})
        return
    if args.heavy_top:
        heavy_top_protocol()
        return
    if args.noise_seeds:
        noise_seeds(args.noise_seeds)
        return
    map_steps = (
        {"adam_steps": 60, "lbfgs_steps": 20}
        if args.quick
        else {"adam_steps": 150, "lbfgs_steps": 100}
    )
    results = {}
    curves = {}
    for name, make in (("single", single_data), ("whole", whole_data)):
        trajs, tests, horizon, n_steps = make()
        rows, times = run_protocol(name, trajs, tests, horizon, n_steps, map_steps=map_steps)
        results[name] = rows
        curves[name] = (times, rows)
    noise = {}
    if not args.no_noise:
        for sigma in (1e-6, 1e-4, 1e-2):
            for name, make in (("single", single_data), ("whole", whole_data)):
                trajs, tests, horizon, n_steps = make()
                rows, _ = run_protocol(
                    name,
                    trajs,
                    tests,
                    horizon,
                    n_steps,
                    sigma=sigma,
                    map_steps=map_steps,
                    methods=("auto", "rk4-fit", "sindy", "lsq+dop853"),
                )
                noise[f"{name}/{sigma:g}"] = rows
        for name in ("single", "whole"):
            noise[f"{name}/0"] = {k: v for k, v in results[name].items() if k != "map"}

    def clean(rows):
        return {
            k: {f: v for f, v in r.items() if not f.startswith("curve")} for k, r in rows.items()
        }

    (OUT / "protocols.json").write_text(
        json.dumps({k: clean(v) for k, v in results.items()}, indent=1)
    )
    (OUT / "noise.json").write_text(json.dumps({k: clean(v) for k, v in noise.items()}, indent=1))
    with open(OUT / "curves.csv", "w", encoding="utf-8") as fh:
        fh.write("protocol,method,t,error,casimir\n")
        for name, (times, rows) in curves.items():
            for method, r in rows.items():
                for t, e, c in zip(times, r["curve_error"], r["curve_casimir"], strict=True):
                    fh.write(f"{name},{method},{t:.6g},{e:.6e},{c:.6e}\n")
    print_tables(results, noise)
    if not args.quick:
        charts(curves, noise)


def noise_seeds(n_seeds: int) -> None:
    """Re-runs pr.learn auto's rows (and, on the single trajectory, the RK4-fit and LSQ rows)
    with ``n_seeds`` noise draws, and patches those rows of protocols.json and noise.json (the
    other rows stay as the full run left them). One draw of noise on one trajectory is a poor
    sample: the error at T = 1000 of every method moves by 5× between draws, so the single
    trajectory's rows report the median over the draws (and keep every draw)."""
    protocols = json.loads((OUT / "protocols.json").read_text())
    noise = json.loads((OUT / "noise.json").read_text())
    for name, make in (("single", single_data), ("whole", whole_data)):
        for sigma in (0.0, 1e-6, 1e-4, 1e-2):
            trajs, tests, horizon, n_steps = make()
            methods = ("auto", "rk4-fit", "lsq+dop853") if name == "single" and sigma else ("auto",)
            draws = range(1, n_seeds + 1) if name == "single" and sigma else (1,)
            runs = [
                run_protocol(
                    name,
                    trajs,
                    tests,
                    horizon,
                    n_steps,
                    sigma=sigma,
                    seed=d - 1,
                    map_steps={},
                    methods=methods,
                )[0]
                for d in draws
            ]
            key = f"{name}/{sigma:g}"
            for method in methods:
                rows = [r[method] for r in runs]
                errs = [r["error_T"] for r in rows]
                med = rows[int(np.argsort(errs)[len(errs) // 2])]
                row = {f: v for f, v in med.items() if not f.startswith("curve")}
                if len(rows) > 1:
                    row["error_T"] = float(np.median(errs))
                    row["error_T_draws"] = errs
                    row["note"] = f"{row['note']} median of {len(rows)} noise draws".strip()
                noise.setdefault(key, {})[method] = row
                if sigma == 0:
                    protocols[name][method] = row
    (OUT / "protocols.json").write_text(json.dumps(protocols, indent=1))
    (OUT / "noise.json").write_text(json.dumps(noise, indent=1))
    print_tables(protocols, noise)
    noise_chart(noise)


def heavy_top_data(
    n_traj: int = 40, records: int = 11, n_test: int = 6, seed: int = 0
) -> tuple[list[np.ndarray], np.ndarray]:
    """The heavy-top protocol's training trajectories and hidden test states (see
    :func:`heavy_top_protocol`)."""
    top = pr.HeavyTop()
    rng = np.random.default_rng(seed)

    def states(m: int) -> np.ndarray:
        g = sphere(rng, m)
        return np.concatenate([rng.normal(size=(m, 3)), g], 1)

    trajs = list(pr.reference_solution(top, states(n_traj), TAU * np.arange(records)))
    return trajs, states(n_test)


def heavy_top_protocol(n_traj: int = 40, records: int = 11, n_test: int = 6, seed: int = 0):
    """Heavy top (DPNN's I = (1, 1.5, 2), mgl = 0.981, χ = e₃), in the spirit of the whole-dynamics
    protocol: ``n_traj`` short trajectories (``records`` records h = 0.1 apart, tight DOP853)
    from random (M, Γ), M ~ N(0, 1)³, |Γ| = 1; ``n_test`` hidden random test states rolled out to
    T = 10 and 100. Methods: pr.learn auto, and the least-squares quadratic vector field
    (order-8 finite differences) rolled out with DOP853. Writes docs/learning/heavy_top.json."""
    top = pr.HeavyTop()
    trajs, tests = heavy_top_data(n_traj, records, n_test, seed)
    times = TAU * np.arange(0, 1001, 5)
    exact = pr.reference_solution(top, tests, times)
    at = {10.0: np.argmin(np.abs(times - 10.0)), 100.0: len(times) - 1}

    def score(traj: np.ndarray) -> dict[str, float]:
        err = np.linalg.norm(traj - exact, axis=-1)
        c = np.asarray(top.casimirs(traj))  # (m, records, 2)
        dc = np.abs(c - c[:, :1]) / np.maximum(np.abs(c[:, :1]), 1.0)
        e = top.hamiltonian(traj)
        de = np.abs(e - e[:, :1]) / np.maximum(np.abs(e[:, :1]), 1e-300)
        return {
            "error_10": float(np.max(err[:, at[10.0]])),
            "error_100": float(np.max(err[:, at[100.0]])),
            "energy": float(np.max(de)),
            "casimir": float(np.max(dc)),
        }

    rows = {}
    t0 = time.perf_counter()
    stepper, report = pr.learn(trajs, TAU, algebra="se3", mode="auto", seed=seed)
    seconds = time.perf_counter() - t0
    print(report)
    traj = pr.integrate(stepper, tests, TAU, 1000, every=5)
    rows["auto"] = {
        **score(traj),
        "parameters": report.kept.parameters,
        "seconds": seconds,
        "note": report.kept.family,
    }
    # The floor: the true H through the same integrator (Taylor-HJ, the order auto used).
    floor = pr.taylor_integrator(top, report.kept.order, "exp")
    rows["true H, same integrator"] = {
        **score(pr.integrate(floor, tests, TAU, 1000, every=5)),
        "parameters": 0,
        "seconds": 0.0,
        "note": f"K = {report.kept.order}",
    }
    # The learned H integrates at any order and h: the same H through Taylor-HJ K = 7.
    finer = pr.taylor_integrator(report.system, 7, "exp")
    rows["auto's H, Taylor-HJ K = 7"] = {
        **score(pr.integrate(finer, tests, TAU, 1000, every=5)),
        "parameters": report.kept.parameters,
        "seconds": seconds,
        "note": "",
    }
    t0 = time.perf_counter()
    family = monomials(6, 2, min_degree=1)
    x, v = velocities(trajs, TAU)
    a = vector_field_design(pr.LieAlgebra.se3(), family, x).reshape(-1, len(family))
    theta, *_ = np.linalg.lstsq(a, v.reshape(-1), rcond=1e-10)
    seconds = time.perf_counter() - t0
    lsq = pr.LiePoissonSystem(
        pr.LieAlgebra.se3(),
        pr.Polynomial({e: float(c) for e, c in zip(family, theta, strict=True)}),
    )
    out = []
    for y in tests:
        sol = solve_ivp(
            lambda t, z: lsq.vector_field(z),
            (0.0, times[-1]),
            y,
            method="DOP853",
            t_eval=times,
            rtol=1e-13,
            atol=1e-13,
        )
        out.append(sol.y.T if sol.success else np.full((len(times), 6), np.nan))
    rows["lsq+dop853"] = {
        **score(np.stack(out)),
        "parameters": len(family),
        "seconds": seconds,
        "note": "",
    }
    for k, r in rows.items():
        print(
            f"| {k} {r['note']} | {r['error_10']:.2e} | {r['error_100']:.2e} | {r['energy']:.1e} "
            f"| {r['casimir']:.1e} | {r['parameters']} | {r['seconds']:.1f} |"
        )
    (OUT / "heavy_top.json").write_text(json.dumps(rows, indent=1))


def lotka_volterra_protocol() -> None:
    """PNN's Lotka–Volterra (c = [[0, 1], [−1, 0]], H = u − ln u + v − 2 ln v; their states
    (1, 0.8), (1, 1), (1, 1.2), h = 0.1): one trajectory of 101 records (t ∈ [0, 10]) from each
    of their states for training; hidden test states (1, 0.9), (1, 1.1), (0.8, 1) rolled out to
    T = 10 and 100. H = Σ (a_i x_i − b_i ln x_i) fitted by least squares on the vector field in
    log coordinates, then refined through the integrator
    (:func:`poisson_rs.learn.log_canonical.fit_lotka_volterra`), integrated by log-canonical
    Taylor-HJ K = 3 and 5; beside each the true H through the same integrator. Reference:
    DOP853 in ln x, rtol = atol = 1e-13. Writes docs/learning/lotka_volterra.json."""
    from poisson_rs.learn.log_canonical import fit_lotka_volterra

    c = [[0.0, 1.0], [-1.0, 0.0]]
    lv = pr.lotka_volterra(c, [1.0, 2.0])
    reference = pr.classical(lv, "dop853", tol=1e-13)
    train = np.array([[1.0, 0.8], [1.0, 1.0], [1.0, 1.2]])
    tests = np.array([[1.0, 0.9], [1.0, 1.1], [0.8, 1.0]])
    trajs = list(pr.integrate(reference, train, TAU, 100))
    exact = pr.integrate(reference, tests, TAU, 1000)
    rows = {}

    def score(traj: np.ndarray) -> dict[str, float]:
        err = np.linalg.norm(traj - exact, axis=-1)
        e = lv.hamiltonian(traj)
        return {
            "error_10": float(np.max(err[:, 100])),
            "error_100": float(np.max(err[:, 1000])),
            "energy": float(np.max(np.abs(e - e[:, :1]) / np.abs(e[:, :1]))),
        }

    for order in (3, 5):
        for through in (False, True):
            how = "through the integrator" if through else "vector field (lsq, log coords)"
            fit = fit_lotka_volterra(trajs, TAU, c, order=order, through_integrator=through)
            rows[f"{how} + Taylor-HJ K = {order}"] = {
                **score(pr.integrate(fit.stepper, tests, TAU, 1000)),
                "parameters": fit.n_parameters,
                "seconds": fit.seconds,
                "a": fit.a.tolist(),
                "b": fit.b.tolist(),
            }
        floor = pr.taylor_integrator(lv, order)
        rows[f"true H, Taylor-HJ K = {order}"] = {
            **score(pr.integrate(floor, tests, TAU, 1000)),
            "parameters": 0,
            "seconds": 0.0,
        }
    for k, r in rows.items():
        print(
            f"| {k} | {r['error_10']:.2e} | {r['error_100']:.2e} | {r['energy']:.1e} | "
            f"{r['parameters']} | {r['seconds']:.3f} |"
        )
    (OUT / "lotka_volterra.json").write_text(json.dumps(rows, indent=1))


def print_tables(results, noise) -> None:
    for name in ("single", "whole"):
        t_label = "T = 1000" if name == "single" else "T = 100"
        print(f"\n{name}: error at {t_label} | max rel. energy | max rel. Casimir | params | s")
        for peer, err, cas, params in PEERS[name]:
            print(f"| {peer} (published) | {err} | n/a | {cas} | {params} | n/a |")
        for method, r in results[name].items():
            print(
                f"| {method} {r['note']} | {r['error_T']:.2e} | {r['energy']:.1e} | "
                f"{r['casimir']:.1e} | {r['parameters']} | {r['seconds']:.1f} |"
            )
    if noise:
        print("\nnoise study: error at T (protocol/σ × method)")
        methods = ("auto", "rk4-fit", "sindy", "lsq+dop853")
        print("| protocol | σ | " + " | ".join(methods) + " |")
        for key in sorted(noise, key=lambda k: (k.split("/")[0], float(k.split("/")[1]))):
            name, sigma = key.split("/")
            cells = [
                f"{noise[key][m]['error_T']:.2e}" if m in noise[key] else "n/a" for m in methods
            ]
            print(f"| {name} | {sigma} | " + " | ".join(cells) + " |")


def charts(curves, noise) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for what, label in (
        ("curve_error", "error |y − y_exact|"),
        ("curve_casimir", "relative Casimir error"),
    ):
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        for ax, (name, (times, rows)) in zip(axes, curves.items(), strict=True):
            for method, r in rows.items():
                ax.semilogy(times[1:], np.maximum(r[what][1:], 1e-17), label=method)
            ax.set_title(f"{name} protocol")
            ax.set_xlabel("t")
            ax.set_ylabel(label)
            ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(OUT / f"{what.removeprefix('curve_')}_vs_time.png", dpi=110)
        plt.close(fig)
    noise_chart(noise)


def noise_chart(noise) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, name in zip(axes, ("single", "whole"), strict=True):
        keys = sorted(
            (k for k in noise if k.startswith(name)), key=lambda k: float(k[len(name) + 1 :])
        )
        sig = [max(float(k.split("/")[1]), 1e-8) for k in keys]
        for method in ("auto", "rk4-fit", "sindy", "lsq+dop853"):
            ys = [noise[k][method]["error_T"] if method in noise[k] else np.nan for k in keys]
            ax.loglog(sig, ys, "o-", label=method)
        ax.set_title(f"{name}: error at T vs noise (σ = 0 drawn at 1e-8)")
        ax.set_xlabel("σ (relative)")
        ax.set_ylabel("error at T")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "error_vs_noise.png", dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()

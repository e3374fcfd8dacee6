"""Work–precision for the heavy top: error, energy error and Casimir drift against measured cost.

The scenes are those of ``scenes/heavy_top.toml`` (six states to T = 10),
``scenes/heavy_top_long.toml`` (three states to T = 1000) and ``scenes/heavy_top_learned.toml``
(eight held-out states in the shipped model's domain, to T = 10). Every method runs behind the same
:func:`~poisson_rs.integrate`; one row per method and step (or DOP853 tolerance) records

- ``error_T``: max over states of |μ(T) − μ_ref(T)| / |μ₀| (μ_ref: DOP853, rtol = atol = 1e-13);
- ``max_rel_dH``: max over states and recorded times of |H − H₀| / |H₀|;
- ``max_dC``: max over states, recorded times and the Casimirs |Γ|², M·Γ of |C − C₀| / |μ₀|²;
- ``seconds_per_traj``: best wall time of ``integrate`` on all the states, over the state count;
- ``extrapolated``: a learned model's run left its training domain (drawn with open markers).

Rows use the keys of :mod:`poisson_rs.workprecision` so :func:`~poisson_rs.charts.
work_precision_figure` draws them. Run ``python -m poisson_rs.heavytop_chart --out docs``.
"""

from __future__ import annotations

import argparse
import math
import os
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from .integrators import (
    Stepper,
    classical,
    integrate,
    shipped_models,
    taylor_integrator,
)
from .reference import reference_solution
from .scenes import load_scene
from .systems import LiePoissonSystem

Row = dict[str, Any]
#: Where the scene files are (run from the repository root).
SCENES = Path("scenes")
#: Step counts per scene (coarse to fine): h = 1 … 1/256 at T = 10, h = 1 … 1/16 at T = 1000.
STEPS = {
    "heavy_top": tuple(10 * 2**k for k in range(9)),
    "heavy_top_long": (1000, 4000, 16000),
    "heavy_top_learned": tuple(10 * 2**k for k in range(9)),
}
DOP853_TOLERANCES = {
    "heavy_top": tuple(10.0**-k for k in range(4, 12)),
    "heavy_top_long": (1e-6, 1e-9),
    "heavy_top_learned": tuple(10.0**-k for k in range(4, 12)),
}
#: DOP853's output spacing (its h only samples the output).
DOP853_SPACING = {"heavy_top": 0.1, "heavy_top_long": 1.0, "heavy_top_learned": 0.1}
#: Every scene, in the order they run.
SCENE_NAMES = ("heavy_top", "heavy_top_long", "heavy_top_learned")
ORDERS = (1, 3, 5, 7)


def _methods(system: LiePoissonSystem) -> dict[str, tuple[str, Stepper]]:
    """Taylor-exp K = 1…7, the classical methods, and the shipped learned models trained for
    ``system`` (a model of another system would be scored against the wrong flow)."""
    out = {f"taylor{k}-exp": ("taylor", taylor_integrator(system, k, "exp")) for k in ORDERS}
    for name in ("rk4", "midpoint", "splitting"):
        out[name] = ("classical", classical(system, name))
    for name, model in shipped_models(system).items():
        out[f"learned:{name}"] = ("learned", model)
    return out


def _steps(stepper: Stepper, counts: tuple[int, ...], T: float) -> tuple[int, ...]:
    """The step counts a method runs: all of them, but for a learned model only those whose
    h = T/n it was trained for (h ≤ h_max)."""
    h_max = getattr(stepper, "h_max", math.inf)
    return tuple(n for n in counts if T / n <= h_max * (1 + 1e-12))


def _timed(stepper: Stepper, mu0: np.ndarray, h: float, n: int, every: int) -> tuple[Any, float]:
    """The rollout (with info) and its wall time, best of several calls while short."""

    def call() -> Any:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            return integrate(stepper, mu0, h, n, every=every, return_info=True, on_failure="ignore")

    t0 = time.perf_counter()
    out = call()
    best = total = time.perf_counter() - t0
    count = 1
    while best < 0.05 and total < 0.3 and count < 20:
        t0 = time.perf_counter()
        call()
        dt = time.perf_counter() - t0
        best, total, count = min(best, dt), total + dt, count + 1
    return out, best


def _row(
    scene: str,
    system: LiePoissonSystem,
    method: str,
    family: str,
    mu0: np.ndarray,
    ref: np.ndarray,
    traj: np.ndarray,
    info: Any,
    seconds: float,
    T: float,
    h: float,
    n: int,
    tol: float | None,
) -> Row:
    """One work–precision row. traj: (n_states, records, dim); ref: (n_states, dim) at T."""
    norm = np.linalg.norm(mu0, axis=1)
    failed = bool((~info.converged).any() or not np.isfinite(traj).all())
    row: Row = {
        "scene": scene,
        "method": method,
        "family": family,
        "h": h,
        "tol": tol,
        "n_steps": n,
        "n_states": len(mu0),
        "T": T,
        "error_T": None,
        "max_rel_dH": None,
        "max_dC": None,
        "max_d_gamma2": None,
        "max_d_m_dot_gamma": None,
        "failed": failed,
        # Recorded states outside a learned model's training domain (none for other methods).
        "extrapolated": bool(info.out_of_domain.any()),
        "seconds_per_traj": seconds / len(mu0),
        "seconds": seconds,
    }
    if failed:
        return row
    h0 = system.hamiltonian(mu0)
    c0 = system.casimirs(mu0)
    dh = np.abs(system.hamiltonian(traj) - h0[:, None]) / np.abs(h0)[:, None]
    dc = np.abs(system.casimirs(traj) - c0[:, None, :]) / (norm**2)[:, None, None]
    row.update(
        error_T=float((np.linalg.norm(traj[:, -1] - ref, axis=1) / norm).max()),
        max_rel_dH=float(dh.max()),
        max_dC=float(dc.max()),
        max_d_gamma2=float(dc[..., 0].max()),
        max_d_m_dot_gamma=float(dc[..., 1].max()),
    )
    return row


def run(scenes: tuple[str, ...] = SCENE_NAMES, *, log: Callable[[str], None] = print) -> list[Row]:
    """Every method and step on each scene; rows as documented in the module docstring."""
    rows: list[Row] = []
    for name in scenes:
        scene = load_scene(SCENES / f"{name}.toml")
        system, mu0, T = scene.lie_system, scene.states(), scene.horizon
        t0 = time.perf_counter()
        ref = reference_solution(system, mu0, [T])[:, 0]
        log(f"{name}: reference to T = {T:g} in {time.perf_counter() - t0:.0f} s")
        for method, (family, stepper) in _methods(system).items():
            for n in _steps(stepper, STEPS[name], T):
                # Energy and Casimirs sampled on ≤ ~2000 records (every step at T = 10).
                every = max(1, n // 2000)
                (traj, info), sec = _timed(stepper, mu0, T / n, n, every)
                rows.append(
                    _row(name, system, method, family, mu0, ref, traj, info, sec, T, T / n, n, None)
                )
            last = rows[-1]
            log(f"{name}: {method} error {last['error_T']} at h = {last['h']:g}")
        n_out = round(T / DOP853_SPACING[name])
        for tol in DOP853_TOLERANCES[name]:
            stepper = classical(system, "dop853", tol=tol)
            (traj, info), sec = _timed(stepper, mu0, T / n_out, n_out, 1)
            rows.append(
                _row(
                    name,
                    system,
                    "dop853",
                    "adaptive",
                    mu0,
                    ref,
                    traj,
                    info,
                    sec,
                    T,
                    T / n_out,
                    n_out,
                    tol,
                )
            )
        log(f"{name}: dop853 done ({time.perf_counter() - t0:.0f} s)")
    return rows


def figures(rows: list[Row], out: Path) -> list[Path]:
    """The error, energy and Casimir charts (PNG) from ``rows``, one file per scene (the panels
    of one figure share their y axis, and T = 1000 errors are O(1))."""
    from .charts import work_precision_figure

    sys_name = "heavy top I = (1, 1.5, 2), mgl = 0.981, χ = (0, 0, 1)"
    specs = (
        ("error_T", "max |μ(T) − μ_ref(T)| / |μ₀|", "error", "Error at T against cost"),
        ("max_rel_dH", "max |H − H₀| / |H₀| over [0, T]", "energy", "Energy error against cost"),
        ("max_dC", "max |C − C₀| / |μ₀|², C = |Γ|², M·Γ", "casimirs", "Casimir drift against cost"),
    )
    paths = []
    for scene in dict.fromkeys(r["scene"] for r in rows):
        srows = [r for r in rows if r["scene"] == scene]
        for metric, ylabel, stem, title in specs:
            path = out / f"{scene}_{stem}.png"
            levels = (1e-3, 1e-6, 1e-9) if metric == "error_T" else ()
            work_precision_figure(
                srows, path, metric=metric, ylabel=ylabel, title=f"{title}: {sys_name}",
                levels=levels,
            )  # fmt: skip
            paths.append(path)
    return paths


def main(argv: list[str] | None = None) -> int:
    from .charts import write_rows

    p = argparse.ArgumentParser(prog="python -m poisson_rs.heavytop_chart", description=__doc__)
    p.add_argument("--out", default="out/heavy_top", help="output folder")
    p.add_argument("--threads", type=int, default=1, help="rayon threads (default 1)")
    p.add_argument("--short", action="store_true", help="the T = 10 scenes only")
    p.add_argument("--replot", metavar="JSON", help="redraw the charts from saved rows")
    args = p.parse_args(argv)
    if args.replot is not None:
        import json

        for path in figures(json.loads(Path(args.replot).read_text()), Path(args.out)):
            print(f"wrote {path}")
        return 0
    # One rayon thread: cost per trajectory on one core, as DOP853 (SciPy) runs anyway.
    os.environ.setdefault("RAYON_NUM_THREADS", str(args.threads))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows = run(("heavy_top", "heavy_top_learned") if args.short else SCENE_NAMES)
    write_rows(rows, out / "heavy_top_workprecision.csv")
    for path in figures(rows, out):
        print(f"wrote {path}")
    print(f"wrote {out}/heavy_top_workprecision.csv/json in {time.perf_counter() - t0:.0f} s")
    return 0 if all(math.isfinite(r["seconds"]) for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())

"""Order-n approximate realizations of a polynomial bivector: what each order buys.

On the cubic Nambu bracket C = |x|²/2 + x₁³/3 with H = x₁²/2 + x₂²/3 + x₃²/4
(``scenes/nambu_cubic.toml``), for Taylor-HJ order m on the order-n realization
(``RealizationTaylorIntegrator(system, m, n)``):

- the fitted global order (slope of log error against log h at T = 1 from h = 1/4, 1/8, 1/16 on
  the scene's two states, against DOP853 at rtol = atol = 1e-13; the last pair is dropped where
  the error has reached 1e-13);
- the error at h = 1/16;
- the slope of the one-step Casimir defect max |C(x₁) − C(x₀)| over h = 0.4, 0.2, 0.1 on ten
  seeded states in [−0.6, 0.6]³;
- the time to derive the integrator with sympy (realization terms are cached per bivector, so
  each row counts only what it adds).

Then the 3D log-canonical bracket π_ij = c_ij x_i x_j written as a polynomial bivector (H = x₁ +
x₂ + x₃, Taylor m = 3, 1000 steps of h = 0.1 from (1.2, 0.7, 1.6)): the drift of its Casimir
ln(x₁x₃/x₂) on the order-2 and order-3 realizations against the exact groupoid (Rust).

Last, steps/s of the core's rollout against the NumPy oracle (``RealizationTaylorIntegrator.step``,
the same Newton bisection on lambdified sympy) on 64 states × 20 steps of h = 0.1, best of 3.

Writes a PNG (error against h, Casimir defect against h) and the raw numbers as JSON.

Usage: ``python benches/realization_orders.py --out docs/realization_orders`` (about a minute).
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import time
from pathlib import Path

import numpy as np

import poisson_rs as pr
from poisson_rs.files import atomic_write_bytes, check_output_path
from poisson_rs.structures.polynomial import (
    PolynomialBivector,
    PolynomialPoissonSystem,
    RealizationTaylorIntegrator,
)

CASIMIR = "x1**2/2 + x2**2/2 + x3**2/2 + x1**3/3"
HAMILTONIAN = "x1**2/2 + x2**2/3 + x3**2/4"
#: (m, n): Taylor-HJ order on the order-n realization.
PAIRS = [(1, 2), (3, 2), (1, 3), (3, 3), (3, 4), (5, 4), (5, 5), (5, 6)]
STEPS = (4, 8, 16)
CASIMIR_STEPS = (0.4, 0.2, 0.1)


def reference(system: PolynomialPoissonSystem, x0: np.ndarray, t: float) -> np.ndarray:
    return pr.reference_solution(system, x0, [t])[:, 0]


def nambu_rows() -> list[dict[str, object]]:
    system = PolynomialPoissonSystem(PolynomialBivector.nambu(CASIMIR), HAMILTONIAN)
    x0 = np.array([[0.3, 0.5, -0.4], [0.1, -0.6, 0.3]])
    ref = reference(system, x0, 1.0)
    xr = np.random.default_rng(0).uniform(-0.6, 0.6, (10, 3))
    rows = []
    for m, n in PAIRS:
        start = time.perf_counter()
        integ = RealizationTaylorIntegrator(system, m, n)
        build = time.perf_counter() - start
        errs = [
            float(np.abs(pr.integrate(integ, x0, 1.0 / k, k)[:, -1] - ref).max()) for k in STEPS
        ]
        hs = [1.0 / k for k in STEPS]
        keep = [i for i, e in enumerate(errs) if e > 1e-13] or [0, 1]
        keep = keep if len(keep) >= 2 else [0, 1]
        order = float(
            np.polyfit(np.log([hs[i] for i in keep]), np.log([errs[i] for i in keep]), 1)[0]
        )
        defects = []
        for h in CASIMIR_STEPS:
            c = system.casimirs(pr.integrate(integ, xr, h, 1))
            defects.append(float(np.abs(c[:, 1] - c[:, 0]).max()))
        slope = float(np.polyfit(np.log(CASIMIR_STEPS), np.log(defects), 1)[0])
        rows.append(
            {
                "m": m,
                "n": n,
                "order": order,
                "h": hs,
                "errors": errs,
                "casimir_h": list(CASIMIR_STEPS),
                "casimir_defects": defects,
                "casimir_slope": slope,
                "build_s": build,
            }
        )
        print(
            f"| {m} | {n} | {order:.2f} | {errs[-1]:.2e} | {slope:.2f} | {build:.1f} |", flush=True
        )
    return rows


def log_canonical_drifts() -> dict[str, float]:
    c3 = [[0.0, 1.0, 1.0], [-1.0, 0.0, 1.0], [-1.0, -1.0, 0.0]]
    entries = {(i, j): f"{c3[i][j]}*x{i + 1}*x{j + 1}" for i in range(3) for j in range(i + 1, 3)}
    poly = PolynomialPoissonSystem(PolynomialBivector(3, entries), "x1 + x2 + x3")
    exact = pr.LogCanonicalSystem(
        pr.LogCanonical(c3), pr.LogPolynomial({(1, 0, 0): 1, (0, 1, 0): 1, (0, 0, 1): 1}, [0, 0, 0])
    )
    x0 = np.array([[1.2, 0.7, 1.6]])
    k = np.array([1.0, -1.0, 1.0])
    out = {}
    for label, stepper in (
        ("order-2 realization", RealizationTaylorIntegrator(poly, 3, 2)),
        ("order-3 realization", RealizationTaylorIntegrator(poly, 3, 3)),
        ("exact groupoid", pr.log_canonical_taylor(exact, 3)),
    ):
        cas = np.log(pr.integrate(stepper, x0, 0.1, 1000)) @ k
        out[label] = float(np.abs(cas - cas[..., :1]).max())
        print(f"3D log-canonical, Taylor m = 3, {label}: Casimir drift {out[label]:.2e}")
    return out


def speed_rows() -> list[dict[str, object]]:
    system = PolynomialPoissonSystem(PolynomialBivector.nambu(CASIMIR), HAMILTONIAN)
    x0 = np.random.default_rng(0).uniform(-0.6, 0.6, (64, 3))
    n_steps, rows = 20, []
    for m, n in [(1, 2), (3, 3), (5, 5)]:
        integ = RealizationTaylorIntegrator(system, m, n)

        def numpy_rollout(integ: RealizationTaylorIntegrator = integ) -> None:
            state = x0
            for _ in range(n_steps):
                state, _ = integ.step(state, 0.1)

        def core_rollout(integ: RealizationTaylorIntegrator = integ) -> None:
            pr.integrate(integ, x0, 0.1, n_steps)

        best = {}
        for label, run in (("numpy", numpy_rollout), ("core", core_rollout)) * 3:
            start = time.perf_counter()
            run()
            best[label] = min(best.get(label, np.inf), time.perf_counter() - start)
        work = len(x0) * n_steps
        row = {"m": m, "n": n, **{f"{k}_steps_per_s": work / v for k, v in best.items()}}
        row["ratio"] = best["numpy"] / best["core"]
        rows.append(row)
        print(
            f"m = {m}, n = {n}: core {row['core_steps_per_s']:.3g} steps/s, NumPy "
            f"{row['numpy_steps_per_s']:.3g} ({row['ratio']:.0f}×)"
        )
    return rows


def figure(rows: list[dict[str, object]], path: Path) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 4))
    ax_e, ax_c = fig.subplots(1, 2)
    for r in rows:
        label = f"m = {r['m']}, n = {r['n']}"
        ax_e.loglog(r["h"], r["errors"], "o-", label=label)  # type: ignore[arg-type]
        ax_c.loglog(r["casimir_h"], r["casimir_defects"], "o-", label=label)  # type: ignore[arg-type]
    ax_e.set(xlabel="h", ylabel="max |x − x_ref| at T = 1", title="global error")
    ax_c.set(xlabel="h", ylabel="max |C(x₁) − C(x₀)|", title="Casimir defect of one step")
    ax_c.legend(fontsize=7, ncol=2)
    fig.suptitle("Taylor-HJ order m on the order-n realization, cubic Nambu bracket")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    atomic_write_bytes(path, buf.getvalue())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=None, help="write OUT.png and OUT.json")
    args = ap.parse_args(argv)
    png = json_path = None
    if args.out is not None:
        png, json_path = args.out.with_suffix(".png"), args.out.with_suffix(".json")
        check_output_path(png)
        check_output_path(json_path)
    print("| m | n | fitted order | error at h = 1/16 | Casimir defect slope | build (s) |")
    print("|---|---|---|---|---|---|")
    rows = nambu_rows()
    drifts = log_canonical_drifts()
    speed = speed_rows()
    if png is not None and json_path is not None:
        figure(rows, png)
        doc = {
            "nambu": rows,
            "log_canonical_casimir_drift_1000_steps": drifts,
            "speed_64_states": speed,
        }
        atomic_write_bytes(json_path, (json.dumps(doc, indent=1) + "\n").encode())
        print(f"wrote {png}, {json_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

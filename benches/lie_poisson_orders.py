"""Fitted orders and Casimir drifts of every integrator on the heavy top and sl(2, R): the table
in the README's "Lie–Poisson systems" section.

Order: slope of log error against log h at T = 1 from h = T/20 and T/40 against a DOP853
reference (rtol = atol = 1e-13); Taylor K = 7 from h = T/5 and T/10 at T = 2, where the finer
steps already reach the reference's own error. Casimir drift: the largest |C(μ_k) − C(μ_0)| over
10⁴ steps of h = 0.05, over the system's known Casimirs and two states.

Usage: ``python benches/lie_poisson_orders.py [--json FILE]``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

import poisson_rs as pr
from poisson_rs.files import atomic_write_bytes, check_output_path


def systems() -> dict[str, tuple[pr.LiePoissonSystem, np.ndarray]]:
    sl2 = pr.LiePoissonSystem(
        pr.LieAlgebra.sl2(),
        pr.Polynomial({(2, 0, 0): 0.5, (0, 2, 0): 0.4, (0, 0, 2): 0.3, (0, 1, 1): 0.1}),
    )
    top_states = np.array([[0.3, -0.8, 1.2, 0.6, 0.0, 0.8], [1.0, 0.5, -0.4, 0.0, 0.6, 0.8]])
    return {
        "heavy top": (pr.HeavyTop(), top_states),
        "sl(2,R)": (sl2, np.array([[0.4, 0.7, -0.2], [-0.3, 0.2, 0.5]])),
    }


def fitted_order(
    stepper: object, system: pr.LiePoissonSystem, mu0: np.ndarray, t: float, n: int
) -> float:
    ref = pr.reference_solution(system, mu0, np.array([0.0, t]))[:, -1]
    errs = [np.abs(pr.integrate(stepper, mu0, t / k, k)[:, -1] - ref).max() for k in (n, 2 * n)]
    return float(np.log2(errs[0] / errs[1]))


def casimir_drift(stepper: object, system: pr.LiePoissonSystem, mu0: np.ndarray) -> float:
    c = system.casimirs(pr.integrate(stepper, mu0, 0.05, 10_000))
    return float(np.abs(c - c[:, :1]).max())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path, default=None, help="write the rows here")
    args = ap.parse_args(argv)
    if args.json is not None:
        check_output_path(args.json)
    rows = []
    for name, (system, mu0) in systems().items():
        steppers = {f"taylor{k}-exp": pr.taylor_integrator(system, k) for k in (1, 3, 5, 7)}
        for method in pr.classical_methods(system):
            if method != "dop853":
                steppers[method] = pr.classical(system, method)
        for method, stepper in steppers.items():
            t, n = (2.0, 5) if method == "taylor7-exp" else (1.0, 20)
            row = {
                "system": name,
                "method": method,
                "order": fitted_order(stepper, system, mu0, t, n),
                "casimir_drift": casimir_drift(stepper, system, mu0),
            }
            rows.append(row)
            print(
                f"{name:>10} {method:>12}: order {row['order']:.2f}, "
                f"Casimir drift {row['casimir_drift']:.1e}",
                flush=True,
            )
    if args.json is not None:
        atomic_write_bytes(args.json, (json.dumps(rows, indent=1) + "\n").encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())

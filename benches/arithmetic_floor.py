"""What a learned step's network must compute, against the time of the system's RK4 step:

    OPENBLAS_NUM_THREADS=1 taskset -c 1 python benches/arithmetic_floor.py \\
        --costs docs/step_costs_same_build_copies.json --json docs/arithmetic_floor.json

A learned step solves tar(∇S(h, p), p) = μ by simplified Newton: one pass for S's gradient and
Hessian where the Jacobian is refreshed (at least once a step) and a gradient pass for every
further update. For each shipped model, this counts the flops of those passes through the
network alone, by the rules below, and prices them at the rate of one core's float64 matrix
multiply (NumPy's, measured here: the rate dense multiply-adds reach on this core). Divided by
the measured time of the system's RK4 step (``--costs``: a ``benches/step_costs.py`` JSON), that
is the least "× RK4" the model's step can take, before its polynomial terms, its chart, its solve
and its bookkeeping, which are not counted. Where it exceeds issue #29's target of 50×, no
implementation of that model's step meets the target on this core.

Counting rules, per trajectory and step (a multiply-add is 2 flops; N is the phase space's
dimension, J = 1 + N + N(N + 1)/2 the numbers of a packed jet: value, gradient, Hessian):

- Hessian pass, forward mode: a weight whose input unit carries a full jet takes J multiply-adds.
  The first layer's weights take 1 where the inputs are (t, p) themselves (their jets are
  constant: the gradient is the weight), J where they are the homogeneous map (t|p|, p/|p|).
- Each hidden unit: tanh, 38 flops (the package's: range reduction, a degree-13 Horner chain and
  the finish, ``rust/generating/mlp.rs``), σ' = 1 − y² and σ'' = −2yσ' (4), the gradient's N
  products and the Hessian's N(N + 1)/2 entries σ'H + σ''g_a g_b (4 each).
- Gradient pass, reverse mode: 2 flops a weight forward and 2 back; each hidden unit's tanh and
  its σ' (41).
- Passes a step: one Hessian pass and u − 1 gradient passes, u the model's measured Newton
  updates a step (the core takes the last ∇S from the Hessian, with no pass at the solution).

``--log-taylor`` counts the Lotka–Volterra Taylor-HJ steps of ``benches/step_costs.py`` the same
way: their S is a sum of terms c t^k y^e in y = e^q, and a pass over them is the whole of S's
arithmetic, so the count bounds the step from below as the network's does (the chart, the N×N
solve and the bookkeeping not counted). Per term in m variables, as the core's sparse sums form
it (``ExpPolynomial::taylor_lanes``; the dense sums up to N = 3 add zeros too, so this stays a
floor there): its weight c·t^k times one factor a variable (a division too where the exponent
is negative), its gradient's m multiply-adds (2m) and, in a Hessian pass, its upper Hessian's
m(m + 1)/2 (m(m + 1)); per pass, each coordinate's exponential (25 flops: the core's, in
``rust/exp.rs``) and its table of powers (a multiply a row past y¹). A step is the start's
gradient pass and u Hessian passes (full Newton, u the measured updates); the row also gives the
count with one Hessian pass and u − 1 gradient passes (simplified Newton), the least a step of
that S could take with the same updates.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np

import poisson_rs as pr
from poisson_rs.files import atomic_write_bytes, check_output_path

#: The shipped learned models and the row of ``benches/step_costs.py`` that times each.
MODELS = {
    "default": "rigid body",
    "heavy_top_h05": "heavy top",
    "lotka_volterra_h01": "lotka-volterra",
}
#: Flops of the package's tanh (rust/generating/mlp.rs: 8 in the reduction, 11 multiply-adds in
#: the Horner chain, 8 in the finish).
TANH = 38
#: Issue #29's target for a learned step, in RK4 steps.
TARGET = 50.0
#: Issue #29's target for a Taylor-HJ step, in RK4 steps.
TAYLOR_TARGET = 20.0
#: Flops of the core's exponential (rust/exp.rs: 6 in the reduction, 10 in the Horner chain of
#: c, 6 in the quotient, 3 to finish and scale).
EXP = 25
#: The Lotka–Volterra rows of ``benches/step_costs.py`` that --log-taylor counts, and their orders.
LOG_TAYLOR = ("lotka-volterra", "lotka-volterra 3d", "lotka-volterra 5d")
LOG_TAYLOR_ORDERS = (3, 5)
#: Rows of the table of powers the core builds (rust/structures/log_canonical/taylor.rs).
POWER_TABLE = 8


def network_flops(widths: list[int], n: int, homogeneous: bool) -> dict[str, int]:
    """Flops of one Hessian pass and one gradient pass through an MLP with hidden ``widths``,
    n + 1 inputs and one output, for S on an ``n``-dimensional phase space (the module's
    rules)."""
    if n < 1 or not widths or min(widths) < 1:
        raise ValueError(f"network_flops: widths {widths} and n = {n} must be positive")
    jet = 1 + n + n * (n + 1) // 2
    sizes = [n + 1, *widths, 1]
    weights = [a * b for a, b in itertools.pairwise(sizes)]
    first = 2 * jet if homogeneous else 2
    hessian = weights[0] * first + sum(w * 2 * jet for w in weights[1:])
    units = sum(widths)
    hessian += units * (TANH + 4 + n + 4 * (n * (n + 1) // 2))
    gradient = 4 * sum(weights) + units * (TANH + 3)
    return {"hessian_pass": hessian, "gradient_pass": gradient, "weights": sum(weights)}


def log_taylor_flops(exponents: np.ndarray) -> dict[str, int]:
    """Flops of one Hessian pass and one gradient pass over an exponential polynomial
    S = Σ c t^k y^e whose terms have the rows of ``exponents`` (M, N) (the module's rules)."""
    e = np.asarray(exponents)
    if e.ndim != 2 or e.shape[1] < 1:
        raise ValueError(f"log_taylor_flops: exponents of shape {e.shape} must be (terms, N >= 1)")
    m = (e != 0).sum(axis=1)
    factors = (e > 0).sum(axis=1) + 2 * (e < 0).sum(axis=1)
    weights = int((1 + factors).sum())
    gradient = weights + int((2 * m).sum())
    hessian = gradient + int((m * (m + 1)).sum())
    largest = np.minimum(np.abs(e).max(axis=0), POWER_TABLE)
    per_pass = e.shape[1] * EXP + int(np.maximum(largest - 1, 0).sum())
    return {
        "hessian_pass": hessian + per_pass,
        "gradient_pass": gradient + per_pass,
        "terms": int(e.shape[0]),
    }


def log_taylor_rows(
    table: dict[tuple[str, str], dict[str, Any]], rate: float
) -> list[dict[str, Any]]:
    """One row per Lotka–Volterra system of ``benches/step_costs.py`` and order: its S's count,
    priced at ``rate`` flops/s against the measured RK4 and Taylor steps of ``table``."""
    import step_costs  # the bench's own systems, so the counted S is the timed one

    from poisson_rs.realizations.log_canonical import taylor_arrays

    systems = {label: system for label, system, _, _ in step_costs.cases(1, "lotka-volterra")}
    rows = []
    for label in LOG_TAYLOR:
        for order in LOG_TAYLOR_ORDERS:
            _, exponents, _ = taylor_arrays(systems[label], order)
            count = log_taylor_flops(exponents)
            step = table[(label, f"taylor{order}-log")]
            rk4 = table[(label, "rk4")]["ns_per_step"]
            u = step["newton_updates_per_step"]
            full = count["gradient_pass"] + u * count["hessian_pass"]
            simplified = count["hessian_pass"] + u * count["gradient_pass"]
            rows.append(
                {
                    "system": label,
                    "order": order,
                    **count,
                    "updates_per_step": u,
                    "flops_per_step": full,
                    "flops_per_step_simplified": simplified,
                    "floor_vs_rk4": full / rate * 1e9 / rk4,
                    "floor_vs_rk4_simplified": simplified / rate * 1e9 / rk4,
                    "rk4_ns": rk4,
                    "measured_ns": step["ns_per_step"],
                    "measured_vs_rk4": step["ns_per_step"] / rk4,
                    "target_within_floor": full / rate * 1e9 / rk4 <= TAYLOR_TARGET,
                }
            )
    return rows


def matmul_rate(size: int = 1024, repeats: int = 5) -> float:
    """Float64 flops per second of NumPy's ``size``² matrix product on this thread (best of
    ``repeats``)."""
    rng = np.random.default_rng(0)
    a, b = rng.random((size, size)), rng.random((size, size))
    a @ b
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - start)
    return 2.0 * size**3 / best


def measured(costs: Path, log_taylor: bool = False) -> dict[tuple[str, str], dict[str, Any]]:
    """(system, stepper) → row of a ``benches/step_costs.py`` JSON (with ``log_taylor``, the
    Lotka–Volterra Taylor rows too); SystemExit naming the file and what is missing otherwise."""
    try:
        rows = json.loads(costs.read_text())["rows"]
        table = {(r["system"], r["stepper"]): r for r in rows}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SystemExit(f"--costs {costs}: not a step_costs.py JSON ({exc})") from None
    for name, system in MODELS.items():
        for stepper in ("rk4", f"learned:{name}"):
            if (system, stepper) not in table:
                raise SystemExit(f"--costs {costs}: no row for {system}, {stepper}")
    if not log_taylor:
        return table
    for system in LOG_TAYLOR:
        for stepper in ["rk4", *(f"taylor{k}-log" for k in LOG_TAYLOR_ORDERS)]:
            if (system, stepper) not in table:
                raise SystemExit(f"--costs {costs}: no row for {system}, {stepper}")
    return table


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--costs", type=Path, required=True, help="a step_costs.py JSON")
    ap.add_argument("--json", type=Path, help="write the rows here")
    ap.add_argument(
        "--peak",
        type=float,
        help="also price the flops at this rate, GFLOP/s (e.g. the vector units' peak)",
    )
    ap.add_argument(
        "--log-taylor",
        action="store_true",
        help="also count the Lotka-Volterra Taylor-HJ steps of step_costs.py",
    )
    args = ap.parse_args()
    if args.peak is not None and not args.peak > 0:
        raise SystemExit(f"--peak: {args.peak} GFLOP/s must be positive")
    if args.json is not None:
        check_output_path(args.json)
    table = measured(args.costs, args.log_taylor)
    rate = matmul_rate()
    print(f"float64 matrix multiply, one thread: {rate / 1e9:.1f} GFLOP/s")
    rows = []
    for name, system in MODELS.items():
        model = pr.load_model(name)
        config = json.loads(model.metadata["config"])
        homogeneous = config.get("inputs", "t,p") == "homogeneous"
        count = network_flops(list(config["widths"]), model.dim, homogeneous)
        step = table[(system, f"learned:{name}")]
        rk4 = table[(system, "rk4")]["ns_per_step"]
        updates = step["newton_updates_per_step"]
        flops = count["hessian_pass"] + (updates - 1.0) * count["gradient_pass"]
        floor_ns = flops / rate * 1e9
        row = {
            "model": name,
            "system": system,
            "widths": list(config["widths"]),
            "inputs": "homogeneous" if homogeneous else "t,p",
            **count,
            "updates_per_step": updates,
            "network_flops_per_step": flops,
            "floor_ns": floor_ns,
            "rk4_ns": rk4,
            "floor_vs_rk4": floor_ns / rk4,
            "measured_ns": step["ns_per_step"],
            "measured_vs_rk4": step["ns_per_step"] / rk4,
            "network_share_of_matmul_rate": floor_ns / step["ns_per_step"],
            "target_within_floor": floor_ns / rk4 <= TARGET,
        }
        if args.peak is not None:
            row["floor_vs_rk4_at_peak"] = flops / (args.peak * 1e9) * 1e9 / rk4
        rows.append(row)
        print(
            f"{name:20s} {count['weights']:5d} weights: Hessian pass {count['hessian_pass']:7d}, "
            f"gradient pass {count['gradient_pass']:6d} flops; {updates:.2f} updates -> "
            f"{flops:8.0f} flops = {floor_ns:7.1f} ns at the multiply's rate = "
            f"{floor_ns / rk4:6.1f}x RK4 ({rk4:.2f} ns); measured {step['ns_per_step']:.1f} ns "
            f"= {step['ns_per_step'] / rk4:.1f}x"
            + (
                f"; at {args.peak:g} GFLOP/s {row['floor_vs_rk4_at_peak']:.1f}x"
                if args.peak is not None
                else ""
            ),
            flush=True,
        )
    taylor = log_taylor_rows(table, rate) if args.log_taylor else []
    for row in taylor:
        print(
            f"{row['system']:18s} K = {row['order']}: {row['terms']:4d} terms, Hessian pass "
            f"{row['hessian_pass']:6d}, gradient pass {row['gradient_pass']:5d} flops; "
            f"{row['updates_per_step']:.2f} updates -> {row['flops_per_step']:8.0f} flops = "
            f"{row['floor_vs_rk4']:5.1f}x RK4 ({row['rk4_ns']:.2f} ns; simplified Newton "
            f"{row['floor_vs_rk4_simplified']:.1f}x); measured {row['measured_vs_rk4']:.1f}x",
            flush=True,
        )
    if args.json is not None:
        doc = {
            "costs": str(args.costs),
            "matmul_flops_per_s": rate,
            "peak_flops_per_s": None if args.peak is None else args.peak * 1e9,
            "rows": rows,
            **({"log_taylor_rows": taylor} if args.log_taylor else {}),
        }
        atomic_write_bytes(args.json, (json.dumps(doc, indent=1) + "\n").encode())


if __name__ == "__main__":
    sys.exit(main())

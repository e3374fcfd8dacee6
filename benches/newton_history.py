"""Newton's work along a rollout when a step starts from the steps before it:

    PYTHONPATH=python python benches/newton_history.py --json docs/newton_history.json

Issue #29 asks for fewer Newton updates a step, naming the previous step's p as a predictor. A
bisection step solves tar(∇S(h, p), p) = μ for p; along a rollout the offset d = p − μ changes by
O(h) a step, so the steps before give a start for free, with no pass through S:

- ``core``: the core's own start (from a jet of S's cheap terms at μ; ``newton_predictors.py``'s
  "hessian"), for comparison: it costs no network pass;
- ``mu``: p₀ = μ (no prediction);
- ``previous``: p₀ = μₙ + dₙ₋₁, the last step's offset carried over (O(h²) from the solution);
- ``extrapolated``: p₀ = μₙ + 2dₙ₋₁ − dₙ₋₂ (O(h³)).

And the Jacobian: simplified Newton takes a fresh one (S's Hessian, the chart's Jacobian, an
inverse) at a step's first update and again while updates contract by less than 1/4 (the core's
rule, ``fresh``). A stiff solver's alternative (Hairer & Wanner, *Solving ODEs II*, IV.8) is
``carried r``: keep the last step's inverse and refresh only after an update k ≥ 2 that
contracted by less than r (the ratio of its size to the update's before). A step then needs a
Hessian pass only where the carried inverse has gone stale. Replayed: every start with the
fresh rule, and the core's start with the carried rule at r = 1/4, 1/16 and 1/64.

The replay runs in float64 torch (the package's ``newton_system``: autograd through ∂S/∂p and the
package's ``tar``) on the seeded states of ``benches/step_costs.py``, h = 0.1, for the Taylor-HJ
steps of the rigid body and the heavy top and the shipped learned models on them. A reference
rollout of ``--steps`` steps (each solved to the core's tolerance) gives the offsets; from the
third step on, every start and Jacobian rule is replayed on every step, the carried inverse
carried along the replay's own steps, each solve stopping at |δ|∞ ≤ tol·|p|∞ as the core's does.
Reported: mean updates and mean Hessian passes (refreshes) a step, and the largest distance of a
replayed solution from the reference one, relative to |p|∞. No timing: for a learned model the
flops of a Hessian pass and a gradient pass are ``benches/arithmetic_floor.py``'s, and the cost
column prices each mix with them.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

import poisson_rs as pr
from poisson_rs.files import atomic_write_bytes, check_output_path
from poisson_rs.generating import newton_system, solve_momentum
from poisson_rs.realizations.lie_groupoid import sou

sys.path.insert(0, str(Path(__file__).resolve().parent))
from arithmetic_floor import network_flops
from newton_predictors import predict, series
from step_costs import H, rigid_states, top_states

#: The core's simplified-Newton rule (`SIMPLIFIED_RATE` in rust/step.rs).
SIMPLIFIED_RATE = 0.25
#: (start, Jacobian rule, the contraction below which a carried inverse is kept; None: fresh
#: at each step's first update).
COMBOS: tuple[tuple[str, str, float | None], ...] = (
    ("core", "fresh", None),
    ("mu", "fresh", None),
    ("previous", "fresh", None),
    ("extrapolated", "fresh", None),
    ("core", "carried 1/4", 1 / 4),
    ("core", "carried 1/16", 1 / 16),
    ("core", "carried 1/64", 1 / 64),
)
MAX_ITER = 50


def steppers() -> list[tuple[str, Any, str]]:
    """(label, stepper, states' system) for every replayed row."""
    rigid = pr.RigidBody((1.5, 2.0, 2.5))
    top = pr.HeavyTop((1.0, 1.5, 2.0), 0.981, (0.0, 0.0, 1.0))
    rows: list[tuple[str, Any, str]] = []
    for chart in ("exp", "cayley"):
        for k in (3, 5):
            rows.append(
                (
                    f"rigid body, Taylor K={k} {chart}",
                    pr.taylor_integrator(rigid, k, chart=chart),
                    "rigid",
                )
            )
    for k in (3, 5):
        rows.append(
            (f"heavy top, Taylor K={k} exp", pr.taylor_integrator(top, k, chart="exp"), "top")
        )
    rows.append(("rigid body, learned default", pr.load_model("default"), "rigid"))
    rows.append(("heavy top, learned heavy_top_h05", pr.load_model("heavy_top_h05"), "top"))
    return rows


def reference(
    stepper: Any, mu0: torch.Tensor, steps: int
) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """μₙ and the solved pₙ of a rollout of ``steps`` steps: (mus, ps), each (B, n)."""
    g, chart = stepper.generating, stepper.chart
    mus, ps = [mu0], []
    t = torch.full((mu0.shape[0],), H, dtype=mu0.dtype)
    for _ in range(steps):
        p, done = solve_momentum(g, mus[-1], H, chart=chart, tol=stepper.tol, max_iter=MAX_ITER)
        if not bool(done.all()):
            raise RuntimeError("the reference solve did not converge")
        ps.append(p)
        pv = p.clone().requires_grad_(True)
        with torch.enable_grad():
            (x,) = torch.autograd.grad(g(t, pv).sum(), pv)
        mus.append(sou(chart, x.detach(), p, algebra=g.algebra).detach())
    return mus[:-1], ps


def replay(
    stepper: Any,
    mu: torch.Tensor,
    p0: torch.Tensor,
    inv: torch.Tensor | None,
    rate: float = SIMPLIFIED_RATE,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Simplified Newton from ``p0`` for every state; ``inv`` the carried inverse Jacobians (None:
    fresh at the first update), refreshed after an update that contracted by less than ``rate``.
    Returns (p, inverse in use at the end, updates (B,), refreshes (B,))."""
    g, chart, tol = stepper.generating, stepper.chart, stepper.tol
    b = mu.shape[0]
    t = torch.full((b,), H, dtype=mu.dtype)
    p = p0.clone()
    active = torch.ones(b, dtype=torch.bool)
    refresh = torch.full((b,), inv is None)
    cur = torch.zeros(b, mu.shape[1], mu.shape[1], dtype=mu.dtype) if inv is None else inv.clone()
    last = torch.full((b,), float("inf"), dtype=mu.dtype)
    updates = torch.zeros(b, dtype=torch.long)
    refreshes = torch.zeros(b, dtype=torch.long)
    for _ in range(MAX_ITER):
        if not bool(active.any()):
            break
        f, jac = newton_system(g, chart, t, p.detach().requires_grad_(True), mu)
        take = active & refresh
        if bool(take.any()):
            cur[take] = torch.linalg.inv(jac[take])
        refreshes += take.long()
        delta = -(cur @ f.detach()[..., None])[..., 0]
        delta = torch.where(active[:, None], delta, torch.zeros_like(delta))
        p = p + delta
        updates += active.long()
        size = delta.abs().amax(-1)
        done = size <= tol * p.abs().amax(-1).clamp_min(1e-300)
        refresh = torch.where(active, size > rate * last, refresh)
        last = torch.where(active, size, last)
        active = active & ~done
    if bool(active.any()):
        raise RuntimeError(f"a replayed solve did not converge in {MAX_ITER} updates")
    return p, cur, updates, refreshes


def row_for(label: str, stepper: Any, mu0: np.ndarray, steps: int) -> dict[str, Any]:
    """Every start and rule replayed on steps 2 … ``steps`` − 1 of the reference rollout; the
    first of them only sets up the carried inverse, the rest are counted."""
    mus, ps = reference(stepper, torch.as_tensor(mu0), steps)
    cheap = series(stepper.system, 3, stepper.chart)
    out: dict[str, Any] = {"stepper": label, "states": len(mu0), "counted_steps": steps - 3}
    for start, rule, rate in COMBOS:
        inv: torch.Tensor | None = None
        ups, refs, worst = [], [], 0.0
        for n in range(2, steps):
            d1, d2 = ps[n - 1] - mus[n - 1], ps[n - 2] - mus[n - 2]
            if start == "core":
                p0 = torch.stack(
                    [predict(stepper.system, cheap, stepper.chart, m, "hessian") for m in mus[n]]
                )
            else:
                p0 = {"mu": mus[n], "previous": mus[n] + d1, "extrapolated": mus[n] + 2 * d1 - d2}[
                    start
                ]
            carried = inv if rate is not None else None
            p, inv, u, r = replay(stepper, mus[n], p0, carried, rate or SIMPLIFIED_RATE)
            gap = (p - ps[n]).abs().amax(-1) / ps[n].abs().amax(-1)
            worst = max(worst, float(gap.max()))
            if n > 2:
                ups.append(u.double().mean().item())
                refs.append(r.double().mean().item())
        out[f"{start}, {rule}"] = {
            "updates": float(np.mean(ups)),
            "hessian_passes": float(np.mean(refs)),
            "largest_gap": worst,
            # Mean updates of each counted step, in order: a carried inverse ages.
            "updates_by_step": ups,
            "hessian_passes_by_step": refs,
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--states", type=int, default=32, help="states per system (32)")
    ap.add_argument("--steps", type=int, default=13, help="steps of each rollout (13, >= 4)")
    ap.add_argument("--json", type=Path, help="write the rows here")
    args = ap.parse_args()
    if args.states < 1 or args.steps < 4:
        raise SystemExit("--states must be at least 1 and --steps at least 4")
    if args.json is not None:
        check_output_path(args.json)
    torch.set_default_dtype(torch.float64)
    states = {
        "rigid": rigid_states(args.states, np.random.default_rng(42)),
        "top": top_states(args.states, np.random.default_rng(42)),
    }
    rows = []
    cols = [f"{s}, {r}" for s, r, _ in COMBOS]
    print("| stepper | " + " | ".join(cols) + " |")
    print("|---|" + "---|" * len(cols))
    for label, stepper, which in steppers():
        row = row_for(label, stepper, states[which], args.steps)
        net = stepper.metadata.get("config") if hasattr(stepper, "metadata") else None
        if net is not None and "widths" in json.loads(net) and "learned" in label:
            config = json.loads(net)
            count = network_flops(
                list(config["widths"]), stepper.dim, config.get("inputs") == "homogeneous"
            )
            for c in cols:
                u, r = row[c]["updates"], row[c]["hessian_passes"]
                row[c]["network_flops"] = (
                    r * count["hessian_pass"] + (u - r) * count["gradient_pass"]
                )
        rows.append(row)
        cells = []
        for c in cols:
            cell = f"{row[c]['updates']:.2f} upd, {row[c]['hessian_passes']:.2f} H"
            if "network_flops" in row[c]:
                cell += f", {row[c]['network_flops']:.0f} flops"
            cells.append(cell)
        print(f"| {label} | " + " | ".join(cells) + " |", flush=True)
    if args.json is not None:
        doc = {"h": H, "simplified_rate": SIMPLIFIED_RATE, "rows": rows}
        atomic_write_bytes(args.json, (json.dumps(doc, indent=1) + "\n").encode())


if __name__ == "__main__":
    main()

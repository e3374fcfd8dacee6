"""Newton updates per Taylor-HJ step with the core's predictors and with the others tried.

    PYTHONPATH=python python benches/newton_predictors.py --json docs/newton_predictors.json

A Taylor-HJ step on g* solves tar(∇S(h, p), p) = μ for p by simplified Newton (a fresh Jacobian
while the updates contract by less than 1/4, stop once |δ|∞ ≤ 1e-12 · |p|∞), started from a
prediction. First order, from x₀ the gradient of S's t-linear terms at μ, O(h²) from the
solution: "linear" (tar's part linear in x₀, p₀ = μ + ½ ad*_{x₀} μ) or "chart" (p₀ = 2μ −
tar(x₀, μ), the whole chart at x₀). "second": "linear" in the exponential chart, "chart" in the
Cayley one, then one step of the fixed-point iteration p ← p + μ − tar(x, p) with x the gradient
of S's t¹ and t² terms at p₀ (the cheap part of S: no network, no t³ … t^K terms; on g* the
Taylor-HJ S has no t² term, so x is t∇H at p₀), O(h³): the core's start on se(3) before.
"hessian", the core's start now: a fixed-point step with x linearized at μ, x₀ + Hess·(p − μ),
x₀ and Hess from one pass at μ (no pass at p): :data:`CORE_START` gives the t-degrees of x₀'s
and the Hessian's terms. The Cayley chart takes S's t³ terms too (its S₃ is 10–20× the
exponential chart's and, left out, the start's largest error: 2.78 updates a step where it
takes 2.06). On se(3) the step leaves 3.00 updates, as "second" does, for less: no second pass
and no chart at p (the core sums tar to second order in x there, O(h⁴) from this). "second"
saved an update on so(3) but cost more than the 3×3 update it saved; "hessian" saves it for
less (``benches/step_costs.py``, docs/performance.md).

Each row replays the four in float64 torch (autograd Jacobians, the package's own ``tar`` and
Taylor terms) on the states of ``benches/step_costs.py`` (seed 42, h = 0.1) and counts the
updates; the core's own count on the same states (``integrate(..., return_info=True)``, one
step) checks the replay of its start. Reported: mean updates per step and the median
size of each update. No timing: what an update saved is worth is the cost of an update, in
``docs/step_costs.json``.

The same replay weighs a stop the core does not take: after update k ≥ 2, stop where the
contraction θ = |δₖ| / |δₖ₋₁| puts the error left, θ/(1 − θ)·|δₖ| (Hairer & Wanner, IV.8), below
a share of the bound. Per share: the mean updates it would take, the share of solves it stops
before the size rule does, and the largest error it would leave (the size of the update it
skips, relative to |p|∞). Update 1 is full Newton and update 2 simplified, so θ₂ is not the rate
of update 3: the estimate is off by up to ~30× (docs/performance.md, "Tried and rejected").
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
from poisson_rs.realizations.lie_groupoid import tar
from poisson_rs.taylor import system_taylor_terms

sys.path.insert(0, str(Path(__file__).resolve().parent))
from step_costs import H, rigid_states, top_states

#: The core's simplified-Newton rule (`SIMPLIFIED_RATE` in rust/step.rs): a fresh Jacobian while
#: the updates contract by less than this. Its tolerance is read off the stepper.
SIMPLIFIED_RATE = 0.25


def polynomial(powers: np.ndarray, coeffs: np.ndarray, max_t: int | None = None) -> Any:
    """S(t, p) = Σ c tᵏ pᵉ over the terms with k ≤ max_t (all when None), in torch."""
    keep = np.ones(len(powers), bool) if max_t is None else powers[:, 0] <= max_t
    pw, cf = torch.as_tensor(powers[keep]), torch.as_tensor(coeffs[keep])

    def s(t: float, p: torch.Tensor) -> torch.Tensor:
        m = t ** pw[:, 0].to(p.dtype)
        for i in range(p.shape[-1]):
            m = m * p[..., i : i + 1] ** pw[:, i + 1]
        return (m * cf).sum(-1)

    return s


def gradient(s: Any, t: float, p: torch.Tensor, graph: bool = False) -> torch.Tensor:
    if not p.requires_grad:
        p = p.detach().requires_grad_(True)
    return torch.autograd.grad(s(t, p), p, create_graph=graph)[0]


#: The core's start ("hessian"), by algebra and chart: the largest power of t in S's terms that
#: x₀ and the Hessian are taken from.
CORE_START = {("so3", "exp"): 2, ("so3", "cayley"): 3, ("other", "exp"): 2}

#: The predictors replayed (see the module's docstring).
PREDICTORS = ("linear", "chart", "second", "hessian")

#: Shares of the bound tol·|p|∞ the contraction estimate is weighed at (the module's docstring).
ESTIMATE_SHARES = (1e-2, 1e-3)


def estimate_stop(sizes: list[float], scales: list[float], tol: float, share: float) -> int:
    """The update after which the contraction estimate (or the size rule) would stop a solve
    whose size-rule updates are ``sizes`` (|p|∞ after each in ``scales``), counted from 1."""
    for k in range(1, len(sizes)):
        bound = tol * scales[k]
        theta = sizes[k] / sizes[k - 1]
        if sizes[k] <= bound or (theta < 1.0 and sizes[k] * theta <= share * bound * (1 - theta)):
            return k + 1
    return len(sizes)


def series(system: Any, order: int, chart: str) -> tuple[Any, Any, Any, Any]:
    """S, its t-linear terms, its terms up to t² and those up to t³ (torch callables), once per
    row."""
    powers, coeffs = system_taylor_terms(system, order, chart)
    return tuple(polynomial(powers, coeffs, k) for k in (None, 1, 2, 3))  # type: ignore[return-value]


def predict(
    system: Any, s: tuple[Any, Any, Any, Any], chart: str, mu: torch.Tensor, predictor: str
) -> torch.Tensor:
    """The start p₀ of a predictor of :data:`PREDICTORS` for one state ``mu`` (n,), from the
    terms ``s`` of :func:`series` (only its cheap terms, up to t³, are read)."""
    alg = system.algebra
    _, s1, s2, s3 = s
    cheap = {2: s2, 3: s3}[CORE_START[("so3" if alg.is_so3() else "other", chart)]]
    x0 = gradient(cheap if predictor == "hessian" else s1, H, mu)
    if predictor == "linear" or (predictor in ("second", "hessian") and chart == "exp"):
        # tar(x, p) = p − ½ ad*_x p + O(|x|²): p₀ = μ + ½ ad*_{x₀} μ, the core's predictor.
        one = torch.ones((), dtype=mu.dtype)
        _, lin = torch.autograd.functional.jvp(
            lambda e: tar(chart, e * x0, mu, alg), (0 * one,), (one,)
        )
        p = mu - lin
    else:
        p = mu + (mu - tar(chart, x0, mu, alg))
    if predictor == "second":
        xa = gradient(s2, H, p)
        p = p + (mu - tar(chart, xa, p, alg))
    elif predictor == "hessian":
        # The same fixed-point step with ∇S(p₀) linearized at μ: x₀ + Hess · (p₀ − μ).
        hess = torch.autograd.functional.hessian(lambda q: cheap(H, q), mu)
        p = p + (mu - tar(chart, x0 + hess @ (p - mu), p, alg))
    return p.detach()


def solve(
    system: Any,
    s: tuple[Any, Any, Any, Any],
    chart: str,
    mu: torch.Tensor,
    predictor: str,
    tol: float,
) -> tuple[int, list[float], list[float]]:
    """Simplified Newton from a predictor of :data:`PREDICTORS` for S = ``s[0]`` (``s`` from
    :func:`series`), stopping at |δ|∞ ≤ tol·|p|∞: updates, their sizes and |p|∞ after each."""
    alg = system.algebra
    p = predict(system, s, chart, mu, predictor)
    full = s[0]
    sizes: list[float] = []
    scales: list[float] = []
    refresh, last, inv = True, float("inf"), None
    while len(sizes) < 50:
        if refresh:
            jac = torch.autograd.functional.jacobian(
                lambda q: tar(chart, gradient(full, H, q, graph=True), q, alg), p
            )
            inv = torch.linalg.inv(jac)
        assert inv is not None
        delta = inv @ (mu - tar(chart, gradient(full, H, p), p, alg))
        p = (p + delta).detach()
        size = float(delta.abs().max())
        sizes.append(size)
        scales.append(float(p.abs().max()))
        if size <= tol * scales[-1]:
            break
        refresh, last = size > SIMPLIFIED_RATE * last, size
    return len(sizes), sizes, scales


def core_updates(stepper: Any, states: np.ndarray) -> float:
    """The core's mean Newton updates over one step of ``states``."""
    _, info = pr.integrate(stepper, states, H, 1, return_info=True)
    return float(np.mean(info.newton_iterations))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--states", type=int, default=64, help="states per system (64)")
    ap.add_argument("--json", type=Path, help="write the rows here")
    args = ap.parse_args()
    if args.json is not None:
        check_output_path(args.json)
    torch.set_default_dtype(torch.float64)
    rng = np.random.default_rng(42)
    systems = [
        (
            "rigid body",
            pr.RigidBody((1.5, 2.0, 2.5)),
            rigid_states(args.states, rng),
            ("exp", "cayley"),
        ),
        (
            "heavy top",
            pr.HeavyTop((1.0, 1.5, 2.0), 0.981, (0.0, 0.0, 1.0)),
            top_states(args.states, rng),
            ("exp",),
        ),
    ]
    rows = []
    tol = pr.taylor_integrator(systems[0][1], order=3).tol
    print(
        "| system | chart, K | core | linear | chart | second | hessian "
        "| median |δ| (each predictor) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for label, system, states, charts in systems:
        for chart in charts:
            for order in (3, 5):
                row: dict[str, Any] = {"system": label, "chart": chart, "order": order}
                stepper = pr.taylor_integrator(system, order=order, chart=chart)
                row["core"] = core_updates(stepper, states)
                terms = series(system, order, chart)
                for key in PREDICTORS:
                    runs = [
                        solve(system, terms, chart, torch.as_tensor(m), key, stepper.tol)
                        for m in states
                    ]
                    # Under "<predictor>_updates": "chart" is the row's chart.
                    row[f"{key}_updates"] = float(np.mean([n for n, _, _ in runs]))
                    depth = max(len(z) for _, z, _ in runs)
                    row[f"{key}_median_sizes"] = [
                        float(np.median([z[i] for _, z, _ in runs if len(z) > i]))
                        for i in range(depth)
                    ]
                    for share in ESTIMATE_SHARES:
                        stops = [estimate_stop(z, sc, stepper.tol, share) for _, z, sc in runs]
                        left = [
                            z[k] / sc[k - 1] if k < n else 0.0
                            for (n, z, sc), k in zip(runs, stops, strict=True)
                        ]
                        row[f"{key}_estimate_{share:g}"] = {
                            "updates": float(np.mean(stops)),
                            "stopped_sooner": float(
                                np.mean([k < n for (n, _, _), k in zip(runs, stops, strict=True)])
                            ),
                            "largest_error_left": float(max(left)),
                        }
                rows.append(row)
                sizes = " / ".join(
                    ", ".join(f"{v:.1e}" for v in row[f"{k}_median_sizes"]) for k in PREDICTORS
                )
                counts = " | ".join(f"{row[f'{k}_updates']:.2f}" for k in PREDICTORS)
                print(f"| {label} | {chart}, {order} | {row['core']:.2f} | {counts} | {sizes} |")
                for share in ESTIMATE_SHARES:
                    est = [row[f"{k}_estimate_{share:g}"] for k in PREDICTORS]
                    print(
                        f"|   estimate stop at {share:g} of the bound | | | "
                        + " | ".join(
                            f"{e['updates']:.2f} ({100 * e['stopped_sooner']:.0f} % sooner, "
                            f"left ≤ {e['largest_error_left']:.1e})"
                            for e in est
                        )
                        + " | |"
                    )
    if args.json is not None:
        doc = {
            "h": H,
            "tol": tol,
            "states": args.states,
            "estimate_shares": ESTIMATE_SHARES,
            "rows": rows,
        }
        atomic_write_bytes(args.json, (json.dumps(doc, indent=1) + "\n").encode())


if __name__ == "__main__":
    main()

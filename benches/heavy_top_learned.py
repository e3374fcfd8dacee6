"""Learned heavy-top models against their own Taylor terms: the table in docs/heavy_top.md.

Each run trains exact Taylor terms K (exp chart) plus t^(K+2) · MLP(t, p) on the HJ residual for
t ∈ [0, h] (Adam, cosine schedule, the network starting at zero output; optional L-BFGS), then
measures, against DOP853 (rtol = atol = 1e-13) and for the model and the same Taylor terms alone:

- the one-step error at h on 64 held-out states (M uniform in [−1.2, 1.2]³, Γ a random unit
  vector; seed 123), median and max of |μ₁ − μ(h)|;
- the error at T = 10, step h, on 8 held-out states in the domain (the first of seed 123 whose
  exact orbit keeps |Mᵢ| ≤ half_width; with the cube domain, the first 8): median and max of
  |μ(T) − μ_ref(T)| / |μ₀|;
- max |H − H₀|/|H₀| and max |C − C₀|/|μ₀|² (C = |Γ|², M·Γ) over that run, the Casimir drift over
  400 steps (also with full Newton for the model), and steps/s (256 states × 200 steps, one
  thread);
- the range of |Γ_p| over the bisection momenta p, and the Taylor terms' residual in bins of |M|;
- how well the network learned the missing part of S at t = h: the RMS error of S and of ∂S/∂p
  (all of it, and the part across the Casimir gradients (0, Γ) and (Γ, M), which moves the step)
  relative to the Taylor terms' own, with Taylor K = 13 standing in for the exact S.

Sampling: "uniform" draws p uniformly over the domain ("cube": |μᵢ| ≤ half_width in R⁶; "top":
|Mᵢ| ≤ half_width, r_min ≤ |Γ| ≤ r_max); "orbits" draws ``--fraction`` of each batch near the
exact orbits of ``--train-states`` states (seed 7, drawn like the held-out ones; relative noise
``--noise``), the rest uniformly. The rows of docs/heavy_top.md:

    python benches/heavy_top_learned.py --domain cube --sampling uniform --iterations 3000
    python benches/heavy_top_learned.py --domain cube --sampling orbits --iterations 3000
    python benches/heavy_top_learned.py --domain top --widths 32 32 --iterations 6000 --batch 2048

``--out`` keeps the model file; ``--model`` measures a model file (a shipped model's name
included) instead of training; ``--json`` appends the row to a JSON-lines file. The shipped
``heavy_top_h05``, trained by ``poisson-rs train`` (the command is in its file), measures with

    python benches/heavy_top_learned.py --model heavy_top_h05 --taylor-order 1
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch

import poisson_rs as pr
from poisson_rs.files import check_output_path
from poisson_rs.train import TrainConfig, _zero_output, build_model, save_result, train

T = 10.0


def states(seed: int, n: int) -> np.ndarray:
    """n heavy-top states (M, Γ): M uniform in [−1.2, 1.2]³, Γ a random unit vector."""
    rng = np.random.default_rng(seed)
    m = rng.uniform(-1.2, 1.2, (n, 3))
    g = rng.normal(size=(n, 3))
    return np.hstack([m, g / np.linalg.norm(g, axis=1, keepdims=True)])


def states_inside(seed: int, n: int, half_width: float) -> np.ndarray:
    """The first n of :func:`states` (seed) whose exact orbit keeps |Mᵢ| ≤ half_width up to
    T = 10 (checked at 201 times): held-out states in a top domain (|Γ| = 1 on every orbit)."""
    top = pr.HeavyTop()
    cand = states(seed, 8 * n)
    orbits = pr.reference_solution(top, cand, np.linspace(0.0, T, 201))
    inside = np.abs(orbits[..., :3]).max(axis=(1, 2)) <= half_width
    if inside.sum() < n:
        raise ValueError(f"fewer than {n} of {len(cand)} orbits stay in |M_i| <= {half_width}")
    return cand[inside][:n]


def fit_quality(model: pr.LearnedIntegrator, cfg: TrainConfig, h: float) -> dict[str, float]:
    """RMS errors of the model's S and ∂S/∂p at t = h over 4096 held-out p (M uniform in
    [−1.5, 1.5]³, |Γ| = 0.98), relative to those of its Taylor terms alone; Taylor K = 13 is
    the reference S."""

    def taylor(k: int) -> torch.nn.Module:
        f = build_model(TrainConfig(**{**cfg.__dict__, "taylor_order": k, "widths": (1,)}))
        _zero_output(f)
        return f

    rng = np.random.default_rng(5)
    n = 4096
    g = rng.normal(size=(n, 3))
    gamma = 0.98 * g / np.linalg.norm(g, axis=1)[:, None]
    p_np = np.hstack([rng.uniform(-1.5, 1.5, (n, 3)), gamma])
    p = torch.tensor(p_np, requires_grad=True)
    t = torch.full((n,), h, dtype=torch.float64)

    def value_grad(f: torch.nn.Module) -> tuple[np.ndarray, np.ndarray]:
        v = f(t, p)
        (grad,) = torch.autograd.grad(v.sum(), p)
        return v.detach().numpy(), grad.numpy()

    (ve, ge), (vb, gb) = value_grad(taylor(13)), value_grad(taylor(cfg.taylor_order))
    vl, gl = value_grad(model.generating)
    # Orthonormal basis of the Casimir gradients d|Γ|² ∝ (0, Γ), d(M·Γ) = (Γ, M) at each p.
    a = np.hstack([np.zeros((n, 3)), p_np[:, 3:]])
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.hstack([p_np[:, 3:], p_np[:, :3]])
    b -= (b * a).sum(1, keepdims=True) * a
    b /= np.linalg.norm(b, axis=1, keepdims=True)

    def across(v: np.ndarray) -> np.ndarray:
        return v - (v * a).sum(1, keepdims=True) * a - (v * b).sum(1, keepdims=True) * b

    def ratio(x: np.ndarray, y: np.ndarray) -> float:
        return float(np.sqrt(np.mean(x**2) / np.mean(y**2)))

    return {
        "S_error_relative": ratio(vl - ve, vb - ve),
        "dS_error_relative": ratio(gl - ge, gb - ge),
        "dS_error_across_casimirs_relative": ratio(across(gl - ge), across(gb - ge)),
    }


def full_newton(model: pr.LearnedIntegrator) -> pr.LearnedIntegrator:
    """The same model file with full Newton (a Jacobian every update) instead of the default."""
    assert model.path is not None
    return pr.load_model(model.path, newton="full")


def invariants_and_speed(
    name: str, stepper: pr.Stepper, held: np.ndarray, traj: np.ndarray | None, h: float
) -> dict[str, float]:
    """For ``name``: max |H − H₀|/|H₀| and max |C − C₀|/|μ₀|² over the T = 10 run ``traj``
    (n, steps + 1, 6) when given; the Casimir drift over 400 steps (T = 200) from the held-out
    states; steps per second on 256 states × 200 steps (one rayon thread as set by the caller's
    RAYON_NUM_THREADS, best of 3)."""
    top = pr.HeavyTop()
    out: dict[str, float] = {}
    norm2 = (held * held).sum(1)[:, None, None]
    if traj is not None:
        h0 = top.hamiltonian(held)[:, None]
        out[f"T10_max_dH_{name}"] = float((np.abs(top.hamiltonian(traj) - h0) / np.abs(h0)).max())
        c = top.casimirs(traj)
        out[f"T10_max_dC_{name}"] = float((np.abs(c - c[:, :1]) / norm2).max())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        long = pr.integrate(stepper, held, h, 400)
        c = top.casimirs(long)
        out[f"T200_max_dC_{name}"] = float((np.abs(c - c[:, :1]) / norm2).max())
        many = states(99, 256)
        best = math.inf
        for _ in range(3):
            t0 = time.perf_counter()
            pr.integrate(stepper, many, h, 200)
            best = min(best, time.perf_counter() - t0)
    out[f"steps_per_s_{name}"] = 256 * 200 / best
    return out


def newton_gamma_range(model: pr.LearnedIntegrator, mu0: np.ndarray, h: float) -> list[float]:
    """[min, max] of |Γ_p| over the bisection momenta p of one step of h from the exact orbit
    points of ``mu0`` at 21 times in [0, T]: where the step map evaluates S."""
    from poisson_rs.generating import solve_momentum

    orbit = pr.reference_solution(pr.HeavyTop(), mu0, np.linspace(0.0, T, 21)).reshape(-1, 6)
    p, ok = solve_momentum(model.generating, torch.as_tensor(orbit), h)
    g = np.linalg.norm(p.numpy()[ok.numpy(), 3:], axis=1)
    return [float(g.min()), float(g.max())]


def residual_profile(order: int, h: float) -> dict[str, float]:
    """RMS HJ residual of the Taylor terms K = ``order`` alone (t uniform in [0, h]) over the top
    domain |Mᵢ| ≤ 3, 0.95 ≤ |Γ| ≤ 1.05, in bins of |M|: how steeply it grows with |M|."""
    from poisson_rs.train import _sample_domain, hj_residual

    cfg = TrainConfig(
        system=pr.HeavyTop().to_dict(), chart="exp", inputs="t,p", taylor_order=order,
        widths=(1,), domain="top", half_width=3.0, r_min=0.95, r_max=1.05, h_max=h,
    )  # fmt: skip
    s_fn = build_model(cfg)
    _zero_output(s_fn)
    t, p = _sample_domain(cfg, 100_000, torch.Generator().manual_seed(0), torch.float64, "cpu")
    r = hj_residual(s_fn, pr.HeavyTop(), t, p, create_graph=False).numpy()
    m = np.linalg.norm(p[:, :3].numpy(), axis=1)
    edges = (0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.2)
    return {
        f"{a:g}-{b:g}": float(np.sqrt(np.mean(r[(m >= a) & (m < b)] ** 2)))
        for a, b in itertools.pairwise(edges)
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--domain", choices=["cube", "top"], default="top")
    ap.add_argument("--half-width", type=float, default=2.0, help="of μ (cube) or M (top)")
    ap.add_argument("--r-min", type=float, default=0.95, help="of |Γ| (top)")
    ap.add_argument("--r-max", type=float, default=1.05, help="of |Γ| (top)")
    ap.add_argument("--sampling", choices=["uniform", "orbits"], default="uniform")
    ap.add_argument("--train-states", type=int, default=16, help="orbits 'orbits' sampling follows")
    ap.add_argument("--noise", type=float, default=0.05, help="offset of an orbit point, / |μ|")
    ap.add_argument("--fraction", type=float, default=0.9, help="share of points near the orbits")
    ap.add_argument("--widths", type=int, nargs="+", default=[16, 16])
    ap.add_argument("--taylor-order", dest="order", type=int, default=3)
    ap.add_argument("--h", type=float, default=0.5)
    ap.add_argument("--iterations", type=int, default=3000)
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--lr", type=float, default=3e-3)
    ap.add_argument("--lbfgs", type=int, default=0, help="L-BFGS iterations after Adam")
    ap.add_argument("--weight-power", type=float, default=0.0, help="residual / (1+|p|²)^(q/2)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None, help="keep the model file here")
    ap.add_argument("--model", default=None, help="measure this model file or name; no training")
    ap.add_argument("--json", type=Path, default=None, help="append the row (JSON lines)")
    args = ap.parse_args(argv)
    for path in (args.out, args.json):
        if path is not None:
            check_output_path(path)
    torch.set_num_threads(1)
    os.environ.setdefault("RAYON_NUM_THREADS", "1")  # steps/s on one core, like the charts
    top = pr.HeavyTop()
    scene: dict[str, object] = {}
    if args.sampling == "orbits":
        scene = {
            "sampling": "scene",
            "sampling_fraction": args.fraction,
            "sampling_states": tuple(map(tuple, states(7, args.train_states).tolist())),
            "sampling_horizon": T,
            "sampling_noise": args.noise,
        }
    cfg = TrainConfig(
        system=top.to_dict(),
        chart="exp",
        inputs="t,p",
        taylor_order=args.order,
        widths=tuple(args.widths),
        domain=args.domain,
        half_width=args.half_width,
        r_min=args.r_min,
        r_max=args.r_max,
        weight_power=args.weight_power,
        h_max=args.h,
        batch=args.batch,
        iterations=args.iterations,
        lr=args.lr,
        lbfgs_iterations=args.lbfgs,
        seed=args.seed,
        **scene,
    )
    row: dict[str, object] = {
        k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()
    }
    with tempfile.TemporaryDirectory() as tmp:
        if args.model is None:
            t0 = time.perf_counter()
            result = train(cfg, progress=False)
            row["train_seconds"] = round(time.perf_counter() - t0, 1)
            row["validation_rms"] = result.validation_rms
            row["baseline_rms"] = result.baseline_rms
            path = args.out or Path(tmp) / "model.safetensors"
            save_result(result, path, name="heavy_top_learned", command=" ".join(sys.argv))
            model = pr.load_model(path)
        else:
            model = pr.load_model(args.model)
            row["train_seconds"] = model.metadata.get("train_seconds")
            row["parameters"] = model.n_parameters
        base = pr.taylor_integrator(top, args.order)
        mu0 = states(123, 64)
        ref_h = pr.reference_solution(top, mu0, np.array([0.0, args.h]))[:, -1]
        held = (
            states_inside(123, 8, model.domain["half_width"])
            if model.domain["kind"] == "top"
            else mu0[:8]
        )
        ref_t = pr.reference_solution(top, held, np.array([0.0, T]))[:, -1]
        norm = np.linalg.norm(held, axis=1)
        n = round(T / args.h)
        for name, stepper in (("learned", model), ("taylor", base)):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # orbits may leave the domain
                one = np.linalg.norm(pr.integrate(stepper, mu0, args.h, 1)[:, -1] - ref_h, axis=1)
                traj = pr.integrate(stepper, held, args.h, n)
            err = np.linalg.norm(traj[:, -1] - ref_t, axis=1) / norm
            row[f"one_step_median_{name}"] = float(np.median(one))
            row[f"one_step_max_{name}"] = float(one.max())
            row[f"T10_median_{name}"] = float(np.median(err))
            row[f"T10_max_{name}"] = float(err.max())
            row.update(invariants_and_speed(name, stepper, held, traj, args.h))
        row.update(
            invariants_and_speed("learned_full_newton", full_newton(model), held, None, args.h)
        )
        row.update(fit_quality(model, cfg, args.h))
        row["newton_gamma_p_range"] = newton_gamma_range(model, mu0, args.h)
        row["taylor_residual_rms_by_M"] = residual_profile(args.order, args.h)
    ratio = float(row["T10_median_taylor"]) / float(row["T10_median_learned"])  # type: ignore[arg-type]
    row["T10_median_ratio_taylor_over_learned"] = ratio
    print(json.dumps(row, indent=1))
    if args.json is not None:
        with open(args.json, "a", encoding="utf-8") as f:
            f.write(json.dumps(row) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

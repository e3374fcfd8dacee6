"""Accuracy against size and speed: the default recipe trained at several widths and depths.

For each architecture (the hidden widths of the MLP in the default ansatz: Cayley chart, exact
Taylor terms to t³ plus t⁵·|p|⁶·MLP(|p|t, p/|p|)) and seed, :func:`run_sweep` trains a model with
the :class:`~poisson_rs.train.TrainConfig` defaults and measures it on the paper's scene
(I = (1.5, 2, 2.5), h = 0.1, T = 10) against :func:`~poisson_rs.exact_solution`:

- ``error_112``, ``error_320``: |μ(T) − μ_exact(T)| from (1, 1, 2) and from (3, 2, 0);
- ``error_held_out``: the largest such error over 16 held-out states (the paper scene's shell,
  1.5 ≤ |μ| ≤ 2.9, seed 1), which no training option here looks at;
- ``max_rel_dH``: max |H − H₀|/H₀ over [0, T] and the two states;
- ``params``: trainable parameters of the network; ``train_seconds``: wall-clock training time;
- ``steps_per_s``: trajectory steps per second of the Rust rollout, ``integrate`` on a batch of
  64 states (with the rayon threads of the calling process).

Shipped models (by default the paper's 500-250-250-250 network) are measured from their files,
not retrained, and Taylor series without a network give reference rows. Rows are plain dicts
(CSV/JSON ready, :data:`COLUMNS`); the figure is :func:`poisson_rs.studies.figures.sweep_figure`.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import statistics
import time
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..integrators import (
    BisectionIntegrator,
    Stepper,
    integrate,
    list_models,
    load_model,
    taylor_integrator,
)
from ..scenes import ShellStates
from ..structures.lie_poisson import RigidBody
from .demo import PAPER_STATES

if TYPE_CHECKING:
    from ..train import TrainConfig, TrainResult

Row = dict[str, Any]
Progress = Callable[[str], None]

INERTIA = (1.5, 2.0, 2.5)
H = 0.1
HORIZON = 10.0
#: (4, 4) to (64, 64) at depth 2, and one depth-3 network of the size of (32, 32).
ARCHITECTURES: tuple[tuple[int, ...], ...] = (
    (4, 4),
    (8, 8),
    (16, 16),
    (32, 32),
    (16, 16, 16),
    (64, 64),
)
SEEDS = (0, 1, 2)
#: The paper scene's held-out states (``scenes/paper.toml``).
HELD_OUT = ShellStates(1.5, 2.9, 16, seed=1)
SPEED_BATCH = 64
#: Taylor series (order K, chart) measured as reference lines.
BASELINES: tuple[tuple[int, str], ...] = ((3, "cayley"), (5, "cayley"), (3, "exp"), (5, "exp"))
SHIPPED = ("paper",)
#: Where a shipped model was trained, when not on the 2-core CPU (its metadata records the time).
TRAINED_ON = {"paper": "H100"}
#: ``poisson-rs sweep --fast``: two tiny networks, one seed, a few iterations (seconds; tests).
FAST: dict[str, Any] = {
    "architectures": ((4,), (4, 4)),
    "seeds": (0,),
    "iterations": 20,
    "batch": 256,
    "shipped": (),
    "speed_seconds": 0.02,
}

COLUMNS = (
    "model",
    "kind",
    "widths",
    "depth",
    "seed",
    "params",
    "sampling",
    "iterations",
    "train_seconds",
    "trained_on",
    "validation_rms",
    "error_112",
    "error_320",
    "error_held_out",
    "max_rel_dH",
    "converged",
    "steps_per_s",
)
"""Every row's keys, in this order. ``kind``: "learned" (trained here), "shipped" or "taylor";
``widths``: hidden widths joined by "-" ("" without a network); ``sampling``: "uniform" or
"scene F, noise σ" (TrainConfig.sampling_fraction and sampling_noise); ``seed``, ``train_seconds``,
``validation_rms``: None where they do not apply; a failed trajectory's errors are inf."""

_NUMERIC = (
    "params",
    "iterations",
    "train_seconds",
    "validation_rms",
    "error_112",
    "error_320",
    "error_held_out",
    "max_rel_dH",
    "steps_per_s",
)


def label(widths: Sequence[int]) -> str:
    """The name of an architecture: its hidden widths joined by "-", e.g. "16-16-16"."""
    return "-".join(str(w) for w in widths)


def parameter_count(widths: Sequence[int], n_inputs: int = 4) -> int:
    """Weights and biases of a tanh MLP n_inputs → widths → 1."""
    sizes = [n_inputs, *widths, 1]
    return sum((a + 1) * b for a, b in itertools.pairwise(sizes))


def speed_states(n: int = SPEED_BATCH) -> np.ndarray:
    """n seeded states with |μ| uniform between |(1,1,2)| and |(3,2,0)|: (n, 3)."""
    r = np.linalg.norm(PAPER_STATES, axis=1)
    return ShellStates(float(r.min()), float(r.max()), n, seed=0).sample()


def rollout_speed(
    stepper: Stepper,
    *,
    batch: int = SPEED_BATCH,
    h: float = H,
    min_seconds: float = 0.2,
    repeats: int = 3,
) -> float:
    """Trajectory steps per second of ``integrate(stepper, ...)`` on ``batch`` states at step h:
    batch · n_steps / wall-clock seconds, n_steps doubled until one call takes ``min_seconds``
    (after a one-step warm-up, which also starts the rayon pool), then the fastest of
    ``repeats`` calls of that length. A trajectory whose Newton solve fails stops stepping, so
    the speed of a failing stepper is overstated; :func:`measure` reports failures in
    ``converged``."""
    states = speed_states(batch)
    n = 4
    with warnings.catch_warnings():
        # A model trained on a cube sees some of these states outside it: that is not timed.
        warnings.simplefilter("ignore", RuntimeWarning)
        integrate(stepper, states, h, 1, on_failure="ignore")
        while True:
            dt = _timed(stepper, states, h, n)
            if dt >= min_seconds:
                break
            n *= 2
        # Best of several: on a shared machine the other processes only ever add time.
        dt = min([dt, *(_timed(stepper, states, h, n) for _ in range(repeats - 1))])
    return batch * n / dt


def _timed(stepper: Stepper, states: np.ndarray, h: float, n: int) -> float:
    """Wall-clock seconds of one rollout of n steps; every = n keeps only the end states, so the
    time is the stepping's."""
    t0 = time.perf_counter()
    integrate(stepper, states, h, n, every=n, on_failure="ignore")
    return time.perf_counter() - t0


def measure(stepper: Stepper, *, speed_seconds: float = 0.2) -> Row:
    """Accuracy and speed of a stepper on the paper's scene (h = 0.1, T = 10): the measured
    columns of a row (``error_112`` ... ``steps_per_s``, see the module docstring)."""
    body = RigidBody(INERTIA)
    states = np.concatenate([PAPER_STATES, HELD_OUT.sample()])  # (18, 3): scene, then held out
    with warnings.catch_warnings():
        # Failures are reported as inf errors; a held-out state may lie outside a model's domain.
        warnings.simplefilter("ignore", RuntimeWarning)
        traj, info = integrate(
            stepper, states, H, round(HORIZON / H), return_info=True, on_failure="ignore"
        )
    exact = body.reference(states, np.array([HORIZON]))[:, 0]
    err = np.linalg.norm(traj[:, -1] - exact, axis=-1)
    h0 = body.hamiltonian(states[:2])
    with np.errstate(invalid="ignore"):
        dh = np.abs(body.hamiltonian(traj[:2]) - h0[:, None]).max(axis=1) / h0
    bad = ~info.converged | ~np.isfinite(err)
    err = np.where(bad, np.inf, err)
    dh = np.where(bad[:2] | ~np.isfinite(dh), np.inf, dh)
    return {
        "error_112": float(err[0]),
        "error_320": float(err[1]),
        "error_held_out": float(err[2:].max()),
        "max_rel_dH": float(dh.max()),
        "converged": bool(info.converged.all()),
        "steps_per_s": rollout_speed(stepper, min_seconds=speed_seconds),
    }


def _check_architectures(architectures: Sequence[Sequence[int]]) -> list[tuple[int, ...]]:
    if isinstance(architectures, (str, bytes)) or not len(architectures):
        raise ValueError("architectures must be a non-empty list of hidden widths, e.g. [(8, 8)]")
    out = []
    for widths in architectures:
        ws = tuple(widths)
        if not ws or not all(isinstance(w, int) and not isinstance(w, bool) for w in ws):
            raise ValueError(
                f"an architecture must be a non-empty list of integers, got {widths!r}"
            )
        if min(ws) < 1:
            raise ValueError(f"widths must be >= 1, got {widths!r}")
        out.append(ws)
    if len(set(out)) != len(out):
        raise ValueError(f"architectures repeat: {[label(w) for w in out]}")
    return out


def _check_seeds(seeds: Sequence[int]) -> list[int]:
    seeds = list(seeds)
    if not seeds:
        raise ValueError("seeds must not be empty")
    for s in seeds:
        if isinstance(s, bool) or not isinstance(s, int) or s < 0:
            raise ValueError(f"seeds must be integers >= 0, got {s!r}")
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"seeds repeat: {seeds}")
    return seeds


def run_sweep(
    architectures: Sequence[Sequence[int]] = ARCHITECTURES,
    seeds: Sequence[int] = SEEDS,
    *,
    iterations: int | None = None,
    batch: int | None = None,
    overrides: Mapping[str, Any] | None = None,
    shipped: Sequence[str] = SHIPPED,
    baselines: bool = True,
    speed_seconds: float = 0.2,
    models_out: str | Path | None = None,
    progress: Progress | None = None,
    client: Any = None,
    threads: int = 1,
) -> list[Row]:
    """Trains every architecture with every seed and measures it; then the ``shipped`` models
    and (``baselines``) the Taylor series of :data:`BASELINES`. Returns rows (:data:`COLUMNS`),
    learned first, in the order given.

    ``iterations`` and ``batch`` replace the recipe's (None: TrainConfig's 2000 and 2048);
    ``overrides`` sets other TrainConfig fields (not widths or seed), e.g. the sampling.
    ``models_out``: a folder to save each trained model in, as ``{widths}_seed{seed}.safetensors``.
    Everything is checked before the first training run: raises ValueError for no or empty
    architectures, negative or repeated seeds, an unknown shipped model or a bad configuration.

    ``client``: a ``distributed.Client`` that runs each training (and its measurement) as a
    future, on ``threads`` torch threads in its worker; a progress bar follows them. Same
    configurations and seeds, so the same models and accuracy columns as the serial run (the
    timings are the workers').
    """
    from ..train import TrainConfig, save_result

    archs = _check_architectures(architectures)
    seed_list = _check_seeds(seeds)
    known = list_models()
    for name in shipped:
        if name not in known:
            raise ValueError(f"unknown shipped model {name!r}; known: {', '.join(known)}")
    if not (math.isfinite(speed_seconds) and speed_seconds > 0):
        raise ValueError(f"speed_seconds must be > 0, got {speed_seconds!r}")
    extra = dict(overrides or {})
    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    for key in extra:
        if key in ("widths", "seed") or key not in fields:
            raise ValueError(f"overrides cannot set {key!r} (widths and seeds are swept)")
    if iterations is not None:
        extra["iterations"] = iterations
    if batch is not None:
        extra["batch"] = batch
    configs = [
        (w, s, TrainConfig(**{**extra, "widths": w, "seed": s})) for w in archs for s in seed_list
    ]
    for _, _, cfg in configs:
        cfg.validate()
    out_dir = Path(models_out) if models_out is not None else None
    rows: list[Row] = []
    trained: Iterator[tuple[Row, TrainResult]]
    if client is None:
        trained = (_train_row(w, s, cfg, speed_seconds) for w, s, cfg in configs)
    else:
        from ..ensembles import run_all

        jobs: list[tuple[tuple[Any, ...], dict[str, Any]]] = [
            ((w, s, cfg, speed_seconds, threads), {}) for w, s, cfg in configs
        ]
        trained = iter(run_all(client, _train_row, jobs, desc="training", progress=bool(progress)))
    for (widths, seed, _), (row, result) in zip(configs, trained, strict=True):
        name = label(widths)
        if out_dir is not None:
            save_result(
                result,
                out_dir / f"{name}_seed{seed}.safetensors",
                name=f"sweep-{name}-seed{seed}",
                command="poisson_rs.sweep.run_sweep",
            )
        rows.append(row)
        if progress is not None:
            progress(_describe(row))
    for name in shipped:
        m = load_model(name)
        md = m.metadata
        seconds = md.get("train_seconds")
        row = {
            "model": name,
            "kind": "shipped",
            "widths": label(md["widths"]),
            "depth": len(md["widths"]),
            "seed": int(md["seed"]) if "seed" in md else None,
            "params": m.n_parameters,
            "sampling": "uniform",
            "iterations": int(md["iterations"]) if "iterations" in md else None,
            "train_seconds": float(seconds) if seconds is not None else None,
            "trained_on": TRAINED_ON.get(name, "CPU"),
            "validation_rms": float(md["validation_rms_residual"])
            if "validation_rms_residual" in md
            else None,
            **measure(m, speed_seconds=speed_seconds),
        }
        rows.append(row)
        if progress is not None:
            progress(_describe(row))
    if baselines:
        for order, chart in BASELINES:
            taylor = taylor_integrator(RigidBody(INERTIA), order, chart)
            row = {
                "model": f"taylor{order}-{chart}",
                "kind": "taylor",
                "widths": "",
                "depth": 0,
                "seed": None,
                "params": 0,
                "sampling": "",
                "iterations": 0,
                "train_seconds": None,
                "trained_on": "",
                "validation_rms": None,
                **measure(taylor, speed_seconds=speed_seconds),
            }
            rows.append(row)
            if progress is not None:
                progress(_describe(row))
    return [{k: r[k] for k in COLUMNS} for r in rows]


def _train_row(
    widths: tuple[int, ...],
    seed: int,
    cfg: TrainConfig,
    speed_seconds: float,
    threads: int | None = None,
) -> tuple[Row, TrainResult]:
    """Trains one configuration and measures it (in this process or a worker, there on
    ``threads`` torch threads): its row and the training result."""
    from ..train import export_bytes, train

    if threads is not None:
        import torch

        torch.set_num_threads(threads)
    result = train(cfg, progress=False)
    model = BisectionIntegrator(export_bytes(result.model, cfg))
    name = label(widths)
    sampling = cfg.sampling
    if cfg.sampling == "scene":
        sampling = f"scene {cfg.sampling_fraction:g}, noise {cfg.sampling_noise:g}"
    row: Row = {
        "model": name,
        "kind": "learned",
        "widths": name,
        "depth": len(widths),
        "seed": seed,
        "params": model.n_parameters,
        "sampling": sampling,
        "iterations": result.iterations_run,
        "train_seconds": round(result.seconds, 2),
        "trained_on": "CPU",
        "validation_rms": result.validation_rms,
        **measure(model, speed_seconds=speed_seconds),
    }
    return row, result


def _describe(row: Row) -> str:
    seed = "" if row["seed"] is None else f" seed {row['seed']}"
    return (
        f"{row['model']}{seed}: {row['params']} params, error t=10 {row['error_112']:.2e} / "
        f"{row['error_320']:.2e}, held out {row['error_held_out']:.2e}, max dH/H "
        f"{row['max_rel_dH']:.1e}, {row['steps_per_s']:.3g} steps/s"
        + ("" if row["train_seconds"] is None else f", trained in {row['train_seconds']:.1f} s")
    )


def medians(rows: Sequence[Row]) -> list[Row]:
    """One row per model: the median over its seeds of every numeric column (None where any seed
    has none), ``n_seeds``, and ``converged`` only if every seed's rollouts converged."""
    groups: dict[str, list[Row]] = {}
    for r in rows:
        groups.setdefault(r["model"], []).append(r)
    out = []
    for group in groups.values():
        first = group[0]
        row: Row = {k: first[k] for k in ("model", "kind", "widths", "depth", "sampling")}
        row["n_seeds"] = len(group)
        for k in _NUMERIC:
            vals = [r[k] for r in group]
            if any(v is None for v in vals):
                row[k] = None
            elif all(isinstance(v, int) for v in vals):
                row[k] = statistics.median_low(vals)  # counts stay integers
            else:
                row[k] = float(statistics.median(vals))
        row["trained_on"] = first["trained_on"]
        row["converged"] = all(bool(r["converged"]) for r in group)
        out.append(row)
    return out

"""``poisson-rs train``: train a generating function on the Hamilton–Jacobi residual (or a scene's
recipe until its target is met) and write the model file."""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import shlex
from pathlib import Path
from typing import Any

from .common import (
    POSITIVE,
    STEPS,
    number,
    sampling_flags,
    system_spec,
    threads_type,
    vectors,
)

NAME = "train"
#: Integers a training option may take (iterations, batch, points, widths).
COUNT = number(integer=True, low=1, high=10**9)
COUNT0 = number(integer=True, low=0, high=10**9)
SEED = number(integer=True, low=0, high=2**63 - 1)
ORDER = number(integer=True, low=1, high=15)
REAL = number(low=0.0, high=1e12)


def refuse_existing(path: str, flag: str, force: bool) -> None:
    """ValueError when ``path`` exists and ``force`` is off: a finished model (or another run's
    checkpoint) is not replaced without being asked to."""
    if not force and os.path.lexists(path):
        raise ValueError(f"{flag} {path} exists; give --force to replace it")


def add_parser(sub: Any) -> argparse.ArgumentParser:
    t = sub.add_parser(NAME, help="train a generating function on the HJ residual")
    t.add_argument("--preset", choices=["default", "paper"], default="default")
    t.add_argument(
        "--scene",
        default=None,
        help="scene file (TOML): derive the domain from it and stop once its target is met",
    )
    t.add_argument("--out", required=True, help="model file to write (.safetensors)")
    t.add_argument("--name", default=None, help="model name recorded in the file")
    t.add_argument(
        "--inertia", type=POSITIVE, nargs=3, metavar="I", help="the rigid body's principal moments"
    )
    t.add_argument(
        "--system",
        default=None,
        help="the Lie–Poisson system: rigid-body (default), heavy-top (I = (1, 1.5, 2), "
        "mgl = 0.981, χ = (0, 0, 1)), or a JSON file of LiePoissonSystem.to_dict(); other "
        "systems default to the exp chart and, unless H is homogeneous quadratic, 't,p' inputs",
    )
    t.add_argument("--chart", choices=["cayley", "exp"])
    t.add_argument("--widths", type=COUNT, nargs="*", metavar="W", help="hidden layer widths")
    t.add_argument("--inputs", choices=["t,p", "homogeneous"], help="MLP ansatz")
    t.add_argument("--taylor-order", dest="taylor_order", type=ORDER, help="exact Taylor terms K")
    t.add_argument("--mlp-power", dest="mlp_power", type=ORDER, help="m in t^m·MLP")
    t.add_argument("--domain", choices=["cube", "shell", "top"])
    t.add_argument("--r-min", dest="r_min", type=POSITIVE)
    t.add_argument("--r-max", dest="r_max", type=POSITIVE)
    t.add_argument("--half-width", dest="half_width", type=POSITIVE)
    t.add_argument(
        "--weight-power",
        dest="weight_power",
        type=REAL,
        help="divide each HJ residual by (1 + |p|^2)^(q/2) (0: unweighted)",
    )
    t.add_argument("--h-max", dest="h_max", type=POSITIVE, help="t is sampled in [0, h_max]")
    t.add_argument("--batch", type=COUNT)
    t.add_argument("--points", dest="n_points", type=COUNT0, help="fixed point pool (0: resample)")
    t.add_argument("--iterations", type=COUNT0)
    t.add_argument("--lr", type=POSITIVE)
    t.add_argument("--schedule", choices=["cosine", "constant"])
    t.add_argument("--seed", type=SEED)
    t.add_argument(
        "--lbfgs-iterations", dest="lbfgs_iterations", type=COUNT0, help="L-BFGS polish after Adam"
    )
    t.add_argument(
        "--data-weight", dest="data_weight", type=REAL, help="weight λ of the trajectory-data loss"
    )
    t.add_argument(
        "--data-points",
        dest="data_points",
        type=COUNT0,
        help="exact one-step pairs for the data loss",
    )
    t.add_argument("--data-h", dest="data_h", type=POSITIVE, help="step of the data pairs (h_max)")
    sampling_flags(t)
    t.add_argument(
        "--sampling-states",
        dest="sampling_states",
        type=number(low=-1e12, high=1e12),
        nargs="+",
        metavar="X",
        help="initial states whose orbits scene sampling follows: dim numbers each",
    )
    t.add_argument(
        "--sampling-horizon", dest="sampling_horizon", type=POSITIVE, help="orbit time span (10)"
    )
    t.add_argument("--dtype", choices=["float32", "float64"])
    t.add_argument(
        "--device", help="auto (default: CUDA where torch sees it, else the CPU), cpu, cuda, cuda:0"
    )
    t.add_argument(
        "--derivatives",
        choices=["reverse", "autograd"],
        help="how the HJ loss takes dS/dt, dS/dp: hand-written reverse pass (default, faster) or "
        "nested autograd (as the shipped models were trained)",
    )
    t.add_argument("--checkpoint", default=None, help="checkpoint file (written periodically)")
    t.add_argument("--checkpoint-every", dest="checkpoint_every", type=STEPS, default=500)
    t.add_argument("--resume", action="store_true", help="continue from --checkpoint")
    t.add_argument("--no-progress", dest="no_progress", action="store_true")
    t.add_argument(
        "--init",
        choices=["zero", "xavier"],
        help="network start: zero output (training starts from the Taylor terms) or "
        "Xavier-uniform in every layer (the paper; models recorded without this option)",
    )
    t.add_argument(
        "--threads",
        type=threads_type,
        default=None,
        help="torch threads (default: 1 on a machine with <= 2 cores, else torch's default)",
    )
    t.add_argument(
        "--max-seconds",
        dest="max_seconds",
        type=POSITIVE,
        default=None,
        help="stop training after this wall time and save the model reached (default: no limit)",
    )
    t.add_argument(
        "--force",
        action="store_true",
        help="replace an existing --out (and --checkpoint) file, and train a scene even when "
        "its Taylor terms alone meet the target",
    )
    _document_train_flags(t)
    return t


def run(args: argparse.Namespace) -> int:

    from ..files import check_output_path, probe_writable
    from ..train import PRESETS, TrainConfig, baseline_rms, save_result, train, use_threads

    # Every check before any work: a bad output would otherwise fail after the training.
    check_output_path(args.out)
    refuse_existing(args.out, "--out", args.force)
    if args.checkpoint is not None:
        check_output_path(args.checkpoint)
        # --resume reads the checkpoint it will then replace: that is what it is for.
        if not args.resume:
            refuse_existing(args.checkpoint, "--checkpoint", args.force)
    # The write path itself, tried before the work (a name can pass every check and still fail).
    probe_writable(args.out)
    if args.checkpoint is not None:
        probe_writable(args.checkpoint)
    # One thread policy for the CLI and train(): torch's threads and rayon's (scene evaluations).
    threads = use_threads(args.threads, "--threads")

    flags: dict[str, Any] = {}
    for f in dataclasses.fields(TrainConfig):
        v = getattr(args, f.name, None)
        if v is not None:
            flags[f.name] = tuple(v) if isinstance(v, list) else v
    if args.n_points == 0:
        flags["n_points"] = None
    dim = 3
    if "system" in flags:
        system = system_spec(flags["system"])
        flags["system"] = system.to_dict()
        dim = system.dim
        if "chart" not in flags and not system.algebra.is_so3():
            flags["chart"] = "exp"
        if "inputs" not in flags and not system.polynomial.is_homogeneous(2):
            flags["inputs"] = "t,p"
    if "sampling_states" in flags:
        flags["sampling_states"] = vectors(flags["sampling_states"], dim, "--sampling-states")
    command = "poisson-rs " + shlex.join(args.argv)
    if args.scene is not None:
        import json

        from ..integrators import load_model
        from ..scenes import train_scene

        path = train_scene(
            args.scene,
            args.out,
            progress=not args.no_progress,
            command=command,
            name=args.name,
            overrides=flags,
            max_seconds=args.max_seconds,
            force=args.force,
        )
        if path is None:
            return 0  # the Taylor terms alone meet the target: nothing to train
        met = json.loads(load_model(path).metadata["target_met"])
        print(f"scene target {'met' if met else 'NOT met'} -> {path}")
        return 0 if met else 1
    cfg = TrainConfig(**{**PRESETS[args.preset], **flags})
    cfg.validate()
    print(f"training: {cfg} on {threads} torch thread(s)")
    print(
        f"baseline: the Taylor terms alone (K = {cfg.taylor_order}, no network) have validation "
        f"RMS residual {baseline_rms(cfg):.3e}"
    )
    if cfg.lbfgs_iterations:
        print(
            f"then an L-BFGS polish of up to {cfg.lbfgs_iterations} iterations (full batch; "
            "its losses are reported when it ends)",
            flush=True,
        )
    result = train(
        cfg,
        checkpoint=args.checkpoint,
        checkpoint_every=args.checkpoint_every,
        resume=args.resume,
        progress=not args.no_progress,
        max_seconds=args.max_seconds,
    )
    if result.timed_out:
        print(f"stopped after {result.iterations_run} iterations: --max-seconds reached")
    if result.lbfgs_losses:
        first, last = result.lbfgs_losses[0], result.lbfgs_losses[-1]
        print(
            f"L-BFGS polish: {result.lbfgs_iterations_run} iterations, "
            f"{len(result.lbfgs_losses)} loss evaluations, loss {first:.3e} -> {last:.3e}"
        )
    if not math.isfinite(result.final_loss):
        raise ValueError(
            f"training diverged (final loss {result.final_loss}); nothing written to {args.out}"
        )
    name = args.name or Path(args.out).stem
    path = save_result(result, args.out, name=name, command=command)
    its = max(result.iterations_run, 1)
    print(
        f"final loss {result.final_loss:.3e}, "
        f"validation RMS residual {result.validation_rms:.3e} "
        f"(Taylor terms alone: {result.baseline_rms:.3e}), "
        f"{result.seconds:.1f} s ({result.seconds / its:.4f} s/iteration) -> {path}"
    )
    return 0


#: Help for the ``train`` options that have none inline; _document_train_flags adds defaults.
_TRAIN_HELP = {
    "preset": "named configuration the other options override",
    "inertia": "principal moments of inertia I1 I2 I3",
    "chart": "chart of the symplectic groupoid",
    "domain": "training domain of the momenta p",
    "r_min": "inner radius of the shell domain (of |Gamma| in the top domain)",
    "r_max": "outer radius of the shell domain (of |Gamma| in the top domain)",
    "half_width": "half width of the cube domain (of M in the top domain)",
    "batch": "training points per Adam iteration",
    "iterations": "Adam iterations",
    "lr": "Adam learning rate",
    "schedule": "learning-rate schedule (cosine: decay to 1%% of --lr)",
    "seed": "random seed (initialisation and points)",
    "dtype": "floating-point type of training",
    "checkpoint_every": "iterations between two checkpoints",
    "no_progress": "no progress bar",
}


def _document_train_flags(t: argparse.ArgumentParser) -> None:
    """Gives every ``train`` option a help text that shows its default: the TrainConfig default
    (and the paper preset's, where it differs), since the flags themselves default to None."""
    from ..train import PRESETS, TrainConfig

    defaults = {f.name: f.default for f in dataclasses.fields(TrainConfig)}
    for action in t._actions:
        if action.dest in ("help", "out", "scene", "name", "resume", "checkpoint"):
            continue
        text = action.help or _TRAIN_HELP.get(action.dest, "")
        if "default" in text:
            action.help = text
            continue
        if action.dest in defaults:
            shown = defaults[action.dest]
            paper = PRESETS["paper"].get(action.dest, shown)
            extra = f"; paper preset: {paper}" if paper != shown else ""
            text += f" (default: {'none' if shown is None else shown}{extra})"
        elif action.default not in (None, False):
            text += " (default: %(default)s)"
        action.help = text.strip()

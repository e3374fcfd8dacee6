"""``poisson-rs learn DATA --algebra so3 --h 0.1 --out model.safetensors``.

Exposes :func:`add_parser` (registers the subcommand on an argparse ``subparsers``) and
:func:`run` (executes parsed arguments, returns the exit status).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import sys
from pathlib import Path

from ..files import atomic_write_bytes, check_output_path
from ..structures.lie_poisson import LieAlgebra, LiePoissonSystem
from ..untrusted import parsing

__all__ = ["add_parser", "run"]


#: The subcommand this module adds (``poisson-rs learn``).
NAME = "learn"


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Adds the ``learn`` subcommand; returns its parser."""
    p = subparsers.add_parser(
        "learn",
        help="learn a Poisson integrator from trajectories",
        description=(
            "Learn a Poisson integrator from trajectories (.npz, .csv or a Zarr store) whose "
            "Poisson structure is known: a polynomial Hamiltonian stepped by Taylor-HJ, or the "
            "generating function of the time-h map."
        ),
    )
    p.add_argument("data", help="trajectory file: .npz, .csv or a Zarr directory")
    p.add_argument(
        "--algebra",
        default="so3",
        help="so3, se3, sl2, or a JSON file with structure constants {'structure_constants': ...}",
    )
    p.add_argument("--h", required=True, help="time between records (> 0)")
    p.add_argument("--mode", default="auto", choices=("auto", "hamiltonian", "map", "hj+data"))
    p.add_argument(
        "--degree",
        default=None,
        help="polynomial degree of H (mode hamiltonian) or of the correction (mode hj+data)",
    )
    p.add_argument(
        "--system",
        default=None,
        help="mode hj+data: JSON file of the known system (LiePoissonSystem.to_dict())",
    )
    p.add_argument("--out", required=True, help="model file to write (.safetensors)")
    p.add_argument("--seed", default="0", help="seed of the held-out split and of the network")
    p.add_argument("--force", action="store_true", help="replace an existing --out file")
    p.set_defaults(func=run)
    return p


def _algebra(spec: str) -> LieAlgebra | str:
    if spec in ("so3", "se3", "sl2"):
        return spec
    with parsing(f"--algebra {spec}", "structure_constants"):
        if not os.path.isfile(spec):
            raise ValueError("not so3, se3, sl2 or an existing JSON file")
        with open(spec, encoding="utf-8") as fh:
            raw = json.load(fh)
        return LieAlgebra.from_dict(raw)


def run(args: argparse.Namespace) -> int:
    """Runs ``learn``: writes the model file and prints the report. Returns 0 on success."""
    from .api import learn

    with parsing("--h", None):
        h = float(args.h)
        if not (math.isfinite(h) and h > 0):
            raise ValueError(f"must be finite and > 0, got {args.h}")
    with parsing("--seed", None):
        seed = int(args.seed)
    degree = None
    if args.degree is not None:
        with parsing("--degree", None):
            degree = int(args.degree)
    system = None
    if args.system is not None:
        with parsing(f"--system {args.system}", "system"):
            with open(args.system, encoding="utf-8") as fh:
                system = LiePoissonSystem.from_dict(json.load(fh))
    out = Path(args.out)
    check_output_path(out)
    if out.exists() and not args.force:
        print(f"error: {out} exists; pass --force to replace it", file=sys.stderr)
        return 2
    command = "poisson-rs " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    _, report = learn(
        args.data,
        h,
        algebra=None if system is not None else _algebra(args.algebra),
        system=system,
        mode=args.mode,
        degree=degree,
        seed=seed,
        command=command,
    )
    atomic_write_bytes(out, report.kept.model_bytes)
    print(report)
    print(f"wrote {out}")
    return 0

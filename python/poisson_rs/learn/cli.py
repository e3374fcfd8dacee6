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

from ..files import atomic_write_bytes, check_output_path, probe_writable, read_input_bytes
from ..structures.lie_poisson import LieAlgebra
from ..untrusted import parsing
from .data import MAX_SYSTEM_FILE_BYTES, read_system_file

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
        default=None,
        help="the Poisson structure (required unless --system gives it): so3, se3, sl2, or a "
        "JSON file with structure constants {'structure_constants': ...}; nothing is assumed",
    )
    p.add_argument("--h", required=True, help="time between records (> 0)")
    p.add_argument("--mode", default="auto", choices=("auto", "hamiltonian", "map", "hj+data"))
    p.add_argument(
        "--degree",
        default=None,
        help="polynomial degree of H (mode hamiltonian) or of the correction (mode hj+data), 1..4",
    )
    p.add_argument(
        "--max-degree",
        default=None,
        help="the largest degree of H modes auto and hamiltonian try, 1..4 (default 4)",
    )
    p.add_argument(
        "--system",
        default=None,
        help="mode hj+data: JSON file of the known system (LiePoissonSystem.to_dict()); gives "
        "the algebra too",
    )
    p.add_argument("--out", required=True, help="model file to write (.safetensors)")
    p.add_argument("--seed", default="0", help="seed of the held-out split and of the network")
    p.add_argument(
        "--force",
        action="store_true",
        help="replace an existing --out file (also one that appears while learning)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
    return p


def _algebra(spec: str) -> LieAlgebra | str:
    if spec in ("so3", "se3", "sl2"):
        return spec
    with parsing(f"--algebra {spec}", "structure_constants"):
        if not os.path.isfile(spec):
            raise ValueError("not so3, se3, sl2 or an existing JSON file")
        raw = json.loads(read_input_bytes(spec, max_bytes=MAX_SYSTEM_FILE_BYTES, what="file"))
        return LieAlgebra.from_dict(raw)


def run(args: argparse.Namespace) -> int:
    """Runs ``learn``: writes the model file and prints the report. Returns 0 on success.

    Everything is checked before the fit: the numbers, the algebra (never assumed), the system
    file, and the output (a writable path, probed by writing a temporary file beside it; an
    existing file without ``--force``). The model is then linked in place only where nothing
    is, unless ``--force``: a file that appeared at ``--out`` during the fit is not replaced."""
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
    max_degree = None
    if getattr(args, "max_degree", None) is not None:
        with parsing("--max-degree", None):
            max_degree = int(args.max_degree)
    system = None
    if args.system is not None:
        system = read_system_file(args.system, f"--system {args.system}")
    if system is None and args.algebra is None:
        raise ValueError(
            "--algebra: the Poisson structure is not assumed; give --algebra (so3, se3, sl2 or "
            "a JSON file of structure constants) or --system"
        )
    out = Path(args.out)
    check_output_path(out)
    if os.path.lexists(out) and not args.force:
        print(f"error: {out} exists; pass --force to replace it", file=sys.stderr)
        return 2
    # The write path itself, tried before the fit (a path can pass every check and still fail).
    probe_writable(out)
    command = "poisson-rs " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    _, report = learn(
        args.data,
        h,
        algebra=None if system is not None else _algebra(args.algebra),
        system=system,
        mode=args.mode,
        degree=degree,
        max_degree=max_degree,
        seed=seed,
        command=command,
        progress=False if getattr(args, "no_progress", False) else None,
    )
    print(report)
    try:
        atomic_write_bytes(out, report.kept.model_bytes, replace=args.force)
    except ValueError as exc:
        print(
            f"error: {exc}; give --force to replace it (the model was not written)", file=sys.stderr
        )
        return 2
    print(f"wrote {out}")
    return 0

"""``poisson-rs learn DATA --algebra so3 --h 0.1 --out model.safetensors``, and on any structure
``poisson-rs learn DATA --structure SYSTEM.json|discover --h 0.1 --out learned.json``.

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
import time
import warnings
from pathlib import Path
from typing import Any

from ..files import atomic_write_bytes, check_output_path, probe_writable, read_input_bytes
from ..structures.lie_poisson import LieAlgebra
from ..untrusted import parsing
from .data import MAX_SYSTEM_FILE_BYTES, check_seed, read_system_file
from .options import MAX_DEGREE

__all__ = [
    "NOT_EXPLAINED_STATUS",
    "SYSTEM_FILE_FORMAT",
    "add_parser",
    "run",
    "system_document",
]


#: The subcommand this module adds (``poisson-rs learn``).
NAME = "learn"
#: Exit status of a structure discovery whose data no (bracket, H) pair explained.
NOT_EXPLAINED_STATUS = 3
#: The ``learned.format`` entry of a learned-system JSON file.
SYSTEM_FILE_FORMAT = "poisson_rs learned system"
#: Suffixes of the two kinds of output.
MODEL_SUFFIX, SYSTEM_SUFFIX = ".safetensors", ".json"

_EPILOG = f"""\
output (--out):
  A Lie-Poisson model (--algebra, --system, or --structure naming a Lie-Poisson
  system file) is a model file: --out must end in {MODEL_SUFFIX} (read it with
  --model, or pr.load_model). Any other learned system (--structure naming
  another structure, and --structure discover, whatever bracket it finds) is a
  JSON file: --out must end in {SYSTEM_SUFFIX}. It holds the learned system's
  to_dict() (poisson-rs demo --system OUT.json, learn --structure OUT.json and
  pr.system_from_dict read it), plus a "learned" entry: the integrator that
  rebuilds the same stepper (pr.taylor_integrator(system, order, chart)) and
  the report's summary. The suffix is checked before the fit, and an existing
  --out is replaced only with --force.

exit status:
  0  learned and written
  2  bad input (a flag, a file, the data, --out): one line on stderr, nothing
     learned or written
  {NOT_EXPLAINED_STATUS}  --structure discover: NOT EXPLAINED (no bracket and H pair reached
     the data's noise level); the report is printed and nothing is written,
     unless --keep-unexplained (the best pair tried is then written, and the
     status is still {NOT_EXPLAINED_STATUS})
"""


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Adds the ``learn`` subcommand; returns its parser."""
    p = subparsers.add_parser(
        "learn",
        help="learn a Poisson integrator from trajectories",
        description=(
            "Learn a Poisson integrator from trajectories (.npz, .csv or a Zarr store): on a "
            "known Lie-Poisson structure (--algebra, --system) a polynomial Hamiltonian stepped "
            "by Taylor-HJ, or the generating function of the time-h map; on any other known "
            "structure (--structure SYSTEM.json) H through that structure's own Taylor-HJ "
            "integrator; with --structure discover the bracket and H both."
        ),
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("data", help="trajectory file: .npz, .csv or a Zarr directory")
    p.add_argument(
        "--algebra",
        default=None,
        help="the Poisson structure (required unless --system or --structure gives it): so3, "
        "se3, sl2, or a JSON file with structure constants {'structure_constants': ...}; "
        "nothing is assumed",
    )
    p.add_argument(
        "--structure",
        default=None,
        metavar="SYSTEM.json|discover",
        help="the Poisson structure as any system's to_dict() in a JSON file (its own H is "
        "ignored, an expression system's bracket is its 'structure' entry's; modes auto and "
        "hamiltonian, and map on a Lie-Poisson system), or the word discover: the bracket is "
        "learned too (modes auto and hamiltonian). Not with --algebra or --system",
    )
    p.add_argument("--h", required=True, help="time between records (> 0)")
    p.add_argument("--mode", default="auto", choices=("auto", "hamiltonian", "map", "hj+data"))
    p.add_argument(
        "--degree",
        default=None,
        help=f"polynomial degree of H (mode hamiltonian) or of the correction (mode hj+data), "
        f"1..{MAX_DEGREE}",
    )
    p.add_argument(
        "--max-degree",
        default=None,
        help=f"the largest degree of H modes auto and hamiltonian try, 1..{MAX_DEGREE} "
        f"(default {MAX_DEGREE})",
    )
    p.add_argument(
        "--system",
        default=None,
        help="mode hj+data: JSON file of the known system (LiePoissonSystem.to_dict()); gives "
        "the algebra too",
    )
    p.add_argument(
        "--out",
        required=True,
        help=f"file to write: {MODEL_SUFFIX} for a Lie-Poisson model, {SYSTEM_SUFFIX} for "
        "any other learned system (see below)",
    )
    p.add_argument("--seed", default="0", help="seed of the held-out split and of the network")
    p.add_argument(
        "--force",
        action="store_true",
        help="replace an existing --out file (also one that appears while learning)",
    )
    p.add_argument(
        "--keep-unexplained",
        action="store_true",
        help=f"--structure discover: write the best pair tried even when the data are NOT "
        f"EXPLAINED (the exit status is still {NOT_EXPLAINED_STATUS})",
    )
    p.add_argument(
        "--max-seconds",
        help="--structure discover: a time budget (s); no pair after the first is started once "
        "it is spent, and the best tried is kept",
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


def _degree(text: str, flag: str) -> int:
    with parsing(flag, None):
        try:
            value = int(text)
        except ValueError:
            value = 0
        if not 1 <= value <= MAX_DEGREE:
            raise ValueError(f"must be an integer in 1..{MAX_DEGREE}, got {text!r}")
        return value


def _structure(spec: str, mode: str) -> Any:
    """The system ``--structure`` names (a JSON file of any system's ``to_dict()``), checked
    against ``mode``: ValueError naming the flag for a file that cannot be read, is not JSON,
    is not a system, or offers no learning in ``mode``."""
    from ..structures import system_from_dict

    with parsing(f"--structure {spec}"):
        raw = read_input_bytes(spec, max_bytes=MAX_SYSTEM_FILE_BYTES, what="system file")
        try:
            data = json.loads(raw.decode("utf-8"))
        except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError
            raise ValueError(f"not a JSON file ({exc})") from None
        if not isinstance(data, dict):
            raise ValueError("must hold a JSON object (a system's to_dict())")
        system = system_from_dict(data)
    if getattr(system, "kind", None) == "expression":
        # Its bracket is its 'structure' entry's (the term library's results are such files):
        # that system offers the Hamiltonian families, and the H is ignored either way.
        system = system.base
    title = getattr(system, "title", type(system).__name__)
    if getattr(system, "trainable", False):  # Lie–Poisson: learned on T*G, as --algebra
        if mode == "hj+data":
            raise ValueError(
                f"--structure {spec}: mode hj+data takes the known H from --system; --structure "
                "gives the structure only (its H is ignored)"
            )
        return system
    modes = tuple(system.learn_modes()) if hasattr(system, "learn_modes") else ()
    if mode not in modes:
        why = (
            f"the modes that apply to it: {', '.join(modes)}"
            if modes
            else "no mode applies to it (it offers no Hamiltonian family to learn)"
        )
        raise ValueError(f"--structure {spec}: --mode {mode} does not apply to {title}; {why}")
    return system


def _json_safe(value: Any) -> Any:
    """``value`` with every non-finite float as None (the file is strict JSON)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if hasattr(value, "item"):  # a numpy scalar
        return _json_safe(value.item())
    return value


def _integrator_settings(report: Any) -> dict[str, Any]:
    """What rebuilds the learned stepper: ``pr.taylor_integrator(system, order, chart)``."""
    system, kept = report.structure, report.kept
    chart = getattr(getattr(kept.fit, "family", None), "chart", None)
    if chart is None:
        charts = tuple(system.taylor_charts())
        chart = charts[0] if charts else None
    return {"method": "taylor-hj", "order": int(kept.order), "chart": chart}


def system_document(report: Any, command: str, seconds: float) -> dict[str, Any]:
    """The JSON a learned system is written as: its ``to_dict()`` (any system reader takes it)
    plus ``learned``: the format, the integrator's settings, the report's summary."""
    kept = report.kept
    doc = dict(report.structure.to_dict())
    if "learned" in doc:
        raise ValueError("the learned system's to_dict() has a 'learned' entry already")
    doc["learned"] = _json_safe(
        {
            "format": SYSTEM_FILE_FORMAT,
            "version": 1,
            "integrator": _integrator_settings(report),
            "report": {
                "mode": report.mode,
                "explained": report.explained,
                "kept": kept.family,
                "reason": kept.reason,
                "errors_on": "held-out" if report.held_out else "training",
                "one_step": kept.one_step,
                "rollout": kept.rollout,
                "rollout_span": report.span,
                "threshold": report.threshold,
                "noise": report.noise,
                "h": report.h,
                "seed": report.seed,
                "data_sha256": report.data_sha256,
                "data_shape": list(report.data_shape),
                "hamiltonian": report.hamiltonian_text,
                "hamiltonian_family": report.hamiltonian_family,
                "gauge": report.gauge,
                "bracket": report.bracket,
                "bracket_family": kept.bracket_family,
                "jacobi_residual": kept.jacobi_residual,
                "casimirs": kept.casimirs_text,
                "candidates": report.rows(),
            },
            "command": command,
            "seconds": round(seconds, 3),
        }
    )
    return doc


def run(args: argparse.Namespace) -> int:
    """Runs ``learn``: writes the model or system file and prints the report. Returns 0 on
    success, :data:`NOT_EXPLAINED_STATUS` where structure discovery explained nothing.

    Everything is checked before the fit: the numbers, the structure (never assumed: --algebra,
    --system or --structure), the system files, and the output (its suffix for the result the
    input asks for, a writable path probed by writing a temporary file beside it, an existing
    file without ``--force``). The result is then linked in place only where nothing is, unless
    ``--force``: a file that appeared at ``--out`` during the fit is not replaced."""
    from .api import learn

    with parsing("--h", None):
        h = float(args.h)
        if not (math.isfinite(h) and h > 0):
            raise ValueError(f"must be finite and > 0, got {args.h}")
    with parsing("--seed", None):
        seed = check_seed(int(args.seed))
    degree = None if args.degree is None else _degree(args.degree, "--degree")
    max_degree = None
    if getattr(args, "max_degree", None) is not None:
        max_degree = _degree(args.max_degree, "--max-degree")
        if degree is not None and degree > max_degree:
            raise ValueError(f"--degree {degree} exceeds --max-degree {max_degree}")
    max_seconds = None
    if getattr(args, "max_seconds", None) is not None:
        with parsing("--max-seconds", None):
            max_seconds = float(args.max_seconds)
            if not (math.isfinite(max_seconds) and max_seconds > 0):
                raise ValueError(f"must be finite and > 0, got {args.max_seconds}")
    spec = getattr(args, "structure", None)
    if max_seconds is not None and spec != "discover":
        raise ValueError("--max-seconds applies to --structure discover only")
    structure: Any = None
    if spec is not None:
        if args.algebra is not None or args.system is not None:
            raise ValueError(
                f"--structure {spec}: give the structure once: --structure, or --algebra / "
                "--system, not both"
            )
        if spec == "discover":
            if args.mode not in ("auto", "hamiltonian"):
                raise ValueError(
                    f"--structure discover: --mode {args.mode} does not apply to structure "
                    "discovery; the modes that apply to it: auto, hamiltonian"
                )
            structure = "discover"
        else:
            structure = _structure(spec, args.mode)
    system = None
    if args.system is not None:
        system = read_system_file(args.system, f"--system {args.system}")
    if system is None and args.algebra is None and structure is None:
        raise ValueError(
            "--algebra: the Poisson structure is not assumed; give --algebra (so3, se3, sl2 or "
            "a JSON file of structure constants), --system, or --structure (a system file, or "
            "discover)"
        )
    algebra = None if system is not None or structure is not None else _algebra(args.algebra)
    # A Lie–Poisson structure gives a model file; any other learned system a JSON file.
    writes_model = structure is None or getattr(structure, "trainable", False)
    out = Path(args.out)
    suffix = MODEL_SUFFIX if writes_model else SYSTEM_SUFFIX
    if out.suffix.lower() != suffix:
        what = (
            "a Lie-Poisson model is written as a model file"
            if writes_model
            else "a learned system (not a Lie-Poisson model file) is written as JSON"
        )
        raise ValueError(f"--out {out}: {what}; give a path ending in {suffix}")
    with parsing(f"--out {out}"):
        check_output_path(out)
    if os.path.lexists(out) and not args.force:
        print(f"poisson-rs learn: --out {out} exists; pass --force to replace it", file=sys.stderr)
        return 2
    # The write path itself, tried before the fit (a path can pass every check and still fail).
    with parsing(f"--out {out}"):
        probe_writable(out)
    command = "poisson-rs " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        # The report says NOT EXPLAINED itself, and the exit status tells a script.
        from .discover import NotExplainedWarning

        warnings.simplefilter("ignore", NotExplainedWarning)
        _, report = learn(
            args.data,
            h,
            algebra=algebra,
            system=system,
            structure=structure,
            mode=args.mode,
            degree=degree,
            max_degree=max_degree,
            seed=seed,
            command=command,
            progress=False if getattr(args, "no_progress", False) else None,
            max_seconds=max_seconds,
        )
    seconds = time.perf_counter() - t0
    print(report)
    status = 0
    if not report.explained:
        status = NOT_EXPLAINED_STATUS
        if not getattr(args, "keep_unexplained", False):
            print(
                f"poisson-rs learn: NOT EXPLAINED: no candidate reached the data's noise level; "
                f"{out} not written (--keep-unexplained writes the best tried)",
                file=sys.stderr,
            )
            return status
    if writes_model:
        raw = report.kept.model_bytes
    else:
        doc = system_document(report, command, seconds)
        raw = (json.dumps(doc, indent=1, allow_nan=False) + "\n").encode("utf-8")
    try:
        atomic_write_bytes(out, raw, replace=args.force)
    except ValueError as exc:
        print(
            f"poisson-rs learn: --out: {exc}; give --force to replace it (nothing was written)",
            file=sys.stderr,
        )
        return 2
    print(f"wrote {out} (learned in {seconds:.1f} s)")
    return status

"""``poisson-rs sweep``: accuracy against parameter count and rollout speed, over network sizes."""

from __future__ import annotations

import argparse
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .common import (
    check_out_dir,
    check_scheduler,
    number,
    sampling_flags,
    scheduler,
    scheduler_flag,
    table,
    threads_type,
)

NAME = "sweep"
#: The fields ``sweep --replot`` draws from; a file without them is refused in one line.
REPLOT_FIELDS = ("kind", "model", "params", "depth", "error_112", "error_320", "steps_per_s")


def read_rows(path: str) -> list[dict[str, Any]]:
    """The rows of a saved sweep (``sweep.json``), checked before they are drawn."""
    import json

    from ..files import check_input_file
    from ..untrusted import parsing

    check_input_file(path, max_bytes=64 << 20, what="sweep rows file")
    with parsing(f"--replot {path}"):
        rows = json.loads(Path(path).read_text(encoding="utf-8"))
        if not isinstance(rows, list) or not rows or not all(isinstance(r, dict) for r in rows):
            raise ValueError("must hold a non-empty JSON list of sweep rows (sweep.json)")
    for i, r in enumerate(rows):
        missing = [k for k in REPLOT_FIELDS if k not in r]
        if missing:
            from ..untrusted import InputError

            raise InputError(
                f"--replot {path}", f"row {i}", f"no {', '.join(missing)}: not a sweep's rows"
            )
    return rows


def add_parser(sub: Any) -> argparse.ArgumentParser:
    sw = sub.add_parser(
        NAME, help="accuracy against parameter count and rollout speed, over network sizes"
    )
    sw.add_argument("--out", default="out/sweep", help="output folder (default: out/sweep)")
    sw.add_argument("--stem", default="sweep", help="file name stem (default: sweep)")
    sw.add_argument(
        "--widths", nargs="+", metavar="W,W", help="architectures, e.g. 8,8 16,16,16 (default: 6)"
    )
    sw.add_argument(
        "--seeds",
        type=number(integer=True, low=0, high=2**63 - 1),
        nargs="+",
        help="training seeds (default: 0 1 2)",
    )
    sw.add_argument(
        "--iterations",
        type=number(integer=True, low=1, high=10**9),
        help="Adam iterations (default: 2000)",
    )
    sampling_flags(sw)
    sw.add_argument("--no-paper", dest="no_paper", action="store_true", help="skip the paper model")
    sw.add_argument("--fast", action="store_true", help="two tiny networks, 20 iterations (tests)")
    sw.add_argument(
        "--threads", type=threads_type, default=1, help="torch and rayon threads (default 1)"
    )
    sw.add_argument("--models-out", dest="models_out", help="folder to save the trained models in")
    sw.add_argument("--replot", metavar="JSON", help="redraw the chart from rows saved")
    sw.add_argument("--title", default=None, help="figure title")
    sw.add_argument("--no-progress", dest="no_progress", action="store_true")
    scheduler_flag(sw)
    return sw


def _architectures(values: Sequence[str]) -> list[tuple[int, ...]]:
    """Architectures from "8,8" "16,16,16" to [(8, 8), (16, 16, 16)]; ValueError if malformed."""
    out = []
    for v in values:
        try:
            out.append(tuple(int(w) for w in v.split(",")))
        except ValueError:
            raise ValueError(f"--widths takes integers like 8,8 or 16,16,16; got {v!r}") from None
    return out


def _sweep_title(rows: Sequence[dict[str, Any]]) -> str:
    """What a sweep trained, from its rows: iterations, seeds and sampling of the learned ones."""
    learned = [r for r in rows if r["kind"] == "learned"]
    if not learned:
        return ""
    its = sorted({r["iterations"] for r in learned})
    seeds = sorted({r["seed"] for r in learned})
    sampling = ", ".join(sorted({r["sampling"] for r in learned}))
    return (
        f"Default recipe (Cayley, Taylor K=3 + t⁵·MLP) at several sizes: "
        f"{'/'.join(map(str, its))} Adam iterations, seeds {', '.join(map(str, seeds))}, "
        f"{sampling} sampling; paper's scene, h = 0.1, T = 10"
    )


def run(args: argparse.Namespace) -> int:
    import time

    from ..files import check_output_path, check_outputs
    from ..studies import figures as charts
    from ..studies.sweep import FAST, medians, run_sweep

    out = check_out_dir(args.out)
    check_scheduler(args.scheduler)
    png = out / f"{args.stem}.png"
    stems = (args.stem, f"{args.stem}_medians")
    check_outputs(out, [f"{args.stem}.png", *(f"{x}.{e}" for x in stems for e in ("csv", "json"))])
    if args.models_out is not None:
        check_output_path(args.models_out, kind="dir")
    if args.replot is not None:
        rows = read_rows(args.replot)
        charts.sweep_figure(rows, png, title=args.title or _sweep_title(rows))
        print(f"wrote {png}")
        return 0
    import torch

    # One torch thread for training and one rayon thread for the rollouts (read when the rayon
    # pool starts, at this process's first rollout): costs per core, steady on a shared machine.
    torch.set_num_threads(args.threads)
    os.environ.setdefault("RAYON_NUM_THREADS", str(args.threads))
    kwargs: dict[str, Any] = dict(FAST) if args.fast else {}
    if args.widths is not None:
        kwargs["architectures"] = _architectures(args.widths)
    if args.seeds is not None:
        kwargs["seeds"] = args.seeds
    if args.iterations is not None:
        kwargs["iterations"] = args.iterations
    if args.no_paper:
        kwargs["shipped"] = ()
    overrides: dict[str, Any] = {}
    for key in ("sampling", "sampling_fraction", "sampling_noise"):
        if getattr(args, key) is not None:
            overrides[key] = getattr(args, key)
    if overrides.get("sampling") == "scene":
        # The orbits of the states the sweep measures: the paper's two.
        from ..studies.demo import PAPER_STATES

        overrides["sampling_states"] = tuple(map(tuple, PAPER_STATES.tolist()))
    t0 = time.perf_counter()
    with scheduler(args.scheduler) as client:
        rows = run_sweep(
            overrides=overrides,
            models_out=args.models_out,
            progress=None if args.no_progress else lambda m: print(f"  {m}", flush=True),
            client=client,
            threads=args.threads,
            **kwargs,
        )
    charts.write_rows(rows, out / f"{args.stem}.csv")
    med = medians(rows)
    charts.write_rows(med, out / f"{args.stem}_medians.csv")
    charts.sweep_figure(rows, png, title=args.title or _sweep_title(rows))
    cols = ["model", "params", "error_112", "error_320", "error_held_out", "max_rel_dH"]
    print(table(med, [*cols, "steps_per_s", "train_seconds"]))
    print(
        f"wrote {png}, {args.stem}.csv/json and {args.stem}_medians.csv/json to {out} "
        f"in {time.perf_counter() - t0:.0f} s"
    )
    return 0

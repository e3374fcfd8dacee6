"""``poisson-rs select SCENE.toml``: the cheapest integrator and step that meet a target on a
scene's states, by the pointwise error at T, the energy error or the Casimir drift over [0, T]."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any

from .common import MAX_STEPS, POSITIVE, number, threads_type

NAME = "select"
METRICS = ("error", "energy", "casimir")


def add_parser(sub: Any) -> argparse.ArgumentParser:
    se = sub.add_parser(
        NAME, help="the cheapest integrator and step meeting an error target on a scene"
    )
    se.add_argument("scene", help="scene file (TOML); its [select] table gives the defaults")
    se.add_argument(
        "--target",
        type=number(low=0.0, low_open=True, high=1e6),
        nargs="+",
        help="largest value of the metric allowed (one selection per value)",
    )
    se.add_argument(
        "--metric",
        choices=METRICS,
        default=None,
        help="error: max |x(T) - x_ref(T)|/|x0|; energy: max |H - H0|/|H0| over [0, T]; "
        "casimir: max |C - C0|/|x0|^d over [0, T], d the degree of C (0, absolute, for the "
        "log-form Casimirs of Lotka–Volterra) (default: the scene's, else error)",
    )
    se.add_argument("--T", type=POSITIVE, default=None, help="horizon (default: the scene's)")
    se.add_argument("--h", type=POSITIVE, default=None, help="measure at this step only")
    se.add_argument("--models", nargs="+", help="learned models (default: the shipped ones)")
    se.add_argument("--json", default=None, help="write every candidate's row to this file")
    se.add_argument("--threads", type=threads_type, default=1, help="rayon threads (default 1)")
    se.add_argument(
        "--budget",
        type=number(low=0.0, low_open=True, high=1e7),
        default=20.0,
        help="seconds per candidate's ladder, rollouts included (default 20)",
    )
    se.add_argument(
        "--max-steps",
        dest="max_steps",
        type=number(integer=True, low=1, high=MAX_STEPS),
        default=1 << 20,
        help="finest rung: most steps to T (default 2^20)",
    )
    return se


def run(args: argparse.Namespace) -> int:
    from ..files import atomic_write_bytes, check_output_path
    from ..scenes import load_scene
    from ..studies.select import NoCandidateError, select

    if args.json is not None:
        check_output_path(args.json)
    # As for chart: one rayon thread prices every method on one core, as DOP853 runs anyway.
    os.environ.setdefault("RAYON_NUM_THREADS", str(args.threads))
    scene = load_scene(args.scene)
    spec = scene.select
    targets = args.target or (spec.targets if spec else None)
    if not targets:
        raise ValueError(f"{args.scene}: give --target or a [select] table with a target")
    # `is None`, not `or`: a zero would otherwise fall back silently (the parser refuses it).
    T = args.T if args.T is not None else (spec.T if spec else scene.horizon)
    h = args.h if args.h is not None else (spec.h if spec else None)
    metric = args.metric or (spec.metric if spec else "error")
    models = args.models or (list(spec.models) if spec and spec.models else None)
    system, mu0 = scene.lie_system, scene.states()
    rows, code = [], 0
    for target in targets:
        try:
            _, _, report = select(
                system,
                mu0,
                T=T,
                target=target,
                metric=metric,
                h=h,
                models=models,
                max_steps=args.max_steps,
                budget_s=args.budget,
            )
        except NoCandidateError as e:
            report, code = e.report, 1
            print(report.table())
            print(f"poisson-rs select: {e}")
        else:
            print(report.table())
            w = report.winner
            assert w is not None and w.passing is not None
            knob = f"tol = {w.passing.tol:.0e}" if w.passing.tol else f"h = {w.passing.h:g}"
            print(
                f"selected for {metric} <= {target:.0e}: {w.name} at {knob} "
                f"({report.seconds:.0f} s)"
            )
        print()
        rows += [{"scene": scene.name, **r} for r in report.rows()]
    if args.json is not None:
        atomic_write_bytes(Path(args.json), json.dumps(rows, indent=1).encode())
        print(f"wrote {args.json}")
    return code

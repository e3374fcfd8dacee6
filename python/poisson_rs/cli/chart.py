"""``poisson-rs chart [SCENE.toml]``: work–precision charts (error, energy error and Casimir drift
against measured cost) for any system; the paper's and the separatrix scenes by default."""

from __future__ import annotations

import argparse
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .common import check_out_dir, check_scheduler, scheduler, scheduler_flag, threads_type

NAME = "chart"
CHART_OUTPUTS = (
    "workprecision.csv",
    "workprecision.json",
    "long_run_energy.csv",
    "long_run_energy.json",
    "workprecision_error.png",
    "workprecision_energy.png",
    "workprecision_casimirs.png",
    "long_run_energy.png",
)


def add_parser(sub: Any) -> argparse.ArgumentParser:
    c = sub.add_parser(
        NAME, help="work–precision charts: error, energy error and Casimir drift against cost"
    )
    c.add_argument(
        "scene",
        nargs="?",
        default=None,
        help="scene file (TOML) of any system: chart its states to its horizon (default: the "
        "paper's and the separatrix scenes of the rigid body)",
    )
    c.add_argument("--out", default="out/chart", help="output folder (default: out/chart)")
    c.add_argument("--quick", action="store_true", help="a tiny sweep (seconds; for tests)")
    c.add_argument("--scene", dest="scene_flag", default=None, help="the same as SCENE")
    c.add_argument(
        "--model",
        action="append",
        metavar="PATH",
        help="also chart this model (file or shipped name; repeatable) against the classical "
        "methods; it must be trained for the chart's system",
    )
    c.add_argument(
        "--threads",
        type=threads_type,
        default=1,
        help="rayon threads for the rollouts (default 1: cost per trajectory on one core)",
    )
    c.add_argument(
        "--no-paper",
        dest="no_paper",
        action="store_true",
        help="skip the shipped paper-configuration model (253k parameters, slow)",
    )
    scheduler_flag(c)
    return c


def run(args: argparse.Namespace) -> int:
    from ..files import check_outputs

    check_out_dir(args.out)
    check_scheduler(args.scheduler)
    check_outputs(args.out, CHART_OUTPUTS)
    # Rayon reads this when its pool starts, at the first rollout, which is still to come (in a
    # process that already stepped, the pool keeps its size). One thread measures each method's
    # cost on one core, as DOP853 (SciPy, serial) runs anyway, and keeps the timings steady when
    # another process holds a core: a 2-core rollout then runs serially on some calls and in
    # parallel on others.
    previous = os.environ.get("RAYON_NUM_THREADS")
    os.environ["RAYON_NUM_THREADS"] = str(args.threads)
    try:
        return _chart(args)
    finally:
        if previous is None:
            del os.environ["RAYON_NUM_THREADS"]
        else:
            os.environ["RAYON_NUM_THREADS"] = previous


def _chart(args: argparse.Namespace) -> int:
    import time

    from ..integrators import load_model
    from ..studies import figures as charts
    from ..studies.workprecision import LEVELS, run_chart

    t0 = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    def progress(msg: str) -> None:
        print(f"{time.perf_counter() - t0:6.1f} s  {msg}", flush=True)

    models = [load_model(m) for m in args.model or ()]
    scene = None
    if args.scene and args.scene_flag and args.scene != args.scene_flag:
        raise ValueError("give the scene once (SCENE or --scene)")
    scene_path = args.scene or args.scene_flag
    if scene_path is not None:
        from ..scenes import load_scene
        from ..studies.workprecision import Scene

        sc = load_scene(scene_path)
        scene = Scene(sc.name, sc.lie_system, sc.states(), sc.horizon, sc.description)
    with scheduler(args.scheduler) as client:
        data = run_chart(
            quick=args.quick,
            include_paper=not args.no_paper,
            progress=progress,
            client=client,
            models=models,
            scene=scene,
        )
    charts.write_rows(data.rows, out / "workprecision.csv")
    charts.write_rows(data.long_rows, out / "long_run_energy.csv")
    # A long description (a scene file's) would not fit in the title: the name alone then.
    scenes = "; ".join(
        s.name if len(s.description) > 80 else f"{s.name}: {s.description}" for s in data.scenes
    )
    first = data.scenes[0].system
    system = charts.figure_label(first)
    # The system's own letter and reference: x and DOP853 off g*, μ and the exact flow on it.
    m, ref = charts.state_symbol(first), getattr(first, "reference_name", "DOP853")
    charts.work_precision_figure(
        data.rows,
        out / "workprecision_error.png",
        ylabel=f"max |{m}(T) − {m}_ref(T)|  (reference: {ref})",
        title=f"Error at T against cost: {system} ({scenes})",
        levels=LEVELS,
    )
    charts.work_precision_figure(
        data.rows,
        out / "workprecision_energy.png",
        metric="max_rel_dH",
        ylabel="max |H − H₀| / |H₀| over [0, T]",
        title=f"Energy error against cost: {system}",
    )
    charts.work_precision_figure(
        data.rows,
        out / "workprecision_casimirs.png",
        metric="max_rel_dC",
        ylabel=f"max |C − C₀| / |{m}₀|^deg C over [0, T]\n{data.casimir_label}",
        title=f"Casimir drift against cost: {system}",
    )
    n_long = max((r["step"] for r in data.long_rows), default=0)
    charts.long_run_figure(
        data.long_rows,
        out / "long_run_energy.png",
        title=f"Energy error over {n_long} steps of h = {data.long_h:g}: {system}, "
        f"{data.scenes[0].name} scene",
        symbol=charts.state_symbol(data.scenes[0].system),
    )
    failed = sorted(
        {f"{r['method']} ({r['scene']}, h={r['h']:g})" for r in data.rows if r["failed"]}
    )
    print()
    for line in data.notes:
        print(f"note: {line}")
    if failed:
        print(f"failed runs (recorded, marked × in the charts): {', '.join(failed)}")
    for line in level_summary(data.rows, LEVELS, data.scenes[0].name):
        print(line)
    print(
        f"(timings on {args.threads} rayon thread(s); an integrate() call costs "
        f"{data.call_overhead_s * 1e6:.0f} µs before any step, so timings batch the states to "
        "amortise it: see the timing_batch column)"
    )
    print(
        f"wrote {out}/workprecision_error.png, workprecision_energy.png, "
        "workprecision_casimirs.png, long_run_energy.png, "
        f"workprecision.csv/json, long_run_energy.csv/json in {time.perf_counter() - t0:.0f} s"
    )
    return 0


def level_summary(rows: Sequence[dict[str, Any]], levels: Sequence[float], scene: str) -> list[str]:
    """Per error level: the fastest method on ``scene``, the runner-up and the learned."""
    from ..studies.workprecision import rank_at_level

    horizon = next((r["T"] for r in rows if r["scene"] == scene), 10.0)
    lines = [
        f"fastest to reach max |x(T) − x_ref(T)| ≤ level, {scene} scene, T = {horizon:g} (s per "
        "trajectory,",
        "interpolated log–log between neighbouring measured points; [cheapest measured point]):",
    ]
    for level in levels:
        ranked = rank_at_level(rows, level, scene=scene)
        if not ranked:
            lines.append(f"  {level:.0e}: no method reaches it")
            continue
        win = ranked[0]
        measured = rank_at_level(rows, level, scene=scene, interpolate=False)
        point = next((m for m in measured if m["method"] == win["method"]), None)
        knob = ""
        if point is not None:
            what = f"tol={point['tol']:.0e}" if point["tol"] is not None else f"h={point['h']:g}"
            knob = f" [{what}: {point['seconds']:.1e} s]"
        line = f"  {level:.0e}: {win['method']} {win['seconds']:.1e} s{knob}"
        if len(ranked) > 1:
            nxt = ranked[1]
            line += f"; next {nxt['method']} {nxt['seconds'] / win['seconds']:.1f}×"
        for i, r in enumerate(ranked):
            if r["method"].startswith("learned:") and i > 0:
                ratio = r["seconds"] / win["seconds"]
                line += f"; {r['method']} #{i + 1}/{len(ranked)} {ratio:.1f}×"
        lines.append(line)
    return lines

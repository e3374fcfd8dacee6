"""``poisson-rs stability [SCENE.toml]``: where each method breaks as the step size grows, over
many initial states, for any system (the paper's rigid body by default)."""

from __future__ import annotations

import argparse
from typing import Any

from .common import (
    MAX_STEPS,
    POSITIVE,
    check_out_dir,
    check_scheduler,
    number,
    progress_printer,
    scheduler,
    scheduler_flag,
    table,
)

NAME = "stability"
STABILITY_OUTPUTS = (
    "stability.csv",
    "stability.json",
    "stability_map.png",
    "stability_summary.png",
    "first_failures.csv",
    "first_failures.json",
)


def add_parser(sub: Any) -> argparse.ArgumentParser:
    st = sub.add_parser(NAME, help="stability map: where each method breaks as h grows")
    st.add_argument(
        "scene",
        nargs="?",
        default=None,
        help="scene file (TOML) of any system: map its states and system (default: the "
        "paper's rigid body on a grid of radii and directions)",
    )
    st.add_argument("--out", default="out/stability", help="output folder")
    st.add_argument(
        "--horizon", type=POSITIVE, default=20.0, help="time T of the error (default 20)"
    )
    st.add_argument(
        "--threshold",
        type=number(low=0.0, low_open=True, high=1e6),
        default=0.1,
        help="relative error called broken (default 0.1)",
    )
    st.add_argument("--quick", action="store_true", help="two step sizes only (for tests)")
    st.add_argument("--scene", dest="scene_flag", default=None, help="the same as SCENE")
    st.add_argument(
        "--model",
        action="append",
        metavar="PATH",
        help="also map this model (file or shipped name; repeatable); it must be trained for "
        "the map's system",
    )
    st.add_argument("--no-progress", dest="no_progress", action="store_true")
    scheduler_flag(st)
    return st


def run(args: argparse.Namespace) -> int:
    from functools import partial

    from ..files import check_outputs
    from ..integrators import load_model
    from ..structures.lie_poisson import RigidBody
    from ..studies import figures
    from ..studies.stability import (
        QUICK_STEP_SIZES,
        STEP_SIZES,
        default_methods,
        first_failures,
        stability_map,
        states,
    )

    out = check_out_dir(args.out)
    check_scheduler(args.scheduler)
    check_outputs(args.out, STABILITY_OUTPUTS)
    steps = QUICK_STEP_SIZES if args.quick else STEP_SIZES
    if args.horizon / min(steps) > MAX_STEPS:
        raise ValueError(
            f"--horizon {args.horizon:g} needs {args.horizon / min(steps):.3g} steps of "
            f"h = {min(steps):g}; at most {MAX_STEPS:.0e} are taken"
        )
    scene_path = args.scene or args.scene_flag
    if args.scene and args.scene_flag and args.scene != args.scene_flag:
        raise ValueError("give the scene once (SCENE or --scene)")
    system: Any = RigidBody()
    mu0, labels = states(system)
    if scene_path is not None:
        from ..scenes import load_scene

        sc = load_scene(scene_path)
        system = sc.lie_system
        mu0 = sc.states()
        labels = ["(" + ", ".join(f"{v:g}" for v in s) + ")" for s in mu0]
    methods = default_methods(system)
    for path in args.model or ():
        model = load_model(path)  # checked here, before the map's work
        if model.system != system:
            raise ValueError(
                f"--model {path} integrates {figures.system_label(model.system)}, not "
                f"{figures.system_label(system)}"
            )
        methods[f"learned:{model.name}"] = partial(load_model, path)
    out.mkdir(parents=True, exist_ok=True)
    with scheduler(args.scheduler) as client:
        rows = stability_map(
            system,
            step_sizes=steps,
            horizon=args.horizon,
            methods=methods,
            progress=progress_printer(args),
            client=client,
            states=(mu0, labels),
        )
    figures.write_rows(rows, out / "stability.csv")
    figures.stability_figure(rows, out / "stability_map.png", system=system)
    figures.stability_summary_figure(rows, out / "stability_summary.png", system=system)
    first = first_failures(rows, threshold=args.threshold)
    figures.write_rows(first, out / "first_failures.csv")
    print(f"where each method first breaks (relative error > {args.threshold:g} or a step fails):")
    print(table(first, ["method", "h_breaks", "how"]))
    print(f"wrote {out}/stability_map.png, stability_summary.png, stability.csv/json")
    return 0

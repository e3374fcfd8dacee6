"""``poisson-rs demo``: rollouts of a scene's states by a learned model, Taylor series and the
classical methods, against the exact solution (rigid body) or a DOP853 reference (any system)."""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .common import POSITIVE, STEPS, check_out_dir, system_spec, table

if TYPE_CHECKING:
    from ..structures.lie_poisson import LiePoissonSystem

NAME = "demo"

#: Files ``demo`` writes for the rigid body with a learned model (the paper's figures).
DEMO_OUTPUTS = (
    "fig2_orbits.png",
    "fig3_errors.png",
    "trajectories.csv",
    "metrics.csv",
    "metrics.json",
)
#: Files ``demo`` writes for any other system (or scene).
SYSTEM_DEMO_OUTPUTS = (
    "orbits.png",
    "states_errors.png",
    "trajectories.csv",
    "metrics.csv",
    "metrics.json",
)
PAPER_H, PAPER_STEPS = 0.1, 10_000
#: Share of the machine's memory one demo may hold in trajectories.
MEMORY_SHARE = 0.25


def add_parser(sub: Any) -> argparse.ArgumentParser:
    d = sub.add_parser(
        NAME, help="a scene's rollouts (default: the paper's) with figures and a table"
    )
    d.add_argument("--model", default=None, help="model file or shipped name (default: default)")
    d.add_argument(
        "--scene",
        default=None,
        help="a scene file (TOML) of any system: its states, first step size and horizon "
        "replace the paper's (--h and --steps, when given, replace the scene's)",
    )
    d.add_argument(
        "--system",
        default=None,
        help="run the demo on a system instead of the paper's model: rigid-body, heavy-top or a "
        "JSON file of any system's to_dict(), such as the system 'poisson-rs learn --structure' "
        "writes (its Taylor-HJ and classical methods against the exact flow or a DOP853 "
        "reference, from the system's demo states)",
    )
    d.add_argument("--out", default="out/demo", help="output folder (default: out/demo)")
    d.add_argument(
        "--steps", type=STEPS, default=None, help="number of steps (default 10000, or the scene's)"
    )
    d.add_argument(
        "--h", type=POSITIVE, default=None, help="step size (default 0.1, or the scene's first)"
    )
    d.add_argument(
        "--no-paper",
        dest="with_paper",
        action="store_false",
        help="skip the shipped paper-configuration model (its 253k-parameter rollout is slow)",
    )
    d.add_argument(
        "--no-strict",
        dest="strict",
        action="store_false",
        help="let learned models step beyond the h_max they were trained for (extrapolate)",
    )
    return d


def _memory_bytes() -> float:
    """Physical memory of this machine (bytes); 4 GiB when it cannot be read."""
    try:
        return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return float(4 << 30)


def check_memory(n_states: int, dim: int, steps: int, n_methods: int) -> None:
    """ValueError, before any work, when every method's trajectories (and the reference) would
    take more than MEMORY_SHARE of the machine's memory: the demo keeps every step."""
    need = 8.0 * n_states * (steps + 1) * dim * (n_methods + 2)
    have = MEMORY_SHARE * _memory_bytes()
    if need > have:
        most = int(have / (8.0 * n_states * dim * (n_methods + 2))) - 1
        raise ValueError(
            f"--steps {steps} would keep {need / 2**30:.1f} GiB of trajectories ({n_methods} "
            f"methods, {n_states} states); at most {max(most, 0)} steps fit in "
            f"{MEMORY_SHARE:.0%} of this machine's memory"
        )


def run(args: argparse.Namespace) -> int:
    from ..files import check_outputs
    from ..integrators import list_models, load_model, taylor_integrator
    from ..protocols import Stepper
    from ..studies import figures
    from ..studies.demo import PAPER_STATES, run_scene

    check_out_dir(args.out)
    states = PAPER_STATES
    system: LiePoissonSystem | None = None
    if args.scene is not None:
        from ..scenes import load_scene

        if args.system is not None:
            raise ValueError("give --scene or --system, not both (a scene names its system)")
        sc = load_scene(args.scene)
        states, system = sc.states(), sc.lie_system
        # The scene's step and horizon, unless the command line gives its own.
        if args.h is None:
            args.h = sc.h[0]
        if args.steps is None:
            args.steps = sc.n_steps(args.h)
        print(f"scene {sc.name}: h = {args.h:g}, {args.steps} steps (T = {args.h * args.steps:g})")
    args.h = PAPER_H if args.h is None else args.h
    args.steps = PAPER_STEPS if args.steps is None else args.steps
    if args.system is not None:
        if args.model is not None:
            raise ValueError("give --model or --system, not both (a model names its system)")
        return _demo_system(args, None, system_spec(args.system))
    if system is not None and args.model is None and load_model().system != system:
        # No model of the scene's system was asked for: the Taylor and classical methods.
        return _demo_system(args, None, system, states)
    model = load_model(args.model)
    if system is not None and model.system != system:
        raise ValueError(
            f"the scene integrates {_label(system)} but the model {model.name!r} was trained "
            f"for {_label(model.system)}; give --model with a model of the scene's system"
        )
    from ..model_files import BisectionIntegrator

    if not isinstance(model, BisectionIntegrator) or "cayley" not in model.system.taylor_charts():
        # The paper's figures compare the Cayley and exp charts: elsewhere, the generic demo.
        return _demo_system(args, model, model.system, states if system is not None else None)
    body = model.system
    check_outputs(args.out, DEMO_OUTPUTS)
    methods: dict[str, Stepper] = {
        f"learned:{model.name}": model,
        f"taylor3-{model.chart}": taylor_integrator(body, 3, model.chart),
        f"taylor5-{model.chart}": taylor_integrator(body, 5, model.chart),
    }
    other = "exp" if model.chart == "cayley" else "cayley"
    methods[f"taylor3-{other}"] = taylor_integrator(body, 3, other)
    if args.with_paper and "paper" in list_models() and model.name != "paper":
        # The paper's own configuration, trained as stated: the honest reference point, but
        # only for the body it was trained for (another body's exact solution would score it
        # against the wrong flow).
        paper = load_model("paper")
        if paper.system == body:
            methods["learned:paper"] = paper
        else:
            print(f"not adding learned:paper: it was trained for {_label(paper.system)}")
    check_memory(len(states), 3, args.steps, len(methods))
    print(f"model: {model!r}")
    print(f"scene: {_label(body)}, states {states.tolist()}")
    print(f"       {args.steps} steps of h = {args.h}")
    scene = run_scene(methods, body, states, args.h, args.steps, strict=args.strict)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    learned = scene.runs[0]
    figures.orbit_figure(scene, [learned], out / "fig2_orbits.png")
    figures.error_figure(scene, scene.runs, out / "fig3_errors.png")
    write_metrics(scene, out, args.h, args.steps)
    _report_failures(scene)
    print(f"wrote {out}/fig2_orbits.png, fig3_errors.png, metrics.csv/json, trajectories.csv")
    return 0


def _label(system: Any) -> str:
    from ..studies.figures import system_label

    return system_label(system)


def _report_failures(scene: Any) -> None:
    failed = [r.name for r in scene.runs if r.info is not None and not r.info.converged.all()]
    if failed:
        print(f"Newton failed in: {', '.join(failed)}")


def write_metrics(scene: Any, out: Path, h: float, steps: int) -> None:
    """The demo's trajectories and metrics (at T = 10 and at the end) as files, and the table
    (an unknown Casimir drift is NaN in the files and "n/a" in the table)."""
    from ..studies import figures

    figures.write_trajectories(scene, scene.runs, out / "trajectories.csv")
    # One row per distinct step index: h·steps = 10 would list every row twice.
    horizons = {round(t / h): t for t in (10.0, h * steps) if round(t / h) <= steps}
    rows = scene.metrics(horizons=tuple(horizons.values()))
    figures.write_rows(rows, out / "metrics.csv")
    print(table(rows, ["method", "state", "T", "error", "max_rel_dH", "max_rel_dC", "steps_per_s"]))


def _demo_system(
    args: argparse.Namespace,
    model: Any,
    system: LiePoissonSystem,
    states: np.ndarray | None = None,
) -> int:
    """The demo on any system: Taylor K = 3, 5, 7 (exp chart; 1, 3, 5, 7 on the exact
    log-canonical groupoid) and the classical methods (and ``model``
    if given) from ``states`` (default: the system's demo states) against a DOP853 reference;
    the orbits, the states with their error, energy and Casimir drifts, and the metrics."""
    from ..files import check_outputs
    from ..integrators import classical, classical_methods, taylor_integrator
    from ..studies import figures
    from ..studies.demo import demo_states, run_scene
    from ..studies.methods import default_chart, taylor_orders

    if states is None:
        states = demo_states(system)
    check_outputs(args.out, SYSTEM_DEMO_OUTPUTS)
    methods: dict[str, Any] = {}
    if model is not None:
        methods[f"learned:{model.name}"] = model
    chart = default_chart(system)
    # m = 1 shows order 2 too.
    for k in taylor_orders(system, (1, 3, 5, 7)):
        methods[f"taylor{k}-{chart}"] = taylor_integrator(system, k, chart)
    for name in classical_methods(system):
        if name != "dop853":
            methods[name] = classical(system, name)
    check_memory(len(states), system.dim, args.steps, len(methods))
    print(f"system: {_label(system)}, states {states.tolist()}")
    print(f"        {args.steps} steps of h = {args.h}; reference: DOP853, rtol = atol = 1e-13")
    scene = run_scene(methods, system, states, args.h, args.steps, strict=args.strict)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    # The most accurate method by measured error: the first listed is the lowest Taylor order.
    figures.orbit_figure(scene, [scene.most_accurate()], out / "orbits.png")
    figures.state_figure(scene, scene.runs, out / "states_errors.png")
    write_metrics(scene, out, args.h, args.steps)
    _report_failures(scene)
    print(f"wrote {out}/{', '.join(SYSTEM_DEMO_OUTPUTS)}")
    return 0

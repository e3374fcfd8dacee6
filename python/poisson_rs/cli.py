"""Command line: ``poisson-rs demo`` (the paper's scene), ``train``, ``models``, ``chart``,
``stability`` and ``sweep``."""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import shlex
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .systems import RigidBody

if TYPE_CHECKING:
    from .systems import LiePoissonSystem


def _table(rows: Sequence[dict[str, Any]], cols: Sequence[str]) -> str:
    def fmt(v: Any) -> str:
        return f"{v:.2e}" if isinstance(v, float) else str(v)

    cells = [[fmt(r[c]) for c in cols] for r in rows]
    widths = [max(len(c), *(len(x[i]) for x in cells)) for i, c in enumerate(cols)]
    line = "  ".join(c.ljust(w) for c, w in zip(cols, widths, strict=True))
    body = ["  ".join(x.ljust(w) for x, w in zip(r, widths, strict=True)) for r in cells]
    return "\n".join([line, "-" * len(line), *body])


#: Files ``demo`` writes in its folder, checked before any work.
DEMO_OUTPUTS = (
    "fig2_orbits.png",
    "fig3_errors.png",
    "trajectories.csv",
    "metrics.csv",
    "metrics.json",
)
STABILITY_OUTPUTS = (
    "stability.csv",
    "stability.json",
    "stability_map.png",
    "stability_summary.png",
    "first_failures.csv",
    "first_failures.json",
)
CHART_OUTPUTS = (
    "workprecision.csv",
    "workprecision.json",
    "long_run_energy.csv",
    "long_run_energy.json",
    "workprecision_error.png",
    "workprecision_energy.png",
    "long_run_energy.png",
)


def _check_positive(**values: float) -> None:
    """ValueError naming the first option that is not a finite number > 0."""
    for name, v in values.items():
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"--{name.replace('_', '-')} must be a finite number > 0, got {v}")


def _default_threads() -> int:
    """Torch threads when --threads is not given: 1 on a machine with at most 2 cores (shared
    with other work, where more threads only contend), else torch's own default."""
    import torch

    return 1 if (os.cpu_count() or 1) <= 2 else torch.get_num_threads()


def cmd_demo(args: argparse.Namespace) -> int:
    from . import charts
    from .demo import PAPER_STATES, run_scene
    from .files import check_outputs
    from .integrators import list_models, load_model, taylor_integrator

    _check_positive(h=args.h, steps=args.steps)
    states = PAPER_STATES
    if args.scene is not None:
        from .scenes import load_scene

        if args.system is not None:
            raise ValueError("give --scene or --system, not both (a scene names its system)")
        sc = load_scene(args.scene)
        states, args.h = sc.states(), sc.h[0]
        args.steps = sc.n_steps(args.h)
        if not isinstance(sc.lie_system, RigidBody):
            model = load_model(args.model) if args.model is not None else None
            if model is not None and model.system != sc.lie_system:
                raise ValueError(f"--model integrates {model.system!r}, not {sc.lie_system!r}")
            return _demo_system(args, model, sc.lie_system, states)
    if args.system is not None:
        if args.model is not None:
            raise ValueError("give --model or --system, not both (a model names its system)")
        return _demo_system(args)
    check_outputs(args.out, DEMO_OUTPUTS)
    model = load_model(args.model)
    if not isinstance(model.system, RigidBody):
        return _demo_system(args, model)
    body = model.body
    if args.scene is not None and sc.lie_system != body:
        raise ValueError(
            f"the scene integrates {sc.lie_system!r} but the model {model.name!r} was trained for "
            f"{body!r}; give --model with a model of the scene's body"
        )
    methods = {
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
            print(f"not adding learned:paper: it was trained for {paper.system!r}, not {body!r}")
    print(f"model: {model!r}")
    print(f"scene: I = {body.inertia}, states {states.tolist()}")
    print(f"       {args.steps} steps of h = {args.h}")
    scene = run_scene(methods, body, states, args.h, args.steps, strict=args.strict)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    learned = scene.runs[0]
    charts.paper_figure_2(scene, learned, out / "fig2_orbits.png")
    charts.paper_figure_3(scene, scene.runs, out / "fig3_errors.png")
    _write_metrics(scene, out, args.h, args.steps)
    failed = [r.name for r in scene.runs if r.info is not None and not r.info.converged.all()]
    if failed:
        print(f"Newton failed in: {', '.join(failed)}")
    print(f"wrote {out}/fig2_orbits.png, fig3_errors.png, metrics.csv/json, trajectories.csv")
    return 0


def _write_metrics(scene: Any, out: Path, h: float, steps: int) -> None:
    """The demo's trajectories and metrics (at T = 10 and at the end) as files, and the table."""
    from . import charts

    charts.write_trajectories(scene, scene.runs, out / "trajectories.csv")
    # One row per distinct step index: h·steps = 10 would list every row twice.
    horizons = {round(t / h): t for t in (10.0, h * steps)}
    rows = scene.metrics(horizons=tuple(horizons.values()))
    charts.write_rows(rows, out / "metrics.csv")
    print(
        _table(rows, ["method", "state", "T", "error", "max_rel_dH", "max_rel_dC", "steps_per_s"])
    )


#: Files ``demo --system`` writes.
SYSTEM_DEMO_OUTPUTS = ("states_errors.png", "trajectories.csv", "metrics.csv", "metrics.json")


def _demo_system(
    args: argparse.Namespace,
    model: Any = None,
    system: LiePoissonSystem | None = None,
    states: np.ndarray | None = None,
) -> int:
    """The demo on a system other than the rigid body: Taylor-exp K = 3, 5, 7 and the classical
    methods (and ``model`` if given) from ``states`` (default: the system's demo states) against
    a DOP853 reference; a figure of the states with their error, energy and Casimir drifts, and
    the metrics."""
    from . import charts
    from .demo import HEAVY_TOP_STATES, run_scene
    from .files import check_outputs
    from .integrators import classical, classical_methods, taylor_integrator
    from .systems import HeavyTop

    if system is None:
        system = model.system if model is not None else _system_spec(args.system)
    if isinstance(system, RigidBody):
        raise ValueError("--system rigid-body is the paper's scene: run demo without --system")
    if states is None:
        if not isinstance(system, HeavyTop):
            raise ValueError(
                f"demo --system knows demo states for the heavy top only, not {system!r}; "
                "give a scene file (demo --scene) with the system and its states"
            )
        states = HEAVY_TOP_STATES
    check_outputs(args.out, SYSTEM_DEMO_OUTPUTS)
    methods: dict[str, Any] = {}
    if model is not None:
        methods[f"learned:{model.name}"] = model
    for k in (3, 5, 7):
        methods[f"taylor{k}-exp"] = taylor_integrator(system, k, "exp")
    for name in classical_methods(system):
        if name != "dop853":
            methods[name] = classical(system, name)
    print(f"system: {system!r}, states {states.tolist()}")
    print(f"        {args.steps} steps of h = {args.h}; reference: DOP853, rtol = atol = 1e-13")
    scene = run_scene(methods, system, states, args.h, args.steps, strict=args.strict)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    charts.state_figure(scene, scene.runs, out / "states_errors.png")
    _write_metrics(scene, out, args.h, args.steps)
    print(f"wrote {out}/{', '.join(SYSTEM_DEMO_OUTPUTS)}")
    return 0


def cmd_train(args: argparse.Namespace, argv: Sequence[str]) -> int:
    import torch

    from .files import check_output_path
    from .train import PRESETS, TrainConfig, baseline_rms, save_result, train

    # Every check before any work: a bad output would otherwise fail after the training.
    check_output_path(args.out)
    if args.checkpoint is not None:
        check_output_path(args.checkpoint)
    if args.checkpoint_every < 1:
        raise ValueError(f"--checkpoint-every must be >= 1, got {args.checkpoint_every}")
    if args.max_seconds is not None:
        _check_positive(max_seconds=args.max_seconds)
    threads = _default_threads() if args.threads is None else args.threads
    if threads < 1:
        raise ValueError(f"--threads must be >= 1, got {threads}")
    torch.set_num_threads(threads)
    # Read when rayon's pool starts, at the first rollout (scene evaluations).
    os.environ.setdefault("RAYON_NUM_THREADS", str(threads))

    flags: dict[str, Any] = {}
    for f in dataclasses.fields(TrainConfig):
        v = getattr(args, f.name, None)
        if v is not None:
            flags[f.name] = tuple(v) if isinstance(v, list) else v
    if args.n_points == 0:
        flags["n_points"] = None
    dim = 3
    if "system" in flags:
        try:
            system = _system_spec(flags["system"])
        except (OSError, ValueError) as e:
            print(f"poisson-rs train: --system: {e}", file=sys.stderr)
            return 2
        flags["system"] = system.to_dict()
        dim = system.dim
        if "chart" not in flags and not system.algebra.is_so3():
            flags["chart"] = "exp"
        if "inputs" not in flags and not system.polynomial.is_homogeneous(2):
            flags["inputs"] = "t,p"
    if "sampling_states" in flags:
        flags["sampling_states"] = _vectors(flags["sampling_states"], dim, "--sampling-states")
    command = "poisson-rs " + shlex.join(argv)
    if args.scene is not None:
        import json

        from .integrators import load_model
        from .scenes import train_scene

        path = train_scene(
            args.scene,
            args.out,
            progress=not args.no_progress,
            command=command,
            name=args.name,
            overrides=flags,
            max_seconds=args.max_seconds,
        )
        met = json.loads(load_model(path).metadata["target_met"])
        print(f"scene target {'met' if met else 'NOT met'} -> {path}")
        return 0 if met else 1
    cfg = TrainConfig(**{**PRESETS[args.preset], **flags})
    try:
        cfg.validate()
    except ValueError as e:
        print(f"poisson-rs train: {e}", file=sys.stderr)
        return 2
    print(f"training: {cfg} on {threads} torch thread(s)")
    print(
        f"baseline: the Taylor terms alone (K = {cfg.taylor_order}, no network) have validation "
        f"RMS residual {baseline_rms(cfg):.3e}"
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


def _triples(values: Sequence[float], flag: str) -> tuple[tuple[float, float, float], ...]:
    """A flat list x y z x y z ... as 3-vectors; ValueError unless its length is a multiple of 3."""
    return _vectors(values, 3, flag)  # type: ignore[return-value]


def _vectors(values: Sequence[float], dim: int, flag: str) -> tuple[tuple[float, ...], ...]:
    """A flat list of numbers as dim-vectors; ValueError unless its length is a multiple of dim."""
    if not values or len(values) % dim:
        raise ValueError(f"{flag} needs {dim} numbers for each state, got {len(values)} numbers")
    flat = [float(v) for v in values]
    return tuple(tuple(flat[i : i + dim]) for i in range(0, len(flat), dim))


#: Systems ``train --system`` knows by name (a JSON file of ``system.to_dict()`` gives any other).
NAMED_SYSTEMS = ("rigid-body", "heavy-top")


def _system_spec(spec: str) -> LiePoissonSystem:
    """A system from a name in NAMED_SYSTEMS or a JSON file holding ``system.to_dict()``."""
    import json

    from .systems import HeavyTop, LiePoissonSystem, RigidBody

    if spec == "rigid-body":
        return RigidBody()
    if spec == "heavy-top":
        return HeavyTop()
    path = Path(spec)
    if not path.is_file():
        raise ValueError(
            f"{spec!r} is neither a known system ({', '.join(NAMED_SYSTEMS)}) nor a JSON file"
        )
    if path.stat().st_size > 1 << 20:
        raise ValueError(f"{spec} is over 1 MiB; a system description is a few lines of JSON")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{spec} is not a JSON system description ({e})") from e
    if not isinstance(data, dict):
        raise ValueError(f"{spec} must hold a JSON object (a system's to_dict())")
    return LiePoissonSystem.from_dict(data)


def _sampling_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--sampling",
        choices=["uniform", "scene"],
        help="training points uniform over the domain, or partly near the scene's orbits",
    )
    p.add_argument(
        "--sampling-fraction",
        dest="sampling_fraction",
        type=float,
        help="share of each batch near the orbits with --sampling scene (default 0.5)",
    )
    p.add_argument(
        "--sampling-noise",
        dest="sampling_noise",
        type=float,
        help="offset of an orbit point, relative to |μ| (default 0.02)",
    )


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


def cmd_sweep(args: argparse.Namespace) -> int:
    import json
    import os
    import time

    import torch

    from . import charts
    from .files import check_output_path, check_outputs
    from .sweep import FAST, medians, run_sweep

    out = Path(args.out)
    png = out / f"{args.stem}.png"
    stems = (args.stem, f"{args.stem}_medians")
    check_outputs(out, [f"{args.stem}.png", *(f"{x}.{e}" for x in stems for e in ("csv", "json"))])
    if args.models_out is not None:
        check_output_path(args.models_out, kind="dir")
    if args.replot is not None:
        rows = json.loads(Path(args.replot).read_text())
        charts.sweep_figure(rows, png, title=args.title or _sweep_title(rows))
        print(f"wrote {png}")
        return 0
    if args.threads < 1:
        raise ValueError(f"--threads must be >= 1, got {args.threads}")
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
        from .demo import PAPER_STATES

        overrides["sampling_states"] = tuple(map(tuple, PAPER_STATES.tolist()))
    t0 = time.perf_counter()
    from .ensembles import scheduler_client

    with scheduler_client(args.scheduler) as client:
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
    print(_table(med, [*cols, "steps_per_s", "train_seconds"]))
    print(
        f"wrote {png}, {args.stem}.csv/json and {args.stem}_medians.csv/json to {out} "
        f"in {time.perf_counter() - t0:.0f} s"
    )
    return 0


def cmd_models(args: argparse.Namespace) -> int:
    import json

    from .integrators import list_models, load_model

    for name in list_models():
        m = load_model(name)
        md = m.metadata
        try:
            recorded = json.loads(md.get("config", "{}"))
        except ValueError:
            recorded = {}
        command = _runnable_command(md.get("command", "?"), recorded, name)
        print(f"{name}: {m!r}\n  command: {command}\n  seed: {md.get('seed', '?')}")
    return 0


def _runnable_command(command: str, recorded: Any, name: str) -> str:
    """The recorded training command as one to run here: ``--out`` a relative ``NAME.safetensors``
    (not the training machine's path), plus the options added since the model was trained whose
    new defaults would train another model."""
    try:
        words = shlex.split(command)
    except ValueError:
        return command
    if words[:2] != ["poisson-rs", "train"]:
        return command
    if "--out" in words[:-1]:
        words[words.index("--out") + 1] = f"{name}.safetensors"
    if isinstance(recorded, dict) and recorded:
        # Recorded before the option existed: trained with nested autograd (the default is now
        # the reverse pass, whose weights end ~1e-14 away) and from a Xavier-uniform network.
        if "derivatives" not in recorded and "--derivatives" not in words:
            words += ["--derivatives", "autograd"]
        if "init" not in recorded and "--init" not in words:
            words += ["--init", "xavier"]
    return shlex.join(words)


def _level_summary(
    rows: Sequence[dict[str, Any]], levels: Sequence[float], scene: str = "paper"
) -> list[str]:
    """Per error level: the fastest method on ``scene``, the runner-up and the learned."""
    from .workprecision import rank_at_level

    horizon = next((r["T"] for r in rows if r["scene"] == scene), 10.0)
    lines = [
        f"fastest to reach max |μ(T) − μ_exact(T)| ≤ level, {scene} scene, T = {horizon:g} (s per "
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


def cmd_chart(args: argparse.Namespace) -> int:
    import os

    from .files import check_outputs

    if args.threads < 1:
        raise ValueError(f"--threads must be >= 1, got {args.threads}")
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

    from . import charts
    from .integrators import load_model
    from .workprecision import LEVELS, run_chart

    t0 = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    def progress(msg: str) -> None:
        print(f"{time.perf_counter() - t0:6.1f} s  {msg}", flush=True)

    from .ensembles import scheduler_client

    models = [load_model(m) for m in args.model or ()]
    scene = None
    if args.scene is not None:
        from .scenes import load_scene
        from .workprecision import Scene

        sc = load_scene(args.scene)
        scene = Scene(sc.name, sc.body, sc.states(), sc.horizon, sc.description)
    with scheduler_client(args.scheduler) as client:
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
    scenes = "; ".join(f"{s.name}: {s.description}" for s in data.scenes)
    charts.work_precision_figure(
        data.rows,
        out / "workprecision_error.png",
        title=f"Error at T against cost ({scenes})",
        levels=LEVELS,
    )
    charts.work_precision_figure(
        data.rows,
        out / "workprecision_energy.png",
        metric="max_rel_dH",
        ylabel="max |H − H₀| / H₀ over [0, T]",
        title="Energy error against cost",
    )
    n_long = max((r["step"] for r in data.long_rows), default=0)
    charts.long_run_figure(
        data.long_rows,
        out / "long_run_energy.png",
        title=f"Energy error over {n_long} steps of h = 0.1, paper scene",
    )
    failed = sorted(
        {f"{r['method']} ({r['scene']}, h={r['h']:g})" for r in data.rows if r["failed"]}
    )
    print()
    for line in data.notes:
        print(f"note: {line}")
    if failed:
        print(f"failed runs (recorded, marked × in the charts): {', '.join(failed)}")
    for line in _level_summary(data.rows, LEVELS, data.scenes[0].name):
        print(line)
    print(
        f"(timings on {args.threads} rayon thread(s); an integrate() call costs "
        f"{data.call_overhead_s * 1e6:.0f} µs before any step, so timings batch the states to "
        "amortise it: see the timing_batch column)"
    )
    print(
        f"wrote {out}/workprecision_error.png, workprecision_energy.png, long_run_energy.png, "
        f"workprecision.csv/json, long_run_energy.csv/json in {time.perf_counter() - t0:.0f} s"
    )
    return 0


def cmd_select(args: argparse.Namespace) -> int:
    import json

    from .files import atomic_write_bytes, check_output_path
    from .scenes import load_scene
    from .select import NoCandidateError, select

    if args.threads < 1:
        raise ValueError(f"--threads must be >= 1, got {args.threads}")
    if args.json is not None:
        check_output_path(args.json)
    # As for chart: one rayon thread prices every method on one core, as DOP853 runs anyway.
    os.environ.setdefault("RAYON_NUM_THREADS", str(args.threads))
    scene = load_scene(args.scene)
    spec = scene.select
    targets = args.target or (spec.targets if spec else None)
    if not targets:
        raise ValueError(f"{args.scene}: give --target or a [select] table with a target")
    T = args.T or (spec.T if spec else scene.horizon)
    h = args.h if args.h is not None else (spec.h if spec else None)
    models = args.models or (list(spec.models) if spec and spec.models else None)
    _check_positive(budget=args.budget)
    system, mu0 = scene.lie_system, scene.states()
    rows, code = [], 0
    for target in targets:
        try:
            _, _, report = select(
                system,
                mu0,
                T=T,
                target=target,
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
            print(f"selected for {target:.0e}: {w.name} at {knob} ({report.seconds:.0f} s)")
        print()
        rows += [{"scene": scene.name, **r} for r in report.rows()]
    if args.json is not None:
        atomic_write_bytes(Path(args.json), json.dumps(rows, indent=1).encode())
        print(f"wrote {args.json}")
    return code


def cmd_stability(args: argparse.Namespace) -> int:
    from . import charts
    from .files import check_outputs
    from .stability import QUICK_STEP_SIZES, STEP_SIZES, first_failures, stability_map

    _check_positive(horizon=args.horizon, threshold=args.threshold)
    check_outputs(args.out, STABILITY_OUTPUTS)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    steps = QUICK_STEP_SIZES if args.quick else STEP_SIZES
    from .ensembles import scheduler_client

    methods = None
    body = RigidBody()
    if args.scene is not None:
        from .scenes import load_scene

        body = load_scene(args.scene).body  # ValueError for a scene on another system
    if args.model or args.scene is not None:
        from functools import partial

        from .integrators import load_model
        from .stability import default_methods

        methods = default_methods(body)
        for path in args.model or ():
            model = load_model(path)  # checked here, before the map's work
            if model.system != body:
                raise ValueError(f"--model {path} integrates {model.system!r}, not {body!r}")
            methods[f"learned:{model.name}"] = partial(load_model, path)
    with scheduler_client(args.scheduler) as client:
        rows = stability_map(
            body=body,
            step_sizes=steps,
            horizon=args.horizon,
            methods=methods,
            progress=_progress(args),
            client=client,
        )
    charts.write_rows(rows, out / "stability.csv")
    charts.stability_figure(rows, out / "stability_map.png")
    charts.stability_summary_figure(rows, out / "stability_summary.png")
    first = first_failures(rows, threshold=args.threshold)
    charts.write_rows(first, out / "first_failures.csv")
    print(f"where each method first breaks (relative error > {args.threshold:g} or Newton fails):")
    print(_table(first, ["method", "h_breaks", "how"]))
    print(f"wrote {out}/stability_map.png, stability_summary.png, stability.csv/json")
    return 0


def _scheduler_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="run the independent jobs on Dask: 'local' (a LocalCluster, one single-threaded "
        "worker process per core) or a scheduler address such as tcp://host:8786 (default: "
        "serial, in this process; needs poisson_rs[distributed])",
    )


def _progress(args: argparse.Namespace) -> Callable[[str], None] | None:
    if getattr(args, "no_progress", False):
        return None
    return lambda msg: print(f"  {msg}", file=sys.stderr, flush=True)


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
    from .train import PRESETS, TrainConfig

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


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="poisson-rs", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)

    d = sub.add_parser("demo", help="the paper's scene with the default model: figures and table")
    d.add_argument("--model", default=None, help="model file or shipped name (default: default)")
    d.add_argument(
        "--scene",
        default=None,
        help="a scene file (TOML): its system, states, first step size and horizon replace the "
        "paper's",
    )
    d.add_argument(
        "--system",
        default=None,
        help="run the demo on another system instead of the paper's rigid body: heavy-top "
        "(Taylor-exp and classical methods against a DOP853 reference)",
    )
    d.add_argument("--out", default="out/demo", help="output folder (default: out/demo)")
    d.add_argument("--steps", type=int, default=10_000, help="number of steps (default 10000)")
    d.add_argument("--h", type=float, default=0.1, help="step size (default 0.1)")
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

    t = sub.add_parser("train", help="train a generating function on the HJ residual")
    t.add_argument("--preset", choices=["default", "paper"], default="default")
    t.add_argument(
        "--scene",
        default=None,
        help="scene file (TOML): derive the domain from it and stop once its target is met",
    )
    t.add_argument("--out", required=True, help="model file to write (.safetensors)")
    t.add_argument("--name", default=None, help="model name recorded in the file")
    t.add_argument(
        "--inertia", type=float, nargs=3, metavar="I", help="the rigid body's principal moments"
    )
    t.add_argument(
        "--system",
        default=None,
        help="the Lie–Poisson system: rigid-body (default), heavy-top (I = (1, 1.5, 2), "
        "mgl = 0.981, χ = (0, 0, 1)), or a JSON file of LiePoissonSystem.to_dict(); other "
        "systems default to the exp chart and, unless H is homogeneous quadratic, 't,p' inputs",
    )
    t.add_argument("--chart", choices=["cayley", "exp"])
    t.add_argument("--widths", type=int, nargs="*", metavar="W", help="hidden layer widths")
    t.add_argument("--inputs", choices=["t,p", "homogeneous"], help="MLP ansatz")
    t.add_argument("--taylor-order", dest="taylor_order", type=int, help="exact Taylor terms K")
    t.add_argument("--mlp-power", dest="mlp_power", type=int, help="m in t^m·MLP")
    t.add_argument("--domain", choices=["cube", "shell", "top"])
    t.add_argument("--r-min", dest="r_min", type=float)
    t.add_argument("--r-max", dest="r_max", type=float)
    t.add_argument("--half-width", dest="half_width", type=float)
    t.add_argument(
        "--weight-power",
        dest="weight_power",
        type=float,
        help="divide each HJ residual by (1 + |p|^2)^(q/2) (0: unweighted)",
    )
    t.add_argument("--h-max", dest="h_max", type=float, help="t is sampled in [0, h_max]")
    t.add_argument("--batch", type=int)
    t.add_argument("--points", dest="n_points", type=int, help="fixed point pool (0: resample)")
    t.add_argument("--iterations", type=int)
    t.add_argument("--lr", type=float)
    t.add_argument("--schedule", choices=["cosine", "constant"])
    t.add_argument("--seed", type=int)
    t.add_argument(
        "--lbfgs-iterations", dest="lbfgs_iterations", type=int, help="L-BFGS polish after Adam"
    )
    t.add_argument(
        "--data-weight", dest="data_weight", type=float, help="weight λ of the trajectory-data loss"
    )
    t.add_argument(
        "--data-points", dest="data_points", type=int, help="exact one-step pairs for the data loss"
    )
    t.add_argument("--data-h", dest="data_h", type=float, help="step of the data pairs (h_max)")
    _sampling_flags(t)
    t.add_argument(
        "--sampling-states",
        dest="sampling_states",
        type=float,
        nargs="+",
        metavar="X",
        help="initial states whose orbits scene sampling follows: dim numbers each",
    )
    t.add_argument(
        "--sampling-horizon", dest="sampling_horizon", type=float, help="orbit time span (10)"
    )
    t.add_argument("--dtype", choices=["float32", "float64"])
    t.add_argument("--device", help="cpu, cuda, cuda:0, ...")
    t.add_argument(
        "--derivatives",
        choices=["reverse", "autograd"],
        help="how the HJ loss takes dS/dt, dS/dp: hand-written reverse pass (default, faster) or "
        "nested autograd (as the shipped models were trained)",
    )
    t.add_argument("--checkpoint", default=None, help="checkpoint file (written periodically)")
    t.add_argument("--checkpoint-every", dest="checkpoint_every", type=int, default=500)
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
        type=int,
        default=None,
        help="torch threads (default: 1 on a machine with <= 2 cores, else torch's default)",
    )
    t.add_argument(
        "--max-seconds",
        dest="max_seconds",
        type=float,
        default=None,
        help="stop training after this wall time and save the model reached (default: no limit)",
    )
    _document_train_flags(t)

    sub.add_parser("models", help="list the shipped models and how they were trained")

    se = sub.add_parser(
        "select", help="the cheapest integrator and step meeting an error target on a scene"
    )
    se.add_argument("scene", help="scene file (TOML); its [select] table gives the defaults")
    se.add_argument(
        "--target",
        type=float,
        nargs="+",
        help="max |mu(T) - mu_ref(T)|/|mu0| (one selection per value)",
    )
    se.add_argument("--T", type=float, default=None, help="horizon (default: the scene's)")
    se.add_argument("--h", type=float, default=None, help="measure at this step only")
    se.add_argument("--models", nargs="+", help="learned models (default: the shipped ones)")
    se.add_argument("--json", default=None, help="write every candidate's row to this file")
    se.add_argument("--threads", type=int, default=1, help="rayon threads (default 1)")
    se.add_argument(
        "--budget", type=float, default=20.0, help="seconds per candidate's ladder (default 20)"
    )
    se.add_argument(
        "--max-steps",
        dest="max_steps",
        type=int,
        default=1 << 20,
        help="finest rung: most steps to T (default 2^20)",
    )

    st = sub.add_parser("stability", help="stability map: where each method breaks as h grows")
    st.add_argument("--out", default="out/stability", help="output folder")
    st.add_argument("--horizon", type=float, default=20.0, help="time T of the error (default 20)")
    st.add_argument("--threshold", type=float, default=0.1, help="relative error called broken")
    st.add_argument("--quick", action="store_true", help="two step sizes only (for tests)")
    st.add_argument(
        "--scene",
        default=None,
        help="map this rigid-body scene file's body (TOML) instead of the paper's",
    )
    st.add_argument(
        "--model",
        action="append",
        metavar="PATH",
        help="also map this model (file or shipped name; repeatable); it must be trained for "
        "the map's body",
    )
    st.add_argument("--no-progress", dest="no_progress", action="store_true")
    _scheduler_flag(st)

    c = sub.add_parser("chart", help="work–precision charts: error and energy error against cost")
    c.add_argument("--out", default="out/chart", help="output folder (default: out/chart)")
    c.add_argument("--quick", action="store_true", help="a tiny sweep (seconds; for tests)")
    c.add_argument(
        "--scene",
        default=None,
        help="chart this rigid-body scene file (TOML: body, states, horizon) instead of the "
        "paper's and the separatrix scenes",
    )
    c.add_argument(
        "--model",
        action="append",
        metavar="PATH",
        help="also chart this model (file or shipped name; repeatable) against the classical "
        "methods; it must be trained for the chart's body",
    )
    c.add_argument(
        "--threads",
        type=int,
        default=1,
        help="rayon threads for the rollouts (default 1: cost per trajectory on one core)",
    )
    c.add_argument(
        "--no-paper",
        dest="no_paper",
        action="store_true",
        help="skip the shipped paper-configuration model (253k parameters, slow)",
    )
    _scheduler_flag(c)
    sw = sub.add_parser(
        "sweep", help="accuracy against parameter count and rollout speed, over network sizes"
    )
    sw.add_argument("--out", default="out/sweep", help="output folder (default: out/sweep)")
    sw.add_argument("--stem", default="sweep", help="file name stem (default: sweep)")
    sw.add_argument(
        "--widths", nargs="+", metavar="W,W", help="architectures, e.g. 8,8 16,16,16 (default: 6)"
    )
    sw.add_argument("--seeds", type=int, nargs="+", help="training seeds (default: 0 1 2)")
    sw.add_argument("--iterations", type=int, help="Adam iterations (default: 2000)")
    _sampling_flags(sw)
    sw.add_argument("--no-paper", dest="no_paper", action="store_true", help="skip the paper model")
    sw.add_argument("--fast", action="store_true", help="two tiny networks, 20 iterations (tests)")
    sw.add_argument("--threads", type=int, default=1, help="torch and rayon threads (default 1)")
    sw.add_argument("--models-out", dest="models_out", help="folder to save the trained models in")
    sw.add_argument("--replot", metavar="JSON", help="redraw the chart from rows saved")
    sw.add_argument("--title", default=None, help="figure title")
    sw.add_argument("--no-progress", dest="no_progress", action="store_true")
    _scheduler_flag(sw)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    try:
        if args.command == "demo":
            return cmd_demo(args)
        if args.command == "train":
            return cmd_train(args, argv)
        if args.command == "chart":
            return cmd_chart(args)
        if args.command == "stability":
            return cmd_stability(args)
        if args.command == "sweep":
            return cmd_sweep(args)
        if args.command == "select":
            return cmd_select(args)
        return cmd_models(args)
    except (ValueError, FileNotFoundError) as e:
        print(f"poisson-rs {args.command}: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

"""What one step of every stepper of the package costs, in one process, one thread:
``RAYON_NUM_THREADS=1 taskset -c 0 python benches/step_costs.py``.

For the rigid body (I = (1.5, 2, 2.5)), the heavy top (I = (1, 1.5, 2), mgl = 0.981, χ = e₃),
Lotka–Volterra (PNN's 2D system, the 3D one of ``scenes/lotka_volterra_3d.toml`` and a 5D one), an
affine structure (``scenes/extended_pendulum.toml``) and a polynomial bivector
(``scenes/nambu_cubic.toml``; their scenes' states scaled by seeded factors in [0.95, 1.05]),
h = 0.1, a batch of seeded states (``--batch``, default 4096): every fixed-step classical method
the system names (``pr.classical_methods``; DOP853 left out: it is adaptive and in SciPy),
Taylor-HJ K = 3 and 5 in each chart the system names (``system.taylor_charts()``; the exact
log-canonical groupoid for Lotka–Volterra, a polynomial bivector's default realization only), and
the shipped learned models of that system. ``--system`` picks one system, ``--stepper``
(repeatable) the steppers to time, ``--model FILE`` (repeatable) adds a model file, timed as
``learned:FILE`` on the system it was trained for. Each stepper rolls the batch forward for a fixed
amount of work and keeps only the final state; a cell is the median of ``--rounds`` timed rollouts
after a warm-up, rounds alternating the steppers. Reported: ns per trajectory-step, the ratio to
the package's own RK4 step in the same run, and the mean Newton updates per step of the implicit
ones (from ``integrate(..., return_info=True)``). ``--json FILE`` writes the numbers.

``--baseline DIR`` times the build before in the same run: ``DIR`` is a directory from which
``import poisson_rs`` loads that build (a checkout's ``python/`` with its extension built, or a
``site-packages`` where its wheel is installed). This build and that one then run in two worker
processes on the same core, one timed rollout at a time, the builds alternating within every
round; each cell gains the baseline's ns per step, the ratio now / before and its Newton updates.
A stepper one build lacks is "n/a" there.

Each build is timed from ``--copies`` (default 2) fresh copies of its package, one worker
process each, the copies alternating within every round too: the same extension ran one kernel
up to 1.3× apart from two files holding the same bytes (``benches/placements.py``). A cell is
the median over the copies of each copy's median, printed with the copies' range; now / before
is the ratio of those medians, with the range any copy of one build against any copy of the
other gives (``vs_baseline_range`` in the JSON). Build both the way the wheel is built
(``benches/build_core.sh``; ``cargo build --release`` skips the profile's LTO and compiles other
code), for a revision ``REV``::

    benches/build_core.sh REV /tmp/base
    RAYON_NUM_THREADS=1 taskset -c 0 python benches/step_costs.py --baseline /tmp/base/python \
        --copies 3

A step's cost is only half of the choice: what it buys in accuracy is charted by ``poisson-rs
select`` and the work–precision charts; this table says where the time of a step goes.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

os.environ.setdefault("RAYON_NUM_THREADS", "1")

import numpy as np

import poisson_rs as pr
from poisson_rs.files import atomic_write_bytes, check_output_path
from poisson_rs.scenes import load_scene

sys.path.insert(0, str(Path(__file__).resolve().parent))
from placements import fresh_copies, ratio_range, summary

H = 0.1
#: A 5-D Lotka–Volterra system (c of rank 4: one Casimir), for the dimensions above 3.
LV5_C = [
    [0.0, 1.0, -1.0, 1.0, 0.0],
    [-1.0, 0.0, 1.0, 0.0, 1.0],
    [1.0, -1.0, 0.0, 1.0, -1.0],
    [-1.0, 0.0, -1.0, 0.0, 1.0],
    [0.0, -1.0, 1.0, -1.0, 0.0],
]
LV5_B = [1.0, 2.0, 1.5, 0.5, 1.0]
#: The package's scene files.
SCENES = Path(__file__).resolve().parent.parent / "scenes"
#: Trajectory-steps per timed rollout.
WORK = 200_000


def rigid_states(batch: int, rng: np.random.Generator) -> np.ndarray:
    """On spheres of radius 1 to 3 (inside the default model's shell 1 ≤ |μ| ≤ 4)."""
    d = rng.normal(size=(batch, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(1.0, 3.0, (batch, 1))


def top_states(batch: int, rng: np.random.Generator) -> np.ndarray:
    """M in [−1.5, 1.5]³ and Γ a unit vector (inside the learned model's top domain)."""
    g = rng.normal(size=(batch, 3))
    return np.concatenate(
        [rng.uniform(-1.5, 1.5, (batch, 3)), g / np.linalg.norm(g, axis=1, keepdims=True)], axis=1
    )


def lotka_volterra_states(batch: int, rng: np.random.Generator, b: np.ndarray) -> np.ndarray:
    """Within a log distance of 0.4 of the equilibrium x* = b (inside the learned model's box)."""
    return np.exp(rng.uniform(-0.4, 0.4, (batch, len(b)))) * b


def steppers(system: Any, learned: list[str]) -> dict[str, Any]:
    """Every stepper of ``system`` this build offers, by name. One that the build cannot make
    (an older build, under ``--baseline``) is left out, and the table says n/a."""
    makers: dict[str, Any] = {}
    # Through the structure protocol: the system's own classical methods and Taylor-HJ charts.
    for name in pr.classical_methods(system):
        if name != "dop853":
            makers[name] = lambda n=name: pr.classical(system, n)
    # Every chart the system has; where it has more than two (a polynomial bivector's
    # realizations of order 1 to 6 beside the matched one), its default, the first, only.
    charts = system.taylor_charts()
    for order in (3, 5):
        for chart in charts if len(charts) <= 2 else charts[:1]:
            makers[f"taylor{order}-{chart}"] = lambda k=order, c=chart: pr.taylor_integrator(
                system, order=k, chart=c
            )
    for name in learned:
        makers[f"learned:{name}"] = lambda n=name: pr.load_model(n)
    out: dict[str, Any] = {}
    for name, make in makers.items():
        try:
            out[name] = make()
        except (AttributeError, TypeError, ValueError, KeyError, OSError) as exc:
            print(f"{name}: not in this build ({type(exc).__name__}: {exc})", file=sys.stderr)
    return out


def cases(batch: int, which: str) -> list[tuple[str, Any, np.ndarray, list[str]]]:
    """(label, system, seeded states, learned model names) of the systems ``which`` names."""
    rng = np.random.default_rng(42)
    out = [
        ("rigid body", pr.RigidBody((1.5, 2.0, 2.5)), rigid_states(batch, rng), ["default"]),
        (
            "heavy top",
            pr.HeavyTop((1.0, 1.5, 2.0), 0.981, (0.0, 0.0, 1.0)),
            top_states(batch, rng),
            ["heavy_top_h05"],
        ),
    ]
    pnn = pr.lotka_volterra([[0.0, 1.0], [-1.0, 0.0]], [1.0, 2.0])
    lv3 = pr.lotka_volterra([[0.0, 1.0, 1.0], [-1.0, 0.0, 1.0], [-1.0, -1.0, 0.0]], [1.0, 2.0, 1.0])
    out += [
        (
            "lotka-volterra",
            pnn,
            lotka_volterra_states(batch, rng, np.array([1.0, 2.0])),
            ["lotka_volterra_h01"],
        ),
        (
            "lotka-volterra 3d",
            lv3,
            lotka_volterra_states(batch, rng, np.array([1.0, 2.0, 1.0])),
            [],
        ),
        (
            "lotka-volterra 5d",
            pr.lotka_volterra(LV5_C, LV5_B),
            lotka_volterra_states(batch, rng, np.array(LV5_B)),
            [],
        ),
    ]
    for label, name in SCENE_CASES.items():
        scene = load_scene(SCENES / f"{name}.toml")
        points = np.asarray(scene.points, dtype=float)
        out.append((label, scene.system, scene_states(points, batch, rng), []))
    if which == "all":
        return out
    return [c for c in out if system_key(c[0]) == which]


def system_key(label: str) -> str:
    """The ``--system`` value that picks a case: its label up to a dimension or a parenthesis."""
    for tail in (" 3d", " 5d"):
        label = label.removesuffix(tail)
    return label.split(" (")[0].replace(" ", "-")


#: The structures with no system of their own above, from the package's scenes (label: scene).
SCENE_CASES = {
    "affine (extended pendulum)": "extended_pendulum",
    "polynomial bivector (Nambu cubic)": "nambu_cubic",
}


def scene_states(points: np.ndarray, batch: int, rng: np.random.Generator) -> np.ndarray:
    """The scene's states, each coordinate scaled by a seeded factor in [0.95, 1.05]."""
    picks = points[rng.integers(0, len(points), batch)]
    return picks * rng.uniform(0.95, 1.05, picks.shape)


def steps_for(name: str, batch: int) -> int:
    """Steps of one timed rollout: cheap explicit steps take more, so every timing is well
    above noise (the same in every build)."""
    n = max(1, WORK // batch)
    return n * 20 if name in ("rk4", "splitting", "splitting_casimir", "log_splitting") else n


class Build:
    """The steppers of the build this process imports, timed on request."""

    def __init__(self, batch: int, which: str, models: list[str] | None = None) -> None:
        # A learned model's orbits may leave its training domain over the rollout: that
        # changes its accuracy, not the cost of a step, and the warning would only clutter.
        warnings.filterwarnings("ignore", message=".*outside the training domain.*")
        self.batch = batch
        files = {f: pr.load_model(f).system for f in models or []}
        self.table = {
            label: (
                mu0,
                steppers(system, [*learned, *(f for f, s in files.items() if s == system)]),
            )
            for label, system, mu0, learned in cases(batch, which)
        }

    def names(self) -> dict[str, list[str]]:
        return {label: list(t) for label, (_, t) in self.table.items()}

    def package(self) -> str:
        return str(Path(pr.__file__).resolve().parent)

    def updates(self, label: str, name: str) -> float | None:
        """Mean Newton updates per step over one rollout (None for explicit steps)."""
        mu0, table = self.table[label]
        n = steps_for(name, self.batch)
        _, info = pr.integrate(table[name], mu0, H, n, every=n, return_info=True)
        if not np.all(info.converged):
            raise RuntimeError(f"{label}, {name}: a step failed in the bench rollout")
        total = float(np.sum(info.newton_iterations))
        return total / (len(mu0) * n) if total else None

    def time(self, label: str, name: str) -> float:
        """Seconds per trajectory-step of one rollout."""
        mu0, table = self.table[label]
        n = steps_for(name, self.batch)
        start = time.perf_counter()
        pr.integrate(table[name], mu0, H, n, every=n)
        return (time.perf_counter() - start) / (len(mu0) * n)


class Worker:
    """A :class:`Build` in a child process that imports ``poisson_rs`` from ``path`` (one JSON
    request and answer per line); the child inherits this process's core and threads."""

    def __init__(self, path: Path, batch: int, which: str, models: list[str]) -> None:
        env = {**os.environ, "PYTHONPATH": str(path)}
        extra = [a for f in models for a in ("--model", f)]
        self.proc = subprocess.Popen(
            [
                sys.executable,
                __file__,
                "--worker",
                "--batch",
                str(batch),
                "--system",
                which,
                *extra,
            ],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=env,
            text=True,
        )

    def _ask(self, method: str, *args: Any) -> Any:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(json.dumps([method, *args]) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise SystemExit(f"the worker for {method} exited (code {self.proc.wait()})")
        answer = json.loads(line)
        if "error" in answer:
            raise SystemExit(answer["error"])
        return answer["value"]

    def names(self) -> dict[str, list[str]]:
        return dict(self._ask("names"))

    def package(self) -> str:
        return str(self._ask("package"))

    def updates(self, label: str, name: str) -> float | None:
        value = self._ask("updates", label, name)
        return None if value is None else float(value)

    def time(self, label: str, name: str) -> float:
        return float(self._ask("time", label, name))

    def close(self) -> None:
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        self.proc.wait()


def serve(batch: int, which: str, models: list[str]) -> None:
    """The worker's loop: requests on stdin, answers on the real stdout; anything the package
    prints goes to stderr, so it cannot break the protocol."""
    out = sys.stdout
    sys.stdout = sys.stderr
    build = Build(batch, which, models)
    for line in sys.stdin:
        method, *args = json.loads(line)
        try:
            answer = {"value": getattr(build, method)(*args)}
        except Exception as exc:  # reported to the parent, which stops
            answer = {"error": f"{method}{tuple(args)}: {type(exc).__name__}: {exc}"}
        out.write(json.dumps(answer) + "\n")
        out.flush()


def check_models(models: list[str], which: str) -> None:
    """Before any work: every ``--model`` file loads and was trained for a system this run
    times; SystemExit naming the file otherwise."""
    systems = [system for _, system, _, _ in cases(1, which)]
    for f in models:
        try:
            system = pr.load_model(f).system
        except (OSError, ValueError) as exc:
            raise SystemExit(f"--model {f}: {exc}") from None
        if system not in systems:
            raise SystemExit(f"--model {f}: trained for {system!r}, which --system {which} omits")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=4096)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument(
        "--system",
        choices=(
            "all",
            "rigid-body",
            "heavy-top",
            "lotka-volterra",
            "affine",
            "polynomial-bivector",
        ),
        default="all",
    )
    parser.add_argument(
        "--baseline",
        type=Path,
        default=None,
        help="a directory from which `import poisson_rs` loads the build before",
    )
    parser.add_argument(
        "--stepper",
        action="append",
        default=None,
        help="time only this stepper (repeatable; RK4 always runs, for the ratios)",
    )
    parser.add_argument(
        "--model",
        action="append",
        default=[],
        help="a model file to time too, as learned:FILE on its system (repeatable)",
    )
    parser.add_argument(
        "--copies",
        type=int,
        default=2,
        help="time each build from this many fresh copies of its package (placements; >= 1)",
    )
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.batch < 1 or args.rounds < 1 or args.copies < 1:
        raise SystemExit("--batch, --rounds and --copies must be at least 1")
    if args.worker:
        return serve(args.batch, args.system, args.model)
    if args.json is not None:
        check_output_path(args.json)
    check_models(args.model, args.system)
    here = Path(pr.__file__).resolve().parent.parent
    sources = {"now": here}
    if args.baseline is not None:
        if not (args.baseline / "poisson_rs" / "__init__.py").is_file():
            raise SystemExit(f"--baseline: {args.baseline} holds no poisson_rs package")
        if (args.baseline / "poisson_rs").resolve() == here / "poisson_rs":
            raise SystemExit(f"--baseline: both builds are {here / 'poisson_rs'}")
        sources["before"] = args.baseline
    with tempfile.TemporaryDirectory(prefix="step_costs_") as tmp:
        builds: dict[str, list[Worker]] = {}
        try:
            for key, source in sources.items():
                copies = fresh_copies(source / "poisson_rs", args.copies, Path(tmp) / key)
                builds[key] = []
                for copy in copies:
                    worker = Worker(copy.parent, args.batch, args.system, args.model)
                    builds[key].append(worker)
                    loaded = Path(worker.package())
                    if loaded != copy.resolve():  # a package on the path ahead of PYTHONPATH
                        raise SystemExit(f"{key}: the worker loaded {loaded}, not {copy}")
                print(f"{key}: {source / 'poisson_rs'}, {args.copies} fresh copies")
            only = None if args.stepper is None else {"rk4", *args.stepper}
            rows = measure(builds, args.batch, args.rounds, only)
        except RuntimeError as exc:  # a failed step in a worker's rollout: said, no traceback
            raise SystemExit(str(exc)) from None
        finally:
            for workers in builds.values():
                for w in workers:
                    w.close()
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; load average {load}")
    if args.json is not None:
        meta = {
            "h": H,
            "batch": args.batch,
            "rounds": args.rounds,
            "copies": args.copies,
            "load_average": load,
        }
        if args.baseline is not None:
            meta["baseline"] = str(args.baseline)
        atomic_write_bytes(args.json, json.dumps({**meta, "rows": rows}, indent=1).encode())


def measure(
    builds: dict[str, list[Worker]], batch: int, rounds: int, only: set[str] | None = None
) -> list[dict[str, Any]]:
    """Every system's steppers (those in ``only`` where given) in every build: Newton updates
    from one rollout of the first copy, then ``rounds`` rounds of one timed rollout per stepper,
    build and copy, the builds' order and the copies' order alternating."""
    names = {key: copies[0].names() for key, copies in builds.items()}
    if only is not None:
        offered = {n for table in names.values() for steppers in table.values() for n in steppers}
        unknown = sorted(only - offered)
        if unknown:
            raise SystemExit(
                f"--stepper: no stepper named {', '.join(unknown)} here; "
                f"the steppers: {', '.join(sorted(offered))}"
            )
    rows: list[dict[str, Any]] = []
    keys = list(builds)
    for label in names["now"]:
        order = list(names["now"][label])
        for key in builds:
            order += [n for n in names[key].get(label, []) if n not in order]
        if only is not None:
            order = [n for n in order if n in only]
            if order == ["rk4"]:
                continue
        have = {key: set(names[key].get(label, [])) for key in builds}
        updates = {
            key: {n: copies[0].updates(label, n) for n in order if n in have[key]}
            for key, copies in builds.items()
        }
        # times[key][name][copy]: that copy's timed rollouts.
        times = {key: {n: [[] for _ in copies] for n in order} for key, copies in builds.items()}
        for r in range(rounds):
            for name in order:
                for key in keys if r % 2 == 0 else keys[::-1]:
                    if name not in have[key]:
                        continue
                    copies = list(enumerate(builds[key]))
                    for c, worker in copies if r % 2 == 0 else copies[::-1]:
                        times[key][name][c].append(worker.time(label, name))
        # Per copy: the median of its rounds, in ns.
        med = {
            key: {n: [statistics.median(v) * 1e9 for v in per] for n, per in t.items() if per[0]}
            for key, t in times.items()
        }
        for name in order:
            row: dict[str, Any] = {"system": label, "stepper": name, "batch": batch}
            for key in keys:
                tag = "" if key == "now" else "_baseline"
                per, rk4 = med[key].get(name), med[key].get("rk4")
                ns = None if per is None else summary(per)[0]
                row["ns_per_step" + tag] = ns
                row["ns_per_step_copies" + tag] = per
                row["vs_rk4" + tag] = ns / summary(rk4)[0] if ns is not None and rk4 else None
                row["newton_updates_per_step" + tag] = updates[key].get(name)
            if "before" in builds:
                a, b = row["ns_per_step_copies"], row["ns_per_step_copies_baseline"]
                both = a is not None and b is not None
                ratios = ratio_range(a, b) if both else None
                row["vs_baseline"] = None if ratios is None else ratios[0]
                row["vs_baseline_range"] = None if ratios is None else list(ratios[1:])
            rows.append(row)
            print(line_of(row), flush=True)
    return rows


def line_of(row: dict[str, Any]) -> str:
    """One printed row: ns per step (the copies' range where there are several), × RK4, Newton
    updates; with a baseline, its cells and now/before with its range over the copies."""

    def cell(
        ns: float | None, per: list[float] | None, ratio: float | None, u: float | None
    ) -> str:
        if ns is None or per is None or ratio is None:
            return f"{'n/a':>9s} {'':11s}"
        spread = f" [{min(per):.1f}-{max(per):.1f}]" if len(per) > 1 else ""
        note = f", {u:.2f} upd" if u is not None else ""
        return f"{ns:9.1f} ns{spread} {ratio:7.1f}x RK4{note}"

    text = f"{row['system']:17s} {row['stepper']:24s} " + cell(
        row["ns_per_step"], row["ns_per_step_copies"], row["vs_rk4"], row["newton_updates_per_step"]
    )
    if "vs_baseline" in row:
        text += " | before " + cell(
            row["ns_per_step_baseline"],
            row["ns_per_step_copies_baseline"],
            row["vs_rk4_baseline"],
            row["newton_updates_per_step_baseline"],
        )
        ratio, (lo, hi) = row["vs_baseline"], row["vs_baseline_range"] or (None, None)
        text += (
            f" | now/before {ratio:.2f} [{lo:.2f}-{hi:.2f}]"
            if ratio is not None
            else " | now/before n/a"
        )
    return text


if __name__ == "__main__":
    main()

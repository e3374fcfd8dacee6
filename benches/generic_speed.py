"""Rigid-body speed of the dimension-generic core against a build of the core from before it was
generic, in one process: both extension modules are loaded side by side and timed in
alternation, so machine noise hits both alike.

The baseline is the `_core` extension built from an earlier commit (the last one whose core was
written for dimension 3 only). Build it once with::

    git worktree add /tmp/old-core 5d58c5d
    cd /tmp/old-core
    CARGO_TARGET_DIR=/tmp/old-target cargo build --release --features python --lib

then run ``python benches/generic_speed.py --baseline /tmp/old-target/release/libpoisson_rs.so``.

Instruction counts, which a loaded machine does not disturb: ``--profile MODEL`` runs one
rollout of one trajectory (5,000 steps of the default model, 20,000 of taylor5-cayley) with one
build only (``--baseline PATH`` for the earlier one, else this one), for
``RAYON_NUM_THREADS=1 valgrind --tool=callgrind python benches/generic_speed.py --profile default``
and ``callgrind_annotate``, summing the lines of the core's shared library.
It prints, per model and batch, steps/s of both builds and their ratio (generic / baseline), the
median over interleaved repeats; ``--json FILE`` writes the numbers.

Models: the shipped default learned model (121 MLP parameters) and the Taylor K=5 integrator in
the Cayley chart, written without the structure-constant tensor so that the old core reads it.
"""

from __future__ import annotations

import argparse
import importlib.machinery
import importlib.util
import json
import statistics
import sys
import time
from importlib import resources
from pathlib import Path
from types import ModuleType

import numpy as np
from safetensors.numpy import save

from poisson_rs import _core
from poisson_rs.files import atomic_write_bytes, check_output_path
from poisson_rs.taylor import taylor_terms

INERTIA = (1.5, 2.0, 2.5)

#: Steps of the one-trajectory rollout ``--profile`` runs, per model.
PROFILE_STEPS = {"default": 5000, "taylor5-cayley": 20000}


def load_baseline(path: Path) -> ModuleType:
    """The old extension under another package name (its init function is still PyInit__core)."""
    loader = importlib.machinery.ExtensionFileLoader("baseline_core._core", str(path))
    spec = importlib.util.spec_from_file_location("baseline_core._core", path, loader=loader)
    if spec is None:
        raise SystemExit(f"cannot load {path}")
    module = importlib.util.module_from_spec(spec)
    loader.exec_module(module)
    return module


def taylor5_bytes() -> bytes:
    """Taylor K=5, Cayley chart, as a rigid-body model file both cores read."""
    powers, coeffs = taylor_terms(INERTIA, 5, "cayley")
    meta = {"format": "poisson_rs.generating/1", "chart": "cayley"}
    return save({"poly.powers": powers, "poly.coeffs": coeffs}, metadata=meta)


def steps_per_second(core: ModuleType, model: object, states: np.ndarray, n_steps: int) -> float:
    t0 = time.perf_counter()
    core.rollout_model(model, states, 0.1, n_steps, n_steps)
    return len(states) * n_steps / (time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", type=Path, default=None, help="the old _core shared library")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument(
        "--profile",
        choices=list(PROFILE_STEPS),
        default=None,
        help="one rollout of one build only, for callgrind",
    )
    args = ap.parse_args(argv)
    if args.json is not None:
        check_output_path(args.json)
    default = resources.files("poisson_rs.models").joinpath("default.safetensors").read_bytes()
    models = {"default": default, "taylor5-cayley": taylor5_bytes()}
    if args.profile is not None:
        core = _core if args.baseline is None else load_baseline(args.baseline)
        model = core.Model.from_bytes(models[args.profile])
        n = PROFILE_STEPS[args.profile]
        core.rollout_model(model, np.array([[1.0, 1.0, 2.0]]), 0.1, n, n)
        return 0
    if args.baseline is None:
        ap.error("--baseline is needed to compare the two builds")
    old = load_baseline(args.baseline)
    rng = np.random.default_rng(0)
    rows = []
    for name, data in models.items():
        new_model, old_model = _core.Model.from_bytes(data), old.Model.from_bytes(data)
        for batch in (1, 64, 4096):
            states = rng.normal(size=(batch, 3)) * 2.0
            n_steps = max(20, 40_000 // batch)
            for core, model in ((_core, new_model), (old, old_model)):
                steps_per_second(core, model, states, n_steps)  # warm-up
            new_s, old_s = [], []
            for r in range(args.repeats):
                # Alternate which build goes first: whichever runs second sees a warmer cache.
                if r % 2:
                    old_s.append(steps_per_second(old, old_model, states, n_steps))
                    new_s.append(steps_per_second(_core, new_model, states, n_steps))
                else:
                    new_s.append(steps_per_second(_core, new_model, states, n_steps))
                    old_s.append(steps_per_second(old, old_model, states, n_steps))
            ratio = statistics.median(n / o for n, o in zip(new_s, old_s, strict=True))
            row = {
                "model": name,
                "batch": batch,
                "generic_steps_per_s": statistics.median(new_s),
                "baseline_steps_per_s": statistics.median(old_s),
                "ratio": ratio,
            }
            rows.append(row)
            print(
                f"{name:>15} batch {batch:>5}: generic {row['generic_steps_per_s']:10.4g} "
                f"baseline {row['baseline_steps_per_s']:10.4g} steps/s, ratio {ratio:.3f}",
                flush=True,
            )
    if args.json:
        atomic_write_bytes(args.json, (json.dumps(rows, indent=1) + "\n").encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())

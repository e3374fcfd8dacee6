"""RK4 rollouts on a GPU: poisson_rs's device path (``pr.on_device``: the stepper's torch step,
compiled by torch.compile on CUDA) against JAX ``jit(vmap(lax.scan))`` RK4 on the same device,
in float64 and float32, on the systems of ``benches/peers.py``:

    python benches/device_rollout.py --device cuda --batch 1000000 --steps 1000 --json out.json

JAX runs on its default device: install a CUDA build of jax beside the ``bench`` extra's pins to
put it on the GPU (the script prints JAX's device, and says when it is not the one torch uses).
Each cell is the median of ``--rounds`` timed rollouts after a warm-up (both compile there),
contenders alternated, final state only (``every = steps``); trajectory-steps per second and the
ratio to JAX. Every contender's final states are checked against the Rust core's on the CPU for
a slice of the batch (float64: RK4 in another summation order, so 1e-10 or better on the
non-chaotic systems; float32: single precision).

The Rust core on the CPU (``core``) runs beside them: what the same call costs without a device.
Without CUDA (``--device cpu``, the default where torch sees none) it runs the CPU reference path
at a small batch (eager; ``--compile on`` compiles it for the CPU): that checks the script and
the agreement, and its timings say nothing about a GPU.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import peers

import poisson_rs as pr
from poisson_rs.files import atomic_write_bytes, check_output_path

SYSTEMS = ("rigid body", "heavy top", "lotka-volterra", "extended pendulum", "point vortices")


def rk4_stepper(system: str) -> Any:
    """The package's RK4 stepper of a peers.py system."""
    if system in peers.EXPRESSION_SCENES:
        from poisson_rs.scenes import load_scene

        return load_scene(peers.SCENES / peers.EXPRESSION_SCENES[system]).system.classical("rk4")
    if system == "lotka-volterra":
        return pr.log_canonical_classical(pr.lotka_volterra(peers.LV_C, peers.LV_B), "rk4")
    body = (
        pr.RigidBody(peers.RIGID_I)
        if system == "rigid body"
        else pr.HeavyTop(peers.TOP_I, peers.MGL, peers.COM)
    )
    return pr.classical(body, "rk4")


def main() -> None:
    import torch

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    cuda = torch.cuda.is_available()
    ap.add_argument("--device", default="cuda" if cuda else "cpu")
    ap.add_argument("--batch", type=int, default=1_000_000 if cuda else 4096)
    ap.add_argument("--steps", type=int, default=1000 if cuda else 50)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--dtypes", nargs="+", default=["float64", "float32"])
    ap.add_argument("--systems", nargs="+", default=list(SYSTEMS), choices=SYSTEMS)
    ap.add_argument("--check", type=int, default=256, help="trajectories checked on the core")
    ap.add_argument(
        "--compile",
        choices=("auto", "on", "off"),
        default="auto",
        help="torch.compile the device step (auto: on CUDA; 'on' compiles for the CPU too)",
    )
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    if args.json is not None:
        check_output_path(args.json)
    rows: list[dict[str, Any]] = []
    jax_device = None
    for system in args.systems:
        h = peers.step_size(system)
        x0 = peers.states(system, args.batch)
        core = pr.integrate(rk4_stepper(system), x0[: args.check], h, args.steps, every=args.steps)
        for dtype in args.dtypes:
            runners: dict[str, Any] = {}
            compile_ = None if args.compile == "auto" else args.compile == "on"
            dev = pr.on_device(rk4_stepper(system), args.device, dtype=dtype, compile=compile_)
            # The Rust core on the CPU: what the same call costs without a device.
            cpu = rk4_stepper(system)
            runners["core"] = lambda x, n, s=cpu, h=h: pr.integrate(
                s, np.asarray(x, dtype=np.float64), h, n, every=n
            )[:, -1]
            runners["poisson_rs"] = lambda x, n, d=dev, h=h: pr.integrate(d, x, h, n, every=n)[
                :, -1
            ]
            jax_run = peers.jax_runner(system, dtype)
            if jax_run is not None:
                import jax

                jax_device = str(jax.devices()[0])
                runners["jax"] = jax_run
            start = x0.astype(dtype)
            times: dict[str, list[float]] = {k: [] for k in runners}
            errors: dict[str, float] = {}
            for name, run in runners.items():  # warm-up (compilation) and agreement
                out = np.asarray(run(start, args.steps), dtype=np.float64)
                ref = core[:, -1]
                errors[name] = float(np.abs(out[: args.check] - ref).max() / np.abs(ref).max())
            for _ in range(args.rounds):
                for name, run in runners.items():
                    t0 = time.perf_counter()
                    run(start, args.steps)
                    times[name].append(time.perf_counter() - t0)
            work = args.batch * args.steps
            rate = {k: work / statistics.median(v) for k, v in times.items()}
            for name in runners:
                row = {
                    "system": system,
                    "dtype": dtype,
                    "contender": name,
                    "device": {"poisson_rs": args.device, "core": "cpu"}.get(name, jax_device),
                    "batch": args.batch,
                    "steps": args.steps,
                    "steps_per_s": rate[name],
                    "vs_jax": rate[name] / rate["jax"] if "jax" in rate else None,
                    "max_rel_diff_vs_core": errors[name],
                }
                rows.append(row)
                vs = f"{row['vs_jax']:.2f}× JAX" if row["vs_jax"] is not None else ""
                print(
                    f"{system:18s} {dtype:8s} {name:11s} {rate[name]:10.3g} steps/s {vs:>10s}  "
                    f"vs core {errors[name]:.1e}"
                )
    if jax_device is not None and not jax_device.lower().startswith(args.device[:3]):
        print(f"note: JAX ran on {jax_device}, poisson_rs on {args.device}", file=sys.stderr)
    if args.json is not None:
        meta = {
            "device": args.device,
            "torch_device_name": torch.cuda.get_device_name() if cuda else "cpu",
            "jax_device": jax_device,
            "torch": torch.__version__,
        }
        atomic_write_bytes(args.json, json.dumps({**meta, "rows": rows}, indent=1).encode())


if __name__ == "__main__":
    main()

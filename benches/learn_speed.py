"""pr.learn mode "auto" wall time on the LocSympNets single-trajectory rigid-body protocol and on
the heavy-top protocol of ``data_protocols.py``, with the kept family, its held-out one-step and
rollout errors, and the learned stepper's states after 10⁴ (rigid body, T = 1000) and 1000
(heavy top, T = 100) steps from the protocols' test states.

    PYTHONPATH=python taskset -c 1 python benches/learn_speed.py
    # this checkout against another one's python/, alternated, each run a fresh process:
    PYTHONPATH=python taskset -c 1 python benches/learn_speed.py --against OTHER/python --rounds 2
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
PROTOCOLS = ("single", "heavy")


def run(protocol: str) -> dict:
    """One pr.learn fit in this process: seconds, kept family, errors, final states."""
    import torch

    sys.path.insert(0, str(HERE))
    import data_protocols as dp

    import poisson_rs as pr

    torch.set_num_threads(1)
    if protocol == "single":
        trajs, tests, _, steps = dp.single_data()
        algebra = "so3"
    else:
        trajs, tests = dp.heavy_top_data()
        steps, algebra = 1000, "se3"
    t0 = time.perf_counter()
    stepper, report = pr.learn(trajs, dp.TAU, algebra=algebra, mode="auto", seed=0, progress=False)
    seconds = time.perf_counter() - t0
    final = np.asarray(pr.integrate(stepper, tests, dp.TAU, steps, every=steps))[:, -1]
    kept = report.kept
    return {
        "seconds": seconds,
        "family": kept.family,
        "parameters": kept.parameters,
        "one_step": kept.one_step,
        "rollout": kept.rollout,
        "final": final.tolist(),
        "package": str(Path(pr.__file__).resolve().parents[1]),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--one", choices=PROTOCOLS, help=argparse.SUPPRESS)
    parser.add_argument("--protocols", nargs="+", choices=PROTOCOLS, default=list(PROTOCOLS))
    parser.add_argument("--against", help="another checkout's python/ directory, alternated")
    parser.add_argument("--rounds", type=int, default=1)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(run(args.one)))
        return
    trees = [os.environ.get("PYTHONPATH", "")]
    if args.against:
        trees = [args.against, *trees]
    for protocol in args.protocols:
        results: dict[str, list[dict]] = {t: [] for t in trees}
        for _ in range(args.rounds):
            for tree in trees:
                env = {**os.environ, "PYTHONPATH": tree}
                out = subprocess.run(
                    [sys.executable, __file__, "--one", protocol],
                    env=env,
                    check=True,
                    capture_output=True,
                    text=True,
                ).stdout
                results[tree].append(json.loads(out.strip().splitlines()[-1]))
        for rs in results.values():
            r = rs[-1]
            secs = ", ".join(f"{x['seconds']:.2f}" for x in rs)
            print(
                f"{protocol:<6} {r['package']}: {secs} s  kept {r['family']} "
                f"({r['parameters']} parameters)  one-step {r['one_step']:.3e}  "
                f"rollout {r['rollout']:.3e}"
            )
        if len(trees) == 2:
            a, b = (np.array(results[t][-1]["final"]) for t in trees)
            print(f"{protocol:<6} max |final state difference| {np.abs(a - b).max():.2e}")


if __name__ == "__main__":
    main()

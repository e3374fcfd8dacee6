"""``pr.learn`` on a structure whose H no polynomial or term library holds: the affine bracket of
PNN's extended pendulum with H = u²/2 + v²/2 + u(r − u² − v²) + 0.3/(1 + v²) (a rational bump in v),
exact records (DOP853 at 1e-13) from 10 seeded states in [−0.8, 0.8]² × [0.2, 1.8], 101 records
each, h = 0.1, one thread:

    PYTHONPATH=python taskset -c 0 python benches/learn_network_h.py \
        --json docs/learning/network_h.json

Writes the search's table (every family tried: parameters, seconds, held-out one-step error,
rollout error, verdict), and as references the true H through the integrators the candidates are
stepped by: the implicit midpoint rule (the network family's) and Taylor-HJ by jets of order 5
(the term libraries'); and the Casimir r − u² − v²'s largest drift over 1000 steps of the kept
stepper from a held-out state.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

os.environ.setdefault("RAYON_NUM_THREADS", "1")

import numpy as np
import torch

import poisson_rs as pr
from poisson_rs.files import atomic_write_bytes, check_output_path
from poisson_rs.learn.data import prepare
from poisson_rs.learn.scoring import errors
from poisson_rs.scenes import load_scene

SCENE = Path(__file__).resolve().parent.parent / "scenes" / "extended_pendulum_pnn.toml"
H = "u**2/2 + v**2/2 + u*(r - u**2 - v**2) + 0.3/(1 + v**2)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", required=True, help="output file")
    args = ap.parse_args()
    out = check_output_path(args.json)
    torch.set_num_threads(1)
    bracket = load_scene(SCENE).system.base
    s = pr.with_hamiltonian(bracket, H)
    x0 = np.random.default_rng(0).uniform(-0.8, 0.8, size=(10, 3))
    x0[:, 2] += 1.0
    h = 0.1
    records = s.reference(x0, np.arange(101) * h)
    t0 = time.perf_counter()
    _, report = pr.learn(records, h, structure=bracket, progress=False)
    seconds = time.perf_counter() - t0
    print(report)
    data = prepare(records, h, None, test_fraction=0.2, seed=0, system=bracket)
    refs = {
        "true H, implicit midpoint": errors(pr.classical(s, "midpoint"), data),
        "true H, jets order 5": errors(s.taylor_integrator(5), data),
    }
    kept = report.kept
    roll = pr.integrate(kept.stepper, data.test[0][0], h, 1000)
    c = np.asarray(bracket.casimirs(roll)).ravel()
    payload = {
        "command": "PYTHONPATH=python taskset -c 0 python benches/learn_network_h.py --json "
        + args.json,
        "hamiltonian": H,
        "records": list(records.shape),
        "h": h,
        "seconds": round(seconds, 1),
        "threshold": report.threshold,
        "candidates": [
            {
                "family": cand.family,
                "parameters": cand.parameters,
                "seconds": round(cand.seconds, 1),
                "one_step": cand.one_step,
                "rollout": cand.rollout,
                "kept": cand is kept,
                "reason": cand.reason,
            }
            for cand in report.candidates
        ],
        "kept_hamiltonian": kept.hamiltonian_text,
        "references": {k: {"one_step": v[0], "rollout": v[1]} for k, v in refs.items()},
        "kept_casimir_drift_1000_steps": float(np.abs(c - c[0]).max()),
    }
    for k, v in refs.items():
        print(f"{k}: one-step {v[0]:.2e}, rollout {v[1]:.2e}")
    atomic_write_bytes(out, json.dumps(payload, indent=1).encode())


if __name__ == "__main__":
    main()

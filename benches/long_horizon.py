"""Cost against Casimir drift and energy error at a long horizon, rigid body: the package's
fixed-step integrators against RK4 at the step it needs, plain and with projection onto the
Casimir level set (|μ| renormalised after every step, the trick a user reaches for first).

``taskset -c 0 python benches/long_horizon.py --out docs/long_horizon`` writes
``long_horizon.png`` and ``long_horizon.json`` (every point: method, h, seconds, max |C/C₀ − 1|
and max |H/H₀ − 1| over the kept states). Defaults: T = 1e5, 16 seeded states with |μ| ≤ 3,
I = (1.5, 2, 2.5), states kept every 1000 steps, one thread (``RAYON_NUM_THREADS=1``). The
projected RK4 runs in numba (``pip install 'poisson_rs[bench]'``); without numba it is skipped
with a message.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("RAYON_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import numpy as np

import poisson_rs as pr

INERTIA = (1.5, 2.0, 2.5)
#: (method, steps) swept; RK4 down to the step that keeps the Casimir to ~1e-12 at T = 1e5.
SWEEP: dict[str, list[float]] = {
    "rk4": [0.1, 0.025, 0.00625, 0.0015625],
    "splitting": [0.1, 0.05],
    "splitting4": [0.1],
    "splitting_casimir": [0.1, 0.05],
    "midpoint": [0.1, 0.05],
    "dmv": [0.1],
}
#: Steps of RK4 with projection.
PROJECTED = [0.1, 0.05, 0.025, 0.0125]


def invariants(traj: np.ndarray, inv: np.ndarray) -> tuple[float, float]:
    """Max |C/C₀ − 1| and |H/H₀ − 1| over (n, records, 3); NaN if a trajectory failed."""
    c = np.sum(traj**2, axis=-1)
    h = 0.5 * np.sum(traj**2 * inv, axis=-1)
    return float(np.max(np.abs(c / c[:, :1] - 1))), float(np.max(np.abs(h / h[:, :1] - 1)))


def projected_rk4() -> Any:
    """RK4 with |μ| renormalised after every step, in numba; None without numba."""
    try:
        import numba
    except ImportError:
        print("numba is not installed: projected RK4 skipped", file=sys.stderr)
        return None
    i0, i1, i2 = (1.0 / v for v in INERTIA)

    @numba.njit(cache=False)
    def run(mu0: np.ndarray, h: float, n: int, every: int) -> np.ndarray:
        out = np.empty((mu0.shape[0], n // every + 1, 3))
        for b in range(mu0.shape[0]):
            x, y, z = mu0[b, 0], mu0[b, 1], mu0[b, 2]
            r0 = np.sqrt(x * x + y * y + z * z)
            out[b, 0] = mu0[b]
            for k in range(n):
                # RK4 on μ̇ = μ × (μ/I), in scalars (no array per stage).
                a1 = y * z * i2 - z * y * i1
                b1 = z * x * i0 - x * z * i2
                c1 = x * y * i1 - y * x * i0
                xx, yy, zz = x + 0.5 * h * a1, y + 0.5 * h * b1, z + 0.5 * h * c1
                a2 = yy * zz * i2 - zz * yy * i1
                b2 = zz * xx * i0 - xx * zz * i2
                c2 = xx * yy * i1 - yy * xx * i0
                xx, yy, zz = x + 0.5 * h * a2, y + 0.5 * h * b2, z + 0.5 * h * c2
                a3 = yy * zz * i2 - zz * yy * i1
                b3 = zz * xx * i0 - xx * zz * i2
                c3 = xx * yy * i1 - yy * xx * i0
                xx, yy, zz = x + h * a3, y + h * b3, z + h * c3
                a4 = yy * zz * i2 - zz * yy * i1
                b4 = zz * xx * i0 - xx * zz * i2
                c4 = xx * yy * i1 - yy * xx * i0
                x += h / 6.0 * (a1 + 2.0 * (a2 + a3) + a4)
                y += h / 6.0 * (b1 + 2.0 * (b2 + b3) + b4)
                z += h / 6.0 * (c1 + 2.0 * (c2 + c3) + c4)
                s = r0 / np.sqrt(x * x + y * y + z * z)
                x, y, z = x * s, y * s, z * s
                if (k + 1) % every == 0:
                    r = (k + 1) // every
                    out[b, r, 0], out[b, r, 1], out[b, r, 2] = x, y, z
        return out

    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--horizon", type=float, default=1e5)
    parser.add_argument("--states", type=int, default=16)
    parser.add_argument("--every", type=int, default=1000)
    parser.add_argument("--out", type=Path, default=Path("docs/long_horizon"))
    args = parser.parse_args()
    rng = np.random.default_rng(42)
    mu0 = rng.uniform(-3, 3, (args.states, 3))
    body = pr.RigidBody(INERTIA)
    inv = 1.0 / np.array(INERTIA)
    points: list[dict[str, Any]] = []

    def record(method: str, h: float, seconds: float, traj: np.ndarray) -> None:
        dc, dh = invariants(traj, inv)
        points.append({"method": method, "h": h, "seconds": seconds, "casimir": dc, "energy": dh})
        print(f"{method:18s} h={h:<7g} {seconds:8.2f} s  dC {dc:.1e}  dH {dh:.1e}", flush=True)

    for method, steps in SWEEP.items():
        stepper = pr.classical(body, method)
        for h in steps:
            n = round(args.horizon / h)
            every = min(args.every, n)
            start = time.perf_counter()
            traj = pr.integrate(stepper, mu0, h, n - n % every, every=every)
            record(method, h, time.perf_counter() - start, traj)
    run = projected_rk4()
    if run is not None:
        run(mu0[:1], 0.1, 10, 10)  # compile
        for h in PROJECTED:
            n = round(args.horizon / h)
            every = min(args.every, n)
            start = time.perf_counter()
            traj = run(mu0, h, n - n % every, every)
            record("rk4 + projection", h, time.perf_counter() - start, traj)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"horizon": args.horizon, "states": args.states, "inertia": INERTIA}
    args.out.with_suffix(".json").write_text(json.dumps({**meta, "points": points}, indent=1))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    for key, ax, label in (
        ("casimir", axes[0], "max |C/C₀ − 1|"),
        ("energy", axes[1], "max |H/H₀ − 1|"),
    ):
        for method in dict.fromkeys(p["method"] for p in points):
            pts = [p for p in points if p["method"] == method]
            x = [max(p[key], 1e-17) for p in pts]
            ax.loglog(x, [p["seconds"] for p in pts], "o-", label=method)
        ax.set_xlabel(label + f" at T = {args.horizon:g}")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel(f"seconds, {args.states} states, one thread")
    axes[1].legend(fontsize=8)
    fig.suptitle("Rigid body: cost against invariant errors (error < 1e-17 plotted at 1e-17)")
    fig.tight_layout()
    fig.savefig(args.out.with_suffix(".png"), dpi=120)


if __name__ == "__main__":
    main()

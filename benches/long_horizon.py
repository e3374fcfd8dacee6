"""Cost against Casimir drift and energy error at a long horizon, rigid body, heavy top or 3D
Lotka–Volterra: the
package's fixed-step integrators against RK4 at the step it needs, plain and with projection onto
the Casimir level sets (the trick a user reaches for first).

``taskset -c 0 python benches/long_horizon.py --out docs/long_horizon`` writes
``long_horizon.png`` and ``long_horizon.json`` (every point: method, h, seconds, the Casimir and
energy errors over the kept states). Defaults: T = 1e5, 16 seeded states, states kept every 1000
steps, one thread (``RAYON_NUM_THREADS=1``, XLA single-threaded). The peers: RK4 with
projection in numba (one trajectory at a time), and RK4 in JAX ``jit(vmap(lax.scan))``, plain and
with the same projection, compiled before the clock starts (``pip install 'poisson_rs[bench]'``;
a missing peer is skipped with a message, ``--no-jax`` skips JAX).

- ``--system rigid-body`` (default): I = (1.5, 2, 2.5), μ uniform in [−3, 3]³; errors max
  |C/C₀ − 1| (C = |μ|²) and max |H/H₀ − 1|; projection renormalises |μ|.
- ``--system heavy-top``: I = (1, 1.5, 2), mgl = 0.981, χ = e₃; M uniform in [−2, 2]³ and Γ a
  random unit vector; the Casimir error is the larger of max ||Γ|² − 1| and max |M·Γ −
  M₀·Γ₀| / (|M₀| |Γ₀|), the energy error max |H − H₀| / (½ M₀·I⁻¹M₀ + mgl |χ| |Γ₀|) (H₀ itself
  can be near 0); projection renormalises Γ to |Γ₀| and then moves M along Γ back to M₀·Γ₀.
- ``--system lotka-volterra``: the 3D system of ``scenes/lotka_volterra_3d.toml`` (c = [[0, 1,
  1], [−1, 0, 1], [−1, −1, 0]], b = (1, 2, 1), H = Σ x_i − b_i ln x_i), states within a log
  distance of 0.4 of x* = b; the Casimir error max |C − C₀| of C = ln x₁ − ln x₂ + ln x₃ (the log
  form, absolute), the energy error max |H/H₀ − 1|; the package's steppers are RK4 in x, the log
  splittings and Taylor-HJ on the exact groupoid; projection moves q = ln x back onto the plane
  k·q = C₀ along k = (1, −1, 1).

``--methods a,b`` runs only those of the package's methods (and no peer); ``--merge`` keeps the
points of an existing JSON at ``--out`` whose method was not run (the chart is redrawn from all).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("RAYON_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault(
    "XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
)

import numpy as np

import poisson_rs as pr
from poisson_rs.files import atomic_write_bytes, check_output_path

INERTIA = (1.5, 2.0, 2.5)
TOP_INERTIA, MGL, COM = (1.0, 1.5, 2.0), 0.981, (0.0, 0.0, 1.0)
#: (method, steps) swept; RK4 down to the step that keeps the Casimir to ~1e-12 at T = 1e5.
SWEEP: dict[str, list[float]] = {
    "rk4": [0.1, 0.025, 0.00625, 0.0015625],
    "splitting": [0.1, 0.05],
    "splitting4": [0.1],
    "splitting_casimir": [0.1, 0.05],
    "midpoint": [0.1, 0.05],
    "dmv": [0.1],
}
TOP_SWEEP: dict[str, list[float]] = {
    "rk4": [0.1, 0.025, 0.00625, 0.0015625, 0.00078125, 0.000390625],
    "splitting": [0.1, 0.05],
    "midpoint": [0.1, 0.05],
    "taylor3": [0.1, 0.05],
    "taylor5": [0.1, 0.2],
}
LV_C = ((0.0, 1.0, 1.0), (-1.0, 0.0, 1.0), (-1.0, -1.0, 0.0))
LV_B = (1.0, 2.0, 1.0)
LV_K = (1.0, -1.0, 1.0)
LV_SWEEP: dict[str, list[float]] = {
    "rk4": [0.1, 0.025, 0.00625, 0.0015625],
    "log_splitting": [0.1, 0.05],
    "log_splitting4": [0.1, 0.05, 0.025],
    "midpoint": [0.1],
    "taylor5": [0.1, 0.05],
    "taylor7": [0.1, 0.05],
}
#: Lotka–Volterra's projected RK4 needs h ≈ 0.0016 for the energy at T = 1e5.
LV_PROJECTED = [0.1, 0.025, 0.00625, 0.003125, 0.0015625]
#: Steps of RK4 with projection (the heavy top's energy needs the two smaller ones).
PROJECTED = [0.1, 0.05, 0.025, 0.0125]
TOP_PROJECTED = [*PROJECTED, 0.00625, 0.003125]


def top_invariants(traj: np.ndarray) -> tuple[float, float]:
    """Heavy top, (n, records, 6): the Casimir and energy errors of the module docstring."""
    m, g = traj[..., :3], traj[..., 3:]
    inv = 1.0 / np.array(TOP_INERTIA)
    arm = MGL * np.array(COM)
    gg = np.sum(g * g, axis=-1)
    mg = np.sum(m * g, axis=-1)
    scale_mg = np.linalg.norm(m[:, :1], axis=-1) * np.linalg.norm(g[:, :1], axis=-1)
    casimir = max(
        float(np.max(np.abs(gg / gg[:, :1] - 1))),
        float(np.max(np.abs(mg - mg[:, :1]) / scale_mg)),
    )
    kinetic = 0.5 * np.sum(m * m * inv, axis=-1)
    h = kinetic + np.sum(g * arm, axis=-1)
    scale_h = kinetic[:, :1] + np.linalg.norm(arm) * np.sqrt(gg[:, :1])
    return casimir, float(np.max(np.abs(h - h[:, :1]) / scale_h))


def projected_top_rk4() -> Any:
    """Heavy-top RK4 with Γ renormalised and M·Γ restored after every step, in numba."""
    try:
        import numba
    except ImportError:
        print("numba is not installed: projected RK4 skipped", file=sys.stderr)
        return None
    inv = 1.0 / np.array(TOP_INERTIA)
    arm = MGL * np.array(COM)

    @numba.njit(cache=False)
    def field(y: np.ndarray, out: np.ndarray) -> None:
        w0, w1, w2 = y[0] * inv[0], y[1] * inv[1], y[2] * inv[2]
        g0, g1, g2 = y[3], y[4], y[5]
        out[0] = y[1] * w2 - y[2] * w1 + g1 * arm[2] - g2 * arm[1]
        out[1] = y[2] * w0 - y[0] * w2 + g2 * arm[0] - g0 * arm[2]
        out[2] = y[0] * w1 - y[1] * w0 + g0 * arm[1] - g1 * arm[0]
        out[3] = g1 * w2 - g2 * w1
        out[4] = g2 * w0 - g0 * w2
        out[5] = g0 * w1 - g1 * w0

    @numba.njit(cache=False)
    def run(mu0: np.ndarray, h: float, n: int, every: int) -> np.ndarray:
        out = np.empty((mu0.shape[0], n // every + 1, 6))
        k1, k2, k3, k4, y = np.empty(6), np.empty(6), np.empty(6), np.empty(6), np.empty(6)
        for b in range(mu0.shape[0]):
            mu = mu0[b].copy()
            r0 = np.sqrt(mu[3] ** 2 + mu[4] ** 2 + mu[5] ** 2)
            c0 = mu[0] * mu[3] + mu[1] * mu[4] + mu[2] * mu[5]
            out[b, 0] = mu
            for k in range(n):
                field(mu, k1)
                for i in range(6):
                    y[i] = mu[i] + 0.5 * h * k1[i]
                field(y, k2)
                for i in range(6):
                    y[i] = mu[i] + 0.5 * h * k2[i]
                field(y, k3)
                for i in range(6):
                    y[i] = mu[i] + h * k3[i]
                field(y, k4)
                for i in range(6):
                    mu[i] += h / 6.0 * (k1[i] + 2.0 * (k2[i] + k3[i]) + k4[i])
                s = r0 / np.sqrt(mu[3] ** 2 + mu[4] ** 2 + mu[5] ** 2)
                for i in range(3, 6):
                    mu[i] *= s
                d = (c0 - (mu[0] * mu[3] + mu[1] * mu[4] + mu[2] * mu[5])) / (r0 * r0)
                for i in range(3):
                    mu[i] += d * mu[3 + i]
                if (k + 1) % every == 0:
                    out[b, (k + 1) // every] = mu
        return out

    return run


def invariants(traj: np.ndarray, inv: np.ndarray) -> tuple[float, float]:
    """Max |C/C₀ − 1| and |H/H₀ − 1| over (n, records, 3); NaN if a trajectory failed."""
    c = np.sum(traj**2, axis=-1)
    h = 0.5 * np.sum(traj**2 * inv, axis=-1)
    return float(np.max(np.abs(c / c[:, :1] - 1))), float(np.max(np.abs(h / h[:, :1] - 1)))


def lv_invariants(traj: np.ndarray) -> tuple[float, float]:
    """3D Lotka–Volterra, (n, records, 3): max |C − C₀| (log form) and max |H/H₀ − 1|."""
    q = np.log(traj)
    c = q @ np.array(LV_K)
    h = np.sum(traj - np.array(LV_B) * q, axis=-1)
    return float(np.max(np.abs(c - c[:, :1]))), float(np.max(np.abs(h / h[:, :1] - 1)))


def projected_lv_rk4() -> Any:
    """3D Lotka–Volterra: RK4 in x with q = ln x moved back onto k·q = C₀ after every step, in
    numba; None without numba."""
    try:
        import numba
    except ImportError:
        print("numba is not installed: projected RK4 skipped", file=sys.stderr)
        return None
    c = np.array(LV_C)
    b = np.array(LV_B)
    k = np.array(LV_K)

    @numba.njit(cache=False)
    def field(x: np.ndarray, out: np.ndarray) -> None:
        for i in range(3):
            acc = 0.0
            for j in range(3):
                acc += c[i, j] * (x[j] - b[j])
            out[i] = x[i] * acc

    @numba.njit(cache=False)
    def run(x0: np.ndarray, h: float, n: int, every: int) -> np.ndarray:
        out = np.empty((x0.shape[0], n // every + 1, 3))
        k1, k2, k3, k4, y = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3)
        for t in range(x0.shape[0]):
            x = x0[t].copy()
            c0 = 0.0
            for i in range(3):
                c0 += k[i] * np.log(x[i])
            out[t, 0] = x
            for s in range(n):
                field(x, k1)
                for i in range(3):
                    y[i] = x[i] + 0.5 * h * k1[i]
                field(y, k2)
                for i in range(3):
                    y[i] = x[i] + 0.5 * h * k2[i]
                field(y, k3)
                for i in range(3):
                    y[i] = x[i] + h * k3[i]
                field(y, k4)
                for i in range(3):
                    x[i] += h / 6.0 * (k1[i] + 2.0 * (k2[i] + k3[i]) + k4[i])
                d = 0.0
                for i in range(3):
                    d += k[i] * np.log(x[i])
                d = (d - c0) / 3.0  # |k|² = 3
                for i in range(3):
                    x[i] *= np.exp(-k[i] * d)
                if (s + 1) % every == 0:
                    out[t, (s + 1) // every] = x
        return out

    return run


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


def jax_rk4(system: str, project: bool) -> Any:
    """RK4 in JAX, ``jit(vmap)`` over the states with ``lax.scan`` over the steps (the 20 lines a
    user would write), plain or with the same projection as the numba runner after every step;
    ``run(mu0, h, n, every)`` returns (states, n // every + 1, dim) and excludes compilation
    (each (h, n, every) is compiled ahead of time before the clock starts). None without JAX."""
    try:
        import jax
        import jax.numpy as jnp
    except ImportError:
        print("jax is not installed: JAX RK4 skipped", file=sys.stderr)
        return None
    jax.config.update("jax_enable_x64", True)
    top, lv = system == "heavy-top", system == "lotka-volterra"
    inv = jnp.array([1.0 / v for v in (TOP_INERTIA if top else INERTIA)])
    arm = MGL * jnp.array(COM)
    lv_c, lv_b, lv_k = jnp.array(LV_C), jnp.array(LV_B), jnp.array(LV_K)

    def field(mu: Any) -> Any:
        if lv:
            return mu * (lv_c @ (mu - lv_b))
        if not top:
            return jnp.cross(mu, mu * inv)
        m, g = mu[:3], mu[3:]
        w = m * inv
        return jnp.concatenate([jnp.cross(m, w) + jnp.cross(g, arm), jnp.cross(g, w)])

    def projection(mu: Any, mu0: Any) -> Any:
        if lv:
            d = (jnp.dot(lv_k, jnp.log(mu)) - jnp.dot(lv_k, jnp.log(mu0))) / 3.0
            return mu * jnp.exp(-lv_k * d)
        if not top:
            return mu * (jnp.linalg.norm(mu0) / jnp.linalg.norm(mu))
        r0, c0 = jnp.linalg.norm(mu0[3:]), jnp.dot(mu0[:3], mu0[3:])
        g = mu[3:] * (r0 / jnp.linalg.norm(mu[3:]))
        m = mu[:3] + (c0 - jnp.dot(mu[:3], g)) / (r0 * r0) * g
        return jnp.concatenate([m, g])

    def trajectory(mu0: Any, h: float, n: int, every: int) -> Any:
        def step(mu: Any, _: Any) -> tuple[Any, None]:
            k1 = field(mu)
            k2 = field(mu + 0.5 * h * k1)
            k3 = field(mu + 0.5 * h * k2)
            k4 = field(mu + h * k3)
            mu = mu + h / 6.0 * (k1 + 2.0 * (k2 + k3) + k4)
            return (projection(mu, mu0) if project else mu), None

        def block(mu: Any, _: Any) -> tuple[Any, Any]:
            mu = jax.lax.scan(step, mu, None, length=every)[0]
            return mu, mu

        records = jax.lax.scan(block, mu0, None, length=n // every)[1]
        return jnp.concatenate([mu0[None], records])

    def run(mu0: np.ndarray, h: float, n: int, every: int) -> np.ndarray:
        fn = jax.jit(jax.vmap(lambda m: trajectory(m, h, n, every)))
        compiled = fn.lower(mu0).compile()
        start = time.perf_counter()
        out = np.asarray(compiled(mu0).block_until_ready())
        run.seconds = time.perf_counter() - start  # type: ignore[attr-defined]
        return out

    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--system", choices=("rigid-body", "heavy-top", "lotka-volterra"), default="rigid-body"
    )
    parser.add_argument("--horizon", type=float, default=1e5)
    parser.add_argument("--states", type=int, default=16)
    parser.add_argument("--every", type=int, default=1000)
    parser.add_argument("--out", type=Path, default=Path("docs/long_horizon"))
    parser.add_argument("--no-jax", action="store_true", help="skip the JAX RK4 rows")
    parser.add_argument(
        "--methods", help="comma-separated: only these of the package's methods, no peer"
    )
    parser.add_argument(
        "--merge", action="store_true", help="keep the other methods' points of --out's JSON"
    )
    args = parser.parse_args()
    json_path, png_path = args.out.with_suffix(".json"), args.out.with_suffix(".png")
    for p in (json_path, png_path):  # before minutes of work, not after
        check_output_path(p)
    kept: list[dict[str, Any]] = []
    if args.merge:
        try:
            kept = json.loads(json_path.read_text())["points"]
        except (OSError, ValueError, KeyError) as exc:
            parser.error(f"--merge: cannot read the points of {json_path}: {exc}")
    rng = np.random.default_rng(42)
    top = args.system == "heavy-top"
    lv = args.system == "lotka-volterra"
    steppers: dict[str, Any] = {}
    if lv:
        mu0 = np.exp(rng.uniform(-0.4, 0.4, (args.states, 3))) * np.array(LV_B)
        system = pr.lotka_volterra(LV_C, LV_B)
        run = None if args.methods else projected_lv_rk4()
        sweep, measure, projected = LV_SWEEP, lv_invariants, LV_PROJECTED
        for name in sweep:
            steppers[name] = (
                pr.log_canonical_taylor(system, int(name[6:]))
                if name.startswith("taylor")
                else pr.log_canonical_classical(system, name)
            )
    elif top:
        # Every state draws the same numbers whatever the sweep: --merge compares like with like.
        g = rng.normal(size=(args.states, 3))
        mu0 = np.concatenate(
            [rng.uniform(-2, 2, (args.states, 3)), g / np.linalg.norm(g, axis=1, keepdims=True)],
            axis=1,
        )
        body: pr.LiePoissonSystem = pr.HeavyTop(TOP_INERTIA, MGL, COM)
        sweep, run, measure = (
            TOP_SWEEP,
            None if args.methods else projected_top_rk4(),
            top_invariants,
        )
        projected = TOP_PROJECTED
    else:
        mu0 = rng.uniform(-3, 3, (args.states, 3))
        body = pr.RigidBody(INERTIA)
        inv = 1.0 / np.array(INERTIA)
        sweep, run, projected = SWEEP, None if args.methods else projected_rk4(), PROJECTED

        def measure(traj: np.ndarray) -> tuple[float, float]:
            return invariants(traj, inv)

    if not lv:
        steppers = {
            name: pr.taylor_integrator(body, int(name[6:]))
            if name.startswith("taylor")
            else pr.classical(body, name)
            for name in sweep
        }
    if args.methods:
        wanted = args.methods.split(",")
        unknown = sorted(set(wanted) - set(sweep))
        if unknown:
            parser.error(f"--methods: {unknown} not among {sorted(sweep)}")
        sweep = {m: sweep[m] for m in wanted}
        run = None
        args.no_jax = True

    points: list[dict[str, Any]] = []

    def record(method: str, h: float, seconds: float, traj: np.ndarray) -> None:
        dc, dh = measure(traj)
        points.append({"method": method, "h": h, "seconds": seconds, "casimir": dc, "energy": dh})
        print(f"{method:18s} h={h:<7g} {seconds:8.2f} s  dC {dc:.1e}  dH {dh:.1e}", flush=True)

    for method, steps in sweep.items():
        stepper = steppers[method]
        for h in steps:
            n = round(args.horizon / h)
            every = min(args.every, n)
            start = time.perf_counter()
            traj = pr.integrate(stepper, mu0, h, n - n % every, every=every)
            record(method, h, time.perf_counter() - start, traj)
    if run is not None:
        run(mu0[:1], 0.1, 10, 10)  # compile
        for h in projected:
            n = round(args.horizon / h)
            every = min(args.every, n)
            start = time.perf_counter()
            traj = run(mu0, h, n - n % every, every)
            record("rk4 + projection", h, time.perf_counter() - start, traj)
    for project, label in ((False, "rk4 (JAX)"), (True, "rk4 + projection (JAX)")):
        jrun = None if args.no_jax else jax_rk4(args.system, project)
        if jrun is None:
            continue
        for h in projected if project else sweep["rk4"]:
            n = round(args.horizon / h)
            every = min(args.every, n)
            traj = jrun(mu0, h, n - n % every, every)
            record(label, h, jrun.seconds, traj)
    ran = {p["method"] for p in points}
    points = [p for p in kept if p["method"] not in ran] + points
    meta = {
        "system": args.system,
        "horizon": args.horizon,
        "states": args.states,
        "system_data": {"c": LV_C, "b": LV_B}
        if lv
        else {"inertia": TOP_INERTIA if top else INERTIA},
    }
    atomic_write_bytes(json_path, json.dumps({**meta, "points": points}, indent=1).encode())
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    labels = (
        ("max Casimir error (|Γ|², M·Γ), relative", "max |ΔH| / H scale")
        if top
        else ("max |C − C₀|, C = ln(x₁x₃/x₂)", "max |H/H₀ − 1|")
        if lv
        else ("max |C/C₀ − 1|", "max |H/H₀ − 1|")
    )
    for key, ax, label in (("casimir", axes[0], labels[0]), ("energy", axes[1], labels[1])):
        for method in dict.fromkeys(p["method"] for p in points):
            pts = [p for p in points if p["method"] == method]
            x = [max(p[key], 1e-17) for p in pts]
            ax.loglog(x, [p["seconds"] for p in pts], "o-", label=method)
        ax.set_xlabel(label + f" at T = {args.horizon:g}")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel(f"seconds, {args.states} states, one thread")
    axes[1].legend(fontsize=8)
    name = "Heavy top" if top else "3D Lotka–Volterra" if lv else "Rigid body"
    fig.suptitle(f"{name}: cost against invariant errors (error < 1e-17 plotted at 1e-17)")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120)
    atomic_write_bytes(png_path, buf.getvalue())


if __name__ == "__main__":
    main()

"""RK4 rollouts of poisson_rs against the 20 lines a user would write in JAX and numba, in one
process, one thread: ``taskset -c 0 python benches/peers.py``.

Workloads (h = 0.1 unless said, final state only, so no contender pays for storing a trajectory):

- the rigid body, I = (1.5, 2, 2.5), batches 1, 64 and 4096;
- the heavy top, I = (1, 1.5, 2), mgl = 0.981, χ = e₃, batches 64 and 4096;
- PNN's Lotka–Volterra system (u̇ = u(v − 2), v̇ = v(1 − u), a log-canonical bracket), batches 64
  and 4096;
- two expression Hamiltonians (not polynomials), the shipped scenes' systems with H as text:
  PNN's extended pendulum (``scenes/extended_pendulum_pnn.toml``: H = ½u² − cos v + u(r − u² −
  v²) on the affine bracket {u, v} = −1, {u, r} = −2v, {v, r} = 2u) and three point vortices
  (``scenes/point_vortices.toml``: Γ = (1, 1, 0.5), H = −(1/4π) Σ_{i<j} Γ_iΓ_j log|z_i − z_j|²,
  {x_i, y_i} = 1/Γ_i, h = 0.05), batches 64 and 4096. The peers' fields are derived by hand and
  simplified as a user would (the pendulum's u̇ = −sin v, v̇ = u + r − u² − v², ṙ = 2(uu̇ + vv̇);
  the vortices' Biot–Savart sums pair by pair), which costs them fewer operations than π∇H;
- ``integrate()`` of one state for one step: the cost of one call, in µs.

Contenders: poisson_rs (its extension's rollout, called as ``pr.integrate`` calls it with
``every=n_steps``, from fresh copies of the file: ``--copies`` below), JAX ``jit(vmap(lax.scan))``
RK4 (float64) and numba ``@njit`` RK4 (a loop over trajectories and steps), and, with ``--baseline
PATH``, the ``_core`` extension of an earlier build loaded beside this one (e.g. the main
checkout's, to say what a change bought). Time the build a user runs: the wheel ``pip`` installs is
a cdylib-only build (``cargo rustc --crate-type cdylib``); ``benches/build_core.sh REV DIR`` builds
a revision that way, and its ``DIR/python/poisson_rs/_core.abi3.so`` is a ``--baseline`` (while the
profile had thin LTO, which ``cargo build`` skips beside the rlib, the wheel's code differed from
``cargo build``'s: the rigid body's RK4 once ran 3× slower in the wheel; docs/performance.md, "The
build the benches time"). Rounds alternate the contenders; each cell is the median of ``--rounds``
(≥ 5) timed runs after a warm-up (JAX compiles there). A missing peer is skipped with a message.
Every contender's final states are checked against ``pr.integrate``'s: numba gives the same bits on
the heavy top and agrees as JAX does on the rigid body (where the core takes the factored field
(1/I_k − 1/I_j) μ_j μ_k), JAX to 3e-10 or better (the same RK4, summed in a different order), except
on the heavy top's 10⁴ steps, where chaotic orbits amplify that order to O(1). On the expression
systems the peers' fields are other formulas (and the core has its own sin), so no bits are shared:
the vortices agree to 1e-12 or better, the pendulum to a few 1e-9 at worst, from the few states that
pass close to its separatrix's saddle (the median trajectory agrees to 1e-14 over 200 steps, 1e-12
over 10⁴).

Peers install with ``pip install 'poisson_rs[bench]'``, which pins jax[cpu] 0.10.2 and numba
0.68.1: the ratios compare across runs only with those versions (and on the same machine).
``--copies N`` (default 2) times this build and the baseline from N fresh copies each of their
extension file, loaded side by side, the copies alternating with the peers: the same extension ran
one kernel up to 1.3× apart from two files holding the same bytes (``benches/placements.py``). A
build's rate is the median over its copies of each copy's median, printed with the copies' range
(``rate_copies`` in the JSON); the one-call costs time the installed files.
``--systems`` runs only the named systems' workloads. Pin one thread: the script sets
``RAYON_NUM_THREADS=1``, XLA's and numba's thread counts to 1 before importing them; run it
under ``taskset -c 0`` as well. ``--json FILE`` writes the numbers.
"""

from __future__ import annotations

import argparse
import importlib.machinery
import importlib.util
import json
import math
import os
import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

os.environ.setdefault("RAYON_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault(
    "XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
)

import numpy as np

import poisson_rs as pr
from poisson_rs.files import atomic_write_bytes, check_output_path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from placements import fresh_copies, summary

H = 0.1
RIGID_I = (1.5, 2.0, 2.5)
TOP_I = (1.0, 1.5, 2.0)
MGL = 0.981
COM = (0.0, 0.0, 1.0)
#: PNN's Lotka–Volterra: ẋ_i = x_i Σ_j c_ij (x_j − b_j).
LV_C = ((0.0, 1.0), (-1.0, 0.0))
LV_B = (1.0, 2.0)
SCENES = Path(__file__).resolve().parent.parent / "scenes"
#: The expression systems: the shipped scenes' systems (H as text), at the scenes' steps.
EXPRESSION_SCENES = {
    "extended pendulum": "extended_pendulum_pnn.toml",
    "point vortices": "point_vortices.toml",
}
#: The circulations of scenes/point_vortices.toml: {x_i, y_i} = 1/Γ_i.
GAMMA = (1.0, 1.0, 0.5)
STEP = {"extended pendulum": 0.1, "point vortices": 0.05}
DIM = {
    "rigid body": 3,
    "heavy top": 6,
    "lotka-volterra": 2,
    "extended pendulum": 3,
    "point vortices": 2 * len(GAMMA),
}


def step_size(system: str) -> float:
    return STEP.get(system, H)


#: (system, batch, steps): about 1e6 trajectory-steps each (RK4 at 1e7–1e8 steps/s).
WORKLOADS = [
    ("rigid body", 1, 200_000),
    ("rigid body", 64, 10_000),
    ("rigid body", 4096, 200),
    ("heavy top", 64, 10_000),
    ("heavy top", 4096, 200),
    ("lotka-volterra", 64, 10_000),
    ("lotka-volterra", 4096, 200),
    ("extended pendulum", 64, 10_000),
    ("extended pendulum", 4096, 200),
    ("point vortices", 64, 10_000),
    ("point vortices", 4096, 200),
]

Runner = Callable[[np.ndarray, int], np.ndarray]


def states(system: str, batch: int) -> np.ndarray:
    """Seeded initial states: |μ| ≤ 3 for the rigid body; M in [−1, 1]³ and |Γ| = 1 for the
    top; within a log distance of 0.5 of the equilibrium (1, 2) for Lotka–Volterra; (u, v) in
    [−1, 1]², r in [0, 2] for the pendulum; the vortices within 0.2 of the scene's first state."""
    rng = np.random.default_rng(42)
    if system == "extended pendulum":
        return rng.uniform([-1.0, -1.0, 0.0], [1.0, 1.0, 2.0], (batch, 3))
    if system == "point vortices":
        first = np.array([1.0, 0.0, -0.5, 0.6, -0.3, -0.8])
        return first + rng.uniform(-0.2, 0.2, (batch, 6))
    if system == "rigid body":
        return rng.uniform(-3.0, 3.0, (batch, 3))
    if system == "lotka-volterra":
        return np.exp(rng.uniform(-0.5, 0.5, (batch, 2))) * np.array(LV_B)
    m = rng.uniform(-1.0, 1.0, (batch, 3))
    g = rng.normal(size=(batch, 3))
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    return np.concatenate([m, g], axis=1)


def poisson_rs_runner(system: str, core: ModuleType | None = None) -> Runner | None:
    """RK4 through ``pr.integrate`` (``core``: call that extension's rollout directly, for a
    baseline build; None where that build has no such rollout)."""
    h = step_size(system)
    if system in EXPRESSION_SCENES:
        from poisson_rs.protocols import NEWTON_MAX_ITER, NEWTON_TOL
        from poisson_rs.scenes import load_scene

        expr = load_scene(SCENES / EXPRESSION_SCENES[system]).system
        field = expr.classical("rk4")
        if core is None:
            return lambda x0, n: pr.integrate(field, x0, h, n, every=n)[:, -1]
        if not hasattr(core, "rollout_hamiltonian_field"):
            return None
        tables = (*expr.tape, *expr.terms.tables())
        # The fast path that build's integrate takes: H's distance terms where it reads them.
        extra = {} if expr.distances is None else {"distances": expr.distances.table()}
        return lambda x0, n: core.rollout_hamiltonian_field(
            "rk4", *tables, x0, h, n, n, NEWTON_TOL, NEWTON_MAX_ITER,
            program=expr.field_program, **extra,
        )[0][:, -1]  # fmt: skip
    if system == "lotka-volterra":
        lv = pr.lotka_volterra(LV_C, LV_B)
        if core is None:
            rk4 = pr.log_canonical_classical(lv, "rk4")
            return lambda x0, n: pr.integrate(rk4, x0, H, n, every=n)[:, -1]
        powers, coeffs, b = lv.log_hamiltonian.to_arrays()
        c = np.ascontiguousarray(LV_C)
        return lambda x0, n: core.rollout_log_classical("rk4", c, powers, coeffs, b, x0, H, n, n)[
            0
        ][:, -1]
    body: pr.LiePoissonSystem = (
        pr.RigidBody(RIGID_I) if system == "rigid body" else pr.HeavyTop(TOP_I, MGL, COM)
    )
    stepper = pr.classical(body, "rk4")
    if core is None:
        return lambda mu0, n: pr.integrate(stepper, mu0, H, n, every=n)[:, -1]
    if system == "rigid body":
        return lambda mu0, n: core.rollout_classical("rk4", RIGID_I, mu0, H, n, n)[0][:, -1]
    powers, coeffs = body.polynomial.to_arrays()
    c = np.ascontiguousarray(body.algebra.c)
    return lambda mu0, n: core.rollout_lie_poisson("rk4", c, powers, coeffs, mu0, H, n, n)[0][:, -1]


def vortex_field(z: Any, pi: float) -> list[Any]:
    """ẋ_i = −Σ_j Γ_j (y_i − y_j) / (2π d_ij²), ẏ_i = Σ_j Γ_j (x_i − x_j) / (2π d_ij²), pair by
    pair, for z = (x1, y1, x2, y2, …) (the field of the scene's H on {x_i, y_i} = 1/Γ_i)."""
    n = len(GAMMA)
    out: list[Any] = [0.0] * (2 * n)
    for i in range(n):
        for j in range(i + 1, n):
            ex, ey = z[2 * i] - z[2 * j], z[2 * i + 1] - z[2 * j + 1]
            w = 1.0 / (2.0 * pi * (ex * ex + ey * ey))
            out[2 * i] = out[2 * i] - GAMMA[j] * ey * w
            out[2 * i + 1] = out[2 * i + 1] + GAMMA[j] * ex * w
            out[2 * j] = out[2 * j] + GAMMA[i] * ey * w
            out[2 * j + 1] = out[2 * j + 1] - GAMMA[i] * ex * w
    return out


def jax_runner(system: str, dtype: str = "float64") -> Runner | None:
    """JAX ``jit(vmap(lax.scan))`` RK4 on JAX's default device, its constants in ``dtype``
    (pass states of that dtype)."""
    try:
        import jax
        import jax.numpy as jnp
    except ImportError:
        print("jax is not installed: skipped (pip install 'poisson_rs[bench]')", file=sys.stderr)
        return None
    jax.config.update("jax_enable_x64", True)
    inv = jnp.array([1.0 / v for v in (RIGID_I if system == "rigid body" else TOP_I)], dtype=dtype)
    arm = jnp.array([MGL * v for v in COM], dtype=dtype)

    lv_c, lv_b = jnp.array(LV_C, dtype=dtype), jnp.array(LV_B, dtype=dtype)
    h = step_size(system)

    def field(mu: Any) -> Any:
        if system == "extended pendulum":
            # π∇H of H = u²/2 − cos v + u(r − u² − v²), simplified by hand: u̇ = −sin v,
            # v̇ = u + r − u² − v², ṙ = 2(u u̇ + v v̇) (r − u² − v² is a Casimir).
            u, v, r = mu[0], mu[1], mu[2]
            du = -jnp.sin(v)
            dv = u + r - u * u - v * v
            return jnp.stack([du, dv, 2.0 * (u * du + v * dv)])
        if system == "point vortices":
            return jnp.stack(vortex_field(mu, jnp.pi))
        if system == "lotka-volterra":
            return mu * (lv_c @ (mu - lv_b))
        if system == "rigid body":
            return jnp.cross(mu, mu * inv)
        m, g = mu[:3], mu[3:]
        w = m * inv
        return jnp.concatenate([jnp.cross(m, w) + jnp.cross(g, arm), jnp.cross(g, w)])

    def step(mu: Any, _: Any) -> tuple[Any, None]:
        k1 = field(mu)
        k2 = field(mu + 0.5 * h * k1)
        k3 = field(mu + 0.5 * h * k2)
        k4 = field(mu + h * k3)
        return mu + h / 6.0 * (k1 + 2.0 * (k2 + k3) + k4), None

    compiled: dict[int, Any] = {}

    def run(mu0: np.ndarray, n: int) -> np.ndarray:
        if n not in compiled:
            one = lambda mu: jax.lax.scan(step, mu, None, length=n)[0]  # noqa: E731
            compiled[n] = jax.jit(jax.vmap(one))
        return np.asarray(compiled[n](mu0).block_until_ready())

    return run


def numba_runner(system: str) -> Runner | None:
    try:
        import numba
    except ImportError:
        print("numba is not installed: skipped (pip install 'poisson_rs[bench]')", file=sys.stderr)
        return None
    inv = np.array([1.0 / v for v in (RIGID_I if system == "rigid body" else TOP_I)])
    arm = MGL * np.array(COM)
    dim = DIM[system]
    h = step_size(system)
    lv = system == "lotka-volterra"
    pendulum, vortices = system == "extended pendulum", system == "point vortices"
    c01, c10, b0, b1 = LV_C[0][1], LV_C[1][0], LV_B[0], LV_B[1]
    gamma, n_vortices = np.array(GAMMA), len(GAMMA)

    @numba.njit(cache=False, fastmath=False)
    def field(mu: np.ndarray, out: np.ndarray) -> None:
        if pendulum:  # as in jax_runner: u̇ = −sin v, v̇ = u + r − u² − v², ṙ = 2(u u̇ + v v̇)
            u, v, r = mu[0], mu[1], mu[2]
            du = -math.sin(v)
            dv = u + r - u * u - v * v
            out[0], out[1], out[2] = du, dv, 2.0 * (u * du + v * dv)
            return
        if vortices:  # vortex_field's sums, pair by pair
            out[:] = 0.0
            for i in range(n_vortices):
                for j in range(i + 1, n_vortices):
                    ex, ey = mu[2 * i] - mu[2 * j], mu[2 * i + 1] - mu[2 * j + 1]
                    w = 1.0 / (2.0 * math.pi * (ex * ex + ey * ey))
                    out[2 * i] -= gamma[j] * ey * w
                    out[2 * i + 1] += gamma[j] * ex * w
                    out[2 * j] += gamma[i] * ey * w
                    out[2 * j + 1] -= gamma[i] * ex * w
            return
        if lv:
            out[0] = mu[0] * (c01 * (mu[1] - b1))
            out[1] = mu[1] * (c10 * (mu[0] - b0))
            return
        w0, w1, w2 = mu[0] * inv[0], mu[1] * inv[1], mu[2] * inv[2]
        out[0] = mu[1] * w2 - mu[2] * w1
        out[1] = mu[2] * w0 - mu[0] * w2
        out[2] = mu[0] * w1 - mu[1] * w0
        if dim == 6:
            g0, g1, g2 = mu[3], mu[4], mu[5]
            out[0] += g1 * arm[2] - g2 * arm[1]
            out[1] += g2 * arm[0] - g0 * arm[2]
            out[2] += g0 * arm[1] - g1 * arm[0]
            out[3] = g1 * w2 - g2 * w1
            out[4] = g2 * w0 - g0 * w2
            out[5] = g0 * w1 - g1 * w0

    @numba.njit(cache=False, fastmath=False)
    def run(mu0: np.ndarray, n: int) -> np.ndarray:
        out = mu0.copy()
        k1, k2, k3, k4, y = (
            np.empty(dim),
            np.empty(dim),
            np.empty(dim),
            np.empty(dim),
            np.empty(dim),
        )
        for b in range(out.shape[0]):
            mu = out[b]
            for _ in range(n):
                field(mu, k1)
                for i in range(dim):
                    y[i] = mu[i] + 0.5 * h * k1[i]
                field(y, k2)
                for i in range(dim):
                    y[i] = mu[i] + 0.5 * h * k2[i]
                field(y, k3)
                for i in range(dim):
                    y[i] = mu[i] + h * k3[i]
                field(y, k4)
                for i in range(dim):
                    mu[i] += h / 6.0 * (k1[i] + 2.0 * (k2[i] + k3[i]) + k4[i])
        return out

    return run  # type: ignore[no-any-return]


def load_core(path: Path, package: str = "baseline_core") -> ModuleType:
    """A ``_core`` extension file (an earlier build's, or a copy), loaded beside this one as
    ``<package>._core``."""
    name = f"{package}._core"
    loader = importlib.machinery.ExtensionFileLoader(name, str(path))
    spec = importlib.util.spec_from_file_location(name, path, loader=loader)
    if spec is None:
        raise SystemExit(f"cannot load {path}")
    module = importlib.util.module_from_spec(spec)
    loader.exec_module(module)
    return module


def timed(run: Runner, mu0: np.ndarray, n: int) -> tuple[float, np.ndarray]:
    start = time.perf_counter()
    out = run(mu0, n)
    return time.perf_counter() - start, out


def call_cost(fn: Callable[[], Any], rounds: int) -> float:
    """Median seconds of one call, over ``rounds`` batches of calls of about 50 ms."""
    fn()
    calls = 1
    while True:
        start = time.perf_counter()
        for _ in range(calls):
            fn()
        if time.perf_counter() - start > 0.05:
            break
        calls *= 2
    samples = []
    for _ in range(rounds):
        start = time.perf_counter()
        for _ in range(calls):
            fn()
        samples.append((time.perf_counter() - start) / calls)
    return statistics.median(samples)


def one_call_costs(rounds: int, baseline: ModuleType | None) -> dict[str, float]:
    """Seconds of one call of RK4 on one rigid-body state for one step, per contender."""
    rk4 = pr.classical(pr.RigidBody(RIGID_I), "rk4")
    one = np.array([1.0, 1.0, 2.0])
    calls: dict[str, float] = {
        "poisson_rs": call_cost(lambda: pr.integrate(rk4, [1.0, 1.0, 2.0], H, 1), rounds)
    }
    jax_run = jax_runner("rigid body")
    if jax_run is not None:
        calls["jax"] = call_cost(lambda: jax_run(one[None], 1), rounds)
    numba_run = numba_runner("rigid body")
    if numba_run is not None:
        calls["numba"] = call_cost(lambda: numba_run(one[None], 1), rounds)
    core = poisson_rs_runner("rigid body", pr._core)
    assert core is not None
    calls["poisson_rs (_core call only)"] = call_cost(lambda: core(one[None], 1), rounds)
    lazy = pr._core.rollout_classical
    calls["poisson_rs (_core call, lazy diagnostics)"] = call_cost(
        lambda: lazy("rk4", RIGID_I, one[None], H, 1, 1, lazy=True), rounds
    )
    if baseline is not None:
        b = poisson_rs_runner("rigid body", baseline)
        assert b is not None
        calls["baseline (_core call only)"] = call_cost(lambda: b(one[None], 1), rounds)
    return calls


def workload(
    system: str, batch: int, n: int, rounds: int, cores: dict[str, list[ModuleType]]
) -> dict[str, Any]:
    """One workload's rates (trajectory-steps/s) and agreement with ``pr.integrate``: each build
    from each of its copies (``cores``), JAX and numba, in alternating rounds."""
    mu0 = states(system, batch)
    runners: dict[str, Runner | None] = {"jax": jax_runner(system), "numba": numba_runner(system)}
    for key, copies in cores.items():
        for i, core in enumerate(copies):
            runners[f"{key}#{i}"] = poisson_rs_runner(system, core)
    live = {k: r for k, r in runners.items() if r is not None}
    reference = poisson_rs_runner(system)
    assert reference is not None
    ref = reference(mu0, n)
    agree: dict[str, float] = {}
    for name, run in live.items():  # warm-up (JIT compiles) and agreement
        key = name.split("#")[0]
        agree[key] = max(agree.get(key, 0.0), float(np.abs(run(mu0, n) - ref).max()))
    samples: dict[str, list[float]] = {k: [] for k in live}
    names = list(live)
    for r in range(rounds):
        for name in names if r % 2 == 0 else names[::-1]:
            samples[name].append(timed(live[name], mu0, n)[0])
    per_copy: dict[str, list[float]] = {}
    for name, v in samples.items():
        per_copy.setdefault(name.split("#")[0], []).append(batch * n / statistics.median(v))
    rate = {k: summary(v)[0] for k, v in per_copy.items()}
    order = ["poisson_rs", "jax", "numba", "baseline"]
    rate = {k: rate[k] for k in order if k in rate}

    def shown(k: str) -> str:
        v = per_copy[k]
        return f"{k} {rate[k]:.2e}" + (f" [{min(v):.2e}-{max(v):.2e}]" if len(v) > 1 else "")

    print(
        f"{system:17s} batch {batch:5d}: "
        + ", ".join(shown(k) for k in rate)
        + " trajectory-steps/s; max |diff| "
        + ", ".join(f"{k} {v:.1e}" for k, v in agree.items() if k != "poisson_rs"),
        flush=True,
    )
    return {
        "system": system,
        "batch": batch,
        "steps": n,
        "h": step_size(system),
        "rate": rate,
        "rate_copies": {k: v for k, v in per_copy.items() if k in cores},
        "agree": agree,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=7, help="timed rounds per cell (>= 5)")
    parser.add_argument("--baseline", type=Path, help="an earlier build's _core extension")
    parser.add_argument("--json", type=Path, help="write the numbers here")
    parser.add_argument(
        "--copies",
        type=int,
        default=2,
        help="time each build from this many fresh copies of its extension (placements; >= 1)",
    )
    parser.add_argument(
        "--systems",
        nargs="+",
        choices=sorted(DIM),
        help="run only these systems' workloads (and skip the one-call costs)",
    )
    args = parser.parse_args()
    if args.json:  # before minutes of work, not after
        check_output_path(args.json)
    if args.copies < 1:
        raise SystemExit("--copies must be at least 1")
    if args.baseline is not None and not args.baseline.is_file():
        raise SystemExit(f"--baseline: {args.baseline} is not a file")
    rounds = max(5, args.rounds)
    baseline = load_core(args.baseline) if args.baseline else None
    sources = {"poisson_rs": Path(pr._core.__file__)}
    if args.baseline is not None:
        sources["baseline"] = args.baseline
    with tempfile.TemporaryDirectory(prefix="peers_") as tmp:
        cores = {
            key: [
                load_core(copy, f"placement_{key}_{i}")
                for i, copy in enumerate(fresh_copies(source, args.copies, Path(tmp) / key))
            ]
            for key, source in sources.items()
        }
        rows = [
            workload(system, batch, n, rounds, cores)
            for system, batch, n in WORKLOADS
            if not args.systems or system in args.systems
        ]
    calls = {} if args.systems else one_call_costs(rounds, baseline)
    if calls:
        print(
            "one call, one state, one step: "
            + ", ".join(f"{k} {v * 1e6:.2f} us" for k, v in calls.items())
        )
    load = os.getloadavg()
    machine = f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores"
    print(f"machine: {machine}; load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    if args.json:
        data = {
            "workloads": rows,
            "call_seconds": calls,
            "copies": args.copies,
            "load": load,
            "machine": machine,
        }
        atomic_write_bytes(args.json, json.dumps(data, indent=1).encode())


if __name__ == "__main__":
    main()

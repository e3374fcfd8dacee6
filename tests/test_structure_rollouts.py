"""Rollouts on every Poisson structure beyond g* keep the guarantees the Lie–Poisson ones have:
each trajectory's bits do not depend on its batch, its position in it, the record stride, the
thread count or a fork, a Dask cluster gives the same bits, and Ctrl-C stops a long rollout.

The steppers cover each structure and each kind of step the core runs on it: Taylor-HJ, the
learned S and the classical methods on the exact log-canonical groupoid, Taylor-HJ on the
order-n realization of a cubic Nambu bracket, and Taylor-HJ on an affine bracket's central
extension.
"""

from __future__ import annotations

import functools
import os
import signal
import subprocess
import sys
import textwrap
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from conftest import interrupt_long_rollout

import poisson_rs as pr

PNN = pr.lotka_volterra([[0.0, 1.0], [-1.0, 0.0]], [1.0, 2.0])
#: 3D Lotka–Volterra with the Casimir x1 x3 / x2.
LV3 = pr.lotka_volterra([[0.0, 1.0, 1.0], [-1.0, 0.0, 1.0], [-1.0, -1.0, 0.0]], [1.0, 2.0, 1.0])


@functools.cache
def _cubic() -> pr.PolynomialPoissonSystem:
    """The cubic Nambu system, built (by sympy) once, when a test first needs it."""
    return pr.PolynomialPoissonSystem(
        pr.PolynomialBivector.nambu("x1**2/2 + x2**2/2 + x3**2/2 + x1**3/3"), "x1**2/2 + x2**2/3"
    )


def _pendulum() -> pr.AffinePoissonSystem:
    c = np.zeros((3, 3, 3))
    c[0, 2, 1], c[2, 0, 1] = 2.0, -2.0
    c[1, 2, 0], c[2, 1, 0] = -2.0, 2.0
    h = {(2, 0, 0): 0.5, (0, 2, 0): 0.5, (0, 4, 0): -1.0 / 24.0}
    return pr.affine_poisson_system(c, [[0, -1, 0], [1, 0, 0], [0, 0, 0]], h)


def _states(name: str, n: int, seed: int) -> np.ndarray:
    """Seeded states on bounded orbits: within a log distance of 0.4 of the equilibrium x* = b
    for Lotka–Volterra (inside the learned model's box), a small ball for the Nambu and affine
    brackets."""
    rng = np.random.default_rng(seed)
    if name.startswith("pnn"):
        return np.exp(rng.uniform(-0.4, 0.4, (n, 2))) * [1.0, 2.0]
    if name.startswith("lv3"):
        return np.exp(rng.uniform(-0.4, 0.4, (n, 3))) * [1.0, 2.0, 1.0]
    return rng.uniform(-0.5, 0.5, (n, 3))


#: name → (stepper factory, h). Factories, so that nothing is built at collection time.
STEPPERS: dict[str, tuple[Callable[[], Any], float]] = {
    "pnn-taylor5": (lambda: pr.log_canonical_taylor(PNN, 5), 0.1),
    "pnn-learned": (lambda: pr.load_model("lotka_volterra_h01"), 0.1),
    "pnn-log_splitting4": (lambda: pr.log_canonical_classical(PNN, "log_splitting4"), 0.1),
    "lv3-taylor3": (lambda: pr.log_canonical_taylor(LV3, 3), 0.1),
    "lv3-rk4": (lambda: pr.log_canonical_classical(LV3, "rk4"), 0.1),
    "lv3-midpoint": (lambda: pr.log_canonical_classical(LV3, "midpoint"), 0.1),
    "nambu-taylor3": (lambda: pr.RealizationTaylorIntegrator(_cubic(), 3), 0.1),
    "affine-taylor3": (lambda: pr.affine_taylor(_pendulum(), 3), 0.1),
}


@pytest.fixture(scope="module", params=sorted(STEPPERS))
def case(request: pytest.FixtureRequest) -> tuple[str, Any, float]:
    factory, h = STEPPERS[request.param]
    return request.param, factory(), h


def _bits(traj: np.ndarray, info: pr.RolloutInfo) -> tuple[bytes, ...]:
    return (traj.tobytes(), info.converged.tobytes(), info.failure_code.tobytes())


def test_each_trajectory_has_its_own_bits(case: tuple[str, Any, float]) -> None:
    """A state rolled out alone, in a batch, or in the reversed batch gets the same bits; a
    record stride keeps every k-th state of the full rollout exactly."""
    name, stepper, h = case
    x0 = _states(name, 21, seed=61)
    traj, info = pr.integrate(stepper, x0, h, 60, return_info=True)
    assert np.isfinite(traj).all() and info.converged.all(), name
    back = pr.integrate(stepper, x0[::-1], h, 60)
    assert back[::-1].tobytes() == traj.tobytes()
    for i in (0, 7, 20):
        alone, alone_info = pr.integrate(stepper, x0[i], h, 60, return_info=True)
        assert alone.tobytes() == traj[i].tobytes(), (name, i)
        assert bool(alone_info.converged) == bool(info.converged[i])
    strided = pr.integrate(stepper, x0, h, 60, every=4)
    assert strided.tobytes() == np.ascontiguousarray(traj[:, ::4]).tobytes()


def test_threads_give_the_sequential_results() -> None:
    """The same steppers from four Python threads at once give the sequential bits."""
    from concurrent.futures import ThreadPoolExecutor

    jobs = [(STEPPERS[n][0](), _states(n, 24, seed=62), STEPPERS[n][1]) for n in sorted(STEPPERS)]

    def run(job: tuple[Any, np.ndarray, float]) -> tuple[bytes, ...]:
        stepper, x0, h = job
        return _bits(*pr.integrate(stepper, x0, h, 200, every=5, return_info=True))

    sequential = [run(job) for job in jobs]
    with ThreadPoolExecutor(max_workers=4) as pool:
        concurrent = list(pool.map(run, jobs * 2))
    assert concurrent == sequential * 2


# One digest of every stepper's rollout (trajectory, convergence, failure codes), printed by a
# fresh interpreter: the same for any rayon thread count.
_DIGEST = """
import hashlib
import sys
sys.path.insert(0, {tests!r})
import numpy as np
import poisson_rs as pr
from test_structure_rollouts import STEPPERS, _bits, _states
h = hashlib.sha256()
for name in sorted(STEPPERS):
    factory, step = STEPPERS[name]
    traj, info = pr.integrate(factory(), _states(name, 40, seed=63), step, 300, every=7,
                              return_info=True)
    for b in _bits(traj, info):
        h.update(b)
print(h.hexdigest())
"""


def _run_python(code: str, env: dict[str, str] | None = None) -> str:
    proc = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, **(env or {})},
    )
    assert proc.returncode == 0, f"exit {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    return proc.stdout


def test_results_do_not_depend_on_the_thread_count() -> None:
    code = _DIGEST.format(tests=os.path.dirname(__file__))
    one = _run_python(code, env={"RAYON_NUM_THREADS": "1"}).strip()
    two = _run_python(code, env={"RAYON_NUM_THREADS": "2"}).strip()
    assert len(one) == 64 and one == two


def _child_rollouts(x0: dict[str, np.ndarray]) -> list[bytes]:
    from poisson_rs import _core

    assert _core.serial_rollouts()
    return [
        pr.integrate(STEPPERS[n][0](), x0[n], STEPPERS[n][1], 100).tobytes() for n in sorted(x0)
    ]


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork()")
def test_forked_child_rolls_out_the_same_bits() -> None:
    """After rollouts in the parent (rayon's pool started), a forked child's rollouts of every
    structure neither hang nor differ."""
    import multiprocessing as mp

    names = ["pnn-taylor5", "pnn-learned", "lv3-rk4", "nambu-taylor3", "affine-taylor3"]
    x0 = {n: _states(n, 32, seed=64) for n in names}
    parent = [pr.integrate(STEPPERS[n][0](), x0[n], STEPPERS[n][1], 100).tobytes() for n in names]
    with mp.get_context("fork").Pool(1) as pool:
        child = pool.apply_async(_child_rollouts, (x0,)).get(timeout=120)
    assert child == [parent[names.index(n)] for n in sorted(names)]


# A rollout of 10⁹ steps that keeps 1001 states; "ready" is printed just before it starts.
_LONG_ROLLOUT = """
import signal
import sys
# A background job of a non-interactive shell inherits SIGINT ignored: restore the handler.
signal.signal(signal.SIGINT, signal.default_int_handler)
sys.path.insert(0, {tests!r})
import numpy as np
import poisson_rs as pr
from test_structure_rollouts import STEPPERS, _states
factory, h = STEPPERS[sys.argv[1]]
stepper, x0 = factory(), _states(sys.argv[1], int(sys.argv[2]), seed=65)
print("ready", flush=True)
pr.integrate(stepper, x0, h, 10**9, every=10**6)
print("finished", flush=True)
"""


@pytest.mark.parametrize(
    ("name", "copies"),
    [("pnn-taylor5", 1), ("pnn-learned", 64), ("lv3-rk4", 8), ("nambu-taylor3", 4)],
)
def test_ctrl_c_interrupts_a_long_rollout(name: str, copies: int) -> None:
    code = textwrap.dedent(_LONG_ROLLOUT.format(tests=os.path.dirname(__file__)))
    # The rollout (10⁹ steps) cannot finish; the helper's wait for the exit is the guard.
    out, err, returncode, _ = interrupt_long_rollout(code, name, str(copies))
    assert "finished" not in out
    assert "KeyboardInterrupt" in err, err
    assert returncode == -signal.SIGINT, (returncode, err)

"""The splittings, discrete Moser–Veselov and the heavy top's splitting run in SIMD lanes:
every trajectory's result is its own, whatever shares its block, chunk or thread.

The oracle is the same integrator on each state alone (a block of one lane, the scalar
arithmetic): the batch must reproduce it bit for bit, Newton counts and residuals included,
and the bytes must not depend on the number of threads.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from conftest import PAPER_INERTIA

import poisson_rs as pr

BODY = pr.RigidBody(PAPER_INERTIA)
RIGID_METHODS = ["splitting", "splitting4", "splitting_casimir", "dmv"]


def _cases() -> list[tuple[str, pr.ClassicalIntegrator]]:
    cases = [(m, pr.classical(BODY, m)) for m in RIGID_METHODS]
    cases.append(("top-splitting", pr.classical(pr.HeavyTop(), "splitting")))
    return cases


def _states(n: int, dim: int, seed: int) -> np.ndarray:
    """Seeded states with norms spread over a decade, so the lanes' angles and Newton counts
    differ."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, dim))
    return d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.3, 3.0, (n, 1))


@pytest.mark.parametrize(("name", "stepper"), _cases(), ids=[c[0] for c in _cases()])
def test_a_batch_equals_each_state_alone(name: str, stepper: pr.ClassicalIntegrator) -> None:
    mu0 = _states(21, stepper.body.dim, seed=len(name))  # 21: blocks of 8, 8 and a padded 5
    batch, info = pr.integrate(stepper, mu0, 0.05, 40, every=4, return_info=True)
    assert info.converged.all()
    for i in range(len(mu0)):
        alone, one = pr.integrate(stepper, mu0[i], 0.05, 40, every=4, return_info=True)
        assert np.array_equal(batch[i], alone), f"{name}: trajectory {i}"
        assert info.newton_iterations[i] == one.newton_iterations[0]
        assert info.max_residual[i] == one.max_residual[0]


_DIGEST = """
import hashlib
import numpy as np
import poisson_rs as pr
rng = np.random.default_rng(17)
h = hashlib.sha256()
body = pr.RigidBody((1.5, 2.0, 2.5))
steppers = [pr.classical(body, m) for m in ("splitting", "splitting4", "splitting_casimir", "dmv")]
steppers.append(pr.classical(pr.HeavyTop(), "splitting"))
for stepper in steppers:
    # 300 states: several chunks of 64, so two threads share the work.
    mu = rng.uniform(-2.0, 2.0, size=(300, stepper.body.dim))
    traj, info = pr.integrate(stepper, mu, 0.05, 200, every=10, return_info=True)
    h.update(traj.tobytes())
    h.update(info.max_residual.tobytes())
    h.update(info.newton_iterations.tobytes())
print(h.hexdigest())
"""


def _digest(threads: int) -> str:
    proc = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(_DIGEST)],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "RAYON_NUM_THREADS": str(threads)},
    )
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.strip()


def test_results_do_not_depend_on_the_thread_count() -> None:
    one, two = _digest(1), _digest(2)
    assert len(one) == 64 and one == two


def test_a_failing_dmv_lane_fails_alone() -> None:
    dmv = pr.classical(BODY, "dmv")
    mu0 = _states(11, 3, seed=5)
    clean = pr.integrate(dmv, mu0, 0.1, 10)
    bad = mu0.copy()
    bad[4] = [1e300, -1e300, 1e300]  # |y|² overflows in the Newton solve
    with pytest.warns(RuntimeWarning, match="quarter turn"):  # the step check says so too
        out, info = pr.integrate(dmv, bad, 0.1, 10, return_info=True, on_failure="ignore")
    assert not info.converged[4] and info.failed_step[4] == 0
    assert np.isnan(out[4, 1:]).all()
    others = np.arange(11) != 4
    assert info.converged[others].all()
    assert np.array_equal(out[others], clean[others])

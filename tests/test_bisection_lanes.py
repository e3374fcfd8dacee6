"""Bisection steps solved in blocks (polynomial jets and tanh rows in SIMD lanes, Newton in
lockstep): every trajectory's result is its own, whatever else shares its block.

The oracle is the same integrator run on each state alone (a block of one lane): the lanes never
mix trajectories, so the batch must reproduce it bit for bit, for batch sizes that are not
multiples of the lane count, and a trajectory whose Newton solve fails must not touch the others.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import PAPER_INERTIA

import poisson_rs as pr

BODY = pr.RigidBody(PAPER_INERTIA)


def _steppers() -> dict[str, pr.BisectionIntegrator]:
    return {
        "taylor5-exp": pr.taylor_integrator(BODY, order=5, chart="exp"),
        "taylor3-cayley": pr.taylor_integrator(BODY, order=3, chart="cayley"),
        "default": pr.load_model("default"),
    }


def _states(n: int, seed: int) -> np.ndarray:
    """Seeded states on spheres of radius 1 to 3 (inside the default model's shell)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(1.0, 3.0, (n, 1))


@pytest.mark.parametrize("name", ["taylor5-exp", "taylor3-cayley", "default"])
@pytest.mark.parametrize("n", [5, 37])
def test_a_batch_equals_each_state_alone(name: str, n: int):
    stepper = _steppers()[name]
    assert stepper.batch > 1  # these solve in blocks
    mu0 = _states(n, seed=n)
    batch, info = pr.integrate(stepper, mu0, 0.1, 20, return_info=True)
    assert info.converged.all()
    for i in range(n):
        alone, one = pr.integrate(stepper, mu0[i : i + 1], 0.1, 20, return_info=True)
        assert np.array_equal(batch[i], alone[0]), f"{name}: trajectory {i}"
        assert info.newton_iterations[i] == one.newton_iterations[0]
        assert info.max_residual[i] == one.max_residual[0]


def test_a_failing_trajectory_leaves_its_block_alone():
    stepper = _steppers()["taylor5-exp"]
    mu0 = _states(11, seed=3)
    clean = pr.integrate(stepper, mu0, 0.1, 10)
    bad = mu0.copy()
    bad[4] = [400.0, -300.0, 250.0]  # |x| = |h ∇S| far beyond the exp chart's 2π
    with pytest.warns(RuntimeWarning, match="quarter turn"):  # the step check says so too
        out, info = pr.integrate(stepper, bad, 0.1, 10, return_info=True, on_failure="ignore")
    assert not info.converged[4] and info.failed_step[4] == 0
    assert info.failure_code[4] == 4  # chart singular, as the scalar step says
    assert np.isnan(out[4, 1:]).all()
    others = np.arange(11) != 4
    assert info.converged[others].all()
    assert np.array_equal(out[others], clean[others])


@pytest.mark.parametrize("chart", ["exp", "cayley"])
def test_lane_solver_agrees_with_full_newton_and_predicts(chart: str):
    """The so(3) lane solver (simplified Newton from the explicit predictor) against the generic
    full-Newton path (dual-number Jacobian, started from μ): both solve the same equation to
    the tolerance, so the states agree to ~1e-12 after 50 steps, and the Casimir is kept to
    round-off. The predictor starts Newton O(h²) from the solution (in the Cayley chart with the
    chart's quadratic term), so either chart needs about 3 updates a step where simplified Newton
    from μ needs 3.9 (a count, not a timing)."""
    lanes = pr.taylor_integrator(BODY, order=5, chart=chart)
    full = pr.TaylorIntegrator(lanes._bytes, tol=lanes.tol, max_iter=lanes.max_iter, newton="full")
    mu0 = _states(37, seed=17)
    a, ia = pr.integrate(lanes, mu0, 0.1, 50, return_info=True)
    b, ib = pr.integrate(full, mu0, 0.1, 50, return_info=True)
    assert ia.converged.all() and ib.converged.all()
    r = np.linalg.norm(mu0, axis=1)
    assert np.abs(a - b).max(axis=(1, 2)).max() <= 1e-12 * r.max()
    casimir = np.abs(np.linalg.norm(a, axis=2) - r[:, None]).max()
    assert casimir <= 1e-14 * r.max()
    per_step = ia.newton_iterations.sum() / (37 * 50)
    # benches/newton_predictors.py: 3.00 in both charts on its states (Cayley 3.66 before).
    assert per_step < 3.1, per_step

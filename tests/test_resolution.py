"""Silent wrong answers at extreme scales, now caught: steps too large to resolve the motion warn,
the nearly symmetric body gets a splitting that resolves it, and homogeneous models step tiny
states. Oracles: the exact rigid-body flow and the Casimir."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import poisson_rs as pr

PAPER_STATES = np.array([[1.0, 1.0, 2.0], [3.0, 2.0, 0.0]])


def test_the_paper_scenes_do_not_warn() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        pr.integrate(pr.load_model(), PAPER_STATES, 0.1, 5)
        pr.integrate(pr.load_model("large_step_h05"), PAPER_STATES, 0.5, 5)
        pr.integrate(pr.taylor_integrator(pr.RigidBody(), 7, "exp"), PAPER_STATES, 0.5, 5)


def test_a_taylor_step_beyond_its_range_warns_and_is_wrong() -> None:
    """|μ| ≈ 100 at h = 0.1: a step turns the body by 5.3 rad. The result is O(1) wrong although
    every step converged, which is what the warning is for."""
    body = pr.RigidBody()
    mu0 = np.array([60.0, 50.0, 60.0])
    with pytest.warns(RuntimeWarning, match=r"turns state 0 by 5\.29 rad.*use h <= 0\.0297"):
        traj, info = pr.integrate(pr.taylor_integrator(body, 5), mu0, 0.1, 20, return_info=True)
    exact = pr.exact_solution(body, mu0, 0.1 * np.arange(21))
    assert info.converged.all()
    assert np.abs(traj - exact).max() / np.linalg.norm(mu0) > 1.0
    # Below the suggested step it is resolved and silent.
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        traj = pr.integrate(pr.taylor_integrator(body, 5), mu0, 0.005, 400)
    exact = pr.exact_solution(body, mu0, 0.005 * np.arange(401))
    assert np.abs(traj - exact).max() / np.linalg.norm(mu0) < 1e-2


def test_splitting_on_an_extreme_body_warns() -> None:
    body = pr.RigidBody((1e-8, 1.0, 1e8))
    with pytest.warns(RuntimeWarning, match="more than a quarter turn"):
        pr.integrate(pr.classical(body, "splitting"), [1.0, 1.0, 1.0], 0.1, 3)


def test_the_heavy_top_is_checked_too() -> None:
    with pytest.warns(RuntimeWarning, match="quarter turn"):
        pr.integrate(pr.classical(pr.HeavyTop(), "rk4"), [50.0, 0, 0, 0, 0, 1.0], 0.1, 2)


def test_casimir_splitting_resolves_the_nearly_symmetric_body() -> None:
    body = pr.RigidBody((1.0, 1.0, 1.001))
    mu0 = np.array([[1.0, 2.0, 3.0], [3.0, 2.0, 0.0]])
    times = 0.1 * np.arange(1001)
    exact = pr.exact_solution(body, mu0, times)
    plain = pr.integrate(pr.classical(body, "splitting"), mu0, 0.1, 1000)
    fasso = pr.integrate(pr.classical(body, "splitting_casimir"), mu0, 0.1, 1000)
    assert np.abs(plain - exact).max() > 1e-2
    assert np.abs(fasso - exact).max() < 1e-10
    c = np.sum(fasso**2, axis=-1)
    assert np.abs(c - c[:, :1]).max() < 1e-12


def test_casimir_splitting_is_second_order_on_the_paper_body() -> None:
    body = pr.RigidBody()
    stepper = pr.classical(body, "splitting_casimir")
    assert stepper.order == 2 and stepper.poisson
    end = pr.exact_solution(body, PAPER_STATES, np.array([0.0, 1.0]))[:, -1]
    errs = [
        np.abs(pr.integrate(stepper, PAPER_STATES, 1.0 / n, n)[:, -1] - end).max() for n in (20, 40)
    ]
    assert np.log2(errs[0] / errs[1]) == pytest.approx(2.0, abs=0.1)


@pytest.mark.parametrize("scale", [1e-30, 1e-60, 1e-120, 1e-200])
def test_homogeneous_models_step_tiny_states(scale: float) -> None:
    """The default model's MLP term is |p|^6 · N: negligible at tiny |μ|, where 1/|p| and its
    derivatives overflowed (failure code 3). It steps them now, keeping the Casimir."""
    model = pr.load_model()
    assert model.generating.inputs == "homogeneous"
    mu0 = scale * np.array([1.0, 1.0, 2.0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # outside the training shell, on purpose
        traj, info = pr.integrate(model, mu0, 0.1, 10, return_info=True, on_failure="ignore")
    assert info.converged.all(), info.failure_code
    c = np.sum((traj / scale) ** 2, axis=-1)  # scaled: |μ|² itself underflows at 1e-200
    assert np.abs(c / c[0] - 1).max() < 1e-12

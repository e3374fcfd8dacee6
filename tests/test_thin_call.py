"""The thin path of integrate() (plain arguments, no info asked for, diagnostics summarised in
the core): the same trajectories, checks, warnings and errors as the full path."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import poisson_rs as pr
from poisson_rs import _core
from poisson_rs.integrators import _summary

BODY = pr.RigidBody((1.5, 2.0, 2.5))
TOP = pr.HeavyTop()


@pytest.mark.parametrize("name", ["rk4", "midpoint", "splitting", "dmv"])
def test_thin_path_equals_the_full_path(name: str):
    stepper = pr.classical(BODY, name)
    rng = np.random.default_rng(17)
    mu0 = rng.normal(size=(11, 3))
    thin = pr.integrate(stepper, mu0, 0.1, 8)
    full, info = pr.integrate(stepper, mu0, 0.1, 8, return_info=True)
    np.testing.assert_array_equal(thin, full)
    assert info.converged.all()
    # every dividing n_steps takes the thin path too: every 4th state of the same rollout.
    np.testing.assert_array_equal(pr.integrate(stepper, mu0, 0.1, 8, every=4), full[:, ::4])
    # One state as a list of ints, as floats, as a 1-D array: the same numbers.
    one = pr.integrate(stepper, [1, 1, 2], 0.1, 3)
    np.testing.assert_array_equal(one, pr.integrate(stepper, [1.0, 1.0, 2.0], 0.1, 3))
    np.testing.assert_array_equal(one, pr.integrate(stepper, np.array([1.0, 1, 2]), 0.1, 3))
    assert one.shape == (4, 3)


def test_thin_path_heavy_top_equals_full_path():
    stepper = pr.classical(TOP, "rk4")
    mu0 = np.random.default_rng(5).normal(size=(9, 6))
    full, _ = pr.integrate(stepper, mu0, 0.05, 5, return_info=True)
    np.testing.assert_array_equal(pr.integrate(stepper, mu0, 0.05, 5), full)


@pytest.mark.parametrize("bad", [[1.0, float("nan"), 2.0], [[1.0, 1.0, 2.0], [np.inf, 0, 0]]])
def test_thin_path_refuses_non_finite_states(bad):
    stepper = pr.classical(BODY, "rk4")
    with pytest.raises(ValueError, match="NaN or infinite"):
        pr.integrate(stepper, bad, 0.1, 1)
    with pytest.raises(ValueError, match="NaN or infinite"):
        pr.integrate(stepper, bad, 0.1, 1, return_info=True)


def test_thin_path_keeps_type_and_shape_errors():
    stepper = pr.classical(BODY, "rk4")
    with pytest.raises(TypeError, match="mu0 must be an array of real numbers"):
        pr.integrate(stepper, [True, False, True], 0.1, 1)
    with pytest.raises(TypeError, match="mu0 must be an array of real numbers"):
        pr.integrate(stepper, ["1", "2", "3"], 0.1, 1)
    with pytest.raises(ValueError, match=r"mu0 must have shape \(3,\) or \(n, 3\)"):
        pr.integrate(stepper, [1.0, 2.0], 0.1, 1)
    with pytest.raises(ValueError, match="on_failure"):
        pr.integrate(stepper, [1.0, 1.0, 2.0], 0.1, 1, on_failure="loud")  # type: ignore[arg-type]


def test_thin_path_reports_failures_and_unresolved_steps():
    stepper = pr.classical(BODY, "rk4")
    mu0 = [[1.0, 1.0, 2.0], [1e200, 1e200, 1e200]]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        traj = pr.integrate(stepper, mu0, 0.1, 3)
    messages = [str(w.message) for w in caught]
    assert any("turns state 1" in m for m in messages), messages
    assert any("1 of 2 trajectories failed (first: trajectory 1 at step 0" in m for m in messages)
    # The warnings name the caller's line, as on the full path.
    assert all(w.filename == __file__ for w in caught)
    assert np.isfinite(traj[0]).all() and np.isnan(traj[1, 1:]).all()
    with pytest.raises(RuntimeError, match="trajectories failed"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pr.integrate(stepper, mu0, 0.1, 3, on_failure="raise")


def test_core_summary_matches_the_arrays():
    """The core's summary (what integrate() warns from) against the same numbers computed in
    NumPy from the diagnostic arrays, with failures and a NaN-free batch."""
    rng = np.random.default_rng(3)
    mu0 = rng.normal(size=(20, 3)) * rng.choice([1.0, 1e200], size=(20, 1), p=[0.7, 0.3])
    _, lazy = _core.rollout_classical("rk4", BODY.inertia, mu0, 0.1, 4, lazy=True)
    arrays = lazy.arrays()
    assert len(lazy) == 20
    expect = _summary(arrays)
    got = lazy.summary()
    assert got[:4] == expect[:4] and got[5] == expect[5]
    assert got[4] == expect[4]
    _, eager = _core.rollout_classical("rk4", BODY.inertia, mu0, 0.1, 4)
    for key, value in eager.items():
        np.testing.assert_array_equal(arrays[key], value)
        assert arrays[key].dtype == value.dtype


def test_summary_with_no_angles_is_nan():
    raw = {
        "converged": np.ones(2, dtype=bool),
        "failed_step": np.full(2, -1),
        "failure_code": np.zeros(2, dtype=np.int8),
        "step_angle": np.full(2, np.nan),
    }
    n_failed, first, _, _, top, worst = _summary(raw)
    assert (n_failed, first, worst) == (0, -1, -1) and np.isnan(top)


def test_lists_read_by_the_core_equal_arrays():
    """A list of plain numbers goes to the core without NumPy; anything else in a list takes
    NumPy's conversion, with the same result and the same errors as before."""
    stepper = pr.classical(BODY, "rk4")
    ref = pr.integrate(stepper, np.array([1.0, -2.0, 0.5]), 0.1, 4)
    for same in ([1.0, -2.0, 0.5], [1, -2.0, 0.5], [np.float64(1.0), -2, 0.5], [[1.0, -2.0, 0.5]]):
        got = pr.integrate(stepper, same, 0.1, 4)
        np.testing.assert_array_equal(got.reshape(ref.shape), ref)
    # An int beyond int64 was an object array, refused with its dtype named: still so.
    with pytest.raises(TypeError, match="dtype object"):
        pr.integrate(stepper, [2**70, 1, 2], 0.1, 1)
    with pytest.raises(ValueError, match="NaN or infinite"):
        pr.integrate(stepper, [1.0, float("inf"), 2], 0.1, 1)
    top = pr.classical(TOP, "rk4")
    state = [0.1, -0.2, 0.3, 0.0, 0.6, 0.8]
    np.testing.assert_array_equal(
        pr.integrate(top, state, 0.05, 3), pr.integrate(top, np.array([state]), 0.05, 3)[0]
    )

"""Classical baselines behind ``integrate()``: orders against the exact flow, invariants, bad input.

Orders are fitted as in test_accuracy.py (log error against log h at a fixed end time).
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import random_states

import poisson_rs as pr
from poisson_rs import _core

BODY = pr.RigidBody((1.5, 2.0, 2.5))
SCENE_STATES = np.array([[1.0, 1.0, 2.0], [3.0, 2.0, 0.0]])
RUST_METHODS = ("rk4", "midpoint", "splitting", "splitting4", "dmv")
POISSON_METHODS = ("midpoint", "splitting", "splitting4", "dmv")


def _global_error(stepper: pr.ClassicalIntegrator, h: float, t_end: float) -> float:
    """Largest Euclidean error at t_end over the two scene states."""
    n = round(t_end / h)
    assert abs(n * h - t_end) < 1e-12
    final = pr.integrate(stepper, SCENE_STATES, h, n)[:, -1]
    exact = pr.exact_solution(BODY, SCENE_STATES, [t_end])[:, -1]
    return float(np.max(np.linalg.norm(final - exact, axis=-1)))


@pytest.mark.parametrize(
    ("name", "expected", "hs"),
    [
        ("rk4", 4, (0.1, 0.05, 0.025, 0.0125)),
        ("midpoint", 2, (0.1, 0.05, 0.025, 0.0125)),
        ("splitting", 2, (0.1, 0.05, 0.025, 0.0125)),
        ("splitting4", 4, (0.1, 0.05, 0.025, 0.0125)),
        ("dmv", 2, (0.1, 0.05, 0.025, 0.0125)),
    ],
)
def test_fitted_order(name: str, expected: int, hs: tuple[float, ...]):
    stepper = pr.classical(BODY, name)
    errors = np.array([_global_error(stepper, h, 2.0) for h in hs])
    # Errors near round-off would flatten the slope and make the fit meaningless.
    assert errors.min() > 1e-11, f"errors reach round-off: {errors}"
    fitted = float(np.polyfit(np.log(hs), np.log(errors), 1)[0])
    assert abs(fitted - expected) <= 0.3, f"fitted order {fitted:.2f}, expected {expected}"


def _relative_drift(values: np.ndarray) -> np.ndarray:
    """max_k |v_k/v_0 − 1| per trajectory; values (n, T)."""
    return np.max(np.abs(values / values[:, :1] - 1.0), axis=1)


@pytest.fixture(scope="module")
def long_rollouts() -> dict[str, np.ndarray]:
    """10,000 steps of h = 0.1 from the scene states and 4 seeded random ones, per method."""
    mu0 = np.vstack([SCENE_STATES, random_states(np.random.default_rng(7), 4)])
    out = {}
    for name in RUST_METHODS:
        traj, info = pr.integrate(pr.classical(BODY, name), mu0, 0.1, 10_000, return_info=True)
        assert info.converged.all()
        assert np.isfinite(traj).all()
        out[name] = traj
    return out


@pytest.mark.parametrize("name", POISSON_METHODS)
def test_casimir_kept_to_round_off(long_rollouts: dict[str, np.ndarray], name: str):
    drift = _relative_drift(BODY.casimir(long_rollouts[name]))
    assert drift.max() <= 1e-12, f"Casimir drift {drift}"


def test_rk4_casimir_drifts(long_rollouts: dict[str, np.ndarray]):
    # RK4 is not Poisson: shows that the Casimir test above can tell.
    drift = _relative_drift(BODY.casimir(long_rollouts["rk4"]))
    assert drift.min() > 1e-10, f"Casimir drift {drift}"


@pytest.mark.parametrize("name", ["splitting", "splitting4"])
def test_splitting_energy_bounded_without_drift(long_rollouts: dict[str, np.ndarray], name: str):
    traj = long_rollouts[name]
    d_h = np.abs(BODY.hamiltonian(traj) / BODY.hamiltonian(traj[:, :1]) - 1.0)
    first, second = d_h[:, :5001].max(axis=1), d_h[:, 5001:].max(axis=1)
    assert np.all(first > 0)
    assert np.all(second <= 2.0 * first), f"energy drifts: {first} then {second}"
    assert np.all(first <= (1e-3 if name == "splitting" else 1e-5)), first


@pytest.mark.parametrize("name", ["midpoint", "dmv"])
def test_energy_kept_by_midpoint_and_dmv(long_rollouts: dict[str, np.ndarray], name: str):
    # Both keep H exactly (midpoint: H is quadratic; DMV: it is integrable), up to round-off.
    drift = _relative_drift(BODY.hamiltonian(long_rollouts[name]))
    assert drift.max() <= 1e-12, f"energy drift {drift}"


def test_rk4_energy_drifts(long_rollouts: dict[str, np.ndarray]):
    # RK4's energy error grows (dissipates) over the 10⁴ steps, unlike the splittings'.
    d_h = np.abs(BODY.hamiltonian(long_rollouts["rk4"]) - BODY.hamiltonian(SCENE_STATES[:1]))
    assert d_h[0, 5001:].max() > 1.5 * d_h[0, :5001].max()


@pytest.mark.parametrize("name", RUST_METHODS)
def test_other_inertia_and_every(name: str):
    # Unsorted inertia, a state on each side of the separatrix, every > 1.
    body = pr.RigidBody((3.0, 0.7, 1.9))
    mu0 = random_states(np.random.default_rng(11), 5)
    stepper = pr.classical(body, name)
    full = pr.integrate(stepper, mu0, 0.01, 300)
    sparse = pr.integrate(stepper, mu0, 0.01, 300, every=7)
    np.testing.assert_array_equal(sparse, full[:, ::7])
    exact = pr.exact_solution(body, mu0, 0.01 * np.arange(301))
    tol = 1e-6 if name in ("rk4", "splitting4") else 1e-2
    assert np.max(np.abs(full - exact)) <= tol


def test_dop853_agrees_with_exact():
    stepper = pr.classical(BODY, "dop853")
    mu0 = np.vstack([SCENE_STATES, random_states(np.random.default_rng(3), 2)])
    traj, info = pr.integrate(stepper, mu0, 0.1, 100, every=2, return_info=True)
    assert traj.shape == (4, 51, 3)
    exact = pr.exact_solution(BODY, mu0, 0.2 * np.arange(51))
    assert np.max(np.abs(traj - exact)) <= 1e-9
    assert info.converged.all()
    # The same keys and dtypes as a Rust rollout's info.
    _, rust_info = _core.rollout_classical("rk4", BODY.inertia, mu0, 0.1, 2)
    dop_info = stepper.rollout(mu0, 0.1, 2, 1)[1]
    assert {k: v.dtype for k, v in dop_info.items()} == {k: v.dtype for k, v in rust_info.items()}


def test_single_state_and_zero_steps():
    stepper = pr.classical(BODY, "splitting")
    assert pr.integrate(stepper, [1.0, 1.0, 2.0], 0.1, 10).shape == (11, 3)
    zero_steps = pr.integrate(stepper, SCENE_STATES, 0.1, 0)
    np.testing.assert_array_equal(zero_steps, SCENE_STATES[:, None])
    assert pr.integrate(pr.classical(BODY, "dop853"), [1.0, 1.0, 2.0], 0.1, 10).shape == (11, 3)


def test_newton_failure_is_reported():
    # One Newton update cannot meet the tolerance: the trajectory stops at its first step.
    stepper = pr.classical(BODY, "midpoint", max_iter=1)
    traj, info = pr.integrate(stepper, SCENE_STATES, 0.1, 5, return_info=True, on_failure="ignore")
    assert not info.converged.any()
    assert (info.failed_step == 0).all() and (info.failure_code == 1).all()
    assert np.isnan(traj[:, 1:]).all()


def test_bad_input():
    with pytest.raises(ValueError, match="valid names: rk4, midpoint"):
        pr.classical(BODY, "rk5")
    with pytest.raises(ValueError, match="valid names"):
        pr.classical(BODY, None)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="Poisson system"):
        pr.classical((1.5, 2.0, 2.5), "rk4")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="tol"):
        pr.classical(BODY, "midpoint", tol=0.0)
    with pytest.raises(ValueError, match="max_iter"):
        pr.classical(BODY, "dmv", max_iter=0)
    with pytest.raises(ValueError, match="strictly positive"):
        pr.RigidBody((1.0, 0.0, 2.0))
    mu0 = SCENE_STATES.copy()
    with pytest.raises(ValueError, match="valid names: rk4, midpoint, splitting, splitting4, dmv"):
        _core.rollout_classical("dop853", BODY.inertia, mu0, 0.1, 10)
    for inertia in [(1.0, 0.0, 2.0), (1.0, -1.0, 2.0), (1.0, float("nan"), 2.0), (np.inf, 1, 1)]:
        with pytest.raises(ValueError, match="inertia"):
            _core.rollout_classical("rk4", inertia, mu0, 0.1, 10)
    with pytest.raises(ValueError, match="h must be"):
        _core.rollout_classical("rk4", BODY.inertia, mu0, -0.1, 10)
    with pytest.raises(ValueError, match="every"):
        _core.rollout_classical("rk4", BODY.inertia, mu0, 0.1, 10, every=0)
    with pytest.raises(ValueError, match="shape"):
        _core.rollout_classical("rk4", BODY.inertia, np.zeros((2, 4)), 0.1, 10)
    with pytest.raises(MemoryError):
        _core.rollout_classical("rk4", BODY.inertia, mu0, 0.1, 2**40)


# --- every Lie–Poisson system's method table ---------------------------------------------------

QUARTIC = pr.LiePoissonSystem(
    pr.LieAlgebra.so3(), pr.Polynomial({(4, 0, 0): 0.25, (0, 2, 0): 0.5, (0, 0, 2): 1.0})
)
TABLE_SYSTEMS = {"rigid body": BODY, "heavy top": pr.HeavyTop(), "quartic so(3)": QUARTIC}


def _table_cases() -> list[tuple[str, str]]:
    return [
        (key, name)
        for key, system in TABLE_SYSTEMS.items()
        for name in system.classical_methods()
        if name != "dop853"
    ]


@pytest.mark.parametrize(("key", "name"), _table_cases())
def test_method_table_claims_hold(key: str, name: str):
    """The (order, Poisson) a system's table gives each of its methods, checked on the system:
    the order fitted against the system's own DOP853 reference, and a Poisson step keeping the
    algebra's Casimirs to round-off over 2,000 steps."""
    system = TABLE_SYSTEMS[key]
    stepper = pr.classical(system, name)
    order, poisson = system.method_table[name]
    assert (stepper.order, stepper.poisson) == (order, poisson)
    x0 = system.demo_states[:1]
    hs = (0.08, 0.04, 0.02)
    exact = system.reference_solution(x0, [0.0, 0.8])[:, -1]
    errors = [
        float(np.abs(pr.integrate(stepper, x0, h, round(0.8 / h))[:, -1] - exact).max()) for h in hs
    ]
    fitted = float(np.polyfit(np.log(hs), np.log(errors), 1)[0])
    assert abs(fitted - order) <= 0.35, f"{key} {name}: fitted order {fitted:.2f}, table {order}"
    if poisson:
        traj = pr.integrate(stepper, x0, 0.1, 2_000)
        c = system.casimirs(traj)
        drift = np.abs(c - c[:, :1]).max() / np.abs(c[:, :1]).max()
        assert drift <= 1e-12, f"{key} {name}: Casimir drift {drift:.1e}"

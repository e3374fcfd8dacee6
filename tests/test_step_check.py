"""The step-size check runs in Rust on every initial state, with the Hessian of H in the local
rate, and is recorded per trajectory in ``RolloutInfo.step_angle``; the SIMD-lane RK4 behind
``integrate()`` gives every trajectory the same bits whatever the batch around it. Oracles: the
closed-form rate |ω| of the rigid body, the exact flow, finite differences of the vector field,
and one-at-a-time rollouts."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import poisson_rs as pr
from poisson_rs import _core
from poisson_rs.integrators import MAX_STEP_ANGLE
from poisson_rs.structures.lie_poisson import LieAlgebra, LiePoissonSystem, Polynomial

BODY = pr.RigidBody((1.5, 2.0, 2.5))


def quartic_body() -> LiePoissonSystem:
    """H = Σ μᵢ⁴/(4 Iᵢ) on so(3): its gradient μ³/I turns μ, its Hessian 3μ²/I moves ∇H."""
    terms = {tuple(4 * int(i == j) for j in range(3)): 0.25 / BODY.inertia[i] for i in range(3)}
    return LiePoissonSystem(LieAlgebra.so3(), Polynomial(terms), name="quartic")


def jacobian_fd(system: LiePoissonSystem, mu: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """∂f/∂μ by central differences of f(μ) = ad*_{∇H(μ)} μ."""
    c = system.algebra.c

    def field(m: np.ndarray) -> np.ndarray:
        return np.einsum("ijk,i,k->j", c, system.grad_hamiltonian(m), m)

    cols = [(field(mu + eps * e) - field(mu - eps * e)) / (2 * eps) for e in np.eye(len(mu))]
    return np.stack(cols, axis=1)


def test_step_angle_is_h_omega_for_the_rigid_body_in_every_method() -> None:
    rng = np.random.default_rng(0)
    mu0 = rng.uniform(-3, 3, (9, 3))
    want = 0.1 * np.linalg.norm(mu0 / np.array(BODY.inertia), axis=1)
    for name in ("rk4", "midpoint", "splitting", "dmv"):
        _, info = pr.integrate(pr.classical(BODY, name), mu0, 0.1, 2, return_info=True)
        np.testing.assert_allclose(info.step_angle, want, rtol=1e-12)
    _, info = pr.integrate(pr.taylor_integrator(BODY, 3), mu0, 0.1, 2, return_info=True)
    np.testing.assert_allclose(info.step_angle, want, rtol=1e-12)
    # DOP853 chooses its own steps: n/a, never 0.
    _, info = pr.integrate(pr.classical(BODY, "dop853"), mu0[:2], 0.1, 2, return_info=True)
    assert np.isnan(info.step_angle).all()


def test_every_state_is_checked_not_only_the_first_4096() -> None:
    mu0 = np.tile([1.0, 1.0, 2.0], (5000, 1))
    mu0[4500] = [60.0, 50.0, 60.0]  # turns 5.3 rad a step at h = 0.1
    with pytest.warns(RuntimeWarning, match=r"turns state 4500 by 5\.29 rad"):
        _, info = pr.integrate(pr.classical(BODY, "rk4"), mu0, 0.1, 1, return_info=True)
    assert np.flatnonzero(info.step_angle > MAX_STEP_ANGLE).tolist() == [4500]


def test_the_local_rate_includes_the_hessian() -> None:
    """The quartic body at μ = (1, 2, 0.5): the rotation rate |∇H| alone would pass h = 0.3,
    yet RK4 is far from a fine reference there. The rate is ‖∂f/∂μ‖_F (finite differences)."""
    body = quartic_body()
    mu = np.array([1.0, 2.0, 0.5])
    h = 0.3
    rotation = h * np.linalg.norm(body.grad_hamiltonian(mu))
    assert rotation < MAX_STEP_ANGLE
    jac = jacobian_fd(body, mu)
    angle = _core.step_angles(
        np.ascontiguousarray(body.algebra.c), *body.polynomial.to_arrays(), mu[None], h
    )[0]
    assert angle == pytest.approx(h * np.linalg.norm(jac), rel=1e-7)
    assert angle > MAX_STEP_ANGLE
    rk4 = pr.classical(body, "rk4")
    with pytest.warns(RuntimeWarning, match="turns state 0"):
        coarse = pr.integrate(rk4, mu, h, 20)[-1]
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        fine = pr.integrate(rk4, mu, h / 100, 2000)[-1]
    assert np.linalg.norm(coarse - fine) / np.linalg.norm(mu) > 0.05


@pytest.mark.parametrize("system", [BODY, pr.HeavyTop()], ids=["rigid", "top"])
def test_rk4_lanes_give_each_trajectory_its_own_bits(system: LiePoissonSystem) -> None:
    """A batch of 13 (not a multiple of the 8 lanes) equals the trajectories stepped one at a
    time (a lone trajectory takes the scalar path), bit for bit."""
    rng = np.random.default_rng(1)
    mu0 = rng.uniform(-2, 2, (13, system.dim))
    rk4 = pr.classical(system, "rk4")
    batch = pr.integrate(rk4, mu0, 0.05, 37, every=4)
    for i in range(len(mu0)):
        assert np.array_equal(pr.integrate(rk4, mu0[i], 0.05, 37, every=4), batch[i])


def test_an_overflowing_lane_fails_alone() -> None:
    mu0 = np.tile([1.0, 1.0, 2.0], (11, 1))
    mu0[5] = 1e120  # μ × (μ/I) overflows in the first step
    rk4 = pr.classical(BODY, "rk4")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        traj, info = pr.integrate(rk4, mu0, 0.1, 6, return_info=True)
    assert info.converged.tolist() == [i != 5 for i in range(11)]
    assert info.failed_step[5] >= 0 and info.failure_code[5] == 3
    assert np.isnan(traj[5, info.failed_step[5] + 1 :]).all()
    assert np.array_equal(traj[0], pr.integrate(rk4, mu0[0], 0.1, 6))


def test_dask_carries_the_step_angle() -> None:
    da = pytest.importorskip("dask.array")
    mu0 = np.tile([1.0, 1.0, 2.0], (6, 1))
    mu0[4] = [60.0, 50.0, 60.0]
    stepper = pr.classical(BODY, "rk4")
    _, info = pr.integrate(
        stepper, da.from_array(mu0, chunks=3), 0.1, 2, return_info=True, on_failure="ignore"
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        _, eager = pr.integrate(stepper, mu0, 0.1, 2, return_info=True)
    assert np.array_equal(info.step_angle.compute(), eager.step_angle)

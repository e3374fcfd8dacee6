"""Tests for the closed-form free rigid body flow against DOP853 and its invariants."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest
from scipy.special import ellipj

from poisson_rs.structures.lie_poisson import RigidBody
from poisson_rs.structures.lie_poisson_reference import dop853_solution, exact_solution

PAPER_INERTIA = (1.5, 2.0, 2.5)
PERMUTATIONS = list(itertools.permutations(range(3)))


def _rel_err(a: np.ndarray, b: np.ndarray, mu0: np.ndarray) -> float:
    """Max |a − b| relative to |μ₀| (per trajectory), over everything."""
    norms = np.linalg.norm(np.atleast_2d(mu0), axis=-1)
    diff = np.abs(np.asarray(a) - np.asarray(b)).reshape(norms.size, -1)
    return float(np.max(diff / norms[:, None]))


def _delta(inertia: tuple[float, float, float], mu: np.ndarray) -> float:
    """2H·I_mid − |μ|²: > 0 circulates about the smallest-inertia axis, < 0 the largest."""
    body = RigidBody(inertia)
    return float(2.0 * body.hamiltonian(mu) * np.median(inertia) - body.casimir(mu))


def _separatrix_state(inertia: tuple[float, float, float], rel: float) -> np.ndarray:
    """State with μ_min = (1 + rel)·(separatrix value), μ_mid = 3.5, μ_max = 5 (body order)."""
    order = np.argsort(inertia)
    i1, i2, i3 = np.asarray(inertia)[order]
    nu = 5.0 * np.array([np.sqrt((i3 - i2) * i1 / (i3 * (i2 - i1))) * (1.0 + rel), 0.7, 1.0])
    mu = np.empty(3)
    mu[order] = nu
    return mu


# --- RigidBody --------------------------------------------------------------------------------


def test_rigid_body_defaults_and_storage() -> None:
    assert RigidBody().inertia == PAPER_INERTIA
    body = RigidBody(np.array([3, 1, 2]))
    assert body.inertia == (3.0, 1.0, 2.0)
    assert all(type(v) is float for v in body.inertia)
    assert hash(body) == hash(RigidBody((3.0, 1.0, 2.0)))
    with pytest.raises(dataclasses.FrozenInstanceError):
        body.inertia = (1.0, 1.0, 1.0)  # type: ignore[misc]


@pytest.mark.parametrize(
    ("inertia", "match"),
    [
        ((1.0, 2.0), "exactly 3"),
        ((1.0, 2.0, 3.0, 4.0), "exactly 3"),
        ((1.0, 0.0, 2.0), "strictly positive"),
        ((1.0, -2.0, 3.0), "strictly positive"),
        ((1.0, float("nan"), 3.0), "finite"),
        ((1.0, float("inf"), 3.0), "finite"),
        (("1", "2", "3"), "real numbers"),
        ("123", "entries must be real numbers"),
        (5.0, "sequence of 3 real numbers"),
        (np.ones((3, 1)), "real numbers"),
    ],
)
def test_rigid_body_rejects_bad_inertia(inertia: object, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        RigidBody(inertia)  # type: ignore[arg-type]


def test_rigid_body_methods() -> None:
    body = RigidBody((1.0, 2.0, 4.0))
    mu = np.array([1.0, 2.0, 4.0])
    assert body.hamiltonian(mu) == pytest.approx(0.5 * (1.0 + 2.0 + 4.0))
    assert body.casimir(mu) == pytest.approx(21.0)
    np.testing.assert_allclose(body.grad_hamiltonian(mu), [1.0, 1.0, 1.0])
    np.testing.assert_allclose(body.vector_field(mu), np.cross(mu, [1.0, 1.0, 1.0]))

    rng = np.random.default_rng(42)
    batch = rng.normal(size=(4, 5, 3))
    assert body.hamiltonian(batch).shape == (4, 5)
    assert body.casimir(batch).shape == (4, 5)
    assert body.grad_hamiltonian(batch).shape == (4, 5, 3)
    field = body.vector_field(batch)
    assert field.shape == (4, 5, 3)
    np.testing.assert_allclose(field, np.cross(batch, body.grad_hamiltonian(batch)))
    # Both H and C are conserved: the field is orthogonal to both gradients.
    np.testing.assert_allclose(np.sum(field * batch, axis=-1), 0.0, atol=1e-12)
    np.testing.assert_allclose(
        np.sum(field * body.grad_hamiltonian(batch), axis=-1), 0.0, atol=1e-12
    )
    with pytest.raises(ValueError, match="mu must have shape"):
        body.hamiltonian(np.ones(2))
    with pytest.raises(ValueError, match="mu must have shape"):
        body.vector_field(1.0)


# --- Jacobi elliptic functions (private helper) ------------------------------------------------


def test_jacobi_helper_matches_scipy_and_limits() -> None:
    from poisson_rs.structures.lie_poisson_reference import _jacobi_sn_cn_dn

    rng = np.random.default_rng(42)
    m = np.array([0.0, 1e-12, 0.1, 0.5, 0.9, 0.99])
    u = rng.uniform(-30.0, 30.0, size=(m.size, 50))
    sn, cn, dn = _jacobi_sn_cn_dn(u, m, 1.0 - m)
    ref_sn, ref_cn, ref_dn, _ = ellipj(u, m[:, None])
    np.testing.assert_allclose(sn, ref_sn, rtol=0, atol=1e-13)
    np.testing.assert_allclose(cn, ref_cn, rtol=0, atol=1e-13)
    np.testing.assert_allclose(dn, ref_dn, rtol=0, atol=1e-13)

    # m = 1 exactly: hyperbolic limit; 1 − m tiny: still periodic (quarter period K(m)).
    u1 = np.linspace(-20.0, 20.0, 81)[None, :]
    sn, cn, dn = _jacobi_sn_cn_dn(u1, np.array([1.0]), np.array([0.0]))
    np.testing.assert_allclose(sn, np.tanh(u1), atol=1e-15)
    np.testing.assert_allclose(cn, 1.0 / np.cosh(u1), atol=1e-15)
    np.testing.assert_allclose(dn, 1.0 / np.cosh(u1), atol=1e-15)
    m1 = 1e-40
    quarter = 0.5 * np.log(16.0 / m1)  # K(m) + O(m1 log m1)
    sn, cn, dn = _jacobi_sn_cn_dn(
        np.array([[quarter, 2 * quarter, 3 * quarter]]), np.array([1.0]), np.array([m1])
    )
    np.testing.assert_allclose(sn, [[1.0, 0.0, -1.0]], atol=1e-14)
    np.testing.assert_allclose(cn, [[0.0, -1.0, 0.0]], atol=1e-14)
    # dn(K) = √m1 = 1e-20 exactly; cn is only accurate to ~eps absolutely, and so is dn.
    np.testing.assert_allclose(dn, [[0.0, 1.0, 0.0]], atol=1e-15)


# --- exact solution vs DOP853 ------------------------------------------------------------------


def test_exact_matches_dop853_random_states() -> None:
    rng = np.random.default_rng(42)
    times = np.linspace(0.0, 20.0, 81)
    sides = {"smallest": 0, "largest": 0}
    unsorted = 0
    worst = 0.0
    for k in range(60):
        inertia = PAPER_INERTIA if k % 4 == 0 else tuple(float(v) for v in rng.uniform(0.5, 3.0, 3))
        unsorted += inertia != tuple(sorted(inertia))
        mu0 = rng.normal(size=3) * rng.uniform(0.2, 5.0)
        sides["smallest" if _delta(inertia, mu0) > 0 else "largest"] += 1
        body = RigidBody(inertia)
        exact = exact_solution(body, mu0, times)
        assert exact.shape == (times.size, 3) and exact.dtype == np.float64
        worst = max(worst, _rel_err(exact, dop853_solution(body, mu0, times), mu0))
    assert sides["smallest"] >= 10 and sides["largest"] >= 10, sides
    assert unsorted >= 30
    assert worst <= 1e-9, worst


def test_exact_matches_dop853_negative_unsorted_times() -> None:
    rng = np.random.default_rng(7)
    body = RigidBody((2.5, 1.5, 2.0))
    mu0 = rng.normal(size=(3, 3))
    times = np.array([3.0, -7.5, 0.0, 12.0, -0.25, 3.0, -20.0])
    exact = exact_solution(body, mu0, times)
    assert exact.shape == (3, times.size, 3)
    assert _rel_err(exact, dop853_solution(body, mu0, times), mu0) <= 1e-9
    np.testing.assert_array_equal(dop853_solution(body, mu0, times)[:, 2], mu0)


@pytest.mark.parametrize("mu0", [(1.0, 1.0, 2.0), (3.0, 2.0, 0.0)])
def test_paper_states_to_t100(mu0: tuple[float, float, float]) -> None:
    body = RigidBody(PAPER_INERTIA)
    times = np.linspace(0.0, 100.0, 401)
    exact = exact_solution(body, mu0, times)
    assert _rel_err(exact, dop853_solution(body, mu0, times), np.asarray(mu0)) <= 1e-9


# --- orientation under permutations of the axes -----------------------------------------------


@pytest.mark.parametrize("perm", PERMUTATIONS)
def test_axis_permutation_is_time_reversal_for_odd_permutations(perm: tuple[int, ...]) -> None:
    # With ν = μ[perm] and J = I[perm]: ν̇ = sign(perm) ν × ν/J.
    sign = np.linalg.det(np.eye(3)[list(perm)])
    inertia = np.array(PAPER_INERTIA)
    mu0 = np.array([0.3, -1.1, 0.8])
    times = np.linspace(-5.0, 5.0, 21)
    direct = exact_solution(RigidBody(tuple(inertia[list(perm)])), mu0[list(perm)], times)
    mapped = exact_solution(RigidBody(tuple(inertia)), mu0, sign * times)[:, list(perm)]
    np.testing.assert_allclose(direct, mapped, rtol=0, atol=1e-13)
    oracle = dop853_solution(RigidBody(tuple(inertia[list(perm)])), mu0[list(perm)], times)
    assert _rel_err(direct, oracle, mu0) <= 1e-9


@pytest.mark.parametrize("inertia", [(1.0, 2.0, 3.0), (3.0, 2.0, 1.0), (2.0, 3.0, 1.0)])
def test_time_derivative_is_vector_field(inertia: tuple[float, float, float]) -> None:
    rng = np.random.default_rng(3)
    body = RigidBody(inertia)
    mu0 = rng.normal(size=(8, 3))
    h = 1e-5
    t = np.array([0.37, 0.37 - h, 0.37 + h])
    traj = exact_solution(body, mu0, t)
    derivative = (traj[:, 2] - traj[:, 1]) / (2.0 * h)
    np.testing.assert_allclose(derivative, body.vector_field(traj[:, 0]), atol=1e-8)


# --- separatrix --------------------------------------------------------------------------------


@pytest.mark.parametrize("inertia", [PAPER_INERTIA, (2.5, 1.5, 2.0)])
@pytest.mark.parametrize("rel", [1e-6, -1e-6])
def test_near_separatrix(inertia: tuple[float, float, float], rel: float) -> None:
    body = RigidBody(inertia)
    mu0 = _separatrix_state(inertia, rel)
    assert np.sign(_delta(inertia, mu0)) == np.sign(rel)
    times = np.linspace(-30.0, 30.0, 241)
    exact = exact_solution(body, mu0, times)
    # Passing the saddle amplifies errors: against a 30-digit mpmath Taylor integration at
    # t = −18, DOP853 is off by 9e-10 and exact_solution by 5e-11, hence 1e-8 here.
    assert _rel_err(exact, dop853_solution(body, mu0, times), mu0) <= 1e-8
    # Circulation: the component along the axis it circulates about keeps its sign, the other
    # changes sign within the window (half period 2K/λ ≈ 17 here).
    i_min, i_max = int(np.argmin(inertia)), int(np.argmax(inertia))
    kept, flipped = (i_min, i_max) if rel > 0 else (i_max, i_min)
    assert np.all(exact[:, kept] > 0)
    assert np.any(exact[:, flipped] < 0)


@pytest.mark.parametrize("rel", [1e-10, -1e-10, 1e-14, -1e-14])
def test_very_near_separatrix(rel: float) -> None:
    body = RigidBody(PAPER_INERTIA)
    mu0 = _separatrix_state(PAPER_INERTIA, rel)
    assert np.sign(_delta(PAPER_INERTIA, mu0)) == np.sign(rel)
    # Up to the first close approach of the saddle; beyond it the problem itself is
    # ill-conditioned (relative input perturbations of 1e-16 move the state by ~1e-7 at t ≈ 28
    # for rel = 1e-10), and DOP853 is the less accurate of the two there.
    times = np.linspace(-12.0, 12.0, 97)
    exact = exact_solution(body, mu0, times)
    assert _rel_err(exact, dop853_solution(body, mu0, times), mu0) <= 1e-9
    # Forward and backward, the orbit passes the saddle (0, ±|μ|, 0) at a relative distance of
    # order √|rel| (≈ 0.8√|rel| for this state), and does not hit it.
    times = np.linspace(-25.0, 25.0, 1001)
    traj = exact_solution(body, mu0, times)
    distance = np.hypot(traj[:, 0], traj[:, 2]) / np.linalg.norm(mu0)
    for half in (distance[times < 0], distance[times > 0]):
        assert 0.1 * np.sqrt(abs(rel)) < half.min() < 2.0 * np.sqrt(abs(rel))


def test_on_separatrix_exactly() -> None:
    # For I = (2, 3, 6), 2H·I₂ − |μ|² = (μ₁² − μ₃²)/2: exactly zero in floating point at μ₁ = ±μ₃.
    body = RigidBody((2.0, 3.0, 6.0))
    mu0 = np.array([[1.0, 0.3, 1.0], [-1.0, 0.3, 1.0], [0.5, -2.0, -0.5], [1.0, 0.0, -1.0]])
    assert np.all(2.0 * body.hamiltonian(mu0) * 3.0 - body.casimir(mu0) == 0.0)
    times = np.linspace(-8.0, 8.0, 65)
    exact = exact_solution(body, mu0, times)
    assert _rel_err(exact, dop853_solution(body, mu0, times), mu0) <= 1e-9
    # Heteroclinic orbit: μ₁, μ₃ keep their signs and the state tends to (0, ±|μ|, 0).
    far = exact_solution(body, mu0, [-200.0, 200.0])
    assert np.all(np.sign(far[..., 0]) == np.sign(mu0[:, None, 0]))
    assert np.all(np.sign(far[..., 2]) == np.sign(mu0[:, None, 2]))
    norms = np.broadcast_to(np.linalg.norm(mu0, axis=1)[:, None], far.shape[:2])
    np.testing.assert_allclose(np.abs(far[..., 1]), norms, rtol=1e-14)
    assert np.all(far[:, 0, 1] * far[:, 1, 1] < 0)
    # Continuous across the separatrix at moderate times.
    nearby = exact_solution(body, mu0 * [1.0 + 1e-12, 1.0, 1.0], times)
    np.testing.assert_allclose(nearby, exact, atol=1e-9)


# --- invariants and consistency ----------------------------------------------------------------


def test_invariants_conserved_to_t1000() -> None:
    rng = np.random.default_rng(42)
    times = np.linspace(0.0, 1000.0, 2001)
    for inertia in [PAPER_INERTIA, (2.5, 0.7, 1.9), (1.0, 1.0 + 1e-9, 2.0)]:
        body = RigidBody(inertia)
        mu0 = np.vstack([rng.normal(size=(20, 3)), [[1.0, 1.0, 2.0], [3.0, 2.0, 0.0]]])
        traj = exact_solution(body, mu0, times)
        h, c = body.hamiltonian(traj), body.casimir(traj)
        np.testing.assert_allclose(h, h[:, :1] * np.ones_like(h), rtol=1e-13, atol=0)
        np.testing.assert_allclose(c, c[:, :1] * np.ones_like(c), rtol=1e-13, atol=0)


def test_initial_condition_reproduced() -> None:
    rng = np.random.default_rng(42)
    for _ in range(20):
        body = RigidBody(tuple(float(v) for v in rng.uniform(0.5, 3.0, 3)))
        mu0 = rng.normal(size=(10, 3))
        at_zero = exact_solution(body, mu0, [0.0])[:, 0]
        assert _rel_err(at_zero, mu0, mu0) <= 1e-14


def test_group_property() -> None:
    rng = np.random.default_rng(42)
    body = RigidBody((2.2, 0.9, 1.4))
    mu0 = rng.normal(size=(6, 3))
    s, t = 13.7, np.array([-41.0, -3.2, 0.0, 8.9, 57.3])
    mid = exact_solution(body, mu0, [s])[:, 0]
    np.testing.assert_allclose(
        exact_solution(body, mid, t), exact_solution(body, mu0, s + t), rtol=0, atol=1e-11
    )


@pytest.mark.parametrize("scale", [1e-150, 1e150, 3.0])
def test_homogeneity_and_extreme_magnitudes(scale: float) -> None:
    # μ(t; s μ₀) = s μ(s t; μ₀).
    body = RigidBody((2.5, 1.5, 2.0))
    mu0 = np.array([1.0, 1.0, 2.0])
    times = np.linspace(-10.0, 10.0, 21)
    scaled = exact_solution(body, scale * mu0, times / scale)
    np.testing.assert_allclose(scaled / scale, exact_solution(body, mu0, times), atol=1e-13)


# --- symmetric tops and equilibria --------------------------------------------------------------


@pytest.mark.parametrize("inertia", [(2.0, 2.0, 3.0), (2.0, 3.0, 2.0), (3.0, 1.0, 1.0)])
def test_symmetric_top(inertia: tuple[float, float, float]) -> None:
    rng = np.random.default_rng(42)
    body = RigidBody(inertia)
    mu0 = rng.normal(size=(5, 3))
    times = np.linspace(-15.0, 15.0, 61)
    exact = exact_solution(body, mu0, times)
    assert _rel_err(exact, dop853_solution(body, mu0, times), mu0) <= 1e-9
    # Uniform rotation about the symmetry axis: that component is constant.
    axis = next(i for i in range(3) if inertia.count(inertia[i]) == 1)
    np.testing.assert_array_equal(exact[..., axis], np.repeat(mu0[:, None, axis], times.size, 1))
    # The nearly symmetric body goes through the elliptic formulas and stays close.
    eps = 1e-9
    nearly = list(inertia)
    nearly[(axis + 1) % 3] += eps
    close = exact_solution(RigidBody(tuple(nearly)), mu0, times)
    assert _rel_err(close, exact, mu0) <= 1e-6


def test_spherical_body_is_static() -> None:
    body = RigidBody((1.3, 1.3, 1.3))
    mu0 = np.array([[0.2, -1.0, 3.0]])
    out = exact_solution(body, mu0, [-4.0, 0.0, 9.0])
    np.testing.assert_array_equal(out, np.repeat(mu0[:, None], 3, axis=1))


@pytest.mark.parametrize("inertia", [PAPER_INERTIA, (2.0, 2.5, 1.5)])
def test_equilibria(inertia: tuple[float, float, float]) -> None:
    body = RigidBody(inertia)
    mu0 = np.vstack([np.diag([2.0, -3.0, 0.5]), -np.eye(3), np.zeros((1, 3))])
    times = np.array([-100.0, 0.0, 1.0, 1e6])
    out = exact_solution(body, mu0, times)
    np.testing.assert_array_equal(out, np.repeat(mu0[:, None], times.size, axis=1))
    # Tiny perturbations of the stable axes stay close; the middle axis departs.
    rng = np.random.default_rng(42)
    perturbed = 10.0 * (np.eye(3) + 1e-7 * rng.normal(size=(3, 3)))
    t = np.linspace(0.0, 20.0, 41)
    traj = exact_solution(body, perturbed, t)
    assert _rel_err(traj[:, :11], dop853_solution(body, perturbed, t[:11]), perturbed) <= 1e-9
    drift = np.max(np.linalg.norm(traj - perturbed[:, None], axis=-1), axis=1) / 10.0
    middle = int(np.argsort(inertia)[1])
    assert np.all(np.delete(drift, middle) < 1e-5)
    assert drift[middle] > 0.1


# --- shapes and bad input -----------------------------------------------------------------------


def test_shapes() -> None:
    body = RigidBody()
    assert exact_solution(body, [1.0, 1.0, 2.0], np.linspace(0, 1, 4)).shape == (4, 3)
    assert exact_solution(body, np.ones((2, 3)), [0.5]).shape == (2, 1, 3)
    assert exact_solution(body, np.ones((0, 3)), [0.5, 1.0]).shape == (0, 2, 3)
    assert exact_solution(body, [1.0, 1.0, 2.0], []).shape == (0, 3)
    assert dop853_solution(body, np.ones((2, 3)), [0.5, -0.5]).shape == (2, 2, 3)
    assert dop853_solution(body, [1.0, 1.0, 2.0], []).shape == (0, 3)


@pytest.mark.parametrize("solver", [exact_solution, dop853_solution])
@pytest.mark.parametrize(
    ("mu0", "times", "match"),
    [
        (np.ones(2), [1.0], r"mu0 must have shape \(3,\) or \(n, 3\)"),
        (np.ones((2, 4)), [1.0], r"mu0 must have shape \(3,\) or \(n, 3\)"),
        (np.ones((2, 2, 3)), [1.0], r"mu0 must have shape \(3,\) or \(n, 3\)"),
        (1.0, [1.0], r"mu0 must have shape \(3,\) or \(n, 3\)"),
        ([1.0, np.nan, 2.0], [1.0], "mu0 must be finite"),
        ([[1.0, 1.0, 2.0], [np.inf, 0.0, 0.0]], [1.0], "mu0 must be finite"),
        (["a", "b", "c"], [1.0], "mu0 must be an array of real numbers"),
        ([1.0, 1.0, 2.0], 1.0, "times must be a 1-D array"),
        ([1.0, 1.0, 2.0], [[1.0, 2.0]], "times must be a 1-D array"),
        ([1.0, 1.0, 2.0], [0.0, np.inf], "times must be finite"),
        ([1.0, 1.0, 2.0], [np.nan], "times must be finite"),
    ],
)
def test_bad_input_raises(solver: object, mu0: object, times: object, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        solver(RigidBody(), mu0, times)  # type: ignore[operator]


def test_body_must_be_rigid_body() -> None:
    with pytest.raises(TypeError, match="body must be a RigidBody"):
        exact_solution((1.5, 2.0, 2.5), [1.0, 1.0, 2.0], [1.0])  # type: ignore[arg-type]

"""The term library beyond polynomials (:mod:`poisson_rs.hamiltonian_library`) and
``pr.learn`` reaching for it where no polynomial explains the data."""

from __future__ import annotations

import numpy as np
import pytest

import poisson_rs as pr
from poisson_rs.hamiltonian_library import LibraryFamily, supports_library
from poisson_rs.scenes import load_scene


@pytest.fixture(scope="module")
def pendulum():
    """PNN's extended pendulum: the affine bracket with H = ½u² − cos v + u(r − u² − v²)."""
    return load_scene("scenes/extended_pendulum_pnn.toml").system


def test_gradients_match_finite_differences(pendulum):
    fam = LibraryFamily(pendulum.base, 2)
    rng = np.random.default_rng(0)
    x = rng.normal(size=(6, 3))
    g = fam.gradients(x)
    eps = 1e-6
    for i in range(3):
        step = np.zeros(3)
        step[i] = eps
        plus = [fam.system(np.eye(len(fam))[m]).hamiltonian(x + step) for m in range(len(fam))]
        minus = [fam.system(np.eye(len(fam))[m]).hamiltonian(x - step) for m in range(len(fam))]
        fd = (np.stack(plus, axis=1) - np.stack(minus, axis=1)) / (2 * eps)
        np.testing.assert_allclose(g[:, i, :], fd, atol=1e-8)


def test_text_is_the_sum_of_the_terms(pendulum):
    fam = LibraryFamily(pendulum.base, 3)
    rng = np.random.default_rng(1)
    theta = rng.normal(size=len(fam))
    x = rng.normal(size=(5, 3))
    system = fam.system(theta)
    each = np.stack(
        [fam.system(np.eye(len(fam))[m]).hamiltonian(x) for m in range(len(fam))], axis=1
    )
    np.testing.assert_allclose(system.hamiltonian(x), each @ theta, rtol=1e-13, atol=1e-13)
    assert fam.name == "poly3+trig" and len(fam) == 19 + 6


def test_restrict_and_bad_keys(pendulum):
    fam = LibraryFamily(pendulum.base, 2)
    sub = fam.restrict([(2, 0, 0), ("cos", 1)])
    assert sub.exponents == [(2, 0, 0), ("cos", 1)]
    assert sub.text([0.5, -1.0]) == "(0.5)*u**2 + (-1.0)*cos(v)"
    with pytest.raises(ValueError, match="keys must be terms of the library poly2"):
        fam.restrict([("tan", 0)])


def test_only_structures_with_a_jet_realization_offer_it(pendulum):
    assert supports_library(pendulum.base)
    assert not supports_library(pr.lotka_volterra([[0, 1], [-1, 0]], [1, 2]))


def test_learn_finds_the_pendulums_cosine_and_beats_every_polynomial(pendulum):
    """PNN's protocol (3 states, h = 0.1, 100 steps): no polynomial degree reaches the noise
    level; the library's poly3+trig does, and its field is the true one up to the Casimir."""
    h = 0.1
    states = np.array([[0.0, 1.0, 1.0], [0.0, 1.5, 2.35], [0.0, 2.0, 4.2]])
    trajs = list(np.asarray(pr.reference_solution(pendulum, states, np.arange(101) * h)))
    stepper, report = pr.learn(trajs, h, structure=pendulum.base, seed=0, progress=False)
    families = [c.family for c in report.candidates]
    assert families[:3] == ["poly2", "poly3", "poly4"]
    assert report.kept.family == "poly3+trig"
    assert report.kept.one_step <= report.threshold
    assert all(c.one_step > 100 * report.kept.one_step for c in report.candidates[:3])
    assert "cos(v)" in report.hamiltonian_text
    x = np.random.default_rng(2).uniform(-1.0, 1.0, size=(20, 3))
    np.testing.assert_allclose(
        report.system.vector_field(x), pendulum.vector_field(x), rtol=0, atol=1e-5
    )
    # The Casimir r − u² − v² is kept to round-off by the learned jets stepper.
    roll = pr.integrate(stepper, states[0], h, 200)
    c = roll[:, 2] - roll[:, 0] ** 2 - roll[:, 1] ** 2
    assert np.max(np.abs(c - c[0])) < 1e-12

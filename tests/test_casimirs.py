"""Polynomial Casimirs of any Lie algebra, found as a null space: the known ones recovered
(compared as spans), none for an algebra that has none, and conservation by the Taylor integrator
on a random orbit as the independent check."""

from __future__ import annotations

import numpy as np
import pytest

import poisson_rs as pr
from poisson_rs.casimirs import (
    casimir_values,
    max_casimir_drift,
    polynomial_casimirs,
    set_casimirs,
    system_casimirs,
)
from poisson_rs.structures.lie_poisson import Polynomial


def _values(polys: list[Polynomial], mu: np.ndarray) -> np.ndarray:
    return np.stack([p(mu) for p in polys], -1)


def _same_span(found: list[Polynomial], expected: list[Polynomial], dim: int) -> None:
    """The two lists span the same space of functions: compared on 40 random points, the
    ranks of each and of both together agree."""
    mu = np.random.default_rng(7).normal(size=(40, dim))
    a, b = _values(found, mu), _values(expected, mu)
    rank = np.linalg.matrix_rank
    assert rank(a) == rank(b) == rank(np.hstack([a, b])) == len(expected)


def _quadratic(dim: int, pairs: dict[tuple[int, int], float]) -> Polynomial:
    terms: dict[tuple[int, ...], float] = {}
    for (i, j), v in pairs.items():
        e = [0] * dim
        e[i] += 1
        e[j] += 1
        terms[tuple(e)] = terms.get(tuple(e), 0.0) + v
    return Polynomial(terms)


def test_so3_casimir_is_the_squared_norm() -> None:
    found = polynomial_casimirs(pr.LieAlgebra.so3(), 4)
    assert len(found) == 1  # (|μ|²)² at degree 4 is a product, not a new one
    _same_span(found, [_quadratic(3, {(0, 0): 1, (1, 1): 1, (2, 2): 1})], 3)
    assert dict(found[0].terms) == {(2, 0, 0): 1.0, (0, 2, 0): 1.0, (0, 0, 2): 1.0}


def test_se3_casimirs_are_gamma_squared_and_m_dot_gamma() -> None:
    found = polynomial_casimirs(pr.LieAlgebra.se3(), 3)
    gamma2 = _quadratic(6, {(3, 3): 1, (4, 4): 1, (5, 5): 1})
    m_gamma = _quadratic(6, {(0, 3): 1, (1, 4): 1, (2, 5): 1})
    _same_span(found, [gamma2, m_gamma], 6)


def test_sl2_casimir() -> None:
    found = polynomial_casimirs(pr.LieAlgebra.sl2(), 4)
    _same_span(found, [_quadratic(3, {(0, 0): 1, (1, 2): 4})], 3)


def test_a_solvable_algebra_without_casimirs_has_none() -> None:
    # The "book" algebra [e3, e1] = e1, [e3, e2] = e2: its coadjoint orbits are open half
    # planes and cones, no polynomial is constant on them but the constants.
    c = np.zeros((3, 3, 3))
    c[2, 0, 0], c[0, 2, 0] = 1.0, -1.0
    c[2, 1, 1], c[1, 2, 1] = 1.0, -1.0
    book = pr.LieAlgebra(c)
    assert polynomial_casimirs(book, 4) == []
    system = pr.LiePoissonSystem(book, _quadratic(3, {(0, 0): 0.5, (1, 1): 0.5, (2, 2): 0.5}))
    assert system_casimirs(system) is None and casimir_values(system, np.ones(3)) is None
    # An unknown invariant is NaN, never a zero drift.
    assert np.isnan(max_casimir_drift(system, np.ones((2, 4, 3)))).all()


def test_found_casimirs_are_kept_by_the_taylor_integrator_on_a_random_orbit() -> None:
    # so(3) × so(3) with a cubic H (no closed form Casimir known to the package): the found
    # Casimirs |a|², |b|² are conserved by the Poisson integrator to round-off, while H is not.
    e = pr.LieAlgebra.so3().c
    c = np.zeros((6, 6, 6))
    c[:3, :3, :3] = e
    c[3:, 3:, 3:] = e
    algebra = pr.LieAlgebra(c)
    h = Polynomial({(2, 0, 0, 0, 0, 0): 0.5, (0, 0, 0, 0, 2, 0): 0.7, (1, 0, 0, 1, 1, 0): 0.3})
    system = pr.LiePoissonSystem(algebra, h)
    assert system.casimirs(np.ones(6)) is None  # not known in closed form
    found = polynomial_casimirs(algebra, 3)
    assert len(found) == 2
    mu0 = np.random.default_rng(3).normal(size=(4, 6))
    traj = pr.integrate(pr.taylor_integrator(system, 3, "exp"), mu0, 0.05, 200)
    drift = max_casimir_drift(system, traj)
    assert np.nanmax(drift) < 1e-12
    energy = np.abs(system.hamiltonian(traj) - system.hamiltonian(mu0)[:, None])
    assert energy.max() > 1e3 * np.nanmax(drift) * np.abs(system.hamiltonian(mu0)).max()


def test_a_user_passes_their_own_casimirs_and_wrong_ones_are_refused() -> None:
    c = np.zeros((2, 2, 2))
    c[0, 1, 1], c[1, 0, 1] = 1.0, -1.0  # [e1, e2] = e2: no polynomial Casimir
    algebra = pr.LieAlgebra(c)
    with pytest.raises(ValueError, match="not a Casimir"):
        set_casimirs(algebra, [_quadratic(2, {(0, 0): 1.0})])
    with pytest.raises(ValueError, match="max_degree"):
        polynomial_casimirs(algebra, 0)
    with pytest.raises(TypeError):
        polynomial_casimirs(c, 2)  # type: ignore[arg-type]
    # The abelian algebra: every function is a Casimir; the user chooses the one to record.
    flat = pr.LieAlgebra(np.zeros((2, 2, 2)))
    set_casimirs(flat, [_quadratic(2, {(0, 1): 1.0})])
    system = pr.LiePoissonSystem(flat, _quadratic(2, {(0, 0): 1.0}))
    np.testing.assert_allclose(casimir_values(system, np.array([2.0, 3.0])), [6.0])


def test_found_casimirs_are_named_by_their_formula() -> None:
    # so(3) ⊕ R: the search finds μ₄ and μ₁² + μ₂² + μ₃²; the label says which, not how many.
    c = np.zeros((4, 4, 4))
    c[:3, :3, :3] = pr.LieAlgebra.so3().c
    system = pr.LiePoissonSystem(pr.LieAlgebra(c), Polynomial({(2, 0, 0, 0): 1.0}))
    assert len(system.found_casimirs()) == 2
    assert system.casimir_label == "C = μ₄, μ₁² + μ₂² + μ₃²"
    assert "found" not in system.casimir_label


def test_a_polynomial_prints_as_its_formula() -> None:
    p = Polynomial({(1, 1, 0): -2.0, (0, 0, 2): 0.25, (0, 0, 0): 3.0, (2, 0, 0): 1.0})
    assert p.formula() == "3 + μ₁² − 2 μ₁μ₂ + 0.25 μ₃²"
    assert p.formula(("a", "b", "c")) == "3 + a² − 2 ab + 0.25 c²"
    assert Polynomial({(0, 0): 0.0}).formula() == "0"
    assert Polynomial({(0, 1): -1.0}).formula() == "−μ₂"

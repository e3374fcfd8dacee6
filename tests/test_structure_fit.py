"""The sparsity of H fitted through a structure's own integrator
(:mod:`poisson_rs.learn.structure_fit`): the information-criterion pruning on its own, and on
noisy records of a known H."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from poisson_rs.learn.data import prepare
from poisson_rs.learn.structure_fit import bic_support, fit_structure_hamiltonian
from poisson_rs.scenes import load_scene

SCENES = Path(__file__).resolve().parents[1] / "scenes"


def _linear_problem(seed: int, noise: float, near: float) -> tuple[np.ndarray, np.ndarray, list]:
    """A least-squares problem J θ ≈ b with 3 true terms of 12; column 11 is column 0 plus
    ``near`` times noise (a term the records barely tell from a true one). Returns J, b and the
    true support."""
    rng = np.random.default_rng(seed)
    jac = rng.normal(size=(400, 12))
    jac[:, 11] = jac[:, 0] + near * rng.normal(size=400)
    theta = np.zeros(12)
    theta[[0, 4, 7]] = [1.0, -0.5, 0.25]
    b = jac @ theta + noise * rng.normal(size=400)
    return jac, b, [0, 4, 7]


def _full_fit(jac: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    theta, *_ = np.linalg.lstsq(jac, b, rcond=None)
    return theta, jac @ theta - b


def test_bic_keeps_the_true_terms_and_drops_what_fits_the_noise() -> None:
    """Over 40 seeded problems (9 spurious terms each, one a near twin of a true term, all
    nonzero in the full fit): every true term kept every time, and of the 360 spurious ones
    no more than chance keeps (a χ²₁ tail beyond log N = 6.0: 1.4 % a term, 5 expected)."""
    spurious = 0
    for seed in range(40):
        jac, b, true = _linear_problem(seed, noise=1e-3, near=1e-3)
        theta, residual = _full_fit(jac, b)
        assert np.all(theta != 0)
        kept = bic_support(jac, residual, theta, list(range(12)))
        assert set(true) <= set(kept), (seed, kept)
        spurious += len(kept) - len(true)
    assert spurious <= 10, spurious


def test_bic_never_drops_a_true_term_of_exact_data() -> None:
    jac, b, true = _linear_problem(1, noise=0.0, near=1e-1)
    theta, residual = _full_fit(jac, b)
    kept = bic_support(jac, residual, theta, list(range(12)))
    assert set(true) <= set(kept)


def test_bic_starts_from_the_given_terms() -> None:
    jac, b, _ = _linear_problem(2, noise=1e-3, near=1e-3)
    theta, residual = _full_fit(jac, b)
    kept = bic_support(jac, residual, theta, [0, 3, 4, 7])
    assert kept == [0, 4, 7]
    # Fewer records than terms: nothing to choose from, the start comes back.
    assert bic_support(jac[:3], residual[:3], theta, [0, 1, 2, 3]) == [0, 1, 2, 3]


def test_noisy_records_give_back_h_up_to_its_casimir_gauge() -> None:
    """The shipped extended pendulum, H = ½u² + ½v² − v⁴/24 on {u, v} = −1, {u, r} = −2v,
    {v, r} = 2u (Casimir C = r − u² − v²), from 6 trajectories with noise 1e-4·|z| on every
    record. Of the 34 terms of degree ≤ 4, all of them fit the noise without the pruning; with
    it the fit keeps the 3 true terms and those of C and C² (the gauge: the least-norm H), and
    the learned H is the true one plus a·C + b·C² to 1e-3."""
    system = load_scene(SCENES / "extended_pendulum.toml").system
    rng = np.random.default_rng(0)
    points = np.array([[0.8, -0.5, 2.0], [0.0, 1.0, 0.5], [1.2, 0.3, 1.0]])
    starts = points[rng.integers(3, size=6)] + 0.1 * rng.normal(size=(6, 3))
    trajs = np.asarray(system.reference_solution(starts, np.arange(41) * 0.1))
    noisy = trajs + 1e-4 * np.linalg.norm(trajs, axis=-1, keepdims=True) * rng.normal(
        size=trajs.shape
    )
    data = prepare(list(noisy), 0.1, None, test_fraction=0.2, seed=0, system=system)
    dense = fit_structure_hamiltonian(data, system, 4, order=3, sparse=False)
    assert dense.n_parameters > 20
    fit = fit_structure_hamiltonian(data, system, 4, order=3)
    kept = {e for e, c in zip(fit.family.exponents, fit.theta, strict=True) if c != 0}
    true = {(2, 0, 0), (0, 2, 0), (0, 4, 0)}
    gauge = {(0, 0, 1), (0, 0, 2), (2, 0, 1), (0, 2, 1), (4, 0, 0), (2, 2, 0)}
    assert kept == true | gauge, kept

    def h(coef: dict, z: np.ndarray) -> np.ndarray:
        return sum(c * np.prod(z**e, axis=1) for e, c in coef.items())

    z = points[rng.integers(3, size=200)] + 0.3 * rng.normal(size=(200, 3))
    learned = h(dict(zip(fit.family.exponents, fit.theta, strict=True)), z)
    want = h({(2, 0, 0): 0.5, (0, 2, 0): 0.5, (0, 4, 0): -1.0 / 24.0}, z)
    casimir = z[:, 2] - z[:, 0] ** 2 - z[:, 1] ** 2
    basis = np.column_stack([np.ones(200), casimir, casimir**2])
    ab, *_ = np.linalg.lstsq(basis, learned - want, rcond=None)
    assert np.max(np.abs(learned - want - basis @ ab)) < 1e-3 * np.max(np.abs(want))

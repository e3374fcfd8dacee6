"""A Hamiltonian with a network in it, fitted through the implicit midpoint rule
(poisson_rs.learn.mlp_hamiltonian): its expression, the fit on data the rule itself made, a
non-polynomial H against the true H through the same rule, the Casimir, pr.learn's use of it,
and bad input."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch

import poisson_rs as pr
from poisson_rs.expressions import Expression, default_names
from poisson_rs.learn.data import prepare
from poisson_rs.learn.mlp_hamiltonian import (
    MlpConfig,
    MlpFamily,
    fit_mlp_hamiltonian,
    mlp_expression,
    mlp_family,
)
from poisson_rs.learn.scoring import errors
from poisson_rs.scenes import load_scene

BUMP_H = "u**2/2 + v**2/2 + u*(r - u**2 - v**2) + 0.3/(1 + v**2)"


@pytest.fixture(scope="module")
def bracket() -> Any:
    return load_scene("scenes/extended_pendulum_pnn.toml").system.base


def _states(n: int, seed: int) -> np.ndarray:
    x0 = np.random.default_rng(seed).uniform(-0.8, 0.8, size=(n, 3))
    x0[:, 2] += 1.0
    return x0


def test_the_expression_is_the_network_it_was_written_from() -> None:
    rng = np.random.default_rng(0)
    exps = [(1, 0, 0), (0, 2, 0), (1, 1, 1)]
    c, w, b, a = rng.normal(size=3), rng.normal(size=(4, 3)), rng.normal(size=4), rng.normal(size=4)
    center, scale = rng.normal(size=3), rng.uniform(0.5, 2.0, size=3)
    h = Expression(mlp_expression(exps, c, w, b, a, center, scale), default_names(3))
    x = rng.normal(size=(50, 3))
    want = (
        c[0] * x[:, 0] + c[1] * x[:, 1] ** 2 + c[2] * x.prod(1)
        + np.tanh(((x - center) / scale) @ w.T + b) @ a
    )  # fmt: skip
    assert np.abs(h(x) - want).max() < 1e-12


def test_data_the_midpoint_rule_made_from_an_h_in_the_family_are_reproduced(bracket: Any) -> None:
    """A cubic H is in the family (network output zero): on records the midpoint rule itself
    made, the rule's defect vanishes at the true H, and the fit finds it."""
    s = pr.with_hamiltonian(bracket, "u**2/2 + v**2/2 + u*(r - u**2 - v**2)")
    mid = pr.classical(s, "midpoint", tol=1e-14, max_iter=50)
    trajs = pr.integrate(mid, _states(6, 1), 0.1, 40)
    torch.set_num_threads(1)
    data = prepare(trajs, 0.1, None, test_fraction=0.2, seed=0, system=bracket)
    fit = fit_mlp_hamiltonian(
        data, bracket, family=MlpFamily(bracket, 4, 3), config=MlpConfig(iterations=300)
    )
    assert fit.history[-1] < 1e-14 * fit.history[0]
    one, roll = errors(fit.stepper, data)
    assert one < 1e-9 and roll < 1e-7


def test_a_non_polynomial_h_is_fitted_to_the_rules_own_limit(bracket: Any) -> None:
    """Exact records of H with 0.3/(1 + v²): the fitted H through the midpoint rule comes
    within 3× of the true H through the same rule on held-out data, where the polynomial part
    alone (no network) is 10× further off; the quadratic Casimir r − u² − v² is kept."""
    s = pr.with_hamiltonian(bracket, BUMP_H)
    trajs = s.reference(_states(10, 0), np.arange(101) * 0.1)
    torch.set_num_threads(1)
    data = prepare(trajs, 0.1, None, test_fraction=0.2, seed=0, system=bracket)
    truth, _ = errors(pr.classical(s, "midpoint"), data)
    cfg = MlpConfig(iterations=2000, lbfgs_iterations=500)
    fit = fit_mlp_hamiltonian(data, bracket, family=MlpFamily(bracket, 8, 3), config=cfg)
    bare = fit_mlp_hamiltonian(data, bracket, family=MlpFamily(bracket, 0, 3), config=cfg)
    one, _ = errors(fit.stepper, data)
    alone, _ = errors(bare.stepper, data)
    assert one < 3 * truth and alone > 10 * one, (truth, one, alone)
    roll = pr.integrate(fit.stepper, data.test[0][0], 0.1, 100)
    c = bracket.casimirs(roll)
    assert np.abs(c - c[0]).max() < 1e-12 * max(1.0, np.abs(c[0]).max())


def test_pr_learn_tries_it_last_and_reports_it(bracket: Any) -> None:
    """With max_degree 1 no polynomial or library explains the data; the network family is
    tried last, reported with its parameters, and kept as the best."""
    s = pr.with_hamiltonian(bracket, BUMP_H)
    trajs = s.reference(_states(6, 3), np.arange(41) * 0.1)
    torch.set_num_threads(1)
    _, report = pr.learn(trajs, 0.1, structure=bracket, max_degree=1, progress=False)
    families = [c.family for c in report.candidates]
    assert families[-1] == "poly1+mlp8" and report.kept.family == "poly1+mlp8"
    assert report.kept.one_step < 0.3 * min(c.one_step for c in report.candidates[:-1])
    assert report.kept.parameters == 3 + 8 * 5
    assert "no refit" in report.kept.reason and "tanh" in report.kept.hamiltonian_text


def test_an_h_beyond_the_expression_limits_is_not_tried_and_bad_sizes_are_refused(
    bracket: Any,
) -> None:
    # In 3-D, 48 units beside a cubic fit the expression limits (1024 instructions); 49 do not.
    assert MlpFamily(bracket, 48, 3).writable()
    assert not MlpFamily(bracket, 49, 3).writable()
    # Every weight negative is the costliest text (a negation each): it must still parse.
    rng = np.random.default_rng(4)
    fam = MlpFamily(bracket, 8, 3)
    m = len(fam.exponents)
    text = mlp_expression(
        fam.exponents, -rng.uniform(1, 2, m), -rng.uniform(1, 2, (8, 3)), -rng.uniform(1, 2, 8),
        -rng.uniform(1, 2, 8), np.zeros(3), np.ones(3),
    )  # fmt: skip
    Expression(text, default_names(3))
    # In 8-D a cubic beside 8 units does not fit: pr.learn's family is made smaller.
    four = load_scene("scenes/point_vortices_4.toml").system.base
    chosen = mlp_family(four, 4)
    assert chosen is not None and chosen.writable()
    assert (chosen.degree, chosen.width) == (2, 8)
    assert mlp_family(load_scene("scenes/charged_particle_pnn.toml").system, 4).degree == 3
    for width in (-1, 65, True, 2.0):
        with pytest.raises(ValueError, match="width"):
            MlpFamily(bracket, width)
    with pytest.raises(ValueError, match="degree"):
        MlpFamily(bracket, 8, 5)

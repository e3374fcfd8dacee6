"""The shipped learned heavy-top model against independent oracles: its own Taylor terms and a
DOP853 reference on held-out states (the claim in docs/heavy_top.md), the torch step map, torch
autograd for the derivatives, and the Casimirs |Γ|², M·Γ (kept to round-off by a Poisson map)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import assert_step_and_derivatives_match_torch

import poisson_rs as pr

NAME = "heavy_top_h05"
TOP = pr.HeavyTop()


def held_out(seed: int, n: int) -> np.ndarray:
    """n states (M, Γ): M uniform in [−1.2, 1.2]³, Γ a random unit vector (the scene's law;
    training never saw these: it draws from the whole top domain with its own seeds)."""
    rng = np.random.default_rng(seed)
    m = rng.uniform(-1.2, 1.2, (n, 3))
    g = rng.normal(size=(n, 3))
    return np.hstack([m, g / np.linalg.norm(g, axis=1, keepdims=True)])


def held_out_inside(seed: int, n: int, half_width: float) -> np.ndarray:
    """The first n of ``held_out(seed, 8n)`` whose exact orbit keeps |Mᵢ| ≤ half_width up to
    T = 10 (201 times): states whose whole run lies in the model's domain."""
    cand = held_out(seed, 8 * n)
    orbits = pr.reference_solution(TOP, cand, np.linspace(0.0, 10.0, 201))
    inside = np.abs(orbits[..., :3]).max(axis=(1, 2)) <= half_width
    assert inside.sum() >= n
    return cand[inside][:n]


@pytest.fixture(scope="module")
def model() -> pr.LearnedIntegrator:
    return pr.load_model(NAME)


def test_it_is_a_heavy_top_model_with_its_record(model: pr.LearnedIntegrator) -> None:
    assert NAME in pr.list_models()
    assert model.system == TOP and model.dim == 6 and model.chart == "exp"
    assert model.domain["kind"] == "top"
    meta = model.metadata
    assert meta["h_max"] == 0.5 and meta["seed"] == 0 and meta["train_seconds"] > 0
    assert "poisson-rs train" in meta["command"] and "--system heavy-top" in meta["command"]


def test_ten_times_below_its_taylor_terms_on_held_out_states(
    model: pr.LearnedIntegrator,
) -> None:
    """At its h = 0.5 to T = 10, median over 8 held-out states in its domain, against DOP853
    (rtol 1e-13); the same states as ``benches/heavy_top_learned.py``."""
    mu0 = held_out_inside(123, 8, model.domain["half_width"])
    ref = pr.reference_solution(TOP, mu0, np.array([0.0, 10.0]))[:, -1]
    norm = np.linalg.norm(mu0, axis=1)
    traj, info = pr.integrate(model, mu0, 0.5, 20, return_info=True)
    assert info.converged.all() and not info.out_of_domain.any()
    err = np.linalg.norm(traj[:, -1] - ref, axis=1) / norm
    base = pr.taylor_integrator(TOP, int(model.metadata["taylor_order"]), "exp")
    err_base = np.linalg.norm(pr.integrate(base, mu0, 0.5, 20)[:, -1] - ref, axis=1) / norm
    assert np.median(err_base) / np.median(err) >= 10.0, (np.median(err), np.median(err_base))


def test_rust_and_torch_step_maps_agree(model: pr.LearnedIntegrator) -> None:
    mu = held_out(7, 16)
    for h in (0.5, 0.2):
        assert_step_and_derivatives_match_torch(model, mu, h)


# One of the four orbits leaves |Mᵢ| ≤ 2 before T = 200: the Casimirs are kept by any S, so the
# model's extrapolation warning says nothing about this check.
@pytest.mark.filterwarnings("ignore:LearnedIntegrator 'heavy_top_h05'.*training domain")
def test_casimirs_are_kept_to_round_off(model: pr.LearnedIntegrator) -> None:
    """Full Newton: round-off. The default simplified Newton stops at a relative update of
    tol = 1e-12 with a stale Jacobian, and each step then leaves ~4e-14 in the Casimirs."""
    mu0 = held_out(11, 4)
    for newton, bound in (("full", 1e-13), ("simplified", 400 * 1e-12)):
        traj = pr.integrate(pr.load_model(NAME, newton=newton), mu0, 0.5, 400)  # T = 200
        c = TOP.casimirs(traj)
        drift = np.abs(c - c[:, :1]).max()
        assert drift < bound, (newton, drift)
        # The energy error stays bounded (no drift) over the same run: a Poisson map's way.
        h = TOP.hamiltonian(traj)
        assert np.abs(h - h[:, :1]).max() < 1e-2
    assert model.batch > 1  # the default is the simplified Newton (a batched model)


def test_it_refuses_steps_beyond_its_training(model: pr.LearnedIntegrator) -> None:
    with pytest.raises(ValueError, match="exceeds h_max"):
        pr.integrate(model, held_out(1, 1), 0.6, 2)
    with pytest.raises(ValueError, match=r"mu0 must have shape \(6,\) or \(n, 6\)"):
        pr.integrate(model, np.ones((1, 3)), 0.1, 1)

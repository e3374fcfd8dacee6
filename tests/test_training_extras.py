"""Training extras: L-BFGS polishing after Adam, and a data term on the model's one-step map."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from conftest import random_states

import poisson_rs as pr
from poisson_rs.integrators import BisectionIntegrator, integrate
from poisson_rs.structures.lie_poisson import RigidBody
from poisson_rs.structures.lie_poisson_reference import exact_solution
from poisson_rs.train import (
    TrainConfig,
    data_from_exact,
    data_loss,
    export_bytes,
    save_result,
    step_map,
    train,
)

H = 0.1


def _tiny(**overrides: Any) -> TrainConfig:
    """A configuration small enough to train in about a second."""
    base: dict[str, Any] = {"widths": (8,), "batch": 256, "iterations": 60, "lr": 1e-2, "seed": 7}
    base.update(overrides)
    return TrainConfig(**base)


def _pairs(n: int = 48, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """n exact one-step pairs at h = 0.1 from states in the training shell 1 ≤ |μ| ≤ 4."""
    states = random_states(np.random.default_rng(seed), n, 1.2, 3.8)
    return data_from_exact(RigidBody((1.5, 2.0, 2.5)), states, H)


def _t(a: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(a, dtype=torch.float64)


def test_lbfgs_lowers_the_validation_residual_after_adam():
    adam = train(_tiny(), progress=False, log_every=1)
    polished = train(_tiny(lbfgs_iterations=30), progress=False, log_every=1)
    # The Adam phase is untouched; polishing comes after it.
    assert polished.losses == adam.losses and polished.iterations_run == adam.iterations_run
    assert 0 < polished.lbfgs_iterations_run <= 30
    assert len(polished.lbfgs_losses) >= polished.lbfgs_iterations_run
    assert np.isfinite(polished.lbfgs_losses).all()
    assert polished.validation_rms < 0.5 * adam.validation_rms, (
        f"{adam.validation_rms:.3e} -> {polished.validation_rms:.3e}"
    )
    assert adam.lbfgs_iterations_run == 0 and adam.lbfgs_losses == []
    # The reported final loss is the polished one, not Adam's last.
    assert adam.final_loss == adam.losses[-1]
    assert polished.final_loss == polished.lbfgs_losses[-1] < adam.final_loss


def test_new_fields_are_recorded_in_the_model_file(tmp_path: Path):
    result = train(_tiny(iterations=5, lbfgs_iterations=2), progress=False)
    path = save_result(result, tmp_path / "m.safetensors", name="m", command="-")
    meta = pr.load_model(path).metadata
    config = json.loads(meta["config"])
    assert config["lbfgs_iterations"] == 2 and config["data_weight"] == 0.0
    assert meta["final_loss"] == result.lbfgs_losses[-1]


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        ({"lbfgs_iterations": -1}, "lbfgs_iterations"),
        ({"lbfgs_iterations": 2.5}, "lbfgs_iterations"),
        ({"data_weight": -1.0}, "data_weight"),
        ({"data_weight": float("nan")}, "data_weight"),
        ({"data_points": -1}, "data_points"),
        ({"data_h": 0.0}, "data_h"),
        ({"data_points": 10}, "data_weight"),  # pairs without a weight would be unused
        ({"data_weight": 1.0}, "data_points"),  # a weight without pairs
    ],
    ids=lambda v: "-".join(f"{k}={x}" for k, x in v.items()) if isinstance(v, dict) else None,
)
def test_new_fields_are_validated(overrides: dict[str, Any], match: str):
    with pytest.raises(ValueError, match=match):
        train(_tiny(**overrides), progress=False)


def test_train_checks_user_data():
    mu_k, mu_k1 = _pairs(4)
    with pytest.raises(ValueError, match="not both"):
        train(_tiny(data_weight=1.0, data_points=4), data=(mu_k, mu_k1), progress=False)
    with pytest.raises(ValueError, match="data_weight"):
        train(_tiny(), data=(mu_k, mu_k1), progress=False)
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        train(_tiny(data_weight=1.0), data=(mu_k, mu_k1[:3]), progress=False)
    bad = mu_k1.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        train(_tiny(data_weight=1.0), data=(mu_k, bad), progress=False)


def test_data_from_exact_follows_the_exact_flow():
    states = random_states(np.random.default_rng(1), 3, 1.0, 3.0)
    mu_k, mu_k1 = data_from_exact(RigidBody((1.5, 2.0, 2.5)), states, H, n_steps=4)
    assert mu_k.shape == mu_k1.shape == (12, 3)
    want = exact_solution(RigidBody((1.5, 2.0, 2.5)), states, H * np.arange(5))
    np.testing.assert_array_equal(mu_k.reshape(3, 4, 3), want[:, :-1])
    np.testing.assert_array_equal(mu_k1.reshape(3, 4, 3), want[:, 1:])


def test_data_loss_vanishes_on_the_models_own_steps_only():
    cfg = _tiny(iterations=10)
    model = train(cfg, progress=False).model
    states = random_states(np.random.default_rng(2), 16, 1.2, 3.8)
    traj = integrate(BisectionIntegrator(export_bytes(model, cfg)), states, H, 3)  # (16, 4, 3)
    own = (_t(traj[:, :-1].reshape(-1, 3)), _t(traj[:, 1:].reshape(-1, 3)))
    assert float(data_loss(model, *own, H).detach()) < 1e-24
    # The torch step map is the Rust one.
    out, ok = step_map(model, own[0], H)
    assert bool(ok.all())
    np.testing.assert_allclose(out.detach().numpy(), own[1].numpy(), rtol=0, atol=1e-12)
    # Exact pairs are not the model's steps: its one-step error shows.
    exact = tuple(_t(a) for a in _pairs())
    assert float(data_loss(model, *exact, H).detach()) > 1e-14


def test_the_data_loss_has_a_gradient_in_the_weights():
    model = train(_tiny(iterations=5), progress=False).model
    data_loss(model, *(_t(a) for a in _pairs(8)), H).backward()
    grads = [p.grad for p in model.mlp.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert any(float(g.abs().max()) > 0 for g in grads if g is not None)


def test_training_with_data_lowers_the_data_loss():
    pairs = _pairs()
    tensors = tuple(_t(a) for a in pairs)
    hj_only = train(_tiny(), progress=False)
    # Adam alone moves the data term slowly in 60 iterations; L-BFGS brings it down 10×.
    with_data = train(_tiny(data_weight=10.0, lbfgs_iterations=20), data=pairs, progress=False)
    before = float(data_loss(hj_only.model, *tensors, H).detach().sqrt())
    assert with_data.data_rms == pytest.approx(
        float(data_loss(with_data.model, *tensors, H).detach().sqrt()), rel=1e-9
    )
    assert with_data.data_rms < 0.3 * before, f"{before:.3e} -> {with_data.data_rms:.3e}"
    assert np.isnan(hj_only.data_rms)


def test_the_step_maps_weight_gradient_matches_finite_differences():
    # The map's derivative in the weights includes how the Newton solution p moves with them.
    model = train(_tiny(iterations=5), progress=False).model
    with torch.no_grad():
        model.output_scale *= 1000.0  # let the network move the step visibly
    mu = torch.tensor([[1.0, 1.0, 2.0], [3.0, 2.0, 0.5]], dtype=torch.float64)
    w = model.mlp[0].weight
    d = torch.randn(w.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    out, _ = step_map(model, mu, H)
    grad = torch.autograd.grad(out, w, grad_outputs=torch.ones_like(out))[0]
    eps = 1e-6
    with torch.no_grad():
        w += eps * d
        plus = step_map(model, mu, H)[0].sum()
        w -= 2 * eps * d
        minus = step_map(model, mu, H)[0].sum()
        w += eps * d
    fd = float(plus - minus) / (2 * eps)
    assert float((grad * d).sum()) == pytest.approx(fd, rel=1e-5, abs=1e-9)

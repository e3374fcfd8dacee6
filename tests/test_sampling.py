"""Training points weighted towards a scene: a configured share of each batch lies on (or near)
the exact orbits of the scene's states, the rest stays uniform; bad settings are refused."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from poisson_rs import RigidBody, exact_solution, load_model
from poisson_rs.cli import main
from poisson_rs.scenes import derive_config, parse_scene
from poisson_rs.train import TrainConfig, sample_points, save_result, train

STATES = ((1.0, 1.0, 2.0), (3.0, 2.0, 0.0))


def _scene_cfg(**overrides: Any) -> TrainConfig:
    base: dict[str, Any] = {"sampling": "scene", "sampling_states": STATES}
    base.update(overrides)
    return TrainConfig(**base)


def _draw(cfg: TrainConfig, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    t, p = sample_points(cfg, n, torch.Generator().manual_seed(seed), torch.float64, "cpu")
    return t.numpy(), p.numpy()


def _on_orbit(p: np.ndarray, body: RigidBody) -> np.ndarray:
    """Whether each point shares |μ|² and H (to rounding) with one of STATES: (n,) bool. Both are
    kept by the exact flow, and a uniform point matches neither with probability 0."""
    c, e = body.casimir(p), body.hamiltonian(p)
    hit = np.zeros(len(p), bool)
    for mu in np.asarray(STATES):
        c0, e0 = body.casimir(mu), body.hamiltonian(mu)
        hit |= (np.abs(c - c0) <= 1e-12 * c0) & (np.abs(e - e0) <= 1e-12 * e0)
    return hit


@pytest.mark.parametrize("fraction", [0.25, 0.5, 1.0])
def test_a_fraction_of_each_batch_lies_on_the_orbits(fraction: float):
    cfg = _scene_cfg(sampling_fraction=fraction, sampling_noise=0.0)
    cfg.validate()
    n = 1001
    t, p = _draw(cfg, n)
    assert t.shape == (n,) and p.shape == (n, 3)
    assert (t >= 0).all() and (t <= cfg.h_max).all()
    assert _on_orbit(p, RigidBody(cfg.inertia)).sum() == round(fraction * n)


def test_fraction_zero_draws_exactly_the_uniform_points():
    _, uniform = _draw(TrainConfig(), 512, seed=3)
    _, scene = _draw(_scene_cfg(sampling_fraction=0.0), 512, seed=3)
    np.testing.assert_array_equal(uniform, scene)


def test_orbit_points_follow_the_flow_up_to_the_horizon():
    # A horizon of 1e-9: every orbit point is its initial state (the flow barely moves).
    cfg = _scene_cfg(sampling_fraction=1.0, sampling_noise=0.0, sampling_horizon=1e-9)
    _, p = _draw(cfg, 200)
    dist = np.min(np.linalg.norm(p[:, None, :] - np.asarray(STATES)[None], axis=-1), axis=1)
    assert dist.max() < 1e-8
    # Both states are drawn.
    assert len({tuple(np.round(q, 6)) for q in p}) == 2
    # Over [0, 10] they sweep the exact arcs: every point is within rounding of one of them.
    cfg = _scene_cfg(sampling_fraction=1.0, sampling_noise=0.0, sampling_horizon=10.0)
    _, p = _draw(cfg, 50)
    arcs = exact_solution(RigidBody(cfg.inertia), STATES, np.linspace(0.0, 10.0, 2048))
    d = np.linalg.norm(p[:, None, :] - arcs.reshape(1, -1, 3), axis=-1).min(axis=1)
    assert d.max() < 1e-12


def test_noise_is_relative_to_the_orbit_radius():
    sigma = 0.03
    cfg = _scene_cfg(sampling_fraction=1.0, sampling_noise=sigma)
    _, p = _draw(cfg, 4000)
    r = np.linalg.norm(p, axis=1)
    r0 = np.linalg.norm(np.asarray(STATES), axis=1)
    # Each point's radius is near one of the two orbit radii; the radial offset is σ·|μ|·z.
    k = np.argmin(np.abs(r[:, None] - r0[None]), axis=1)
    rel = r / r0[k] - 1.0
    assert np.std(rel) == pytest.approx(sigma, rel=0.1)
    assert abs(np.mean(rel)) < 0.1 * sigma


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        ({"sampling": "orbits"}, "sampling must be one of"),
        ({"sampling": "scene"}, "needs sampling_states"),
        ({"sampling_states": STATES}, "unused"),
        ({"sampling": "scene", "sampling_states": STATES, "sampling_fraction": 1.5}, r"\[0, 1\]"),
        ({"sampling": "scene", "sampling_states": STATES, "sampling_fraction": -0.1}, r"\[0, 1\]"),
        (
            {"sampling": "scene", "sampling_states": STATES, "sampling_fraction": float("nan")},
            r"\[0, 1\]",
        ),
        ({"sampling": "scene", "sampling_states": ((0.0, 0.0, 0.0),)}, "non-zero finite"),
        ({"sampling": "scene", "sampling_states": ((1.0, 2.0),)}, "3-vectors"),
        ({"sampling": "scene", "sampling_states": ((1.0, float("inf"), 0.0),)}, "finite"),
        ({"sampling": "scene", "sampling_states": STATES, "sampling_noise": -0.1}, "noise"),
        ({"sampling": "scene", "sampling_states": STATES, "sampling_horizon": 0.0}, "horizon"),
    ],
)
def test_bad_sampling_settings_are_refused(overrides: dict[str, Any], match: str):
    with pytest.raises(ValueError, match=match):
        TrainConfig(**overrides).validate()
    with pytest.raises(ValueError, match=match):
        train(TrainConfig(**overrides), progress=False)


def test_training_with_scene_sampling_records_it(tmp_path: Path):
    cfg = _scene_cfg(widths=(4,), batch=64, iterations=5, seed=2)
    result = train(cfg, progress=False)
    assert result.iterations_run == 5 and np.isfinite(result.losses).all()
    path = save_result(result, tmp_path / "m.safetensors", name="m", command="test")
    recorded = json.loads(load_model(path).metadata["config"])
    assert recorded["sampling"] == "scene"
    assert recorded["sampling_states"] == [list(s) for s in STATES]
    # The network starts from the same weights as under uniform sampling (same init draws).
    base = train(TrainConfig(widths=(4,), batch=64, iterations=0, seed=2), progress=False)
    first = train(_scene_cfg(widths=(4,), batch=64, iterations=0, seed=2), progress=False)
    for a, b in zip(base.model.parameters(), first.model.parameters(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


_SCENE = {
    "system": {"inertia": [1.5, 2.0, 2.5]},
    "states": {"points": [[1.0, 1.0, 2.0]], "shell": {"r_min": 1.5, "r_max": 2.9, "n": 3}},
    "steps": {"h": 0.1, "horizon": 2.0},
    "target": {"error": 1e-3},
}


def test_a_scene_file_asks_for_scene_sampling_of_its_own_orbits():
    scene = parse_scene(
        {**_SCENE, "model": {"sampling": "scene", "sampling_fraction": 0.3}}, name="s"
    )
    cfg = derive_config(scene)
    assert cfg.sampling == "scene" and cfg.sampling_fraction == 0.3
    np.testing.assert_array_equal(np.asarray(cfg.sampling_states), scene.states())
    assert cfg.sampling_horizon == scene.horizon
    # Without it the scene trains uniformly, with no states recorded.
    plain = derive_config(parse_scene(_SCENE, name="s"))
    assert plain.sampling == "uniform" and plain.sampling_states == ()
    with pytest.raises(ValueError, match="model"):
        parse_scene({**_SCENE, "model": {"sampling": "near"}}, name="s")
    with pytest.raises(ValueError, match="model"):
        parse_scene({**_SCENE, "model": {"sampling": "scene", "sampling_fraction": 2}}, name="s")


def test_cli_refuses_scene_sampling_without_states(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    out = str(tmp_path / "m.safetensors")
    assert main(["train", "--sampling", "scene", "--out", out, "--no-progress"]) == 2
    assert "sampling_states" in capsys.readouterr().err
    bad = ["train", "--sampling", "scene", "--sampling-states", "1", "1", "--out", out]
    assert main(bad) == 2
    assert "3 numbers for each state" in capsys.readouterr().err
    assert main(["train", "--sampling-fraction", "2", "--out", out]) == 2
    assert not Path(out).exists()

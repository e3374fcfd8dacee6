"""Scene files: parsing and validation, the training configuration they derive, their evaluation
(checked against a direct computation), target-driven stopping, and the shipped scene models."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

import poisson_rs as pr
from poisson_rs.scenes import (
    Scene,
    TargetStop,
    derive_config,
    evaluate,
    load_scene,
    meets_target,
    parse_scene,
    train_scene,
)
from poisson_rs.train import TrainConfig, train

SCENES = Path(__file__).resolve().parents[1] / "scenes"

VALID = """
name = "small"
[system]
inertia = [1.5, 2.0, 2.5]
[states]
points = [[1.0, 1.0, 2.0], [3.0, 2.0, 0.0]]
shell = { r_min = 1.5, r_max = 2.9, n = 3, seed = 4 }
[steps]
h = [0.1, 0.2]
horizon = 2
[target]
error = 1e-3
energy = 1e-4
newton = "all"
[model]
widths = [4]
iterations = 7
margin = [0.5, 1.5]
evaluate_every = 3
"""


def _doc(**changes: Any) -> dict[str, Any]:
    """The VALID document with sections replaced (a value of None deletes the key)."""
    import tomllib

    data = tomllib.loads(VALID)
    for key, value in changes.items():
        section, _, leaf = key.partition("__")
        table = data if not leaf else data.setdefault(section, {})
        name = leaf or section
        if value is None:
            table.pop(name, None)
        else:
            table[name] = value
    return data


def test_a_scene_file_parses(tmp_path: Path):
    path = tmp_path / "s.toml"
    path.write_text(VALID)
    scene = load_scene(path)
    assert scene.name == "small" and scene.path == path
    assert scene.inertia == (1.5, 2.0, 2.5)
    assert scene.h == (0.1, 0.2) and scene.horizon == 2.0
    assert [scene.n_steps(h) for h in scene.h] == [20, 10]
    assert scene.target.error == 1e-3 and scene.target.energy == 1e-4
    assert scene.target.newton == "all"
    assert scene.model == {"widths": (4,), "iterations": 7}
    assert scene.evaluate_every == 3 and scene.margin == (0.5, 1.5)
    states = scene.states()
    assert states.shape == (5, 3)
    np.testing.assert_array_equal(states[:2], [[1, 1, 2], [3, 2, 0]])
    r = np.linalg.norm(states[2:], axis=1)
    assert ((r >= 1.5) & (r <= 2.9)).all()
    # The held-out states depend on their seed only.
    np.testing.assert_array_equal(states, load_scene(path).states())
    # Without a name the file's stem is used; a scalar h is a one-element tuple.
    data = _doc(name=None, steps__h=0.5)
    other = parse_scene(data, name="stem")
    assert other.name == "stem" and other.h == (0.5,)


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"colour": "red"}, "'colour'"),
        ({"steps__hh": 0.1}, "'steps.hh'"),
        ({"system__inertia": [1.0, 2.0]}, "'system.inertia'"),
        ({"system__inertia": [1.0, -2.0, 3.0]}, "'system.inertia'"),
        ({"system__inertia": None}, "'system.inertia'"),
        ({"states__points": [[1.0, 2.0]]}, r"'states.points\[0\]'"),
        ({"states__points": [[0.0, 0.0, 0.0]]}, r"'states.points\[0\]'"),
        ({"states__points": [[1.0, "a", 2.0]]}, r"'states.points\[0\]'"),
        ({"states__shell": {"r_min": 2.0, "r_max": 1.0, "n": 3}}, "'states.shell.r_max'"),
        ({"states__shell": {"r_min": 1.0, "r_max": 2.0, "n": 0}}, "'states.shell.n'"),
        ({"states__shell": {"r_min": 1.0, "r_max": 2.0}}, "'states.shell.n'"),
        ({"states__shell": {"r_min": 1.0, "r_max": 2.0, "n": 2, "m": 1}}, "'states.shell.m'"),
        ({"states": {}}, "'states'"),
        ({"steps__h": None}, "'steps.h'"),
        ({"steps__h": -0.1}, "'steps.h'"),
        ({"steps__h": []}, "'steps.h'"),
        ({"steps__h": True}, "'steps.h'"),
        ({"steps__horizon": 1.05}, "'steps.horizon'"),
        ({"target": {}}, "'target'"),
        ({"target__newton": "most"}, "'target.newton'"),
        ({"target__error": 0.0}, "'target.error'"),
        ({"target__energy": "small"}, "'target.energy'"),
        ({"model__depth": 3}, "'model.depth'"),
        ({"model__widths": 8}, "'model.widths'"),
        ({"model__widths": [8, 0]}, "'model.widths'"),
        ({"model__chart": "quaternion"}, "'model'.*chart"),
        ({"model__lr": -1.0}, "'model'.*lr"),
        ({"model__margin": [1.1, 1.2]}, "'model.margin'"),
        ({"model__evaluate_every": 0}, "'model.evaluate_every'"),
        ({"name": ""}, "'name'"),
    ],
    ids=lambda v: ",".join(v) if isinstance(v, dict) else None,
)
def test_bad_scenes_raise_naming_the_key(changes: dict[str, Any], match: str):
    with pytest.raises(ValueError, match=match):
        parse_scene(_doc(**changes), name="bad")


def test_files_that_are_not_toml_are_refused(tmp_path: Path):
    path = tmp_path / "broken.toml"
    path.write_text("[system\ninertia = 1")
    with pytest.raises(ValueError, match="not valid TOML"):
        load_scene(path)
    with pytest.raises(FileNotFoundError):
        load_scene(tmp_path / "missing.toml")


def test_derive_config_covers_the_states_visited():
    scene = parse_scene(_doc(), name="small")
    cfg = derive_config(scene)
    r = np.linalg.norm(scene.states(), axis=1)
    assert cfg.domain == "shell"
    assert cfg.r_min == pytest.approx(0.5 * r.min()) and cfg.r_max == pytest.approx(1.5 * r.max())
    assert cfg.h_max == 0.2 and cfg.inertia == scene.inertia
    assert cfg.widths == (4,) and cfg.iterations == 7
    # Keyword overrides win over the scene's [model]; the default margin is 0.8 / 1.2.
    cfg = derive_config(parse_scene(_doc(model=None), name="s"), iterations=3, seed=5)
    assert (cfg.iterations, cfg.seed) == (3, 5)
    assert cfg.r_min == pytest.approx(0.8 * r.min()) and cfg.r_max == pytest.approx(1.2 * r.max())
    # A scene whose [model] picks a cube keeps it.
    cube = derive_config(parse_scene(_doc(model={"domain": "cube"}), name="c"))
    assert cube.domain == "cube" and cube.domain_dict()["kind"] == "cube"


def test_evaluate_matches_a_direct_computation():
    scene = parse_scene(_doc(), name="small")
    body = scene.body
    taylor = pr.taylor_integrator(body, 3, "cayley")
    result = evaluate(taylor, scene)
    mu0 = scene.states()
    exact = pr.exact_solution(body, mu0, [scene.horizon])[:, 0]
    errors, energies = [], []
    for h, row in zip(scene.h, result["per_h"], strict=True):
        traj = pr.integrate(taylor, mu0, h, scene.n_steps(h))
        err = np.linalg.norm(traj[:, -1] - exact, axis=1)
        e = body.hamiltonian(traj)
        dh = np.max(np.abs(e - e[:, :1]), axis=1) / e[:, 0]
        np.testing.assert_allclose(row["error"], err, rtol=1e-12)
        np.testing.assert_allclose(row["energy"], dh, rtol=1e-12)
        assert row["n_steps"] == round(2.0 / h) and all(row["converged"])
        errors.append(err.max())
        energies.append(dh.max())
    assert result["error"] == pytest.approx(max(errors), rel=1e-12)
    assert result["energy"] == pytest.approx(max(energies), rel=1e-12)
    assert result["converged"] and result["n_failed"] == 0
    assert result["casimir"] < 1e-12
    # The thresholds are compared with the measured numbers.
    loose = parse_scene(_doc(target={"error": 2 * max(errors)}), name="s")
    tight = parse_scene(_doc(target={"error": 0.5 * max(errors)}), name="s")
    assert meets_target(result, loose) and not meets_target(result, tight)
    assert result["target_met"] == meets_target(result, scene)
    json.dumps(result)  # JSON-able, to be stored in model metadata


def test_evaluate_reports_newton_failures_as_infinite_errors():
    # At h = 3 the exponential chart's |x| = h|I⁻¹μ| passes its singularity from (3, 2, 0).
    data = _doc(
        steps={"h": 3.0, "horizon": 3.0},
        states={"points": [[3.0, 2.0, 0.0]]},
        target={"error": 1e9},
    )
    scene = parse_scene(data, name="huge")
    result = evaluate(pr.taylor_integrator(scene.body, 1, "exp"), scene)
    assert not result["converged"] and result["n_failed"] == 1
    assert math.isinf(result["error"]) and not result["target_met"]


def test_evaluate_refuses_a_model_for_another_body():
    scene = parse_scene(_doc(system={"inertia": [1.0, 2.0, 3.0]}), name="other")
    with pytest.raises(ValueError, match="inertia"):
        evaluate(pr.taylor_integrator(pr.RigidBody((1.5, 2.0, 2.5)), 3), scene)


def _easy_scene(error: float) -> Scene:
    data = _doc(
        steps={"h": 0.1, "horizon": 1.0},
        target={"error": error},
        model={"widths": [4], "batch": 64, "iterations": 200, "lr": 1e-2, "seed": 3},
    )
    data["model"]["evaluate_every"] = 10
    return parse_scene(data, name="easy")


def test_target_driven_training_stops_once_the_target_is_met():
    # Taylor K=3 plus a tiny network is far inside error 1e-2 from the start: the first rollout
    # (after 10 of 200 iterations) meets the target and ends training.
    scene = _easy_scene(1e-2)
    cfg = derive_config(scene)
    stopper = TargetStop(scene, cfg)
    result = train(cfg, progress=False, evaluate_every=scene.evaluate_every, stop=stopper)
    assert result.stopped_early and result.iterations_run == 10
    assert [row["iteration"] for row in stopper.history] == [10]
    assert stopper.history[0]["target_met"] and stopper.history[0]["error"] <= 1e-2
    # An unreachable target runs every iteration, rolling out every 10 and after the last one.
    cfg = derive_config(_easy_scene(1e-15), iterations=25)
    never = TargetStop(_easy_scene(1e-15), cfg)
    full = train(cfg, progress=False, evaluate_every=10, stop=never)
    assert not full.stopped_early and full.iterations_run == 25
    assert [row["iteration"] for row in never.history] == [10, 20, 25]
    assert not any(row["target_met"] for row in never.history)


def test_a_stop_that_never_fires_leaves_training_unchanged():
    cfg = TrainConfig(widths=(4,), batch=64, iterations=12, lr=1e-2, seed=3)
    plain = train(cfg, progress=False, log_every=1)
    calls: list[int] = []

    def stop(i: int, _model: Any) -> bool:
        calls.append(i)
        return False

    watched = train(cfg, progress=False, log_every=1, evaluate_every=5, stop=stop)
    assert calls == [5, 10, 12]
    assert watched.losses == plain.losses and watched.iterations_run == plain.iterations_run == 12
    for a, b in zip(plain.model.parameters(), watched.model.parameters(), strict=True):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match="evaluate_every"):
        train(cfg, progress=False, evaluate_every=0, stop=stop)


def test_train_scene_records_the_scene_in_the_model(tmp_path: Path):
    path = tmp_path / "easy.toml"
    path.write_text(VALID.replace("error = 1e-3", "error = 1e-1").replace("energy = 1e-4", ""))
    # K = 3 alone meets this easy target: forced, to check what a trained model records.
    out = train_scene(path, tmp_path / "m.safetensors", progress=False, force=True)
    assert out is not None
    model = pr.load_model(out)
    meta = model.metadata
    assert meta["name"] == "m" and meta["scene"] == "small"
    assert meta["command"] == f"poisson-rs train --scene {path} --out {tmp_path / 'm.safetensors'}"
    assert json.loads(meta["target_met"]) is True
    assert json.loads(meta["scene_target"]) == {"error": 1e-1, "newton": "all"}
    measured = json.loads(meta["scene_result"])
    again = evaluate(model, load_scene(path))
    assert measured["error"] == again["error"] and measured["energy"] == again["energy"]
    # The scene's [model] caps training at 7 iterations, rolled out every 3.
    assert json.loads(meta["iterations_run"]) <= 7 and json.loads(meta["evaluations"]) >= 1


SHIPPED = [("paper.toml", "paper_h01"), ("large_step.toml", "large_step_h05")]


@pytest.mark.parametrize(("scene_file", "name"), SHIPPED)
def test_shipped_scene_models_meet_their_targets(scene_file: str, name: str):
    assert name in pr.list_models()
    scene = load_scene(SCENES / scene_file)
    model = pr.load_model(name)
    meta = model.metadata
    assert meta["command"].startswith(f"poisson-rs train --scene scenes/{scene_file} --out ")
    assert meta["seed"] == 0 and meta["scene"] == scene.name
    assert json.loads(meta["target_met"]) is True
    result = evaluate(model, scene)
    assert result["target_met"], result
    # The numbers recorded at training time are those measured now (same file, same rollout).
    recorded = json.loads(meta["scene_result"])
    assert recorded["error"] == pytest.approx(result["error"], rel=1e-9)
    assert recorded["energy"] == pytest.approx(result["energy"], rel=1e-9)
    # The same chart and Taylor order without the network misses the target: the network is
    # what meets it (the scene files say which plain series meet it without one).
    plain = pr.taylor_integrator(scene.body, int(meta["taylor_order"]), model.chart)
    assert not evaluate(plain, scene)["target_met"]


def test_train_scene_stops_when_the_taylor_terms_alone_meet_the_target(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "easy.toml"
    path.write_text(VALID.replace("error = 1e-3", "error = 1e-1").replace("energy = 1e-4", ""))
    out = tmp_path / "m.safetensors"
    assert train_scene(path, out, progress=True) is None
    assert "Taylor terms alone (K = 3, cayley chart) already meet" in capsys.readouterr().out
    assert not out.exists()
    from poisson_rs.cli import main

    assert main(["train", "--scene", str(path), "--out", str(out), "--no-progress"]) == 0
    assert not out.exists()


def test_a_scene_names_its_algebra_or_a_system_file(tmp_path: Path) -> None:
    top = pr.HeavyTop()
    terms = ", ".join(
        "[" + ", ".join(map(str, (*k, v))) + "]" for k, v in top.polynomial.terms.items()
    )
    named = tmp_path / "named.toml"
    named.write_text(
        f"""[system]
algebra = "se3"
hamiltonian = {{ dim = 6, terms = [{terms}] }}
[states]
points = [[0.3, -0.8, 1.2, 0.6, 0.0, 0.8]]
[steps]
h = 0.1
horizon = 1.0
[target]
error = 1e-3
"""
    )
    scene = load_scene(named)
    assert scene.lie_system.algebra == pr.LieAlgebra.se3()
    assert scene.lie_system.polynomial == top.polynomial
    (tmp_path / "top.json").write_text(json.dumps(top.to_dict()))
    filed = tmp_path / "filed.toml"
    rest = named.read_text().split("[states]")[1]
    filed.write_text('[system]\nsystem_file = "top.json"\n[states]' + rest)
    assert load_scene(filed).lie_system == top
    # An se(3)* scene trains on the "top" domain: |Γ| near 1, M within the orbits' reach.
    cfg = derive_config(load_scene(filed))
    assert cfg.domain == "top" and cfg.r_min < 1.0 < cfg.r_max and cfg.half_width > 1.2
    bad = named.read_text().replace('algebra = "se3"', 'algebra = "so4"')
    named.write_text(bad)
    with pytest.raises(ValueError, match="so4"):
        load_scene(named)
    filed.write_text('[system]\nsystem_file = "missing.json"\n[states]\npoints = [[1.0, 0, 0]]\n')
    with pytest.raises((ValueError, FileNotFoundError), match=r"missing\.json"):
        load_scene(filed)


def test_select_table_takes_a_metric(tmp_path: Path) -> None:
    path = tmp_path / "s.toml"
    path.write_text(VALID + '\n[select]\ntarget = 1e-6\nmetric = "energy"\n')
    scene = load_scene(path)
    assert scene.select is not None and scene.select.metric == "energy"
    path.write_text(VALID + '\n[select]\ntarget = 1e-6\nmetric = "speed"\n')
    with pytest.raises(ValueError, match=r"select\.metric"):
        load_scene(path)

"""Heavy-top scenes (and other systems): loading, evaluation, bad files, poisson-rs select."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import poisson_rs as pr
from poisson_rs.cli import main
from poisson_rs.scenes import evaluate as evaluate_scene
from poisson_rs.scenes import load_scene, parse_scene, summary

SCENES = Path(__file__).resolve().parents[1] / "scenes"
TOP = {"kind": "heavy_top", "inertia": [1.0, 1.5, 2.0], "mgl": 0.981, "com": [0.0, 0.0, 1.0]}


def top_scene(**changes: object) -> dict[str, object]:
    data: dict[str, object] = {
        "system": dict(TOP),
        "states": {"points": [[0.5, 0.3, 1.0, 0.0, 0.6, 0.8], [1.0, -0.5, 0.2, 0.6, 0.0, 0.8]]},
        "steps": {"h": 0.1, "horizon": 1.0},
        "target": {"error": 1e-6},
    }
    data.update(changes)
    return data


@pytest.mark.parametrize(
    ("name", "n", "targets"),
    [
        ("heavy_top", 6, (1e-3, 1e-6, 1e-9)),
        ("heavy_top_long", 3, (1e-3, 1e-6, 1e-9)),
        ("heavy_top_learned", 8, (1e-2, 1e-3, 1e-6)),
    ],
)
def test_heavy_top_scenes_load(name: str, n: int, targets: tuple[float, ...]) -> None:
    scene = load_scene(SCENES / f"{name}.toml")
    assert scene.lie_system == pr.HeavyTop((1.0, 1.5, 2.0), 0.981, (0.0, 0.0, 1.0))
    mu0 = scene.states()
    assert mu0.shape == (n, 6)
    np.testing.assert_allclose(np.linalg.norm(mu0[:, 3:], axis=1), 1.0, rtol=1e-15)
    assert scene.select is not None and scene.select.targets == targets
    assert scene.body is scene.system  # the alias, kept one release, on every scene


def test_rigid_body_scenes_are_unchanged() -> None:
    scene = load_scene(SCENES / "paper.toml")
    assert scene.lie_system == pr.RigidBody((1.5, 2.0, 2.5)) and scene.body == scene.lie_system
    assert scene.states().shape == (18, 3) and scene.select is None


def test_heavy_top_scene_evaluates_against_dop853() -> None:
    scene = parse_scene(top_scene(), name="t")
    top = scene.lie_system
    good = summary(evaluate_scene(pr.taylor_integrator(top, 5, "exp"), scene))
    assert good["target_met"] and good["error"] < 1e-8
    assert good["casimir"] < 1e-14  # |Γ|² and M·Γ kept to round-off by a Poisson map
    rk4 = summary(evaluate_scene(pr.classical(top, "rk4"), scene))
    assert rk4["casimir"] > 1e-10 and rk4["error"] > good["error"]
    with pytest.raises(ValueError, match="the model is for RigidBody"):
        evaluate_scene(pr.load_model("default"), scene)


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"system": {**TOP, "kind": "spinning_plate"}}, "'spinning_plate' is not one of"),
        ({"system": {"kind": "heavy_top", "inertia": [1.0, 1.5, 2.0]}}, "'mgl'"),
        ({"system": {"inertia": [1.0, 1.5, 2.0], "mgl": 1.0}}, "system.mgl' is not known"),
        ({"states": {"points": [[1.0, 1.0, 2.0]]}}, r"points\[0\]' must be 6 numbers"),
        (
            {
                "system": {"kind": "lotka_volterra", "c": [[0, 1], [-1, 0]], "b": [1, 2]},
                "states": {"shell": {"r_min": 1, "r_max": 2, "n": 4}},
            },
            "outside the open positive orthant.*give 'states.points'",
        ),
        ({"select": {"T": 1.0}}, "select.target' is missing"),
        ({"select": {"target": [1e-3], "h": 0.3}}, "whole number of steps h = 0.3"),
        ({"select": {"target": 1e-3, "models": "default"}}, "list of model names"),
        ({"select": {"target": 1e-3, "budget": 3}}, "select.budget' is not known"),
    ],
)
def test_bad_scene_files_get_clear_errors(changes: dict[str, object], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        parse_scene(top_scene(**changes), name="bad")


def test_cli_select_prints_the_table(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "top.toml"
    path.write_text(
        '[system]\nkind = "heavy_top"\ninertia = [1.0, 1.5, 2.0]\nmgl = 0.981\n'
        "com = [0.0, 0.0, 1.0]\n[states]\npoints = [[0.5, 0.3, 1.0, 0.0, 0.6, 0.8]]\n"
        "[steps]\nh = 0.5\nhorizon = 1.0\n[target]\nerror = 1e-3\n"
        '[select]\ntarget = 1e-4\nmodels = ["default"]\n'
    )
    out = tmp_path / "select.json"
    assert main(["select", str(path), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "selected for error <= 1e-04" in text and "trained for RigidBody" in text
    assert out.is_file()
    argv = ["select", str(path), "--target", "1e-17", "--T", "0.5", "--budget", "1"]
    assert main([*argv, "--max-steps", "256"]) == 1
    assert "no candidate meets 1e-17 at T = 0.5; best was" in capsys.readouterr().out
    path.write_text("[system]\nkind = 3\n")
    assert main(["select", str(path)]) == 2


def test_heavy_top_charts_take_the_learned_model_of_their_system_only() -> None:
    from poisson_rs.studies.workprecision import default_methods, steps_to

    methods = {m.name: m for m in default_methods(pr.HeavyTop())}
    assert methods["learned:heavy_top_h05"].family == "learned"
    assert "taylor3-exp" in methods and "taylor3-cayley" not in methods  # exp only off so(3)
    other = default_methods(pr.HeavyTop(mgl=0.5))
    assert not any(m.name.startswith("learned:") for m in other)
    # Step counts are per 10 time units: the same step sizes h on every horizon.
    assert steps_to(10.0, (10, 20, 40)) == (10, 20, 40)
    assert steps_to(1000.0, (10, 20)) == (1000, 2000)

"""The public CLI charts and maps a user's own model beside the others, and refuses a model
trained for another system before any work."""

from __future__ import annotations

from pathlib import Path

import pytest

import poisson_rs as pr
from poisson_rs.cli import main
from poisson_rs.export import model_bytes
from poisson_rs.taylor import system_taylor_terms


def _model(tmp_path: Path, system: pr.LiePoissonSystem, name: str) -> Path:
    """A Taylor K=3 model file of ``system`` named ``name`` (a user's own model)."""
    powers, coeffs = system_taylor_terms(system, 3, "exp")
    path = tmp_path / f"{name}.safetensors"
    path.write_bytes(
        model_bytes(
            powers=powers,
            coeffs=coeffs,
            layers=[],
            mlp_power=1,
            chart="exp",
            system=system,
            h_max=1.0,
            domain={"kind": "all"},
            record={"name": name},
        )
    )
    return path


@pytest.mark.parametrize("command", ["chart", "stability"])
def test_a_model_of_another_system_is_refused_before_the_work(
    tmp_path: Path, command: str, capsys: pytest.CaptureFixture[str]
) -> None:
    model = _model(tmp_path, pr.HeavyTop(), "top")
    code = main([command, "--quick", "--out", str(tmp_path / "out"), "--model", str(model)])
    assert code != 0
    assert "heavy top" in capsys.readouterr().err  # the system by name, not its repr


def test_stability_maps_a_users_model(tmp_path: Path) -> None:
    out = tmp_path / "out"
    model = _model(tmp_path, pr.RigidBody(), "mine")
    code = main(["stability", "--quick", "--no-progress", "--out", str(out), "--model", str(model)])
    assert code == 0
    assert "learned:mine" in (out / "stability.csv").read_text()


def test_demo_refuses_model_and_system_together(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(["demo", "--system", "heavy-top", "--model", "default", "--out", str(tmp_path)])
    assert code != 0
    assert "not both" in capsys.readouterr().err


SCENES = Path(__file__).resolve().parents[1] / "scenes"


def test_demo_runs_a_heavy_top_scene(tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert main(["demo", "--scene", str(SCENES / "heavy_top.toml"), "--out", str(out)]) == 0
    rows = (out / "metrics.csv").read_text()
    assert "taylor7-exp" in rows and "splitting" in rows
    assert (out / "states_errors.png").stat().st_size > 0


def test_chart_and_stability_take_a_rigid_body_scene(tmp_path: Path) -> None:
    scene = str(SCENES / "large_step.toml")
    assert (
        main(["chart", "--quick", "--no-paper", "--scene", scene, "--out", str(tmp_path / "c")])
        == 0
    )
    assert "large_step" in (tmp_path / "c" / "workprecision.csv").read_text()
    assert (
        main(
            [
                "stability",
                "--quick",
                "--no-progress",
                "--scene",
                scene,
                "--out",
                str(tmp_path / "s"),
            ]
        )
        == 0
    )


def test_shipped_models_join_only_maps_of_their_own_body() -> None:
    from poisson_rs.studies.stability import default_methods

    assert "learned:default" in default_methods(pr.RigidBody())
    assert not any(k.startswith("learned:") for k in default_methods(pr.RigidBody((1, 1, 1.001))))

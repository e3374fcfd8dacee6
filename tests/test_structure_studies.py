"""The studies and the CLI on structures beyond g*: ``demo``, ``chart``, ``stability`` and
``select`` run end to end on PNN's Lotka–Volterra scene (log-canonical) with its own methods
(Taylor-HJ on the exact groupoid, RK4, midpoint, the log splittings, DOP853), the Casimirs in
log form where c has a null vector and "n/a" where it is invertible, and one-line errors for bad
log-canonical scenes."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

import poisson_rs as pr
from poisson_rs.casimirs import casimir_degrees, casimir_label, max_casimir_drift
from poisson_rs.cli import main
from poisson_rs.scenes import load_scene
from poisson_rs.studies import stability
from poisson_rs.studies.methods import taylor_charts
from poisson_rs.studies.workprecision import default_methods

SCENES = Path(__file__).resolve().parents[1] / "scenes"
PNN = SCENES / "lotka_volterra_pnn.toml"
LV3 = SCENES / "lotka_volterra_3d.toml"

#: PNN's system on a short horizon (fast end-to-end runs).
SHORT = """name = "pnn_short"
[system]
kind = "lotka_volterra"
c = [[0.0, 1.0], [-1.0, 0.0]]
b = [1.0, 2.0]
[states]
points = [[1.0, 0.8], [1.0, 1.2]]
[steps]
h = 0.1
horizon = 2.0
[target]
error = 1e-3
[select]
target = [1e-4]
"""

BAD_SCENES = {
    "not antisymmetric": (
        SHORT.replace("[-1.0, 0.0]]", "[1.0, 0.0]]"),
        "system.c.*antisymmetric",
    ),
    "outside the orthant": (
        SHORT.replace("[1.0, 1.2]]", "[1.0, -1.2]]"),
        r"states.points\[1\].*positive orthant",
    ),
    "missing b": (SHORT.replace("b = [1.0, 2.0]\n", ""), "system.b' is missing"),
    "b of the wrong size": (SHORT.replace("b = [1.0, 2.0]", "b = [1.0]"), "system.b"),
    "ragged c": (SHORT.replace("[-1.0, 0.0]]", "[-1.0]]"), "system.c.*square"),
    "a training table": (
        SHORT + "[model]\nwidths = [4]\n",
        "training a learned S is not available",
    ),
}


@pytest.fixture
def short(tmp_path: Path) -> Path:
    path = tmp_path / "pnn_short.toml"
    path.write_text(SHORT)
    return path


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def test_scene_parses_lotka_volterra() -> None:
    scene = load_scene(PNN)
    assert scene.lie_system == pr.lotka_volterra([[0, 1], [-1, 0]], [1, 2])
    assert scene.lie_system.component_names == ("u", "v")
    np.testing.assert_array_equal(scene.states(), [[1.0, 0.8], [1.0, 1.0], [1.0, 1.2]])
    assert scene.h == (0.1,) and scene.n_steps(0.1) == 1500
    three = load_scene(LV3).lie_system
    assert three.component_names == ("x₁", "x₂", "x₃")
    assert three.structure.casimir_vectors.tolist() == [[1, -1, 1]]


@pytest.mark.parametrize("case", sorted(BAD_SCENES))
def test_bad_lotka_volterra_scenes_give_one_line(
    case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text, pattern = BAD_SCENES[case]
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ValueError, match=pattern):
        load_scene(path)
    assert main(["demo", "--scene", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("poisson-rs demo:") and "\n" not in err
    assert "Traceback" not in err


def test_methods_per_system() -> None:
    lv = load_scene(PNN).lie_system
    assert taylor_charts(lv) == ("log",)
    assert pr.classical_methods(lv) == [
        "rk4",
        "midpoint",
        "log_splitting",
        "log_splitting4",
        "dop853",
    ]
    names = [m.name for m in default_methods(lv)]
    # The shipped learned model of this system comes first (docs/learned_log_canonical.md).
    assert names[0] == "learned:lotka_volterra_h01"
    assert names[1:5] == ["taylor1-log", "taylor3-log", "taylor5-log", "taylor7-log"]
    assert {"rk4", "midpoint", "log_splitting", "log_splitting4", "dop853"} <= set(names)
    assert sum(n.startswith("learned:") for n in names) == 1
    # The Lie–Poisson systems keep theirs.
    assert taylor_charts(pr.RigidBody()) == ("cayley", "exp")
    assert taylor_charts(pr.HeavyTop()) == ("exp",)


def test_casimirs_in_log_form_absolute_and_na_when_c_is_invertible() -> None:
    three = load_scene(LV3).lie_system
    assert casimir_degrees(three) == (0,)
    assert casimir_label(three).startswith("C = ln x₁ − ln x₂ + ln x₃")
    x0 = np.array([[1.2, 0.7, 1.6]])
    # Oracle: the drift of a trajectory scaled so that ln(x₁x₃/x₂) moves by exactly 1e-3.
    traj = np.stack([x0[0], x0[0] * np.array([np.exp(1e-3), 1.0, 1.0])])[None]
    np.testing.assert_allclose(max_casimir_drift(three, traj)[0], [0.0, 1e-3], rtol=1e-9)
    pnn = load_scene(PNN).lie_system
    assert np.isnan(max_casimir_drift(pnn, traj[..., :2])).all()
    assert "n/a" in casimir_label(pnn)


def test_demo_on_the_pnn_scene(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "demo"
    assert main(["demo", "--scene", str(PNN), "--out", str(out), "--steps", "40"]) == 0
    text = capsys.readouterr().out
    assert "n/a" in text  # c is invertible: no Casimir, never a 0 drift
    rows = _rows(out / "metrics.csv")
    methods = {r["method"] for r in rows}
    assert methods == {
        "taylor1-log",
        "taylor3-log",
        "taylor5-log",
        "taylor7-log",
        "rk4",
        "midpoint",
        "log_splitting",
        "log_splitting4",
    }
    assert all(r["max_rel_dC"] in ("", "nan") for r in rows)
    final = {r["method"]: float(r["error"]) for r in rows if r["state"] == "(1, 0.8)"}
    # Taylor m = 7 (order 8) is far ahead of m = 1 (order 2) at h = 0.1.
    assert final["taylor7-log"] < 1e-3 * final["taylor1-log"]
    for name in ("orbits.png", "states_errors.png", "trajectories.csv", "metrics.json"):
        assert (out / name).stat().st_size > 0


def test_demo_on_the_3d_scene_keeps_the_casimir(tmp_path: Path) -> None:
    out = tmp_path / "demo3"
    assert main(["demo", "--scene", str(LV3), "--out", str(out), "--steps", "300"]) == 0
    drift = {r["method"]: float(r["max_rel_dC"]) for r in _rows(out / "metrics.csv")}
    for name in ("taylor1-log", "taylor5-log", "log_splitting", "log_splitting4"):
        assert drift[name] < 1e-12, name  # Poisson maps: ln x₁ − ln x₂ + ln x₃ to round-off
    assert drift["rk4"] > 1e-8 and drift["midpoint"] > 1e-8


def test_chart_on_a_log_canonical_scene_fits_the_orders(short: Path, tmp_path: Path) -> None:
    out = tmp_path / "chart"
    assert main(["chart", str(short), "--quick", "--out", str(out)]) == 0
    rows = [r for r in _rows(out / "workprecision.csv") if r["failed"] == "False"]
    assert {r["method"] for r in rows} >= {
        "taylor3-log",
        "taylor5-log",
        "rk4",
        "midpoint",
        "log_splitting",
        "log_splitting4",
    }

    def order(method: str) -> float:
        pts = sorted((float(r["h"]), float(r["error_T"])) for r in rows if r["method"] == method)
        h, e = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
        return float(np.polyfit(h, e, 1)[0])

    assert order("taylor3-log") == pytest.approx(4.0, abs=0.3)
    assert order("log_splitting") == pytest.approx(2.0, abs=0.2)
    assert order("log_splitting4") == pytest.approx(4.0, abs=0.3)
    for r in rows:
        assert r["max_rel_dC"] in ("", "nan")  # PNN's c is invertible
    for name in ("workprecision_error.png", "workprecision_casimirs.png", "long_run_energy.png"):
        assert (out / name).stat().st_size > 0


def test_stability_on_the_pnn_scene(short: Path, tmp_path: Path) -> None:
    out = tmp_path / "stability"
    argv = ["stability", str(short), "--quick", "--out", str(out), "--horizon", "2"]
    assert main([*argv, "--no-progress"]) == 0
    rows = _rows(out / "stability.csv")
    assert {r["method"] for r in rows} == {
        "learned:lotka_volterra_h01",  # the shipped model of this system
        "taylor3-log",
        "taylor5-log",
        "log_splitting",
        "log_splitting4",
        "midpoint",
        "rk4",
    }
    small = [r for r in rows if float(r["h"]) == 0.1]
    assert all(float(r["rel_error"]) < 1e-2 for r in small)


def test_stability_states_stay_in_the_orthant() -> None:
    lv = load_scene(LV3).lie_system
    mu0, labels = stability.states(lv)
    assert (mu0 > 0).all() and len(mu0) == len(labels) == 12
    # Log distance ρ from the equilibrium x* = b.
    rho = np.linalg.norm(np.log(mu0 / lv.log_hamiltonian.b), axis=1)
    np.testing.assert_allclose(sorted(set(np.round(rho, 12))), lv.sample_radii)


def test_select_on_the_pnn_scene(short: Path, tmp_path: Path) -> None:
    out = tmp_path / "select.json"
    argv = ["select", str(short), "--budget", "3", "--json", str(out)]
    assert main(argv) == 0
    data = json.loads(out.read_text())
    text = json.dumps(data)
    for name in ("taylor5-log", "log_splitting4", "rk4"):
        assert name in text
    # The shipped model of this system is a candidate; the rigid body's are excluded, saying why.
    assert "learned:lotka_volterra_h01" in text and "trained for RigidBody" in text


def test_select_api_refuses_states_outside_the_orthant() -> None:
    lv = load_scene(PNN).lie_system
    with pytest.raises(ValueError, match="positive orthant"):
        pr.select(lv, [[1.0, -0.5]], T=1.0, target=1e-3)
    stepper, h, _ = pr.select(lv, [[1.0, 0.8]], T=1.0, target=1e-4, budget_s=5.0)
    traj = pr.integrate(stepper, [1.0, 0.8], h, round(1.0 / h))
    ref = pr.reference_solution(lv, [1.0, 0.8], [1.0])[0]
    assert np.linalg.norm(traj[-1] - ref) / np.linalg.norm([1.0, 0.8]) <= 1e-4
    assert math.isfinite(h)


def test_train_refuses_a_log_canonical_scene_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["train", "--scene", str(PNN), "--out", str(tmp_path / "m.safetensors")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "training a learned S is not available" in err and "\n" not in err
    assert not (tmp_path / "m.safetensors").exists()


def test_select_by_casimir_picks_a_poisson_method() -> None:
    """On the 3D scene only the Poisson maps keep ln x₁ − ln x₂ + ln x₃ to round-off: a Casimir
    target of 1e-12 at T = 10 is met by them at large steps, RK4 needs tiny ones."""
    system = load_scene(LV3).lie_system
    states = load_scene(LV3).states()
    stepper, h, report = pr.select(
        system, states, T=10.0, target=1e-12, metric="casimir", budget_s=3.0
    )
    assert stepper.name in ("log_splitting", "log_splitting4") or stepper.name.endswith("-log")
    traj = pr.integrate(stepper, states, h, round(10.0 / h))
    assert np.nanmax(max_casimir_drift(system, traj)) <= 1e-12
    assert "rk4" in str(report)

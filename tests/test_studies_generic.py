"""One study pipeline for every system: demo, chart and stability on the heavy top and on a
user's ``lie_poisson`` scene whose Casimirs are unknown (NaN in the data, "n/a" in tables and
figures, never 0), figures that name components by the system, wrap large state grids, give
each learned model its own colour and list only the markers drawn."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from matplotlib.figure import Figure

import poisson_rs as pr
from poisson_rs.cli import main
from poisson_rs.studies import figures
from poisson_rs.studies.demo import run_scene

SCENES = Path(__file__).resolve().parents[1] / "scenes"

#: A solvable algebra without polynomial Casimirs ([e3, e1] = e1, [e3, e2] = e2), quadratic H.
BOOK = """name = "book"
[system]
kind = "lie_poisson"
name = "book algebra"
algebra = { structure_constants = [[[0,0,0],[0,0,0],[-1,0,0]], [[0,0,0],[0,0,0],[0,-1,0]],
  [[1,0,0],[0,1,0],[0,0,0]]] }
hamiltonian = { dim = 3, terms = [[2,0,0,0.5],[0,2,0,0.5],[0,0,2,0.5]] }
[states]
points = [[0.3, 0.2, 0.5], [0.1, -0.4, 0.2]]
[steps]
h = 0.05
horizon = 1.0
[target]
error = 1e-3
"""


@pytest.fixture
def book(tmp_path: Path) -> Path:
    path = tmp_path / "book.toml"
    path.write_text(BOOK)
    return path


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def test_demo_on_a_users_scene_reports_unknown_casimirs_as_na(
    book: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "demo"
    assert main(["demo", "--scene", str(book), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert " n/a " in text  # the table's Casimir column
    rows = _rows(out / "metrics.csv")
    assert rows and all(r["max_rel_dC"] == "nan" for r in rows)  # NaN, never 0
    assert all(math.isnan(r["max_rel_dC"]) for r in json.loads((out / "metrics.json").read_text()))
    header = (out / "trajectories.csv").read_text().splitlines()[0].split(",")
    assert "ref_μ₁" in header and "taylor3-exp_μ₃" in header
    assert (out / "orbits.png").stat().st_size > 0 and (out / "states_errors.png").is_file()


def test_demo_scene_honours_h_and_steps(
    book: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "demo"
    assert (
        main(["demo", "--scene", str(book), "--h", "0.1", "--steps", "4", "--out", str(out)]) == 0
    )
    assert "h = 0.1, 4 steps (T = 0.4)" in capsys.readouterr().out
    rows = json.loads((out / "metrics.json").read_text())
    assert rows and all(r["T"] == pytest.approx(0.4) for r in rows)
    lines = (out / "trajectories.csv").read_text().splitlines()
    assert len(lines) == 1 + 2 * 5  # two states, steps 0..4


def test_demo_heavy_top_scene_names_m_and_gamma(tmp_path: Path) -> None:
    out = tmp_path / "top"
    argv = ["demo", "--scene", str(SCENES / "heavy_top.toml"), "--steps", "20", "--out", str(out)]
    assert main(argv) == 0
    header = (out / "trajectories.csv").read_text().splitlines()[0]
    assert "ref_M₁" in header and "ref_Γ₃" in header
    rows = _rows(out / "metrics.csv")
    assert all(float(r["max_rel_dC"]) < 1e-12 for r in rows if r["method"].startswith("taylor"))


@pytest.mark.parametrize("command", ["chart", "stability"])
def test_chart_and_stability_run_on_a_users_scene(
    book: Path, tmp_path: Path, command: str, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / command
    argv = [command, str(book), "--quick", "--out", str(out)]
    if command == "stability":
        argv += ["--no-progress", "--horizon", "1"]
    assert main(argv) == 0, capsys.readouterr().err
    data = out / ("workprecision.csv" if command == "chart" else "stability.csv")
    rows = _rows(data)
    assert rows and all(r["max_rel_dC"] == "nan" for r in rows)
    assert any(float(r["max_rel_dH"]) > 0 for r in rows if r["max_rel_dH"] != "")


def test_chart_on_the_heavy_top_scene_records_its_casimirs(tmp_path: Path) -> None:
    out = tmp_path / "chart"
    assert main(["chart", str(SCENES / "heavy_top.toml"), "--quick", "--out", str(out)]) == 0
    rows = json.loads((out / "workprecision.json").read_text())
    assert {r["scene"] for r in rows} == {"heavy_top"}
    taylor = [r for r in rows if r["method"].startswith("taylor") and not r["failed"]]
    assert taylor and max(r["max_rel_dC"] for r in taylor) < 1e-12
    assert "learned:heavy_top_h05" in {r["method"] for r in rows}
    assert (out / "workprecision_casimirs.png").is_file()


def test_component_names_and_titles_come_from_the_system() -> None:
    assert pr.HeavyTop().component_names == ("M₁", "M₂", "M₃", "Γ₁", "Γ₂", "Γ₃")
    assert pr.RigidBody().component_names == ("μ₁", "μ₂", "μ₃")
    sl2 = pr.LiePoissonSystem(pr.LieAlgebra.sl2(), pr.Polynomial({(2, 0, 0): 1.0}))
    assert sl2.component_names == ("μ_h", "μ_e", "μ_f")
    c = np.zeros((10, 10, 10))
    big = pr.LiePoissonSystem(pr.LieAlgebra(c), pr.Polynomial({(2,) + (0,) * 9: 1.0}))
    assert big.component_names[-1] == "μ₁₀"
    label = figures.system_label(pr.HeavyTop())
    assert label.startswith("heavy top") and "HeavyTop(" not in label
    assert "LiePoissonSystem(" not in figures.system_label(sl2)


def test_every_learned_model_gets_a_colour_of_its_own() -> None:
    names = [f"learned:user_model_{k}" for k in range(10)]
    colours = [figures.method_style(n)["color"] for n in names]
    assert len(set(colours)) == len(colours)
    assert colours == [figures.method_style(n)["color"] for n in names]  # stable
    others = {figures.method_style(m)["color"] for m in ("rk4", "midpoint", "dop853", "splitting")}
    assert not others & set(colours)
    assert figures.method_style("learned:default")["color"] == "black"


def _keep_figures(monkeypatch: pytest.MonkeyPatch) -> list[Figure]:
    kept: list[Figure] = []
    real = figures._savefig

    def keep(fig: Figure, path: Path, **kwargs: Any) -> Path:
        kept.append(fig)
        return real(fig, path, **kwargs)

    monkeypatch.setattr(figures, "_savefig", keep)
    return kept


def test_state_grids_wrap_for_eight_states(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    kept = _keep_figures(monkeypatch)
    body = pr.RigidBody()
    states = np.random.default_rng(0).normal(size=(8, 3)) * 2
    scene = run_scene({"rk4": pr.classical(body, "rk4")}, body, states, 0.1, 10)
    figures.error_figure(scene, scene.runs, tmp_path / "e.png")
    visible = [ax for ax in kept[-1].axes if ax.get_visible()]
    assert len(visible) == 3 * 8
    columns = {round(ax.get_position().x0, 3) for ax in visible}
    assert len(columns) == figures.GRID_COLUMNS  # 4 columns, 2 blocks of rows
    figures.orbit_figure(scene, scene.runs, tmp_path / "o.png")
    assert len([ax for ax in kept[-1].axes if ax.get_visible()]) == 8


def test_legend_lists_only_the_markers_drawn(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    kept = _keep_figures(monkeypatch)
    row = {"scene": "s", "method": "rk4", "h": 0.1, "tol": None, "T": 1.0, "failed": False,
           "error_T": 1e-6, "seconds_per_traj": 1e-4, "extrapolated": False}  # fmt: skip
    figures.work_precision_figure([row, {**row, "h": 0.05, "error_T": 1e-8}], tmp_path / "a.png")
    labels = [t.get_text() for t in kept[-1].legends[0].get_texts()]
    assert labels == ["rk4"]
    failed = {**row, "h": 0.5, "failed": True, "error_T": None}
    figures.work_precision_figure([row, failed], tmp_path / "b.png")
    labels = [t.get_text() for t in kept[-1].legends[0].get_texts()]
    assert "failed run (top edge)" in labels and not any(">" in t for t in labels)


def test_every_that_does_not_divide_the_steps_is_documented_where_integrate_is_called() -> None:
    # integrate() keeps steps 0, every, 2·every, ...: with every ∤ n_steps the final state is
    # not there. Its docstring says so, and the studies only call it with divisors.
    from poisson_rs.studies.select import _every

    taylor = pr.taylor_integrator(pr.RigidBody(), 3)
    traj = pr.integrate(taylor, [1.0, 1.0, 2.0], 0.1, 10, every=3)
    assert traj.shape == (4, 3)  # steps 0, 3, 6, 9
    assert "NOT the final one" in (pr.integrate.__doc__ or "")
    for n in (1, 7, 100, 1000, 4096, 10**6, 999_983):
        assert n % _every(n) == 0 and n // _every(n) >= min(n, 100)  # the final state is kept


def test_the_kirchhoff_scene_names_its_algebra_and_uses_the_se3_casimirs() -> None:
    from poisson_rs.scenes import load_scene

    scene = load_scene(SCENES / "kirchhoff.toml")
    system = scene.lie_system
    assert system.algebra == pr.LieAlgebra.se3() and system.name == "Kirchhoff body"
    assert figures.system_label(system) == "Kirchhoff body on se(3)*"
    mu0 = scene.states()
    traj = pr.integrate(pr.taylor_integrator(system, 3, "exp"), mu0, 0.1, 100)
    from poisson_rs.casimirs import max_casimir_drift

    assert np.nanmax(max_casimir_drift(system, traj)) < 1e-13


def test_learned_colours_stay_distinct_past_the_palette() -> None:
    names = [f"learned:many_{k}" for k in range(3 * len(figures.LEARNED_COLOURS))]
    colours = [figures.learned_colour(n) for n in names]
    assert len(set(colours)) == len(colours)


def _breaks_inside_brackets(text: str) -> bool:
    """Whether ``text`` has a line break inside (), [] or {}."""
    depth = 0
    for ch in text:
        if ch in "([{":
            depth += 1
        elif ch in ")]}":
            depth -= 1
        elif ch == "\n" and depth > 0:
            return True
    return False


def test_states_errors_of_six_components_fills_its_canvas(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Two blocks of components (M, Γ) per state: one full column per state, and the legend
    # right beside the panels, inside the figure.
    kept = _keep_figures(monkeypatch)
    top = pr.HeavyTop()
    methods = {"rk4": pr.classical(top, "rk4"), "midpoint": pr.classical(top, "midpoint")}
    scene = run_scene(methods, top, top.demo_states, 0.1, 20)
    figures.state_figure(scene, scene.runs, tmp_path / "states_errors.png")
    fig = kept[-1]
    visible = [ax for ax in fig.axes if ax.get_visible()]
    assert len(visible) == len(fig.axes) == 2 * (2 + 3)
    columns = {round(ax.get_position().x0, 3) for ax in visible}
    assert len(columns) == 2  # one per state, none empty
    (legend,) = fig.legends
    assert [t.get_text() for t in legend.get_texts()] == ["rk4", "midpoint"]
    box = legend.get_window_extent()
    page = fig.bbox
    assert page.x0 <= box.x0 and box.x1 <= page.x1 and page.y0 <= box.y0 and box.y1 <= page.y1
    right = max(ax.get_window_extent().x1 for ax in visible)
    assert 0 <= box.x0 - right < 0.1 * page.width  # beside the panels, not detached
    assert right > 0.75 * page.width  # the panels use the canvas


def test_stability_summary_shows_every_failed_method(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Three methods failing at the same h: each keeps a row of its own in the failures panel.
    kept = _keep_figures(monkeypatch)
    failing = {"rk4": {0.5, 1.0}, "midpoint": {1.0}, "taylor3-exp": {1.0}}
    rows = [
        {
            "method": method,
            "h": h,
            "state": state,
            "converged": not (h in failing.get(method, set()) and state == "b"),
            "rel_error": 1e-3 * h,
            "max_rel_dH": 1e-4 * h,
            "max_rel_dC": 1e-14,
        }
        for method in ("taylor3-exp", "rk4", "midpoint", "splitting")
        for h in (0.1, 0.5, 1.0)
        for state in ("a", "b")
    ]
    figures.stability_summary_figure(rows, tmp_path / "s.png", system=pr.RigidBody())
    (panel,) = [ax for ax in kept[-1].axes if ax.get_gid() == figures.FAILURES_GID]
    drawn = {line.get_label(): line for line in panel.lines}
    assert set(drawn) == set(failing)
    for method, hs in failing.items():
        assert set(drawn[method].get_xdata()) == hs
    rows_y = {method: set(line.get_ydata()) for method, line in drawn.items()}
    assert all(len(y) == 1 for y in rows_y.values())
    assert len({next(iter(y)) for y in rows_y.values()}) == len(failing)  # no two overlap


def test_titles_never_embed_a_matrix_nor_break_inside_brackets(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    kept = _keep_figures(monkeypatch)
    lv3 = pr.lotka_volterra([[0, 1, 1], [-1, 0, 1], [-1, -1, 0]], [1, 2, 1])
    assert "[[" in figures.system_label(lv3)  # messages keep the matrix
    label = figures.figure_label(lv3)
    assert "[" not in label and label.startswith("Lotka–Volterra")
    scene = run_scene({"rk4": pr.classical(lv3, "rk4")}, lv3, lv3.demo_states, 0.1, 5)
    figures.state_figure(scene, scene.runs, tmp_path / "s.png")
    figures.orbit_figure(scene, scene.runs, tmp_path / "o.png")
    for fig in kept:
        title = fig.get_suptitle()
        assert title and "[" not in title and not _breaks_inside_brackets(title)
    # A long title wraps at spaces outside its brackets only.
    long = "a system, c = [[0, 1, 1], [-1, 0, 1], [-1, -1, 0]], I = (1.5, 2.0, 2.5), " * 3
    wrapped = figures.wrap_title(long.strip(), 4.0, 10)
    assert "\n" in wrapped and not _breaks_inside_brackets(wrapped)


def test_the_demo_orbit_figure_shows_the_most_accurate_method(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Chosen by the error measured against the reference, not by the order of the methods
    # (the first is the lowest Taylor order, the least accurate).
    kept = _keep_figures(monkeypatch)
    out = tmp_path / "demo"
    scene = SCENES / "lotka_volterra_3d.toml"
    assert main(["demo", "--scene", str(scene), "--steps", "20", "--out", str(out)]) == 0
    header, *lines = (out / "trajectories.csv").read_text().splitlines()
    names = header.split(",")
    worst = {
        col.removesuffix("_error"): max(float(line.split(",")[k]) for line in lines)
        for k, col in enumerate(names)
        if col.endswith("_error")
    }
    best = min(worst, key=worst.__getitem__)
    assert best != next(iter(worst))  # the order alone would have shown another
    (orbits,) = [f for f in kept if "steps of h" in f.get_suptitle()]
    (legend,) = orbits.legends
    assert [t.get_text() for t in legend.get_texts()] == ["reference", best]

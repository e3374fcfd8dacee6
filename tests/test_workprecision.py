"""Work–precision chart: the ``chart --quick`` path end to end, failure records, level ranking."""

from __future__ import annotations

import csv
import itertools
import json
from pathlib import Path

import numpy as np
import pytest

import poisson_rs as pr
from poisson_rs.cli import main
from poisson_rs.studies import workprecision as wp

SWEEP_COLUMNS = {
    "scene",
    "method",
    "family",
    "h",
    "tol",
    "n_steps",
    "n_states",
    "T",
    "error_T",
    "max_rel_dH",
    "max_rel_dC",
    "failed",
    "n_failed",
    "failure",
    "extrapolated",
    "out_of_domain",
    "seconds_per_traj",
    "cpu_seconds_per_traj",
    "timing_batch",
    "repeats",
    "newton_iters_per_step",
}


@pytest.fixture(scope="module")
def quick_out(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("chart")
    assert main(["chart", "--quick", "--out", str(out)]) == 0
    return out


def _read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def test_quick_chart_writes_figures_and_numbers(quick_out: Path) -> None:
    for name in ("workprecision_error", "workprecision_energy", "long_run_energy"):
        png = quick_out / f"{name}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", png
    rows = _read_csv(quick_out / "workprecision.csv")
    assert set(rows[0]) == SWEEP_COLUMNS
    # Every quick method appears on both scenes at each of the quick step sizes.
    fixed = [r for r in rows if r["family"] != "adaptive"]
    methods = {r["method"] for r in fixed}
    assert {"learned:default", "taylor3-cayley", "taylor5-cayley", "taylor3-exp"} <= methods
    assert len(fixed) == 2 * len(methods) * len(wp.QUICK_STEPS)
    assert {r["scene"] for r in rows} == {"paper", "separatrix"}
    # The default model (trained for h <= 0.1) is measured at h = 0.2 too, and flagged.
    learned = {float(r["h"]): r["extrapolated"] for r in rows if r["method"] == "learned:default"}
    assert learned[0.2] == "True" and learned[0.1] == "False"
    # The JSON holds the same rows, and is strict JSON (a missing number is null, never NaN).
    text = (quick_out / "workprecision.json").read_text()
    as_json = json.loads(text, parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))
    assert len(as_json) == len(rows) and set(as_json[0]) == SWEEP_COLUMNS
    long_rows = _read_csv(quick_out / "long_run_energy.csv")
    assert {"method", "state", "t", "max_rel_dH", "max_rel_dC"} <= set(long_rows[0])
    assert {r["state"] for r in long_rows} == {"(1, 1, 2)", "(3, 2, 0)"}
    # Windows run up to the full quick horizon for a method that cannot fail there.
    t3 = [float(r["t"]) for r in long_rows if r["method"] == "taylor3-cayley"]
    assert max(t3) == pytest.approx(2000 * 0.1)


def test_errors_shrink_with_h_for_taylor(quick_out: Path) -> None:
    rows = json.loads((quick_out / "workprecision.json").read_text())
    for scene in ("paper", "separatrix"):
        pts = sorted(
            (r for r in rows if r["method"] == "taylor5-cayley" and r["scene"] == scene),
            key=lambda r: -r["h"],
        )
        assert not any(r["failed"] for r in pts)
        errors = [r["error_T"] for r in pts]
        # Order 6: halving h cuts the error far more than 2×.
        assert all(b < a / 8 for a, b in itertools.pairwise(errors)), errors


def test_failed_run_is_recorded() -> None:
    """h = 3 on the exponential chart hits its singularity from (3, 2, 0): a failed row."""
    scene = wp.paper_scene()
    stepper = pr.taylor_integrator(scene.body, 3, "exp")
    h, n = 3.0, 4
    exact = pr.exact_solution(scene.body, scene.states, h * np.arange(n + 1))
    row = wp.measure(scene, "taylor3-exp", "taylor", stepper, h, n, exact, repeats=False)
    assert row["failed"] is True
    assert row["n_failed"] >= 1
    assert "chart singular" in row["failure"]
    assert row["error_T"] is None and row["max_rel_dH"] is None
    assert row["seconds_per_traj"] is not None  # its cost is still on the chart
    # And through a sweep: the row is there, not dropped.
    method = wp.Method("taylor3-exp", "taylor", stepper)
    rows = wp.sweep([scene], [method], steps=(4, 100), repeats=False)
    assert [r["failed"] for r in rows] == [True, False]


def _row(method: str, h: float, err: float | None, sec: float, failed: bool = False) -> dict:
    return {
        "scene": "paper",
        "method": method,
        "h": h,
        "tol": None,
        "error_T": err,
        "seconds_per_traj": sec,
        "failed": failed,
    }


def test_fastest_at_level_on_a_synthetic_table() -> None:
    rows = [
        # a: reaches 1e-6 only at its second point, cost 4.
        _row("a", 0.2, 1e-3, 1.0),
        _row("a", 0.1, 1e-6, 4.0),
        # b: cheap but never better than 1e-4; its failed point is ignored.
        _row("b", 0.2, 1e-2, 0.5),
        _row("b", 0.1, 1e-4, 0.8),
        _row("b", 0.05, None, 0.1, failed=True),
        # c: reaches 1e-6 at cost 2 (measured), more than a's interpolated crossing of 1e-4.
        _row("c", 0.2, 1e-6, 2.0),
        {**_row("c", 0.1, 1e-9, 1.0), "scene": "separatrix"},  # another scene: ignored
    ]
    best = wp.fastest_at_level(rows, 1e-6, scene="paper", interpolate=False)
    assert best is not None and best["method"] == "c" and best["seconds"] == 2.0
    assert wp.fastest_at_level(rows, 1e-9, scene="paper") is None
    # 1e-2: b's first point (0.5) beats a (1.0) and c (2.0).
    assert wp.fastest_at_level(rows, 1e-2, scene="paper")["method"] == "b"  # type: ignore[index]
    # 1e-4 with interpolation: a crosses it a third of the way (in log error) from 1e-3 to
    # 1e-6, at cost 4^(1/3) ≈ 1.59 (log–log); b reaches it at a measured 0.8; c only at 2.0.
    ranked = wp.rank_at_level(rows, 1e-4, scene="paper")
    assert [r["method"] for r in ranked] == ["b", "a", "c"]
    assert ranked[1]["interpolated"] and ranked[1]["seconds"] == pytest.approx(4 ** (1 / 3))
    # Without interpolation a only counts at its measured 1e-6 point.
    ranked = wp.rank_at_level(rows, 1e-4, scene="paper", interpolate=False)
    assert [(r["method"], r["seconds"]) for r in ranked] == [("b", 0.8), ("c", 2.0), ("a", 4.0)]


def test_fastest_at_level_needs_no_scene_name_for_a_users_one_scene_rows() -> None:
    # A user's scene is not called "paper": no hidden default may make it find nothing.
    rows = [
        {**_row("a", 0.2, 1e-3, 1.0), "scene": "mine"},
        {**_row("b", 0.1, 1e-5, 3.0), "scene": "mine"},
    ]
    best = wp.fastest_at_level(rows, 1e-4)
    assert best is not None and best["method"] == "b"
    with pytest.raises(ValueError, match="give scene"):
        wp.fastest_at_level([*rows, {**_row("c", 0.1, 1e-9, 1.0), "scene": "other"}], 1e-4)
    # An unknown metric value (NaN: no Casimir known) reaches no level.
    nan_rows = [{**r, "error_T": float("nan")} for r in rows]
    assert wp.fastest_at_level(nan_rows, 1e-4) is None


def test_separatrix_scene_sits_on_both_sides() -> None:
    scene = wp.separatrix_scene()
    i2 = scene.body.inertia[1]
    h, c = scene.body.hamiltonian(scene.states), scene.body.casimir(scene.states)
    np.testing.assert_allclose((2 * h * i2 - c) / c, [1e-3, -1e-3, 1e-2], rtol=1e-9)


def test_a_long_run_cut_short_ends_where_its_note_says() -> None:
    # A budget too small for the run: the last window ends on the step where it stopped, so
    # the figure's "to t = ..." and the note's "(t = ...)" are the same number.
    import re

    scene = wp.paper_scene()
    body = scene.system
    method = wp.Method("taylor3-cayley", "taylor", pr.taylor_integrator(body, 3, "cayley"))
    notes: list[str] = []
    rows = wp.long_run(scene, [method], n_steps=10**7, budget_s=0.3, notes=notes)
    note = next(n for n in notes if "stopped at" in n)
    stopped = int(re.search(r"stopped at (\d+) of", note).group(1))  # type: ignore[union-attr]
    assert max(r["step"] for r in rows) == stopped
    assert f"(t = {stopped * 0.1:g})" in note
    assert max(r["t"] for r in rows) == pytest.approx(stopped * 0.1)


def test_long_run_energy_error_is_relative_to_a_negative_h0() -> None:
    """A heavy top hanging down has H₀ < 0: the energy error is |H − H₀| / |H₀| (small for a
    Poisson integrator), not |H − |H₀|| / |H₀| (2, whatever the method)."""
    top = pr.HeavyTop()
    states = np.array([[0.2, -0.1, 0.3, 0.0, 0.0, -1.0], [0.5, 0.3, -0.2, 0.6, 0.0, -0.8]])
    assert (top.hamiltonian(states) < 0).all()
    scene = wp.Scene("hanging", top, states, 10.0)
    method = wp.Method("taylor5-exp", "taylor", pr.taylor_integrator(top, 5, "exp"))
    rows = wp.long_run(scene, [method], h=0.1, n_steps=200, budget_s=30.0)
    assert 0 < max(r["max_rel_dH"] for r in rows) < 1e-6

"""Polynomial-bivector systems in the studies: the cubic Nambu scene parses (and refuses
anything but a polynomial text), its classical integrators have their orders against DOP853,
and ``demo``, ``chart``, ``stability`` and ``select`` run on it end to end with the Nambu Casimir
reported absolute."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

import poisson_rs as pr
from poisson_rs.cli import main
from poisson_rs.scenes import load_scene
from poisson_rs.structures.polynomial import VectorFieldIntegrator
from poisson_rs.studies.methods import taylor_charts, taylor_orders

SCENE = Path(__file__).resolve().parents[1] / "scenes" / "nambu_cubic.toml"


def test_scene_parses_the_nambu_system() -> None:
    system = load_scene(SCENE).lie_system
    assert system.kind == "polynomial_bivector"
    x = np.random.default_rng(2).normal(size=(5, 3))
    c = system.casimirs(x)[:, 0]
    np.testing.assert_allclose(c, (x**2).sum(1) / 2 + x[:, 0] ** 3 / 3, rtol=1e-13)
    assert taylor_charts(system) == ("realization",)
    assert taylor_orders(system) == (1, 3, 5)
    assert pr.classical_methods(system) == ["rk4", "midpoint", "dop853"]


@pytest.mark.parametrize(
    "text",
    ['__import__("os").system("true")', "x1 + y", "exp(x1)", "x4**2", ""],
)
def test_scene_refuses_anything_but_a_polynomial(text: str, tmp_path: Path) -> None:
    path = tmp_path / "bad.toml"
    # A TOML literal string: the text as it is, quotes included.
    source = SCENE.read_text().replace('"x1**2/2 + x2**2/3 + x3**2/4"', f"'{text}'")
    path.write_text(source)
    with pytest.raises(ValueError, match=r"system\.hamiltonian"):
        load_scene(path)


@pytest.mark.parametrize(("name", "order"), [("rk4", 4.0), ("midpoint", 2.0)])
def test_classical_orders_against_dop853(name: str, order: float) -> None:
    system = load_scene(SCENE).lie_system
    x0 = np.array([[0.3, 0.5, -0.4], [0.1, -0.6, 0.3]])
    ref = pr.reference_solution(system, x0, [2.0])[:, 0]
    stepper = VectorFieldIntegrator(system, name)
    hs = [2.0 / n for n in (5, 10, 20)]
    errs = [np.abs(pr.integrate(stepper, x0, h, round(2.0 / h))[:, -1] - ref).max() for h in hs]
    assert np.polyfit(np.log(hs), np.log(errs), 1)[0] == pytest.approx(order, abs=0.2)


def test_demo_on_the_nambu_scene(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    assert main(["demo", "--scene", str(SCENE), "--out", str(out), "--steps", "20"]) == 0
    with (out / "metrics.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    methods = {r["method"] for r in rows}
    assert methods == {
        "taylor1-realization",
        "taylor3-realization",
        "taylor5-realization",
        "rk4",
        "midpoint",
    }
    drift = {r["method"]: float(r["max_rel_dC"]) for r in rows}
    # The realizations of order 3 and 5 keep C only to O(h⁵) and O(h⁷) a step: a drift, not
    # round-off, is reported, and the higher order drifts less.
    assert 1e-12 < drift["taylor3-realization"] < 1e-6
    assert drift["taylor5-realization"] < drift["taylor3-realization"] / 10


def test_realization_charts() -> None:
    """The chart "realization" matches the Taylor order, "realization{n}" names n; others fail."""
    system = load_scene(SCENE).lie_system
    assert pr.taylor_integrator(system, 5).realization_order == 5  # type: ignore[attr-defined]
    assert pr.taylor_integrator(system, 1, "realization2").name == "taylor1-realization2"
    for bad in ("realization0", "realization7", "realizationx", "exp", "log"):
        with pytest.raises(ValueError, match="realization1"):
            pr.taylor_integrator(system, 3, bad)


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def _slope(rows: list[dict[str, str]], method: str, column: str) -> float:
    pts = sorted((float(r["h"]), float(r[column])) for r in rows if r["method"] == method)
    return float(np.polyfit(np.log([p[0] for p in pts]), np.log([p[1] for p in pts]), 1)[0])


def test_chart_on_the_nambu_scene_fits_the_orders(tmp_path: Path) -> None:
    out = tmp_path / "chart"
    assert main(["chart", str(SCENE), "--quick", "--out", str(out)]) == 0
    rows = [r for r in _rows(out / "workprecision.csv") if r["failed"] == "False"]
    assert {r["method"] for r in rows} == {
        "taylor3-realization",
        "taylor5-realization",
        "rk4",
        "midpoint",
    }
    assert _slope(rows, "taylor3-realization", "error_T") == pytest.approx(4.0, abs=0.3)
    assert _slope(rows, "rk4", "error_T") == pytest.approx(4.0, abs=0.3)
    assert _slope(rows, "midpoint", "error_T") == pytest.approx(2.0, abs=0.2)
    # On the order-3 realization the Casimir defect is O(h⁵) a step: over a fixed T it drifts
    # as h⁴, a number, never "n/a".
    assert _slope(rows, "taylor3-realization", "max_rel_dC") == pytest.approx(4.0, abs=0.3)
    for name in ("workprecision_error.png", "workprecision_casimirs.png", "long_run_energy.png"):
        assert (out / name).stat().st_size > 0


def test_stability_and_select_on_the_nambu_scene(tmp_path: Path) -> None:
    out = tmp_path / "stability"
    argv = ["stability", str(SCENE), "--quick", "--out", str(out), "--horizon", "2"]
    assert main([*argv, "--no-progress"]) == 0
    rows = _rows(out / "stability.csv")
    assert {r["method"] for r in rows} == {
        "taylor3-realization",
        "taylor5-realization",
        "rk4",
        "midpoint",
    }
    small = [r for r in rows if float(r["h"]) == 0.1]
    assert small and all(float(r["rel_error"]) < 1e-4 for r in small)
    report = tmp_path / "select.json"
    assert main(["select", str(SCENE), "--budget", "3", "--json", str(report)]) == 0
    text = json.dumps(json.loads(report.read_text()))
    for name in ("taylor3-realization", "taylor5-realization", "rk4", "dop853"):
        assert name in text


@pytest.mark.parametrize("name", ["rk4", "midpoint"])
def test_core_classical_steps_equal_the_numpy_oracle(name: str) -> None:
    """RK4 and the midpoint rule run in the core (SIMD lanes) on the field's expanded terms;
    the NumPy step on the lambdified field is the oracle (the midpoint rule there by
    fixed-point iteration, so the two agree to the tolerance, not bit for bit)."""
    system = load_scene(SCENE).lie_system
    x0 = np.random.default_rng(5).uniform(-0.6, 0.6, (9, 3))
    stepper = VectorFieldIntegrator(system, name)
    traj = pr.integrate(stepper, x0, 0.1, 20)
    x = x0.copy()
    for _ in range(20):
        x, ok = stepper.step(x, 0.1)
        assert ok.all()
    np.testing.assert_allclose(traj[:, -1], x, rtol=0, atol=1e-12)
    # One state alone has the bits it has in the batch.
    assert pr.integrate(stepper, x0[4], 0.1, 20).tobytes() == traj[4].tobytes()


def test_core_classical_blow_up_is_a_failure_code() -> None:
    system = load_scene(SCENE).lie_system
    x0 = np.array([[0.3, 0.5, -0.4], [40.0, 40.0, 40.0]])
    traj, info = pr.integrate(
        VectorFieldIntegrator(system, "rk4"), x0, 0.5, 200, return_info=True, on_failure="ignore"
    )
    assert info.converged[0] and np.isfinite(traj[0]).all()
    assert not info.converged[1] and info.failure_code[1] == 3
    assert np.isnan(traj[1, info.failed_step[1] + 1 :]).all()

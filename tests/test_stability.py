"""The stability map: its rows, the failures it must record, and its reading."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from poisson_rs import RigidBody, taylor_integrator
from poisson_rs.studies.stability import (
    default_methods,
    directions,
    first_failures,
    stability_map,
    states,
)


def test_directions_straddle_the_separatrix() -> None:
    body = RigidBody()
    i2 = body.inertia[1]
    # Sign of 2H·I₂ − C tells the side: positive circulates about axis 1, negative about axis 3.
    side = {
        k: float(np.sum(d**2 * (i2 / np.array(body.inertia) - 1)))
        for k, d in directions(body).items()
    }
    assert side["axis 1 side"] > 0 > side["axis 3 side"]
    assert 0 < side["separatrix"] < 1e-2
    mu0, labels = states(body, radii=(1.0, 6.0))
    assert mu0.shape == (6, 3) and len(labels) == 6
    np.testing.assert_allclose(np.linalg.norm(mu0, axis=1), [1, 1, 1, 6, 6, 6])


def test_map_records_failures_instead_of_numbers() -> None:
    body = RigidBody()
    methods = {"taylor3-exp": lambda: taylor_integrator(body, 3, "exp")}
    rows = stability_map(
        body, step_sizes=(0.1, 2.0), radii=(1.0, 6.0), horizon=4.0, methods=methods
    )
    assert len(rows) == 2 * 6
    small = [r for r in rows if r["h"] == 0.1]
    assert all(r["converged"] and r["rel_error"] < 1e-3 for r in small)
    # |x| ≈ h|μ|/I reaches the exponential chart's singularity at 2π: Newton must say so.
    failed = [r for r in rows if not r["converged"]]
    assert failed and all(r["h"] == 2.0 and r["radius"] == pytest.approx(6.0) for r in failed)
    assert all(r["failure"] == "chart singular" and np.isnan(r["rel_error"]) for r in failed)
    for r in rows:
        assert r["max_rel_dC"] < 1e-12 or not r["converged"]


def test_first_failures_orders_methods_by_the_step_where_they_break() -> None:
    def row(m: str, h: float, err: float, ok: bool = True) -> dict[str, object]:
        return {"method": m, "h": h, "rel_error": err, "converged": ok, "failure": "x"}

    rows = [
        row("a", 0.1, 1e-5),
        row("a", 1.0, 1e-5, ok=False),
        row("b", 0.1, 0.5),
        row("b", 1.0, 1.0),
        row("c", 0.1, 1e-5),
        row("c", 1.0, 1e-3),
    ]
    got = first_failures(rows, threshold=0.1)
    assert [r["method"] for r in got] == ["b", "a", "c"]
    assert got[0]["h_breaks"] == 0.1 and "error > 0.1" in got[0]["how"]
    assert got[1]["h_breaks"] == 1.0 and "step failure" in got[1]["how"]
    assert got[2]["h_breaks"] == pytest.approx(float("inf"))


def test_cli_writes_the_map_and_its_numbers(tmp_path: Path) -> None:
    import csv

    from poisson_rs.cli import main

    assert main(["stability", "--quick", "--out", str(tmp_path), "--no-progress"]) == 0
    for name in (
        "stability_map.png",
        "stability_summary.png",
        "stability.csv",
        "stability.json",
        "first_failures.csv",
    ):
        assert (tmp_path / name).stat().st_size > 0, name
    with (tmp_path / "stability.csv").open() as f:
        rows = list(csv.DictReader(f))
    # Every method × 2 step sizes × 12 states is recorded.
    n_methods = len(default_methods(RigidBody()))
    assert n_methods >= 7 and len(rows) == n_methods * 2 * 12
    assert {"rel_error", "max_rel_dH", "max_rel_dC", "converged", "failure"} <= set(rows[0])


def test_the_map_takes_the_taylor_orders_the_system_offers_a_study() -> None:
    """Jets stop at order 3 in a study (a fifth-order jet step of the four vortices takes over
    100 ms): the map of an expression system has no taylor5; the rigid body keeps both orders in
    its first chart."""
    from poisson_rs.scenes import load_scene

    scene = Path(__file__).resolve().parent.parent / "scenes" / "point_vortices_4.toml"
    vortices = [k for k in default_methods(load_scene(scene).system) if k.startswith("taylor")]
    assert vortices == ["taylor3-jets"]
    rigid = [k for k in default_methods(RigidBody()) if k.startswith("taylor")]
    assert rigid == ["taylor3-cayley", "taylor5-cayley", "taylor3-exp"]

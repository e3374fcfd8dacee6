"""The size sweep: a tiny seeded run returns every column with the right types, its parameter
counts are the models', its errors agree with an independent torch rollout against the exact
solution, the chart and tables are written, and bad input is refused before any training."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from poisson_rs import RigidBody, exact_solution, integrate, load_model
from poisson_rs.cli import main
from poisson_rs.studies.demo import PAPER_STATES
from poisson_rs.studies.sweep import (
    BASELINES,
    COLUMNS,
    HELD_OUT,
    medians,
    parameter_count,
    run_sweep,
)

ARCHS = ((4,), (3, 5))
TINY: dict[str, Any] = {"iterations": 15, "batch": 128, "shipped": (), "speed_seconds": 0.01}


@pytest.fixture(scope="module")
def swept(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[dict[str, Any]], Path]:
    folder = tmp_path_factory.mktemp("sweep_models")
    return run_sweep(ARCHS, (1,), models_out=folder, **TINY), folder


def test_rows_have_every_column_with_its_type(swept: tuple[list[dict[str, Any]], Path]):
    rows, _ = swept
    assert [r["model"] for r in rows] == [
        "4",
        "3-5",
        "taylor3-cayley",
        "taylor5-cayley",
        "taylor3-exp",
        "taylor5-exp",
    ]
    for r in rows:
        assert tuple(r) == COLUMNS
        assert isinstance(r["params"], int) and isinstance(r["depth"], int)
        assert isinstance(r["converged"], bool) and r["converged"]
        for k in ("error_112", "error_320", "error_held_out", "max_rel_dH", "steps_per_s"):
            assert isinstance(r[k], float) and math.isfinite(r[k]) and r[k] > 0, k
    learned = [r for r in rows if r["kind"] == "learned"]
    assert [r["seed"] for r in learned] == [1, 1]
    assert all(r["iterations"] == 15 and r["train_seconds"] > 0 for r in learned)
    assert all(r["sampling"] == "uniform" and r["trained_on"] == "CPU" for r in learned)
    taylor = [r for r in rows if r["kind"] == "taylor"]
    assert all(r["params"] == 0 and r["seed"] is None for r in taylor)
    # The reference lines are the known values (README table): Taylor K=3 (Cayley) from (1,1,2)
    # 4.35e-4 and from (3,2,0) 8.54e-3; K=5 (Cayley) 5.58e-6 and 3.99e-4.
    assert taylor[0]["error_112"] == pytest.approx(4.35e-4, rel=0.01)
    assert taylor[0]["error_320"] == pytest.approx(8.54e-3, rel=0.01)
    assert taylor[1]["error_112"] == pytest.approx(5.58e-6, rel=0.01)
    assert taylor[1]["error_320"] == pytest.approx(3.99e-4, rel=0.01)


def test_parameter_counts_are_the_models(swept: tuple[list[dict[str, Any]], Path]):
    rows, folder = swept
    for widths, row in zip(ARCHS, rows, strict=False):
        model = load_model(folder / f"{row['model']}_seed1.safetensors")
        torch_count = sum(p.numel() for p in model.generating.mlp.parameters())
        assert row["params"] == model.n_parameters == torch_count == parameter_count(widths)
        assert model.metadata["widths"] == widths
    assert parameter_count((8, 8)) == 121  # the default model's, as the README says


def test_errors_match_a_recomputation_against_the_exact_solution(
    swept: tuple[list[dict[str, Any]], Path],
):
    """Each saved model rolled out again from the 18 states, its end states compared with the
    closed-form solution at t = 10, its energy along the way with H(μ₀)."""
    rows, folder = swept
    body = RigidBody((1.5, 2.0, 2.5))
    states = np.concatenate([PAPER_STATES, HELD_OUT.sample()])
    exact = exact_solution(body, states, [10.0])[:, 0]
    for row in rows[:2]:
        model = load_model(folder / f"{row['model']}_seed1.safetensors")
        traj = integrate(model, states, 0.1, 100)
        err = np.linalg.norm(traj[:, -1] - exact, axis=1)
        h0 = body.hamiltonian(states[:2])
        dh = np.max(np.abs(body.hamiltonian(traj[:2]) - h0[:, None]) / h0[:, None])
        assert row["error_112"] == pytest.approx(err[0], rel=1e-12)
        assert row["error_320"] == pytest.approx(err[1], rel=1e-12)
        assert row["error_held_out"] == pytest.approx(err[2:].max(), rel=1e-12)
        assert row["max_rel_dH"] == pytest.approx(dh, rel=1e-12)
    # The Rust steps are the model's own: one step against the pure-torch step map.
    model = load_model(folder / "4_seed1.safetensors")
    torch_step = model.torch_step(torch.as_tensor(PAPER_STATES), 0.1).numpy()
    np.testing.assert_allclose(integrate(model, PAPER_STATES, 0.1, 1)[:, 1], torch_step, rtol=1e-12)


def test_the_sweep_is_seeded(swept: tuple[list[dict[str, Any]], Path]):
    rows, _ = swept
    again = run_sweep(ARCHS[:1], (1,), baselines=False, **TINY)
    assert len(again) == 1
    for k in ("error_112", "error_320", "error_held_out", "max_rel_dH", "validation_rms"):
        assert again[0][k] == rows[0][k], k


def test_medians_over_seeds():
    def row(model: str, seed: int, err: float, seconds: float | None) -> dict[str, Any]:
        return {
            **dict.fromkeys(COLUMNS),
            "model": model,
            "kind": "learned",
            "depth": 2,
            "seed": seed,
            "params": 121,
            "iterations": 2000,
            "train_seconds": seconds,
            "error_112": err,
            "converged": seed != 2,
        }

    rows = [row("8-8", 0, 1e-4, 10.0), row("8-8", 1, 3e-4, 30.0), row("8-8", 2, 2e-4, None)]
    rows.append(row("4-4", 0, 5e-3, 5.0))
    med = medians(rows)
    assert [m["model"] for m in med] == ["8-8", "4-4"]
    assert med[0]["n_seeds"] == 3 and med[0]["error_112"] == pytest.approx(2e-4)
    assert med[0]["params"] == 121 and isinstance(med[0]["params"], int)
    assert med[0]["train_seconds"] is None  # one seed has no time: no median
    assert med[0]["converged"] is False and med[1]["converged"] is True


def test_cli_sweep_writes_tables_and_chart_and_replots(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    out = tmp_path / "out"
    args = ["sweep", "--fast", "--widths", "4", "--no-progress", "--out", str(out)]
    assert main(args) == 0
    names = {p.name for p in out.iterdir()}
    assert {"sweep.png", "sweep.csv", "sweep.json", "sweep_medians.csv"} <= names
    assert (out / "sweep.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = json.loads((out / "sweep.json").read_text())
    assert [r["model"] for r in rows] == ["4"] + [f"taylor{k}-{c}" for k, c in BASELINES]
    assert rows[0]["iterations"] == 20
    lines = (out / "sweep.csv").read_text().splitlines()
    assert lines[0].split(",") == list(COLUMNS) and len(lines) == len(rows) + 1
    assert "taylor5-exp" in capsys.readouterr().out
    # Redrawn from the saved numbers alone, with a shipped point and a failed rollout added.
    rows.append({**rows[0], "model": "paper", "kind": "shipped", "trained_on": "H100"})
    rows.append({**rows[0], "seed": 2, "error_320": math.inf, "converged": False})
    (out / "more.json").write_text(json.dumps(rows))
    (out / "sweep.png").unlink()
    assert main(["sweep", "--replot", str(out / "more.json"), "--out", str(out)]) == 0
    assert (out / "sweep.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"architectures": []}, "non-empty list of hidden widths"),
        ({"architectures": [()]}, "non-empty list of integers"),
        ({"architectures": [(8, 0)]}, ">= 1"),
        ({"architectures": [(8, 2.5)]}, "integers"),
        ({"architectures": [(8,), (8,)]}, "repeat"),
        ({"seeds": [-1]}, ">= 0"),
        ({"seeds": []}, "must not be empty"),
        ({"seeds": [0, 0]}, "repeat"),
        ({"shipped": ["no-such-model"]}, "unknown shipped model 'no-such-model'"),
        ({"iterations": -1}, "invalid iterations"),
        ({"overrides": {"widths": (4,)}}, "cannot set 'widths'"),
        ({"overrides": {"sampling": "scene"}}, "needs sampling_states"),
        ({"speed_seconds": 0.0}, "speed_seconds"),
    ],
)
def test_bad_input_is_refused_before_training(kwargs: dict[str, Any], match: str):
    args = {"architectures": [(4,)], "seeds": [0], **kwargs}
    architectures, seeds = args.pop("architectures"), args.pop("seeds")
    with pytest.raises(ValueError, match=match):
        run_sweep(architectures, seeds, **args)


def test_cli_refuses_malformed_widths(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    assert main(["sweep", "--widths", "8,x", "--out", str(tmp_path)]) == 2
    assert "8,8" in capsys.readouterr().err
    assert main(["sweep", "--seeds", "-1", "--fast", "--out", str(tmp_path)]) == 2
    assert "--seeds: needs an integer in [0," in capsys.readouterr().err
    assert not any(tmp_path.iterdir())

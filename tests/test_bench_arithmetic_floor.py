"""`benches/arithmetic_floor.py`: the flops a learned step's network takes, by the module's
counting rules, and its refusal of a costs file it cannot read."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
# The benches are scripts, not part of the package: make their directory importable.
sys.path.insert(0, str(ROOT / "benches"))
import arithmetic_floor as af  # noqa: E402


def test_counts_of_a_network_small_enough_to_count_by_hand() -> None:
    # n = 1: a packed jet is (value, gradient, Hessian), J = 3. Widths (2,): layers 2 → 2 → 1,
    # 4 and 2 weights. Hessian pass: the first layer 4 × 2 ((t, p) inputs: value only), the
    # output 2 × 2J = 12, each hidden unit tanh 38 + σ', σ'' 4 + gradient 1 + Hessian 4 = 47.
    assert af.network_flops([2], 1, homogeneous=False) == {
        "hessian_pass": 8 + 12 + 2 * 47,
        "gradient_pass": 4 * 6 + 2 * 41,
        "weights": 6,
    }
    # Homogeneous inputs carry full jets into the first layer: 4 × 2J = 24 instead of 8.
    assert af.network_flops([2], 1, homogeneous=True)["hessian_pass"] == 24 + 12 + 2 * 47


def test_the_hessian_pass_grows_with_the_jet_and_the_gradient_pass_does_not() -> None:
    # n = 3 → 6: J goes 10 → 28; a weight of an inner layer costs 2J in the Hessian pass and 4
    # in the gradient pass whatever n is.
    a, b = af.network_flops([8, 8], 3, False), af.network_flops([8, 9], 3, False)
    assert b["hessian_pass"] - a["hessian_pass"] == 8 * 20 + 1 * 20 + (38 + 4 + 3 + 24)
    assert b["gradient_pass"] - a["gradient_pass"] == 4 * (8 + 1) + 41
    c = af.network_flops([8, 9], 6, False)
    assert c["gradient_pass"] - b["gradient_pass"] == 4 * 3 * 8  # three more inputs


@pytest.mark.parametrize(("widths", "n"), [([], 3), ([4, 0], 3), ([4], 0)])
def test_a_network_without_units_is_refused(widths: list[int], n: int) -> None:
    with pytest.raises(ValueError, match="must be positive"):
        af.network_flops(widths, n, False)


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    script = ROOT / "benches" / "arithmetic_floor.py"
    return subprocess.run(
        [sys.executable, str(script), *args], cwd=cwd, capture_output=True, text=True, timeout=300
    )


def test_a_costs_file_it_cannot_read_is_named(tmp_path: Path) -> None:
    bad = tmp_path / "costs.json"
    bad.write_text("{not json")
    run = _run("--costs", str(bad), cwd=tmp_path)
    assert run.returncode != 0 and f"--costs {bad}: not a step_costs.py JSON" in run.stderr
    bad.write_text(json.dumps({"rows": [{"system": "rigid body", "stepper": "rk4"}]}))
    run = _run("--costs", str(bad), cwd=tmp_path)
    assert run.returncode != 0 and "no row for rigid body, learned:default" in run.stderr
    assert "GFLOP/s" not in run.stdout  # refused before the multiply was timed


def _costs(with_log_taylor: bool) -> list[dict[str, object]]:
    """Made-up costs: RK4 1 ns, each learned and Taylor step 100 ns, 3 updates."""
    rows: list[dict[str, object]] = []
    for name, system in af.MODELS.items():
        rows.append({"system": system, "stepper": "rk4", "ns_per_step": 1.0})
        rows.append(
            {
                "system": system,
                "stepper": f"learned:{name}",
                "ns_per_step": 100.0,
                "newton_updates_per_step": 3.0,
            }
        )
    for system in af.LOG_TAYLOR if with_log_taylor else ():
        rows.append({"system": system, "stepper": "rk4", "ns_per_step": 1.0})
        for k in af.LOG_TAYLOR_ORDERS:
            rows.append(
                {
                    "system": system,
                    "stepper": f"taylor{k}-log",
                    "ns_per_step": 100.0,
                    "newton_updates_per_step": 3.0,
                }
            )
    return rows


def test_the_floor_of_the_shipped_models_from_a_costs_file(tmp_path: Path) -> None:
    # Costs made up so that every ratio is known: RK4 1 ns, each learned step 100 ns, 3 updates.
    costs = tmp_path / "costs.json"
    costs.write_text(json.dumps({"rows": _costs(False)}))
    out = tmp_path / "floor.json"
    run = _run("--costs", str(costs), "--json", str(out), "--peak", "100", cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    doc = json.loads(out.read_text())
    rate = doc["matmul_flops_per_s"]
    for row in doc["rows"]:
        flops = row["hessian_pass"] + 2 * row["gradient_pass"]
        assert row["network_flops_per_step"] == flops
        assert row["floor_vs_rk4"] == pytest.approx(flops / rate * 1e9)
        assert row["floor_vs_rk4_at_peak"] == pytest.approx(flops / 100.0)
        assert row["measured_vs_rk4"] == 100.0
    widths = {r["model"]: (r["widths"], r["inputs"]) for r in doc["rows"]}
    assert widths["default"] == ([8, 8], "homogeneous")
    assert widths["heavy_top_h05"] == ([32, 32], "t,p")


def test_counts_of_an_exponential_polynomial_small_enough_to_count_by_hand() -> None:
    # N = 2, terms y₁, y₁² y₂⁻¹ and a constant. Weights c·t^k times a factor each (a division
    # too for y₂⁻¹): 2 + 4 + 1 = 7. Gradients 2m: 2 + 4 + 0. Upper Hessians m(m + 1): 2 + 6 + 0.
    # A pass: two exponentials (50) and y₁'s table up to y₁² (1).
    e = np.array([[1, 0], [2, -1], [0, 0]])
    assert af.log_taylor_flops(e) == {
        "hessian_pass": 7 + 6 + 8 + 51,
        "gradient_pass": 7 + 6 + 51,
        "terms": 3,
    }


def test_exponents_that_are_not_a_table_are_refused() -> None:
    with pytest.raises(ValueError, match="must be"):
        af.log_taylor_flops(np.array([1, 2, 3]))


def test_the_lotka_volterra_taylor_floors_from_a_costs_file(tmp_path: Path) -> None:
    costs = tmp_path / "costs.json"
    # Without the Taylor rows, --log-taylor is refused before the multiply is timed.
    costs.write_text(json.dumps({"rows": _costs(False)}))
    run = _run("--costs", str(costs), "--log-taylor", cwd=tmp_path)
    assert run.returncode != 0 and "no row for lotka-volterra, taylor3-log" in run.stderr
    assert "GFLOP/s" not in run.stdout
    costs.write_text(json.dumps({"rows": _costs(True)}))
    out = tmp_path / "floor.json"
    run = _run("--costs", str(costs), "--json", str(out), "--log-taylor", cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    doc = json.loads(out.read_text())
    rate = doc["matmul_flops_per_s"]
    rows = {(r["system"], r["order"]): r for r in doc["log_taylor_rows"]}
    assert set(rows) == {(s, k) for s in af.LOG_TAYLOR for k in af.LOG_TAYLOR_ORDERS}
    for row in rows.values():
        assert row["flops_per_step"] == row["gradient_pass"] + 3 * row["hessian_pass"]
        assert row["flops_per_step_simplified"] == row["hessian_pass"] + 3 * row["gradient_pass"]
        assert row["floor_vs_rk4"] == pytest.approx(row["flops_per_step"] / rate * 1e9)
        assert row["measured_vs_rk4"] == 100.0
    # The counted S is the bench's: PNN's system at K = 3 has the fewest terms, the 5-D one at
    # K = 5 has 247 (15, 99, 108, 24 and 1 in one to five variables).
    assert rows[("lotka-volterra 5d", 5)]["terms"] == 247
    assert min(rows.values(), key=lambda r: r["terms"]) is rows[("lotka-volterra", 3)]

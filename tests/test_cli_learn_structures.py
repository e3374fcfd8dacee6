"""``poisson-rs learn --structure SYSTEM.json|discover``: a learned system written as JSON (its
``to_dict()`` plus the integrator's settings and the report's summary) that every ``--system``
reads back, NOT EXPLAINED as its own exit status, and every bad input refused with one line
naming the flag before any work."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.integrate import solve_ivp

import poisson_rs as pr
from poisson_rs.cli import main
from poisson_rs.cli.common import system_spec
from poisson_rs.learn import api
from poisson_rs.learn.cli import NOT_EXPLAINED_STATUS, SYSTEM_FILE_FORMAT
from poisson_rs.structures.expression_system import with_hamiltonian

H = 0.1
LV = pr.lotka_volterra([[0, 1], [-1, 0]], [1.0, 2.0])
LV_STARTS = np.array([[1.0, 0.8], [1.0, 1.0], [1.0, 1.2]])


@cache
def _lv_records() -> np.ndarray:
    """Exact Lotka–Volterra records: 3 trajectories × 41, h = 0.1 (PNN's starts)."""
    return np.asarray(LV.reference_solution(LV_STARTS, np.arange(41) * H))


@pytest.fixture
def files(tmp_path: Path) -> dict[str, str]:
    """The LV records (.npz), the LV system (.json) and a rigid body (.json) in tmp_path."""
    np.savez(tmp_path / "lv.npz", trajectories=_lv_records())
    (tmp_path / "lv.json").write_text(json.dumps(LV.to_dict()))
    (tmp_path / "rb.json").write_text(json.dumps(pr.RigidBody().to_dict()))
    return {
        "data": str(tmp_path / "lv.npz"),
        "lv_json": str(tmp_path / "lv.json"),
        "rb_json": str(tmp_path / "rb.json"),
    }


def _never(*args: Any, **kwargs: Any) -> Any:
    raise AssertionError("pr.learn ran on refused input")


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


# --- --structure FILE: learn → JSON → read back ----------------------------------------------


def test_structure_file_round_trip(
    files: dict[str, str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "learned.json"
    argv = ["learn", files["data"], "--structure", files["lv_json"], "--h", "0.1"]
    assert main([*argv, "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "KEPT" in printed and f"wrote {out}" in printed
    doc = json.loads(out.read_text())  # strict JSON: no NaN
    learned = doc["learned"]
    assert learned["format"] == SYSTEM_FILE_FORMAT
    assert learned["integrator"] == {"method": "taylor-hj", "order": 5, "chart": "log"}
    summary = learned["report"]
    assert summary["explained"] and summary["kept"] == "log+poly1"
    assert summary["one_step"] <= summary["threshold"]
    assert "ln(u)" in summary["hamiltonian"]
    # What every verb's --system reads; the same system as pr.learn's, H to 1e-8.
    back = system_spec(str(out))
    stepper, report = pr.learn(_lv_records(), H, structure=LV, progress=False)
    x = _lv_records().reshape(-1, 2)
    assert back.kind == "log_canonical"
    assert np.max(np.abs(back.hamiltonian(x) - report.system.hamiltonian(x))) <= 1e-8
    # And close to the true H (up to a constant: none here, H = u − ln u + v − 2 ln v).
    assert np.max(np.abs(back.hamiltonian(x) - LV.hamiltonian(x))) <= 1e-5
    # The integrator the file names steps as the learned stepper does.
    rebuilt = pr.taylor_integrator(back, learned["integrator"]["order"], "log")
    a = pr.integrate(rebuilt, LV_STARTS, H, 50)
    b = pr.integrate(stepper, LV_STARTS, H, 50)
    assert np.max(np.abs(a - b)) <= 1e-12
    # The file is a structure file too: --structure takes it back (its H ignored), and so is
    # an expression system on the same bracket (what the term library learns).
    (tmp_path / "expr.json").write_text(json.dumps(with_hamiltonian(LV, "u*v").to_dict()))
    for spec in (out, tmp_path / "expr.json"):
        again = tmp_path / f"{spec.stem}-again.json"
        argv = ["learn", files["data"], "--structure", str(spec), "--h", "0.1", "--no-progress"]
        assert main([*argv, "--out", str(again)]) == 0
        doc = json.loads(again.read_text())
        assert doc["kind"] == "log_canonical"
        np.testing.assert_allclose(pr.system_from_dict(doc).hamiltonian(x), back.hamiltonian(x))


def test_a_learned_system_file_runs_the_demo(
    files: dict[str, str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A real process writes the file; ``poisson-rs demo --system`` runs on it."""
    out = tmp_path / "learned.json"
    env = {**os.environ, "PYTHONPATH": str(Path(pr.__file__).resolve().parents[1])}
    argv = ["learn", files["data"], "--structure", files["lv_json"], "--h", "0.1"]
    done = subprocess.run(
        [sys.executable, "-m", "poisson_rs.cli", *argv, "--out", str(out), "--no-progress"],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert "KEPT" in done.stdout and out.is_file()
    demo = tmp_path / "demo"
    assert main(["demo", "--system", str(out), "--steps", "20", "--out", str(demo)]) == 0
    assert "taylor5-log" in (demo / "metrics.csv").read_text()
    assert "system: learned, log-canonical" in capsys.readouterr().out


def test_a_lie_poisson_structure_file_writes_a_model_file(
    files: dict[str, str], tmp_path: Path
) -> None:
    """A Lie–Poisson system learns on T*G, as --algebra does: a model file."""
    rng = np.random.default_rng(3)
    x0 = rng.normal(size=(6, 3))
    x0 /= np.linalg.norm(x0, axis=1)[:, None]
    np.savez(
        tmp_path / "rb.npz",
        trajectories=np.asarray(pr.reference_solution(pr.RigidBody(), x0, np.arange(6) * H)),
    )
    out = tmp_path / "m.safetensors"
    argv = ["learn", str(tmp_path / "rb.npz"), "--structure", files["rb_json"], "--h", "0.1"]
    argv += ["--mode", "hamiltonian", "--degree", "2", "--no-progress", "--out", str(out)]
    assert main(argv) == 0
    model = pr.load_model(str(out))
    assert model.metadata["learn_mode"] == "hamiltonian"


# --- --structure discover ----------------------------------------------------------------------


def test_discover_writes_the_learned_bracket_and_h(
    files: dict[str, str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "found.json"
    argv = ["learn", files["data"], "--structure", "discover", "--h", "0.1", "--no-progress"]
    assert main([*argv, "--out", str(out)]) == 0
    assert "bracket: {u, v} = 1*u*v" in capsys.readouterr().out
    doc = json.loads(out.read_text())
    summary = doc["learned"]["report"]
    assert summary["mode"] == "discover/auto" and summary["explained"]
    assert summary["bracket"] == "{u, v} = 1*u*v"
    assert summary["kept"] == "log-canonical/log+poly1"
    back = pr.system_from_dict(doc)
    x = _lv_records().reshape(-1, 2)
    np.testing.assert_allclose(back.vector_field(x), LV.vector_field(x), rtol=0, atol=1e-5)
    stepper, _ = pr.learn(_lv_records(), H, structure="discover", progress=False)
    settings = doc["learned"]["integrator"]
    rebuilt = pr.taylor_integrator(back, settings["order"], settings["chart"])
    a = pr.integrate(rebuilt, LV_STARTS, H, 50)
    assert np.max(np.abs(a - pr.integrate(stepper, LV_STARTS, H, 50))) <= 1e-12


def test_discover_writes_a_found_lie_algebra_as_json(tmp_path: Path) -> None:
    """A Lie–Poisson bracket found by discovery is a system file, not a model file."""
    rb = pr.RigidBody((2.0, 1.0, 2.0 / 3.0))
    rng = np.random.default_rng(0)
    x0 = rng.normal(size=(6, 3))
    x0 /= np.linalg.norm(x0, axis=1)[:, None]
    np.savez(tmp_path / "rb.npz", trajectories=pr.reference_solution(rb, x0, np.arange(41) * H))
    argv = ["learn", str(tmp_path / "rb.npz"), "--structure", "discover", "--h", "0.1"]
    assert main([*argv, "--no-progress", "--out", str(tmp_path / "x.safetensors")]) == 2
    assert main([*argv, "--no-progress", "--out", str(tmp_path / "rb_found.json")]) == 0
    doc = json.loads((tmp_path / "rb_found.json").read_text())
    assert doc["kind"] == "lie_poisson" and doc["learned"]["integrator"]["chart"] == "exp"
    back = system_spec(str(tmp_path / "rb_found.json"))
    x = rng.normal(size=(10, 3))
    np.testing.assert_allclose(back.vector_field(x), rb.vector_field(x), rtol=0, atol=1e-7)


def _damped_records(path: Path) -> None:
    """Lotka–Volterra with self-limitation (u̇ = u(v − 2 − u/2)): a stable focus, so no
    Poisson system; exact records, 3 × 21."""
    out = []
    for z0 in LV_STARTS:
        sol = solve_ivp(
            lambda t, z: [z[0] * (z[1] - 2 - 0.5 * z[0]), z[1] * (1 - z[0])],
            (0, 2),
            z0,
            t_eval=np.arange(21) * H,
            method="DOP853",
            rtol=1e-13,
            atol=1e-13,
        )
        out.append(sol.y.T)
    np.savez(path, trajectories=np.array(out))


def test_discover_not_explained_has_its_own_status_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _damped_records(tmp_path / "damped.npz")
    out = tmp_path / "d.json"
    argv = ["learn", str(tmp_path / "damped.npz"), "--structure", "discover", "--degree", "1"]
    argv += ["--h", "0.1", "--no-progress", "--out", str(out)]
    assert main(argv) == NOT_EXPLAINED_STATUS == 3
    captured = capsys.readouterr()
    assert "NOT EXPLAINED" in captured.out
    assert "NOT EXPLAINED" in _one_line(captured.err) and "--keep-unexplained" in captured.err
    assert not out.exists()
    assert main([*argv, "--keep-unexplained"]) == NOT_EXPLAINED_STATUS
    doc = json.loads(out.read_text())
    assert doc["learned"]["report"]["explained"] is False
    # A spent budget: the first pair alone is fitted, the rest listed as not tried.
    budget = [*argv, "--keep-unexplained", "--force", "--max-seconds", "1e-9"]
    assert main(budget) == NOT_EXPLAINED_STATUS
    rows = json.loads(out.read_text())["learned"]["report"]["candidates"]
    assert any("time budget (max_seconds = 1e-09)" in r["reason"] for r in rows)


# --- refusals: exit status 2, one line naming the flag, no work --------------------------------


def _bad_cases(tmp: Path, f: dict[str, str]) -> list[tuple[list[str], str]]:
    (tmp / "bad.json").write_text("{")
    (tmp / "list.json").write_text("[1, 2]")
    (tmp / "algebra.json").write_text(json.dumps(pr.LieAlgebra.so3().to_dict()))
    (tmp / "nokind.json").write_text(json.dumps({"kind": "nothing"}))
    # An expression system's bracket is its base's: a rigid body's gives a model file.
    expr = with_hamiltonian(pr.RigidBody(), "x1**2/2 - cos(x3)")
    (tmp / "expr.json").write_text(json.dumps(expr.to_dict()))
    (tmp / "exists.json").write_text("keep me")
    (tmp / "folder.json").mkdir()
    lv, d = f["lv_json"], f["data"]
    out = ["--out", str(tmp / "o.json")]
    model = ["--out", str(tmp / "m.safetensors")]
    return [
        (["--structure", str(tmp / "missing.json"), *out], "--structure"),
        (["--structure", str(tmp / "bad.json"), *out], "--structure"),
        (["--structure", d, *out], "--structure"),  # binary, not JSON
        (["--structure", str(tmp / "list.json"), *out], "--structure"),
        (["--structure", str(tmp / "algebra.json"), *out], "--structure"),
        (["--structure", str(tmp / "nokind.json"), *out], "--structure"),
        (["--structure", str(tmp / "expr.json"), *out], "--out"),
        (["--structure", lv, "--algebra", "so3", *out], "--structure"),
        (["--structure", "discover", "--system", f["rb_json"], *out], "--structure"),
        (["--structure", "discover", "--mode", "map", *out], "--structure"),
        (["--structure", lv, "--mode", "hj+data", *out], "--structure"),
        (["--structure", f["rb_json"], "--mode", "hj+data", *model], "--structure"),
        (["--structure", lv, "--degree", "5", *out], "--degree"),
        (["--structure", "discover", "--degree", "0", *out], "--degree"),
        (["--structure", lv, "--degree", "two", *out], "--degree"),
        (["--structure", lv, "--max-degree", "9", *out], "--max-degree"),
        (["--structure", lv, "--out", str(tmp / "o.safetensors")], "--out"),
        (["--structure", "discover", "--out", str(tmp / "o.npz")], "--out"),
        (["--structure", f["rb_json"], *out], "--out"),  # Lie–Poisson: a model file
        (["--algebra", "so3", *out], "--out"),
        (["--structure", lv, "--out", str(tmp / "exists.json")], "--out"),
        (["--structure", lv, "--out", str(tmp / "folder.json")], "--out"),  # a directory
        (["--structure", lv, "--h", "-1", *out], "--h"),
        (["--structure", "discover", "--seed", "-1", *out], "--seed"),
        (["--structure", "discover", "--max-seconds", "0", *out], "--max-seconds"),
        (["--structure", "discover", "--max-seconds", "nan", *out], "--max-seconds"),
        (["--structure", lv, "--max-seconds", "10", *out], "--max-seconds"),
    ]


def test_every_bad_input_is_one_line_naming_the_flag_before_any_work(
    files: dict[str, str],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setattr(api, "learn", _never)
    for extra, flag in _bad_cases(tmp_path, files):
        argv = ["learn", files["data"], "--h", "0.1", *extra]
        code = main(argv)
        line = _one_line(capsys.readouterr().err)
        assert code == 2, (extra, line)
        assert line.startswith("poisson-rs learn: ") and flag in line, (extra, line)
    assert (tmp_path / "exists.json").read_text() == "keep me"
    assert not (tmp_path / "o.json").exists()


def test_a_file_that_appears_during_the_fit_is_not_replaced(
    files: dict[str, str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "learned.json"
    real = api.learn

    def learn_then_someone_writes(*args: Any, **kwargs: Any) -> Any:
        result = real(*args, **kwargs)
        out.write_text("another run's system")
        return result

    monkeypatch.setattr(api, "learn", learn_then_someone_writes)
    argv = ["learn", files["data"], "--structure", files["lv_json"], "--h", "0.1"]
    assert main([*argv, "--no-progress", "--out", str(out)]) == 2
    assert out.read_text() == "another run's system"


def test_help_documents_the_suffixes_and_the_exit_statuses(
    capsys: pytest.CaptureFixture[str],
) -> None:
    with pytest.raises(SystemExit) as done:
        main(["learn", "--help"])
    assert done.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "--structure SYSTEM.json|discover" in text
    assert "--out must end in .safetensors" in text and "--out must end in .json" in text
    assert f"{NOT_EXPLAINED_STATUS} --structure discover: NOT EXPLAINED" in text
    assert "--keep-unexplained" in text

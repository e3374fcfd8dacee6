"""Regression tests for hardening: writers replace only regular files, checkpoints cannot run
code, settings and outputs are checked before the work, training reports its baseline."""

from __future__ import annotations

import os
import shlex
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from conftest import build_generating, count_dop853_rhs
from matplotlib.figure import Figure

import poisson_rs as pr
from poisson_rs import cli
from poisson_rs.export import save_model
from poisson_rs.files import atomic_write_bytes, check_output_path
from poisson_rs.studies import figures as charts
from poisson_rs.train import TrainConfig, baseline_rms, save_result, train


def _tiny(**overrides: Any) -> TrainConfig:
    base: dict[str, Any] = {"widths": (4,), "batch": 64, "iterations": 5, "lr": 1e-2, "seed": 3}
    return TrainConfig(**{**base, **overrides})


def _save(path: Path) -> Path:
    return save_model(
        build_generating(0, widths=(4,)),
        path,
        inertia=(1.5, 2.0, 2.5),
        h_max=0.1,
        domain={"kind": "shell", "r_min": 1.0, "r_max": 4.0},
    )


# --- writers: only a regular file or a new path ------------------------------------------------


def _specials(tmp_path: Path) -> dict[str, Path]:
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    target = tmp_path / "target.txt"
    target.write_text("keep me")
    link = tmp_path / "link"
    link.symlink_to(target)
    folder = tmp_path / "folder"
    folder.mkdir()
    return {"FIFO": fifo, "symbolic link": link, "directory": folder}


@pytest.mark.parametrize(
    "write",
    [
        _save,
        lambda p: charts.write_rows([{"a": 1}], p),
        lambda p: charts._savefig(Figure(figsize=(1, 1)), p),
        lambda p: atomic_write_bytes(p, b"x"),
    ],
    ids=["save_model", "write_rows", "figure", "atomic_write_bytes"],
)
def test_writers_refuse_fifos_links_and_directories(tmp_path: Path, write: Any):
    for what, path in _specials(tmp_path).items():
        mode = os.lstat(path).st_mode
        with pytest.raises(ValueError, match=what):
            write(path)
        assert os.lstat(path).st_mode == mode  # still the FIFO, link or directory
    assert (tmp_path / "target.txt").read_text() == "keep me"
    assert not list(tmp_path.glob(".*.tmp"))  # no temporary file left behind


def test_writers_replace_a_regular_file_and_create_folders(tmp_path: Path):
    path = tmp_path / "a" / "b" / "model.safetensors"
    _save(path)
    _save(path)  # over a regular file: fine
    assert pr.load_model(path).n_parameters > 0
    assert sorted(p.name for p in path.parent.iterdir()) == ["model.safetensors"]


def test_devices_are_refused():
    # Checked only: writing is never tried on a device.
    with pytest.raises(ValueError, match="character device"):
        check_output_path("/dev/null")
    with pytest.raises(ValueError, match="not a directory"):
        check_output_path("/dev/null/x")


# --- checkpoints: weights only, clear errors ----------------------------------------------------


class _Evil:
    """Unpickles into open(marker, "w"): creates a file when loaded without weights_only."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[Any, ...]:
        return (open, (str(self.marker), "w"))


def test_resume_does_not_run_code_from_the_checkpoint(tmp_path: Path):
    ckpt, marker = tmp_path / "evil.pt", tmp_path / "pwned"
    torch.save({"config": {}, "model": _Evil(marker)}, ckpt)
    with pytest.raises(ValueError, match=r"evil\.pt"):
        train(_tiny(), progress=False, checkpoint=ckpt, resume=True)
    assert not marker.exists()


@pytest.mark.parametrize("content", [b"garbage" * 10, None], ids=["garbage", "truncated"])
def test_bad_checkpoints_give_a_clear_error(tmp_path: Path, content: bytes | None):
    ckpt = tmp_path / "c.pt"
    train(_tiny(iterations=4), progress=False, checkpoint=ckpt, checkpoint_every=2)
    data = ckpt.read_bytes()
    ckpt.write_bytes(content if content is not None else data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"checkpoint .*c\.pt"):
        train(_tiny(iterations=4), progress=False, checkpoint=ckpt, resume=True)


def test_checkpoint_every_and_checkpoint_path_are_checked_before_training(tmp_path: Path):
    calls: list[int] = []
    with pytest.raises(ValueError, match="checkpoint_every"):
        train(_tiny(), progress=False, checkpoint=tmp_path / "c.pt", checkpoint_every=0)
    os.mkfifo(tmp_path / "fifo")
    with pytest.raises(ValueError, match="FIFO"):
        train(
            _tiny(),
            progress=False,
            checkpoint=tmp_path / "fifo",
            callback=lambda i, v: calls.append(i),
        )
    assert calls == []  # refused before the first iteration


# --- settings checked up front; no non-finite model written ------------------------------------


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        ({"lr": float("inf")}, "lr"),
        ({"h_max": float("inf")}, "h_max"),
        ({"r_max": float("inf")}, "r_max"),
        ({"r_max": 1e300}, "r_max"),
        ({"half_width": float("nan"), "domain": "cube"}, "half_width"),
        ({"batch": 10**12}, "batch"),
        ({"widths": (4.5,)}, "widths"),
        ({"device": "foo"}, "device"),
        ({"init": "ones"}, "init"),
    ],
)
def test_absurd_settings_are_refused(overrides: dict[str, Any], match: str):
    with pytest.raises(ValueError, match=match):
        _tiny(**overrides).validate()


def test_a_non_finite_model_is_never_written(tmp_path: Path):
    result = train(_tiny(), progress=False)
    with torch.no_grad():
        result.model.linears[0].weight[0, 0] = float("nan")
    path = tmp_path / "m.safetensors"
    with pytest.raises(ValueError, match="not written"):
        save_result(result, path, name="m", command="x")
    assert not path.exists()


def test_cli_refuses_infinite_settings_without_writing(tmp_path: Path, capsys: Any):
    out = tmp_path / "m.safetensors"
    for flag in (["--lr", "inf"], ["--h-max", "inf"], ["--r-max", "inf"]):
        argv = ["train", "--out", str(out), "--widths", "4", "--iterations", "2", *flag]
        assert cli.main([*argv, "--no-progress"]) == 2
        assert "finite" in capsys.readouterr().err
    assert not out.exists()


# --- outputs checked before the work ----------------------------------------------------------


def test_cli_checks_outputs_before_the_work(tmp_path: Path, capsys: Any, monkeypatch: Any):
    def never(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("the work started")

    monkeypatch.setattr("poisson_rs.train.train", never)
    monkeypatch.setattr("poisson_rs.studies.demo.run_scene", never)
    monkeypatch.setattr("poisson_rs.studies.stability.stability_map", never)
    monkeypatch.setattr("poisson_rs.studies.sweep.run_sweep", never)
    a_file = tmp_path / "file"
    a_file.write_text("")
    cases = [
        ["train", "--out", str(tmp_path)],  # a directory
        ["train", "--out", str(a_file / "x.safetensors")],  # below a file
        ["train", "--out", str(tmp_path / "m"), "--checkpoint-every", "0"],
        ["demo", "--out", str(a_file)],
        ["sweep", "--out", str(a_file), "--fast"],
        ["stability", "--out", str(tmp_path / "s"), "--horizon", "-1"],
        ["stability", "--out", str(tmp_path / "s"), "--threshold", "nan"],
        ["demo", "--out", str(tmp_path / "d"), "--h", "nan"],
    ]
    for argv in cases:
        assert cli.main(argv) == 2, argv
        assert capsys.readouterr().err.startswith(f"poisson-rs {argv[0]}:"), argv


# --- baseline, zero start, time limit ---------------------------------------------------------


def test_training_starts_from_the_series_and_reports_its_baseline():
    cfg = _tiny(iterations=0)
    result = train(cfg, progress=False)
    # Zero output: before any step the model is the Taylor terms alone.
    assert result.validation_rms == pytest.approx(result.baseline_rms, rel=1e-12)
    assert baseline_rms(cfg) == pytest.approx(result.baseline_rms, rel=1e-12)
    assert all(
        not x.any() for x in (result.model.linears[-1].weight, result.model.linears[-1].bias)
    )
    trained = train(_tiny(iterations=40, batch=256), progress=False)
    assert trained.validation_rms < trained.baseline_rms


def test_max_seconds_stops_cleanly_and_the_cli_still_saves(tmp_path: Path, capsys: Any):
    result = train(_tiny(iterations=10**6), progress=False, max_seconds=0.3)
    assert result.timed_out and 0 < result.iterations_run < 10**6
    out = tmp_path / "m.safetensors"
    argv = ["train", "--out", str(out), "--widths", "4", "--iterations", "1000000"]
    assert cli.main([*argv, "--max-seconds", "0.3", "--threads", "1", "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "--max-seconds reached" in text and "Taylor terms alone" in text
    assert pr.load_model(out).metadata["name"] == "m"


def test_train_help_shows_every_default():
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    helps = {a.dest: a.help or "" for a in sub.choices["train"]._actions}
    for dest in ("lr", "iterations", "batch", "r_max", "seed", "checkpoint_every", "threads"):
        assert "default" in helps[dest], dest
    assert "paper preset: 0.0001" in helps["lr"]
    text = sub.choices["train"].format_help()
    assert "(default: 0.003" in text


# --- DOP853: bounded work ---------------------------------------------------------------------


def test_dop853_fails_fast_on_overflowing_states(monkeypatch: pytest.MonkeyPatch):
    runs = count_dop853_rhs(monkeypatch)
    with pytest.raises(RuntimeError, match="non-finite"):
        pr.dop853_solution(pr.RigidBody(), [1e200, 1e200, 1e200], [1.0])
    assert runs == []  # refused before any integration


def test_dop853_work_is_bounded(monkeypatch: pytest.MonkeyPatch):
    from poisson_rs import reference

    # The budget scaled down so that the test is fast; |mu| = 1e10 needs ~1e10 times more steps.
    monkeypatch.setattr(reference, "_DOP853_MAX_STEPS", 2000, raising=False)
    runs = count_dop853_rhs(monkeypatch)
    dop = pr.classical(pr.RigidBody(), "dop853")
    with pytest.raises(RuntimeError, match="failed"), pytest.warns(RuntimeWarning, match="budget"):
        pr.integrate(dop, [1e10, 2e10, 3e10], 0.1, 100, on_failure="raise")
    # One state over the budget does not lose the batch: it comes back NaN, the others finite.
    with pytest.warns(RuntimeWarning, match="budget"):
        traj, info = pr.integrate(
            dop, [[1e10, 2e10, 3e10], [1.0, 1.0, 2.0]], 0.1, 100, return_info=True
        )
    assert np.isnan(traj[0, 1:]).all() and np.isfinite(traj[1]).all()
    np.testing.assert_array_equal(info.converged, [False, True])
    # No run went past the budget: 12 right-hand sides a step, and the one that stops it.
    assert runs and max(runs) <= 12 * 2000 + 1, runs
    # Ordinary states stay within it.
    assert np.isfinite(pr.integrate(dop, [1.0, 1.0, 2.0], 0.1, 100)).all()


# --- smaller validation gaps ------------------------------------------------------------------


@pytest.mark.timeout(60)  # a guard: a regression would block on the FIFO instead of failing
def test_load_model_refuses_fifos_and_devices(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    fifo = tmp_path / "m.safetensors"
    os.mkfifo(fifo)

    def no_read(self: Path) -> bytes:
        raise AssertionError(f"{self} was read before it was checked")

    monkeypatch.setattr(Path, "read_bytes", no_read)
    with pytest.raises(ValueError, match="FIFO"):
        pr.load_model(fifo)  # would block forever on the open
    with pytest.raises(ValueError, match="character device"):
        pr.load_model("/dev/zero")  # would read until the memory runs out


def test_load_model_lists_the_shipped_names():
    with pytest.raises(FileNotFoundError, match=r"shipped models: .*default"):
        pr.load_model("nope")


def test_overflowing_h_max_does_not_turn_the_strict_check_off(tmp_path: Path):
    from safetensors.numpy import load_file, save_file

    path = _save(tmp_path / "m.safetensors")
    tensors = load_file(str(path))
    from safetensors import safe_open

    with safe_open(str(path), "np") as f:
        meta = dict(f.metadata())
    save_file(tensors, str(path), metadata={**meta, "h_max": "1e400"})
    with pytest.raises(ValueError, match="h_max"):
        pr.load_model(path)


def test_torch_step_checks_h(tmp_path: Path):
    model = pr.load_model(_save(tmp_path / "m.safetensors"))
    mu = torch.tensor([[1.0, 1.0, 2.0]])
    for bad, err in ((-0.1, ValueError), (float("nan"), ValueError), ("0.1", TypeError)):
        with pytest.raises(err, match="h must"):
            model.torch_step(mu, bad)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="h must"):
        model.torch_step(mu, True)


def test_integrate_refuses_masked_arrays():
    mu0 = np.ma.masked_array([[1.0, 1.0, 2.0], [9.0, 9.0, 9.0]], mask=[[0, 0, 0], [1, 1, 1]])
    with pytest.raises(TypeError, match="masked array"):
        pr.integrate(pr.taylor_integrator(), mu0, 0.1, 2)


def test_warnings_name_the_model_and_the_reason(tmp_path: Path):
    model = pr.load_model(_save(tmp_path / "mine.safetensors"))
    with pytest.warns(RuntimeWarning, match=r"'mine'.*outside the training domain"):
        pr.integrate(model, [10.0, 0.0, 0.0], 0.1, 1, on_failure="ignore")
    codes = "|".join(pr.FAILURE_CODES.values())
    with pytest.warns(RuntimeWarning, match=rf"'taylor3-exp'.*failed .*: ({codes})\)"):
        pr.integrate(pr.taylor_integrator(order=3, chart="exp"), [300.0, 0.0, 1.0], 2.0, 5)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        (b"\xff\xfe\x00binary", "not UTF-8"),
        (
            b"[system]\ninertia = [1.5, 2.0, 2.5]\n[states]\nshell = {r_min = 1, r_max = 2, "
            b"n = 100000000000}\n[steps]\nh = 0.1\nhorizon = 1.0\n[target]\nerror = 0.1\n",
            "states",
        ),
        (
            b"[system]\ninertia = [1.5, 2.0, 2.5]\n[states]\npoints = [[1.0, 1.0, 2.0]]\n"
            b"[steps]\nh = 0.1\nhorizon = 1e12\n[target]\nerror = 0.1\n",
            "memory",
        ),
        (
            b"[system]\ninertia = [1.5, 2.0, 2.5]\n[states]\npoints = [[1e300, 1.0, 2.0]]\n"
            b"[steps]\nh = 0.1\nhorizon = 1.0\n[target]\nerror = 0.1\n",
            "r_max",
        ),
    ],
    ids=["binary", "huge-shell", "huge-horizon", "huge-point"],
)
@pytest.mark.timeout(60)  # a guard: a regression would block on the FIFO instead of failing
def test_bad_scene_files_are_refused_up_front(
    tmp_path: Path, text: bytes, match: str, monkeypatch: pytest.MonkeyPatch
):
    from poisson_rs import scenes

    def no_work(*_: Any, **__: Any) -> Any:
        raise AssertionError("the scene's work started before it was refused")

    # The work a scene's values scale: drawing its shell's states, solving reference orbits.
    monkeypatch.setattr(scenes.ShellStates, "sample", no_work)
    monkeypatch.setattr(scenes, "reference_solution", no_work)
    path = tmp_path / "s.toml"
    path.write_bytes(text)
    with pytest.raises(ValueError, match=match):
        scenes.load_scene(path)
    fifo = tmp_path / "fifo.toml"
    os.mkfifo(fifo)
    with pytest.raises(ValueError, match="FIFO"):
        scenes.load_scene(fifo)


# --- CLI frictions ----------------------------------------------------------------------------


def test_models_prints_runnable_relative_commands(capsys: Any):
    assert cli.main(["models"]) == 0
    lines = [x for x in capsys.readouterr().out.splitlines() if "command:" in x]
    assert lines and all("/root/" not in x and "add --" not in x for x in lines)
    for line in lines:
        words = shlex.split(line.split("command:", 1)[1])
        if "poisson-rs" not in words:
            # Trained by a bench script (the log-canonical model): a script of the repository,
            # named relative to its root.
            script = next(w for w in words if w.endswith(".py"))
            root = Path(__file__).resolve().parents[1]
            assert not os.path.isabs(script) and (root / script).is_file()
            continue
        out = words[words.index("--out") + 1]
        assert not os.path.isabs(out) and "/" not in out
        assert cli.build_parser().parse_args(words[1:]).command == "train"  # it parses


def test_demo_rows_are_not_doubled(tmp_path: Path, capsys: Any):
    argv = ["demo", "--steps", "100", "--no-paper", "--out", str(tmp_path)]
    assert cli.main(argv) == 0
    out = capsys.readouterr().out
    rows = [x for x in out.splitlines() if x.startswith(("learned:", "taylor"))]
    assert len(rows) == len(set(rows)) == 4 * 2  # 4 methods × 2 states, once each
    # And the step-size message points at a flag that exists.
    assert cli.main([*argv, "--h", "0.2"]) == 2
    assert "--no-strict" in capsys.readouterr().err


# --- figures ----------------------------------------------------------------------------------


def test_scene_figures_colour_methods_by_name_and_state_the_system(
    tmp_path: Path, monkeypatch: Any
):
    from poisson_rs.studies.demo import run_scene

    figs: list[Figure] = []
    real = charts._savefig

    def keep(fig: Figure, path: Path, **kwargs: Any) -> Path:
        figs.append(fig)
        return real(fig, path, **kwargs)

    monkeypatch.setattr(charts, "_savefig", keep)
    body = pr.RigidBody((1.0, 2.0, 3.0))
    methods = {"taylor3-cayley": pr.taylor_integrator(body, 3), "rk4": pr.classical(body, "rk4")}
    scene = run_scene(methods, body, np.array([[1.0, 1.0, 2.0]]), 0.1, 5)
    colours = []
    for order in (scene.runs, scene.runs[::-1]):
        charts.paper_figure_3(scene, order, tmp_path / "f3.png")
        fig = figs[-1]
        colours.append({ln.get_label(): ln.get_color() for ln in fig.axes[0].get_lines()})
        assert fig.legends and "I = (1.0, 2.0, 3.0)" in fig.get_suptitle()
    assert colours[0] == colours[1]
    assert colours[0]["rk4"] == charts.method_style("rk4")["color"]
    charts.paper_figure_2(scene, scene.runs[0], tmp_path / "f2.png")
    assert "I = (1.0, 2.0, 3.0)" in figs[-1].get_suptitle()

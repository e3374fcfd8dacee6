"""Regression tests for hardening: writers replace only regular files, checkpoints cannot run
code, settings and outputs are checked before the work, training reports its baseline."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest
import torch
from conftest import build_generating
from matplotlib.figure import Figure

import poisson_rs as pr
from poisson_rs import charts, cli
from poisson_rs.export import save_model
from poisson_rs.files import atomic_write_bytes, check_output_path
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
    monkeypatch.setattr("poisson_rs.scene.run_scene", never)
    monkeypatch.setattr("poisson_rs.stability.stability_map", never)
    monkeypatch.setattr("poisson_rs.sweep.run_sweep", never)
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

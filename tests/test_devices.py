"""Torch devices by name (``poisson_rs.devices``): "auto", the checks, and training's use of
them. No CUDA device is needed: where one is absent, asking for it is refused before any work,
and "auto" resolves to the CPU."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

import poisson_rs as pr
import poisson_rs.train as train_module
from poisson_rs import devices
from poisson_rs.train import TrainConfig, save_result, train


def _tiny(**overrides: Any) -> TrainConfig:
    base: dict[str, Any] = {"widths": (4,), "batch": 64, "iterations": 5, "lr": 1e-2, "seed": 3}
    return TrainConfig(**{**base, **overrides})


@pytest.mark.parametrize(("cuda", "expected"), [(False, "cpu"), (True, "cuda")])
def test_auto_is_cuda_exactly_when_torch_sees_it(
    monkeypatch: pytest.MonkeyPatch, cuda: bool, expected: str
):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: cuda)
    assert devices.auto_device() == expected
    cfg = _tiny()
    # Resolved where the configuration is made: what a run records names the device used.
    assert cfg.device == expected
    assert dataclasses.asdict(cfg)["device"] == expected
    assert dataclasses.replace(cfg, device="auto").device == expected
    assert _tiny(device="cpu").device == "cpu"


def test_training_on_auto_without_cuda_is_training_on_the_cpu(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    auto = train(_tiny(), progress=False)
    cpu = train(_tiny(device="cpu"), progress=False)
    assert auto.losses == cpu.losses
    for a, b in zip(auto.model.state_dict().values(), cpu.model.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    assert json.loads(json.dumps(dataclasses.asdict(auto.config)))["device"] == "cpu"


@pytest.mark.parametrize("device", ["cuda", "cuda:0", "cuda:3"])
def test_cuda_without_a_device_is_refused_before_any_work(
    monkeypatch: pytest.MonkeyPatch, device: str
):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)

    def never(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("training started")

    monkeypatch.setattr(train_module, "_train", never)
    with pytest.raises(ValueError, match=r"device .*no CUDA device.*'auto'"):
        train(_tiny(device=device), progress=False)


def test_a_cuda_index_beyond_the_devices_seen_is_refused(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert devices.check_device("cuda:0") == torch.device("cuda:0")
    with pytest.raises(ValueError, match=r"device 'cuda:1': torch sees 1 CUDA device"):
        devices.check_device("cuda:1")


@pytest.mark.parametrize("bad", ["foo", "gpu", "meta", "mps", "cuda:x", "", "auto "])
def test_other_names_are_refused_naming_device(bad: str):
    with pytest.raises(ValueError, match="device"):
        devices.check_device(bad)
    with pytest.raises(ValueError, match="device"):
        _tiny(device=bad).validate()


@pytest.mark.parametrize("bad", [0, None, 1.5, ["cpu"]])
def test_a_device_that_is_not_a_string_is_refused(bad: Any):
    with pytest.raises(TypeError, match="device must be a string"):
        devices.check_device(bad)
    with pytest.raises(ValueError, match="device must be a string"):
        _tiny(device=bad).validate()


def test_a_model_recorded_as_trained_on_cuda_loads_and_steps_here(tmp_path: Path):
    result = train(_tiny(device="cpu"), progress=False)
    # What a GPU run leaves: its configuration names CUDA; the weights come back as CPU float64.
    result.config.device = "cuda"
    assert all(v.device.type == "cpu" for v in result.model.state_dict().values())
    path = save_result(result, tmp_path / "m.safetensors", name="m", command="train --device cuda")
    stepper = pr.load_model(path)
    mu0 = np.array([[1.0, 0.5, -0.3], [0.2, -1.1, 0.7]])
    traj = np.asarray(pr.integrate(stepper, mu0, 0.05, 20))
    assert traj.shape == (2, 21, 3) and np.isfinite(traj).all()
    # A learned Lie–Poisson step keeps the Casimir |μ|² to rounding, wherever it was trained.
    c = (traj**2).sum(-1)
    assert np.abs(c / c[:, :1] - 1).max() < 1e-12
    assert json.loads(pr.load_model(path).metadata["config"])["device"] == "cuda"

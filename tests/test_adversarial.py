"""Regression tests for the defects an adversarial pass found: models rebuilt from the bytes read
once, relabelled models refused, outputs whose temporary names always fit and whose write path is
tried before the work, atomic Zarr stores, bounded threads and DOP853 work, one clear error for
untrusted input, and the low-severity file and metadata gaps."""

from __future__ import annotations

import json
import os
import signal
import stat
import subprocess
import sys
import textwrap
import time
from fractions import Fraction
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import count_dop853_rhs
from safetensors.numpy import load

import poisson_rs as pr
from poisson_rs import export, files, integrators, train
from poisson_rs.untrusted import InputError

MU = np.array([[1.0, 1.0, 2.0], [3.0, 2.0, 0.0]])


def shipped_bytes(name: str) -> bytes:
    return resources.files("poisson_rs.models").joinpath(f"{name}.safetensors").read_bytes()


def edit_metadata(data: bytes, **changes: str | None) -> bytes:
    """The model file ``data`` with metadata keys changed (None: removed), tensors untouched."""
    size = int.from_bytes(data[:8], "little")
    meta = dict(json.loads(data[8 : 8 + size])["__metadata__"])
    for k, v in changes.items():
        if v is None:
            meta.pop(k, None)
        else:
            meta[k] = v
    return export.safetensors_bytes(load(data), meta)


# --- torch_step and the model file -------------------------------------------------------------


def test_torch_uses_the_bytes_read_at_load_not_the_file(tmp_path: Path) -> None:
    path = tmp_path / "m.safetensors"
    path.write_bytes(shipped_bytes("paper_h01"))
    model = pr.load_model(path)
    # The file is replaced by another model after loading: torch must still run the loaded one.
    path.write_bytes(shipped_bytes("default"))
    rust = pr.integrate(model, MU, 0.1, 1)[:, 1]
    torch_mu = model.torch_step(MU, 0.1).detach().numpy()
    np.testing.assert_allclose(torch_mu, rust, rtol=0, atol=1e-10)


@pytest.mark.timeout(60)  # a guard: a read of the FIFO would block forever instead of failing
def test_torch_step_does_not_hang_when_the_path_becomes_a_fifo(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "m.safetensors"
    path.write_bytes(shipped_bytes("default"))
    model = pr.load_model(path)
    path.unlink()
    os.mkfifo(path)

    def no_read(self: Path) -> bytes:
        raise AssertionError(f"{self} was read again after loading")

    monkeypatch.setattr(Path, "read_bytes", no_read)
    out = model.torch_step(MU, 0.1)
    assert out.shape == (2, 3)


# --- relabelled models ------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["default", "paper", "paper_h01"])
def test_a_model_whose_inertia_was_edited_is_refused(name: str) -> None:
    data = shipped_bytes(name)
    pr.integrators.LearnedIntegrator(data)  # the original loads
    body = json.dumps(pr.RigidBody((1.0, 2.0, 3.0)).to_dict())
    edited = edit_metadata(data, system=body, inertia="[1.0, 2.0, 3.0]")
    with pytest.raises(ValueError, match="t¹ terms"):
        pr.integrators.LearnedIntegrator(edited)


def test_a_heavy_top_relabelled_with_another_mgl_is_refused() -> None:
    data = shipped_bytes("heavy_top_h05")
    top = pr.HeavyTop((1.0, 1.5, 2.0), 2.0, (0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="t¹ terms"):
        pr.integrators.LearnedIntegrator(edit_metadata(data, system=json.dumps(top.to_dict())))


def test_taylor_models_of_any_system_pass_the_first_order_check() -> None:
    quartic = pr.LiePoissonSystem(
        pr.LieAlgebra.so3(), pr.Polynomial({(4, 0, 0): 0.25, (0, 2, 0): 0.5, (0, 0, 2): 1.0})
    )
    for system in (pr.RigidBody(), pr.HeavyTop(), quartic):
        pr.taylor_integrator(system, order=3)


# --- output paths and temporary names ---------------------------------------------------------


def test_temporary_names_fit_for_the_longest_legal_name(tmp_path: Path) -> None:
    target = tmp_path / ("m" * 240 + ".safetensors")  # 252 bytes: legal
    assert len(os.fsencode(target.name)) == 252
    tmp = files.temporary_name(target)
    assert len(os.fsencode(tmp.name)) <= 255 and tmp.parent == target.parent
    files.probe_writable(target)
    assert list(tmp_path.iterdir()) == []  # the probe leaves nothing behind
    files.atomic_write_bytes(target, b"abc")
    assert target.read_bytes() == b"abc"
    # Multi-byte characters are cut at a character boundary.
    wide = tmp_path / ("é" * 126)
    assert len(os.fsencode(files.temporary_name(wide).name)) <= 255


def test_probe_writable_fails_before_the_work(tmp_path: Path) -> None:
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        if os.access(ro, os.W_OK):
            pytest.skip("running as a user who can write anywhere")
        with pytest.raises(ValueError, match="cannot write"):
            files.probe_writable(ro / "model.safetensors")
    finally:
        ro.chmod(0o700)
    with pytest.raises(ValueError):
        files.probe_writable(tmp_path / ("x" * 256))
    made = tmp_path / "a" / "b" / "m.safetensors"
    files.probe_writable(made)
    assert not (tmp_path / "a").exists()  # folders the probe made are removed


def test_a_long_checkpoint_name_is_written(tmp_path: Path) -> None:
    cfg = train.TrainConfig(widths=(4,), iterations=2, batch=16, seed=0)
    ckpt = tmp_path / ("c" * 250 + ".pt")
    train.train(cfg, checkpoint=ckpt, checkpoint_every=1, progress=False)
    assert ckpt.exists()


def test_replacing_an_output_keeps_its_mode(tmp_path: Path) -> None:
    path = tmp_path / "out.bin"
    path.write_bytes(b"old")
    path.chmod(0o600)
    files.atomic_write_bytes(path, b"new")
    assert stat.S_IMODE(path.stat().st_mode) == 0o600 and path.read_bytes() == b"new"


def test_replacing_an_output_gives_the_path_a_new_file(tmp_path: Path) -> None:
    # The documented choice: atomic replacement over writing in place, so another hard link to
    # the old file keeps the old contents (never a half-written mix).
    path, link = tmp_path / "out.bin", tmp_path / "link.bin"
    path.write_bytes(b"old")
    os.link(path, link)
    files.atomic_write_bytes(path, b"new")
    assert path.read_bytes() == b"new" and link.read_bytes() == b"old"


def test_model_bytes_are_deterministic() -> None:
    # In a fresh interpreter each: a hash map's order changes between processes.
    code = textwrap.dedent(
        """
        import hashlib, poisson_rs as pr
        m = pr.taylor_integrator(pr.HeavyTop(), order=3)
        print(hashlib.sha256(m._bytes).hexdigest())
        """
    )
    digests = {
        subprocess.run(
            [sys.executable, "-c", code],
            capture_output=True,
            text=True,
            check=True,
            env={**os.environ, "PYTHONHASHSEED": str(seed)},
        ).stdout
        for seed in (1, 2)
    }
    assert len(digests) == 1


# --- metadata ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"h_max": "٣"}, "h_max"),
        ({"h_max": "1_0"}, "h_max"),
        ({"taylor_order": "-1"}, "taylor_order"),
        ({"mlp_power": "٣"}, "mlp_power"),
        ({"widths": "[" * 100_000 + "]" * 100_000}, "widths"),
        ({"domain": json.dumps({"kind": "top", "half_width": 2, "r_min": 0.5, "r_max": 2})}, None),
        ({"system": '{"kind": "rigid_body", "inertia": [1, "x", 3]}'}, "system"),
        ({"system": "[" * 50_000}, "system"),
    ],
)
def test_bad_metadata_is_one_clear_error(changes: dict[str, str], field: str | None) -> None:
    edited = edit_metadata(shipped_bytes("default"), **changes)
    with pytest.raises(ValueError) as err:
        pr.integrators.LearnedIntegrator(edited)
    assert isinstance(err.value, InputError), err.value
    if field is not None:  # named as a field, or (where the core refuses it) in the message
        assert err.value.field == field or field in str(err.value), err.value
    assert "\n" not in str(err.value)


def test_a_top_domain_needs_a_six_dimensional_model() -> None:
    with pytest.raises(ValueError, match="dimension 3"):
        integrators._check_domain({"kind": "top", "half_width": 2, "r_min": 0.5, "r_max": 2}, 3)


# --- numbers given to the API -----------------------------------------------------------------


@pytest.mark.parametrize(
    ("h", "error"),
    [(10**400, ValueError), (1e-320, ValueError), (True, TypeError), ("0.1", TypeError)],
)
def test_bad_steps_are_one_clear_error(h: Any, error: type[Exception]) -> None:
    with pytest.raises(error, match="h"):
        integrators._check_step(h)


def test_a_fraction_is_a_step() -> None:
    assert integrators._check_step(Fraction(1, 10)) == 0.1
    assert integrators._check_step(np.float32(0.5)) == 0.5


def test_model_methods_take_any_real_time() -> None:
    model = pr.taylor_integrator(order=3)
    for bad in (10**400, float("nan"), -1.0):
        with pytest.raises(ValueError, match="h"):
            model.hj_residual(MU, bad)
        with pytest.raises(ValueError, match="t"):
            model.derivatives(bad, MU)
        with pytest.raises(ValueError, match="h"):
            model.torch_step(MU, bad)
    exact = model.torch_step(MU, 0.1).detach().numpy()
    np.testing.assert_array_equal(model.torch_step(MU, Fraction(1, 10)).detach().numpy(), exact)
    np.testing.assert_array_equal(
        model.hj_residual(MU, Fraction(1, 10)), model.hj_residual(MU, 0.1)
    )


@pytest.mark.parametrize("value", [2**64, 2**53 + 1, -1])
def test_bad_counts_are_one_clear_error(value: int) -> None:
    with pytest.raises(ValueError, match="n_steps"):
        integrators._check_count("n_steps", value)
    with pytest.raises(TypeError, match="every"):
        integrators._check_count("every", 2.0, 1)


def test_lie_algebra_names_the_broken_rule() -> None:
    with pytest.raises(ValueError, match=r"c\[i,i,k\] = 0.*c\[0,0,0\] = 1.0"):
        pr.LieAlgebra(np.ones((3, 3, 3)))
    c = np.zeros((3, 3, 3))
    c[0, 1, 2] = c[1, 0, 2] = 1.0
    with pytest.raises(ValueError, match=r"c\[i,j,k\] = -c\[j,i,k\]"):
        pr.LieAlgebra(c)


def test_huge_structure_constants_keep_the_jacobi_check() -> None:
    so3 = pr.LieAlgebra.so3().c
    pr.LieAlgebra(so3 * 1e200)
    bad = so3 * 1e200
    bad[0, 1, 0], bad[1, 0, 0] = 1e200, -1e200
    with pytest.raises(ValueError, match="Jacobi"):
        pr.LieAlgebra(bad)
    with pytest.raises(ValueError, match="finite"):
        pr.LieAlgebra(np.full((3, 3, 3), np.nan))


@pytest.mark.parametrize(
    "spec",
    [
        {"kind": "heavy_top", "inertia": [1, 1, 1]},
        {"kind": "lie_poisson", "algebra": {"structure_constants": "x"}, "hamiltonian": 3},
        {"kind": "rigid_body", "inertia": {"a": 1}},
        [],
    ],
)
def test_system_dictionaries_fail_with_one_value_error(spec: Any) -> None:
    with pytest.raises(InputError):
        pr.LiePoissonSystem.from_dict(spec)


# --- training configuration, threads, checkpoints ---------------------------------------------


def test_train_config_accepts_a_system_object() -> None:
    cfg = train.TrainConfig(system=pr.HeavyTop(), chart="exp", domain="top", inputs="t,p")
    assert cfg.lie_system() == pr.HeavyTop()
    json.dumps(cfg.system)
    cfg.validate()


def test_threads_are_bounded_by_the_machine() -> None:
    cfg = train.TrainConfig(widths=(4,), iterations=1, batch=8)
    with pytest.raises(ValueError, match="threads must lie in 1"):
        train.train(cfg, threads=100_000, progress=False)
    with pytest.raises(TypeError):
        train.check_threads(2.0)
    assert 1 <= train.default_threads() <= train.max_threads()
    if train.cpu_cores() <= 2:
        assert train.default_threads() == 1


def test_train_restores_the_thread_count() -> None:
    import torch

    before = torch.get_num_threads()
    cfg = train.TrainConfig(widths=(4,), iterations=1, batch=8)
    train.train(cfg, threads=1, progress=False)
    assert torch.get_num_threads() == before


def _checkpoint(tmp_path: Path) -> tuple[train.TrainConfig, Path, dict[str, Any]]:
    import torch

    cfg = train.TrainConfig(widths=(4,), iterations=3, batch=16, seed=0)
    ckpt = tmp_path / "run.pt"
    train.train(cfg, checkpoint=ckpt, checkpoint_every=1, progress=False, max_seconds=1e9)
    return cfg, ckpt, torch.load(ckpt, weights_only=True)


@pytest.mark.parametrize(
    ("entry", "value"),
    [
        ("losses", ["x"]),
        ("seconds", float("nan")),
        ("generator", [1, 2, 3]),
        ("model", {"mlp.0.weight": 3}),
        ("optimizer", "adam"),
        ("iteration", 10**6),
    ],
)
def test_checkpoints_with_bad_entries_are_refused(
    tmp_path: Path, entry: str, value: object
) -> None:
    import torch

    cfg, ckpt, state = _checkpoint(tmp_path)
    state[entry] = value
    torch.save(state, ckpt)
    with pytest.raises(InputError, match=entry):
        train.train(cfg, checkpoint=ckpt, resume=True, progress=False)


def test_a_checkpoint_with_mismatched_shapes_is_refused(tmp_path: Path) -> None:
    import torch

    cfg, ckpt, state = _checkpoint(tmp_path)
    key = next(iter(state["model"]))
    state["model"][key] = torch.zeros(7, 7, dtype=torch.float64)
    torch.save(state, ckpt)
    with pytest.raises(InputError, match="model"):
        train.train(cfg, checkpoint=ckpt, resume=True, progress=False)


# --- DOP853 ------------------------------------------------------------------------------------


def test_dop853_refuses_huge_states_at_once_and_keeps_the_rest(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    runs = count_dop853_rhs(monkeypatch)
    with pytest.raises(RuntimeError, match="budget"):
        pr.dop853_solution(pr.RigidBody(), [1e30, 1e30, 1e30], [1.0])
    quartic = pr.LiePoissonSystem(
        pr.LieAlgebra.so3(), pr.Polynomial({(4, 0, 0): 0.25, (0, 2, 0): 0.5, (0, 0, 2): 1.0})
    )
    with pytest.raises(RuntimeError, match="budget"):
        pr.reference_solution(quartic, [1e12, 0.0, 1.0], [1.0])
    assert runs == []  # refused from the estimate: the whole budget would take minutes
    with pytest.warns(RuntimeWarning, match="gave up on 1 of 2"):
        out = pr.dop853_solution(
            pr.RigidBody(), [[1e30, 1e30, 1e30], [1.0, 1.0, 2.0]], [0.0, 1.0], failures="nan"
        )
    assert np.isnan(out[0, 1]).all() and np.isfinite(out[1]).all()


# --- Zarr stores -------------------------------------------------------------------------------


class _FailingStepper:
    """Delegates to a classical integrator and fails on its ``fail_at``-th rollout call."""

    def __init__(self, fail_at: int) -> None:
        self.inner = pr.classical(pr.RigidBody(), "rk4")
        self.calls = 0
        self.fail_at = fail_at
        self.system = self.inner.system
        self.dim = 3

    def rollout(self, *args: Any) -> Any:
        self.calls += 1
        if self.calls == self.fail_at:
            raise KeyboardInterrupt
        return self.inner.rollout(*args)


def test_to_zarr_interrupted_leaves_nothing_and_a_rerun_works(tmp_path: Path) -> None:
    pytest.importorskip("zarr")
    from poisson_rs import ensembles

    path = tmp_path / "ens.zarr"
    mu0 = np.tile(MU, (8, 1))
    with pytest.raises(KeyboardInterrupt):
        ensembles.to_zarr(
            _FailingStepper(3), mu0, 0.1, 5, path, chunk=2,
            compute_kwargs={"scheduler": "synchronous"},
        )  # fmt: skip
    assert list(tmp_path.iterdir()) == []
    ensembles.to_zarr(pr.classical(pr.RigidBody(), "rk4"), mu0, 0.1, 5, path, chunk=2)
    import zarr

    group = zarr.open_group(str(path), mode="r")
    assert group.attrs["complete"] is True
    expected = pr.integrate(pr.classical(pr.RigidBody(), "rk4"), mu0, 0.1, 5)
    np.testing.assert_array_equal(np.asarray(group["trajectories"]), expected)
    assert ensembles.zarr_system(path) == pr.RigidBody()


def test_to_zarr_killed_by_a_signal_leaves_nothing_at_the_path(tmp_path: Path) -> None:
    pytest.importorskip("zarr")
    path = tmp_path / "ens.zarr"
    code = textwrap.dedent(
        f"""
        import signal
        # A job started in the background by a non-interactive shell inherits SIGINT ignored:
        # restore the handler an interactive session has.
        signal.signal(signal.SIGINT, signal.default_int_handler)
        import numpy as np, poisson_rs as pr
        from poisson_rs import ensembles
        mu0 = np.random.default_rng(0).normal(size=(4000, 3))
        print("start", flush=True)
        # Taylor-HJ: minutes of work, so the signal always comes first.
        ensembles.to_zarr(pr.taylor_integrator(pr.RigidBody(), 5), mu0, 0.01, 20000,
                          {str(path)!r}, chunk=100)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "start"
    time.sleep(3)
    assert proc.poll() is None, "the ensemble ended before the signal"
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=120)
    assert proc.returncode != 0  # interrupted, not finished
    assert not path.exists()
    from poisson_rs import ensembles

    ensembles.to_zarr(pr.classical(pr.RigidBody(), "rk4"), MU, 0.1, 3, path)
    assert ensembles.zarr_system(path) == pr.RigidBody()

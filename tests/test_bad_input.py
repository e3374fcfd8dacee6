"""integrate() and load_model() refuse bad input with messages that name the problem, accept every
reasonable array layout, report Newton failures instead of hiding them, and return the documented
shapes."""

from __future__ import annotations

import json
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from conftest import RandomModel, random_states
from safetensors import safe_open
from safetensors.numpy import load_file, save_file

import poisson_rs as pr
from poisson_rs.export import FORMAT

MU = np.array([[1.0, 1.0, 2.0], [3.0, 2.0, 0.0], [-0.5, 2.5, 1.0]])


@pytest.fixture(scope="module")
def taylor3() -> pr.TaylorIntegrator:
    return pr.taylor_integrator(order=3)


# --- integrate: refusals ------------------------------------------------------------------------


@pytest.mark.parametrize(
    "mu0",
    [np.ones(2), np.ones((4, 3, 1)), np.ones((5, 4)), np.ones((3, 1)), np.float64(1.0)],
    ids=["(2,)", "(4,3,1)", "(5,4)", "(3,1)", "scalar"],
)
def test_integrate_rejects_wrong_shape(taylor3: pr.TaylorIntegrator, mu0: np.ndarray):
    with pytest.raises(ValueError, match=r"mu0 must have shape \(3,\) or \(n, 3\)"):
        pr.integrate(taylor3, mu0, 0.1, 3)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_integrate_rejects_non_finite_states(taylor3: pr.TaylorIntegrator, bad: float):
    mu0 = MU.copy()
    mu0[1, 2] = bad
    with pytest.raises(ValueError, match="NaN or infinite"):
        pr.integrate(taylor3, mu0, 0.1, 3)


@pytest.mark.parametrize("h", [0.0, -0.1, -0.0, np.nan, np.inf])
def test_integrate_rejects_bad_step_size(taylor3: pr.TaylorIntegrator, h: float):
    with pytest.raises(ValueError, match="h must be finite and > 0"):
        pr.integrate(taylor3, MU, h, 3)


@pytest.mark.parametrize("h", ["0.1", None, True, 0.1j])
def test_integrate_rejects_non_real_step_size(taylor3: pr.TaylorIntegrator, h: object):
    with pytest.raises(TypeError, match="h must be a real number"):
        pr.integrate(taylor3, MU, h, 3)  # type: ignore[arg-type]


def test_integrate_rejects_negative_n_steps(taylor3: pr.TaylorIntegrator):
    with pytest.raises(ValueError, match="n_steps must be >= 0"):
        pr.integrate(taylor3, MU, 0.1, -1)


@pytest.mark.parametrize("n_steps", [2.0, 2.5, "3", None, True])
def test_integrate_rejects_non_integer_n_steps(taylor3: pr.TaylorIntegrator, n_steps: object):
    with pytest.raises(TypeError, match="n_steps must be an integer"):
        pr.integrate(taylor3, MU, 0.1, n_steps)  # type: ignore[arg-type]


@pytest.mark.parametrize("every", [0, -2])
def test_integrate_rejects_every_below_one(taylor3: pr.TaylorIntegrator, every: int):
    with pytest.raises(ValueError, match="every must be >= 1"):
        pr.integrate(taylor3, MU, 0.1, 3, every=every)


def test_integrate_rejects_non_integer_every(taylor3: pr.TaylorIntegrator):
    with pytest.raises(TypeError, match="every must be an integer"):
        pr.integrate(taylor3, MU, 0.1, 3, every=1.5)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "mu0",
    [MU.astype(np.complex128), MU.astype(str), np.array([[1, 2, 3]], dtype=object), MU > 0],
    ids=["complex", "str", "object", "bool"],
)
def test_integrate_rejects_non_real_dtypes(taylor3: pr.TaylorIntegrator, mu0: np.ndarray):
    with pytest.raises(TypeError, match="mu0 must be an array of real numbers"):
        pr.integrate(taylor3, mu0, 0.1, 3)


@pytest.mark.parametrize("stepper", [object(), "taylor3", None, pr.RigidBody()])
def test_integrate_rejects_non_integrators(stepper: object):
    with pytest.raises(TypeError, match="stepper must be an integrator"):
        pr.integrate(stepper, MU, 0.1, 3)  # type: ignore[arg-type]


def test_integrate_rejects_unknown_on_failure(taylor3: pr.TaylorIntegrator):
    with pytest.raises(ValueError, match="on_failure"):
        pr.integrate(taylor3, MU, 0.1, 3, on_failure="shout")  # type: ignore[arg-type]


# --- integrate: accepted layouts ------------------------------------------------------------------


def test_integrate_accepts_any_array_layout(taylor3: pr.TaylorIntegrator):
    reference = pr.integrate(taylor3, MU, 0.1, 20)
    assert reference.dtype == np.float64 and reference.flags.c_contiguous
    fortran = np.asfortranarray(MU)
    assert not fortran.flags.c_contiguous
    wide = np.zeros((6, 6))
    wide[::2, ::2] = MU
    strided = wide[::2, ::2]
    assert strided.shape == (3, 3) and not strided.flags.c_contiguous
    read_only = MU.copy()
    read_only.flags.writeable = False
    for mu0 in (MU.tolist(), fortran, strided, read_only, MU[::-1][::-1]):
        np.testing.assert_array_equal(pr.integrate(taylor3, mu0, 0.1, 20), reference)
    assert read_only.flags.writeable is False  # left untouched


def test_integrate_converts_integer_and_float32_input_exactly(taylor3: pr.TaylorIntegrator):
    as_ints = pr.integrate(taylor3, [1, 1, 2], 0.1, 10)
    np.testing.assert_array_equal(as_ints, pr.integrate(taylor3, [1.0, 1.0, 2.0], 0.1, 10))
    mu32 = MU.astype(np.float32) * np.float32(1.1)  # values that are not exact in float64 terms
    out = pr.integrate(taylor3, mu32, 0.1, 10)
    assert out.dtype == np.float64
    np.testing.assert_array_equal(out, pr.integrate(taylor3, mu32.astype(np.float64), 0.1, 10))


def test_integrate_accepts_numpy_scalars(taylor3: pr.TaylorIntegrator):
    out = pr.integrate(taylor3, MU, np.float32(0.25), np.int64(4), every=np.int32(2))
    np.testing.assert_array_equal(
        out, pr.integrate(taylor3, MU, float(np.float32(0.25)), 4, every=2)
    )


# --- integrate: shapes --------------------------------------------------------------------------


@pytest.mark.parametrize(("n_steps", "every"), [(0, 1), (1, 1), (10, 1), (10, 3), (10, 10), (7, 9)])
def test_output_shapes(taylor3: pr.TaylorIntegrator, n_steps: int, every: int):
    single = pr.integrate(taylor3, MU[0], 0.1, n_steps, every=every)
    batch = pr.integrate(taylor3, MU, 0.1, n_steps, every=every)
    assert single.shape == (n_steps // every + 1, 3)
    assert batch.shape == (len(MU), n_steps // every + 1, 3)
    np.testing.assert_array_equal(batch[0], single)  # trajectories are independent


def test_zero_steps_returns_the_initial_state(taylor3: pr.TaylorIntegrator):
    np.testing.assert_array_equal(pr.integrate(taylor3, MU, 0.1, 0), MU[:, None, :])
    np.testing.assert_array_equal(pr.integrate(taylor3, MU[1], 0.1, 0), MU[1:2])


def test_empty_batch(taylor3: pr.TaylorIntegrator):
    assert pr.integrate(taylor3, np.zeros((0, 3)), 0.1, 5, every=2).shape == (0, 3, 3)


@pytest.mark.parametrize(("n_steps", "every"), [(12, 1), (12, 3), (12, 5), (12, 12), (12, 13)])
def test_every_subsamples_exactly(taylor3: pr.TaylorIntegrator, n_steps: int, every: int):
    full = pr.integrate(taylor3, MU, 0.1, n_steps)
    np.testing.assert_array_equal(
        pr.integrate(taylor3, MU, 0.1, n_steps, every=every), full[:, ::every]
    )


def test_one_state_or_a_batch_of_one_agree(random_model: RandomModel):
    model = random_model(3)
    mu = random_states(np.random.default_rng(3), 1)
    np.testing.assert_array_equal(
        pr.integrate(model, mu[0], 0.1, 5), pr.integrate(model, mu, 0.1, 5)[0]
    )


# --- integrate: Newton failures -----------------------------------------------------------------


def _check_failed(traj: np.ndarray, info: pr.RolloutInfo, every: int = 1) -> None:
    """Each failed trajectory is finite up to its failed step and NaN from the next state on."""
    assert traj.ndim == 3
    for i, ok in enumerate(info.converged):
        if ok:
            assert info.failed_step[i] == -1 and info.failure_code[i] == 0
            assert np.isfinite(traj[i]).all()
            continue
        k = int(info.failed_step[i])
        assert k >= 0 and info.failure_code[i] in (1, 2, 3, 4)
        steps = np.arange(traj.shape[1]) * every
        assert np.isfinite(traj[i, steps <= k]).all()
        assert np.isnan(traj[i, steps > k]).all()


def test_huge_step_fails_with_a_warning_and_nan():
    # h = 50 takes |x| = |∂S/∂p| past the exponential chart's singularity at θ = 2π.
    stepper = pr.taylor_integrator(order=1, chart="exp")
    with pytest.warns(RuntimeWarning, match=r"2 of 2 trajectories failed"):
        traj = pr.integrate(stepper, MU[:2], 50.0, 4)
    assert np.isnan(traj[:, 1:]).all()
    np.testing.assert_array_equal(traj[:, 0], MU[:2])
    traj, info = pr.integrate(stepper, MU[:2], 50.0, 4, return_info=True, on_failure="ignore")
    assert not info.converged.any()
    np.testing.assert_array_equal(info.failed_step, [0, 0])
    _check_failed(traj, info)


def test_failure_mid_trajectory_keeps_earlier_states():
    # At h = 5 from (1,1,2) the exp chart survives three steps; a small state never fails.
    stepper = pr.taylor_integrator(order=1, chart="exp")
    mu0 = np.array([[1.0, 1.0, 2.0], [0.1, 0.1, 0.2]])
    with pytest.warns(RuntimeWarning, match=r"1 of 2 trajectories failed \(first: trajectory 0"):
        traj, info = pr.integrate(stepper, mu0, 5.0, 6, return_info=True)
    np.testing.assert_array_equal(info.converged, [False, True])
    assert info.failed_step[0] == 3 and info.failed_step[1] == -1
    assert info.failure_code[0] == 4  # chart singular
    _check_failed(traj, info)
    # Subsampled output agrees: states up to the failure kept, NaN after.
    sub, sub_info = pr.integrate(
        stepper, mu0, 5.0, 6, every=2, return_info=True, on_failure="ignore"
    )
    np.testing.assert_array_equal(sub_info.failed_step, info.failed_step)
    np.testing.assert_array_equal(sub, traj[:, ::2])
    _check_failed(sub, sub_info, every=2)


def test_wild_mlp_fails_and_can_raise(random_model: RandomModel):
    # An MLP term 10⁴ times the Hamiltonian's size: Newton from p = μ does not converge.
    model = random_model(5, chart="cayley", inputs="t,p", mlp_power=1, output_scale=1e4)
    with pytest.warns(RuntimeWarning, match="trajectories failed"):
        traj, info = pr.integrate(model, MU, 0.1, 5, return_info=True)
    assert not info.converged.all()
    assert (info.failed_step[~info.converged] >= 0).all()
    _check_failed(traj, info)
    with pytest.raises(RuntimeError, match="trajectories failed"):
        pr.integrate(model, MU, 0.1, 5, on_failure="raise")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        quiet = pr.integrate(model, MU, 0.1, 5, on_failure="ignore")
    np.testing.assert_array_equal(np.isnan(quiet), np.isnan(traj))


def test_iteration_cap_reports_no_convergence():
    stepper = pr.taylor_integrator(order=3, max_iter=1)
    traj, info = pr.integrate(stepper, MU, 0.1, 3, return_info=True, on_failure="ignore")
    np.testing.assert_array_equal(info.failure_code, [1, 1, 1])
    np.testing.assert_array_equal(info.failed_step, [0, 0, 0])
    _check_failed(traj, info)


def test_converged_rollout_reports_clean_info(taylor3: pr.TaylorIntegrator):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, info = pr.integrate(taylor3, MU, 0.1, 50, return_info=True, on_failure="raise")
    assert info.converged.all() and (info.failed_step == -1).all()
    assert (info.failure_code == 0).all()
    assert (info.newton_iterations >= 50).all()  # at least one update a step
    assert (info.max_newton_iterations <= taylor3.max_iter).all()
    assert (info.max_residual < 1e-13).all()


# --- load_model ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def model_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A valid model file written by the package (random MLP plus Taylor terms)."""
    from conftest import build_generating, save_generating

    path = tmp_path_factory.mktemp("files") / "good.safetensors"
    return save_generating(build_generating(11, widths=(6, 5), chart="cayley"), path)


def _rewrite(src: Path, dst: Path, **meta_changes: str) -> Path:
    """Copies a model file with some metadata keys replaced."""
    with safe_open(str(src), "np") as f:
        meta = dict(f.metadata())
    meta.update(meta_changes)
    save_file(load_file(str(src)), str(dst), metadata=meta)
    return dst


def test_load_model_good_file(model_file: Path):
    model = pr.load_model(model_file)
    assert model.chart == "cayley" and model.metadata["widths"] == (6, 5)
    assert model.path == model_file
    assert np.isfinite(pr.integrate(model, MU, 0.1, 3)).all()


def test_load_model_missing_file(tmp_path: Path):
    with pytest.raises(FileNotFoundError):
        pr.load_model(tmp_path / "nope.safetensors")
    with pytest.raises(FileNotFoundError):
        pr.load_model(str(tmp_path / "nope.safetensors"))


def test_load_model_rejects_non_path():
    with pytest.raises(TypeError, match="path must be"):
        pr.load_model(42)  # type: ignore[arg-type]


UNREADABLE = {
    "empty": lambda raw: b"",
    "five-bytes": lambda raw: raw[:5],
    "truncated-half": lambda raw: raw[: len(raw) // 2],
    "one-byte-short": lambda raw: raw[:-1],
    "random-bytes": lambda raw: np.random.default_rng(0).bytes(4096),
    "text": lambda raw: b"this is not a model\n" * 20,
}


@pytest.mark.parametrize("corrupt", UNREADABLE.values(), ids=UNREADABLE.keys())
def test_load_model_rejects_unreadable_files(
    model_file: Path, tmp_path: Path, corrupt: Callable[[bytes], bytes]
):
    path = tmp_path / "corrupt.safetensors"
    path.write_bytes(corrupt(model_file.read_bytes()))
    with pytest.raises(ValueError, match="safetensors"):
        pr.load_model(path)


def test_load_model_rejects_foreign_safetensors(tmp_path: Path):
    path = tmp_path / "foreign.safetensors"
    save_file({"weight": np.zeros((3, 3))}, str(path))
    with pytest.raises(ValueError, match="metadata"):
        pr.load_model(path)
    save_file({"weight": np.zeros((3, 3))}, str(path), metadata={"format": "pt"})
    with pytest.raises(ValueError, match="format"):
        pr.load_model(path)


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"format": "poisson_rs.generating/999"}, "format"),
        ({"chart": "quaternion"}, "chart"),
        ({"inertia": "[1.5, 2.0]"}, "inertia"),
        ({"inertia": "[1.5, -2.0, 2.5]"}, "inertia"),
        ({"inertia": "[1.5, 2.0, NaN]"}, "inertia"),
        ({"inertia": "heavy"}, "inertia"),
        ({"h_max": "-1"}, "h_max"),
        ({"h_max": "soon"}, "number"),
        ({"mlp_power": "two"}, "mlp_power"),
        ({"domain": '{"kind": "torus"}'}, "domain"),
        ({"system": "heavy_top"}, "system"),
    ],
    ids=lambda v: next(iter(v)) if isinstance(v, dict) else None,
)
def test_load_model_rejects_bad_metadata(
    model_file: Path, tmp_path: Path, changes: dict[str, str], match: str
):
    bad = _rewrite(model_file, tmp_path / "bad.safetensors", **changes)
    with pytest.raises(ValueError, match=match):
        pr.load_model(bad)


def test_load_model_rejects_widths_that_disagree_with_tensors(model_file: Path, tmp_path: Path):
    # The Rust core steps whatever layers the file holds; the metadata must not claim otherwise.
    for widths in ([6, 4], [6], [6, 5, 5]):
        bad = _rewrite(model_file, tmp_path / "widths.safetensors", widths=json.dumps(widths))
        with pytest.raises(ValueError, match="widths"):
            pr.load_model(bad)


Mutation = Callable[[dict[str, np.ndarray]], dict[str, np.ndarray]]
TENSOR_MUTATIONS = [
    pytest.param(lambda t: {"mlp.1.bias": t["mlp.1.bias"][:-1]}, "bias", id="bias-too-short"),
    pytest.param(
        lambda t: {"mlp.0.weight": t["mlp.0.weight"].astype(np.float32)},
        "float64",
        id="float32-weight",
    ),
    pytest.param(
        lambda t: {"mlp.1.weight": t["mlp.1.weight"][:, :-1].copy()},
        "inputs",
        id="inner-size-mismatch",
    ),
    pytest.param(
        lambda t: {
            "mlp.2.weight": np.vstack([t["mlp.2.weight"]] * 2),
            "mlp.2.bias": np.concatenate([t["mlp.2.bias"]] * 2),
        },
        "1 output",
        id="two-outputs",
    ),
    pytest.param(lambda t: {"extra": np.zeros(2)}, "unexpected tensor", id="stray-tensor"),
    pytest.param(
        lambda t: {"poly.powers": t["poly.powers"][:, :3].copy()},
        "poly.powers is for dimension 2",
        id="powers-of-another-dimension",
    ),
    pytest.param(
        lambda t: {"poly.coeffs": t["poly.coeffs"][:-1].copy()}, "rows", id="coeffs-too-short"
    ),
]


@pytest.mark.parametrize(("mutate", "match"), TENSOR_MUTATIONS)
def test_load_model_rejects_inconsistent_tensors(
    model_file: Path, tmp_path: Path, mutate: Mutation, match: str
):
    with safe_open(str(model_file), "np") as f:
        meta = dict(f.metadata())
    assert meta["format"] == FORMAT
    tensors = load_file(str(model_file))
    path = tmp_path / "t.safetensors"
    save_file({**tensors, **mutate(tensors)}, str(path), metadata=meta)
    with pytest.raises(ValueError, match=match):
        pr.load_model(path)

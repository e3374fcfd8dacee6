"""Where methods fail, and how they say so: Ctrl-C, out-of-domain states and steps, the
Hamilton–Jacobi residual as a trust indicator, bad input found by property-based search,
memory limits, concurrency and long horizons.

Subprocess tests run ``sys.executable`` on small scripts (seeded, fixed states) and bound only
what they measure, never the time to start Python, so that a slow machine does not fail them.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import textwrap
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from conftest import PAPER_INERTIA, RandomModel, interrupt_long_rollout, random_states
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import poisson_rs as pr
from poisson_rs.integrators import count_out_of_domain
from poisson_rs.realizations import lie_groupoid
from poisson_rs.studies.demo import PAPER_STATES
from poisson_rs.train import hj_residual as torch_hj_residual

BODY = pr.RigidBody(PAPER_INERTIA)


@pytest.fixture(scope="module")
def default_model() -> pr.LearnedIntegrator:
    return pr.load_model()


@pytest.fixture(scope="module")
def taylor3() -> pr.TaylorIntegrator:
    return pr.taylor_integrator(BODY, order=3)


@pytest.fixture(scope="module")
def splitting() -> pr.ClassicalIntegrator:
    return pr.classical(BODY, "splitting")


def _run_python(code: str, env: dict[str, str] | None = None, timeout: float = 120.0) -> str:
    """Runs ``code`` in a fresh interpreter; returns its stdout, fails the test on an error."""
    proc = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, **(env or {})},
    )
    assert proc.returncode == 0, f"exit {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    return proc.stdout


# --- 1. Ctrl-C --------------------------------------------------------------------------------

# A rollout of 10⁹ steps (an hour for the learned model, minutes for splitting) that keeps only
# 1001 states; "ready" is printed just before it starts.
_LONG_ROLLOUT = """
import signal
import sys
# A job started in the background by a non-interactive shell inherits SIGINT ignored, and Python
# then installs no handler: restore the one that raises KeyboardInterrupt.
signal.signal(signal.SIGINT, signal.default_int_handler)
import numpy as np
import poisson_rs as pr
body = pr.RigidBody((1.5, 2.0, 2.5))
stepper = pr.load_model() if sys.argv[1] == "learned" else pr.classical(body, "splitting")
mu0 = np.tile([[1.0, 1.0, 2.0], [3.0, 2.0, 0.0]], (int(sys.argv[2]), 1))
print("ready", flush=True)
pr.integrate(stepper, mu0, 0.1, 10**9, every=10**6)
print("finished", flush=True)
"""


@pytest.mark.parametrize(("method", "copies"), [("learned", 1), ("learned", 512), ("splitting", 4)])
def test_ctrl_c_interrupts_a_long_rollout(method: str, copies: int):
    # The rollout (10⁹ steps) cannot finish; the helper's wait for the exit is the guard.
    out, err, code, _ = interrupt_long_rollout(_LONG_ROLLOUT, method, str(copies))
    assert "finished" not in out
    assert "KeyboardInterrupt" in err, err
    # An uncaught KeyboardInterrupt makes Python exit by SIGINT.
    assert code == -signal.SIGINT, (code, err)


# --- 2. Out of domain -------------------------------------------------------------------------


def test_step_beyond_h_max_is_refused_unless_not_strict(default_model: pr.LearnedIntegrator):
    assert default_model.h_max == 0.1
    with pytest.raises(ValueError, match=r"h = 0\.25 exceeds h_max = 0\.1"):
        pr.integrate(default_model, PAPER_STATES, 0.25, 3)
    loose = pr.integrate(default_model, PAPER_STATES, 0.25, 3, strict=False)
    assert loose.shape == (2, 4, 3) and np.isfinite(loose).all()
    # h = h_max itself is fine; so is any h for methods without a limit.
    pr.integrate(default_model, PAPER_STATES, 0.1, 3)
    taylor = pr.taylor_integrator(BODY, order=3)
    assert math.isinf(taylor.h_max)
    pr.integrate(taylor, PAPER_STATES, 0.5, 3)
    pr.integrate(pr.classical(BODY, "rk4"), PAPER_STATES, 0.5, 3)


def test_out_of_domain_counts_recorded_states_of_a_shell(default_model: pr.LearnedIntegrator):
    # The default model was trained on the shell 1 <= |mu| <= 4; |mu| is kept by every step.
    assert default_model.domain == {"kind": "shell", "r_min": 1.0, "r_max": 4.0, "t_max": 0.1}
    mu0 = np.array([[1.0, 1.0, 2.0], [0.3, 0.4, 0.0], [3.0, 2.0, 0.0], [3.0, 3.0, 3.0]])
    with pytest.warns(RuntimeWarning, match="outside the training domain") as record:
        traj, info = pr.integrate(default_model, mu0, 0.1, 20, every=3, return_info=True)
    domain = [str(w.message) for w in record if "training domain" in str(w.message)]
    assert len(domain) == 1  # once a call
    assert "14 recorded states of 2 of 4 trajectories" in domain[0]
    assert info.out_of_domain.dtype == np.int64
    np.testing.assert_array_equal(info.out_of_domain, [0, 7, 0, 7])  # 20 // 3 + 1 records
    # The counts are those of the recorded states, nothing else.
    r = np.linalg.norm(traj, axis=-1)
    np.testing.assert_array_equal(info.out_of_domain, ((r < 1) | (r > 4)).sum(axis=1))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, info = pr.integrate(default_model, PAPER_STATES, 0.1, 10_000, every=10, return_info=True)
    np.testing.assert_array_equal(info.out_of_domain, [0, 0])  # the paper's scene stays inside


def test_out_of_domain_counts_a_cube(random_model: RandomModel):
    # conftest's models were "trained" on the cube [-3, 3]^3; from (3, 2, 0) mu_1 reaches 3.24.
    model = random_model(1, chart="cayley")
    assert model.domain["kind"] == "cube" and model.domain["half_width"] == 3.0
    with pytest.warns(RuntimeWarning, match=r"of 1 of 2 trajectories .*\(the cube"):
        traj, info = pr.integrate(model, PAPER_STATES, 0.1, 200, return_info=True)
    expected = (np.abs(traj) > 3.0).any(axis=-1).sum(axis=1)
    assert expected[0] == 0 and expected[1] > 10
    np.testing.assert_array_equal(info.out_of_domain, expected)


def test_no_domain_means_no_count(taylor3: pr.TaylorIntegrator, splitting: pr.ClassicalIntegrator):
    far = np.array([[30.0, 20.0, 0.0], [1.0, 1.0, 2.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for stepper in (taylor3, splitting, pr.classical(BODY, "dop853")):
            _, info = pr.integrate(stepper, far, 0.01, 5, return_info=True)
            np.testing.assert_array_equal(info.out_of_domain, [0, 0])
            assert info.out_of_domain.dtype == np.int64


def test_out_of_domain_skips_nan_states():
    traj = np.full((3, 4, 3), np.nan)
    traj[:, 0] = [[5.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 0.5]]
    traj[0, 1] = [0.0, 5.0, 0.0]
    shell = {"kind": "shell", "r_min": 1.0, "r_max": 4.0}
    np.testing.assert_array_equal(count_out_of_domain(shell, traj), [2, 0, 1])
    cube = {"kind": "cube", "half_width": 3.0}
    np.testing.assert_array_equal(count_out_of_domain(cube, traj), [2, 0, 0])
    np.testing.assert_array_equal(count_out_of_domain({"kind": "all"}, traj), [0, 0, 0])
    np.testing.assert_array_equal(count_out_of_domain(None, traj), [0, 0, 0])


# --- 2b. The Hamilton–Jacobi residual -----------------------------------------------------------


@pytest.mark.parametrize("chart", ["cayley", "exp"])
def test_hj_residual_of_taylor_series_shrinks_with_order(chart: str):
    mu = random_states(np.random.default_rng(20), 64, 1.0, 4.0)
    high = pr.taylor_integrator(BODY, order=7, chart=chart).hj_residual(mu, 1e-3)
    low = pr.taylor_integrator(BODY, order=1, chart=chart).hj_residual(mu, 1e-3)
    assert high.shape == (64,)
    assert np.abs(high).max() <= 1e-12
    # S = -tH leaves r = O(t^2): about 1e-7 of H here, far above round-off.
    assert np.abs(low).max() > 1e-8
    # At t = 0 every S solves the equation (S_1 = -H).
    assert (
        np.abs(pr.taylor_integrator(BODY, order=1, chart=chart).hj_residual(mu, 0.0)).max() < 1e-15
    )


def _torch_relative_residual(model: pr.BisectionIntegrator, mu: np.ndarray, h: float) -> np.ndarray:
    p = torch.from_numpy(mu)
    t = torch.full((len(mu),), h, dtype=torch.float64)
    r = torch_hj_residual(
        model.generating, model.body.inertia, t, p, create_graph=False, derivatives="autograd"
    )
    return r.detach().numpy() / BODY.hamiltonian(mu)


@pytest.mark.parametrize(
    "make",
    [
        pytest.param(lambda rm: pr.load_model(), id="default"),
        pytest.param(lambda rm: rm(31, chart="cayley", inputs="t,p"), id="cayley-t,p"),
        pytest.param(lambda rm: rm(32, chart="exp", inputs="homogeneous"), id="exp-homogeneous"),
        pytest.param(lambda rm: rm(33, chart="exp", inputs="t,p", mlp_power=1), id="exp-t,p"),
    ],
)
def test_hj_residual_matches_torch_autograd(random_model: RandomModel, make):
    model = make(random_model)
    mu = random_states(np.random.default_rng(21), 128, 0.5, 4.0)
    for h in (0.02, 0.1):
        ours = model.hj_residual(mu, h)
        np.testing.assert_allclose(ours, _torch_relative_residual(model, mu, h), rtol=0, atol=1e-12)
        assert np.abs(ours).max() > 1e-13  # not trivially zero


def test_hj_residual_shapes_and_refusals(default_model: pr.LearnedIntegrator):
    mu = random_states(np.random.default_rng(22), 6, 1.0, 4.0)
    flat = default_model.hj_residual(mu, 0.1)
    np.testing.assert_array_equal(
        default_model.hj_residual(mu.reshape(2, 3, 3), 0.1), flat.reshape(2, 3)
    )
    assert default_model.hj_residual(mu[0], 0.1).shape == ()
    assert default_model.hj_residual(mu[0].tolist(), 0.1) == flat[0]
    np.testing.assert_array_equal(default_model.hj_residual(np.asfortranarray(mu), 0.1), flat)
    with_nan = mu.copy()
    with_nan[2, 1] = np.nan
    got = default_model.hj_residual(with_nan, 0.1)
    assert np.isnan(got[2]) and np.array_equal(np.delete(got, 2), np.delete(flat, 2))
    # Along the paper's scene the default model solves its equation to about 1e-5 of H.
    traj = pr.integrate(default_model, PAPER_STATES, 0.1, 2000, every=20)
    assert np.abs(default_model.hj_residual(traj, 0.1)).max() < 1e-4
    for h, err in ((-0.1, ValueError), (np.nan, ValueError), ("0.1", TypeError), (True, TypeError)):
        with pytest.raises(err, match="h must"):
            default_model.hj_residual(mu, h)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="shape"):
        default_model.hj_residual(np.ones((4, 2)), 0.1)
    with pytest.raises(TypeError, match="real numbers"):
        default_model.hj_residual(mu.astype(complex), 0.1)


@pytest.mark.parametrize("chart", ["cayley", "exp"])
def test_numpy_sou_matches_torch(chart: str):
    # One implementation serves both backends: NumPy (diagnostics) and torch (training).
    rng = np.random.default_rng(23)
    # |x| from 0 (series) across 1 (the switch to the closed form) to near the pole at 2*pi.
    x = rng.normal(size=(300, 3))
    x *= rng.uniform(0.0, 6.0, size=(300, 1)) / np.linalg.norm(x, axis=1, keepdims=True)
    p = rng.normal(size=(300, 3))
    ours = lie_groupoid.sou(chart, x, p)
    theirs = lie_groupoid.sou(chart, torch.from_numpy(x), torch.from_numpy(p)).numpy()
    np.testing.assert_allclose(ours, theirs, rtol=1e-13, atol=1e-13)
    if chart == "exp":
        assert np.isnan(lie_groupoid.sou("exp", np.array([6.5, 0.0, 0.0]), p[0])).all()
    with pytest.raises(ValueError, match="chart"):
        lie_groupoid.sou("quaternion", x, p)


# --- 3. Bad input -------------------------------------------------------------------------------


def _layouts(mu: np.ndarray) -> dict[str, object]:
    """The same states in every layout integrate() should accept."""
    wide = np.zeros((2 * len(mu), 6))
    wide[::2, ::2] = mu
    read_only = mu.copy()
    read_only.flags.writeable = False
    return {
        "list": mu.tolist(),
        "tuple": tuple(map(tuple, mu)),
        "fortran": np.asfortranarray(mu),
        "strided": wide[::2, ::2],
        "negative-strides": mu[::-1, ::-1][::-1, ::-1],
        "read-only": read_only,
        "big-endian": mu.astype(">f8"),
        "broadcast": np.broadcast_to(mu[0], mu.shape),  # zero stride, read-only
    }


@pytest.mark.parametrize("kind", ["learned", "splitting"])
def test_every_layout_gives_the_same_result(random_model: RandomModel, kind: str):
    stepper = random_model(41) if kind == "learned" else pr.classical(BODY, "splitting")
    mu = random_states(np.random.default_rng(24), 4, 1.0, 2.5)
    reference = pr.integrate(stepper, mu, 0.05, 30)
    for name, layout in _layouts(mu).items():
        want = (
            pr.integrate(stepper, np.broadcast_to(mu[0], mu.shape).copy(), 0.05, 30)
            if name == "broadcast"
            else reference
        )
        np.testing.assert_array_equal(pr.integrate(stepper, layout, 0.05, 30), want, err_msg=name)
    # float32 and integer input are converted exactly, not rounded through another type.
    mu32 = mu.astype(np.float32)
    np.testing.assert_array_equal(
        pr.integrate(stepper, mu32, 0.05, 30),
        pr.integrate(stepper, mu32.astype(np.float64), 0.05, 30),
    )
    ints = np.array([[1, 1, 2], [2, 1, 0]], dtype=np.int32)
    np.testing.assert_array_equal(
        pr.integrate(stepper, ints, 0.05, 30), pr.integrate(stepper, ints.astype(float), 0.05, 30)
    )


def test_huge_output_is_refused_before_allocating(taylor3: pr.TaylorIntegrator):
    for stepper in (taylor3, pr.classical(BODY, "splitting")):
        # 24 TB of output (more than any machine has: refused by the check before the
        # allocation, which names the memory that can be used), then a count whose output size
        # overflows 64 bits (refused as a count beyond 2**53 before any size is computed).
        for n_steps, error, match in (
            (10**12, MemoryError, "can be used now.*raise `every` or split the batch"),
            (2**62, ValueError, r"n_steps must be <= 2\*\*53"),
        ):
            with pytest.raises(error, match=match):
                pr.integrate(stepper, [1.0, 1.0, 2.0], 0.1, n_steps)


def test_output_the_system_cannot_give_is_memory_error_not_abort():
    # Under an address-space limit of 512 MiB more than the interpreter holds, a 24 GB output
    # and a 4 GB one must both raise MemoryError: an allocation attempted first would abort the
    # process instead. The core reads the limit (RLIMIT_AS) and refuses both up front. A rollout of
    # 10⁶ steps of 32 trajectories then fits in that limit because only 1001 states each are
    # kept (all of them would take 768 MB).
    out = _run_python(
        """
        import resource
        import numpy as np
        import poisson_rs as pr
        stepper = pr.classical(pr.RigidBody((1.5, 2.0, 2.5)), "splitting")
        pr.integrate(stepper, np.ones((4, 3)), 0.1, 10)  # start rayon's threads first
        with open("/proc/self/status") as f:
            vm = next(int(l.split()[1]) * 1024 for l in f if l.startswith("VmSize:"))
        resource.setrlimit(resource.RLIMIT_AS, (vm + (1 << 29), resource.RLIM_INFINITY))
        for n_steps in (10**9, 4 * 2**30 // 24):
            try:
                pr.integrate(stepper, [1.0, 1.0, 2.0], 0.1, n_steps)
            except MemoryError as e:
                print("MemoryError", e)
        traj = pr.integrate(stepper, np.ones((32, 3)), 0.1, 10**6, every=1000)
        print("shape", traj.shape, np.isfinite(traj).all())
        """
    )
    assert out.count("MemoryError") == 2, out
    assert out.count("address-space limit") == 2, out
    assert "shape (32, 1001, 3) True" in out


def _header(raw: bytes) -> dict[str, Any]:
    """The JSON header of a safetensors file's bytes."""
    n = int.from_bytes(raw[:8], "little")
    return json.loads(raw[8 : 8 + n])


def _rewrite_bytes(model: pr.BisectionIntegrator, **changes: str) -> bytes:
    """The bytes of ``model``'s file with some metadata keys replaced."""
    from safetensors.numpy import load, save

    assert model.path is not None
    raw = model.path.read_bytes()
    return save(load(raw), metadata={**_header(raw)["__metadata__"], **changes})


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"domain": '{"kind": "shell", "r_max": 4.0}'}, "r_min"),
        ({"domain": '{"kind": "shell", "r_min": 4.0, "r_max": 1.0}'}, "r_min < r_max"),
        ({"domain": '{"kind": "shell", "r_min": "one", "r_max": 4.0}'}, "r_min"),
        ({"domain": '{"kind": "cube", "half_width": -3.0}'}, "half_width > 0"),
        ({"domain": '{"kind": "cube", "half_width": Infinity}'}, "half_width"),
        ({"domain": '{"kind": "cube"}'}, "half_width"),
        ({"domain": "[1, 2]"}, "domain"),
        ({"h_max": "nan"}, "h_max"),
        ({"h_max": "0"}, "h_max"),
        ({"inertia": "[1.5, 2.0, 2.5, 1.0]"}, "inertia"),
        ({"inertia": '["1.5", 2.0, 2.5]'}, "inertia"),
        ({"inertia": "[1.5, 2.0, 0.0]"}, "inertia"),
        ({"widths": "[8]"}, "widths"),
        ({"widths": '"8,8"'}, "widths"),
        ({"mlp_inputs": "polar"}, "mlp_inputs"),
        ({"mlp_power": "0"}, "mlp_power"),
        ({"mlp_power": "999"}, "mlp_power"),
        ({"chart": ""}, "chart"),
    ],
    ids=lambda v: "-".join(f"{k}={v[k]}" for k in v)[:40] if isinstance(v, dict) else None,
)
def test_inconsistent_metadata_is_a_value_error(
    default_model: pr.LearnedIntegrator, changes: dict[str, str], match: str
):
    data = _rewrite_bytes(default_model, **changes)
    with pytest.raises(ValueError, match=match):
        pr.LearnedIntegrator(data)


def test_corrupt_weight_files_are_value_errors(default_model: pr.LearnedIntegrator, tmp_path: Path):
    assert default_model.path is not None
    raw = default_model.path.read_bytes()
    n = int.from_bytes(raw[:8], "little")
    start = 8 + n + _header(raw)["mlp.1.weight"]["data_offsets"][0]
    corrupted = {
        "nan-weight": raw[:start] + np.float64(np.nan).tobytes() + raw[start + 8 :],
        "huge-header-length": (2**63).to_bytes(8, "little") + raw[8:],
        "header-length-past-end": (len(raw)).to_bytes(8, "little") + raw[8:],
        "header-not-json": raw[:8] + b"\xff" * n + raw[8 + n :],
        "zeros": bytes(len(raw)),
        "torch-pickle": b"PK\x03\x04" + bytes(200),
    }
    for name, data in corrupted.items():
        with pytest.raises(ValueError):
            pr.LearnedIntegrator(data)
        path = tmp_path / f"{name}.safetensors"
        path.write_bytes(data)
        with pytest.raises(ValueError):
            pr.load_model(path)
    # A directory is not a model either: a clear ValueError, not a crash.
    with pytest.raises(ValueError, match="not a regular file"):
        pr.load_model(tmp_path)


def test_integer_overflowing_arguments_are_refused(taylor3: pr.TaylorIntegrator):
    # Python ints beyond 64 bits cannot reach the core.
    with pytest.raises((OverflowError, ValueError, MemoryError)):
        pr.integrate(taylor3, [1.0, 1.0, 2.0], 0.1, 2**70)
    with pytest.raises((OverflowError, ValueError)):
        pr.integrate(taylor3, [1.0, 1.0, 2.0], 0.1, 10, every=2**70)


# Property-based search over integrate()'s arguments: valid arguments give a correctly shaped
# result (finite, or NaN from a reported failure on), invalid ones a ValueError or TypeError.


def _mostly(good: st.SearchStrategy, bad: st.SearchStrategy) -> st.SearchStrategy:
    """``good`` four times in five, ``bad`` otherwise: most examples get past the checks."""
    return st.integers(0, 4).flatmap(lambda i: bad if i == 0 else good)


_REAL_DTYPES = [np.float64, np.float32, np.dtype(">f8"), np.int64, np.int32, np.uint8]
_ANY_DTYPES = [*_REAL_DTYPES, np.bool_, np.complex128]


@st.composite
def _states(draw: st.DrawFn) -> object:
    good_shape = st.one_of(st.just((3,)), st.tuples(st.integers(0, 4), st.just(3)))
    any_shape = hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=4)
    shape = draw(_mostly(good_shape, any_shape))
    dtype = np.dtype(draw(_mostly(st.sampled_from(_REAL_DTYPES), st.sampled_from(_ANY_DTYPES))))
    if dtype.kind == "f":
        width = dtype.itemsize * 8
        # Mostly moderate values; sometimes anything (NaN, inf, or huge values that overflow
        # during the rollout: a reported failure).
        elements = _mostly(st.floats(-4, 4, width=width), st.floats(width=width))
        arr = draw(hnp.arrays(dtype, shape, elements=elements))
    elif dtype.kind in "iu":
        arr = draw(
            hnp.arrays(
                dtype,
                shape,
                elements=_mostly(st.integers(-3, 3), hnp.from_dtype(dtype))
                if dtype.kind == "i"
                else None,
            )
        )
    else:
        arr = draw(hnp.arrays(dtype, shape))
    return arr.tolist() if arr.dtype.kind in "fi" and draw(st.booleans()) else arr


_H = _mostly(
    st.one_of(st.floats(0.001, 0.3), st.sampled_from([np.float32(0.05), np.float64(0.1), 1])),
    st.one_of(
        st.floats(allow_nan=True, allow_infinity=True),
        st.integers(-2, 2),
        st.sampled_from([True, None, "0.1", 0.1j]),
    ),
)
_N_STEPS = _mostly(
    st.one_of(st.integers(0, 40), st.just(np.int64(7))),
    st.one_of(st.integers(-2, -1), st.sampled_from([2.0, "3", None, False])),
)
_EVERY = _mostly(
    st.one_of(st.integers(1, 45), st.just(np.uint8(3))),
    st.one_of(st.integers(-1, 0), st.sampled_from([1.5, True])),
)


def _is_int(v: object) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))


def _valid(
    stepper: object, mu0: object, h: object, n_steps: object, every: object, strict: bool
) -> bool:
    arr = np.asarray(mu0)
    if arr.dtype.kind not in "fiu" or not (
        arr.shape == (3,) or (arr.ndim == 2 and arr.shape[1] == 3)
    ):
        return False
    with np.errstate(over="ignore"):
        if not np.isfinite(arr.astype(np.float64)).all():
            return False
    if isinstance(h, (bool, np.bool_)) or not isinstance(h, (int, float, np.floating, np.integer)):
        return False
    if not (math.isfinite(h) and h > 0):
        return False
    if strict and isinstance(stepper, pr.BisectionIntegrator) and h > stepper.h_max:
        return False
    return _is_int(n_steps) and n_steps >= 0 and _is_int(every) and every >= 1


@pytest.fixture(scope="module")
def property_steppers(random_model: RandomModel) -> list[object]:
    return [
        pr.taylor_integrator(BODY, order=3),
        random_model(42, widths=(5,)),
        pr.load_model(),
        pr.classical(BODY, "splitting"),
        pr.classical(BODY, "midpoint"),
    ]


@settings(
    derandomize=True,
    max_examples=400,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(
    which=st.integers(0, 4),
    mu0=_states(),
    h=_H,
    n_steps=_N_STEPS,
    every=_EVERY,
    strict=st.booleans(),
)
def test_integrate_arguments_property(
    property_steppers: list[object], which: int, mu0: object, h: object, n_steps: object,
    every: object, strict: bool,
):  # fmt: skip
    stepper = property_steppers[which]
    valid = _valid(stepper, mu0, h, n_steps, every, strict)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # out-of-domain and overflow warnings
        try:
            traj, info = pr.integrate(
                stepper, mu0, h, n_steps, every=every, return_info=True,  # type: ignore[arg-type]
                on_failure="ignore", strict=strict,
            )  # fmt: skip
        except (ValueError, TypeError) as e:
            assert not valid, f"valid arguments refused: {e}"
            assert str(e)
            return
    assert valid, "invalid arguments accepted"
    arr = np.asarray(mu0, dtype=np.float64).reshape(-1, 3)
    records = int(n_steps) // int(every) + 1  # type: ignore[call-overload]
    assert traj.dtype == np.float64
    assert traj.shape == ((records, 3) if np.ndim(mu0) == 1 else (len(arr), records, 3))
    traj = traj.reshape(len(arr), records, 3)
    np.testing.assert_array_equal(traj[:, 0], arr)
    for field in ("converged", "failed_step", "failure_code", "out_of_domain"):
        assert getattr(info, field).shape == (len(arr),)
    for i in range(len(arr)):
        if info.converged[i]:
            assert np.isfinite(traj[i]).all()
        else:
            k = int(info.failed_step[i])
            steps = np.arange(records) * int(every)  # type: ignore[call-overload]
            assert np.isfinite(traj[i, steps <= k]).all()
            assert np.isnan(traj[i, steps > k]).all()


# --- 4. Concurrency -----------------------------------------------------------------------------


def test_threads_give_the_sequential_results(random_model: RandomModel):
    rng = np.random.default_rng(25)
    jobs = [
        (pr.load_model(), random_states(rng, 48, 1.0, 4.0), 0.1),
        (random_model(43, chart="exp"), random_states(rng, 48, 1.0, 3.0), 0.05),
        (pr.classical(BODY, "dmv"), random_states(rng, 48), 0.1),
    ] * 4  # each integrator from 4 threads at once

    def run(job: tuple) -> np.ndarray:
        stepper, mu, h = job
        return pr.integrate(stepper, mu, h, 1000, every=25, on_failure="ignore", strict=False)

    sequential = [run(job) for job in jobs]
    with ThreadPoolExecutor(max_workers=4) as pool:
        concurrent = list(pool.map(run, jobs))
    for a, b in zip(sequential, concurrent, strict=True):
        assert a.tobytes() == b.tobytes()


_DIGEST = """
import hashlib
import numpy as np
import poisson_rs as pr
rng = np.random.default_rng(26)
d = rng.normal(size=(40, 3))
mu = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(1.0, 4.0, size=(40, 1))
h = hashlib.sha256()
for stepper in (pr.load_model(), pr.classical(pr.RigidBody((1.5, 2.0, 2.5)), "midpoint")):
    traj, info = pr.integrate(stepper, mu, 0.1, 3000, every=7, return_info=True)
    h.update(traj.tobytes())
    h.update(info.max_residual.tobytes())
print(h.hexdigest())
"""


def test_results_do_not_depend_on_the_thread_count():
    digests = {n: _run_python(_DIGEST, env={"RAYON_NUM_THREADS": str(n)}).strip() for n in (1, 2)}
    assert digests[1] == digests[2]
    # And the same bytes as this process, whatever its thread count.
    assert _run_python(_DIGEST).strip() == digests[1]
    assert len(digests[1]) == 64


# --- 5. Long horizons -----------------------------------------------------------------------------


def test_a_million_steps_in_bounded_memory(splitting: pr.ClassicalIntegrator):
    # 10⁶ steps of h = 0.1 (t = 10⁵) for 4 states keeps 1001 states each, ~100 KB.
    mu0 = np.array([[1.0, 1.0, 2.0], [3.0, 2.0, 0.0], [-0.5, 2.5, 1.0], [0.1, -3.0, 0.2]])
    traj, info = pr.integrate(splitting, mu0, 0.1, 10**6, every=1000, return_info=True)
    assert traj.shape == (4, 1001, 3) and traj.nbytes == 4 * 1001 * 3 * 8
    assert info.converged.all() and np.isfinite(traj).all()
    np.testing.assert_array_equal(traj[:, 0], mu0)
    # A Poisson map over 10⁶ steps: Casimir to round-off, energy bounded (no drift).
    c = BODY.casimir(traj)
    assert (np.abs(c / c[:, :1] - 1) < 1e-11).all()
    e = BODY.hamiltonian(traj)
    assert (np.abs(e / e[:, :1] - 1) < 1e-2).all()


def test_learned_model_long_horizon(default_model: pr.LearnedIntegrator):
    # 10⁵ steps of the default model from the paper's states, every 1000th kept.
    traj, info = pr.integrate(default_model, PAPER_STATES, 0.1, 10**5, every=1000, return_info=True)
    assert traj.shape == (2, 101, 3)
    assert info.converged.all() and (info.out_of_domain == 0).all()
    c = BODY.casimir(traj)
    assert (np.abs(c / c[:, :1] - 1) < 1e-11).all()
    e = BODY.hamiltonian(traj)
    assert (np.abs(e / e[:, :1] - 1) < 1e-4).all()
    # The same states as a rollout that kept every one of the first 2000 steps.
    full = pr.integrate(default_model, PAPER_STATES, 0.1, 2000)
    np.testing.assert_array_equal(traj[:, :3], full[:, ::1000])

"""The device rollouts (``integrate(..., device=...)``, ``pr.on_device``): the torch step of every
stepper that has one, run on the CPU (the reference path of the CUDA kernels), against the Rust
core's rollout of the same stepper; their refusals before any work; failures reported as the
core reports them."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

import poisson_rs as pr

RB = pr.RigidBody((1.5, 2.0, 2.5))
LV = pr.lotka_volterra([[0, 1, -1], [-1, 0, 1], [1, -1, 0]], [1.0, 2.0, 1.5])


def _states(dim: int, n: int, seed: int, scale: float = 1.0) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, dim)) * scale


def _top_states(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    g = rng.normal(size=(n, 3))
    return np.concatenate([rng.uniform(-1, 1, (n, 3)), g / np.linalg.norm(g, axis=1)[:, None]], 1)


RK4_CASES = {
    "rigid body": (pr.classical(RB, "rk4"), _states(3, 32, 1, 2.0)),
    "heavy top": (pr.classical(pr.HeavyTop(), "rk4"), _top_states(32, 2)),
    "sl(2)": (
        pr.classical(
            pr.LiePoissonSystem(
                pr.LieAlgebra.sl2(), pr.Polynomial({(2, 0, 0): 0.5, (0, 1, 1): 1.0})
            ),
            "rk4",
        ),
        _states(3, 32, 3, 0.5),
    ),
    "Lotka-Volterra 3-D": (
        pr.log_canonical_classical(LV, "rk4"),
        np.exp(np.random.default_rng(4).uniform(-0.4, 0.4, (32, 3))) * [1.0, 2.0, 1.5],
    ),
    "expression H": (
        pr.classical(pr.with_hamiltonian(RB, "x1**2/3 + cos(x2) + sqrt(1 + x3**2)"), "rk4"),
        _states(3, 32, 5),
    ),
}


@pytest.mark.parametrize("case", list(RK4_CASES))
def test_rk4_on_the_cpu_reference_path_is_the_cores_rk4(case: str) -> None:
    """Same formulas in the same order: agreement to a few ulps after 200 steps (the core's
    lanes and torch's vector ops round alike; only the order of a sum may differ)."""
    stepper, x0 = RK4_CASES[case]
    core = pr.integrate(stepper, x0, 0.05, 200, every=20)
    dev = pr.integrate(stepper, x0, 0.05, 200, every=20, device="cpu")
    assert dev.shape == core.shape == (len(x0), 11, x0.shape[1])
    assert np.abs(dev - core).max() <= 1e-12 * np.abs(core).max()


@pytest.mark.parametrize("case", ["rigid body", "Lotka-Volterra 3-D"])
def test_float32_states_stay_at_single_precision_of_the_core(case: str) -> None:
    stepper, x0 = RK4_CASES[case]
    core = pr.integrate(stepper, x0, 0.05, 100)
    dev = pr.integrate(pr.on_device(stepper, "cpu", dtype="float32"), x0, 0.05, 100)
    err = np.abs(dev - core).max() / np.abs(core).max()
    # float32 really is used (not silently float64), and stays near its precision.
    assert 1e-9 < err < 1e-4


@pytest.mark.parametrize("case", list(RK4_CASES))
def test_the_rk4_torch_step_follows_its_input_device(case: str) -> None:
    """On the meta device any constant built on the CPU instead of the input's device fails:
    the check the CUDA path needs, run where no GPU is."""
    stepper, x0 = RK4_CASES[case]
    x = torch.empty((5, x0.shape[1]), dtype=torch.float64, device="meta")
    out = stepper.torch_step(x, 0.1)
    assert out.device.type == "meta" and out.shape == (5, x0.shape[1])
    assert stepper.torch_graph


NEWTON_CASES = {
    "rigid body taylor3-exp": (pr.taylor_integrator(RB, order=3, chart="exp"), _states(3, 8, 6)),
    "rigid body taylor5-cayley": (
        pr.taylor_integrator(RB, order=5, chart="cayley"),
        _states(3, 8, 7),
    ),
    "heavy top taylor3-exp": (pr.taylor_integrator(pr.HeavyTop(), order=3), _top_states(6, 8)),
    "learned default": (
        pr.load_model("default"),
        _states(3, 8, 9) / np.linalg.norm(_states(3, 8, 9), axis=1)[:, None] * 2.0,
    ),
    "Lotka-Volterra taylor3-log": (
        pr.log_canonical_taylor(LV, 3),
        np.exp(np.random.default_rng(10).uniform(-0.4, 0.4, (8, 3))) * [1.0, 2.0, 1.5],
    ),
}


@pytest.mark.parametrize("case", list(NEWTON_CASES))
def test_newton_steps_on_the_cpu_reference_path_are_the_cores(case: str) -> None:
    """Taylor-HJ and learned steps: the same map solved to the same Newton tolerance, so
    trajectories agree to ~1e-12 after 20 steps, and the Poisson maps' Casimirs stay put."""
    stepper, x0 = NEWTON_CASES[case]
    core = pr.integrate(stepper, x0, 0.1, 20, every=5)
    dev = pr.integrate(stepper, x0, 0.1, 20, every=5, device="cpu")
    assert np.isfinite(dev).all()
    assert np.abs(dev - core).max() <= 1e-11 * np.abs(core).max()
    system = stepper.system
    c0, c1 = system.casimirs(dev[:, 0]), system.casimirs(dev[:, -1])
    assert np.abs(c1 - c0).max() <= 1e-12 * max(1.0, np.abs(c0).max())
    # A Newton step branches on convergence: not one graph, so not compiled by default.
    assert not getattr(stepper, "torch_graph", False)
    assert not pr.on_device(stepper, "cpu").compile


def test_a_trajectory_that_blows_up_fails_where_the_cores_fails() -> None:
    stepper = pr.classical(RB, "rk4")
    x0 = np.array([[1.0, 2.0, 3.0], [40.0, -30.0, 50.0]])
    with pytest.warns(RuntimeWarning, match="failed"):
        core, ci = pr.integrate(stepper, x0, 2.0, 40, return_info=True)
    with pytest.warns(RuntimeWarning, match="1 of 2 trajectories failed"):
        dev, di = pr.integrate(stepper, x0, 2.0, 40, return_info=True, device="cpu")
    assert di.failed_step.tolist() == ci.failed_step.tolist()
    assert di.failed_step[1] >= 0 and di.failure_code.tolist() == [0, 3]
    assert np.isnan(dev[1, di.failed_step[1] + 1 :]).all()
    np.testing.assert_allclose(dev[0], core[0], rtol=1e-12, atol=1e-12)


class _Counting:
    """A stepper whose torch step counts its calls (to show refusals come before the work)."""

    dim = 3
    name = "counting"

    def __init__(self) -> None:
        self.calls = 0

    def torch_step(self, mu: torch.Tensor, h: float) -> torch.Tensor:
        self.calls += 1
        return mu

    def rollout(self, x0: np.ndarray, h: float, n: int, every: int) -> tuple[np.ndarray, dict]:
        raise AssertionError("the core path must not run")


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cuda_without_a_gpu_is_refused_before_any_work() -> None:
    s = _Counting()
    with pytest.raises(ValueError, match="device 'cuda': torch sees no CUDA device"):
        pr.integrate(s, np.ones((4, 3)), 0.1, 10, device="cuda")
    assert s.calls == 0


@pytest.mark.parametrize(
    ("device", "error", "match"),
    [
        ("tpu", ValueError, "device must be 'cpu', 'cuda' or 'cuda:N'"),
        ("meta", ValueError, "device must be 'cpu', 'cuda' or 'cuda:N', got 'meta'"),
        ("cuda:x", ValueError, "device must be"),
        (3, TypeError, "device must be a string"),
    ],
)
def test_bad_devices_are_refused_naming_the_device(device: object, error: type, match: str) -> None:
    s = _Counting()
    with pytest.raises(error, match=match):
        pr.integrate(s, np.ones((4, 3)), 0.1, 10, device=device)
    assert s.calls == 0


def test_steppers_without_a_torch_step_are_refused_by_name() -> None:
    with pytest.raises(ValueError, match="classical integrator 'midpoint' has no torch step"):
        pr.integrate(pr.classical(RB, "midpoint"), np.ones(3), 0.1, 5, device="cpu")
    e2 = np.zeros((3, 3, 3))
    e2[0, 2, 1], e2[2, 0, 1], e2[1, 2, 0], e2[2, 1, 0] = 2.0, -2.0, -2.0, 2.0
    pendulum = pr.affine_poisson_system(
        e2, [[0, -1, 0], [1, 0, 0], [0, 0, 0]], {(2, 0, 0): 0.5, (0, 2, 0): 0.5}
    )
    affine = pr.affine_classical(pendulum, "rk4")
    with pytest.raises(TypeError, match="has no torch step"):
        pr.on_device(affine, "cpu")


def test_bad_dtype_and_compile_flags_are_refused() -> None:
    stepper = pr.classical(RB, "rk4")
    with pytest.raises(ValueError, match="dtype must be one of float64, float32"):
        pr.on_device(stepper, "cpu", dtype="float16")
    with pytest.raises(TypeError, match="compile must be"):
        pr.on_device(stepper, "cpu", compile="yes")  # type: ignore[arg-type]


def test_a_device_stepper_pickles_and_keeps_the_wrapped_steppers_attributes() -> None:
    stepper = pr.on_device(pr.load_model("default"), "cpu", dtype="float32")
    back = pickle.loads(pickle.dumps(stepper))
    assert (back.device.type, back.dtype, back.compile) == ("cpu", "float32", False)
    assert back.h_max == stepper.h_max == pr.load_model("default").h_max
    assert back.name == "default on cpu"
    with pytest.raises(AttributeError):
        _ = back.no_such_attribute


def test_the_compiled_step_is_the_eager_step() -> None:
    """What CUDA runs by default (torch.compile of the RK4 step), compiled here for the CPU:
    the same trajectories to round-off."""
    stepper, x0 = RK4_CASES["rigid body"]
    eager = pr.integrate(pr.on_device(stepper, "cpu"), x0, 0.05, 50)
    compiled = pr.integrate(pr.on_device(stepper, "cpu", compile=True), x0, 0.05, 50)
    assert np.abs(compiled - eager).max() <= 1e-13 * np.abs(eager).max()

"""Calls too large for the memory this process may use raise MemoryError, never abort.

Each case runs in a forked child under a real address-space limit (``resource.setrlimit``
RLIMIT_AS, what ``ulimit -v`` sets): the limit the core must read, and under which an
infallible allocation would abort the whole process (SIGABRT) instead of raising.
"""

from __future__ import annotations

import os
import pickle
import resource
import signal
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

import poisson_rs as pr
from poisson_rs.export import model_bytes

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork()")

GIB = 1 << 30


def _vm_size() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmSize:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmSize")


def run_limited(fn: Callable[[], object], headroom: int) -> str:
    """Runs ``fn`` in a forked child whose address space may grow by ``headroom`` bytes; returns
    the name of the exception it raised ("ok" if none). Fails if the child died of a signal."""
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: never returns into pytest
        code = 0
        try:
            os.close(read)
            _, hard = resource.getrlimit(resource.RLIMIT_AS)
            limit = _vm_size() + headroom
            if hard != resource.RLIM_INFINITY:
                limit = min(limit, hard)
            resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
            try:
                fn()
                outcome = "ok"
            except BaseException as exc:  # the point: report what came out
                outcome = f"{type(exc).__name__}: {exc}"
            os.write(write, pickle.dumps(outcome))
        except BaseException:
            code = 3
        finally:
            os._exit(code)
    os.close(write)
    with os.fdopen(read, "rb") as f:
        data = f.read()
    _, status = os.waitpid(pid, 0)
    if os.WIFSIGNALED(status):
        sig = os.WTERMSIG(status)
        pytest.fail(f"the child died of {signal.Signals(sig).name} instead of raising")
    assert os.WEXITSTATUS(status) == 0, "the child failed before running the case"
    return str(pickle.loads(data))


def wide_model(width: int) -> pr.LearnedIntegrator:
    """S = −tH + t³·N with N one tanh layer of ``width`` neurons (tiny weights: a valid model);
    its evaluation workspace grows with the width (about 5 kB per neuron)."""
    rng = np.random.default_rng(0)
    body = pr.RigidBody()
    layers = [
        (rng.normal(0, 1e-3, (width, 4)), np.zeros(width)),
        (rng.normal(0, 1e-3, (1, width)), np.zeros(1)),
    ]
    powers = np.array([[1, 2, 0, 0], [1, 0, 2, 0], [1, 0, 0, 2]])
    coeffs = -0.5 / np.asarray(body.inertia)
    data = model_bytes(
        powers=powers,
        coeffs=coeffs,
        layers=layers,
        mlp_power=3,
        chart="cayley",
        system=body,
        h_max=0.1,
        domain={"kind": "cube", "half_width": 3.0},
    )
    return pr.integrators.LearnedIntegrator(data)


@pytest.fixture(scope="module")
def wide() -> pr.LearnedIntegrator:
    return wide_model(1_000_000)


def test_a_wide_layer_is_memory_error_not_abort(wide: pr.LearnedIntegrator) -> None:
    p = np.ones((4, 3))
    # About 5 GB of workspace under a limit of 1 GB more than the child holds.
    outcome = run_limited(lambda: wide.derivatives(0.1, p), GIB)
    assert outcome.startswith("MemoryError"), outcome
    outcome = run_limited(lambda: wide._core.time_derivative(0.1, p), GIB)
    assert outcome.startswith("MemoryError"), outcome
    outcome = run_limited(lambda: wide.hj_residual(p, 0.1), GIB)
    assert outcome.startswith("MemoryError"), outcome
    # A rollout makes one workspace per thread: counted before it starts.
    outcome = run_limited(lambda: pr.integrate(wide, p, 0.01, 2), GIB)
    assert outcome.startswith("MemoryError"), outcome


def test_a_wide_layer_runs_where_the_memory_is_there() -> None:
    # A narrower layer of the same kind fits, and gives finite numbers: the limit is real.
    model = wide_model(2_000)
    _, _, hess = model.derivatives(0.1, np.ones((2, 3)))
    assert np.isfinite(hess).all()
    outcome = run_limited(lambda: model.derivatives(0.1, np.ones((2, 3))), GIB)
    assert outcome == "ok", outcome


def test_a_big_batch_is_memory_error_not_abort() -> None:
    model = pr.load_model("default")
    n = 6_000_000  # the inputs fit (144 MB each); the core's outputs (about 600 MB) do not
    p = np.tile(np.array([[1.0, 1.0, 2.0]]), (n, 1))

    def residual() -> object:
        return model.hj_residual(p, 0.1)

    outcome = run_limited(residual, 700 << 20)
    assert outcome.startswith("MemoryError"), outcome
    outcome = run_limited(lambda: model.derivatives(0.1, p), 400 << 20)
    assert outcome.startswith("MemoryError"), outcome


def test_a_rollout_too_large_for_the_limit_is_memory_error() -> None:
    model = pr.load_model("default")
    mu0 = np.tile(np.array([[1.0, 1.0, 2.0]]), (100_000, 1))
    # 100,000 trajectories x 1001 records x 3 float64 = 2.4 GB of output under a 1 GB limit.
    outcome = run_limited(lambda: pr.integrate(model, mu0, 0.1, 1000), GIB)
    assert outcome.startswith("MemoryError"), outcome


# ---------------------------------------------------------------------------------------------
# DOP853 and the exact flow: Python-side references check the memory as the core's rollouts do
# ---------------------------------------------------------------------------------------------


def _pendulum() -> pr.AffinePoissonSystem:
    c = np.zeros((3, 3, 3))
    c[0, 2, 1], c[2, 0, 1] = 2.0, -2.0
    c[1, 2, 0], c[2, 1, 0] = -2.0, 2.0
    h = {(2, 0, 0): 0.5, (0, 2, 0): 0.5, (0, 4, 0): -1.0 / 24.0}
    return pr.affine_poisson_system(c, [[0, -1, 0], [1, 0, 0], [0, 0, 0]], h)


#: A system of every structure, and a state in its domain.
DOP853_SYSTEMS: dict[str, tuple[Callable[[], object], list[float]]] = {
    "rigid_body": (lambda: pr.RigidBody(), [1.0, 0.5, -0.3]),
    "heavy_top": (lambda: pr.HeavyTop(), [0.1, 0.2, 0.3, 0.0, 0.6, 0.8]),
    "log_canonical": (lambda: pr.lotka_volterra([[0, 1], [-1, 0]], [1, 2]), [1.0, 0.8]),
    "affine": (_pendulum, [0.3, 0.1, 1.0]),
    "polynomial": (
        lambda: pr.PolynomialPoissonSystem(
            pr.PolynomialBivector.nambu("x1**2/2 + x2**2/2 + x3**2/2 + x1**3/3"),
            "x1**2/2 + x2**2/3",
        ),
        [0.3, 0.5, -0.4],
    ),
}


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    """DOP853 and the elliptic functions fail the test if they ever run."""
    import scipy.integrate

    from poisson_rs.structures import lie_poisson_reference

    def ran(*args: object, **kwargs: object) -> None:
        raise AssertionError("the reference was computed before its memory was checked")

    monkeypatch.setattr(scipy.integrate, "solve_ivp", ran)
    monkeypatch.setattr(lie_poisson_reference, "_flow_sorted", ran)


@pytest.mark.parametrize("name", sorted(DOP853_SYSTEMS))
def test_every_dop853_stepper_refuses_an_output_over_the_budget_before_the_work(
    name: str, no_work: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    from poisson_rs import memory

    make, state = DOP853_SYSTEMS[name]
    stepper = pr.classical(make(), "dop853")
    monkeypatch.setattr(memory, "usable_bytes", lambda: 1 << 20)  # budget: 0.8 MiB
    # 100,001 records of one state: 0.8 MiB of output for a 1D system, several for these.
    with pytest.raises(MemoryError, match=r"dop853 of 1 states at 100001 times needs about "):
        pr.integrate(stepper, state, h=0.01, n_steps=100_000)
    # Direct references go through the same check.
    with pytest.raises(MemoryError, match=r"needs about [\d.]+ MiB"):
        pr.reference_solution(make(), state, np.linspace(0.0, 1.0, 100_001))


def test_the_exact_flow_refuses_an_output_over_the_budget_before_the_work(
    no_work: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    from poisson_rs import memory

    monkeypatch.setattr(memory, "usable_bytes", lambda: 1 << 20)
    with pytest.raises(MemoryError, match=r"the exact flow of 1 states at 100001 times"):
        pr.exact_solution(pr.RigidBody(), [1.0, 0.5, -0.3], np.linspace(0.0, 1.0, 100_001))


def test_dop853_over_the_real_limit_is_the_memory_error_rk4_gives() -> None:
    # Under a real address-space limit (1 GiB more than the child holds) an output 20 % over
    # what is left: RK4 (checked in the core) and DOP853 (checked in Python) both refuse with
    # MemoryError before any work, DOP853 naming the size it was asked for.
    import scipy.integrate

    body = pr.RigidBody()
    n_steps = int(1.2 * GIB / 24)  # one state, 3 float64 a record

    def dop853() -> object:
        def ran(*args: object, **kwargs: object) -> None:
            raise AssertionError("DOP853 ran")

        scipy.integrate.solve_ivp = ran  # the child's own copy of the module
        return pr.integrate(pr.classical(body, "dop853"), [1.0, 0.5, -0.3], 0.01, n_steps)

    outcome = run_limited(dop853, GIB)
    assert outcome.startswith(f"MemoryError: dop853 of 1 states at {n_steps + 1} times"), outcome
    assert "GiB" in outcome
    outcome = run_limited(
        lambda: pr.integrate(pr.classical(body, "rk4"), [1.0, 0.5, -0.3], 0.01, n_steps), GIB
    )
    assert outcome.startswith("MemoryError"), outcome

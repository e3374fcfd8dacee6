"""Shared fixtures: seeded random generating functions, saved to model files and loaded back;
and the harness that interrupts a long rollout in a subprocess."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import pytest
import torch

from poisson_rs import LearnedIntegrator, load_model
from poisson_rs.export import save_model
from poisson_rs.generating import GeneratingFunction
from poisson_rs.taylor import taylor_terms

PAPER_INERTIA = (1.5, 2.0, 2.5)

# The tests use tiny tensors: torch's thread pool only adds overhead on a loaded 2-core machine
# (a 64-state torch_step takes 0.6 s with it and 0.02 s without).
torch.set_num_threads(1)


def assert_step_and_derivatives_match_torch(
    model: LearnedIntegrator, mu: np.ndarray, h: float
) -> None:
    """One Rust step against the torch step map (≤ 1e-11), and ∂S/∂p, ∂²S/∂p² at (h, mu) from
    the core's forward-mode jets against torch autograd (≤ 1e-12, 1e-11). mu: (n, dim)."""
    from poisson_rs import integrate
    from poisson_rs.generating import derivatives

    rust = integrate(model, mu, h, 1)[:, 1]
    torch_out = model.torch_step(torch.as_tensor(mu), h).numpy()
    np.testing.assert_allclose(rust, torch_out, rtol=0, atol=1e-11)
    _, g, hs = model.derivatives(h, mu)
    t = torch.full((len(mu),), h, dtype=torch.float64)
    _, gt, ht = derivatives(model.generating, t, torch.as_tensor(mu))
    np.testing.assert_allclose(g, gt.numpy(), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(hs, ht.numpy(), rtol=1e-11, atol=1e-11)


class RandomModel(Protocol):
    """Signature of the ``random_model`` factory fixture."""

    def __call__(
        self,
        seed: int,
        *,
        chart: str | None = None,
        inputs: str | None = None,
        widths: tuple[int, ...] | None = None,
        taylor_order: int | None = None,
        mlp_power: int | None = None,
        output_scale: float = 0.05,
    ) -> LearnedIntegrator: ...


def build_generating(
    seed: int,
    *,
    chart: str | None = None,
    inputs: str | None = None,
    widths: tuple[int, ...] | None = None,
    taylor_order: int | None = None,
    mlp_power: int | None = None,
    output_scale: float = 0.05,
) -> GeneratingFunction:
    """A seeded random S = Σ_{k≤K} t^k S_k + t^m · N(t, p); unset choices are drawn from ``seed``.

    The MLP gets random non-zero biases and non-trivial input scales, so that export (which folds
    the scales into the first and last layers) is exercised too. ``output_scale`` keeps the MLP a
    perturbation of the Taylor part, so that Newton converges at the step sizes under test.
    """
    rng = np.random.default_rng(seed)
    chart = str(rng.choice(["cayley", "exp"])) if chart is None else chart
    inputs = str(rng.choice(["t,p", "homogeneous"])) if inputs is None else inputs
    if widths is None:
        widths = tuple(int(w) for w in rng.integers(3, 17, size=int(rng.integers(1, 4))))
    taylor_order = int(rng.integers(1, 4)) if taylor_order is None else taylor_order
    mlp_power = int(rng.integers(1, 4)) if mlp_power is None else mlp_power
    powers, coeffs = taylor_terms(PAPER_INERTIA, taylor_order, chart)
    input_scale = (float(rng.uniform(2.0, 10.0)), *(float(s) for s in rng.uniform(0.2, 0.5, 3)))
    torch.manual_seed(seed)
    s_fn = GeneratingFunction(
        widths,
        mlp_power=mlp_power,
        powers=powers,
        coeffs=coeffs,
        chart=chart,
        inputs=inputs,
        input_scale=input_scale,
        output_scale=output_scale,
    )
    with torch.no_grad():
        for layer in s_fn.linears:
            layer.bias.copy_(torch.as_tensor(rng.normal(0.0, 0.5, layer.bias.shape)))
    return s_fn


def save_generating(
    s_fn: GeneratingFunction, path: Path, *, taylor_order: int = 0, **record: object
) -> Path:
    """Writes ``s_fn`` as a model file for the paper's body (h ≤ 1 on the cube [−3, 3]³)."""
    return save_model(
        s_fn,
        path,
        inertia=PAPER_INERTIA,
        h_max=1.0,
        domain={"kind": "cube", "half_width": 3.0, "t_max": 1.0},
        taylor_order=taylor_order,
        record=dict(record),
    )


@pytest.fixture(scope="session")
def random_model(tmp_path_factory: pytest.TempPathFactory) -> RandomModel:
    """Factory: ``random_model(seed, chart=..., widths=..., ...)`` → a loaded LearnedIntegrator.

    Goes through the whole export path (torch module → safetensors file → Rust core), so a test
    comparing its Rust steps with its own torch module (``.generating``, rebuilt from the file)
    checks the file format as well. The metadata records ``taylor_order`` and ``seed``.
    """
    root = tmp_path_factory.mktemp("models")
    cache: dict[tuple[object, ...], LearnedIntegrator] = {}

    def make(
        seed: int,
        *,
        chart: str | None = None,
        inputs: str | None = None,
        widths: tuple[int, ...] | None = None,
        taylor_order: int | None = None,
        mlp_power: int | None = None,
        output_scale: float = 0.05,
    ) -> LearnedIntegrator:
        key = (seed, chart, inputs, widths, taylor_order, mlp_power, output_scale)
        if key not in cache:
            s_fn = build_generating(
                seed,
                chart=chart,
                inputs=inputs,
                widths=widths,
                taylor_order=taylor_order,
                mlp_power=mlp_power,
                output_scale=output_scale,
            )
            order = int(np.max(s_fn.powers[:, 0].numpy(), initial=0))
            path = root / f"model{len(cache)}.safetensors"
            cache[key] = load_model(save_generating(s_fn, path, taylor_order=order, seed=seed))
        return cache[key]

    return make


def random_states(
    rng: np.random.Generator, n: int, r_min: float = 0.5, r_max: float = 3.5
) -> np.ndarray:
    """n states with |μ| uniform in [r_min, r_max] and uniformly random directions: (n, 3)."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * rng.uniform(r_min, r_max, size=(n, 1))


def interrupt_long_rollout(code: str, *args: str) -> tuple[str, str, int, float]:
    """Runs ``code`` (``python -c``, with ``args``), which prints "ready" just before a rollout
    far too long to finish, sends it SIGINT one second later and waits for it to stop.

    Returns (stdout after "ready", stderr, return code, seconds from SIGINT to exit). Fails the
    test if the rollout ended before it was interrupted; the process is killed if it hangs."""
    proc = subprocess.Popen(
        [sys.executable, "-c", code, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "ready"  # however long the imports took
        time.sleep(1.0)
        assert proc.poll() is None, "the rollout ended before it was interrupted"
        sent = time.perf_counter()
        os.kill(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=60)
        latency = time.perf_counter() - sent
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return out, err, proc.returncode, latency


def count_dop853_rhs(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """From now on, one entry per ``solve_ivp`` run (a DOP853 integration) counting the
    right-hand sides it evaluated: the work, measured without a clock."""
    import scipy.integrate

    counts: list[int] = []
    solve_ivp = scipy.integrate.solve_ivp

    def counting(fun: Any, *args: Any, **kwargs: Any) -> Any:
        counts.append(0)

        def counted(t: float, y: np.ndarray) -> Any:
            counts[-1] += 1
            return fun(t, y)

        return solve_ivp(counted, *args, **kwargs)

    monkeypatch.setattr(scipy.integrate, "solve_ivp", counting)
    return counts

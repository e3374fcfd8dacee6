"""The Rust stepper against the pure-torch oracle: same S, same derivatives, same step map.

Each model goes torch module → model file → Rust core, and the oracle is the torch module rebuilt
from that same file, so these tests also pin down the file format (scale folding, tensor layout,
the MLP inputs ansatz).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import RandomModel, random_states

import poisson_rs as pr
from poisson_rs.generating import derivatives

H_VALUES = (0.05, 0.1, 0.3)
RANDOM_SEEDS = range(6)
# Explicit cases, so both charts and both MLP ansätze are covered whatever the seeds draw.
EXPLICIT = [
    pytest.param(100, "cayley", "t,p", (16, 16), 1, id="cayley-tp"),
    pytest.param(101, "exp", "t,p", (8, 12, 6), 2, id="exp-tp"),
    pytest.param(102, "cayley", "homogeneous", (12,), 3, id="cayley-homogeneous"),
    pytest.param(103, "exp", "homogeneous", (10, 10), 4, id="exp-homogeneous"),
]


def _rel_err(a: np.ndarray, b: np.ndarray, mu: np.ndarray) -> float:
    """max |a − b| per state, relative to |μ| of that state."""
    scale = np.linalg.norm(mu, axis=-1)
    return float(np.max(np.abs(a - b).reshape(len(scale), -1) / scale[:, None]))


def _torch_rollout(model: pr.LearnedIntegrator, mu0: np.ndarray, h: float, n: int) -> np.ndarray:
    """n steps of the torch step map: (B, 3) → (B, n + 1, 3)."""
    states = [torch.as_tensor(mu0, dtype=torch.float64)]
    for _ in range(n):
        states.append(model.torch_step(states[-1], h))
    return torch.stack(states, dim=1).numpy()


def _check_step(model: pr.LearnedIntegrator, mu: np.ndarray, h: float) -> None:
    rust = pr.integrate(model, mu, h, 1)[:, 1]
    oracle = model.torch_step(torch.tensor(mu), h).numpy()
    assert np.isfinite(oracle).all(), "the torch Newton solve failed; the model is too wild"
    assert _rel_err(rust, oracle, mu) <= 1e-12
    # The MLP must actually move the step, or a mis-exported MLP would go unnoticed.
    taylor = pr.taylor_integrator(order=model.metadata["taylor_order"], chart=model.chart)
    assert _rel_err(rust, pr.integrate(taylor, mu, h, 1)[:, 1], mu) > 1e-7


@pytest.mark.parametrize("h", H_VALUES)
@pytest.mark.parametrize("seed", RANDOM_SEEDS)
def test_step_map_matches_torch_random_models(random_model: RandomModel, seed: int, h: float):
    model = random_model(seed)
    mu = random_states(np.random.default_rng(seed + 1000), 32)
    _check_step(model, mu, h)


@pytest.mark.parametrize("h", H_VALUES)
@pytest.mark.parametrize(("seed", "chart", "inputs", "widths", "mlp_power"), EXPLICIT)
def test_step_map_matches_torch_both_charts(
    random_model: RandomModel,
    seed: int,
    chart: str,
    inputs: str,
    widths: tuple[int, ...],
    mlp_power: int,
    h: float,
):
    model = random_model(seed, chart=chart, inputs=inputs, widths=widths, mlp_power=mlp_power)
    assert model.chart == chart
    mu = random_states(np.random.default_rng(seed), 32)
    _check_step(model, mu, h)


# MLPs with over 1000 parameters: the Rust core solves them 16 trajectories at a time, each layer
# one matrix product, with simplified Newton by default.
BATCHED = [
    pytest.param(110, "cayley", "t,p", (40, 40), 1, id="cayley-tp-40x40"),
    pytest.param(111, "exp", "homogeneous", (64, 32, 16), 3, id="exp-homogeneous-64x32x16"),
]


@pytest.mark.parametrize("newton", ["simplified", "full"])
@pytest.mark.parametrize(("seed", "chart", "inputs", "widths", "mlp_power"), BATCHED)
def test_batched_step_map_matches_torch(
    random_model: RandomModel,
    seed: int,
    chart: str,
    inputs: str,
    widths: tuple[int, ...],
    mlp_power: int,
    newton: str,
):
    loaded = random_model(seed, chart=chart, inputs=inputs, widths=widths, mlp_power=mlp_power)
    model = pr.LearnedIntegrator(loaded._source, newton=newton)  # type: ignore[arg-type]
    assert model.batch == 16 and model.newton == newton
    # 37 states: two full batches and a partial one.
    mu = random_states(np.random.default_rng(seed), 37)
    _check_step(model, mu, 0.1)


def test_simplified_and_full_newton_agree_over_a_rollout(random_model: RandomModel):
    loaded = random_model(110, chart="cayley", inputs="t,p", widths=(40, 40), mlp_power=1)
    mu = random_states(np.random.default_rng(5), 40)
    runs = {}
    for newton in ("simplified", "full"):
        model = pr.LearnedIntegrator(loaded._source, newton=newton)  # type: ignore[arg-type]
        runs[newton] = pr.integrate(model, mu, 0.1, 50, return_info=True)
    (a, info_a), (b, info_b) = runs["simplified"], runs["full"]
    assert _rel_err(a, b, mu) <= 1e-11
    assert info_a.converged.all() and info_b.converged.all()
    # More updates, each far cheaper: simplified Newton is linear, not quadratic.
    assert (info_a.newton_iterations >= info_b.newton_iterations).all()
    assert info_a.max_residual.max() <= 1e-11 * np.linalg.norm(mu, axis=1).max()


def test_newton_option_is_checked():
    with pytest.raises(ValueError, match="newton must be 'simplified' or 'full'"):
        pr.load_model("default", newton="quasi")  # type: ignore[arg-type]
    # 121 parameters: batched (tanh rows and polynomial jets in SIMD lanes) since it pays off.
    assert pr.load_model("default").batch == 16


@pytest.mark.parametrize("chart", ["cayley", "exp"])
@pytest.mark.parametrize("order", [1, 3, 5])
def test_taylor_step_map_matches_torch(chart: str, order: int):
    # A polynomial-only S travels through model_bytes, not save_model: check that path as well.
    model = pr.taylor_integrator(order=order, chart=chart)
    mu = random_states(np.random.default_rng(order), 32)
    for h in H_VALUES:
        rust = pr.integrate(model, mu, h, 1)[:, 1]
        assert _rel_err(rust, model.torch_step(torch.tensor(mu), h).numpy(), mu) <= 1e-12


@pytest.mark.parametrize("t", [0.0, 0.05, 0.3, 1.0])
@pytest.mark.parametrize(
    ("seed", "chart", "inputs"),
    [(0, None, None), (1, None, None), (100, "cayley", "t,p"), (103, "exp", "homogeneous")],
)
def test_derivatives_match_autograd(
    random_model: RandomModel, seed: int, chart: str | None, inputs: str | None, t: float
):
    model = random_model(seed, chart=chart, inputs=inputs)
    p = random_states(np.random.default_rng(seed + 7), 50, r_min=0.1, r_max=4.0)
    s, grad, hess = model.derivatives(t, p)
    assert s.shape == (50,) and grad.shape == (50, 3) and hess.shape == (50, 3, 3)
    t_batch = torch.full((50,), t, dtype=torch.float64)
    ts, tg, th = (x.numpy() for x in derivatives(model.generating, t_batch, torch.tensor(p)))
    for rust, oracle in ((s, ts), (grad, tg), (hess, th)):
        scale = max(float(np.max(np.abs(oracle))), 1e-300)
        np.testing.assert_allclose(rust, oracle, rtol=1e-12, atol=1e-12 * scale)
    if t == 0.0:
        # S(0, ·) = 0 identically, so all its p-derivatives vanish too.
        assert np.all(s == 0) and np.all(grad == 0) and np.all(hess == 0)
    else:
        assert np.max(np.abs(hess)) > 1e-3  # a non-trivial comparison
    np.testing.assert_allclose(hess, np.swapaxes(hess, 1, 2), rtol=0, atol=1e-14)


@pytest.mark.parametrize("h", [0.1, 0.3])
@pytest.mark.parametrize(
    ("seed", "chart", "inputs"),
    [(2, None, None), (100, "cayley", "t,p"), (101, "exp", "t,p"), (102, "cayley", "homogeneous")],
)
def test_multi_step_rollout_matches_torch(
    random_model: RandomModel, seed: int, chart: str | None, inputs: str | None, h: float
):
    model = random_model(seed, chart=chart, inputs=inputs)
    mu0 = random_states(np.random.default_rng(seed + 50), 8)
    n = 25
    rust = pr.integrate(model, mu0, h, n)
    oracle = _torch_rollout(model, mu0, h, n)
    assert rust.shape == oracle.shape == (8, n + 1, 3)
    # Round-off differences grow at most linearly along an integrable flow.
    assert _rel_err(rust, oracle, mu0) <= 1e-11
    # ... and the states really moved: the comparison is not of near-constant sequences.
    assert _rel_err(rust[:, -1], mu0, mu0) > 1e-2


@pytest.mark.parametrize("chart", ["cayley", "exp"])
def test_torch_step_at_states_with_zero_components(chart: str) -> None:
    # p ** k with a tensor exponent has NaN second derivatives at p = 0; the paper's (3, 2, 0)
    # and the principal axes must step exactly as in Rust.
    model = pr.taylor_integrator(order=5, chart=chart)
    mu = np.array([[3.0, 2.0, 0.0], [0.0, 0.0, 1.5], [0.0, 2.0, 0.0], [0.0, 0.0, 0.0]])
    rust = pr.integrate(model, mu, 0.1, 1)[:, 1]
    ours = model.torch_step(torch.tensor(mu), 0.1).numpy()
    assert np.isfinite(ours).all()
    np.testing.assert_allclose(ours, rust, rtol=0, atol=1e-14)

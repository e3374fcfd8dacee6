"""Lie–Poisson systems end to end: the heavy top on se(3)* and sl(2, R), through the Rust core
against independent oracles — the torch step map (autograd Newton), a DOP853 reference (fitted
orders), and the Casimirs (kept to round-off by every bisection integrator). A system built from
so(3) structure constants reproduces the rigid body to round-off."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import assert_step_and_derivatives_match_torch

import poisson_rs as pr
from poisson_rs.export import save_model
from poisson_rs.generating import GeneratingFunction
from poisson_rs.taylor import system_taylor_terms

TOP = pr.HeavyTop(inertia=(1.0, 1.5, 2.0), mgl=0.981, com=(0.0, 0.0, 1.0))
TOP_STATES = np.array([[0.3, -0.8, 1.2, 0.6, 0.0, 0.8], [1.0, 0.5, -0.4, 0.0, 0.6, 0.8]])


def sl2_system() -> pr.LiePoissonSystem:
    h = pr.Polynomial({(2, 0, 0): 0.5, (0, 2, 0): 0.4, (0, 0, 2): 0.3, (0, 1, 1): 0.1})
    return pr.LiePoissonSystem(pr.LieAlgebra.sl2(), h)


SL2_STATES = np.array([[0.4, 0.7, -0.2], [-0.3, 0.2, 0.5]])


def fitted_order(stepper: object, system: pr.LiePoissonSystem, mu0: np.ndarray, t: float) -> float:
    """Slope of log error against log h at time t, from h = t/20 and t/40, against DOP853."""
    ref = pr.reference_solution(system, mu0, np.array([0.0, t]))[:, -1]
    errs = []
    for n in (20, 40):
        out = pr.integrate(stepper, mu0, t / n, n)[:, -1]
        errs.append(np.abs(out - ref).max())
    return float(np.log2(errs[0] / errs[1]))


@pytest.mark.parametrize(
    ("system", "states"), [(TOP, TOP_STATES), (sl2_system(), SL2_STATES)], ids=["se3", "sl2"]
)
@pytest.mark.parametrize("order", [1, 3, 5])
def test_taylor_orders(system: pr.LiePoissonSystem, states: np.ndarray, order: int) -> None:
    """Taylor K on a quadratic-plus-linear H has order K + 1 for odd K (S_{K+1} = 0)."""
    stepper = pr.taylor_integrator(system, order=order)
    assert stepper.chart == "exp"
    p = fitted_order(stepper, system, states, 1.0)
    assert abs(p - (order + 1)) < 0.35, p


@pytest.mark.parametrize(
    ("name", "order"), [("rk4", 4), ("midpoint", 2), ("splitting", 2)], ids=str
)
def test_heavy_top_classical_orders(name: str, order: int) -> None:
    p = fitted_order(pr.classical(TOP, name), TOP, TOP_STATES, 1.0)
    assert abs(p - order) < 0.3, p


def test_sl2_classical_orders_and_no_splitting() -> None:
    system = sl2_system()
    assert fitted_order(pr.classical(system, "rk4"), system, SL2_STATES, 1.0) == pytest.approx(
        4, abs=0.3
    )
    with pytest.raises(ValueError, match="splitting"):
        pr.classical(system, "splitting")


@pytest.mark.parametrize("order", [1, 3, 5])
def test_bisection_keeps_casimirs_over_ten_thousand_steps(order: int) -> None:
    for system, states in ((TOP, TOP_STATES), (sl2_system(), SL2_STATES)):
        traj = pr.integrate(pr.taylor_integrator(system, order=order), states, 0.05, 10_000)
        c = system.casimirs(traj)
        drift = np.abs(c - c[:, :1]).max()
        assert drift < 1e-11 * max(1.0, np.abs(c).max()), (system, drift)


GROWTH_CASES = {
    # name: (system, chart, states); so(3) compact (both charts), sl(2, R) non-compact, se(3).
    "so3-cayley": (pr.RigidBody((1.5, 2.0, 2.5)), "cayley", 16),
    "so3-exp": (pr.RigidBody((1.5, 2.0, 2.5)), "exp", 16),
    "se3-exp": (TOP, "exp", 8),
    "sl2-exp": (sl2_system(), "exp", 16),
}


def casimir_growth_exponent(
    system: pr.LiePoissonSystem, chart: str, n_states: int, seed: int = 0
) -> float:
    """Growth exponent of the Casimir drift of Taylor-3 (h = 0.1) over n = 10³ … 10⁵ steps.

    States: ``n_states`` seeded draws with |μ| ≤ 0.6. The drift ΔC(n) of every state and
    Casimir, relative to |μ₀|², is recorded every 1000 steps; the exponent is half the slope of
    log mean ΔC² against log n at nine log-spaced records. Round-off that adds up like a random
    walk gives ½, a bias per step 1; the mean over states keeps the estimate within about ±0.1
    (0.36–0.61 over seeds 0–9 here; about 1.0 when the step carried Newton's residual).
    """
    rng = np.random.default_rng(seed)
    mu0 = rng.normal(size=(n_states, system.dim))
    mu0 *= 0.6 * rng.uniform(0.5, 1.0, (n_states, 1)) / np.linalg.norm(mu0, axis=1, keepdims=True)
    stepper = pr.taylor_integrator(system, 3, chart=chart)
    traj = pr.integrate(stepper, mu0, 0.1, 100_000, every=1000)
    c = np.asarray(system.casimirs(traj))  # (states, records, casimirs)
    drift = (c - c[:, :1]) / (np.linalg.norm(mu0, axis=1) ** 2)[:, None, None]
    mean_square = (drift**2).mean(axis=(0, 2))
    records = np.array([1, 2, 3, 5, 10, 20, 30, 50, 100])
    n = records * 1000.0
    slope = np.polyfit(np.log(n), np.log(mean_square[records] + 1e-40), 1)[0]
    return 0.5 * float(slope)


@pytest.mark.parametrize("name", list(GROWTH_CASES))
def test_bisection_casimir_drift_grows_like_round_off(name: str) -> None:
    """The Casimir drift of a bisection rollout is round-off, which grows like √n, not a bias
    per step, which grows like n: the new state is the coadjoint action of the chart's group
    element on μ, not sou at Newton's last iterate (whose residual, up to simplified Newton's
    tolerance and of one sign from step to step, went into C)."""
    system, chart, n_states = GROWTH_CASES[name]
    exponent = casimir_growth_exponent(system, chart, n_states)
    assert exponent <= 0.75, f"{name}: |ΔC| grows like n^{exponent:.2f}"


def test_heavy_top_splitting_keeps_casimirs_and_rk4_does_not() -> None:
    split = pr.integrate(pr.classical(TOP, "splitting"), TOP_STATES, 0.1, 10_000)
    c = TOP.casimirs(split)
    assert np.abs(c - c[:, :1]).max() < 1e-11
    rk4 = pr.integrate(pr.classical(TOP, "rk4"), TOP_STATES, 0.1, 10_000)
    c = TOP.casimirs(rk4)
    assert np.abs(c - c[:, :1]).max() > 1e-9  # drifts: the test above can fail


def test_so3_structure_constants_reproduce_the_rigid_body() -> None:
    body = pr.RigidBody((1.5, 2.0, 2.5))
    generic = pr.LiePoissonSystem(pr.LieAlgebra(body.algebra.c), body.polynomial)
    mu0 = np.array([[1.0, 1.0, 2.0], [3.0, 2.0, 0.0]])
    a = pr.integrate(pr.classical(body, "rk4"), mu0, 0.1, 100)
    b = pr.integrate(pr.classical(generic, "rk4"), mu0, 0.1, 100)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-13)
    ta = pr.integrate(pr.taylor_integrator(body, 3, chart="exp"), mu0, 0.1, 100)
    tb = pr.integrate(pr.taylor_integrator(generic, 3, chart="exp"), mu0, 0.1, 100)
    np.testing.assert_allclose(ta, tb, rtol=0, atol=1e-12)


def random_heavy_top_model(seed: int, tmp_path: Path) -> pr.LearnedIntegrator:
    """A seeded heavy-top model: Taylor K=3 plus t^5 · a small random MLP, exported and loaded."""
    rng = np.random.default_rng(seed)
    powers, coeffs = system_taylor_terms(TOP, 3, "exp")
    torch.manual_seed(seed)
    s_fn = GeneratingFunction(
        (12, 9),
        mlp_power=5,
        powers=powers,
        coeffs=coeffs,
        chart="exp",
        inputs="t,p",
        input_scale=(5.0, *rng.uniform(0.2, 0.5, 6)),
        output_scale=0.05,
        algebra=TOP.algebra,
    )
    with torch.no_grad():
        for layer in s_fn.linears:
            layer.bias.copy_(torch.as_tensor(rng.normal(0.0, 0.5, layer.bias.shape)))
    path = save_model(
        s_fn,
        tmp_path / f"top{seed}.safetensors",
        system=TOP,
        h_max=0.2,
        domain={"kind": "cube", "half_width": 2.0, "t_max": 0.2},
        taylor_order=3,
    )
    return pr.load_model(path)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_heavy_top_rust_and_torch_step_maps_agree(seed: int, tmp_path: Path) -> None:
    model = random_heavy_top_model(seed, tmp_path)
    assert model.system == TOP and model.dim == 6
    rng = np.random.default_rng(100 + seed)
    mu = rng.uniform(-1.5, 1.5, size=(16, 6))
    assert_step_and_derivatives_match_torch(model, mu, 0.1)


def test_learned_model_records_its_system(tmp_path: Path) -> None:
    model = random_heavy_top_model(3, tmp_path)
    assert isinstance(model.system, pr.HeavyTop)
    assert model.system.mgl == pytest.approx(0.981)
    assert model.body is model.system  # the alias, kept one release, on every model
    with pytest.raises(ValueError, match=r"shape \(6,\) or \(n, 6\)"):
        pr.integrate(model, [1.0, 2.0, 3.0], 0.1, 1)
    r = model.hj_residual(TOP_STATES, 0.1)
    assert r.shape == (2,) and np.all(np.abs(r) < 1e-3)


def test_forked_child_rolls_out_serially() -> None:
    """After a rollout in the parent, a forked child's rollout neither hangs nor differs."""
    import multiprocessing as mp

    model = pr.taylor_integrator(TOP, order=3)
    mu = np.tile(TOP_STATES, (32, 1))
    parent = pr.integrate(model, mu, 0.1, 50)
    ctx = mp.get_context("fork")
    with ctx.Pool(1) as pool:
        child = pool.apply_async(_child_rollout, (mu,)).get(timeout=60)
    np.testing.assert_array_equal(parent, child)


def _child_rollout(mu: np.ndarray) -> np.ndarray:
    from poisson_rs import _core

    assert _core.serial_rollouts()
    return pr.integrate(pr.taylor_integrator(TOP, order=3), mu, 0.1, 50)


def test_bad_systems_are_refused() -> None:
    with pytest.raises(ValueError, match="antisymmetric"):
        pr.LieAlgebra(np.ones((3, 3, 3)))
    with pytest.raises(ValueError, match=r"(?i)cayley"):
        pr.taylor_integrator(TOP, 3, chart="cayley")
    with pytest.raises(ValueError):
        pr.LiePoissonSystem(pr.LieAlgebra.se3(), pr.Polynomial({(2, 0, 0): 1.0}))

"""Tests for the groupoid charts: so(3) closed forms, the Bernoulli series for any algebra, and the
bisection map they give (Casimirs kept, Poisson, the right direction of time)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.autograd.functional import jacobian

from poisson_rs.realizations.lie_groupoid import (
    EXP_SERIES_MAX_RADIUS,
    _bernoulli_over_factorial,
    _exp_series,
    check_chart,
    sou,
    tar,
)
from poisson_rs.reference import reference_solution
from poisson_rs.structures.lie_poisson import HeavyTop, LieAlgebra, LiePoissonSystem, Polynomial

torch.set_num_threads(1)

SE3, SL2, SO3 = LieAlgebra.se3(), LieAlgebra.sl2(), LieAlgebra.so3()
SYSTEMS = {
    "heavy_top": HeavyTop(com=(0.3, -0.2, 1.0)),
    "sl2": LiePoissonSystem(
        SL2, Polynomial({(2, 0, 0): 0.5, (0, 1, 1): 1.0, (0, 2, 0): 0.3, (1, 1, 0): 0.2})
    ),
}


def _points(seed: int, n: int, count: int, scale: float) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return scale * rng.normal(size=(count, n)), rng.normal(size=(count, n))


# --- series against the closed forms -------------------------------------------------------------


def test_bernoulli_table() -> None:
    b = _bernoulli_over_factorial()
    assert b[:5] == (1.0, -0.5, 1.0 / 12.0, 0.0, -1.0 / 720.0)
    assert all(v == 0.0 for v in b[3::2])
    # B₂ₖ/(2k)! → (−1)^{k+1} 2/(2π)^{2k}
    for k in (20, 100, 150):
        assert b[2 * k] == pytest.approx((-1) ** (k + 1) * 2.0 / (2 * np.pi) ** (2 * k), rel=1e-13)


def test_generic_series_on_so3_equals_the_closed_form_exp_chart() -> None:
    x, p = _points(0, 3, 200, 1.0)
    x *= np.random.default_rng(1).uniform(0.0, 5.0, (200, 1)) / np.linalg.norm(x, axis=1)[:, None]
    for sign, closed in ((1.0, sou), (-1.0, tar)):
        series = _exp_series(SO3.c, x, p, sign)
        scale = np.maximum(1.0, np.abs(closed("exp", x, p)).max(axis=1, keepdims=True))
        assert np.max(np.abs(series - closed("exp", x, p)) / scale) < 1e-14
    # Torch path too, differentiably.
    xt, pt = torch.tensor(x, requires_grad=True), torch.tensor(p)
    value = _exp_series(SO3.c, xt, pt, 1.0)
    (gx,) = torch.autograd.grad(value.sum(), xt)
    xc = torch.tensor(x, requires_grad=True)
    (gc,) = torch.autograd.grad(sou("exp", xc, pt).sum(), xc)
    np.testing.assert_allclose(gx.numpy(), gc.numpy(), atol=1e-12)


@pytest.mark.parametrize("chart", ["cayley", "exp"])
def test_so3_algebra_takes_the_closed_form_path_bit_for_bit(chart: str) -> None:
    x, p = _points(2, 3, 50, 1.0)
    for f in (sou, tar):
        np.testing.assert_array_equal(f(chart, x, p, SO3), f(chart, x, p))
        np.testing.assert_array_equal(f(chart, x, p, None), f(chart, x, p))


def test_cayley_is_refused_for_other_algebras() -> None:
    assert check_chart("cayley") == "cayley" and check_chart("cayley", SO3) == "cayley"
    assert check_chart("exp", SE3) == "exp"
    with pytest.raises(ValueError, match="so\\(3\\) only; use the 'exp' chart for se3"):
        check_chart("cayley", SE3)
    with pytest.raises(ValueError, match="so\\(3\\) only"):
        sou("cayley", np.zeros(6), np.ones(6), SE3)
    with pytest.raises(ValueError, match="unknown chart"):
        tar("midpoint", np.zeros(3), np.ones(3), SL2)
    with pytest.raises(TypeError, match="algebra must be a LieAlgebra"):
        check_chart("exp", "se3")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 6\)"):
        sou("exp", np.zeros(3), np.ones(3), SE3)


# --- identities of the generic charts ------------------------------------------------------------


@pytest.mark.parametrize("algebra", [SE3, SL2], ids=["se3", "sl2"])
def test_units_difference_and_casimirs(algebra: LieAlgebra) -> None:
    n = algebra.dim
    x, p = _points(3, n, 100, 0.6)
    # Units: x = 0 gives p exactly.
    np.testing.assert_array_equal(sou("exp", np.zeros((100, n)), p, algebra), p)
    np.testing.assert_array_equal(tar("exp", np.zeros((100, n)), p, algebra), p)
    alpha, beta = tar("exp", x, p, algebra), sou("exp", x, p, algebra)
    ad_t_p = np.einsum("...jk,...k->...j", algebra.ad_transpose(x), p)
    np.testing.assert_allclose(alpha - beta, ad_t_p, atol=1e-13)
    # Same coadjoint orbit: every Casimir agrees.
    system = SYSTEMS["heavy_top" if algebra == SE3 else "sl2"]
    np.testing.assert_allclose(system.casimirs(alpha), system.casimirs(beta), atol=1e-12)
    # First terms of the series: β = p − ½ A p + (1/12) A² p + O(x⁴), A = ad_xᵀ.
    small = 1e-3 * x
    a = algebra.ad_transpose(small)
    ap = np.einsum("...jk,...k->...j", a, p)
    aap = np.einsum("...jk,...k->...j", a, ap)
    np.testing.assert_allclose(sou("exp", small, p, algebra), p - 0.5 * ap + aap / 12, atol=1e-11)


def test_torch_matches_numpy_and_broadcasts() -> None:
    x, p = _points(4, 6, 20, 0.7)
    expected = sou("exp", x, p, SE3)
    got = sou("exp", torch.tensor(x), torch.tensor(p), SE3)
    assert isinstance(got, torch.Tensor) and got.dtype == torch.float64
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-14, atol=1e-14)
    # One x against many p.
    many = tar("exp", x[0], p, SE3)
    np.testing.assert_allclose(many, tar("exp", np.broadcast_to(x[0], p.shape), p, SE3))
    assert sou("exp", x[0], p[0], SE3).shape == (6,)


def test_refused_rows_are_nan_and_keep_gradients_finite() -> None:
    # ad_x on se(3) has eigenvalues 0, ±i|ω| (twice): radius |ω|, the rotation part of x.
    x = np.zeros((4, 6))
    x[:, 0] = [0.5, 0.89 * 2 * np.pi, 0.91 * 2 * np.pi, 7.0]
    x[:, 4] = 3.0
    p = np.ones((4, 6))
    out = sou("exp", x, p, SE3)
    assert np.isfinite(out[:2]).all() and np.isnan(out[2:]).all()
    assert 0.89 * 2 * np.pi < EXP_SERIES_MAX_RADIUS < 0.91 * 2 * np.pi
    nan_x = np.full((1, 6), np.nan)
    assert np.isnan(tar("exp", nan_x, np.ones((1, 6)), SE3)).all()
    xt = torch.tensor(x, requires_grad=True)
    value = tar("exp", xt, torch.tensor(p), SE3)
    (grad,) = torch.autograd.grad(value[:2].sum(), xt)
    assert torch.isfinite(grad).all() and (grad[2:] == 0).all()
    # Near the limit the series still converges: α − β = A p holds there too.
    a = np.einsum("...jk,...k->...j", SE3.ad_transpose(x[:2]), p[:2])
    np.testing.assert_allclose(tar("exp", x[:2], p[:2], SE3) - out[:2], a, atol=1e-11)


# --- Poisson structure ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_sou_and_tar_are_opposite_poisson_maps_that_commute(name: str) -> None:
    """With the canonical bracket {x_i, p_j} = δ_ij, tar is Poisson and sou anti-Poisson for the
    project's bracket Π(μ) (μ̇ = Π(μ)∇H); with {p_j, x_i} = δ_ij it is the other way round. Their
    components commute, as source and target of a symplectic groupoid must."""
    system = SYSTEMS[name]
    algebra, n = system.algebra, system.dim
    rng = np.random.default_rng(5)
    eye, zero = torch.eye(n, dtype=torch.float64), torch.zeros(n, n, dtype=torch.float64)
    canonical = torch.cat([torch.cat([zero, eye], 1), torch.cat([-eye, zero], 1)], 0)
    for _ in range(5):
        z = torch.tensor(np.concatenate([0.5 * rng.normal(size=n), rng.normal(size=n)]))
        j_sou = jacobian(lambda z: sou("exp", z[:n], z[n:], algebra), z)
        j_tar = jacobian(lambda z: tar("exp", z[:n], z[n:], algebra), z)
        beta = sou("exp", z[:n], z[n:], algebra).numpy()
        alpha = tar("exp", z[:n], z[n:], algebra).numpy()
        pi_sou = (j_sou @ canonical @ j_sou.T).numpy()
        pi_tar = (j_tar @ canonical @ j_tar.T).numpy()
        np.testing.assert_allclose(pi_sou, -system.poisson_tensor(beta), atol=1e-12)
        np.testing.assert_allclose(pi_tar, system.poisson_tensor(alpha), atol=1e-12)
        np.testing.assert_allclose((j_sou @ canonical @ j_tar.T).numpy(), 0.0, atol=1e-12)


def _bisection(
    system: LiePoissonSystem, mu: np.ndarray, t: float, *, swap: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """The K = 1 bisection map, S = −tH: x = −t∇H(p), tar(x, p) = μ (Newton with autograd
    Jacobians), μ' = sou(x, p); sou and tar trade places with ``swap``. Returns (μ', DΦ(μ))."""
    first, second = (sou, tar) if swap else (tar, sou)
    algebra = system.algebra

    def x_of(p: torch.Tensor) -> torch.Tensor:
        return -t * system.grad_hamiltonian(p)

    def solve(p: torch.Tensor) -> torch.Tensor:
        return first("exp", x_of(p), p, algebra)

    def step(p: torch.Tensor) -> torch.Tensor:
        return second("exp", x_of(p), p, algebra)

    target = torch.tensor(mu)
    p = target.clone()
    for _ in range(30):
        residual = solve(p) - target
        if residual.abs().max() < 1e-15:
            break
        p = p - torch.linalg.solve(jacobian(solve, p), residual)
    assert (solve(p) - target).abs().max() < 1e-13
    # Implicit function theorem: DΦ = ∂step/∂p · (∂solve/∂p)⁻¹.
    derivative = jacobian(step, p) @ torch.linalg.inv(jacobian(solve, p))
    return step(p).numpy(), derivative.numpy()


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_bisection_map_follows_the_flow_keeps_casimirs_and_is_poisson(name: str) -> None:
    system = SYSTEMS[name]
    rng = np.random.default_rng(6)
    for mu in rng.normal(size=(3, system.dim)):
        errors, swapped = [], []
        for t in (0.02, 0.01):
            exact = reference_solution(system, mu, [t])[0]
            new, derivative = _bisection(system, mu, t)
            errors.append(np.abs(new - exact).max())
            swapped.append(np.abs(_bisection(system, mu, t, swap=True)[0] - exact).max())
            np.testing.assert_allclose(system.casimirs(new), system.casimirs(mu), atol=1e-13)
            # Poisson: DΦ Π(μ) DΦᵀ = Π(Φ(μ)).
            pushed = derivative @ system.poisson_tensor(mu) @ derivative.T
            np.testing.assert_allclose(pushed, system.poisson_tensor(new), atol=1e-12)
        # Local error O(t³) (S₂ = 0: the map is symmetric, of global order 2, as DESIGN §1b
        # found); swapped, the map runs time backwards, so the error is O(t) and never small.
        local_order = np.log2(errors[0] / errors[1])
        assert 2.7 < local_order < 3.4, (errors, local_order)
        assert np.log2(swapped[0] / swapped[1]) < 1.2
        assert swapped[1] > 1e3 * errors[1]


def test_bisection_global_order_two_on_the_heavy_top() -> None:
    system = SYSTEMS["heavy_top"]
    mu0 = np.array([0.3, -0.4, 0.8, 0.2, 0.1, 0.9])
    horizon = 1.0
    exact = reference_solution(system, mu0, [horizon])[0]
    errors = []
    for steps in (8, 16):
        mu = mu0.copy()
        for _ in range(steps):
            mu = _bisection(system, mu, horizon / steps)[0]
        errors.append(np.abs(mu - exact).max())
    order = np.log2(errors[0] / errors[1])
    assert 1.8 < order < 2.2, (errors, order)

"""The derivative methods timed by benches/train_methods.py compute the trainer's ∂S/∂t, ∂S/∂p
(and their parameter derivatives, hence the same loss gradient) as nested autograd does."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from conftest import build_generating

from poisson_rs.generating import GeneratingFunction
from poisson_rs.train import TrainConfig, _loss

# The bench is a script, not part of the package: make its directory importable.
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benches"))
import train_methods as tm

CANDIDATES = [name for name in tm.METHODS if name != "nested"]


def points(n: int = 64, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """n points t ∈ [0, 0.2], |p| ≤ 3.5, with the awkward ones included: t = 0 (0⁰ in t^(m−1))
    and coordinates exactly 0 (0⁰ in the polynomial's closed-form gradient)."""
    gen = torch.Generator().manual_seed(seed)
    t = torch.rand(n, generator=gen, dtype=torch.float64) * 0.2
    p = (torch.rand(n, 3, generator=gen, dtype=torch.float64) * 2 - 1) * 3.5
    t[0] = 0.0
    p[1] = torch.tensor([3.0, 2.0, 0.0], dtype=torch.float64)
    p[2] = torch.tensor([0.0, 0.0, -1.5], dtype=torch.float64)
    return t, p


def model(
    seed: int, inputs: str, chart: str, widths: tuple[int, ...] = (7, 5, 6)
) -> GeneratingFunction:
    return build_generating(
        seed,
        chart=chart,
        inputs=inputs,
        widths=widths,
        taylor_order=3,
        mlp_power=2,
        output_scale=0.5,
    )


@pytest.mark.parametrize("chart", ["cayley", "exp"])
@pytest.mark.parametrize("inputs", ["t,p", "homogeneous"])
@pytest.mark.parametrize("name", CANDIDATES)
def test_method_matches_nested_autograd(name: str, inputs: str, chart: str) -> None:
    s_fn = model(3, inputs, chart)
    t, p = points()
    errs = tm.check_method(tm.METHODS[name], s_fn, t, p)  # asserts too; restated for the report
    assert errs["dS/dt"] <= 1e-12 and errs["dS/dp"] <= 1e-12, errs
    assert errs["d2S/dtheta"] <= 1e-10, errs


@pytest.mark.parametrize("name", CANDIDATES)
@pytest.mark.parametrize("mlp_power", [1, 3])
def test_method_without_polynomial_and_other_powers(name: str, mlp_power: int) -> None:
    """S = t^m·MLP alone (the paper's ansatz), and m = 1 where t^(m−1) = t⁰."""
    s_fn = build_generating(5, inputs="t,p", widths=(8,), taylor_order=1, mlp_power=mlp_power)
    s_fn.powers, s_fn.coeffs = s_fn.powers[:0], s_fn.coeffs[:0]
    tm.check_method(tm.METHODS[name], s_fn, *points(seed=1))


@pytest.mark.parametrize("name", CANDIDATES)
def test_polynomial_only(name: str) -> None:
    """No MLP: the closed-form polynomial gradient alone."""
    s_fn = build_generating(7, chart="exp", widths=(), taylor_order=3)
    tm.check_method(tm.METHODS[name], s_fn, *points(seed=2))


@pytest.mark.parametrize("inputs", ["t,p", "homogeneous"])
def test_bench_loss_is_the_trainers(inputs: str) -> None:
    """The bench times ``residual_loss``; it must be ``train._loss`` for every method."""
    s_fn = model(11, inputs, "cayley")
    t, p = points(seed=3)
    p = p + torch.sign(p) * 0.1  # the homogeneous loss divides by |p|²
    cfg = TrainConfig(inputs=inputs)
    ref = _loss(s_fn, cfg, t, p, create_graph=False)
    for method in tm.METHODS.values():
        got = tm.hj_loss(s_fn, cfg.inertia, method)(t, p)
        torch.testing.assert_close(got, ref, rtol=1e-12, atol=0.0)


def test_check_method_rejects_a_wrong_method() -> None:
    """The gate before timing works: a method off by a relative 1e-9 is refused."""
    s_fn = model(13, "homogeneous", "cayley")

    def off(s_fn: GeneratingFunction, t: torch.Tensor, p: torch.Tensor) -> tuple[torch.Tensor, ...]:
        st, sp = tm.hand_forward(s_fn, t, p)
        return st * (1 + 1e-9), sp

    with pytest.raises(AssertionError, match="disagrees"):
        tm.check_method(off, s_fn, *points(seed=4))

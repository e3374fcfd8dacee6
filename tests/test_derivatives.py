"""``generating.hj_derivatives``, the trainer's ∂S/∂t and ∂S/∂p: the hand-written reverse pass
equals nested autograd (values, and the HJ loss's gradient in the weights) for every kind of
generating function, and the trainer's ``derivatives`` option picks it and refuses bad names."""

from __future__ import annotations

from typing import Any

import pytest
import torch
from conftest import build_generating

from poisson_rs.generating import GeneratingFunction, hj_derivatives
from poisson_rs.train import PRESETS, TrainConfig, _loss, train


def points(
    n: int = 64, seed: int = 0, *, zero_row: bool = True
) -> tuple[torch.Tensor, torch.Tensor]:
    """n points t ∈ [0, 0.2] and p ∈ [−3.5, 3.5]³, float64, with the awkward ones included: t = 0
    (0⁰ in t^(m−1)), a coordinate exactly 0 (0⁰ in the polynomial's gradient) and, if
    ``zero_row``, p = 0 (where the homogeneous ansatz clamps |p|)."""
    gen = torch.Generator().manual_seed(seed)
    t = torch.rand(n, generator=gen, dtype=torch.float64) * 0.2
    p = (torch.rand(n, 3, generator=gen, dtype=torch.float64) * 2 - 1) * 3.5
    t[0] = 0.0
    p[1] = torch.tensor([3.0, 2.0, 0.0], dtype=torch.float64)
    if zero_row:
        p[2] = 0.0
    return t, p


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    """max |a − b| / max |b|."""
    a, b = a.detach(), b.detach()
    return float((a - b).abs().max() / b.abs().max().clamp_min(1e-300))


# (chart, inputs, hidden widths, Taylor order K, m): every branch of GeneratingFunction.forward.
VARIANTS = [
    ("cayley", "homogeneous", (8, 8), 3, 5),  # the default model's ansatz
    ("cayley", "t,p", (7, 5, 6), 3, 2),
    ("exp", "homogeneous", (6,), 1, 3),
    ("exp", "t,p", (5, 4), 2, 1),
    ("cayley", "t,p", (9, 4), 0, 1),  # the paper's S = t·MLP, no polynomial
    ("exp", "homogeneous", (4, 4), 0, 2),
    ("cayley", "t,p", (), 3, 1),  # no MLP: the polynomial alone
    ("exp", "homogeneous", (), 5, 1),
]
IDS = [f"{c}-{i}-{'x'.join(map(str, w)) or 'poly'}-K{k}-m{m}" for c, i, w, k, m in VARIANTS]


def variant(seed: int, chart: str, inputs: str, widths: tuple[int, ...], k: int, m: int):
    """A seeded random S of that kind (random biases and input scales, see ``build_generating``);
    K = 0 drops the polynomial part entirely."""
    s_fn = build_generating(
        seed,
        chart=chart,
        inputs=inputs,
        widths=widths,
        taylor_order=max(k, 1),
        mlp_power=m,
        output_scale=0.5,
    )
    if k == 0:
        s_fn.powers, s_fn.coeffs = s_fn.powers[:0], s_fn.coeffs[:0]
    return s_fn


@pytest.mark.parametrize(("chart", "inputs", "widths", "k", "m"), VARIANTS, ids=IDS)
def test_reverse_equals_nested_autograd(
    chart: str, inputs: str, widths: tuple[int, ...], k: int, m: int
) -> None:
    s_fn = variant(3, chart, inputs, widths, k, m)
    t, p = points()
    st0, sp0 = hj_derivatives(s_fn, t, p, method="autograd")
    st, sp = hj_derivatives(s_fn, t, p)
    assert st.shape == (64,) and sp.shape == (64, 3)
    assert torch.isfinite(st).all() and torch.isfinite(sp).all()
    assert rel_err(st, st0) <= 1e-12 and rel_err(sp, sp0) <= 1e-12
    # Row-wise as well, so that the small values at t = 0 and p = 0 are held to the same standard.
    atol = 1e-14 * float(st0.detach().abs().max())
    torch.testing.assert_close(st, st0, rtol=1e-12, atol=atol)
    torch.testing.assert_close(sp, sp0, rtol=1e-12, atol=atol)
    if widths:
        # Their derivatives in the weights too: a random functional Σ w·(∂S/∂t, ∂S/∂p) reaches
        # every mixed derivative ∂²S/∂θ∂(t, p) that the loss gradient is built from.
        w = torch.rand(64, 4, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
        params = list(s_fn.mlp.parameters())
        g0 = torch.autograd.grad((w[:, 0] * st0).sum() + (w[:, 1:] * sp0).sum(), params)
        g = torch.autograd.grad((w[:, 0] * st).sum() + (w[:, 1:] * sp).sum(), params)
        assert max(rel_err(a, b) for a, b in zip(g, g0, strict=True)) <= 1e-10


@pytest.mark.parametrize(("chart", "inputs", "widths", "k", "m"), VARIANTS[:6], ids=IDS[:6])
def test_hj_loss_gradients_agree(
    chart: str, inputs: str, widths: tuple[int, ...], k: int, m: int
) -> None:
    """The trainer's loss and its gradient in the weights, by either method. (No p = 0 here: the
    homogeneous loss divides by |p|².)"""
    s_fn = variant(5, chart, inputs, widths, k, m)
    t, p = points(seed=2, zero_row=False)
    params = list(s_fn.mlp.parameters())
    loss = {}
    grads = {}
    for method in ("autograd", "reverse"):
        cfg = TrainConfig(chart=chart, inputs=inputs, derivatives=method)
        loss[method] = _loss(s_fn, cfg, t, p, create_graph=True)
        grads[method] = torch.autograd.grad(loss[method], params)
    assert rel_err(loss["reverse"], loss["autograd"]) <= 1e-12
    for a, b in zip(grads["reverse"], grads["autograd"], strict=True):
        assert rel_err(a, b) <= 1e-10


def test_create_graph_false_returns_plain_tensors() -> None:
    """Like ``autograd.grad(create_graph=False)``: values without a graph, also for the validation
    loss (a no-grad evaluation must not build one)."""
    s_fn = variant(7, "cayley", "homogeneous", (8, 8), 3, 5)
    t, p = points(seed=3)
    for method in ("autograd", "reverse"):
        st, sp = hj_derivatives(s_fn, t, p, method=method, create_graph=False)
        assert not st.requires_grad and not sp.requires_grad
        st_g, sp_g = hj_derivatives(s_fn, t, p, method=method)
        assert st_g.requires_grad and sp_g.requires_grad
        torch.testing.assert_close(st, st_g.detach(), rtol=0, atol=0)


def test_float32_follows_float64() -> None:
    """The paper preset trains in float32: the reverse pass stays within float32 rounding."""
    s_fn = variant(9, "cayley", "t,p", (16, 16), 0, 1)
    t, p = points(seed=4)
    ref = hj_derivatives(s_fn, t, p, method="autograd")
    s32: GeneratingFunction = s_fn.float()  # type: ignore[assignment]
    got = hj_derivatives(s32, t.float(), p.float())
    assert got[0].dtype == torch.float32
    for a, b in zip(got, ref, strict=True):
        assert rel_err(a.double(), b) <= 1e-5


def test_training_with_either_method_starts_alike() -> None:
    """Same seed, same points: the first losses agree to rounding, and both runs train."""
    base: dict[str, Any] = {"widths": (8,), "batch": 256, "iterations": 20, "lr": 1e-2, "seed": 7}
    runs = {
        m: train(TrainConfig(**base, derivatives=m), progress=False, log_every=1)
        for m in ("autograd", "reverse")
    }
    first = [r.losses[0] for r in runs.values()]
    assert first[0] == pytest.approx(first[1], rel=1e-12)
    for r in runs.values():
        assert r.losses[-1] < r.losses[0]
    assert runs["reverse"].config.derivatives == "reverse"


@pytest.mark.parametrize("bad", ["forward", "Reverse", "", None, 1])
def test_bad_method_names_are_refused(bad: Any) -> None:
    with pytest.raises(ValueError, match="derivatives must be one of"):
        TrainConfig(derivatives=bad).validate()
    with pytest.raises(ValueError, match="derivatives must be one of"):
        train(TrainConfig(derivatives=bad, iterations=1), progress=False)
    s_fn = variant(11, "cayley", "t,p", (4,), 1, 1)
    with pytest.raises(ValueError, match="derivatives must be one of"):
        hj_derivatives(s_fn, *points(4), method=bad)


def test_default_is_the_reverse_pass_and_the_paper_preset_nested_autograd() -> None:
    """The paper preset keeps nested autograd, the faster on the GPU it is trained on."""
    assert TrainConfig().derivatives == "reverse"
    assert TrainConfig(**PRESETS["paper"]).derivatives == "autograd"

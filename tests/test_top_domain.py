"""The "top" training domain of se(3)* (M in a cube, |Γ| in a thin shell): sampling, the
configuration's checks, and the out-of-domain count of rollouts."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import poisson_rs as pr
from poisson_rs.integrators import _check_domain, count_out_of_domain
from poisson_rs.train import TrainConfig, _loss, _sample_domain, build_model, hj_residual

TOP = pr.HeavyTop()


def _so3_squared() -> pr.LiePoissonSystem:
    """so(3) ⊕ so(3) with H = |μ|²/2: a 6-dimensional Lie–Poisson system that is not se(3)*."""
    c = np.zeros((6, 6, 6))
    so3 = pr.LieAlgebra.so3().c
    c[:3, :3, :3] = so3
    c[3:, 3:, 3:] = so3
    h = pr.Polynomial({tuple(2 * int(i == j) for j in range(6)): 0.5 for i in range(6)})
    return pr.LiePoissonSystem(pr.LieAlgebra(c), h)


SO3_SQUARED = _so3_squared()
DOMAIN = {"kind": "top", "half_width": 2.0, "r_min": 0.9, "r_max": 1.1}


def top_config(**changes: object) -> TrainConfig:
    base: dict[str, object] = {
        "system": TOP.to_dict(),
        "chart": "exp",
        "inputs": "t,p",
        "domain": "top",
        "half_width": 2.0,
        "r_min": 0.9,
        "r_max": 1.1,
        "h_max": 0.5,
    }
    base.update(changes)
    return TrainConfig(**base)  # type: ignore[arg-type]


def test_top_sampling_fills_the_cube_and_the_shell() -> None:
    cfg = top_config()
    cfg.validate()
    t, p = _sample_domain(cfg, 20000, torch.Generator().manual_seed(3), torch.float64, "cpu")
    m, g = p[:, :3].numpy(), np.linalg.norm(p[:, 3:].numpy(), axis=1)
    assert ((0 <= t) & (t <= 0.5)).all()
    assert np.abs(m).max() <= 2.0 and np.abs(m).max() > 1.99
    assert g.min() >= 0.9 and g.max() <= 1.1
    # Uniform in |Γ| over [0.9, 1.1] and over the directions: both halves of each range get
    # about half of the points (20000 points: the binomial σ is 0.35 %).
    assert abs(np.mean(g < 1.0) - 0.5) < 0.02
    assert abs(np.mean(p[:, 5].numpy() > 0) - 0.5) < 0.02
    # The metadata records every bound the out-of-domain count needs.
    assert cfg.domain_dict() == {**DOMAIN, "t_max": 0.5}


def test_top_inputs_are_scaled_by_the_larger_extent() -> None:
    s_fn = build_model(top_config(half_width=3.0, widths=(4,)))
    scale = s_fn.input_scale.tolist()
    assert scale[0] == pytest.approx(2.0)  # t / h_max
    assert scale[1:] == pytest.approx([1 / 3.0] * 6)


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"system": None}, "domain 'top' is"),  # the rigid body: 3 coordinates
        # Six coordinates, but not se(3)*: so(3) ⊕ so(3) has no (M, Γ) to sample.
        ({"system": SO3_SQUARED.to_dict(), "chart": "exp"}, "not on se\\(3\\)"),
        ({"r_min": 1.1, "r_max": 0.9}, "r_min < r_max"),
        ({"half_width": 0.0}, "half_width"),
        ({"domain": "ball"}, "domain must be one of"),
    ],
)
def test_bad_top_domains_are_refused(changes: dict[str, object], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        top_config(**changes).validate()


def test_out_of_domain_counts_m_and_gamma_separately() -> None:
    inside = [1.9, -1.9, 0.0, 0.0, 0.6, 0.8]
    m_out = [2.1, 0.0, 0.0, 0.0, 0.0, 1.0]
    g_in = [0.0, 0.0, 0.0, 0.0, 0.0, 1.09]
    g_out = [0.0, 0.0, 0.0, 0.0, 0.0, 0.89]
    traj = np.array(
        [
            [inside, m_out, g_out],
            [inside, g_in, inside],
            [g_out, g_out, [np.nan] * 6],
        ]
    )
    np.testing.assert_array_equal(count_out_of_domain(DOMAIN, traj), [2, 0, 2])
    assert _check_domain(DOMAIN) == DOMAIN
    for bad in ({**DOMAIN, "r_min": 1.2}, {**DOMAIN, "half_width": -1.0}, {"kind": "top"}):
        with pytest.raises(ValueError, match="metadata 'domain'"):
            _check_domain(bad)


def test_weight_power_divides_each_residual() -> None:
    """The weighted loss against the unweighted residuals of hj_residual, weighted by hand."""
    cfg = top_config(weight_power=3.0, widths=(4,), init="xavier")
    s_fn = build_model(cfg)
    t, p = _sample_domain(cfg, 64, torch.Generator().manual_seed(1), torch.float64, "cpu")
    r = hj_residual(s_fn, TOP, t, p, create_graph=False)
    by_hand = (r / (1.0 + (p * p).sum(1)) ** 1.5).pow(2).mean()
    got = _loss(s_fn, cfg, t, p, create_graph=False)
    torch.testing.assert_close(got, by_hand, rtol=1e-12, atol=0.0)
    plain = _loss(s_fn, top_config(widths=(4,), init="xavier"), t, p, create_graph=False)
    torch.testing.assert_close(plain, r.pow(2).mean(), rtol=1e-12, atol=0.0)


@pytest.mark.parametrize("q", [-1.0, float("inf"), float("nan"), 17.0])
def test_bad_weight_powers_are_refused(q: float) -> None:
    with pytest.raises(ValueError, match="weight_power"):
        top_config(weight_power=q).validate()

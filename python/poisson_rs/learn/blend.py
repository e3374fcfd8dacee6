"""Mode "hj+data": H known or partly known, the paper's blended loss (Conclusions, "Combination with
Data"): loss = loss_HJ + λ·loss_data.

Two corrections are learned:

- ``correction="polynomial"``: H = H_known + H_θ with H_θ a polynomial
  (:func:`poisson_rs.learn.hamiltonian.fit_polynomial` with ``known=``). S is the Taylor-HJ series
  of H, so loss_HJ vanishes to order K by construction and only loss_data is minimised; the
  result integrates at any h.
- ``correction="network"``: H is taken as known; S = Σ_{k≤K} t^k S_k(H_known) + t^m·MLP(t, p)
  (m = K + 1 by default), trained on mean((HJ residual/|p|²)²) at sampled (t ∈ [0, h], p on the
  data) plus λ/h² × the mean squared relative one-step error on the data pairs
  (:func:`poisson_rs.train.data_loss`, implicit-function gradients). λ trades the two: H_known's
  equation against what the data say. The map steps at the data's h (or below).

Either way S gives a Poisson map, so every Casimir is kept to round-off.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ..generating import GeneratingFunction
from ..structures.lie_poisson import LiePoissonSystem
from ..taylor import system_taylor_terms
from ..train import data_loss, hj_residual
from .data import TrajectoryData

__all__ = ["blended_loss", "fit_blended_map"]


def build_blended_map(
    known: LiePoissonSystem,
    *,
    order: int,
    h: float,
    scale: float,
    widths: tuple[int, ...] = (16, 16),
    mlp_power: int | None = None,
    seed: int = 0,
) -> GeneratingFunction:
    """S = Taylor-HJ of ``known`` to order K + t^m·s·MLP(t/h, p/scale), the MLP's last layer at
    zero (training starts from the series), s = scale² (an energy per unit time^(m−1))."""
    torch.manual_seed(seed)
    n = known.dim
    powers, coeffs = system_taylor_terms(known, order, "exp")
    s_fn = GeneratingFunction(
        widths,
        mlp_power=order + 1 if mlp_power is None else mlp_power,
        powers=powers,
        coeffs=coeffs,
        chart="exp",
        algebra=known.algebra,
        input_scale=(1.0 / h,) + (1.0 / scale,) * n,
        output_scale=scale * scale,
    )
    last = s_fn.linears[-1]
    torch.nn.init.zeros_(last.weight)
    torch.nn.init.zeros_(last.bias)
    return s_fn


def blended_loss(
    s_fn: GeneratingFunction,
    known: LiePoissonSystem,
    t: torch.Tensor,
    p: torch.Tensor,
    mu_k: torch.Tensor,
    mu_k1: torch.Tensor,
    h: float,
    lam: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(total, loss_HJ, loss_data): loss_HJ = mean((r/|p|²)²), r the HJ residual of ``known``
    at (t (B,), p (B, n)); loss_data = :func:`poisson_rs.train.data_loss` on the pairs (m, n);
    total = loss_HJ + λ·loss_data/h² (both then measure a relative error of the vector field)."""
    r = hj_residual(s_fn, known, t, p, create_graph=True)
    l_hj = (r / (p * p).sum(1).clamp_min(1e-300)).pow(2).mean()
    l_data = data_loss(s_fn, mu_k, mu_k1, h)
    return l_hj + lam * l_data / (h * h), l_hj, l_data


def fit_blended_map(
    data: TrajectoryData,
    known: LiePoissonSystem,
    *,
    order: int = 3,
    lam: float = 1.0,
    widths: tuple[int, ...] = (16, 16),
    mlp_power: int | None = None,
    adam_steps: int = 150,
    lbfgs_steps: int = 40,
    lr: float = 3e-3,
    n_hj: int = 256,
    seed: int = 0,
    verbose: bool = False,
) -> tuple[GeneratingFunction, list[float]]:
    """Trains the network correction on ``data.train``; returns (S, [loss_HJ, loss_data] at the
    end). ``lam`` must be ≥ 0 (0: the HJ equation alone)."""
    s_fn = build_blended_map(
        known,
        order=order,
        h=data.h,
        scale=data.scale,
        widths=widths,
        mlp_power=mlp_power,
        seed=seed,
    )
    gen = torch.Generator().manual_seed(seed)
    mu_k, mu_k1 = (torch.as_tensor(a) for a in data.pairs("train"))
    pool = torch.as_tensor(np.concatenate(data.train))
    idx = torch.randint(len(pool), (n_hj,), generator=gen)
    p = pool[idx] * (1.0 + 0.05 * torch.randn(n_hj, 1, generator=gen, dtype=torch.float64))
    t = data.h * torch.rand(n_hj, generator=gen, dtype=torch.float64)

    def total() -> torch.Tensor:
        return blended_loss(s_fn, known, t, p, mu_k, mu_k1, data.h, lam)[0]

    opt = torch.optim.Adam(s_fn.mlp.parameters(), lr=lr)
    for i in range(adam_steps):
        opt.zero_grad()
        loss = total()
        loss.backward()
        opt.step()
        if verbose and i % 50 == 0:
            print(f"  hj+data Adam {i}: {loss.item():.3e}")
    if lbfgs_steps:
        lbfgs = torch.optim.LBFGS(
            s_fn.mlp.parameters(), lr=1.0, max_iter=lbfgs_steps, line_search_fn="strong_wolfe"
        )

        def closure() -> Any:
            lbfgs.zero_grad()
            loss = total()
            loss.backward()
            return loss

        lbfgs.step(closure)
    _, l_hj, l_data = blended_loss(s_fn, known, t, p, mu_k, mu_k1, data.h, lam)
    return s_fn, [float(l_hj.detach()), float(l_data.detach())]

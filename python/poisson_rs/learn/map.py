"""Mode "map": the generating function S_θ(h, p) of the time-h map, learned from pairs alone.

S_θ(t, p) = −t·H₀(p) + t·s·MLP(t, p/scale): H₀ is the quadratic whose order-1 map S = −t·H₀
fits the pairs best (a base that already steps to O(t³)), the
MLP a small tanh network (its last layer starts at zero, so training starts from H₀'s map). The
loss is the mean squared relative one-step error of the bisection map through the implicit step,
with gradients by the implicit function theorem (``train.data_loss``). Any S gives a Poisson map,
so every Casimir is kept to round-off whatever the network learned. The map is trained and valid
at the data's h only.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ..generating import GeneratingFunction
from ..structures.lie_poisson import LieAlgebra
from ..train import data_loss
from .data import TrajectoryData
from .hamiltonian import fit_polynomial, vector_field_design, velocities
from .optimize import levenberg_marquardt
from .series import monomials

__all__ = ["fit_map", "quadratic_guess"]


def quadratic_guess(data: TrajectoryData, algebra: LieAlgebra) -> dict[tuple[int, ...], float]:
    """Quadratic H₀ (no constant; linear terms included) by least squares on finite-difference
    velocities; minimal-norm, so Casimir directions get no weight."""
    family = monomials(algebra.dim, 2, min_degree=1)
    x, v = velocities(data.train, data.h)
    a = vector_field_design(algebra, family, x).reshape(-1, len(family))
    theta, *_ = np.linalg.lstsq(a, v.reshape(-1), rcond=1e-10)
    return {e: float(t) for e, t in zip(family, theta, strict=True)}


def build_map(
    h0: dict[tuple[int, ...], float],
    algebra: LieAlgebra,
    *,
    widths: tuple[int, ...] = (16, 16),
    scale: float = 1.0,
    h: float = 0.1,
    seed: int = 0,
) -> GeneratingFunction:
    """S = −t·H₀ + t·s·MLP(t/h, p/scale), with s = h·scale² (the size of one step's S)."""
    torch.manual_seed(seed)
    n = algebra.dim
    powers = np.array([(1, *e) for e in h0], dtype=np.int64).reshape(-1, 1 + n)
    coeffs = -np.array(list(h0.values()), dtype=np.float64)
    s_fn = GeneratingFunction(
        widths,
        mlp_power=1,
        powers=powers,
        coeffs=coeffs,
        chart="exp",
        algebra=algebra,
        input_scale=(1.0 / h,) + (1.0 / scale,) * n,
        output_scale=h * scale * scale,
    )
    last = s_fn.linears[-1]
    torch.nn.init.zeros_(last.weight)
    torch.nn.init.zeros_(last.bias)
    return s_fn


def fit_map(
    data: TrajectoryData,
    algebra: LieAlgebra,
    *,
    widths: tuple[int, ...] = (16, 16),
    adam_steps: int = 300,
    lbfgs_steps: int = 60,
    lr: float = 3e-3,
    seed: int = 0,
    base: bool = True,
    verbose: bool = False,
) -> tuple[GeneratingFunction, int]:
    """Trains the map's S on ``data.train`` pairs; returns (S, trainable parameters)."""
    torch.manual_seed(seed)
    if base:
        # The best quadratic S = −t·H₀ (Taylor-HJ of order 1) through the step map itself:
        # a few LM iterations, and the network only has to learn the O(t³) rest.
        fit = fit_polynomial(
            data, algebra, 2, order=1, horizon=1, max_iter=8, sparse=False, shooting=False
        )
        h0 = {e: float(t) for e, t in zip(fit.family, fit.theta, strict=True)}
    else:
        h0 = {(0,) * algebra.dim: 0.0}
    h0 = {e: c for e, c in h0.items() if sum(e) > 0} or {
        tuple(1 if i == 0 else 0 for i in range(algebra.dim)): 0.0
    }
    s_fn = build_map(h0, algebra, widths=widths, scale=data.scale, h=data.h, seed=seed)
    mu_k, mu_k1 = (torch.as_tensor(a) for a in data.pairs("train"))
    opt = torch.optim.Adam(s_fn.mlp.parameters(), lr=lr)
    for i in range(adam_steps):
        opt.zero_grad()
        loss = data_loss(s_fn, mu_k, mu_k1, data.h)
        loss.backward()
        opt.step()
        if verbose and i % 50 == 0:
            print(f"  map Adam {i}: {loss.item():.3e}")
    if lbfgs_steps:
        lbfgs = torch.optim.LBFGS(
            s_fn.mlp.parameters(), lr=1.0, max_iter=lbfgs_steps, line_search_fn="strong_wolfe"
        )

        def closure() -> Any:
            lbfgs.zero_grad()
            loss = data_loss(s_fn, mu_k, mu_k1, data.h)
            loss.backward()
            return loss

        lbfgs.step(closure)
        if verbose:
            print(f"  map LBFGS: {float(data_loss(s_fn, mu_k, mu_k1, data.h)):.3e}")
    return s_fn, s_fn.n_parameters()


def fit_polynomial_map(
    data: TrajectoryData,
    algebra: LieAlgebra,
    *,
    degree: int = 6,
    max_iter: int = 30,
    verbose: bool = False,
) -> tuple[np.ndarray, Any, int]:
    """The time-h map's S(h, ·) as a polynomial in p of ``degree`` (no constant), H never formed:
    its coefficients fitted by Levenberg–Marquardt on the one-step residuals of the bisection map
    (derivatives by the implicit function theorem, :func:`poisson_rs.learn.step.bisection_step`),
    from the quadratic whose order-1 map fits best. Polynomial features in place of a network:
    for a polynomial H every Taylor term of S is a polynomial in p, so a few dozen coefficients
    do what hundreds of tanh weights only approximate. Returns (S(h, ·)'s coefficients over the
    basis, the basis, the number of non-zero coefficients)."""
    from .series import basis as make_basis
    from .step import bisection_step

    n = algebra.dim
    b = make_basis(n, degree)
    fit = fit_polynomial(
        data, algebra, 2, order=1, horizon=1, max_iter=8, sparse=False, shooting=False
    )
    s = np.zeros(b.size)
    for e, t in zip(fit.family, fit.theta, strict=True):
        s[b.index[e]] = -data.h * t
    free = np.array([sum(e) > 0 for e in b.exponents])
    mu_k, mu_k1 = data.pairs("train")
    start = torch.as_tensor(mu_k)
    scale = np.linalg.norm(mu_k, axis=1, keepdims=True)

    def evaluate(coeffs: np.ndarray, jacobian: bool):
        try:
            step = bisection_step(
                b, algebra.c, torch.as_tensor(coeffs), start, derivatives=jacobian
            )
        except FloatingPointError:  # a trial step far outside the chart: rejected
            return np.full(mu_k.size, np.inf), None
        r = ((step.out.numpy() - mu_k1) / scale).reshape(-1)
        j = None
        if jacobian:
            assert step.d_coeffs is not None
            j = (step.d_coeffs.numpy()[:, :, free] / scale[..., None]).reshape(len(r), -1)
        return r, j

    def evaluate_free(x: np.ndarray, jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
        trial = s.copy()
        trial[free] = x
        return evaluate(trial, jacobian)

    lm = levenberg_marquardt(
        evaluate_free,
        s[free],
        max_iter=max_iter,
        lam=1e-3,
        rel_tol=1e-4,
        cost_floor=1e-30,
        floor=1e-30,
        label="map-poly LM",
        verbose=verbose,
    )
    s = s.copy()
    s[free] = lm.x
    return s, b, int(np.count_nonzero(s))

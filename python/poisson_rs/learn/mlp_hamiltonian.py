"""A Hamiltonian with a network in it, fitted through the implicit midpoint rule, for ``pr.learn``
on a structure where neither a polynomial nor a term library explains the data.

H_θ(x) = Σ_m c_m x^{e_m} + Σ_j a_j tanh(w_j · (x − x_c)/s + b_j): the monomials of degree 1 …
``degree`` (cubic by default: a few tanh units alone represent a cubic H poorly) and one hidden
layer of ``width`` units on inputs centred and scaled by the training data (no constant: it is
gauge). c starts at the least-squares fit of the polynomial alone; all of θ is then fitted
jointly. The integrator is
the implicit midpoint rule on the structure's field, x_{k+1} = x_k + h π(x̄)∇H_θ(x̄) with
x̄ = (x_k + x_{k+1})/2. On records the midpoint x̄ is known, so the rule's defect on the data,

    d_k(θ) = (x_{k+1} − x_k)/h − π(x̄_k) ∇H_θ(x̄_k),

is explicit in θ: fitting it is fitting *through* the integrator (its one-step map reproduces the
records exactly where d = 0), with no Newton solve inside the loss and no implicit-function
gradient needed. π(x̄_k) does not depend on θ and is evaluated once. The loss is the mean of
|d_k|² / |x̄_k|² relative to its start (the one-step relative error of the scoring, divided by
h), minimised by the package's Adam loop and then L-BFGS (:mod:`poisson_rs.fit`).

The fitted H is written as an expression (:mod:`poisson_rs.expressions`: the weights folded with
the input scaling into ``tanh`` of linear forms), so every tool takes it: the kept candidate's
stepper is the structure's implicit midpoint rule on that expression (the one fitted through),
which keeps quadratic Casimirs exactly. Nothing here names a structure.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ..expressions import Expression, ExpressionError, default_names
from ..fit import FitConfig, adam_loop, lbfgs_polish
from ..hamiltonian_family import monomial_exponents, monomial_gradients, polynomial_text
from ..hamiltonian_library import structure_gauge
from ..protocols import NEWTON_MAX_ITER, NEWTON_TOL
from .data import TrajectoryData
from .structure_fit import StructureFit

__all__ = [
    "MLP_DEGREE",
    "MLP_WIDTH",
    "MlpConfig",
    "MlpFamily",
    "fit_mlp_hamiltonian",
    "mlp_expression",
    "mlp_family",
]

#: Hidden units of the network in H that ``pr.learn`` tries.
MLP_WIDTH = 8
#: Degree of the polynomial beside it.
MLP_DEGREE = 3


def mlp_family(structure: Any, top: int, *, seed: int = 0) -> MlpFamily | None:
    """The family ``pr.learn`` tries on ``structure``: the polynomial degree min(MLP_DEGREE,
    ``top``) and MLP_WIDTH units, made smaller (fewer units, then a lower degree) until H with
    every term fits the expression limits (at least 4 units: fewer fit little); None where
    even 4 units of degree 1 do not."""
    for degree in range(min(MLP_DEGREE, top), 0, -1):
        for width in range(MLP_WIDTH, 3, -2):
            family = MlpFamily(structure, width, degree, seed=seed)
            if family.writable():
                return family
    return None


@dataclass
class MlpConfig(FitConfig):
    """The fit's schedule (full batch: every training record each iteration)."""

    seed: int = 0
    iterations: int = 2000
    batch: int = 0
    lr: float = 1e-2
    schedule: str = "cosine"
    dtype: str = "float64"
    lbfgs_iterations: int = 500


def mlp_expression(
    exponents: list[tuple[int, ...]],
    coeffs: np.ndarray,
    weights: np.ndarray,
    biases: np.ndarray,
    out: np.ndarray,
    center: np.ndarray,
    scale: np.ndarray,
) -> str:
    """Σ_m coeffs_m x^{exponents_m} + Σ_j out_j tanh(Σ_i weights[j, i] (x_i − center_i)/scale_i
    + biases_j) as an expression in x1 … xn, the input scaling folded into the weights."""
    names = default_names(weights.shape[1])
    w = weights / scale[None, :]
    b = biases - w @ center
    parts = [polynomial_text(dict(zip(exponents, coeffs, strict=True)), names)] if exponents else []
    for j in range(w.shape[0]):
        linear = " + ".join(
            [f"({float(b[j])!r})", *(f"({float(w[j, i])!r})*{v}" for i, v in enumerate(names))]
        )
        parts.append(f"({float(out[j])!r})*tanh({linear})")
    return " + ".join(parts) or "0"


class MlpFamily:
    """What ``pr.learn`` reports and scores of an MLP H (the interface of its other Hamiltonian
    families, :class:`poisson_rs.hamiltonian_family.MonomialFamily`): ``name``, ``order`` (2,
    the midpoint rule's), ``description``, ``gauge``, ``text(θ)``; ``linear`` False (its
    coefficients are not a linear refit: the network is fitted on the training records only);
    :meth:`fit` runs the fit."""

    linear = False
    order = 2

    def __init__(
        self,
        structure: Any,
        width: int = MLP_WIDTH,
        degree: int = MLP_DEGREE,
        *,
        seed: int = 0,
    ) -> None:
        for name, v, hi in (("width", width, 64), ("degree", degree, 4)):
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= hi:
                raise ValueError(f"{name} must be an integer in 0..={hi}, got {v!r}")
        self.structure = structure
        self.width = width
        self.degree = degree
        self.seed = seed
        self.exponents: list[tuple[int, ...]] = (
            monomial_exponents(int(structure.dim), degree) if degree else []
        )
        self.name = f"poly{degree}+mlp{width}" if degree else f"mlp{width}"
        self.description = (
            f"a polynomial of degree ≤ {degree} plus a tanh network of {width} units, fitted "
            "through the implicit midpoint rule"
        )
        self.gauge = structure_gauge(structure)
        self._text = ""

    def text(self, theta: Any) -> str:
        """H as fitted (the expression the stepper steps)."""
        return self._text

    def __len__(self) -> int:
        return len(self.exponents) + self.width * (int(self.structure.dim) + 2)

    def writable(self) -> bool:
        """Whether H with every term fits the expression limits (tried on distinct negative
        weights, the costliest: a negative constant is a negation more)."""
        n = int(self.structure.dim)
        k = -np.arange(1, len(self) + 1, dtype=np.float64) / 7.0
        m = len(self.exponents)
        text = mlp_expression(
            self.exponents, k[:m], k[m : m + self.width * n].reshape(self.width, n),
            k[m + self.width * n : m + self.width * (n + 1)], k[m + self.width * (n + 1) :],
            np.zeros(n), np.ones(n),
        )  # fmt: skip
        try:
            Expression(text, default_names(n))
        except ExpressionError:
            return False
        return True

    def fit(self, data: TrajectoryData, *, verbose: bool = False) -> StructureFit:
        return fit_mlp_hamiltonian(data, self.structure, family=self, verbose=verbose)


def fit_mlp_hamiltonian(
    data: TrajectoryData,
    structure: Any,
    *,
    family: MlpFamily | None = None,
    config: MlpConfig | None = None,
    verbose: bool = False,
) -> StructureFit:
    """Fits the MLP H of ``family`` (default :data:`MLP_WIDTH` units) to ``data.train`` through
    the implicit midpoint rule on ``structure``'s bracket (see the module docstring). Returns a
    :class:`~poisson_rs.learn.structure_fit.StructureFit` whose ``stepper`` is that rule on the
    fitted expression and whose ``theta`` holds the network's parameters."""
    from ..integrators import classical
    from ..structures.expression_system import with_hamiltonian

    t0 = time.perf_counter()
    fam = family if family is not None else MlpFamily(structure)
    cfg = config if config is not None else MlpConfig(seed=fam.seed)
    x0 = np.concatenate([t[:-1] for t in data.train])
    x1 = np.concatenate([t[1:] for t in data.train])
    mid = 0.5 * (x0 + x1)
    vel = (x1 - x0) / data.h
    pi = np.asarray(structure.bivector(mid), dtype=np.float64)
    center = mid.mean(0)
    scale = mid.std(0)
    scale[scale < 1e-12] = 1.0
    weight = 1.0 / np.maximum(np.linalg.norm(mid, axis=1), 1e-300) ** 2
    n, width = data.dim, fam.width
    # The polynomial part's field columns π(x̄)∇x^{e_m}, and its least-squares start.
    cols = np.einsum("kij,kjm->kim", pi, monomial_gradients(mid, fam.exponents))
    sw = np.sqrt(weight)[:, None]
    c0 = (
        np.linalg.lstsq((cols * sw[:, :, None]).reshape(-1, cols.shape[2]),
                        (vel * sw).ravel(), rcond=None)[0]
        if fam.exponents else np.zeros(0)
    )  # fmt: skip
    gen = torch.Generator().manual_seed(cfg.seed)
    c = torch.nn.Parameter(torch.tensor(c0))
    w = torch.nn.Parameter(torch.randn(width, n, generator=gen, dtype=torch.float64))
    b = torch.nn.Parameter(0.5 * torch.randn(width, generator=gen, dtype=torch.float64))
    a = torch.nn.Parameter(0.1 * torch.randn(width, generator=gen, dtype=torch.float64))
    params = [c, w, b, a]
    xs = torch.tensor((mid - center) / scale)
    inv_scale = torch.tensor(1.0 / scale)
    pi_t, vel_t, w_t = torch.tensor(pi), torch.tensor(vel), torch.tensor(weight)
    cols_t = torch.tensor(cols)

    def defect() -> torch.Tensor:
        # ∇ of the network in closed form, Σ_j a_j (1 − tanh²) w_j / s: one pass, no autograd
        # inside the loss.
        pre = xs @ w.T + b
        grad = ((1 - torch.tanh(pre) ** 2) * a) @ w * inv_scale
        d = vel_t - torch.einsum("kij,kj->ki", pi_t, grad) - cols_t @ c
        return ((d**2).sum(1) * w_t).mean()

    start = float(defect().detach())
    start = start if math.isfinite(start) and start > 0 else 1.0

    def objective(i: int) -> tuple[torch.Tensor, torch.Tensor]:
        loss = defect()
        return loss / start, loss

    opt = torch.optim.Adam(params, lr=cfg.lr)
    run = adam_loop(cfg, opt, objective, progress=False)
    history = list(run.losses)
    lbfgs_polish(params, lambda: objective(0), cfg.lbfgs_iterations, start=start)
    history.append(float(defect().detach()))
    coeffs = c.detach().numpy().copy()
    weights = w.detach().numpy().copy()
    biases = b.detach().numpy().copy()
    out = a.detach().numpy().copy()
    text = mlp_expression(fam.exponents, coeffs, weights, biases, out, center, scale)
    fam._text = text
    system = with_hamiltonian(structure, text, name="learned")
    stepper = classical(system, "midpoint", tol=NEWTON_TOL, max_iter=NEWTON_MAX_ITER)
    theta = np.concatenate([coeffs, weights.ravel(), biases, out])
    if verbose:
        print(f"{fam.name}: defect {history[0]:.3e} -> {history[-1]:.3e}")
    return StructureFit(
        family=fam,
        theta=theta,
        system=system,
        stepper=stepper,
        history=history,
        seconds=time.perf_counter() - t0,
    )

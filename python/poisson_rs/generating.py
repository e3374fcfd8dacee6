"""Generating functions S(t, p) = P(t, p) + t^m · N(t, p) in torch, and their bisection step map.

P is a sparse polynomial (exact Taylor terms from :mod:`poisson_rs.taylor`, or −tH); N is a tanh
MLP with inputs (t, p₁, p₂, p₃). S(0, ·) = 0 holds by construction: every term of P carries a
positive power of t, and m ≥ 1.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor, nn

from .groupoid import check_chart, sou, tar

MLP_INPUTS: tuple[str, ...] = ("t,p", "homogeneous")


class GeneratingFunction(nn.Module):
    """S(t, p) = Σ cᵢ t^kᵢ p^αᵢ + t^m · N(t, p), with N one of

    - ``inputs="t,p"`` (the paper's ansatz): N = s_out · MLP(t·s_τ, p·s_p);
    - ``inputs="homogeneous"``: N = |p|^(m+1) · s_out · MLP(|p| t·s_τ, p/|p|). Every quadratic
      Hamiltonian's exact S obeys S(t, λp) = λ S(λt, p); this ansatz obeys it too, so the MLP
      only learns a function of τ = |p| t ∈ [0, τ_max] and of the direction p/|p|.

    Parameters
    ----------
    widths:
        Hidden layer widths of the MLP; empty for a purely polynomial S.
    mlp_power:
        m ≥ 1, the power of t multiplying the MLP.
    powers, coeffs:
        Polynomial part: int array (n, 4) of rows (k, a, b, c) for t^k p₁^a p₂^b p₃^c with k ≥ 1,
        and float array (n,).
    inputs:
        "t,p" or "homogeneous" (see above).
    chart:
        Groupoid chart the function is meant for ("cayley" or "exp"); stored, not used here.
    input_scale:
        (4,) scales applied to (t, p₁, p₂, p₃) before the MLP; folded into the first layer on
        export.
    output_scale:
        Scale of the MLP output; folded into the last layer on export.
    """

    def __init__(
        self,
        widths: Sequence[int] = (32, 32),
        *,
        mlp_power: int = 1,
        powers: np.ndarray | None = None,
        coeffs: np.ndarray | None = None,
        chart: str = "cayley",
        inputs: str = "t,p",
        input_scale: Sequence[float] = (1.0, 1.0, 1.0, 1.0),
        output_scale: float = 1.0,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        self.chart = check_chart(chart)
        if inputs not in MLP_INPUTS:
            raise ValueError(f"inputs must be one of {MLP_INPUTS}, got {inputs!r}")
        self.inputs = inputs
        widths = tuple(int(w) for w in widths)
        if any(w < 1 for w in widths):
            raise ValueError(f"layer widths must be positive integers, got {widths}")
        if widths and int(mlp_power) < 1:
            raise ValueError(f"mlp_power must be >= 1 so that S(0, p) = 0, got {mlp_power}")
        self.widths = widths
        self.mlp_power = int(mlp_power)
        powers_t = torch.as_tensor(
            np.zeros((0, 4), dtype=np.int64) if powers is None else np.asarray(powers, np.int64)
        )
        coeffs_t = torch.as_tensor(
            np.zeros(0) if coeffs is None else np.asarray(coeffs, np.float64), dtype=dtype
        )
        if powers_t.ndim != 2 or powers_t.shape[1] != 4 or coeffs_t.shape != powers_t.shape[:1]:
            raise ValueError(
                f"powers must be (n, 4) and coeffs (n,), got {tuple(powers_t.shape)} and "
                f"{tuple(coeffs_t.shape)}"
            )
        if len(powers_t) and (powers_t[:, 0] < 1).any():
            raise ValueError("every polynomial term needs a positive power of t (S(0, p) = 0)")
        if (powers_t < 0).any():
            raise ValueError("polynomial exponents must be non-negative")
        self.register_buffer("powers", powers_t)
        self.register_buffer("coeffs", coeffs_t)
        self.register_buffer("input_scale", torch.tensor(list(input_scale), dtype=dtype))
        self.register_buffer("output_scale", torch.tensor(float(output_scale), dtype=dtype))
        layers: list[nn.Module] = []
        n_in = 4
        for w in widths:
            layers += [nn.Linear(n_in, w, dtype=dtype), nn.Tanh()]
            n_in = w
        if widths:
            layers.append(nn.Linear(n_in, 1, dtype=dtype))
        self.mlp = nn.Sequential(*layers)
        for m in self.mlp:
            if isinstance(m, nn.Linear):
                nn.init.xavier_uniform_(m.weight)
                nn.init.zeros_(m.bias)

    @property
    def linears(self) -> list[nn.Linear]:
        return [m for m in self.mlp if isinstance(m, nn.Linear)]

    def n_parameters(self) -> int:
        return sum(p.numel() for p in self.mlp.parameters())

    def polynomial(self, t: Tensor, p: Tensor) -> Tensor:
        """P(t, p) for t (B,) and p (B, 3) → (B,)."""
        if len(self.coeffs) == 0:
            return torch.zeros_like(t)
        # Integer powers by repeated products, then gathered: ``p ** k`` with a tensor exponent
        # has NaN second derivatives at p = 0 (0 · 0⁻¹), which would poison the Newton Jacobian
        # at states such as (3, 2, 0).
        top = int(self.powers.max())

        def table(x: Tensor) -> Tensor:
            cols = [torch.ones_like(x)]
            for _ in range(top):
                cols.append(cols[-1] * x)
            return torch.stack(cols, dim=1)  # (B, top + 1)

        k = self.powers
        mono = (
            table(t)[:, k[:, 0]]
            * table(p[:, 0])[:, k[:, 1]]
            * table(p[:, 1])[:, k[:, 2]]
            * table(p[:, 2])[:, k[:, 3]]
        )
        return mono @ self.coeffs

    def forward(self, t: Tensor, p: Tensor) -> Tensor:
        """S(t, p) for t (B,) and p (B, 3) → (B,)."""
        s = self.polynomial(t, p)
        if not self.widths:
            return s
        if self.inputs == "t,p":
            z = torch.cat([t[:, None], p], dim=1) * self.input_scale
            return s + t**self.mlp_power * self.output_scale * self.mlp(z)[:, 0]
        # Clamped so that p = 0 gives finite gradients (the term vanishes there to order m + 1).
        r = (p * p).sum(1).clamp_min(1e-300).sqrt()
        z = torch.cat([(r * t)[:, None], p / r[:, None]], dim=1) * self.input_scale
        n = r ** (self.mlp_power + 1) * self.output_scale * self.mlp(z)[:, 0]
        return s + t**self.mlp_power * n

    def exported_layers(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The MLP's (weight (out, in), bias (out,)) pairs as float64, scales folded in."""
        out = []
        lin = self.linears
        for i, layer in enumerate(lin):
            w = layer.weight.detach().to(torch.float64).cpu().numpy().copy()
            b = layer.bias.detach().to(torch.float64).cpu().numpy().copy()
            if i == 0:
                w = w * self.input_scale.detach().to(torch.float64).cpu().numpy()[None, :]
            if i == len(lin) - 1:
                scale = float(self.output_scale)
                w, b = w * scale, b * scale
            out.append((w, b))
        return out


def derivatives(s_fn: GeneratingFunction, t: Tensor, p: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """S, ∂S/∂p and ∂²S/∂p² by autograd, for t (B,) and p (B, 3): (B,), (B, 3), (B, 3, 3)."""
    p = p.detach().requires_grad_(True)
    with torch.enable_grad():
        s = s_fn(t, p)
        (g,) = torch.autograd.grad(s.sum(), p, create_graph=True)
        rows = [torch.autograd.grad(g[:, i].sum(), p, retain_graph=True)[0] for i in range(3)]
    return s.detach(), g.detach(), torch.stack(rows, dim=1).detach()


def newton_system(
    s_fn: GeneratingFunction, chart: str, t: Tensor, p: Tensor, mu: Tensor
) -> tuple[Tensor, Tensor]:
    """F(p) = tar(∂S/∂p(t, p), p) − μ and its Jacobian dF/dp by autograd through ∂S/∂p (so the
    Hessian of S enters exactly). ``p`` must be a leaf requiring grad; F keeps its graph (to p and
    the weights), the Jacobian is detached. t (B,), p and mu (B, 3) → F (B, 3), J (B, 3, 3)."""
    with torch.enable_grad():
        (x,) = torch.autograd.grad(s_fn(t, p).sum(), p, create_graph=True)
        f = tar(chart, x, p) - mu
        rows = [torch.autograd.grad(f[:, i].sum(), p, retain_graph=True)[0] for i in range(3)]
    return f, torch.stack(rows, dim=1).detach()


def solve_momentum(
    s_fn: GeneratingFunction,
    mu: Tensor,
    h: float,
    *,
    chart: str | None = None,
    tol: float = 1e-12,
    max_iter: int = 50,
) -> tuple[Tensor, Tensor]:
    """Newton for p with tar(∂S/∂p(h, p), p) = μ from p = μ, untracked. Stops per state once the
    update satisfies |δ|∞ ≤ tol·|p|∞ (the Rust core's rule). mu (B, 3) → (p (B, 3) detached,
    converged (B,) bool)."""
    chart = check_chart(chart or s_fn.chart)
    mu = mu.detach()
    t = torch.full((mu.shape[0],), float(h), dtype=mu.dtype, device=mu.device)
    p = mu.clone()
    done = torch.zeros(mu.shape[0], dtype=torch.bool, device=mu.device)
    for _ in range(max_iter):
        f, jac = newton_system(s_fn, chart, t, p.detach().requires_grad_(True), mu)
        delta = torch.linalg.solve(jac, -f.detach()[..., None])[..., 0]
        delta = torch.where(done[:, None], torch.zeros_like(delta), delta)
        p = p + delta
        done = done | (delta.abs().amax(-1) <= tol * p.abs().amax(-1).clamp_min(1e-300))
        if bool(done.all()):
            break
    return p.detach(), done & torch.isfinite(p).all(-1)


def bisection_step(
    s_fn: GeneratingFunction,
    mu: Tensor,
    h: float,
    *,
    chart: str | None = None,
    tol: float = 1e-12,
    max_iter: int = 50,
) -> Tensor:
    """One bisection step μ ↦ sou(∂S/∂p(h, p), p) with tar(∂S/∂p(h, p), p) = μ, in pure torch
    (Newton by :func:`solve_momentum`). States that do not converge within ``max_iter`` come back
    as NaN. mu: (B, 3) float64 → (B, 3).
    """
    chart = check_chart(chart or s_fn.chart)
    p, done = solve_momentum(s_fn, mu, h, chart=chart, tol=tol, max_iter=max_iter)
    t = torch.full((mu.shape[0],), float(h), dtype=mu.dtype, device=mu.device)
    pv = p.requires_grad_(True)
    with torch.enable_grad():
        (x,) = torch.autograd.grad(s_fn(t, pv).sum(), pv)
    out = sou(chart, x, p).detach()
    return torch.where(done[:, None], out, torch.full_like(out, float("nan")))

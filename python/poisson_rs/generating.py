"""Generating functions S(t, p) = P(t, p) + t^m · N(t, p) in torch, and their bisection step map.

P is a sparse polynomial (exact Taylor terms from :mod:`poisson_rs.taylor`, or −tH); N is a tanh
MLP with inputs (t, p₁, …, p_n), p ∈ g* ≅ Rⁿ for a Lie algebra g of dimension n (3 for the rigid
body). S(0, ·) = 0 holds by construction: every term of P carries a positive power of t, and
m ≥ 1.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor, nn

from .realizations.lie_groupoid import check_chart, sou, tar

if TYPE_CHECKING:
    from .structures.lie_poisson import LieAlgebra

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
        Polynomial part: int array (m, 1 + n) of rows (k, e₁, …, e_n) for t^k p₁^e₁ ⋯ p_n^e_n
        with k ≥ 1, and float array (m,).
    inputs:
        "t,p" or "homogeneous" (see above).
    chart:
        Groupoid chart the function is meant for ("cayley" or "exp"); used by the step map.
    input_scale:
        (1 + n,) scales applied to (t, p₁, …, p_n) before the MLP; folded into the first layer
        on export.
    algebra:
        The Lie algebra of the groupoid (None: so(3)); its dimension n is the momentum's.
    output_scale:
        Scale of the MLP output; folded into the last layer on export.
    """

    # Buffers (registered in ``__init__``), declared so that they type as tensors, not as
    # ``Tensor | Module`` (what ``nn.Module.__getattr__`` returns).
    powers: Tensor
    coeffs: Tensor
    input_scale: Tensor
    output_scale: Tensor

    def __init__(
        self,
        widths: Sequence[int] = (32, 32),
        *,
        mlp_power: int = 1,
        powers: np.ndarray | None = None,
        coeffs: np.ndarray | None = None,
        chart: str = "cayley",
        inputs: str = "t,p",
        input_scale: Sequence[float] | None = None,
        output_scale: float = 1.0,
        dtype: torch.dtype = torch.float64,
        algebra: LieAlgebra | None = None,
    ) -> None:
        super().__init__()
        self.algebra = None if algebra is None or algebra.is_so3() else algebra
        self.dim = 3 if algebra is None else int(algebra.dim)
        if self.algebra is not None and chart != "exp":
            raise ValueError(
                f"the {chart!r} chart exists for so(3) only; use chart='exp' for {algebra!r}"
            )
        self.chart = check_chart(chart)
        n_in = 1 + self.dim
        if input_scale is None:
            input_scale = (1.0,) * n_in
        if len(input_scale) != n_in:
            raise ValueError(f"input_scale must have {n_in} entries, got {len(input_scale)}")
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
        raw = np.zeros((0, n_in), np.int64) if powers is None else np.asarray(powers, np.int64)
        powers_t = torch.as_tensor(raw.reshape(0, n_in) if raw.size == 0 else raw)
        coeffs_t = torch.as_tensor(
            np.zeros(0) if coeffs is None else np.asarray(coeffs, np.float64), dtype=dtype
        )
        if powers_t.ndim != 2 or powers_t.shape[1] != n_in or coeffs_t.shape != powers_t.shape[:1]:
            raise ValueError(
                f"powers must be (m, {n_in}) and coeffs (m,), got {tuple(powers_t.shape)} and "
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
        """P(t, p) for t (B,) and p (B, n) → (B,)."""
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
        mono = table(t)[:, k[:, 0]]
        for i in range(self.dim):
            mono = mono * table(p[:, i])[:, k[:, 1 + i]]
        return mono @ self.coeffs

    def forward(self, t: Tensor, p: Tensor) -> Tensor:
        """S(t, p) for t (B,) and p (B, n) → (B,)."""
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
    """S, ∂S/∂p and ∂²S/∂p² by autograd, for t (B,) and p (B, n): (B,), (B, n), (B, n, n)."""
    p = p.detach().requires_grad_(True)
    with torch.enable_grad():
        s = s_fn(t, p)
        (g,) = torch.autograd.grad(s.sum(), p, create_graph=True)
        rows = [
            torch.autograd.grad(g[:, i].sum(), p, retain_graph=True)[0] for i in range(p.shape[1])
        ]
    return s.detach(), g.detach(), torch.stack(rows, dim=1).detach()


#: Ways :func:`hj_derivatives` can take ∂S/∂t and ∂S/∂p (``benches/train_methods.py`` times them
#: and three more): "reverse", closed forms plus a hand-written backward pass through the MLP, and
#: "autograd", nested ``torch.autograd.grad`` (how the shipped models were trained).
HJ_DERIVATIVES: tuple[str, ...] = ("reverse", "autograd")


def check_hj_derivatives(method: str) -> str:
    """Returns ``method`` if it names one of :data:`HJ_DERIVATIVES`, else raises ValueError."""
    if method not in HJ_DERIVATIVES:
        raise ValueError(f"derivatives must be one of {HJ_DERIVATIVES}, got {method!r}")
    return method


def polynomial_gradient(s_fn: GeneratingFunction, t: Tensor, p: Tensor) -> Tensor:
    """∂P/∂(t, p₁, …, p_n) of the polynomial part in closed form, for t (B,) and p (B, n) →
    (B, 1 + n). Constant in the MLP parameters (the coefficients are buffers)."""
    if len(s_fn.coeffs) == 0:
        return torch.zeros(t.shape[0], 1 + p.shape[1], dtype=t.dtype, device=t.device)
    k = s_fn.powers.to(t.dtype)  # (m, 1 + n)
    x = torch.cat([t[:, None], p], dim=1)[:, None, :]  # (B, 1, 1 + n)
    # Tensor powers rather than ``polynomial``'s table of products: no data-dependent size (which
    # would break a torch.compile graph), and nothing differentiates this gradient in x, where
    # ``x ** k`` would have NaN second derivatives at 0.
    f = x**k  # (B, m, 1 + n): x_j^k_j
    df = k * x ** (k - 1.0).clamp_min(0.0)  # k_j x_j^(k_j − 1); the clamp keeps 0⁻¹ out
    # Products of the other factors from prefix and suffix products, rather than divided out
    # (x_j may be 0).
    ones = torch.ones_like(f[..., :1])
    before = torch.cumprod(torch.cat([ones, f[..., :-1]], dim=-1), dim=-1)
    after = torch.cumprod(torch.cat([ones, f.flip(-1)[..., :-1]], dim=-1), dim=-1).flip(-1)
    return torch.einsum("bnj,n->bj", df * before * after, s_fn.coeffs)


def mlp_input(s_fn: GeneratingFunction, t: Tensor, p: Tensor) -> tuple[Tensor, Tensor | None]:
    """The MLP input before ``input_scale``, z (B, 1 + n), and its Jacobian rows ∂z/∂t, ∂z/∂p₁..ₙ
    as (B, 1 + n, 1 + n), or None for ``inputs="t,p"`` where z = (t, p) and the Jacobian is the
    identity."""
    if s_fn.inputs == "t,p":
        return torch.cat([t[:, None], p], dim=1), None
    r = (p * p).sum(1).clamp_min(1e-300).sqrt()  # clamped as in GeneratingFunction.forward
    u = p / r[:, None]
    z = torch.cat([(r * t)[:, None], u], dim=1)
    # z = (r t, p/r): rows ∂z/∂t = (r, 0, 0, 0) and ∂z/∂p_k = (t u_k, (δ_ik − u_i u_k)/r).
    eye = torch.eye(p.shape[1], dtype=t.dtype, device=t.device)
    row_t = torch.cat([r[:, None], torch.zeros_like(p)], dim=1)[:, None, :]
    rows_p = torch.cat(
        [(t[:, None] * u)[:, :, None], (eye - u[:, :, None] * u[:, None, :]) / r[:, None, None]],
        dim=2,
    )
    return z, torch.cat([row_t, rows_p], dim=1)


def assemble_derivatives(
    s_fn: GeneratingFunction, t: Tensor, p: Tensor, o: Tensor, do: Tensor
) -> tuple[Tensor, Tensor]:
    """∂S/∂t (B,) and ∂S/∂p (B, n) from the raw MLP output o (B,) and its gradient do (B, 1 + n) in
    (t, p): the product rule through t^m, the output scale and, if homogeneous, |p|^(m+1); plus
    the polynomial's closed-form gradient."""
    g = polynomial_gradient(s_fn, t, p)
    m, c = s_fn.mlp_power, s_fn.output_scale
    if s_fn.inputs == "t,p":
        n, dn_t, dn_p = c * o, c * do[:, 0], c * do[:, 1:]
    else:
        r = (p * p).sum(1).clamp_min(1e-300).sqrt()
        q = c * r ** (m + 1)
        n, dn_t = q * o, q * do[:, 0]
        # ∂(r^(m+1))/∂p_k = (m + 1) r^(m−1) p_k.
        dn_p = ((m + 1) * c * r ** (m - 1) * o)[:, None] * p + q[:, None] * do[:, 1:]
    tm = t**m
    st = g[:, 0] + m * t ** (m - 1) * n + tm * dn_t
    return st, g[:, 1:] + tm[:, None] * dn_p


def first_layer(
    s_fn: GeneratingFunction, t: Tensor, p: Tensor
) -> tuple[Tensor, Tensor, Tensor | None]:
    """The MLP's first pre-activation (B, H), its weight with the input scale folded in (H, 1 + n),
    and the Jacobian rows of its input (B, 1 + n, 1 + n), None for inputs "t,p" (see
    :func:`mlp_input`):
    where every hand-written derivative pass through the MLP starts."""
    first = s_fn.linears[0]
    w0 = first.weight * s_fn.input_scale
    z, jac = mlp_input(s_fn, t, p)
    return torch.nn.functional.linear(z, w0, first.bias), w0, jac


def _hj_derivatives_reverse(
    s_fn: GeneratingFunction, t: Tensor, p: Tensor
) -> tuple[Tensor, Tensor]:
    """∂S/∂t, ∂S/∂p with the MLP's input gradient by a hand-written backward pass: one (B, H)
    cotangent per layer, built from ordinary tensor ops that autograd can differentiate once
    (a first-order backward over this graph instead of autograd's double backward)."""
    if not s_fn.widths:
        g = polynomial_gradient(s_fn, t, p)
        return g[:, 0], g[:, 1:]
    lin = s_fn.linears
    h, w0, jac = first_layer(s_fn, t, p)
    acts = []
    for layer in lin[1:]:
        acts.append(torch.tanh(h))
        h = torch.nn.functional.linear(acts[-1], layer.weight, layer.bias)
    g = lin[-1].weight  # (1, H): ∂o/∂a of the last hidden layer, the same for every sample
    for a, layer in zip(reversed(acts), reversed(lin[:-1]), strict=True):
        w = w0 if layer is lin[0] else layer.weight
        g = ((1.0 - a * a) * g) @ w  # through tanh (tanh' = 1 − tanh²), then the layer below
    do = g if jac is None else (jac @ g[:, :, None])[..., 0]  # (B, 1 + n): ∂o/∂(t, p)
    return assemble_derivatives(s_fn, t, p, h[:, 0], do)


def hj_derivatives(
    s_fn: GeneratingFunction,
    t: Tensor,
    p: Tensor,
    *,
    method: str = "reverse",
    create_graph: bool = True,
) -> tuple[Tensor, Tensor]:
    """∂S/∂t and ∂S/∂p at t (B,) [time] and p (B, n) [momentum] → (B,) and (B, n), for any
    :class:`GeneratingFunction` (chart, polynomial part, MLP inputs and power, or no MLP).

    ``create_graph=True`` keeps them differentiable in the MLP parameters, so that a loss built
    from them can be back-propagated (the HJ loss); False returns them without a graph.
    ``method`` (one of :data:`HJ_DERIVATIVES`) changes the cost, not the values beyond rounding:

    - "reverse": closed-form polynomial gradient and product rules, and the MLP's input gradient
      by a hand-written backward pass, so that training needs a first-order backward only (the
      faster on a CPU: README, Performance);
    - "autograd": nested ``torch.autograd.grad`` of S.sum() (the paper's way).

    t and p are taken as constants: the results are not differentiable in them.
    """
    check_hj_derivatives(method)
    t, p = t.detach(), p.detach()
    if method == "autograd":
        t, p = t.requires_grad_(True), p.requires_grad_(True)
        with torch.enable_grad():
            st, sp = torch.autograd.grad(s_fn(t, p).sum(), (t, p), create_graph=create_graph)
        return st, sp
    # Like autograd.grad's create_graph: a graph to the parameters exactly when asked for.
    with torch.set_grad_enabled(create_graph):
        return _hj_derivatives_reverse(s_fn, t, p)


def newton_system(
    s_fn: GeneratingFunction, chart: str, t: Tensor, p: Tensor, mu: Tensor
) -> tuple[Tensor, Tensor]:
    """F(p) = tar(∂S/∂p(t, p), p) − μ and its Jacobian dF/dp by autograd through ∂S/∂p (so the
    Hessian of S enters exactly). ``p`` must be a leaf requiring grad; F keeps its graph (to p and
    the weights), the Jacobian is detached. t (B,), p and mu (B, n) → F (B, n), J (B, n, n)."""
    with torch.enable_grad():
        (x,) = torch.autograd.grad(s_fn(t, p).sum(), p, create_graph=True)
        f = tar(chart, x, p, algebra=s_fn.algebra) - mu
        rows = [
            torch.autograd.grad(f[:, i].sum(), p, retain_graph=True)[0] for i in range(p.shape[1])
        ]
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
    update satisfies |δ|∞ ≤ tol·|p|∞ (the Rust core's rule). mu (B, n) → (p (B, n) detached,
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
    as NaN. mu: (B, n) float64 → (B, n).
    """
    chart = check_chart(chart or s_fn.chart)
    p, done = solve_momentum(s_fn, mu, h, chart=chart, tol=tol, max_iter=max_iter)
    t = torch.full((mu.shape[0],), float(h), dtype=mu.dtype, device=mu.device)
    pv = p.requires_grad_(True)
    with torch.enable_grad():
        (x,) = torch.autograd.grad(s_fn(t, pv).sum(), pv)
    out = sou(chart, x, p, algebra=s_fn.algebra).detach()
    return torch.where(done[:, None], out, torch.full_like(out, float("nan")))

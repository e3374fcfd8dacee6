"""The bisection step of a polynomial generating function S(h, ·) in torch, with derivatives in
S's coefficients by the implicit function theorem.

One step from μ: solve F(p) = tar(∇S(p), p) − μ = 0 by Newton from p = μ, then μ' = sou(∇S(p), p)
(exponential chart of T*G, any algebra). S(h, p) = Σ_c s_c p^{e_c} is linear in its coefficient
vector s, so with G = ∂(∇S)/∂s (the monomials' gradients) and J = T_x ∇²S + T_p (the Newton
Jacobian),

    dp/ds = −J⁻¹ T_x G,   dμ'/ds = U_x (G + ∇²S dp/ds) + U_p dp/ds,   dμ'/dμ = (U_x ∇²S + U_p) J⁻¹,

where T_•, U_• are the Jacobians of tar and sou. One linear solve with J at the converged p; the
Newton iterations are never differentiated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .series import MonomialBasis, bernoulli_weights

__all__ = ["StepResult", "bisection_step", "chart_maps"]

#: Newton stops once |δ|∞ ≤ NEWTON_TOL·|p|∞.
NEWTON_TOL = 1e-13
NEWTON_MAX_ITER = 30


def _series_terms(a: Tensor) -> int:
    """Terms of the Bernoulli series needed for round-off at ad_xᵀ = a (B, n, n): the series has
    radius 2π, so (ρ/2π)^R ≤ 1e-18 with ρ ≤ ‖A‖_F."""
    rho = float(torch.linalg.matrix_norm(a.detach()).max()) if a.numel() else 0.0
    if not math.isfinite(rho) or rho >= 0.9 * 2 * math.pi:
        raise FloatingPointError(f"the exponential chart is singular here (|ad_x| = {rho:.3g})")
    if rho == 0.0:
        return 2
    return min(400, max(4, math.ceil(math.log(1e-18) / math.log(rho / (2 * math.pi))))) + 2


def chart_maps(c: Tensor, x: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
    """sou(x, p) = Σ_r (B_r/r!) A^r p and tar(x, p) = Σ_r (B_r/r!) (−A)^r p, A = ad_xᵀ,
    (A)_{jk} = Σ_i c[i,j,k] x_i. x, p (B, n) → (B, n), (B, n); differentiable."""
    a = torch.einsum("ijk,bi->bjk", c, x)
    terms = _series_terms(a)
    w = bernoulli_weights(terms)
    term = p
    even = p.clone()
    odd = torch.zeros_like(p)
    for r in range(1, terms + 1):
        term = (a @ term[..., None])[..., 0]
        if w[r] == 0.0:
            continue
        if r % 2:
            odd = odd + w[r] * term
        else:
            even = even + w[r] * term
    return even + odd, even - odd


def _chart_jacobians(c: Tensor, x: Tensor, p: Tensor) -> tuple[Tensor, ...]:
    """sou, tar and their Jacobians in x and p: (B, n) ×2, then U_x, U_p, T_x, T_p (B, n, n).

    In closed form, alongside the series of :func:`chart_maps`: with t_r = A^r p,
    ∂t_r/∂x_i = C_i t_{r−1} + A ∂t_{r−1}/∂x_i ((C_i)_{jk} = c[i,j,k]), and ∂t_r/∂p = A^r; tar's
    terms are the same with the odd ones negated. The three recursions share one stacked
    product V ← A V per term, V = [t_r | A^r | ∂t_r/∂x] (B, n, 1 + 2n), in numpy (its stacked
    matmul is several times faster than torch's for these small matrices)."""
    b, n = p.shape
    cn = c.detach().numpy()
    xn = x.detach().numpy()
    a = (xn @ cn.reshape(n, n * n)).reshape(b, n, n)  # A_jk = Σ_i c[i,j,k] x_i
    terms = _series_terms(torch.from_numpy(a))
    w = bernoulli_weights(terms)
    # (C v)[b, j, i] = Σ_k c[i,j,k] v[b,k]: one product with c as (k, (j, i)).
    cmat = np.ascontiguousarray(cn.transpose(2, 1, 0).reshape(n, n * n))
    v = np.zeros((b, n, 1 + 2 * n))
    v[:, :, 0] = p.detach().numpy()
    v[:, :, 1 : 1 + n] = np.eye(n)
    even = v.copy()
    odd = np.zeros_like(v)
    for r in range(1, terms + 1):
        ct = (v[:, :, 0] @ cmat).reshape(b, n, n)
        v = a @ v
        v[:, :, 1 + n :] += ct
        if w[r] == 0.0:
            continue
        if r % 2:
            odd += w[r] * v
        else:
            even += w[r] * v
    sou = torch.from_numpy(even + odd)
    tar = torch.from_numpy(even - odd)
    return (
        sou[..., 0],
        tar[..., 0],
        sou[..., 1 + n :],
        sou[..., 1 : 1 + n],
        tar[..., 1 + n :],
        tar[..., 1 : 1 + n],
    )


def _chart_jacobians_autograd(c: Tensor, x: Tensor, p: Tensor) -> tuple[Tensor, ...]:
    """:func:`_chart_jacobians` by reverse-mode autograd of :func:`chart_maps`, one row at a time
    (the oracle of the closed form in the tests)."""
    n = x.shape[1]
    xv = x.detach().requires_grad_(True)
    pv = p.detach().requires_grad_(True)
    with torch.enable_grad():
        s, t = chart_maps(c, xv, pv)
        rows = []
        for out in (s, t):
            for i in range(n):
                rows.append(torch.autograd.grad(out[:, i].sum(), (xv, pv), retain_graph=True))
    ux = torch.stack([r[0] for r in rows[:n]], 1)
    up = torch.stack([r[1] for r in rows[:n]], 1)
    tx = torch.stack([r[0] for r in rows[n:]], 1)
    tp = torch.stack([r[1] for r in rows[n:]], 1)
    return s.detach(), t.detach(), ux, up, tx, tp


@dataclass
class StepResult:
    """One step from (B, n) states: ``out`` (B, n), ``converged`` (B,), and where asked for,
    ``d_coeffs`` = dμ'/ds (B, n, N) and ``d_state`` = dμ'/dμ (B, n, n)."""

    out: Tensor
    converged: Tensor
    d_coeffs: Tensor | None = None
    d_state: Tensor | None = None
    #: The solution p of tar(∇S(p), p) = μ (B, n): a start for the next solve near it.
    p: Tensor | None = None


def bisection_step(
    basis: MonomialBasis,
    c: np.ndarray | Tensor,
    coeffs: Tensor,
    mu: Tensor,
    *,
    derivatives: bool = False,
    coeff_jacobian: Tensor | None = None,
    p0: Tensor | None = None,
) -> StepResult:
    """One bisection step of S(h, p) = Σ coeffs[m] p^{e_m} (coefficients of S at the step's h,
    (N,)) from mu (B, n), float64. Non-converged rows come back NaN.

    With ``coeff_jacobian`` = ds/dθ (N, P), ``d_coeffs`` comes back as dμ'/dθ = dμ'/ds · ds/dθ
    (B, n, P), formed without the (B, n, N) intermediate. ``p0`` (B, n): Newton's start in place
    of μ (e.g. the solution ``p`` of a step from nearby states or for nearby coefficients; rows
    that are not finite start from μ); the converged p does not depend on it.

    ∇S and ∇²S are differentiated once as polynomials (coefficient vectors), so each Newton
    iteration evaluates only the monomials at p."""
    ct = torch.tensor(np.array(c, dtype=np.float64))
    coeffs = coeffs.detach()
    mu = mu.detach()
    n = mu.shape[1]
    d = basis.degree_of(coeffs)
    g_poly = basis.grad(coeffs)  # (n, N_{d−1}): ∂S/∂p_i
    h_poly = basis.grad(g_poly).reshape(n * n, -1)  # (n², N_{d−2}): ∂²S/∂p_i∂p_j
    dg, dh = max(d - 1, 0), max(d - 2, 0)

    def derivs(p: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        phi = basis.values(p, dg)
        return phi, phi @ g_poly.T, (phi[:, : basis.count[dh]] @ h_poly.T).reshape(-1, n, n)

    def newton(p: Tensor, mu: Tensor) -> tuple[Tensor, Tensor]:
        done = torch.zeros(mu.shape[0], dtype=torch.bool)
        for _ in range(NEWTON_MAX_ITER):
            _, x, hs = derivs(p)
            _, t, _, _, tx, tp = _chart_jacobians(ct, x, p)
            jac = tx @ hs + tp
            delta = torch.linalg.solve(jac, -(t - mu)[..., None])[..., 0]
            delta = torch.where(done[:, None], torch.zeros_like(delta), delta)
            p = p + delta
            done = done | (delta.abs().amax(-1) <= NEWTON_TOL * p.abs().amax(-1).clamp_min(1e-300))
            if bool(done.all()):
                break
        return p, done & torch.isfinite(p).all(-1)

    if p0 is None:
        p, ok = newton(mu.clone(), mu)
    else:
        p, ok = newton(torch.where(torch.isfinite(p0), p0.detach(), mu), mu)
        retry = ~ok & torch.isfinite(mu).all(-1)
        if bool(retry.any()):  # rows the start did not serve: from μ, as without one
            p_r, ok_r = newton(mu[retry].clone(), mu[retry])
            p, ok = p.clone(), ok.clone()
            p[retry], ok[retry] = p_r, ok_r
    phi, x, hs = derivs(p)
    if not derivatives:
        s, _ = chart_maps(ct, x, p)
        return StepResult(torch.where(ok[:, None], s, torch.full_like(s, math.nan)), ok, p=p)
    s, _, ux, up, tx, tp = _chart_jacobians(ct, x, p)
    out = torch.where(ok[:, None], s, torch.full_like(s, math.nan))
    if coeff_jacobian is None:
        grad = basis.gradients(p)  # (B, n, N): the monomials' gradients
        grad = grad[..., : coeffs.shape[-1]]
    else:
        # Σ_m ∂(p^{e_m})/∂p_i ds_m/dθ_q: the gradients of the polynomials ds/dθ_q at p.
        dpoly = basis.grad(coeff_jacobian.T.contiguous())  # (P, n, N_{d−1})
        grad = torch.einsum("bm,qim->biq", phi[:, : dpoly.shape[-1]], dpoly)
    jac = tx @ hs + tp
    jinv = torch.linalg.inv(jac)
    dp = -jinv @ (tx @ grad)
    d_coeffs = ux @ (grad + hs @ dp) + up @ dp
    d_state = (ux @ hs + up) @ jinv
    return StepResult(out, ok, d_coeffs, d_state, p)

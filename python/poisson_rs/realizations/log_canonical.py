"""The exact symplectic groupoid of a log-canonical structure π_ij = c_ij x_i x_j, and the
Hamilton–Jacobi Taylor series of its generating function.

On the groupoid T*R^n_+ with canonical coordinates (x, p) ({x^i, p_j} = δ^i_j):

    β_i(x, p) = x_i exp(−½ Σ_j c_ij x_j p_j)   (Poisson: {β^i, β^j} = π^{ij}(β)),
    α_i(x, p) = x_i exp(+½ Σ_j c_ij x_j p_j)   (anti-Poisson), {α^i, β^j} = 0.

In log coordinates q = ln x, P_j = x_j p_j (a cotangent lift, so canonical) both are linear:
β(q, P) = q − ½ c P and α(q, P) = q + ½ c P.

A step of size h from q_k reads the Lagrangian bisection P = ∂S/∂q(h, ·): solve
α(q, ∇S(q)) = q_k for q, then q_{k+1} = β(q, ∇S(q)). With S = −hH + O(h³) this gives
q_{k+1} − q_k = −c∇S = h c ∇_q H + …, the flow q̇ = c ∇_q H (checked in the tests).
The generating function solves ∂S/∂t + H(β(q, ∇S)) = 0, S(0, ·) = 0.
"""

from __future__ import annotations

from fractions import Fraction
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..structures.log_canonical import LogCanonicalSystem

FloatArray = NDArray[np.float64]
#: A polynomial in y = e^q: exponent tuple → exact rational coefficient.
Poly = dict[tuple[int, ...], Fraction]


def _is_tensor(x: object) -> bool:
    return type(x).__module__.startswith("torch")


def _cmat(c: FloatArray, like: Any) -> Any:
    if _is_tensor(like):
        import torch

        return torch.tensor(c, dtype=like.dtype, device=like.device)
    return c


def beta_log(c: FloatArray, q: Any, p: Any) -> Any:
    """β(q, P) = q − ½ c P (the source map, Poisson). q, p: (..., n) → (..., n)."""
    return q - 0.5 * (p @ _cmat(c, q).T)


def alpha_log(c: FloatArray, q: Any, p: Any) -> Any:
    """α(q, P) = q + ½ c P (the target map, anti-Poisson). q, p: (..., n) → (..., n)."""
    return q + 0.5 * (p @ _cmat(c, q).T)


def _exp(v: Any) -> Any:
    if _is_tensor(v):
        import torch

        return torch.exp(v)
    return np.exp(v)


def beta(c: FloatArray, x: Any, p: Any) -> Any:
    """β_i(x, p) = x_i exp(−½ Σ_j c_ij x_j p_j). x (positive), p: (..., n) → (..., n)."""
    return x * _exp(-0.5 * ((x * p) @ _cmat(c, x).T))


def alpha(c: FloatArray, x: Any, p: Any) -> Any:
    """α_i(x, p) = x_i exp(+½ Σ_j c_ij x_j p_j). x (positive), p: (..., n) → (..., n)."""
    return x * _exp(0.5 * ((x * p) @ _cmat(c, x).T))


# ---------------------------------------------------------------------------------------------
# Hamilton–Jacobi Taylor series, in exact rational arithmetic on polynomials in y = e^q
# ---------------------------------------------------------------------------------------------


def _add(a: Poly, b: Poly, s: Fraction = Fraction(1)) -> Poly:
    out = dict(a)
    for e, v in b.items():
        out[e] = out.get(e, Fraction(0)) + s * v
    return {e: v for e, v in out.items() if v != 0}


def _mul(a: Poly, b: Poly) -> Poly:
    out: Poly = {}
    for ea, va in a.items():
        for eb, vb in b.items():
            e = tuple(x + y for x, y in zip(ea, eb, strict=True))
            out[e] = out.get(e, Fraction(0)) + va * vb
    return {e: v for e, v in out.items() if v != 0}


def _scale(a: Poly, s: Fraction) -> Poly:
    return {e: v * s for e, v in a.items() if v * s != 0}


def _dq(a: Poly, i: int) -> Poly:
    """∂/∂q_i of a polynomial in y = e^q: y^e ↦ e_i y^e."""
    return {e: v * e[i] for e, v in a.items() if e[i] != 0}


def taylor_terms(system: LogCanonicalSystem, order: int) -> list[Poly]:
    """S_1 … S_order of the exact generating function S = Σ_k t^k S_k, as exact polynomials in
    y = e^q; S_1 omits its log part +Σ_i b_i q_i (so S_1 = −Σ_m a_m y^{e_m} here, and the full
    S_1 = −H). Computed order by order from ∂S/∂t = −H(β(q, ∇S)):
    S_{n+1} = −[tⁿ] H(q − ½ c P(t)) / (n + 1), P(t) = Σ_k t^k ∇S_k, with
    H(q − ½cP) = Σ_m a_m y^{e_m} exp(−½ e_m·cP) − b·q + ½ b·cP.
    """
    if isinstance(order, bool) or not isinstance(order, int) or order < 1:
        raise ValueError(f"order must be an integer >= 1, got {order!r}")
    n = system.dim
    c = [[Fraction(float(v)) for v in row] for row in system.c]
    powers, coeffs, b_arr = system.log_hamiltonian.to_arrays()
    b = [Fraction(float(v)) for v in b_arr]
    mono = [
        (tuple(int(k) for k in e), Fraction(float(a))) for e, a in zip(powers, coeffs, strict=True)
    ]
    zero = tuple([0] * n)
    poly_h: Poly = {e: a for e, a in mono}
    s_terms: list[Poly] = [_scale(poly_h, Fraction(-1))]
    # G[k][i] = ∂S_{k+1}/∂q_i as a polynomial (the b part of S_1 gives the constant +b_i).
    grads: list[list[Poly]] = [[_add(_dq(s_terms[0], i), {zero: b[i]}) for i in range(n)]]
    for step in range(1, order):
        # [t^step] of H(β): needs P up to t^step, i.e. grads[0..step-1].
        # (c ∇S_{k+1})_i as polynomials, k < step.
        cp_vec = [[_scale_sum(c[i], grads[k]) for i in range(n)] for k in range(step)]
        total: Poly = {}
        for e_m, a_m in mono:
            # u_k = −½ Σ_i e_m,i (c ∇S_k)_i, k = 1..step
            u = [
                _scale(
                    _sum([_scale(cp_vec[k][i], Fraction(e_m[i])) for i in range(n) if e_m[i]]),
                    Fraction(-1, 2),
                )
                for k in range(step)
            ]
            ex: list[Poly] = [{zero: Fraction(1)}]
            for j in range(1, step + 1):
                acc: Poly = {}
                for k in range(1, j + 1):
                    acc = _add(acc, _mul(u[k - 1], ex[j - k]), Fraction(k))
                ex.append(_scale(acc, Fraction(1, j)))
            total = _add(total, _mul({e_m: a_m}, ex[step]))
        lin = _sum([_scale(cp_vec[step - 1][i], b[i] / 2) for i in range(n)])
        total = _add(total, lin)
        s_next = _scale(total, Fraction(-1, step + 1))
        # A constant term of S_k moves nothing (only ∇S enters a step): drop it.
        s_next.pop(zero, None)
        s_terms.append(s_next)
        grads.append([_dq(s_next, i) for i in range(n)])
    return s_terms


def _sum(polys: list[Poly]) -> Poly:
    out: Poly = {}
    for p in polys:
        out = _add(out, p)
    return out


def _scale_sum(row: list[Fraction], vec: list[Poly]) -> Poly:
    """Σ_j row[j] vec[j]."""
    return _sum([_scale(v, r) for r, v in zip(row, vec, strict=True) if r != 0])


def taylor_arrays(
    system: LogCanonicalSystem, order: int
) -> tuple[NDArray[np.int64], NDArray[np.int64], FloatArray]:
    """The truncated S = Σ_{k≤order} t^k S_k (without S_1's log part t·b·q) as flat arrays:
    t-powers (M,) int64, y-exponents (M, n) int64, coefficients (M,) float64."""
    terms = taylor_terms(system, order)
    n = system.dim
    tp, ex, co = [], [], []
    for k, poly in enumerate(terms, start=1):
        for e, v in sorted(poly.items()):
            tp.append(k)
            ex.append(e)
            co.append(float(v))
    return (
        np.array(tp, dtype=np.int64),
        np.array(ex, dtype=np.int64).reshape(-1, n),
        np.array(co, dtype=np.float64),
    )


def generating_derivatives(
    system: LogCanonicalSystem, arrays: tuple[Any, Any, Any], t: float, q: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """∇_q S and ∇²_q S at (t, q) for S from :func:`taylor_arrays` plus t·b·q.
    q: (B, n) → (B, n), (B, n, n)."""
    tp, ex, co = arrays
    w = co * t**tp * np.exp(q @ ex.T)  # (B, M)
    grad = w @ ex + t * system.log_hamiltonian.b
    hess = np.einsum("bm,mi,mj->bij", w, ex, ex)
    return grad, hess


def numpy_step(
    system: LogCanonicalSystem,
    arrays: tuple[Any, Any, Any],
    q: FloatArray,
    h: float,
    tol: float = 1e-13,
    max_iter: int = 50,
) -> FloatArray:
    """One Taylor-HJ step in q = ln x, by Newton in NumPy (the oracle of the Rust stepper).
    q: (B, n) → (B, n)."""
    c = system.c
    z = np.array(q, dtype=np.float64)
    for _ in range(max_iter):
        g, hs = generating_derivatives(system, arrays, h, z)
        f = alpha_log(c, z, g) - q
        jac = np.eye(system.dim) + 0.5 * np.einsum("ij,bjk->bik", c, hs)
        delta = np.linalg.solve(jac, -f[..., None])[..., 0]
        z = z + delta
        if np.abs(delta).max() <= tol * max(np.abs(z).max(), 1.0):
            break
    g, _ = generating_derivatives(system, arrays, h, z)
    return beta_log(c, z, g)

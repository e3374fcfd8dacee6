"""The Taylor-HJ series of a polynomial realization in floating point: S_1..S_K of
∂S/∂t + H(β(x, ∇S)) = 0 for a realization β(x, p) given as the core's term table.

:func:`poisson_rs.structures.polynomial.hj_series` derives the same terms exactly with sympy,
which costs seconds per Hamiltonian. Fitting H to trajectories needs the series at every
iterate, so this module runs the recursion

    S_1 = −H,   S_k = −[t^{k−1}] H(β(x, Σ_{j<k} t^j ∇S_j)) / k,

on sparse float64 polynomials (exponents (T, n) int64, coefficients (T,)), in milliseconds. The
two agree to rounding (tested).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

__all__ = ["Poly", "combine", "derivative", "hj_terms", "series_table"]

#: A sparse polynomial in n variables: (exponents (T, n) int64, coefficients (T,) float64).
Poly = tuple[NDArray[np.int64], NDArray[np.float64]]
Series = list[Poly]

#: Exponents are packed into one int64 key per monomial, this many bits per variable.
_BITS = 6


def _zero(n: int) -> Poly:
    return np.zeros((0, n), dtype=np.int64), np.zeros(0)


def _one(n: int) -> Poly:
    return np.zeros((1, n), dtype=np.int64), np.ones(1)


def combine(exps: NDArray[np.int64], coeffs: NDArray[np.float64]) -> Poly:
    """Like terms summed (exponents (T, n) may repeat), exact zeros dropped."""
    n = exps.shape[1]
    if len(coeffs) == 0:
        return _zero(n)
    if exps.max(initial=0) >= 1 << _BITS or n * _BITS > 62:
        raise ValueError("a polynomial of the series exceeds the packed exponent range")
    keys = exps @ (np.int64(1) << (_BITS * np.arange(n, dtype=np.int64)))
    uniq, first, inv = np.unique(keys, return_index=True, return_inverse=True)
    summed = np.bincount(inv.ravel(), weights=coeffs, minlength=len(uniq))
    keep = summed != 0.0
    return np.ascontiguousarray(exps[first][keep]), summed[keep]


def _add(a: Poly, b: Poly) -> Poly:
    return combine(np.concatenate([a[0], b[0]]), np.concatenate([a[1], b[1]]))


def _mul(a: Poly, b: Poly) -> Poly:
    n = a[0].shape[1]
    if len(a[1]) == 0 or len(b[1]) == 0:
        return _zero(n)
    exps = (a[0][:, None, :] + b[0][None, :, :]).reshape(-1, n)
    return combine(exps, np.outer(a[1], b[1]).ravel())


def derivative(a: Poly, i: int) -> Poly:
    """∂a/∂x_i."""
    e, c = a
    rows = e[:, i] > 0
    out = e[rows].copy()
    out[:, i] -= 1
    return combine(out, c[rows] * e[rows, i])


def _series_mul(a: Series, b: Series, top: int) -> Series:
    n = a[0][0].shape[1]
    out = [_zero(n) for _ in range(top + 1)]
    for i, ai in enumerate(a[: top + 1]):
        if len(ai[1]) == 0:
            continue
        for j, bj in enumerate(b[: top + 1 - i]):
            if len(bj[1]):
                out[i + j] = _add(out[i + j], _mul(ai, bj))
    return out


class _Powers:
    """Powers of a few series, truncated at t^top, built once each."""

    def __init__(self, values: Sequence[Series], top: int) -> None:
        self.values, self.top = values, top
        self.cache: dict[tuple[int, int], Series] = {}

    def __call__(self, i: int, e: int) -> Series:
        if (i, e) not in self.cache:
            n = self.values[i][0][0].shape[1]
            self.cache[(i, e)] = (
                [_one(n)] + [_zero(n)] * self.top
                if e == 0
                else _series_mul(self(i, e - 1), self.values[i], self.top)
            )
        return self.cache[(i, e)]


def _compose(terms: Poly, n: int, values: Sequence[Series], top: int, x_part: bool) -> Series:
    """Σ_terms c · x^{e_x} · Π_j values_j^{e_j} as a series in t (to t^top): ``terms`` has
    exponents over (values..., x...) when ``x_part`` (a realization's β_i over (p, x)), over the
    values alone otherwise (H composed with β)."""
    exps, coeffs = terms
    m = len(values)
    powers = _Powers(values, top)
    out = [_zero(n) for _ in range(top + 1)]
    for row, c in zip(exps, coeffs, strict=True):
        head = (
            (row[m:].reshape(1, n), np.array([c]))
            if x_part
            else (
                np.zeros((1, n), dtype=np.int64),
                np.array([c]),
            )
        )
        term: Series = [head] + [_zero(n)] * top
        for j in range(m):
            if row[j]:
                term = _series_mul(term, powers(j, int(row[j])), top)
        out = [_add(o, t) for o, t in zip(out, term, strict=True)]
    return out


def hj_terms(beta: Sequence[Poly], hamiltonian: Poly, order: int) -> list[Poly]:
    """[S_1, …, S_order] for H (a polynomial in x, (T, n)) on the realization β: ``beta`` one
    polynomial per component over (p_1..p_n, x_1..x_n), (T_i, 2n) (the core's β table split by
    component)."""
    n = hamiltonian[0].shape[1]
    s_terms: list[Poly] = [(hamiltonian[0].copy(), -hamiltonian[1])]
    for k in range(2, order + 1):
        top = k - 1
        grad: list[Series] = [[_zero(n)] + [derivative(s, i) for s in s_terms] for i in range(n)]
        beta_t = [_compose(b, n, grad, top, x_part=True) for b in beta]
        h_t = _compose(hamiltonian, n, beta_t, top, x_part=False)
        e, c = h_t[top]
        s_terms.append((e, -c / k))
    return s_terms


def series_table(s_terms: Sequence[Poly]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """S(t, x) = Σ_k t^k S_k as the core's table: coefficients (T,) and exponents (T, 1 + n),
    the power of t first."""
    coeffs, exps = [], []
    for k, (e, c) in enumerate(s_terms, start=1):
        exps.append(np.concatenate([np.full((len(c), 1), k, dtype=np.int64), e], axis=1))
        coeffs.append(c)
    return np.concatenate(coeffs), np.ascontiguousarray(np.concatenate(exps))

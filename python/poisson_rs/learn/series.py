"""The Taylor series in t of the Hamilton–Jacobi generating function, in floating point and
differentiable in the Hamiltonian's coefficients.

:func:`poisson_rs.taylor.lie_taylor_coefficients` computes S = Σ_k t^k S_k exactly (rationals) for
one Hamiltonian; fitting H_θ = Σ_e θ_e μ^e to data needs S and dS/dθ at every iterate, so this
module runs the same recursion (exponential chart of T*G on any g*),

    k S_k = −[t^{k−1}] H_θ(σ(t, p)),   σ = sou(Σ_j t^j ∇S_j, p) = Σ_r (B_r/r!) A^r p,
    (A v)_j = Σ_{i,k} c[i,j,k] x_i v_k,

on dense polynomial coefficient vectors in torch (float64), over the monomials of total degree
≤ D = K(d − 1) + 1 (d = deg H). Every S_k has degree ≤ k(d − 1) + 1, so truncating products at D
loses nothing. The result is one coefficient vector per order; S(h, ·) = Σ_k h^k S_k.
"""

from __future__ import annotations

import itertools
import math
from functools import cache

import numpy as np
import torch
from torch import Tensor

__all__ = ["MonomialBasis", "bernoulli_weights", "series_jacobian", "taylor_series"]


def monomials(n: int, degree: int, min_degree: int = 0) -> list[tuple[int, ...]]:
    """Exponent tuples of the monomials in n variables of total degree in [min_degree, degree],
    sorted by degree then reverse-lexicographically (μ₁² before μ₁μ₂)."""
    out = []
    for d in range(min_degree, degree + 1):
        for combo in itertools.combinations_with_replacement(range(n), d):
            e = [0] * n
            for i in combo:
                e[i] += 1
            out.append(tuple(e))
    return out


class MonomialBasis:
    """Dense polynomials in n variables of total degree ≤ D as coefficient vectors (..., N_d).

    Monomials are sorted by degree, so a polynomial of degree ≤ d is the first N_d = C(n + d, d)
    coefficients: every operation takes and returns such prefixes, and a product of degrees a
    and b costs only the pairs it needs (truncated at D). Index tables are built once per
    (a, b) and cached.
    """

    def __init__(self, n: int, degree: int) -> None:
        self.n, self.degree = n, degree
        self.exponents = monomials(n, degree)
        self.index = {e: i for i, e in enumerate(self.exponents)}
        self.size = len(self.exponents)
        exps = np.array(self.exponents, dtype=np.int64).reshape(self.size, n)
        self.powers = exps
        self._deg = exps.sum(1)
        self.count = [math.comb(n + d, d) for d in range(degree + 1)]
        self._length_degree = {c: d for d, c in enumerate(self.count)}
        self._mul_tables: dict[
            tuple[int, int], tuple[Tensor, Tensor, Tensor, int, Tensor | None]
        ] = {}
        self._diff_tables: dict[tuple[int, int], tuple[Tensor, Tensor, Tensor]] = {}
        self._exponents_t = torch.as_tensor(exps)
        self._factors: tuple[Tensor, Tensor] | None = None

    def degree_of(self, a: Tensor) -> int:
        return self._length_degree[a.shape[-1]]

    def pad(self, a: Tensor, degree: int) -> Tensor:
        """a as a polynomial of degree ≤ ``degree`` (zero-padded)."""
        extra = self.count[degree] - a.shape[-1]
        return a if extra == 0 else torch.nn.functional.pad(a, (0, extra))

    def add(self, a: Tensor, b: Tensor) -> Tensor:
        d = max(self.degree_of(a), self.degree_of(b))
        return self.pad(a, d) + self.pad(b, d)

    def _mul_table(self, da: int, db: int) -> tuple[Tensor, Tensor, Tensor, int, Tensor | None]:
        """The pairs (ia, ib) of monomials whose product is kept, its index ic and degree dc;
        and, where the kept pairs are most of the N_a·N_b, ic over all pairs in row-major order
        (dropped pairs sent to the extra slot N_c)."""
        key = (da, db)
        if key not in self._mul_tables:
            dc = min(da + db, self.degree)
            na, nb = self.count[da], self.count[db]
            deg = self._deg
            keep = deg[:na, None] + deg[None, :nb] <= self.degree
            ia, ib = np.nonzero(keep)
            summed = self.powers[ia] + self.powers[ib]
            ic = np.array([self.index[tuple(e)] for e in summed.tolist()], dtype=np.int64)
            dense = None
            if 2 * len(ia) >= na * nb:
                dense = np.full(na * nb, self.count[dc], dtype=np.int64)
                dense[ia * nb + ib] = ic
            self._mul_tables[key] = (
                torch.as_tensor(ia),
                torch.as_tensor(ib),
                torch.as_tensor(ic),
                dc,
                None if dense is None else torch.as_tensor(dense),
            )
        return self._mul_tables[key]

    def mul(self, a: Tensor, b: Tensor) -> Tensor:
        """Truncated product of prefixes a (..., N_a), b (..., N_b) (broadcast) → (..., N_c).

        Where most pairs are kept, the outer product (contiguous, no gathers) is summed into
        place and the dropped pairs go to a discarded slot."""
        ia, ib, ic, dc, dense = self._mul_table(self.degree_of(a), self.degree_of(b))
        nc = self.count[dc]
        if dense is not None:
            vals = (a[..., :, None] * b[..., None, :]).flatten(-2)
            out = torch.zeros((*vals.shape[:-1], nc + 1), dtype=vals.dtype)
            return out.index_add(-1, dense, vals)[..., :nc]
        vals = a[..., ia] * b[..., ib]
        out = torch.zeros((*vals.shape[:-1], nc), dtype=vals.dtype)
        return out.index_add(-1, ic, vals)

    def diff(self, a: Tensor, i: int) -> Tensor:
        """∂a/∂μ_i, a (..., N_d) → (..., N_{d−1})."""
        d = self.degree_of(a)
        key = (d, i)
        if key not in self._diff_tables:
            exps = self.powers[: self.count[d]]
            src = np.nonzero(exps[:, i] > 0)[0]
            unit = np.eye(self.n, dtype=np.int64)[i]
            dst = [self.index[tuple(e)] for e in (exps[src] - unit).tolist()]
            self._diff_tables[key] = (
                torch.as_tensor(src),
                torch.as_tensor(np.array(dst, dtype=np.int64)),
                torch.as_tensor(exps[src, i].astype(np.float64)),
            )
        src_t, dst_t, factor = self._diff_tables[key]
        out = torch.zeros((*a.shape[:-1], self.count[max(d - 1, 0)]), dtype=a.dtype)
        return out.index_add(-1, dst_t, a[..., src_t] * factor.to(a.dtype))

    def grad(self, a: Tensor) -> Tensor:
        """∇a as n coefficient vectors: a (..., N_d) → (..., n, N_{d−1})."""
        return torch.stack([self.diff(a, i) for i in range(self.n)], -2)

    def variable(self, i: int) -> Tensor:
        """μ_i as a polynomial of degree ≤ 1: (N_1,)."""
        v = torch.zeros(self.count[1], dtype=torch.float64)
        v[self.index[tuple(1 if j == i else 0 for j in range(self.n))]] = 1.0
        return v

    def evaluate(self, coeffs: Tensor, p: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Value (B,), gradient (B, n) and Hessian (B, n, n) of Σ_c coeffs[c] p^{e_c} at p (B, n);
        coeffs (N,), differentiable in both."""
        phi, dphi, ddphi = self.features(p)
        return phi @ coeffs, dphi @ coeffs, ddphi @ coeffs

    def _power_table(self, p: Tensor, degree: int) -> Tensor:
        """p_i^k, k = 0..degree: (degree + 1, B, n)."""
        pw = [torch.ones_like(p)]
        for _ in range(degree):
            pw.append(pw[-1] * p)
        return torch.stack(pw, 0)

    def values(self, p: Tensor, degree: int | None = None) -> Tensor:
        """The monomials of degree ≤ ``degree`` (default: the basis') at p (B, n): (B, N_d)."""
        d = self.degree if degree is None else degree
        table = self._power_table(p, d)
        e = self._exponents_t[: self.count[d]]
        vals = table[e[:, 0], :, 0]
        for i in range(1, self.n):
            vals = vals * table[e[:, i], :, i]
        return vals.T

    def _factor_tables(self) -> tuple[Tensor, Tensor]:
        """For every shift σ (0, the units, the sums of two units): the clamped exponents
        e − σ (S, N, n) and the factors Π_i e_i!/(e_i − σ_i)! (zero where e < σ) (S, N)."""
        if self._factors is None:
            n = self.n
            eye = np.eye(n, dtype=np.int64)
            shifts = [np.zeros(n, np.int64), *eye]
            shifts += [eye[i] + eye[j] for i in range(n) for j in range(n)]
            e = self.powers
            ks, coefs = [], []
            for sh in shifts:
                k = e - sh
                coef = np.ones(self.size)
                for i in range(n):
                    for m in range(int(sh[i])):
                        coef = coef * (e[:, i] - m)
                coefs.append(coef * (k >= 0).all(1))
                ks.append(k.clip(0))
            self._factors = (torch.as_tensor(np.stack(ks)), torch.as_tensor(np.stack(coefs)))
        return self._factors

    def _factor(self, table: Tensor, s: int) -> Tensor:
        """Π_i coefficient·p_i^(e_i − σ_i) over the monomials for shift number s (see
        :meth:`_factor_tables`), from the power table of :meth:`_power_table`: (B, N)."""
        kk, coef = self._factor_tables()
        k = kk[s]
        vals = table[k[:, 0], :, 0]
        for i in range(1, self.n):
            vals = vals * table[k[:, i], :, i]
        return vals.T * coef[s].to(table.dtype)[None, :]

    def features(self, p: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Monomials (B, N), their gradients (B, n, N) and Hessians (B, n, n, N) at p (B, n)."""
        n = self.n
        table = self._power_table(p, self.degree)  # (d + 1, B, n): p_i^k
        phi = self._factor(table, 0)
        dphi = torch.stack([self._factor(table, 1 + i) for i in range(n)], 1)
        hess = torch.stack(
            [
                torch.stack([self._factor(table, 1 + n + n * i + j) for j in range(n)], 1)
                for i in range(n)
            ],
            1,
        )
        return phi, dphi, hess

    def gradients(self, p: Tensor) -> Tensor:
        """The monomials' gradients (B, n, N) at p (B, n)."""
        table = self._power_table(p, self.degree)
        return torch.stack([self._factor(table, 1 + i) for i in range(self.n)], 1)


@cache
def bernoulli_weights(n_max: int) -> tuple[float, ...]:
    """B_r/r! for r = 0..n_max (B₁ = −½)."""
    from fractions import Fraction

    b = [Fraction(0)] * (n_max + 1)
    b[0] = Fraction(1)
    for m in range(1, n_max + 1):
        b[m] = -sum((math.comb(m + 1, j) * b[j] for j in range(m)), Fraction(0)) / (m + 1)
    return tuple(float(b[r] / math.factorial(r)) for r in range(n_max + 1))


@cache
def basis(n: int, degree: int) -> MonomialBasis:
    """A cached :class:`MonomialBasis`."""
    return MonomialBasis(n, degree)


def taylor_series(
    c: np.ndarray, family: list[tuple[int, ...]], theta: Tensor, order: int
) -> tuple[MonomialBasis, Tensor]:
    """S_1..S_K of H_θ = Σ_m θ_m μ^{family[m]} on the dual of the algebra with structure constants
    c (n, n, n), exponential chart.

    theta: (..., P), real or complex (complex steps give exact derivatives, see
    :func:`series_jacobian`). Returns the basis (degree K(d − 1) + 1) and the coefficients
    (..., K, N). Agrees with :func:`poisson_rs.taylor.lie_taylor_coefficients` to rounding.
    """
    n = c.shape[0]
    d = max(sum(e) for e in family)
    basis_ = basis(n, max(1, order * (d - 1) + 1))
    dtype = theta.dtype
    batch = theta.shape[:-1]
    c64 = np.array(c, dtype=np.float64)
    weights = bernoulli_weights(order)
    p_vec = torch.stack([basis_.variable(i) for i in range(n)]).to(dtype).expand(*batch, n, -1)
    # (A v)_a = Σ_b A_ab v_b over the entries (a, b) of A = Σ_i x_i C_i that the structure
    # constants do not make zero.
    ent_a, ent_b = np.nonzero(np.abs(c64).sum(0))
    c_ent = torch.as_tensor(c64[:, ent_a, ent_b]).to(dtype)  # (n, K)
    ent_a_t, ent_b_t = torch.as_tensor(ent_a), torch.as_tensor(ent_b)
    # H's monomials as sorted variable lists; prod series by prefix, as in taylor.py. A monomial
    # of ≥ 2 factors is its prefix's product times its last factor, so H's terms of a length
    # sum as Σ_g prod_g · (Σ_b θ_{g+b} σ_b), one product per prefix g.
    factors = [tuple(i for i, a in enumerate(e) for _ in range(a)) for e in family]
    prefixes = sorted({f[:r] for f in factors for r in range(2, len(f))}, key=len)
    groups: dict[int, list[tuple[int, ...]]] = {}
    for f in factors:
        if len(f) >= 2 and f[:-1] not in groups.setdefault(len(f) - 1, []):
            groups[len(f) - 1].append(f[:-1])
    # Θ_ℓ (..., G_ℓ, n): θ of the monomial g + (b,) for the ℓ-factor prefixes g.
    lin: dict[int, Tensor] = {}
    for ell, gs in groups.items():
        sel = np.zeros((len(family), len(gs) * n))
        for q, f in enumerate(factors):
            if len(f) == ell + 1:
                sel[q, gs.index(f[:-1]) * n + f[-1]] = 1.0
        lin[ell] = (theta @ torch.as_tensor(sel).to(dtype)).reshape(*batch, len(gs), n)
    lin_series: dict[int, list[Tensor]] = {ell: [] for ell in groups}
    prods: dict[tuple[int, ...], list[Tensor]] = {}
    one = torch.ones(1, dtype=dtype)  # the constant 1, degree 0
    mats: list[Tensor] = [torch.zeros(0)]
    w: list[list[Tensor]] = [[p_vec]]
    sigma: list[Tensor] = [p_vec]
    coeffs: list[Tensor] = []
    for k in range(1, order + 1):
        m = k - 1
        if m >= 1:
            x_m = basis_.grad(coeffs[m - 1])  # (..., n, N)
            mats.append(torch.einsum("ik,...iN->...kN", c_ent, x_m))  # (A_m)_{ab}, (..., K, N)
            w.append([])
            for r in range(1, m + 1):
                js = range(m, m + 1) if r == 1 else range(1, m - r + 2)
                acc = torch.zeros(*batch, n, 1, dtype=dtype)
                for j in js:
                    v = w[r - 1][m - j - (r - 1)]  # (..., n, N)
                    prod = basis_.mul(mats[j], v[..., ent_b_t, :])  # (..., K, N_c)
                    av = torch.zeros((*prod.shape[:-2], n, prod.shape[-1]), dtype=dtype)
                    acc = basis_.add(acc, av.index_add(-2, ent_a_t, prod))
                w[r].append(acc)
            sig = torch.zeros(*batch, n, 1, dtype=dtype)
            for r in range(1, m + 1):
                sig = basis_.add(sig, weights[r] * w[r][m - r])
            sigma.append(sig)
        for f in prefixes:
            head = prods[f[:-1]] if len(f) > 2 else [sg[..., f[0], :] for sg in sigma]
            acc = torch.zeros(*batch, 1, dtype=dtype)
            for a in range(m + 1):
                acc = basis_.add(acc, basis_.mul(head[a], sigma[m - a][..., f[-1], :]))
            prods.setdefault(f, []).append(acc)
        h_m = torch.zeros(*batch, 1, dtype=dtype)
        for q, f in enumerate(factors):
            t = theta[..., q : q + 1]
            if len(f) == 0:
                if m == 0:
                    h_m = basis_.add(h_m, t * one)
            elif len(f) == 1:
                h_m = basis_.add(h_m, t * sigma[m][..., f[0], :])
        for ell, gs in groups.items():
            lin_series[ell].append(lin[ell] @ sigma[m])  # (..., G, N_m)
            idx = torch.as_tensor([g[0] for g in gs])
            for a in range(m + 1):
                if ell == 1:
                    head_a = sigma[a][..., idx, :]
                else:
                    head_a = torch.stack([prods[g][a] for g in gs], -2)
                h_m = basis_.add(h_m, basis_.mul(head_a, lin_series[ell][m - a]).sum(-2))
        coeffs.append(-h_m / k)
    return basis_, torch.stack([basis_.pad(c_k, basis_.degree) for c_k in coeffs], -2)


#: Imaginary step of the complex-step derivative: the S_k are polynomials in θ, so
#: Im f(θ + iε e_j)/ε is ∂f/∂θ_j to rounding (no subtraction, no truncation error to speak of).
COMPLEX_STEP = 1e-30


#: Bytes the complex-step batch of :func:`series_jacobian` may hold at once: the P + 1
#: Hamiltonians are evaluated in chunks of rows below it (each row's series is independent).
#: A quartic H on a 6-dimensional algebra asked for 27 GB in one piece.
SERIES_BATCH_BYTES = 1 << 30


def series_row_bytes(n: int, family: list[tuple[int, ...]], order: int) -> int:
    """An upper bound on the bytes one complex row of :func:`taylor_series` holds in its
    largest product: every group of H's monomial prefixes (the same length) times at most
    C(2n + D, D) kept monomial pairs (degree ≤ D in the two factors together), complex128, and
    twice that where the product runs as a dense outer product."""
    d = max(sum(e) for e in family)
    degree = max(1, order * (d - 1) + 1)
    prefixes: dict[int, set[tuple[int, ...]]] = {}
    for e in family:
        f = tuple(i for i, a in enumerate(e) for _ in range(a))
        if len(f) >= 2:
            prefixes.setdefault(len(f) - 1, set()).add(f[:-1])
    groups = max([n, *(len(g) for g in prefixes.values())])
    return 2 * 16 * groups * math.comb(2 * n + degree, degree)


def series_jacobian(
    c: np.ndarray, family: list[tuple[int, ...]], theta: np.ndarray, order: int, h: float
) -> tuple[MonomialBasis, Tensor, Tensor]:
    """S(h, ·) = Σ_k h^k S_k as coefficients (N,) and their Jacobian in θ (N, P), by batched
    complex-step evaluations of :func:`taylor_series` (the P + 1 Hamiltonians in chunks of at
    most :data:`SERIES_BATCH_BYTES`, by :func:`series_row_bytes`)."""
    th = np.asarray(theta, dtype=np.float64)
    p = th.size
    batch = np.tile(th.astype(np.complex128), (p + 1, 1))
    batch[1:] += 1j * COMPLEX_STEP * np.eye(p)
    rows = max(1, SERIES_BATCH_BYTES // series_row_bytes(c.shape[0], family, order))
    parts = [
        taylor_series(c, family, torch.as_tensor(batch[i : i + rows]), order)
        for i in range(0, p + 1, rows)
    ]
    b, sk = parts[0][0], torch.cat([part[1] for part in parts])
    powers = torch.tensor([h**k for k in range(1, order + 1)], dtype=torch.complex128)
    s = torch.einsum("k,bkN->bN", powers, sk)
    return b, s[0].real.clone(), (s[1:].imag / COMPLEX_STEP).T.contiguous()

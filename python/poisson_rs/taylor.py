"""Exact Taylor expansion in time of the Hamilton–Jacobi generating function.

For the free rigid body H(p) = ½ Σ pᵢ²/Iᵢ on so(3)* ≅ R³ and a chart (x, p) of the symplectic
groupoid T*SO(3), the generating function S(t, p) with x = ∂S/∂p solves

    ∂S/∂t(t, p) + H(sou(∂S/∂p(t, p), p)) = 0,    S(0, p) = 0,

with the source map of the chart

    cayley: sou(x, p) = p + ½ x×p + ¼ x (x·p)
    exp:    sou(x, p) = p + ½ x×p + c(|x|) x×(x×p),   c(θ) = (1 − (θ/2)cot(θ/2))/θ².

Writing S = Σ_{k≥1} tᵏ S_k(p) and matching powers of t gives the recursion

    k S_k = −[t^{k−1}] H(sou(Σ_j t^j ∇S_j, p)),

so S₁ = −H and every S_k is a homogeneous polynomial of degree k + 1 in p (x = O(t), hence
the series of c in |x|² truncates at each order). The coefficients are computed exactly with
``fractions.Fraction``; :func:`taylor_terms` exports them as the flat (powers, coeffs) arrays
consumed by the Rust core and the torch module.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from fractions import Fraction

import numpy as np

__all__ = ["CHARTS", "MAX_ORDER", "evaluate_terms", "taylor_coefficients", "taylor_terms"]

#: Largest supported truncation order (S_15 has degree 16 and 153 monomials; exact arithmetic
#: stays well under a second up to here).
MAX_ORDER = 15
#: Supported groupoid charts.
CHARTS = ("cayley", "exp")

Exponent = tuple[int, int, int]


class _Poly:
    """Sparse exact polynomial in (p1, p2, p3): exponent tuple (a, b, c) ↦ Fraction."""

    __slots__ = ("terms",)

    def __init__(self, terms: dict[Exponent, Fraction] | None = None) -> None:
        # Zero coefficients are never stored, so ``not poly.terms`` means poly == 0.
        self.terms: dict[Exponent, Fraction] = (
            {e: c for e, c in terms.items() if c != 0} if terms else {}
        )

    @staticmethod
    def var(i: int) -> _Poly:
        e = [0, 0, 0]
        e[i] = 1
        return _Poly({(e[0], e[1], e[2]): Fraction(1)})

    def __add__(self, other: _Poly) -> _Poly:
        out = dict(self.terms)
        for e, c in other.terms.items():
            out[e] = out.get(e, 0) + c
        return _Poly(out)

    def __neg__(self) -> _Poly:
        return _Poly({e: -c for e, c in self.terms.items()})

    def __sub__(self, other: _Poly) -> _Poly:
        return self + (-other)

    def __mul__(self, other: _Poly) -> _Poly:
        if not self.terms or not other.terms:
            return _Poly()
        out: dict[Exponent, Fraction] = {}
        for (a1, b1, c1), x in self.terms.items():
            for (a2, b2, c2), y in other.terms.items():
                e = (a1 + a2, b1 + b2, c1 + c2)
                out[e] = out.get(e, 0) + x * y
        return _Poly(out)

    def scale(self, s: Fraction) -> _Poly:
        return _Poly({e: s * c for e, c in self.terms.items()})

    def times_var(self, i: int) -> _Poly:
        """Multiply by p_i: a pure exponent shift, much cheaper than a general product."""
        out = {}
        for e, c in self.terms.items():
            f = list(e)
            f[i] += 1
            out[(f[0], f[1], f[2])] = c
        return _Poly(out)

    def diff(self, i: int) -> _Poly:
        """Partial derivative ∂/∂p_i."""
        out = {}
        for e, c in self.terms.items():
            if e[i] > 0:
                f = list(e)
                f[i] -= 1
                out[(f[0], f[1], f[2])] = c * e[i]
        return _Poly(out)


Vec = tuple[_Poly, _Poly, _Poly]


def _vadd(u: Vec, v: Vec) -> Vec:
    return (u[0] + v[0], u[1] + v[1], u[2] + v[2])


def _vscale(u: Vec, s: Fraction) -> Vec:
    return (u[0].scale(s), u[1].scale(s), u[2].scale(s))


def _vmul(u: Vec, f: _Poly) -> Vec:
    return (u[0] * f, u[1] * f, u[2] * f)


def _dot(u: Vec, v: Vec) -> _Poly:
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def _dot_p(u: Vec) -> _Poly:
    """u·p, using exponent shifts instead of products."""
    return u[0].times_var(0) + u[1].times_var(1) + u[2].times_var(2)


def _cross_p(u: Vec) -> Vec:
    """u×p, using exponent shifts instead of products."""
    return (
        u[1].times_var(2) - u[2].times_var(1),
        u[2].times_var(0) - u[0].times_var(2),
        u[0].times_var(1) - u[1].times_var(0),
    )


def _zero_vec() -> Vec:
    return (_Poly(), _Poly(), _Poly())


def _grad(f: _Poly) -> Vec:
    return (f.diff(0), f.diff(1), f.diff(2))


def _bernoulli(n_max: int) -> list[Fraction]:
    """B_0..B_{n_max} (B_1 = −1/2 convention; only even indices are used)."""
    b = [Fraction(0)] * (n_max + 1)
    b[0] = Fraction(1)
    for m in range(1, n_max + 1):
        b[m] = -sum((math.comb(m + 1, j) * b[j] for j in range(m)), Fraction(0)) / (m + 1)
    return b


def _exp_chart_c(n_terms: int) -> list[Fraction]:
    """Coefficients c_n of c(θ) = Σ_n c_n θ^{2n} = (1 − (θ/2)cot(θ/2))/θ².

    From (z/2)cot(z/2) = Σ_n (−1)ⁿ B_{2n} z^{2n}/(2n)!: c_n = (−1)ⁿ B_{2n+2}/(2n+2)!,
    i.e. 1/12, 1/720, 1/30240, 1/1209600, ...
    """
    b = _bernoulli(2 * n_terms)
    return [(-1) ** n * b[2 * n + 2] / math.factorial(2 * n + 2) for n in range(n_terms)]


def _validate(inertia: Sequence[float], order: int, chart: str) -> tuple[Fraction, ...]:
    try:
        vals = [float(v) for v in inertia]
    except (TypeError, ValueError) as exc:
        raise ValueError(f"inertia must be a sequence of 3 numbers, got {inertia!r}") from exc
    if len(vals) != 3:
        raise ValueError(f"inertia must have exactly 3 entries, got {len(vals)}")
    if not all(math.isfinite(v) and v > 0 for v in vals):
        raise ValueError(f"inertia entries must be finite and positive, got {vals}")
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)):
        raise ValueError(f"order must be an int, got {type(order).__name__}")
    if not 1 <= order <= MAX_ORDER:
        raise ValueError(f"order must satisfy 1 <= order <= {MAX_ORDER}, got {order}")
    if chart not in CHARTS:
        raise ValueError(f"chart must be one of {CHARTS}, got {chart!r}")
    # Fraction(float) is exact for binary floats, so S_k are the exact coefficients for the
    # inertia as represented in double precision.
    return tuple(Fraction(v) for v in vals)


def taylor_coefficients(
    inertia: Sequence[float], order: int, chart: str = "cayley"
) -> list[dict[Exponent, Fraction]]:
    """Exact Taylor coefficients S_1, ..., S_order of the generating function.

    Args:
        inertia: principal moments (I1, I2, I3), finite and positive.
        order: truncation order K, 1 <= K <= MAX_ORDER.
        chart: "cayley" or "exp" (groupoid chart defining the source map).

    Returns:
        List of length ``order``; entry k−1 maps exponents (a, b, c) to the exact coefficient of
        p1^a p2^b p3^c in S_k (zero coefficients omitted, so S_k = 0 gives ``{}``).

    Raises:
        ValueError: on invalid inertia, order or chart.
    """
    inv = [1 / i for i in _validate(inertia, order, chart)]
    half, quarter = Fraction(1, 2), Fraction(1, 4)
    p_vec: Vec = (_Poly.var(0), _Poly.var(1), _Poly.var(2))

    # Series in t are lists indexed by the power of t. Every quantity is built one coefficient at
    # a time: [t^m] of sou only needs X_1..X_m, and X_m = ∇S_m is known once S_m is, so each
    # step costs one new coefficient instead of recomputing whole truncated series.
    xs: list[Vec] = [_zero_vec()]  # X_j = ∇S_j, X_0 = 0
    dots: list[_Poly] = [_Poly()]  # d_j = X_j·p
    sig: list[Vec] = [p_vec]  # σ_m = [t^m] sou(X, p), σ_0 = p
    # Exp chart only: q = X·X, qpow[n] = q^{n+1}, v = X(X·p) − p(X·X) = X×(X×p), cs = c(q).
    c_n = _exp_chart_c(order // 2 + 1)
    q: list[_Poly] = [_Poly()]
    qpow: list[list[_Poly]] = []
    v: list[Vec] = [_zero_vec()]
    cs: list[_Poly] = [_Poly({(0, 0, 0): c_n[0]})]

    coeffs: list[_Poly] = []
    for k in range(1, order + 1):
        m = k - 1
        if m >= 1:
            xs.append(_grad(coeffs[m - 1]))
            dots.append(_dot_p(xs[m]))
            # Σ_{i+j=m} X_i (X_j·p); X_0 = 0 so i, j >= 1.
            xd = _zero_vec()
            for i in range(1, m):
                xd = _vadd(xd, _vmul(xs[i], dots[m - i]))
            s_m = _vscale(_cross_p(xs[m]), half)
            if chart == "cayley":
                s_m = _vadd(s_m, _vscale(xd, quarter))
            else:
                q_m = _Poly()
                for i in range(1, m):
                    q_m = q_m + _dot(xs[i], xs[m - i])
                q.append(q_m)
                # Powers of q: q^n starts at t^{2n}; extend each by its coefficient m.
                if 2 * (len(qpow) + 1) <= m:
                    qpow.append([_Poly()] * m)  # coefficient m appended below
                for n, qn in enumerate(qpow):
                    if n == 0:
                        qn.append(q_m)
                    else:
                        prev = qpow[n - 1]
                        acc = _Poly()
                        for a in range(2, m - 2 * n + 1):
                            acc = acc + q[a] * prev[m - a]
                        qn.append(acc)
                c_m = _Poly()
                for n, qn in enumerate(qpow):
                    c_m = c_m + qn[m].scale(c_n[n + 1])
                cs.append(c_m)
                v.append(_vadd(xd, (-p_vec[0] * q_m, -p_vec[1] * q_m, -p_vec[2] * q_m)))
                # [t^m] c(q)·v, with v = O(t²).
                for a in range(0, m - 1):
                    s_m = _vadd(s_m, _vmul(v[m - a], cs[a]))
            sig.append(s_m)
        # [t^m] H(σ) = ½ Σ_i (1/I_i) Σ_{a+b=m} σ_{a,i} σ_{b,i}
        h_m = _Poly()
        for i in range(3):
            acc = _Poly()
            for a in range(m + 1):
                acc = acc + sig[a][i] * sig[m - a][i]
            h_m = h_m + acc.scale(half * inv[i])
        coeffs.append(h_m.scale(Fraction(-1, k)))
    return [dict(sorted(c.terms.items())) for c in coeffs]


def taylor_terms(
    inertia: Sequence[float], order: int, chart: str = "cayley"
) -> tuple[np.ndarray, np.ndarray]:
    """Truncated S(t, p) = Σ_{k=1}^{order} tᵏ S_k(p) as flat arrays.

    Returns:
        powers: int64 array (n_terms, 4); row (k, a, b, c) stands for tᵏ p1^a p2^b p3^c.
        coeffs: float64 array (n_terms,), the coefficients rounded to double.
        Zero terms are dropped; rows are sorted lexicographically by (k, a, b, c).
    """
    rows: list[tuple[int, int, int, int]] = []
    vals: list[float] = []
    for k, s_k in enumerate(taylor_coefficients(inertia, order, chart), start=1):
        for (a, b, c), coef in sorted(s_k.items()):
            rows.append((k, a, b, c))
            vals.append(float(coef))
    powers = np.array(rows, dtype=np.int64).reshape(-1, 4)
    return powers, np.array(vals, dtype=np.float64)


def evaluate_terms(
    powers: np.ndarray, coeffs: np.ndarray, t: np.ndarray | float, p: np.ndarray
) -> np.ndarray:
    """Evaluate Σ_n coeffs[n] t^k p1^a p2^b p3^c with (k, a, b, c) = powers[n].

    Args:
        powers: int array (n_terms, 4).
        coeffs: float array (n_terms,).
        t: times, shape (...,) (broadcast against p's leading shape).
        p: momenta, shape (..., 3).

    Returns:
        float64 array with the broadcast shape of t and p[..., 0].
    """
    powers = np.asarray(powers, dtype=np.int64)
    coeffs = np.asarray(coeffs, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)[..., None]
    p = np.asarray(p, dtype=np.float64)
    # Trailing axis runs over terms; broadcasting handles the batch shape.
    mono = (
        t ** powers[:, 0]
        * p[..., 0:1] ** powers[:, 1]
        * p[..., 1:2] ** powers[:, 2]
        * p[..., 2:3] ** powers[:, 3]
    )
    return mono @ coeffs

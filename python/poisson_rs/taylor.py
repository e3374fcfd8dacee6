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

:func:`lie_taylor_coefficients` does the same for any polynomial Hamiltonian on the dual g* of any
Lie algebra given by its structure constants, in the exponential chart of T*G, where

    sou(x, p) = (ad_x/(e^{ad_x} − 1))ᵀ p = Σ_n (B_n/n!) Aⁿ p,   A = ad_xᵀ,
    (A v)_j = Σ_{i,k} c[i,j,k] x_i v_k,   B_n = 1, −1/2, 1/12, 0, −1/720, ...

On so(3) (c = Levi-Civita) this is the "exp" chart above: A p = −x×p.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from fractions import Fraction
from typing import Any

import numpy as np

__all__ = [
    "CHARTS",
    "MAX_ORDER",
    "MAX_WORK",
    "evaluate_terms",
    "lie_taylor_coefficients",
    "lie_taylor_terms",
    "system_taylor_terms",
    "taylor_coefficients",
    "taylor_terms",
]

#: Largest supported truncation order (S_15 has degree 16 and 153 monomials; exact arithmetic
#: stays well under a second up to here).
MAX_ORDER = 15
#: Supported groupoid charts.
CHARTS = ("cayley", "exp")

#: Budget of exact coefficient products (one monomial times one monomial) for
#: :func:`lie_taylor_coefficients`; about 10 s of pure-Python big-integer work. Exceeding it
#: raises a ValueError naming the order that is too large, instead of running for minutes.
MAX_WORK = 20_000_000

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


# ---------------------------------------------------------------------------------------------
# Any Lie–Poisson system: structure constants + polynomial Hamiltonian, exponential chart
# ---------------------------------------------------------------------------------------------

GeneralExponent = tuple[int, ...]


class _QPoly:
    """Exact sparse polynomial Σ_e num[e] pᵉ / den with integer numerators.

    An exponent vector is packed into one int (``width`` bits per variable), so a monomial
    product is one integer addition; a shared denominator keeps the inner loops on Python ints,
    which is an order of magnitude faster than ``Fraction`` arithmetic term by term.
    """

    __slots__ = ("den", "num")

    def __init__(self, num: dict[int, int], den: int = 1) -> None:
        self.num = num
        self.den = den


_ZERO = _QPoly({})


class _Work:
    """Counts monomial products against :data:`MAX_WORK`; names the order that is too large."""

    __slots__ = ("done", "k", "order")

    def __init__(self, order: int) -> None:
        self.done = 0
        self.k = 1
        self.order = order

    def charge(self, n: int) -> None:
        self.done += n
        if self.done > MAX_WORK:
            raise ValueError(
                f"order {self.order} is too large for this system: computing S_{self.k} exceeds "
                f"the exact-arithmetic budget of {MAX_WORK} monomial products; use order <= "
                f"{self.k - 1} (or a Hamiltonian with fewer or lower-degree terms)"
            )


def _combo(parts: list[tuple[Fraction, _QPoly, _QPoly | None]], work: _Work) -> _QPoly:
    """Σ s·a·b over ``parts`` (b = None means the factor 1), reduced to lowest terms."""
    parts = [(s, a, b) for s, a, b in parts if s and a.num and (b is None or b.num)]
    if not parts:
        return _ZERO
    dens = [s.denominator * a.den * (1 if b is None else b.den) for s, a, b in parts]
    den = math.lcm(*dens)
    out: dict[int, int] = {}
    get = out.get
    for (s, a, b), d in zip(parts, dens, strict=True):
        mult = s.numerator * (den // d)
        if b is None:
            for e, c in a.num.items():
                out[e] = get(e, 0) + mult * c
            continue
        work.charge(len(a.num) * len(b.num))
        for ea, ca in a.num.items():
            ca *= mult
            for eb, cb in b.num.items():
                e = ea + eb
                out[e] = get(e, 0) + ca * cb
    out = {e: c for e, c in out.items() if c}
    if not out:
        return _ZERO
    g = math.gcd(den, *out.values())
    if g > 1:
        out = {e: c // g for e, c in out.items()}
        den //= g
    return _QPoly(out, den)


def _qdiff(f: _QPoly, i: int, width: int) -> _QPoly:
    """∂f/∂p_i on packed exponents."""
    shift, mask = i * width, (1 << width) - 1
    out = {}
    for e, c in f.num.items():
        a = (e >> shift) & mask
        if a:
            out[e - (1 << shift)] = c * a
    if not out:
        return _ZERO
    g = math.gcd(f.den, *out.values())
    return _QPoly({e: c // g for e, c in out.items()}, f.den // g)


def _unpack(e: int, n: int, width: int) -> GeneralExponent:
    mask = (1 << width) - 1
    return tuple((e >> (i * width)) & mask for i in range(n))


def _exact(v: object, what: str) -> Fraction:
    """Exact rational value of a finite real number (floats converted bit for bit)."""
    if isinstance(v, (bool, np.bool_)):
        raise ValueError(f"{what} must be a real number, got {v!r}")
    if isinstance(v, (int, np.integer, Fraction)):
        return Fraction(int(v)) if not isinstance(v, Fraction) else v
    try:
        f = float(v)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what} must be a real number, got {v!r}") from exc
    if not math.isfinite(f):
        raise ValueError(f"{what} must be finite, got {f}")
    return Fraction(f)


def _validate_lie(
    structure_constants: object, hamiltonian: object, order: int
) -> tuple[int, dict[tuple[int, int, int], Fraction], dict[GeneralExponent, Fraction]]:
    """Checks the inputs of :func:`lie_taylor_coefficients`.

    Returns:
        n, the nonzero structure constants {(i, j, k): c[i,j,k]} (exact), and the nonzero terms of
        H {exponent tuple of length n: coefficient} (exact).
    """
    try:
        c = np.asarray(structure_constants, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(
            f"structure_constants must be a real array of shape (n, n, n): {exc}"
        ) from exc
    if c.ndim != 3 or c.shape[0] == 0 or not c.shape[0] == c.shape[1] == c.shape[2]:
        raise ValueError(f"structure_constants must have shape (n, n, n), n >= 1, got {c.shape}")
    if not np.all(np.isfinite(c)):
        raise ValueError("structure_constants must be finite")
    n = c.shape[0]
    scale = float(np.max(np.abs(c))) if c.size else 0.0
    # The bracket must be a Lie bracket, else sou is not the source map of a groupoid. The
    # tolerances allow constants obtained by a floating-point change of basis.
    if np.max(np.abs(c + c.transpose(1, 0, 2)), initial=0.0) > 1e-12 * scale:
        raise ValueError("structure_constants must be antisymmetric: c[i,j,k] = -c[j,i,k]")

    # Jacobi on a few seeded random triples: O(n³) each, unlike the O(n⁵) full tensor, and a
    # violation survives a random triple with probability 1.
    def br(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.einsum("ijk,i,j->k", c, u, v)

    rng = np.random.default_rng(0)
    for _ in range(3):
        x, y, z = rng.standard_normal((3, n))
        jac = br(x, br(y, z)) + br(y, br(z, x)) + br(z, br(x, y))
        if np.max(np.abs(jac)) > 1e-10 * scale**2 * n**2:
            raise ValueError("structure_constants violate the Jacobi identity")
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)):
        raise ValueError(f"order must be an int, got {type(order).__name__}")
    if not 1 <= order <= MAX_ORDER:
        raise ValueError(f"order must satisfy 1 <= order <= {MAX_ORDER}, got {order}")
    if not isinstance(hamiltonian, Mapping):
        raise ValueError(
            "hamiltonian must be a mapping {exponent tuple of length n: coefficient}, "
            f"got {type(hamiltonian).__name__}"
        )
    terms: dict[GeneralExponent, Fraction] = {}
    for key, val in hamiltonian.items():
        if not isinstance(key, tuple) or len(key) != n:
            raise ValueError(
                f"hamiltonian keys must be exponent tuples of length n = {n}, got {key!r}"
            )
        if not all(
            isinstance(a, (int, np.integer)) and not isinstance(a, (bool, np.bool_)) and a >= 0
            for a in key
        ):
            raise ValueError(f"hamiltonian exponents must be non-negative ints, got {key!r}")
        e = tuple(int(a) for a in key)
        coef = _exact(val, f"hamiltonian coefficient of {e}")
        if coef:
            terms[e] = terms.get(e, Fraction(0)) + coef
    consts = {
        (i, j, k): Fraction(float(c[i, j, k])) for i, j, k in zip(*np.nonzero(c), strict=True)
    }
    return n, consts, {e: v for e, v in terms.items() if v}


def lie_taylor_coefficients(
    structure_constants: object, hamiltonian: Mapping[tuple[int, ...], float], order: int
) -> list[dict[GeneralExponent, Fraction]]:
    """Exact Taylor coefficients S_1..S_K of the generating function on any Lie–Poisson g*.

    Solves ∂S/∂t + H(sou(∂S/∂p, p)) = 0, S(0, p) = 0, in the exponential chart of T*G, where
    sou(x, p) = (ad_x/(e^{ad_x} − 1))ᵀ p, for a polynomial Hamiltonian (any degree, not
    necessarily homogeneous). On so(3) with H = ½ Σ pᵢ²/Iᵢ it equals
    ``taylor_coefficients(inertia, order, "exp")``.

    Args:
        structure_constants: array-like (n, n, n), [e_i, e_j] = Σ_k c[i,j,k] e_k; finite,
            antisymmetric in (i, j) and satisfying the Jacobi identity.
        hamiltonian: {exponent tuple (a_1..a_n): coefficient} for H(p) = Σ coef · Π p_i^{a_i}.
            Coefficients are finite reals: floats are converted exactly with ``Fraction(float)``,
            ints and Fractions are used as they are (so 1/3 can be given exactly).
        order: truncation order K, 1 <= K <= MAX_ORDER.

    Returns:
        List of length K; entry k−1 maps exponent tuples (length n) to the exact coefficient of
        that monomial in S_k (zeros omitted, keys sorted).

    Raises:
        ValueError: on invalid inputs, or when the exact computation would exceed MAX_WORK
            monomial products (the message names the order that is too large).
    """
    n, consts, h_terms = _validate_lie(structure_constants, hamiltonian, order)
    work = _Work(order)
    # Degree bound: deg S_k <= k(d − 1) + 1 for deg H = d, and every intermediate polynomial up
    # to [t^{K−1}] H(σ) obeys the same bound, so `width` bits per variable never overflow.
    d = max((sum(e) for e in h_terms), default=0)
    width = max(1, order * (d - 1) + 1).bit_length() + 1
    one = Fraction(1)
    p_vec = [_QPoly({1 << (i * width): 1}) for i in range(n)]
    # Series in t are lists indexed by the power of t; coefficient m of every series needs only
    # X_1..X_m, so each order adds one coefficient instead of recomputing truncated series.
    bern = _bernoulli(order)
    weights = [bern[m] / math.factorial(m) for m in range(order + 1)]
    # mats[j][a][b] = (A_j)_{ab} = Σ_i c[i,a,b] X_{j,i}, with X_j = ∇S_j (mats[0] unused).
    mats: list[list[list[_QPoly]]] = [[]]
    by_entry: dict[tuple[int, int], list[tuple[int, Fraction]]] = {}
    for (i, a, b), val in consts.items():
        by_entry.setdefault((a, b), []).append((i, val))
    # w[r][m − r] = [t^m] A^r p (A = O(t), so A^r p starts at t^r); w[0] = [p].
    w: list[list[list[_QPoly]]] = [[p_vec]]
    sigma: list[list[_QPoly]] = [p_vec]  # σ_m = [t^m] sou as a vector of n polynomials
    # H(σ) monomial by monomial; a monomial is the sorted tuple of its variables with
    # multiplicity, and prods[f][m] = [t^m] Π_{i ∈ f} σ_i shares work between common prefixes.
    factors = {e: tuple(i for i, a in enumerate(e) for _ in range(a)) for e in h_terms}
    prefixes = sorted({f[:r] for f in factors.values() for r in range(2, len(f) + 1)}, key=len)
    prods: dict[tuple[int, ...], list[_QPoly]] = {(): [_QPoly({0: 1})]}

    coeffs: list[_QPoly] = []
    for k in range(1, order + 1):
        work.k = k
        m = k - 1
        if m >= 1:
            x_m = [_qdiff(coeffs[m - 1], i, width) for i in range(n)]
            mats.append(
                [
                    [
                        _combo([(v, x_m[i], None) for i, v in by_entry.get((a, b), [])], work)
                        for b in range(n)
                    ]
                    for a in range(n)
                ]
            )
            # [t^m] A^r p = Σ_{j=1}^{m−r+1} A_j [t^{m−j}] A^{r−1} p, stored as w[r][m − r]
            # (A^0 p = p has only its t^0 coefficient, so r = 1 takes j = m alone). On the last
            # order the odd powers r >= 3 (B_r = 0) are not needed for later ones, so skip them.
            w.append([])
            for r in range(1, m + 1):
                js = range(m, m + 1) if r == 1 else range(1, m - r + 2)
                if k == order and r >= 3 and r % 2:
                    w[r].append([_ZERO] * n)
                    continue
                w[r].append(
                    [
                        _combo(
                            [
                                (one, mats[j][a][b], w[r - 1][m - j - (r - 1)][b])
                                for j in js
                                for b in range(n)
                            ],
                            work,
                        )
                        for a in range(n)
                    ]
                )
            sigma.append(
                [
                    _combo([(weights[r], w[r][m - r][a], None) for r in range(1, m + 1)], work)
                    for a in range(n)
                ]
            )
        for f in prefixes:
            head = prods[f[:-1]] if len(f) > 2 else [sg[f[0]] for sg in sigma]
            prods.setdefault(f, []).append(
                _combo([(one, head[a], sigma[m - a][f[-1]]) for a in range(m + 1)], work)
            )
        parts: list[tuple[Fraction, _QPoly, _QPoly | None]] = []
        for e, h in h_terms.items():
            f = factors[e]
            if len(f) == 0:
                if m == 0:
                    parts.append((h, prods[()][0], None))
            elif len(f) == 1:
                parts.append((h, sigma[m][f[0]], None))
            else:
                parts.append((h, prods[f][m], None))
        # k S_k = −[t^{k−1}] H(σ)
        coeffs.append(_combo([(Fraction(-1, k), _combo(parts, work), None)], work))
    return [
        dict(sorted((_unpack(e, n, width), Fraction(c, s.den)) for e, c in s.num.items()))
        for s in coeffs
    ]


def lie_taylor_terms(
    structure_constants: object, hamiltonian: Mapping[tuple[int, ...], float], order: int
) -> tuple[np.ndarray, np.ndarray]:
    """Truncated S(t, p) = Σ_{k=1}^{order} tᵏ S_k(p) of :func:`lie_taylor_coefficients`, flat.

    Returns:
        powers: int64 array (n_terms, 1 + n); row (k, e_1..e_n) stands for tᵏ Π p_i^{e_i}.
        coeffs: float64 array (n_terms,), the coefficients rounded to double.
        Zero terms are dropped; rows are sorted lexicographically.
    """
    exact = lie_taylor_coefficients(structure_constants, hamiltonian, order)
    n = np.asarray(structure_constants, dtype=np.float64).shape[0]
    # Each S_k is already sorted by exponent, so rows come out sorted by (k, e_1..e_n).
    rows = [(k, *e) for k, s_k in enumerate(exact, start=1) for e in s_k]
    vals = [float(c) for s_k in exact for c in s_k.values()]
    return np.array(rows, dtype=np.int64).reshape(-1, 1 + n), np.array(vals, dtype=np.float64)


def _levi_civita_constants(c: np.ndarray) -> bool:
    eps = np.zeros((3, 3, 3))
    for i, j, k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        eps[i, j, k], eps[j, i, k] = 1.0, -1.0
    return c.shape == (3, 3, 3) and bool(np.array_equal(c, eps))


def system_taylor_terms(
    system: Any, order: int, chart: str = "exp"
) -> tuple[np.ndarray, np.ndarray]:
    """Taylor terms (powers (n_terms, 1 + n), coeffs (n_terms,)) for a Lie–Poisson system.

    ``system`` needs ``algebra.c`` (structure constants (n, n, n)) and ``polynomial.terms``
    ({exponent tuple: coefficient}), as
    :class:`poisson_rs.structures.lie_poisson.LiePoissonSystem` has. A
    rigid body on so(3) (H = Σ w_i p_i², w_i > 0, nothing else) goes through
    :func:`taylor_terms` with I_i = 1/(2 w_i), or the ``inertia`` attribute when there is one,
    so the old exact 1/I_i and the Cayley chart are kept; every other system uses
    :func:`lie_taylor_terms`, which only has the exponential chart.

    Raises:
        ValueError: on a bad chart or order, a chart the system does not support, or invalid
            structure constants or Hamiltonian.
    """
    if chart not in CHARTS:
        raise ValueError(f"chart must be one of {CHARTS}, got {chart!r}")
    c = np.asarray(system.algebra.c, dtype=np.float64)
    terms = {tuple(int(a) for a in e): v for e, v in system.polynomial.terms.items() if v}
    inertia = getattr(system, "inertia", None)
    if inertia is None and _levi_civita_constants(c):
        diag = [(2, 0, 0), (0, 2, 0), (0, 0, 2)]
        if set(terms) == set(diag) and all(float(terms[e]) > 0 for e in diag):
            inertia = tuple(1 / (2 * float(terms[e])) for e in diag)
    if inertia is not None and _levi_civita_constants(c):
        return taylor_terms(inertia, order, chart)
    if chart != "exp":
        raise ValueError(
            f"chart {chart!r} is only available for the rigid body on so(3); use 'exp' here"
        )
    return lie_taylor_terms(c, terms, order)


def evaluate_terms(
    powers: np.ndarray, coeffs: np.ndarray, t: np.ndarray | float, p: np.ndarray
) -> np.ndarray:
    """Evaluate Σ_m coeffs[m] tᵏ Π_i p_i^{e_i} with (k, e_1..e_n) = powers[m], for any n.

    Args:
        powers: int array (n_terms, 1 + n), as returned by :func:`taylor_terms` (n = 3) or
            :func:`lie_taylor_terms`.
        coeffs: float array (n_terms,).
        t: times, shape (...,) (broadcast against p's leading shape).
        p: momenta, shape (..., n).

    Returns:
        float64 array with the broadcast shape of t and p[..., 0].

    Raises:
        ValueError: if the shapes of powers, coeffs and p do not agree.
    """
    powers = np.asarray(powers, dtype=np.int64)
    coeffs = np.asarray(coeffs, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)[..., None]
    p = np.asarray(p, dtype=np.float64)
    if powers.ndim != 2 or powers.shape[1] < 1 or coeffs.shape != (powers.shape[0],):
        raise ValueError(
            f"powers must be (n_terms, 1 + n) and coeffs (n_terms,), got {powers.shape} and "
            f"{coeffs.shape}"
        )
    n = powers.shape[1] - 1
    if p.ndim < 1 or p.shape[-1] != n:
        raise ValueError(f"p must have shape (..., {n}) to match powers, got {p.shape}")
    # Trailing axis runs over terms; broadcasting handles the batch shape. Factors multiply left
    # to right (t, p_1, p_2, ...), as before the generalisation, so n = 3 results are unchanged.
    mono = t ** powers[:, 0]
    for i in range(n):
        mono = mono * p[..., i : i + 1] ** powers[:, 1 + i]
    return mono @ coeffs

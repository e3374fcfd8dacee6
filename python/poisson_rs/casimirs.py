"""Polynomial Casimirs of any Lie algebra, found as a null space, and the Casimir values the
studies record for any system.

A polynomial C on g* is a Casimir when {C, μ_i} = 0 for every coordinate, i.e.

    Σ_{j,k} c[i,j,k] μ_k ∂C/∂μ_j = 0   for i = 1 … n,

with c the structure constants ([e_i, e_j] = Σ_k c[i,j,k] e_k). The condition maps homogeneous
polynomials of degree d to homogeneous ones of degree d, so the Casimirs of degree d are the null
space of one matrix in the monomial coefficients (the invariants of the coadjoint action), and
every polynomial Casimir is a sum of homogeneous ones. :func:`polynomial_casimirs` returns, degree
by degree, a basis of the new ones: those that are not polynomials in the Casimirs of lower
degree (so (|μ|²)² is not listed again at degree 4).

>>> from poisson_rs import LieAlgebra
>>> [sorted(c.terms.items()) for c in polynomial_casimirs(LieAlgebra.so3(), 2)]
[[((0, 0, 2), 1.0), ((0, 2, 0), 1.0), ((2, 0, 0), 1.0)]]
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from .structures.algebra import LieAlgebra, Polynomial

__all__ = ["casimir_degrees", "casimir_values", "polynomial_casimirs", "system_casimirs"]

#: Highest degree searched when a system's Casimirs are not known in closed form.
DEFAULT_DEGREE = 4
#: Most monomials of one degree the search builds a matrix for (dim 6, degree 4: 126).
MAX_MONOMIALS = 2000
#: Singular values below this (relative to the largest) span the null space.
RTOL = 1e-10


def _monomials(dim: int, degree: int) -> list[tuple[int, ...]]:
    """Exponent tuples of the monomials of exactly ``degree`` in ``dim`` variables (graded
    lexicographic, largest first)."""
    out = []
    for combo in itertools.combinations_with_replacement(range(dim), degree):
        powers = [0] * dim
        for v in combo:
            powers[v] += 1
        out.append(tuple(powers))
    return out


def _condition_matrix(c: np.ndarray, degree: int) -> tuple[np.ndarray, list[tuple[int, ...]]]:
    """The matrix A with A·a = 0 ⇔ C = Σ a_α μ^α (degree ``degree``) is a Casimir."""
    dim = c.shape[0]
    monos = _monomials(dim, degree)
    index = {m: r for r, m in enumerate(monos)}
    a = np.zeros((dim * len(monos), len(monos)))
    for col, alpha in enumerate(monos):
        for j in range(dim):
            if alpha[j] == 0:
                continue
            # ∂(μ^α)/∂μ_j = α_j μ^(α − e_j), times μ_k: the monomial α − e_j + e_k.
            for i in range(dim):
                for k in range(dim):
                    coef = c[i, j, k]
                    if coef == 0.0:
                        continue
                    beta = list(alpha)
                    beta[j] -= 1
                    beta[k] += 1
                    a[i * len(monos) + index[tuple(beta)], col] += coef * alpha[j]
    return a, monos


def _null_space(a: np.ndarray) -> np.ndarray:
    """Orthonormal basis of the null space of ``a`` as columns."""
    if a.size == 0:
        return np.eye(a.shape[1])
    _, s, vt = np.linalg.svd(a)
    scale = s[0] if len(s) and s[0] > 0 else 1.0
    rank = int(np.sum(s > RTOL * scale))
    return np.ascontiguousarray(vt[rank:].T)


def _rref_columns(basis: np.ndarray) -> np.ndarray:
    """The columns of ``basis`` replaced by a reduced row-echelon basis of their span (each with
    a leading 1): readable coefficients such as 1, 1, 1 for |μ|²."""
    m = basis.T.copy()
    rows, cols = m.shape
    r = 0
    for col in range(cols):
        if r == rows:
            break
        pivot = r + int(np.argmax(np.abs(m[r:, col])))
        if abs(m[pivot, col]) < 1e-9:
            continue
        m[[r, pivot]] = m[[pivot, r]]
        m[r] /= m[r, col]
        for other in range(rows):
            if other != r:
                m[other] -= m[other, col] * m[r]
        r += 1
    # Round-off off the readable coefficients (1.0000000000000002 → 1.0).
    m = np.round(m, 12)
    m[np.abs(m) < 1e-12] = 0.0
    return m[:r].T


def _as_vector(poly: Polynomial, monos: Sequence[tuple[int, ...]]) -> np.ndarray:
    index = {m: r for r, m in enumerate(monos)}
    v = np.zeros(len(monos))
    for powers, coef in poly.terms.items():
        v[index[powers]] = coef
    return v


def _product(p: Polynomial, q: Polynomial) -> Polynomial:
    terms: dict[tuple[int, ...], float] = {}
    for (a, x), (b, y) in itertools.product(p.terms.items(), q.terms.items()):
        key = tuple(i + j for i, j in zip(a, b, strict=True))
        terms[key] = terms.get(key, 0.0) + x * y
    return Polynomial({k: v for k, v in terms.items() if v != 0.0})


def polynomial_casimirs(algebra: LieAlgebra, max_degree: int = DEFAULT_DEGREE) -> list[Polynomial]:
    """A basis of the homogeneous polynomial Casimirs of g* up to ``max_degree``, without the
    products of lower-degree ones; [] when there are none (a solvable algebra may have none).

    Parameters
    ----------
    algebra : LieAlgebra
    max_degree : int, 1 … 12

    Returns
    -------
    list of Polynomial, in increasing degree; coefficients in reduced row-echelon form.
    """
    if not isinstance(algebra, LieAlgebra):
        raise TypeError(f"algebra must be a LieAlgebra, got {type(algebra).__name__}")
    if isinstance(max_degree, bool) or not isinstance(max_degree, int) or not 1 <= max_degree <= 12:
        raise ValueError(f"max_degree must be an integer in [1, 12], got {max_degree!r}")
    c = algebra.c
    dim = algebra.dim
    found: list[Polynomial] = []
    for degree in range(1, max_degree + 1):
        if math.comb(dim + degree - 1, degree) > MAX_MONOMIALS:
            break
        a, monos = _condition_matrix(c, degree)
        null = _null_space(a)
        if null.shape[1] == 0:
            continue
        # Products of lower-degree Casimirs of total degree ``degree``: not new.
        old = [_as_vector(p, monos) for p in _products_of_degree(found, degree)]
        if old:
            q, _ = np.linalg.qr(np.array(old).T)
            rank = np.linalg.matrix_rank(np.array(old).T)
            q = q[:, :rank]
            null = null - q @ (q.T @ null)
            u, s, _ = np.linalg.svd(null, full_matrices=False)
            keep = s > 1e-8
            null = u[:, keep]
        if null.shape[1] == 0:
            continue
        for col in _rref_columns(null).T:
            terms = {monos[r]: float(v) for r, v in enumerate(col) if v != 0.0}
            found.append(Polynomial(terms))
    return found


def _products_of_degree(polys: Sequence[Polynomial], degree: int) -> list[Polynomial]:
    """Every product of the (homogeneous) ``polys`` whose degree is ``degree``."""
    out: list[Polynomial] = []

    def extend(start: int, current: Polynomial | None, d: int) -> None:
        if d == degree and current is not None:
            out.append(current)
            return
        for idx in range(start, len(polys)):
            p = polys[idx]
            if d + p.degree <= degree:
                extend(idx, p if current is None else _product(current, p), d + p.degree)

    extend(0, None, 0)
    return out


_CACHE: dict[LieAlgebra, list[Polynomial]] = {}


def system_casimirs(
    system: Any, max_degree: int = DEFAULT_DEGREE
) -> Callable[[np.ndarray], np.ndarray] | None:
    """The Casimirs a study records for ``system``: a function μ (..., n) → (..., m), or None
    when none is known or found up to ``max_degree``.

    The system's own ``casimirs`` first (closed forms for so(3), se(3), sl(2), or whatever a
    user's system class returns); else, for a Lie–Poisson system, the polynomial Casimirs of
    its algebra from :func:`polynomial_casimirs` (computed once per algebra)."""
    own = getattr(system, "casimirs", None)
    if own is not None:
        probe = own(np.ones((1, int(system.dim))))
        if probe is not None:
            return lambda mu: np.asarray(own(mu), dtype=np.float64)
    # A system on g* (Lie–Poisson) offers its algebra's polynomial Casimirs, searched once.
    found = getattr(system, "found_casimirs", None)
    polys = found(max_degree) if found is not None else []
    if not polys:
        return None
    return lambda mu: np.stack([p(np.asarray(mu, dtype=np.float64)) for p in polys], -1)


def casimir_degrees(system: Any) -> tuple[int, ...] | None:
    """The degree of each Casimir of :func:`system_casimirs` (used to scale drifts by |μ₀|^d),
    or None when there is none."""
    fn = system_casimirs(system)
    if fn is None:
        return None
    # A system whose Casimirs are not homogeneous polynomials says how to scale them (0: the
    # log-form Casimirs Σ k_i ln x_i of a log-canonical system, whose drift is absolute).
    own = getattr(system, "casimir_degrees", None)
    if own is not None:
        return tuple(int(d) for d in own)
    # Homogeneous: C(2μ) = 2^d C(μ) at a generic point.
    rng = np.random.default_rng(0)
    mu = rng.normal(size=(1, int(system.dim)))
    c1, c2 = fn(mu)[0], fn(2.0 * mu)[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.log2(np.abs(c2) / np.abs(c1))
    return tuple(round(float(x)) if np.isfinite(x) else 2 for x in d)


def casimir_values(system: Any, mu: Any) -> np.ndarray | None:
    """Casimirs of ``system`` at ``mu`` (..., n) → (..., m), or None when none is known."""
    fn = system_casimirs(system)
    return None if fn is None else fn(np.asarray(mu, dtype=np.float64))


def max_casimir_drift(system: Any, traj: np.ndarray) -> np.ndarray:
    """Largest |C − C₀| / |μ₀|^d over the system's Casimirs (d: each one's degree), per
    trajectory and record: traj (n, records, dim) → (n, records). NaN where no Casimir is known
    (an unknown invariant is not reported as kept)."""
    traj = np.asarray(traj, dtype=np.float64)
    fn = system_casimirs(system)
    if fn is None:
        return np.full(traj.shape[:-1], np.nan)
    degrees = np.asarray(casimir_degrees(system), dtype=np.float64)
    c = fn(traj)  # (n, records, m)
    norm0 = np.linalg.norm(traj[:, :1], axis=-1, keepdims=True)  # (n, 1, 1)
    scale = norm0**degrees
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.max(np.abs(c - c[:, :1]) / scale, axis=-1)


def algebra_casimirs(algebra: LieAlgebra, max_degree: int = DEFAULT_DEGREE) -> list[Polynomial]:
    """:func:`polynomial_casimirs` of ``algebra``, computed once per algebra (or the ones
    :func:`set_casimirs` recorded)."""
    if algebra not in _CACHE:
        _CACHE[algebra] = polynomial_casimirs(algebra, max_degree)
    return _CACHE[algebra]


def casimir_label(system: Any) -> str:
    """What the Casimir drift measures, for axis labels: the system's own ``casimir_label``
    ("C = |Γ|², M·Γ", ...), or "no Casimir known"."""
    label = getattr(system, "casimir_label", None)
    if isinstance(label, str):
        return label
    if system_casimirs(system) is None:
        return "no Casimir known (drift n/a)"
    return "the system's Casimirs"


def set_casimirs(algebra: LieAlgebra, casimirs: Sequence[Polynomial]) -> None:
    """Use ``casimirs`` (homogeneous polynomials) for every system on ``algebra`` whose own
    ``casimirs`` returns None, instead of searching: a user's own invariants. Each is checked:
    ValueError when one is not a Casimir of ``algebra``."""
    polys = list(casimirs)
    rng = np.random.default_rng(0)
    mu = rng.normal(size=(8, algebra.dim))
    c = algebra.c
    for p in polys:
        if not isinstance(p, Polynomial) or p.dim != algebra.dim:
            raise ValueError(f"each Casimir must be a Polynomial in {algebra.dim} variables")
        grad = p.gradient(mu)  # (8, n)
        bracket = np.einsum("ijk,sk,sj->si", c, mu, grad)
        size = np.abs(grad).max() * np.abs(mu).max() * max(np.abs(c).max(), 1.0)
        if np.abs(bracket).max() > 1e-9 * max(size, 1.0):
            raise ValueError(f"{p!r} is not a Casimir of {algebra!r}: {{C, μ_i}} ≠ 0")
        if not p.is_homogeneous(p.degree):
            raise ValueError(f"{p!r} is not homogeneous: give each degree separately")
    _CACHE[algebra] = polys

"""Recognising the exact structure behind a polynomial bivector.

A :class:`~poisson_rs.structures.polynomial.PolynomialBivector` gets an order-n approximate
realization, which keeps Casimirs only to O(h^{n+1}) a step. Three families have an exact
symplectic groupoid instead, and :func:`recognize` finds them from the entries:

- **Lie–Poisson**: every π_ij is a linear form Σ_k a_ijk x_k. In the package's convention
  ({x_i, x_j} = −Σ_k c_ijk x_k, ẋ = π∇H; :class:`~poisson_rs.LiePoissonSystem`) the structure
  constants are c_ijk = −a_ijk.
- **Affine**: linear plus a constant ω_ij (the cocycle): {x_i, x_j} = −Σ_k c_ijk x_k + ω_ij,
  integrated on the central extension (:mod:`poisson_rs.structures.affine`).
- **Log-canonical**: π_ij = c_ij x_i x_j (:class:`~poisson_rs.LogCanonical`).

Each candidate is the part of π of that form (its coefficients read off exactly); the relative
residual is max|π − π_fit| / max|π| over seeded points in [−2, 2]^n. A candidate is accepted
when its residual is at most ``tol`` and its data pass their own checks (Jacobi of c to 1e-12,
the cocycle condition); anything else keeps the order-n realization, and the note says how far
the closest form was.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["KINDS", "Recognition", "recognize"]

#: The exact families :func:`recognize` finds, in the order it prefers them.
KINDS = ("lie_poisson", "affine", "log_canonical")

#: Seeded points at which the residuals are measured.
_N_POINTS = 64

_CACHE: dict[tuple[Any, float], Recognition] = {}

#: {(i, j): {exponents: coefficient}}: the entries above the diagonal, term by term.
Terms = dict[tuple[int, int], dict[tuple[int, ...], float]]


@dataclass(frozen=True, eq=False)
class Recognition:
    """What :func:`recognize` found.

    ``kind``: "lie_poisson", "affine", "log_canonical", or None (no exact realization: the
    order-n one is used). ``data``: a :class:`~poisson_rs.LieAlgebra` (Lie–Poisson), a pair
    (LieAlgebra, cocycle ω as an (n, n) float64 array) (affine), a
    :class:`~poisson_rs.LogCanonical` (log-canonical), or None. ``residual``: the relative
    residual max|π − π_fit| / max|π| of the best-fitting form (0.0 for an exact match).
    ``note``: one line saying what was found, or how far the closest form was.
    """

    kind: str | None
    data: Any
    residual: float
    note: str


def _coefficients(
    bivector: Any,
) -> dict[tuple[int, int], dict[tuple[int, ...], float]]:
    """{(i, j): {exponents: coefficient}} for the entries above the diagonal."""
    import sympy

    out = {}
    n = bivector.dim
    for i in range(n):
        for j in range(i + 1, n):
            poly = sympy.Poly(bivector.pi[i, j], *bivector.x)
            out[(i, j)] = {e: float(c) for e, c in poly.terms() if c != 0}
    return out


def _evaluate(terms: Terms, pts: NDArray[np.float64]) -> NDArray[np.float64]:
    """The entries above the diagonal at ``pts`` (B, n) → (B, n(n−1)/2)."""
    cols = []
    for entry in terms.values():
        v = np.zeros(len(pts))
        for e, a in entry.items():
            v += a * np.prod(pts ** np.array(e, dtype=np.float64), axis=1)
        cols.append(v)
    return np.stack(cols, axis=1) if cols else np.zeros((len(pts), 0))


def recognize(bivector: Any, tol: float = 1e-10) -> Recognition:
    """The exact structure of ``bivector`` (Lie–Poisson, affine or log-canonical) when π is of
    that form to a relative residual ``tol``, else ``kind=None``; see the module docstring.
    Cached per bracket and tol."""
    # What a PolynomialBivector offers, checked by name: .polynomial imports this module.
    if not all(hasattr(bivector, a) for a in ("_key", "dim", "pi", "x")):
        raise TypeError(f"bivector must be a PolynomialBivector, got {type(bivector).__name__}")
    if isinstance(tol, bool) or not isinstance(tol, int | float) or not 0 <= tol < 1:
        raise ValueError(f"tol must be a number in [0, 1), got {tol!r}")
    key = (bivector._key, float(tol))
    if key not in _CACHE:
        _CACHE[key] = _recognize(bivector, float(tol))
    return _CACHE[key]


def _recognize(bivector: Any, tol: float) -> Recognition:
    n = bivector.dim
    terms = _coefficients(bivector)
    pts = np.random.default_rng(0).uniform(-2.0, 2.0, size=(_N_POINTS, n))
    full = _evaluate(terms, pts)
    size = float(np.abs(full).max(initial=0.0))
    # The part of π of each form, read off coefficient by coefficient.
    linear = {k: {e: a for e, a in t.items() if sum(e) == 1} for k, t in terms.items()}
    affine = {k: {e: a for e, a in t.items() if sum(e) <= 1} for k, t in terms.items()}
    log_c = {
        (i, j): {e: a for e, a in t.items() if e == tuple(int(m in (i, j)) for m in range(n))}
        for (i, j), t in terms.items()
    }
    fits = {"lie_poisson": linear, "affine": affine, "log_canonical": log_c}
    residual = {}
    for kind, fit in fits.items():
        # An exact match is 0.0, not a rounding-error difference of two evaluations.
        gap = 0.0 if fit == terms else float(np.abs(full - _evaluate(fit, pts)).max())
        residual[kind] = gap / size if size > 0 else 0.0
    refused: list[str] = []
    for kind in KINDS:
        if residual[kind] > tol:
            continue
        try:
            data = _build(kind, fits[kind], n)
        except ValueError as exc:  # e.g. Jacobi of c to 1e-12, the cocycle condition, bounds
            refused.append(f"{kind.replace('_', '-')} to {residual[kind]:.1e} but {exc}")
            continue
        label = kind.replace("_", "-")
        exact = (
            "exactly" if residual[kind] == 0.0 else f"to a relative residual {residual[kind]:.1e}"
        )
        return Recognition(kind, data, residual[kind], f"{label} {exact}")
    best = min(KINDS, key=lambda k: residual[k])
    note = (
        "not recognised: " + "; ".join(refused)
        if refused
        else f"not recognised: closest exact form {best.replace('_', '-')}, "
        f"{residual[best]:.1e} off (relative residual > tol {tol:.0e}); order-n realization"
    )
    return Recognition(None, None, residual[best], note)


def _build(kind: str, fit: Terms, n: int) -> Any:
    """The exact data of ``kind`` from the fitted coefficients (ValueError from their checks)."""
    from .affine import MAX_DIM, _check_cocycle
    from .lie_poisson import LieAlgebra
    from .log_canonical import LogCanonical

    if kind == "log_canonical":
        c = np.zeros((n, n))
        for (i, j), t in fit.items():
            c[i, j] = sum(t.values())
            c[j, i] = -c[i, j]
        return LogCanonical(c)
    c3 = np.zeros((n, n, n))
    omega = np.zeros((n, n))
    for (i, j), t in fit.items():
        for e, a in t.items():
            if sum(e) == 0:
                omega[i, j], omega[j, i] = a, -a
            else:
                k = e.index(1)
                # π_ij = Σ_k a_ijk x_k = −Σ_k c_ijk x_k.
                c3[i, j, k], c3[j, i, k] = -a, a
    algebra = LieAlgebra(c3)
    if kind == "lie_poisson":
        return algebra
    if n + 1 > MAX_DIM:
        raise ValueError(f"its central extension would have dimension {n + 1} > {MAX_DIM}")
    _check_cocycle(algebra.c, omega)
    omega.flags.writeable = False
    return algebra, omega


def exact_system(system: Any, tol: float = 1e-10) -> Any:
    """The exact system equivalent to a :class:`~poisson_rs.PolynomialPoissonSystem` (the same
    π and H): a LiePoissonSystem, an AffinePoissonSystem or a LogCanonicalSystem, or None when
    the bracket is none of them (:func:`recognize`) or H does not fit the exact system's
    Hamiltonian (a log-canonical H keeps its monomials x^k as exp(k·q) terms with b = 0; its
    constant term, which moves nothing, is dropped)."""
    import sympy

    from .affine import affine_poisson_system
    from .lie_poisson import LiePoissonSystem, Polynomial
    from .log_canonical import LogCanonicalSystem, LogPolynomial

    found = recognize(system.structure, tol)
    if found.kind is None:
        return None
    n = system.dim
    h_terms = {e: float(c) for e, c in sympy.Poly(system.h, *system.structure.x).terms()}
    try:
        if found.kind == "log_canonical":
            monomials = {e: a for e, a in h_terms.items() if any(e)}
            return LogCanonicalSystem(
                found.data,
                LogPolynomial(monomials, np.zeros(n)),
                name=system.name,
                component_names=system.component_names,
            )
        poly = Polynomial(h_terms or {(0,) * n: 0.0})
        if found.kind == "lie_poisson":
            return LiePoissonSystem(found.data, poly, name=system.name)
        algebra, omega = found.data
        return affine_poisson_system(
            algebra, omega, poly, name=system.name, component_names=system.component_names
        )
    except ValueError:
        # H outside the exact family's bounds (e.g. an exponent above 16, a coefficient above
        # 1e15): the order-n realization still integrates it.
        return None

"""Any polynomial Poisson bivector π(x) on R^n, checked on construction, with approximate
symplectic realizations of any order up to :data:`MAX_REALIZATION_ORDER` and a Taylor-HJ
integrator on them (stepped by the Rust core; NumPy Newton as its oracle).

- Antisymmetry is checked symbolically and the Jacobi identity
  π^{il}∂_lπ^{jk} + π^{jl}∂_lπ^{ki} + π^{kl}∂_lπ^{ij} = 0 at seeded random points: a bracket
  that fails is refused with an error naming the failing triple (i, j, k).
- The order-n realization (canonical {x^i, p_j} = δ^i_j, convention ẋ = π∇H):
  β = x + β_1 + … + β_n, β_k of degree k in p, solved order by order from the realization
  condition with the homotopy formula of the Poincaré lemma (:meth:`PolynomialBivector.
  realization_terms`); β_1 = −½π p, β_2 = (1/12)π^{lm}∂_lπ^{ij}p_m p_j; α(x, p) = β(x, −p).
  {β^i, β^j} − π^{ij}(β), {α^i, α^j} + π^{ij}(α) and {α^i, β^j} are then O(|p|^n), and a
  Casimir C has C(β) − C(α) = O(|p|^{n+1}) (n even) or O(|p|^{n+2}) (n odd: the defect is odd
  in p).
- The Taylor-HJ series S = Σ_{k≤m} t^k S_k of ∂S/∂t + H(β(x, ∇S)) = 0 is derived with sympy
  (:func:`hj_series`, truncated power series in t); a step solves α(x, ∇S(h, x)) = x_k by
  Newton and returns β(x, ∇S(h, x)). The scheme is symmetric: measured global order
  min(n, m) rounded up to even (m = 3 on n = 3: 4; m = 5 on n = 5: 6; any m on n = 2: 2).
- Nambu structures on R³, {f, g} = ∇C·(∇f × ∇g), i.e. π^{ij} = ε_ijk ∂_k C, satisfy Jacobi for
  any C and keep C: :meth:`PolynomialBivector.nambu`.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from ..protocols import NEWTON_MAX_ITER, NEWTON_TOL, PoissonSystemBase

FloatArray = NDArray[np.float64]
#: Highest order of the approximate realization built here (the recursion has no limit; sympy's
#: cost does: order 5 takes about 5 s on a cubic Nambu bracket, order 6 about 8 s).
MAX_REALIZATION_ORDER = 6
#: Highest Taylor-HJ order built on a realization (sympy's series cost).
MAX_TAYLOR_ORDER = 5

_REALIZATION_TERMS: dict[tuple[int, tuple[str, ...]], list[list[Any]]] = {}
_HJ_SERIES: dict[tuple[Any, ...], list[Any]] = {}


def _symbols(n: int) -> tuple[Any, ...]:
    import sympy

    return tuple(sympy.symbols(f"x1:{n + 1}", real=True))


def _lambdify(args: Sequence[Any], exprs: Sequence[Any]) -> Callable[..., FloatArray]:
    """A vectorised f(*columns) → (B, len(exprs)) from sympy expressions (constants broadcast)."""
    import sympy

    funcs = [sympy.lambdify(args, e, "numpy") for e in exprs]

    def f(*cols: FloatArray) -> FloatArray:
        shape = np.shape(cols[0])
        return np.stack([np.broadcast_to(g(*cols), shape).astype(np.float64) for g in funcs], -1)

    return f


class PolynomialBivector:
    """A polynomial Poisson bivector π on R^n.

    ``entries``: mapping (i, j) → polynomial (sympy expression or string in x1, …, xn) for the
    entries above the diagonal (i < j; an entry given at (j, i) must be the negative of
    (i, j)). Raises ValueError for a non-polynomial entry, a broken antisymmetry, or a failure
    of the Jacobi identity at seeded random points in [−2, 2]^n (naming the triple).
    """

    def __init__(self, dim: int, entries: Mapping[tuple[int, int], Any], *, seed: int = 0) -> None:
        import sympy

        if isinstance(dim, bool) or not isinstance(dim, int) or not 2 <= dim <= 10:
            raise ValueError(f"dim must be an integer in 2..=10, got {dim!r}")
        x = _symbols(dim)
        local = {f"x{i + 1}": s for i, s in enumerate(x)}
        pi = sympy.zeros(dim, dim)
        given: dict[tuple[int, int], Any] = {}
        for key, raw in dict(entries).items():
            i, j = key
            if not (0 <= i < dim and 0 <= j < dim) or i == j:
                raise ValueError(f"entry {key!r}: indices must be distinct and in 0..{dim - 1}")
            expr = sympy.sympify(raw, locals=local) if isinstance(raw, str) else sympy.sympify(raw)
            if not expr.free_symbols <= set(x) or not expr.is_polynomial(*x):
                raise ValueError(f"entry {key!r} = {raw!r} is not a polynomial in x1..x{dim}")
            given[(i, j)] = sympy.expand(expr)
        for (i, j), e in given.items():
            if (j, i) in given and sympy.expand(given[(j, i)] + e) != 0:
                raise ValueError(
                    f"pi must be antisymmetric: pi[{i},{j}] = {e} but pi[{j},{i}] = {given[(j, i)]}"
                )
            pi[i, j], pi[j, i] = e, -e
        self.dim = dim
        self.x = x
        self.pi = pi
        self._pi_num = _lambdify(x, list(pi))
        self._key = (dim, tuple(str(e) for e in pi))
        # Shared by every bivector with the same entries: the terms depend on π alone.
        self._realization_terms = _REALIZATION_TERMS.setdefault(self._key, [])
        self._check_jacobi(seed)

    @classmethod
    def nambu(cls, casimir: Any) -> PolynomialBivector:
        """π^{ij} = ε_ijk ∂_k C on R³ ({f, g} = ∇C·(∇f × ∇g)); C (in x1, x2, x3) is a Casimir."""
        import sympy

        x = _symbols(3)
        c = sympy.sympify(casimir, locals={f"x{i + 1}": s for i, s in enumerate(x)})
        grad = [sympy.diff(c, s) for s in x]
        out = cls(3, {(0, 1): grad[2], (1, 2): grad[0], (0, 2): -grad[1]})
        out.casimir = c
        return out

    casimir: Any = None

    def __reduce__(self) -> tuple[Any, ...]:
        # The lambdified functions do not pickle; the entries (exact sympy text) rebuild them,
        # and a Nambu bracket is rebuilt from its Casimir so that it keeps it.
        if self.casimir is not None:
            return (PolynomialBivector.nambu, (str(self.casimir),))
        entries = {
            (i, j): str(self.pi[i, j]) for i in range(self.dim) for j in range(i + 1, self.dim)
        }
        return (PolynomialBivector, (self.dim, entries))

    def jacobiator(self) -> list[tuple[tuple[int, int, int], Any]]:
        """The Jacobi expressions J^{ijk} for i < j < k, symbolic."""
        import sympy

        pi, x, n = self.pi, self.x, self.dim
        out = []
        for i, j, k in itertools.combinations(range(n), 3):
            expr = sum(
                pi[a, m] * sympy.diff(pi[b, c], x[m])
                for (a, b, c) in ((i, j, k), (j, k, i), (k, i, j))
                for m in range(n)
            )
            out.append(((i, j, k), expr))
        return out

    def _check_jacobi(self, seed: int) -> None:
        triples = self.jacobiator()
        if not triples:
            return
        rng = np.random.default_rng(seed)
        pts = rng.uniform(-2.0, 2.0, size=(16, self.dim))
        scale = max(1.0, float(np.abs(self._pi_num(*pts.T)).max()) ** 2)
        f = _lambdify(self.x, [e for _, e in triples])
        values = np.abs(f(*pts.T)).max(axis=0)
        for (triple, _), v in zip(triples, values, strict=True):
            if v > 1e-9 * scale:
                raise ValueError(
                    f"pi fails the Jacobi identity for the triple (i, j, k) = {triple}: "
                    f"|J^ijk| = {v:.3g} at a random point"
                )

    def __call__(self, x: FloatArray) -> FloatArray:
        """π(x). x: (B, n) → (B, n, n)."""
        x = np.asarray(x, dtype=np.float64)
        return self._pi_num(*x.T).reshape(*x.shape[:-1], self.dim, self.dim)

    def realization(self, order: int = 2) -> tuple[list[Any], list[Any], tuple[Any, ...]]:
        """(β, α, p): sympy expressions of the order-``order`` realization in (x, p), and p's
        symbols, for ``order`` in 1..=:data:`MAX_REALIZATION_ORDER`.

        β = x + Σ_{k≤order} β_k with β_k homogeneous of degree k in p, built by
        :meth:`realization_terms`; α(x, p) = β(x, −p). Order 1 is x ∓ ½π p; order 2 adds
        (1/12)π^{lm}∂_lπ^{ij}p_m p_j. The realization conditions then hold to O(|p|^order).
        """
        import sympy

        if isinstance(order, bool) or not isinstance(order, int):
            raise ValueError(f"realization order must be an integer, got {order!r}")
        if not 1 <= order <= MAX_REALIZATION_ORDER:
            raise ValueError(
                f"realization order must be in 1..={MAX_REALIZATION_ORDER}, got {order!r}"
            )
        terms, p = self.realization_terms(order)
        beta = [sympy.expand(xi + sum(t[i] for t in terms[:order])) for i, xi in enumerate(self.x)]
        flip = {pj: -pj for pj in p}
        alpha = [sympy.expand(b.subs(flip, simultaneous=True)) for b in beta]
        return beta, alpha, p

    def realization_terms(self, order: int) -> tuple[list[list[Any]], tuple[Any, ...]]:
        """([β_1, …, β_order], p): the homogeneous terms of β in p, each a list of n sympy
        expressions, computed once per bivector and cached.

        With b = β_1 + … + β_{k−1} and the canonical bracket {x^i, p_j} = δ^i_j, the
        degree-(k−1) part of {β^i, β^j} − π^{ij}(β) = 0 reads

            ∂β_k^j/∂p_i − ∂β_k^i/∂p_j = Q^{ij},   Q^{ij} = [π^{ij}(x + b) − {b^i, b^j}]_{k−1}.

        Q is a closed 2-form in p (Jacobi and the lower orders make it so), homogeneous of
        degree k − 1, and the homotopy formula of the Poincaré lemma solves it in the radial
        gauge p_j β_k^j = 0: β_k^j = p_i Q^{ij} / (k + 1). k = 1 gives −½π p, k = 2 the
        (1/12) term; on a linear (Lie–Poisson) π the recursion returns the Bernoulli series
        of the exact groupoid (β_3 = 0). Taking α(x, p) = β(x, −p) (β for −π) makes
        {α^i, β^j} vanish to the same order (measured in the tests).
        """
        import sympy

        n, x, pi = self.dim, self.x, self.pi
        p = tuple(sympy.symbols(f"p1:{n + 1}", real=True))
        eps = sympy.Dummy("eps")
        scale = {pj: eps * pj for pj in p}
        terms = self._realization_terms
        for k in range(len(terms) + 1, order + 1):
            b = [sum((t[i] for t in terms), sympy.Integer(0)) for i in range(n)]
            shift = {x[i]: x[i] + b[i] for i in range(n)}
            q = sympy.zeros(n, n)
            for i in range(n):
                for j in range(i + 1, n):
                    bracket = sum(
                        sympy.diff(b[i], x[c]) * sympy.diff(b[j], p[c])
                        - sympy.diff(b[i], p[c]) * sympy.diff(b[j], x[c])
                        for c in range(n)
                    )
                    e = pi[i, j].subs(shift, simultaneous=True) - bracket
                    e = sympy.expand(sympy.expand(e).subs(scale, simultaneous=True))
                    q[i, j] = e.coeff(eps, k - 1)
                    q[j, i] = -q[i, j]
            terms.append(
                [sympy.expand(sum(p[i] * q[i, j] for i in range(n)) / (k + 1)) for j in range(n)]
            )
        return terms[:order], p

    _realization_terms: list[list[Any]]


class PolynomialPoissonSystem(PoissonSystemBase):
    """A polynomial bivector with a polynomial Hamiltonian: ẋ = π(x)∇H(x). The studies'
    system interface: ``dim``, ``hamiltonian``, ``vector_field``, ``casimirs`` (the Nambu
    function when known, else None), ``component_names``, ``to_dict``."""

    kind = "polynomial_bivector"

    def __init__(
        self, structure: PolynomialBivector, hamiltonian: Any, *, name: str | None = None
    ) -> None:
        import sympy

        if not isinstance(structure, PolynomialBivector):
            raise TypeError(
                f"structure must be a PolynomialBivector, got {type(structure).__name__}"
            )
        x = structure.x
        h = sympy.sympify(hamiltonian, locals={f"x{i + 1}": s for i, s in enumerate(x)})
        if not h.free_symbols <= set(x) or not h.is_polynomial(*x):
            raise ValueError(f"hamiltonian {hamiltonian!r} is not a polynomial in x")
        if name is not None and not isinstance(name, str):
            raise ValueError(f"name must be a string or None, got {name!r}")
        self.name = name
        self.structure = structure
        self.h = sympy.expand(h)
        self.component_names = tuple(str(s) for s in x)
        grad = [sympy.diff(self.h, s) for s in x]
        field = [
            sum(structure.pi[i, j] * grad[j] for j in range(structure.dim))
            for i in range(structure.dim)
        ]
        self._h = _lambdify(x, [self.h])
        self._f = _lambdify(x, field)
        # The field's terms for the core's classical steppers (index, coeffs, exponents).
        self.field_table = _term_table([sympy.expand(f) for f in field], x)
        self._c = None if structure.casimir is None else _lambdify(x, [structure.casimir])

    def __reduce__(self) -> tuple[Any, ...]:
        return (_system, (self.structure, str(self.h), self.name))

    def __repr__(self) -> str:
        c = self.structure.casimir
        bracket = f"nambu={str(c)!r}" if c is not None else f"dim={self.dim}"
        return f"PolynomialPoissonSystem({bracket}, hamiltonian={str(self.h)!r})"

    @property
    def dim(self) -> int:
        return self.structure.dim

    def hamiltonian(self, x: Any) -> FloatArray:
        x = np.asarray(x, dtype=np.float64)
        return self._h(*np.moveaxis(x, -1, 0))[..., 0]

    def vector_field(self, x: Any) -> FloatArray:
        x = np.asarray(x, dtype=np.float64)
        return self._f(*np.moveaxis(x, -1, 0))

    @property
    def casimir_degrees(self) -> tuple[int, ...]:
        """0: the Nambu function need not be homogeneous, so its drift is reported absolute."""
        return () if self._c is None else (0,)

    @property
    def casimir_label(self) -> str:
        if self.structure.casimir is None:
            return "no Casimir known (drift n/a)"
        return f"C = {self.structure.casimir} (absolute drift)"

    def casimirs(self, x: Any) -> FloatArray | None:
        if self._c is None:
            return None
        x = np.asarray(x, dtype=np.float64)
        return self._c(*np.moveaxis(x, -1, 0))

    # --- the PoissonSystem protocol (poisson_rs.protocols) ---------------------------------

    def bivector(self, x: Any) -> FloatArray:
        """π(x). x: (..., n) → (..., n, n)."""
        x = np.asarray(x, dtype=np.float64)
        flat = self.structure(x.reshape(-1, self.dim))
        return flat.reshape(*x.shape[:-1], self.dim, self.dim)

    @property
    def title(self) -> str:
        nambu = self.structure.casimir
        what = f"Nambu bracket of C = {nambu}" if nambu is not None else "polynomial bivector"
        return f"{self.name or 'polynomial Poisson system'}: {what}, H = {self.h}"

    def taylor_charts(self) -> tuple[str, ...]:
        """ "realization" (the order matched to the Taylor order, see
        :func:`matched_realization_order`), then "realization1" … "realization6" for one order."""
        return (
            "realization",
            *(f"realization{n}" for n in range(1, MAX_REALIZATION_ORDER + 1)),
        )

    def taylor_orders(self, wanted: Sequence[int]) -> tuple[int, ...]:
        """At most 5: the sympy series grows fast beyond."""
        return tuple(k for k in wanted if k <= MAX_TAYLOR_ORDER)

    def taylor_integrator(
        self, order: int, chart: str | None = None, *, tol: float, max_iter: int
    ) -> RealizationTaylorIntegrator:
        chart = self.chart_or_default(chart)
        tail = chart.removeprefix("realization")
        return RealizationTaylorIntegrator(
            self, order, int(tail) if tail else None, tol=tol, max_iter=max_iter
        )

    def classical_methods(self) -> list[str]:
        return list(VECTOR_FIELD_METHODS)

    def classical(self, name: str, *, tol: float, max_iter: int) -> VectorFieldIntegrator:
        return VectorFieldIntegrator(self, name, tol=tol, max_iter=max_iter)

    def reference_solution(
        self,
        x0: Any,
        times: Any,
        *,
        rtol: float = 1e-13,
        atol: float = 1e-13,
        failures: Literal["raise", "nan"] = "raise",
    ) -> FloatArray:
        """DOP853 on the vector field."""
        from ..reference import field_reference

        field = self.vector_field
        return field_reference(
            lambda y: field(y[None])[0],
            self.dim,
            x0,
            times,
            rtol=rtol,
            atol=atol,
            failures=failures,
        )

    def to_dict(self) -> dict[str, Any]:
        s = self.structure
        return {
            "kind": self.kind,
            "dim": s.dim,
            "entries": [[i, j, str(s.pi[i, j])] for i in range(s.dim) for j in range(i + 1, s.dim)],
            "hamiltonian": str(self.h),
            "casimir": None if s.casimir is None else str(s.casimir),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> PolynomialPoissonSystem:
        if not isinstance(data, Mapping) or data.get("kind") != cls.kind:
            raise ValueError(f"expected a {cls.kind!r} system dictionary, got {data!r}")
        if data.get("casimir") is not None:
            structure = PolynomialBivector.nambu(data["casimir"])
        else:
            structure = PolynomialBivector(
                int(data["dim"]), {(int(i), int(j)): e for i, j, e in data["entries"]}
            )
        return cls(structure, data["hamiltonian"])


def matched_realization_order(order: int) -> int:
    """The realization order that lets Taylor-HJ of ``order`` reach its full order: the odd
    n ≥ max(3, order). With α(x, p) = β(x, −p) the scheme is symmetric, so the global order is
    min(n, m) rounded up to even (measured: n = 3 gives 4, n = 5 gives 6), and an odd n costs
    less than the even n + 1 for the same order. n = 3 for m = 1 keeps C to O(h⁵) a step
    instead of O(h³) for little extra work."""
    return max(3, order + 1 - order % 2)


def _term_table(
    polys: Sequence[Any], gens: Sequence[Any]
) -> tuple[NDArray[np.int64], FloatArray, NDArray[np.int64]]:
    """(index, coeffs, exponents): every term of every polynomial in ``polys`` over ``gens``,
    index naming its polynomial, for the core."""
    import sympy

    index, coeffs, exponents = [], [], []
    for i, poly in enumerate(polys):
        for exps, coef in sympy.Poly(poly, *gens).terms():
            index.append(i)
            coeffs.append(float(coef))
            exponents.append(exps)
    return (
        np.array(index, dtype=np.int64),
        np.array(coeffs, dtype=np.float64),
        np.array(exponents, dtype=np.int64).reshape(len(coeffs), len(gens)),
    )


Series = list[Any]


def _series_mul(a: Series, b: Series, top: int) -> Series:
    """Product of two truncated power series in t (coefficient lists), kept to degree ``top``."""
    import sympy

    out = [sympy.Integer(0)] * (top + 1)
    for i, ai in enumerate(a):
        if ai == 0:
            continue
        for j, bj in enumerate(b[: top + 1 - i]):
            if bj != 0:
                out[i + j] += ai * bj
    return [sympy.expand(c) for c in out]


def _series_compose(poly: Any, gens: Sequence[Any], values: Sequence[Series], top: int) -> Series:
    """poly(values) as a truncated series in t: ``poly`` a sympy polynomial in ``gens`` (its
    coefficients may hold other symbols), each value a coefficient list in t."""
    import sympy

    out = [sympy.Integer(0)] * (top + 1)
    powers: dict[tuple[int, int], Series] = {}

    def power(i: int, e: int) -> Series:
        if (i, e) not in powers:
            powers[(i, e)] = (
                [sympy.Integer(1)] if e == 0 else _series_mul(power(i, e - 1), values[i], top)
            )
        return powers[(i, e)]

    for exps, coef in sympy.Poly(poly, *gens).terms():
        term: Series = [coef]
        for i, e in enumerate(exps):
            if e:
                term = _series_mul(term, power(i, e), top)
        for d, c in enumerate(term):
            out[d] += c
    return [sympy.expand(c) for c in out]


def hj_series(system: PolynomialPoissonSystem, order: int, realization_order: int) -> list[Any]:
    """[S_1, …, S_order]: the Taylor terms of S(t, x) = Σ t^k S_k solving
    ∂S/∂t + H(β(x, ∇S)) = 0 on the order-``realization_order`` realization (S_1 = −H).

    S_k = −[H(β(x, ∇S_{<k}))]_{t^{k−1}} / k. Every quantity is carried as a power series in t
    truncated at t^{order−1}, so the work grows with the orders kept, not with the expanded
    composition (whose full expansion is what made the direct substitution slow).
    """
    import sympy

    key = (system.structure._key, str(system.h), order, realization_order)
    if key in _HJ_SERIES:
        return list(_HJ_SERIES[key])
    x = system.structure.x
    beta, _, p = system.structure.realization(realization_order)
    s_terms: list[Any] = [-system.h]
    for k in range(2, order + 1):
        # ∇S_{<k} = Σ_j t^j ∇S_j: a series with zero constant term.
        grad = [[sympy.Integer(0)] + [sympy.diff(s, xi) for s in s_terms] for xi in x]
        # β(x, ∇S) as series: β is polynomial in p with x-dependent coefficients.
        beta_t = [_series_compose(b, p, grad, k - 1) for b in beta]
        h_t = _series_compose(system.h, x, beta_t, k - 1)
        s_terms.append(sympy.expand(-h_t[k - 1] / k))
    _HJ_SERIES[key] = list(s_terms)
    return s_terms


class RealizationTaylorIntegrator:
    """Taylor-HJ of order ``order`` on the order-``realization_order`` realization of a
    polynomial bivector, rolled out by the Rust core from polynomial coefficients
    (:meth:`step`: the same Newton in NumPy, the oracle); usable with
    :func:`poisson_rs.integrate`."""

    def __init__(
        self,
        system: PolynomialPoissonSystem,
        order: int = 3,
        realization_order: int | None = None,
        *,
        tol: float = NEWTON_TOL,
        max_iter: int = NEWTON_MAX_ITER,
    ) -> None:
        import sympy

        if not isinstance(system, PolynomialPoissonSystem):
            raise TypeError(
                f"system must be a PolynomialPoissonSystem, got {type(system).__name__}"
            )
        if isinstance(order, bool) or not isinstance(order, int) or not 1 <= order <= 5:
            raise ValueError(f"order must be an integer in 1..=5, got {order!r}")
        self._requested = realization_order
        if realization_order is None:
            suffix = ""
            realization_order = matched_realization_order(order)
        else:
            suffix = str(realization_order)
        self.system, self.order, self.realization_order = system, order, realization_order
        self.tol, self.max_iter = float(tol), int(max_iter)
        self.name = f"taylor{order}-realization{suffix}"
        x = system.structure.x
        n = system.dim
        beta, alpha, p = system.structure.realization(realization_order)
        self.s_terms = hj_series(system, order, realization_order)
        s_terms = self.s_terms
        hh = sympy.Symbol("h")
        s_full = sum(hh**j * s for j, s in enumerate(s_terms, start=1))
        grad_s = [sympy.diff(s_full, xi) for xi in x]
        hess_s = [sympy.diff(g, xj) for g in grad_s for xj in x]
        self._grad = _lambdify((hh, *x), grad_s)
        self._hess = _lambdify((hh, *x), hess_s)
        self._alpha = _lambdify((*x, *p), alpha)
        self._alpha_x = _lambdify((*x, *p), [sympy.diff(a, xi) for a in alpha for xi in x])
        self._alpha_p = _lambdify((*x, *p), [sympy.diff(a, pj) for a in alpha for pj in p])
        self._beta = _lambdify((*x, *p), beta)
        self._n = n
        self._tables = (
            *_term_table(beta, (*p, *x)),
            *_term_table(alpha, (*p, *x)),
            *_term_table([s_full], (hh, *x))[1:],  # S(t, x): t first
        )

    @property
    def dim(self) -> int:
        return self._n

    def __reduce__(self) -> tuple[Any, ...]:
        return (
            _realization_integrator,
            (self.system, self.order, self._requested, self.tol, self.max_iter),
        )

    def step(self, xk: FloatArray, h: float) -> tuple[FloatArray, NDArray[np.bool_]]:
        """One step of every row of xk (B, n); returns the new states and which converged."""
        n = self._n
        z = xk.copy()
        hcol = np.full(len(z), h)
        ok = np.zeros(len(z), dtype=bool)
        for _ in range(self.max_iter):
            g = self._grad(hcol, *z.T)
            hs = self._hess(hcol, *z.T).reshape(-1, n, n)
            args = (*z.T, *g.T)
            f = self._alpha(*args) - xk
            jac = (
                self._alpha_x(*args).reshape(-1, n, n) + self._alpha_p(*args).reshape(-1, n, n) @ hs
            )
            with np.errstate(all="ignore"):
                delta = np.linalg.solve(jac, -f[..., None])[..., 0]
            z = z + delta
            size = np.abs(delta).max(axis=1)
            ok = size <= self.tol * np.maximum(np.abs(z).max(axis=1), 1.0)
            if ok.all() or not np.isfinite(z).all():
                break
        g = self._grad(hcol, *z.T)
        out = self._beta(*z.T, *g.T)
        ok &= np.isfinite(out).all(axis=1)
        return out, ok

    def rollout(
        self, mu0: FloatArray, h: float, n_steps: int, every: int
    ) -> tuple[FloatArray, dict[str, np.ndarray]]:
        """The rollout, in the Rust core (``_core.rollout_polynomial_realization``): the same
        Newton bisection as :meth:`step`, with the maps and S as polynomial coefficients."""
        from .. import _core

        return _core.rollout_polynomial_realization(
            *self._tables,
            np.ascontiguousarray(mu0, dtype=np.float64),
            float(h),
            int(n_steps),
            int(every),
            self.tol,
            self.max_iter,
        )


#: The classical integrators of a polynomial-bivector system: (order, Poisson map).
VECTOR_FIELD_METHODS: dict[str, tuple[int, bool]] = {
    "rk4": (4, False),
    "midpoint": (2, False),
    "dop853": (8, False),
}


class VectorFieldIntegrator:
    """A classical baseline for a :class:`PolynomialPoissonSystem` on its vector field,
    driven by :func:`poisson_rs.integrate`:

    - "rk4": explicit RK4, in the Rust core (SIMD lanes; the field's expanded terms);
    - "midpoint": the implicit midpoint rule, in the core: Newton with the exact Jacobian
      (``tol`` relative, ``max_iter`` updates; a trajectory that does not converge fails with
      code 1);
    - "dop853": SciPy's adaptive DOP853 at rtol = atol = ``tol`` (h only spaces the output).

    None is a Poisson map for a non-linear π; a non-finite state fails with code 3.
    :meth:`step` is the same RK4 (and the midpoint rule by fixed-point iteration) in NumPy, the
    tests' oracle.
    """

    def __init__(
        self,
        system: PolynomialPoissonSystem,
        name: str,
        *,
        tol: float = NEWTON_TOL,
        max_iter: int = NEWTON_MAX_ITER,
    ) -> None:
        if not isinstance(system, PolynomialPoissonSystem):
            raise TypeError(
                f"system must be a PolynomialPoissonSystem, got {type(system).__name__}"
            )
        if not (isinstance(name, str) and name in VECTOR_FIELD_METHODS):
            raise ValueError(
                f"unknown classical integrator {name!r} for a polynomial bivector; valid names: "
                + ", ".join(VECTOR_FIELD_METHODS)
            )
        if not 0 < tol < 1:
            raise ValueError(f"tol must lie in (0, 1), got {tol!r}")
        self.system, self.name = system, name
        self.tol, self.max_iter = float(tol), int(max_iter)

    @property
    def dim(self) -> int:
        return self.system.dim

    def __reduce__(self) -> tuple[Any, ...]:
        return (_vector_field_integrator, (self.system, self.name, self.tol, self.max_iter))

    @property
    def order(self) -> int:
        return VECTOR_FIELD_METHODS[self.name][0]

    def step(self, x: FloatArray, h: float) -> tuple[FloatArray, NDArray[np.bool_]]:
        """One step of every row of x (B, n); the new states and which converged."""
        f = self.system.vector_field
        with np.errstate(all="ignore"):
            if self.name == "rk4":
                k1 = f(x)
                k2 = f(x + 0.5 * h * k1)
                k3 = f(x + 0.5 * h * k2)
                k4 = f(x + h * k3)
                new = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
                return new, np.isfinite(new).all(axis=1)
            new = x + h * f(x)
            ok = np.zeros(len(x), dtype=bool)
            for _ in range(self.max_iter):
                nxt = x + h * f(0.5 * (x + new))
                size = np.abs(nxt - new).max(axis=1)
                new = nxt
                ok = size <= self.tol * np.maximum(np.abs(new).max(axis=1), 1.0)
                if ok.all() or not np.isfinite(new).all():
                    break
        return new, ok & np.isfinite(new).all(axis=1)

    def rollout(
        self, mu0: FloatArray, h: float, n_steps: int, every: int
    ) -> tuple[FloatArray, dict[str, np.ndarray]]:
        if self.name in ("rk4", "midpoint"):
            from .. import _core

            return _core.rollout_polynomial_field(
                self.name,
                *self.system.field_table,
                np.ascontiguousarray(mu0, dtype=np.float64),
                float(h),
                int(n_steps),
                int(every),
                self.tol,
                self.max_iter,
            )
        from ..rollout import dop853_rollout

        return dop853_rollout(self.system, mu0, h, n_steps, every, self.tol)

    def __repr__(self) -> str:
        return f"VectorFieldIntegrator(name={self.name!r})"


# Pickling (Dask ships steppers to worker processes): sympy text in, the same objects out.
def _system(structure: PolynomialBivector, h: str, name: str | None) -> PolynomialPoissonSystem:
    return PolynomialPoissonSystem(structure, h, name=name)


def _realization_integrator(
    system: PolynomialPoissonSystem, order: int, n: int | None, tol: float, max_iter: int
) -> RealizationTaylorIntegrator:
    return RealizationTaylorIntegrator(system, order, n, tol=tol, max_iter=max_iter)


def _vector_field_integrator(
    system: PolynomialPoissonSystem, name: str, tol: float, max_iter: int
) -> VectorFieldIntegrator:
    return VectorFieldIntegrator(system, name, tol=tol, max_iter=max_iter)


def _scene_table(raw: Mapping[str, Any]) -> PolynomialPoissonSystem:
    """A ``kind = "nambu"`` [system] table: the Nambu bracket {f, g} = ∇C·(∇f × ∇g) on R³ of the
    polynomial ``casimir`` C, with the polynomial ``hamiltonian`` (strings in x1, x2, x3),
    optional ``name``."""
    from ..tables import only_keys, optional_name, polynomial_text, required
    from ..untrusted import parsing

    only_keys(raw, ("kind", "casimir", "hamiltonian", "name"), "nambu")
    required(raw, "casimir", "hamiltonian")
    casimir = polynomial_text(raw["casimir"], "system.casimir")
    hamiltonian = polynomial_text(raw["hamiltonian"], "system.hamiltonian")
    name = optional_name(raw)
    with parsing("scene", "system.casimir"):
        structure = PolynomialBivector.nambu(casimir)
    with parsing("scene", "system.hamiltonian"):
        return PolynomialPoissonSystem(structure, hamiltonian, name=name)


#: The kinds of system dictionaries and scene [system] tables this module reads.
SYSTEM_KINDS = {PolynomialPoissonSystem.kind: PolynomialPoissonSystem.from_dict}
SCENE_KINDS = {"nambu": _scene_table}

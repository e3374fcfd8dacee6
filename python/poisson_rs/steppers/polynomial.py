"""The polynomial bivector's steppers: Taylor-HJ on its order-n realization (stepped by the Rust
core from sympy's polynomial coefficients; a NumPy Newton as its oracle) and the classical
baselines on its vector field (RK4 and the implicit midpoint rule in the core, DOP853)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..protocols import NEWTON_MAX_ITER, NEWTON_TOL, provides
from ..structures.polynomial import (
    VECTOR_FIELD_METHODS,
    PolynomialBivector,
    PolynomialPoissonSystem,
    _lambdify,
    _term_table,
    hj_series,
    matched_realization_order,
)

FloatArray = NDArray[np.float64]


@provides("polynomial.RealizationTaylorIntegrator")
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


@provides("polynomial.VectorFieldIntegrator")
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
                return new, np.asarray(np.isfinite(new).all(axis=1))
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


def _realization_integrator(
    system: PolynomialPoissonSystem, order: int, n: int | None, tol: float, max_iter: int
) -> RealizationTaylorIntegrator:
    return RealizationTaylorIntegrator(system, order, n, tol=tol, max_iter=max_iter)


def _vector_field_integrator(
    system: PolynomialPoissonSystem, name: str, tol: float, max_iter: int
) -> VectorFieldIntegrator:
    return VectorFieldIntegrator(system, name, tol=tol, max_iter=max_iter)


_TABLES: dict[tuple[Any, ...], tuple[tuple[Any, ...], list[Any]]] = {}


def realization_tables(
    structure: PolynomialBivector, realization_order: int
) -> tuple[tuple[Any, ...], list[Any]]:
    """The order-``realization_order`` realization as the core's (β table, α table) and β
    split by component (sparse polynomials over (p, x)), derived once per bracket."""
    key = (structure._key, realization_order)
    if key not in _TABLES:
        beta, alpha, p = structure.realization(realization_order)
        x = structure.x
        b_tab = _term_table(beta, (*p, *x))
        a_tab = _term_table(alpha, (*p, *x))
        idx, coeffs, exps = b_tab
        split = [(exps[idx == i], coeffs[idx == i]) for i in range(structure.dim)]
        _TABLES[key] = ((*b_tab, *a_tab), split)
    return _TABLES[key]


@provides("polynomial.SeriesRealizationIntegrator")
class SeriesRealizationIntegrator:
    """Taylor-HJ of ``order`` on the order-``realization_order`` realization of ``structure``
    for the Hamiltonian ``hamiltonian`` (a sparse polynomial: exponents (T, n), coefficients
    (T,)), its S_k computed in floating point (:mod:`poisson_rs.realizations.numeric_hj`) and
    stepped by the Rust core: the map of :class:`RealizationTaylorIntegrator` to rounding, built
    in milliseconds instead of sympy's seconds. ``system`` is carried for the tools that read
    it (None while a fit is under way)."""

    poisson = True

    def __init__(
        self,
        structure: PolynomialBivector,
        hamiltonian: tuple[NDArray[np.int64], FloatArray],
        order: int,
        realization_order: int | None = None,
        *,
        system: Any = None,
        tol: float = NEWTON_TOL,
        max_iter: int = NEWTON_MAX_ITER,
    ) -> None:
        from ..realizations.numeric_hj import hj_terms, series_table

        if isinstance(order, bool) or not isinstance(order, int) or not 1 <= order <= 5:
            raise ValueError(f"order must be an integer in 1..=5, got {order!r}")
        r = realization_order or matched_realization_order(order)
        tables, beta = realization_tables(structure, r)
        self.s_terms = hj_terms(beta, hamiltonian, order)
        bi, bc, be, ai, ac, ae = tables
        sc, se = series_table(self.s_terms)
        self._tables = (bi, bc, be, ai, ac, ae, sc, se)
        self._n = structure.dim
        self.system, self.order, self.realization_order = system, order, r
        self.tol, self.max_iter = float(tol), int(max_iter)
        self.name = f"taylor{order}-realization{'' if realization_order is None else r}"

    @property
    def dim(self) -> int:
        return self._n

    def rollout(
        self, mu0: FloatArray, h: float, n_steps: int, every: int
    ) -> tuple[FloatArray, dict[str, np.ndarray]]:
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

    def __repr__(self) -> str:
        return f"SeriesRealizationIntegrator({self.name!r}, dim={self._n})"

"""The integrators each kind of system has, by name, for the studies and the CLI.

A study asks three things of a system: which Taylor-HJ integrators it has (and in which charts),
which classical methods, and how to build each. Lie–Poisson systems answer with
:func:`~poisson_rs.taylor_integrator` (Cayley and exp charts on so(3), exp elsewhere) and
:func:`~poisson_rs.classical`; log-canonical systems (Lotka–Volterra) with
:func:`~poisson_rs.log_canonical_taylor` on the exact groupoid (chart name "log": the step works
in q = ln x) and :func:`~poisson_rs.log_canonical_classical` (RK4, midpoint, the log splittings
of order 2 and 4, DOP853 as the reference); affine systems (Lie–Poisson plus a constant
cocycle) with the same Lie–Poisson methods run on their central extension at level 1
(:func:`~poisson_rs.affine_taylor`, :func:`~poisson_rs.affine_classical`: Taylor-exp, RK4,
midpoint, DOP853); polynomial bivectors (a cubic Nambu bracket, ...) with Taylor-HJ on an
approximate realization (chart name "realization": the order that matches the Taylor order, see
:func:`~poisson_rs.structures.polynomial.matched_realization_order`; "realization1" to
"realization6" pick one; Rust) and RK4, midpoint and DOP853 on the vector field (NumPy).
Names follow one pattern everywhere: ``taylor{k}-{chart}`` and the classical method's own name.
"""

from __future__ import annotations

from typing import Any

from ..integrators import Stepper, classical, classical_methods, taylor_integrator

#: The chart name of the exact log-canonical groupoid (the step works in q = ln x).
LOG_CHART = "log"


def is_log_canonical(system: Any) -> bool:
    """Whether ``system`` is a log-canonical system (e.g. :func:`~poisson_rs.lotka_volterra`)."""
    from ..structures.log_canonical import LogCanonicalSystem

    return isinstance(system, LogCanonicalSystem)


def is_affine(system: Any) -> bool:
    """Whether ``system`` is an affine Poisson system (see :mod:`poisson_rs.structures.affine`)."""
    from ..structures.affine import AffinePoissonSystem

    return isinstance(system, AffinePoissonSystem)


def is_polynomial_bivector(system: Any) -> bool:
    """Whether ``system`` is a polynomial-bivector system (approximate realization)."""
    from ..structures.polynomial import PolynomialPoissonSystem

    return isinstance(system, PolynomialPoissonSystem)


#: The chart name of a polynomial bivector's approximate realization of matched order
#: ("realization{n}" names order n).
REALIZATION_CHART = "realization"


def realization_order_of(chart: str) -> int | None:
    """None for "realization" (matched to the Taylor order), n for "realization{n}";
    ValueError for any other chart."""
    from ..structures.polynomial import MAX_REALIZATION_ORDER

    if chart == REALIZATION_CHART:
        return None
    tail = chart.removeprefix(REALIZATION_CHART)
    if tail != chart and tail.isdigit() and 1 <= int(tail) <= MAX_REALIZATION_ORDER:
        return int(tail)
    raise ValueError(
        f"chart {chart!r}: a polynomial bivector has {REALIZATION_CHART!r} (matched order) or "
        f"'realization1' to 'realization{MAX_REALIZATION_ORDER}'"
    )


def is_supported(system: Any) -> bool:
    """Whether the studies have integrators for ``system``."""
    from ..structures.lie_poisson import LiePoissonSystem

    return (
        isinstance(system, LiePoissonSystem)
        or is_log_canonical(system)
        or is_affine(system)
        or is_polynomial_bivector(system)
    )


def taylor_orders(system: Any, wanted: tuple[int, ...] = (1, 3, 5, 7)) -> tuple[int, ...]:
    """The Taylor-HJ orders of ``wanted`` the system's integrator takes (at most 5 on the
    realization of a polynomial bivector, whose sympy series grows fast)."""
    if is_polynomial_bivector(system):
        return tuple(k for k in wanted if k <= 5)
    return wanted


def is_positive_orthant(system: Any) -> bool:
    """Whether the system's states live in the open positive orthant (log-canonical ones)."""
    return is_log_canonical(system)


def taylor_charts(system: Any) -> tuple[str, ...]:
    """The charts the system's Taylor-HJ integrators are built in: ("cayley", "exp") on so(3),
    ("log",) for a log-canonical system, ("exp",) for any other Lie–Poisson system."""
    if is_log_canonical(system):
        return (LOG_CHART,)
    if is_polynomial_bivector(system):
        return (REALIZATION_CHART,)
    so3 = getattr(getattr(system, "algebra", None), "is_so3", lambda: False)()
    return ("cayley", "exp") if so3 else ("exp",)


def default_chart(system: Any) -> str:
    """The chart the studies use when they pick one: exp, or log for a log-canonical system."""
    if is_polynomial_bivector(system):
        return REALIZATION_CHART
    return LOG_CHART if is_log_canonical(system) else "exp"


def taylor(system: Any, order: int, chart: str | None = None) -> Stepper:
    """The Taylor-HJ integrator of ``order`` for ``system`` in ``chart`` (default:
    :func:`default_chart`). ValueError for a chart the system does not have."""
    chart = default_chart(system) if chart is None else chart
    if is_log_canonical(system):
        if chart != LOG_CHART:
            raise ValueError(
                f"chart {chart!r}: a log-canonical system has one chart, {LOG_CHART!r}"
            )
        from ..integrators import log_canonical_taylor

        return log_canonical_taylor(system, order)
    if is_polynomial_bivector(system):
        realization_order = realization_order_of(chart)
        from ..structures.polynomial import RealizationTaylorIntegrator

        return RealizationTaylorIntegrator(system, order, realization_order)
    if is_affine(system):
        if chart != "exp":
            raise ValueError(f"chart {chart!r}: an affine system is integrated in the exp chart")
        from ..structures.affine import affine_taylor

        return affine_taylor(system, order)
    return taylor_integrator(system, order, chart)  # type: ignore[arg-type]


def classical_names(system: Any) -> list[str]:
    """Names of the classical integrators the system has ("dop853" among them)."""
    if is_log_canonical(system):
        from ..integrators import LOG_CANONICAL_METHODS

        return list(LOG_CANONICAL_METHODS)
    if is_affine(system):
        return classical_methods(system.extension)
    if is_polynomial_bivector(system):
        from ..structures.polynomial import VECTOR_FIELD_METHODS

        return list(VECTOR_FIELD_METHODS)
    return classical_methods(system)


def classical_stepper(system: Any, name: str, **kw: Any) -> Stepper:
    """The classical integrator ``name`` of :func:`classical_names` (``tol`` sets DOP853's
    rtol = atol)."""
    if is_log_canonical(system):
        from ..integrators import log_canonical_classical

        return log_canonical_classical(system, name, **kw)
    if is_affine(system):
        from ..structures.affine import affine_classical

        return affine_classical(system, name, **kw)
    if is_polynomial_bivector(system):
        from ..structures.polynomial import VectorFieldIntegrator

        return VectorFieldIntegrator(system, name, **kw)
    return classical(system, name, **kw)

"""The single names that build integrators for any Poisson system (``taylor_integrator``,
``classical``, ``classical_methods``) and, for one release, the family names as aliases; the
rest of what this module held lives in :mod:`poisson_rs.rollout`, :mod:`poisson_rs.model_files`
and :mod:`poisson_rs.steppers`, and is re-exported here."""

from __future__ import annotations

import numbers
from typing import Any

from .model_files import (  # noqa: F401 (re-exported for one release)
    DEFAULT_MODEL,
    MODELS_PACKAGE,
    BisectionIntegrator,
    LearnedIntegrator,
    TaylorIntegrator,
    _check_domain,
    _check_first_order,
    _domain_sample,
    list_models,
    load_model,
    shipped_models,
)
from .protocols import NEWTON_MAX_ITER, NEWTON_TOL, Stepper, as_system
from .rollout import (  # noqa: F401 (re-exported for one release)
    FAILURE_CODES,
    MAX_COUNT,
    MAX_STEP_ANGLE,
    MIN_STEP,
    RolloutInfo,
    _as_states,
    _check_count,
    _check_step,
    _check_time,
    _describe_domain,
    _summary,
    count_out_of_domain,
    dop853_rollout,
    integrate,
)
from .steppers.learned_realization import (  # noqa: F401 (re-exported for one release)
    MAX_MODEL_BYTES,
    LearnedLogCanonicalIntegrator,
    LearnedPolynomialIntegrator,
)
from .steppers.lie_poisson import (  # noqa: F401 (re-exported for one release)
    CLASSICAL_METHODS,
    LIE_POISSON_METHODS,
    ClassicalIntegrator,
    lie_poisson_taylor,
)
from .steppers.log_canonical import (  # noqa: F401 (re-exported for one release)
    LOG_CANONICAL_METHODS,
    LogCanonicalClassicalIntegrator,
    LogCanonicalTaylorIntegrator,
)
from .structures.lie_poisson import RigidBody


def taylor_integrator(
    system: Any = None,
    order: int = 3,
    chart: str | None = None,
    *,
    tol: float = NEWTON_TOL,
    max_iter: int = NEWTON_MAX_ITER,
) -> Stepper:
    """The Taylor-HJ integrator of ``order`` (S = Σ_{k≤order} t^k S_k, the S_k exact) for any
    Poisson system (default: the paper's rigid body), in ``chart``, one of
    ``system.taylor_charts()`` (default: the first; "cayley" on the rigid body, "exp" on any
    other Lie–Poisson system, "log" on a log-canonical one, "realization" on a polynomial
    bivector).

    Its order of accuracy is ``order``, or ``order + 1`` where S_{order+1} vanishes (odd orders
    for a quadratic Hamiltonian). ``tol`` and ``max_iter`` set the Newton solve of every step
    (relative update, iteration cap), the same defaults on every structure.

    >>> import poisson_rs as pr
    >>> lv = pr.lotka_volterra([[0, 1], [-1, 0]], [1, 2])
    >>> pr.integrate(pr.taylor_integrator(lv, 3), [1.0, 0.8], h=0.1, n_steps=10).shape
    (11, 2)
    """
    system = RigidBody() if system is None else as_system(system)
    _check_newton(tol, max_iter)
    return system.taylor_integrator(order, chart, tol=tol, max_iter=max_iter)


def _check_newton(tol: Any, max_iter: Any) -> None:
    """ValueError naming ``tol`` or ``max_iter`` outside (0, 1) / the integers >= 1."""
    if isinstance(tol, bool) or not (isinstance(tol, numbers.Real) and 0 < float(tol) < 1):
        raise ValueError(f"tol must lie in (0, 1), got {tol!r}")
    if isinstance(max_iter, bool) or not isinstance(max_iter, numbers.Integral) or max_iter < 1:
        raise ValueError(f"max_iter must be an integer >= 1, got {max_iter!r}")


def classical_methods(system: Any) -> list[str]:
    """Names of the classical integrators :func:`classical` builds for ``system``, exactly."""
    return list(as_system(system).classical_methods())


def classical(
    system: Any, name: str, *, tol: float = NEWTON_TOL, max_iter: int = NEWTON_MAX_ITER
) -> Stepper:
    """A classical baseline integrator for any Poisson system, usable with :func:`integrate`.

    ``name`` is one of :func:`classical_methods` ``(system)``: on the rigid body "rk4",
    "midpoint", "splitting", "splitting4", "dmv", "splitting_casimir" (fixed step h, Rust) and
    "dop853" (adaptive, SciPy; h only spaces the output); "rk4", "midpoint", "dop853" on every
    system, plus each structure's own explicit Poisson splittings ("splitting" for the heavy
    top, "log_splitting" and "log_splitting4" for a log-canonical system). ``tol`` and
    ``max_iter`` set the implicit methods' Newton solve; for "dop853" ``tol`` is its rtol and
    atol. TypeError for a ``system`` that is not a Poisson system, ValueError for an unknown
    name (the message lists the valid ones).

    >>> import poisson_rs as pr
    >>> rk4 = pr.classical(pr.RigidBody(), "rk4")
    >>> pr.integrate(rk4, [1.0, 1.0, 2.0], h=0.1, n_steps=10).shape
    (11, 3)
    """
    system = as_system(system)
    names = system.classical_methods()
    if not (isinstance(name, str) and name in names):
        raise ValueError(
            f"unknown classical integrator {name!r} for {system!r}; valid names: {', '.join(names)}"
        )
    _check_newton(tol, max_iter)
    return system.classical(name, tol=tol, max_iter=max_iter)


def log_canonical_taylor(
    system: Any, order: int = 3, *, tol: float = NEWTON_TOL, max_iter: int = NEWTON_MAX_ITER
) -> LogCanonicalTaylorIntegrator:
    """The Taylor-HJ integrator of order ``order`` for a log-canonical system (e.g.
    :func:`~poisson_rs.lotka_volterra`), usable with :func:`integrate`. Its order of accuracy is
    ``order + 1`` for odd ``order`` (the even Taylor terms vanish) and ``order`` otherwise.

    >>> import poisson_rs as pr
    >>> lv = pr.lotka_volterra([[0, 1], [-1, 0]], [1, 2])
    >>> pr.integrate(pr.log_canonical_taylor(lv, 3), [1.0, 0.8], h=0.1, n_steps=10).shape
    (11, 2)
    """
    return LogCanonicalTaylorIntegrator(system, order, tol=tol, max_iter=max_iter)


def log_canonical_classical(
    system: Any, name: str, *, tol: float = NEWTON_TOL, max_iter: int = NEWTON_MAX_ITER
) -> LogCanonicalClassicalIntegrator:
    """A classical baseline ("rk4", "midpoint", "log_splitting", "log_splitting4", "dop853")
    for a log-canonical system; see :class:`LogCanonicalClassicalIntegrator`."""
    return LogCanonicalClassicalIntegrator(system, name, tol=tol, max_iter=max_iter)

"""The integrators a system has, by name, for the studies and the CLI.

A study asks a system (:class:`poisson_rs.PoissonSystem`) three things: which Taylor-HJ
integrators it has (and in which charts), which classical methods, and how to build each; every
answer comes from the system itself. Names follow one pattern everywhere: ``taylor{k}-{chart}``
and the classical method's own name.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from ..integrators import classical, classical_methods, taylor_integrator
from ..protocols import Stepper, as_system


def is_supported(system: Any) -> bool:
    """Whether ``system`` implements :class:`poisson_rs.PoissonSystem`."""
    try:
        as_system(system)
    except TypeError:
        return False
    return True


def taylor_orders(system: Any, wanted: Sequence[int] = (1, 3, 5, 7)) -> tuple[int, ...]:
    """The Taylor-HJ orders of ``wanted`` the system builds."""
    return tuple(as_system(system).taylor_orders(tuple(wanted)))


def taylor_charts(system: Any) -> tuple[str, ...]:
    """The charts the system's Taylor-HJ integrators are built in, the default first, without
    the variants that fix a realization's order ("realization3", ...)."""
    charts = as_system(system).taylor_charts()
    return tuple(c for c in charts if not (c.startswith("realization") and c != "realization"))


def default_chart(system: Any) -> str:
    """The chart the studies use when they pick one: the system's first."""
    return taylor_charts(system)[0]


def taylor(system: Any, order: int, chart: str | None = None) -> Stepper:
    """The Taylor-HJ integrator of ``order`` for ``system`` in ``chart`` (default: the
    system's first). ValueError for a chart the system does not have."""
    return taylor_integrator(system, order, chart)


def classical_names(system: Any) -> list[str]:
    """Names of the classical integrators the system has ("dop853" among them)."""
    return classical_methods(system)


def classical_stepper(system: Any, name: str, **kw: Any) -> Stepper:
    """The classical integrator ``name`` of :func:`classical_names` (``tol`` sets DOP853's
    rtol = atol)."""
    return classical(system, name, **kw)

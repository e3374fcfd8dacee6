"""What the studies ask of a system beyond the protocol's single names
(:func:`~poisson_rs.taylor_integrator`, :func:`~poisson_rs.classical`,
:func:`~poisson_rs.classical_methods`, which they call directly): the charts and orders they
chart. Names follow one pattern everywhere: ``taylor{k}-{chart}`` and the classical method's own
name.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from ..protocols import as_system


def taylor_orders(system: Any, wanted: Sequence[int] = (1, 3, 5, 7)) -> tuple[int, ...]:
    """The Taylor-HJ orders of ``wanted`` the system builds."""
    return tuple(as_system(system).taylor_orders(tuple(wanted)))


def taylor_charts(system: Any) -> tuple[str, ...]:
    """The charts the system's Taylor-HJ integrators are built in, the default first, without
    the variants that fix a realization's order ("realization3", ...): those are one method
    each, not one per chart."""
    charts = as_system(system).taylor_charts()
    return tuple(c for c in charts if not (c.startswith("realization") and c != "realization"))


def default_chart(system: Any) -> str:
    """The chart the studies use when they pick one: the system's first."""
    return taylor_charts(system)[0]

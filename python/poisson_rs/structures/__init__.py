"""Poisson structures and the systems built on them, one module each:

- :mod:`.lie_poisson`: Lie–Poisson systems on g* (a Lie algebra by its structure constants, a
  polynomial Hamiltonian; the rigid body and the heavy top);
- :mod:`.log_canonical`: log-canonical structures π_ij = c_ij x_i x_j with log-polynomial
  Hamiltonians (Lotka–Volterra);
- :mod:`.affine`: affine brackets (Lie–Poisson plus a constant 2-cocycle), through their central
  extension at level 1;
- :mod:`.polynomial`: any polynomial bivector (checked for Jacobi) with its approximate
  realizations of order n.
"""

import importlib
import pkgutil
from collections.abc import Callable, Mapping
from functools import cache
from typing import Any

from .affine import (
    AffinePoissonSystem,
    affine_poisson_system,
    affine_taylor,
    central_extension,
)
from .lie_poisson import HeavyTop, LieAlgebra, LiePoissonSystem, Polynomial, RigidBody
from .log_canonical import (
    LogCanonical,
    LogCanonicalSystem,
    LogPolynomial,
    integer_null_space,
    lotka_volterra,
)
from .polynomial import PolynomialBivector, PolynomialPoissonSystem


@cache
def _kinds(table: str) -> dict[str, Callable[..., Any]]:
    """``table`` ("SYSTEM_KINDS", "SCENE_KINDS" or "BRACKET_FAMILIES") of every structure
    module of this package, merged: a structure module is found by being here, so a new
    structure is one new module."""
    found: dict[str, Callable[..., Any]] = {}
    for info in pkgutil.iter_modules(__path__):
        module = importlib.import_module(f"{__name__}.{info.name}")
        for kind, reader in getattr(module, table, {}).items():
            if kind in found:
                raise RuntimeError(f"structure kind {kind!r} is defined twice")
            found[kind] = reader
    return found


def system_kinds() -> tuple[str, ...]:
    """The ``kind`` of every system dictionary :func:`system_from_dict` reads."""
    return tuple(_kinds("SYSTEM_KINDS"))


def scene_kinds() -> tuple[str, ...]:
    """The ``kind`` of every scene [system] table :func:`system_from_scene_table` reads."""
    return tuple(_kinds("SCENE_KINDS"))


def system_from_dict(data: Mapping[str, Any]) -> Any:
    """Any structure's system from its ``to_dict()``, by its ``kind``; ValueError naming the
    kinds there are otherwise."""
    kind = data.get("kind") if isinstance(data, Mapping) else None
    readers = _kinds("SYSTEM_KINDS")
    if kind not in readers:
        raise ValueError(
            f"a system dictionary needs a 'kind' among {', '.join(sorted(readers))}; got {kind!r}"
        )
    return readers[kind](data)


def system_from_scene_table(raw: Mapping[str, Any], default: str) -> Any:
    """A scene's [system] table as a system, by its ``kind`` (``default`` when absent);
    ValueError naming 'system.kind' and the kinds there are otherwise."""
    kind = raw.get("kind", default)
    readers = _kinds("SCENE_KINDS")
    if not isinstance(kind, str) or kind not in readers:
        raise ValueError(
            f"scene key 'system.kind' = {kind!r} is not one of {', '.join(sorted(readers))}"
        )
    return readers[kind]({**raw, "kind": kind})


__all__ = [
    "AffinePoissonSystem",
    "HeavyTop",
    "LieAlgebra",
    "LiePoissonSystem",
    "LogCanonical",
    "LogCanonicalSystem",
    "LogPolynomial",
    "Polynomial",
    "PolynomialBivector",
    "PolynomialPoissonSystem",
    "RigidBody",
    "affine_poisson_system",
    "affine_taylor",
    "central_extension",
    "integer_null_space",
    "lotka_volterra",
    "scene_kinds",
    "system_from_dict",
    "system_from_scene_table",
    "system_kinds",
]


def bracket_families(dim: int) -> list[Any]:
    """The bivector families (:class:`poisson_rs.bracket_family.BracketFamily`) every structure
    module offers in dimension ``dim`` (its ``BRACKET_FAMILIES`` table), smallest first: what
    structure discovery searches. A new structure joins by having that table."""
    found = [f for f in (make(dim) for make in _kinds("BRACKET_FAMILIES").values()) if f]
    return sorted(found, key=len)

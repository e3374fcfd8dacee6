"""Checks of :func:`poisson_rs.learn`'s options: each bad value gets one ValueError naming the
argument (and the key, for ``map_options``), before any work."""

from __future__ import annotations

import math
import numbers
from typing import Any

__all__ = [
    "MAP_DEGREE_RANGE",
    "MAX_DEGREE",
    "ORDER_RANGE",
    "check_bool",
    "check_int",
    "check_map_options",
]

#: Largest polynomial degree of H fitted (and of a known H in mode "hj+data", whose Taylor-HJ
#: series is formed densely: its size grows like (K(d − 1) + 1)^n).
MAX_DEGREE = 4
#: Taylor-HJ orders K accepted.
ORDER_RANGE = (1, 12)
#: Degrees of the map's polynomial S(h, ·) accepted.
MAP_DEGREE_RANGE = (2, 8)
#: Largest count accepted for iteration counts, horizons and sample sizes.
MAX_COUNT = 1_000_000


def check_int(value: Any, name: str, lo: int, hi: int) -> int:
    """``value`` as an int in [lo, hi], or ValueError naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")
    if not lo <= int(value) <= hi:
        raise ValueError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")
    return int(value)


def check_bool(value: Any, name: str) -> bool:
    if not isinstance(value, bool):
        raise ValueError(f"{name} must be True or False, got {value!r}")
    return value


def check_seconds(value: Any, name: str) -> float | None:
    """``value`` as a time budget in seconds (a finite number > 0) or None, or ValueError naming
    ``name``."""
    return None if value is None else _positive(value, name)


def _positive(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return v


def _widths(value: Any, name: str) -> tuple[int, ...]:
    if not isinstance(value, (tuple, list)) or not value:
        raise ValueError(f"{name} must be a non-empty list of layer widths, got {value!r}")
    return tuple(check_int(w, f"{name}[{i}]", 1, 4096) for i, w in enumerate(value))


#: Options each family takes, and their checks.
_CHECKS: dict[str, dict[str, Any]] = {
    "polynomial": {
        "degree": lambda v, n: check_int(v, n, *MAP_DEGREE_RANGE),
        "max_iter": lambda v, n: check_int(v, n, 1, 10_000),
        "verbose": check_bool,
    },
    "network": {
        "widths": _widths,
        "adam_steps": lambda v, n: check_int(v, n, 0, MAX_COUNT),
        "lbfgs_steps": lambda v, n: check_int(v, n, 0, MAX_COUNT),
        "lr": _positive,
        "base": check_bool,
        "verbose": check_bool,
    },
    "blend": {
        "widths": _widths,
        "mlp_power": lambda v, n: None if v is None else check_int(v, n, 1, 12),
        "adam_steps": lambda v, n: check_int(v, n, 0, MAX_COUNT),
        "lbfgs_steps": lambda v, n: check_int(v, n, 0, MAX_COUNT),
        "lr": _positive,
        "n_hj": lambda v, n: check_int(v, n, 1, MAX_COUNT),
        "verbose": check_bool,
    },
}


def check_map_options(options: Any, family: str) -> dict[str, Any]:
    """``map_options`` checked for ``family`` ("map": its ``kind`` "polynomial" or "network";
    "blend": mode "hj+data" with the network correction). Returns a checked copy (with
    ``kind`` for "map")."""
    if options is None:
        options = {}
    if not isinstance(options, dict):
        raise ValueError(f"map_options must be a dict, got {type(options).__name__}")
    out = dict(options)
    if family == "map":
        kind = out.pop("kind", "polynomial")
        if kind not in ("polynomial", "network"):
            raise ValueError(f"map_options['kind'] must be 'polynomial' or 'network', got {kind!r}")
        family = kind
    else:
        kind = None
    checks = _CHECKS[family]
    for key in list(out):
        if key not in checks:
            hint = " (give seed= to learn)" if key == "seed" else ""
            raise ValueError(
                f"map_options[{key!r}] is not an option of the {family} family{hint}; known: "
                f"{sorted(checks)}"
            )
        out[key] = checks[key](out[key], f"map_options[{key!r}]")
    if kind is not None:
        out["kind"] = kind
    return out


#: Held-out one-step error that counts as exact data when the noise cannot be estimated
#: (trajectories too short for finite differences): nothing smaller is worth a larger model.
EXACT_LEVEL = 1e-10

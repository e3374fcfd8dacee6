"""Values read from untrusted tables (a scene's TOML, a system's JSON), checked one by one: each
refusal is one ValueError naming the dotted key, e.g. ``scene key 'system.c'``."""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from typing import Any


def number(value: Any, key: str, *, positive: bool = True) -> float:
    """A finite real (int or float, not bool); ValueError naming ``key`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"scene key '{key}' must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v) or (positive and v <= 0):
        what = "finite positive" if positive else "finite"
        raise ValueError(f"scene key '{key}' must be a {what} number, got {value!r}")
    return v


def only_keys(raw: Mapping[str, Any], allowed: Sequence[str], kind: str) -> None:
    """ValueError naming the first key of ``raw`` outside ``allowed`` (a [system] table of
    ``kind``)."""
    extra = [k for k in raw if k not in allowed]
    if extra:
        given = ", ".join(k for k in allowed if k != "kind")
        raise ValueError(
            f"scene key 'system.{extra[0]}' is not known for kind = {kind!r} (its keys: {given})"
        )


def required(raw: Mapping[str, Any], *keys: str) -> None:
    """ValueError naming the first of ``keys`` missing from the [system] table ``raw``."""
    for key in keys:
        if key not in raw:
            raise ValueError(f"scene key 'system.{key}' is missing")


def optional_name(raw: Mapping[str, Any]) -> str | None:
    """The table's ``name``: a string or absent."""
    name = raw.get("name")
    if name is not None and not isinstance(name, str):
        raise ValueError(f"scene key 'system.name' must be a string, got {name!r}")
    return name


def matrix(value: Any, key: str) -> list[list[float]]:
    """A square matrix of finite numbers (a list of rows)."""
    if not (isinstance(value, list) and all(isinstance(row, list) for row in value)):
        raise ValueError(
            f"scene key '{key}' must be a list of rows (an n × n matrix), got {value!r}"
        )
    for j, row in enumerate(value):
        if len(row) != len(value):
            raise ValueError(f"scene key '{key}' must be square: row {j} has {len(row)} entries")
    return [[number(v, key, positive=False) for v in row] for row in value]


#: A polynomial as a table may write it: numbers, the variables x1…x9, + − * / ** and
#: parentheses, nothing else (the string then goes to sympy, which must never see a name).
_POLYNOMIAL_TEXT = re.compile(r"(?:x[1-9]|[0-9.+\-*/() ])+")


def polynomial_text(value: Any, key: str, variables: str = "x1, x2, x3") -> str:
    """A polynomial's text, checked character by character before any parser sees it."""
    if not isinstance(value, str) or not 0 < len(value) <= 2000:
        raise ValueError(f"scene key '{key}' must be a polynomial in {variables} (a string)")
    if not _POLYNOMIAL_TEXT.fullmatch(value):
        raise ValueError(
            f"scene key '{key}' = {value!r}: only numbers, {variables}, + - * / ** and "
            "parentheses are allowed"
        )
    return value
